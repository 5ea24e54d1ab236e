"""Staged recipes: one YAML file that trains a policy from scratch through a list of stages.

A recipe chains the configs a policy needs (dense targets, expert iteration, the re-ranker, PPO)
into one command, ``mrchaos-train conf/recipes/<name>.yaml``. Each stage is a config plus
overrides; it runs in its own folder inside the run (``runs/<recipe>/<stage>/``) and starts from
the previous stage's checkpoint::

    name: rerank
    stages:
      - name: dense
        config: ../dense.yaml          # relative to this file
      - name: exit
        config: ../exit.yaml           # starts from dense's weights
      - name: rerank
        config: ../rerank.yaml
        init_from: "@dense"            # an earlier stage instead of the previous one
        overrides:
          rerank.data: ["@exit"]       # "@stage" is that stage's folder
      - name: longer
        continues: "@rerank"           # resume that run in its folder, with more epochs
        overrides:
          rerank.epochs: 6
    overrides:                         # every stage's, under its own
      threads: 2

Why the chain lives here and not in the stage configs: a stage config's own ``init_from`` may name
a shipped policy (so that it also runs alone), but a recipe must reproduce the shipped weights
from nothing, so inside a recipe every stage but the first starts from its own earlier stages
and the first may not start from a checkpoint at all.

The run's ``config.yaml`` records every stage's resolved config, so ``--resume`` rebuilds the
stages from the run, not from the YAML files, skips the stages that finished (each leaves
``stage.json`` with its result) and continues the one that stopped from its last checkpoint.
"""

from __future__ import annotations

import dataclasses
import json
import logging
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from mrchaos.core.atomic import write_atomic
from mrchaos.learn.config import ConfigError, TrainConfig, config_from_dict, config_to_dict, load_config

__all__ = [
    "Recipe",
    "Stage",
    "is_recipe",
    "load_recipe",
    "resume_recipe",
    "finish_recipe",
    "run_recipe",
    "train_config",
]

log = logging.getLogger(__name__)

#: The keys of a recipe file (``overrides``: for every stage, under each stage's own).
RECIPE_KEYS = ("name", "runs_dir", "overrides", "stages")
#: The keys of a stage entry in a recipe file (``continues``: resume an earlier stage's run in its
#: folder with this stage's overrides, instead of a new run from a config).
STAGE_KEYS = ("name", "config", "overrides", "init_from", "continues")
#: A stage's result file: present once the stage has finished.
DONE = "stage.json"


@dataclass(frozen=True)
class Stage:
    """One resolved stage: its name, its folder and its config (``init_from`` already chained).
    ``continues``: the folder is an earlier stage's, whose run this stage resumes."""

    name: str
    run_dir: Path
    config: TrainConfig
    continues: bool = False

    @property
    def marker(self) -> Path:
        """Its result file, written when it finishes (one per stage, also in a shared folder)."""
        return _marker(self.run_dir, self.name, self.continues)

    @property
    def done(self) -> bool:
        """Whether the stage finished (its result is written)."""
        return self.marker.exists()


def _marker(folder: Path, name: str, continues: bool) -> Path:
    return folder / (f"stage.{name}.json" if continues else DONE)


@dataclass(frozen=True)
class Recipe:
    """A staged run: its folder and its stages in order."""

    name: str
    run_dir: Path
    stages: tuple[Stage, ...]

    def to_dict(self) -> dict:
        """The run's ``config.yaml``: every stage's resolved config."""
        return {
            "name": self.name,
            "run_dir": str(self.run_dir),
            "stages": [
                {"name": s.name, "folder": s.run_dir.name, "continues": s.continues, "config": config_to_dict(s.config)}
                for s in self.stages
            ],
        }


def is_recipe(path: str | Path) -> bool:
    """Whether a YAML file is a staged recipe (a top-level ``stages`` list) rather than one config."""
    try:
        data = yaml.safe_load(Path(path).read_text())
    except (OSError, yaml.YAMLError):
        return False  # load_config reports the file's problem
    return isinstance(data, dict) and "stages" in data


def _read_yaml(path: Path) -> dict:
    if not path.exists():
        raise ConfigError(f"{path}: no such recipe file")
    try:
        data = yaml.safe_load(path.read_text())
    except yaml.YAMLError as e:
        raise ConfigError(f"{path}: not valid YAML ({e})") from None
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: the top level must be a mapping, got {data!r}")
    return data


def _split_overrides(overrides: list[str], names: list[str], where: str) -> tuple[dict[str, str], dict[str, list[str]]]:
    """Command-line overrides: the recipe's own (``name``, ``runs_dir``), and each stage's
    (``stage:key=value`` for one stage, ``key=value`` for every stage)."""
    own: dict[str, str] = {}
    per_stage: dict[str, list[str]] = {n: [] for n in names}
    for ov in overrides:
        key, sep, value = ov.partition("=")
        if not sep:
            raise ConfigError(f"override {ov!r}: expected key=value")
        stage, colon, key = key.rpartition(":")
        if key.strip() in ("name", "runs_dir"):
            if colon:
                raise ConfigError(f"override {ov!r}: {key} belongs to the recipe, not to a stage")
            own[key.strip()] = value
        elif colon:
            if stage not in per_stage:
                raise ConfigError(f"override {ov!r}: {where} has no stage {stage!r} (its stages: {', '.join(names)})")
            per_stage[stage].append(f"{key}={value}")
        else:
            for n in names:
                per_stage[n].append(ov)
    return own, per_stage


def _resolve_refs(value: Any, folders: dict[str, Path], where: str) -> Any:
    """``"@stage"`` strings (alone or in lists) become that earlier stage's folder."""
    if isinstance(value, list):
        return [_resolve_refs(v, folders, where) for v in value]
    if isinstance(value, str) and value.startswith("@"):
        if value[1:] not in folders:
            raise ConfigError(f"{where}: {value!r} names no earlier stage (earlier: {', '.join(folders) or 'none'})")
        return str(folders[value[1:]])
    return value


def load_recipe(path: str | Path, overrides: list[str] | None = None) -> Recipe:
    """Resolve a recipe file: each stage's config loaded relative to the file, its overrides and the
    command line's applied, its folder inside the run and its ``init_from`` chained."""
    path = Path(path)
    data = _read_yaml(path)
    unknown = sorted(set(data) - set(RECIPE_KEYS))
    if unknown:
        raise ConfigError(f"{path}: unknown recipe keys {unknown} (known: {', '.join(RECIPE_KEYS)})")
    common = data.get("overrides") or {}
    if not isinstance(common, dict):
        raise ConfigError(f"{path}: overrides must be a mapping of dotted keys to values")
    entries = data.get("stages")
    if not isinstance(entries, list) or not entries:
        raise ConfigError(f"{path}: stages must be a non-empty list")
    names = []
    for i, e in enumerate(entries):
        if not isinstance(e, dict) or not isinstance(e.get("name"), str) or ("config" in e) == ("continues" in e):
            raise ConfigError(f"{path}: stage {i + 1} needs a name, and a config or the stage it continues")
        bad = sorted(set(e) - set(STAGE_KEYS))
        if bad:
            raise ConfigError(f"{path}: stage {e['name']!r}: unknown keys {bad} (known: {', '.join(STAGE_KEYS)})")
        if e["name"] in names or not e["name"] or "/" in e["name"] or ":" in e["name"]:
            raise ConfigError(f"{path}: stage names must be distinct and plain, got {e['name']!r} twice or malformed")
        names.append(e["name"])
    own, per_stage = _split_overrides(list(overrides or []), names, str(path))
    name = str(own.get("name", data.get("name", path.stem)))
    run_dir = Path(str(own.get("runs_dir", data.get("runs_dir", "runs")))) / name
    folders: dict[str, Path] = {}
    stages: list[Stage] = []
    by_name: dict[str, Stage] = {}
    for i, e in enumerate(entries):
        where = f"{path}: stage {e['name']!r}"
        ovs = e.get("overrides") or {}
        if not isinstance(ovs, dict):
            raise ConfigError(f"{where}: overrides must be a mapping of dotted keys to values")
        ovs = common | ovs
        stage_ovs = [
            f"{k}={yaml.safe_dump(_resolve_refs(v, folders, where), default_flow_style=True).strip()}"
            for k, v in ovs.items()
        ]
        if "continues" in e:
            if "init_from" in e:
                raise ConfigError(f"{where}: a stage that continues another starts from that run, not init_from")
            ref = e["continues"]
            if not (isinstance(ref, str) and ref.startswith("@") and ref[1:] in by_name):
                raise ConfigError(f"{where}: continues must name an earlier stage as '@name', got {ref!r}")
            earlier = by_name[ref[1:]]
            try:
                cfg = config_from_dict(config_to_dict(earlier.config), where, stage_ovs + per_stage[e["name"]])
            except ConfigError as err:
                raise ConfigError(f"{where}: {err}") from None
            stage = Stage(e["name"], earlier.run_dir, cfg, continues=True)
        else:
            if i == 0:
                if e.get("init_from") is not None:
                    raise ConfigError(f"{where}: the first stage starts from scratch (a recipe reproduces its policy)")
                init = None
            else:
                init = _resolve_refs(e.get("init_from", f"@{names[i - 1]}"), folders, where)
            try:
                cfg = load_config(path.parent / str(e["config"]), stage_ovs + per_stage[e["name"]])
            except ConfigError as err:
                raise ConfigError(f"{where}: {err}") from None
            folder = run_dir / e["name"]
            cfg = dataclasses.replace(cfg, name=e["name"], runs_dir=str(run_dir), init_from=init)
            stage = Stage(e["name"], folder, cfg)
        stages.append(stage)
        by_name[stage.name] = stage
        folders[stage.name] = stage.run_dir
    return Recipe(name, run_dir, tuple(stages))


def resume_recipe(run_dir: str | Path, overrides: list[str] | None = None) -> Recipe:
    """The recipe a staged run was started with (its ``config.yaml``), ``stage:key=value`` or
    ``key=value`` overrides applied to the stages that have not finished."""
    run_dir = Path(run_dir)
    data = _read_yaml(run_dir / "config.yaml")
    if "stages" not in data:
        raise ConfigError(f"{run_dir}: not a staged run (its config.yaml has no stages)")
    names = [s["name"] for s in data["stages"]]
    own, per_stage = _split_overrides(list(overrides or []), names, str(run_dir))
    if own:
        raise ConfigError(f"{run_dir}: a resumed run keeps its name and folder ({', '.join(own)} given)")
    stages = []
    for s in data["stages"]:
        folder, continues = run_dir / s.get("folder", s["name"]), bool(s.get("continues", False))
        overrides_left = [] if _marker(folder, s["name"], continues).exists() else per_stage[s["name"]]
        cfg = config_from_dict(s["config"], f"{run_dir / 'config.yaml'}: stage {s['name']!r}", overrides_left)
        cfg = _moved(cfg, Path(str(data.get("run_dir", run_dir))), run_dir)
        stages.append(Stage(s["name"], folder, cfg, continues))
    return Recipe(str(data.get("name", run_dir.name)), run_dir, tuple(stages))


def _moved(cfg: TrainConfig, was: Path, now: Path) -> TrainConfig:
    """A stage's config with the run's folder where it is now (a run may move between sessions):
    its folder and the earlier stages it reads."""
    if was == now:
        return cfg

    def move(p: str) -> str:
        q = Path(p)
        return str(now / q.relative_to(was)) if q.is_relative_to(was) else p

    init = move(cfg.init_from) if cfg.init_from else None
    rerank = dataclasses.replace(cfg.rerank, data=[move(d) for d in cfg.rerank.data])
    return dataclasses.replace(cfg, runs_dir=str(now), init_from=init, rerank=rerank)


class _StageTag(logging.Filter):
    """Prefixes log lines with the stage's name while it runs (once per record)."""

    def __init__(self, label: str) -> None:
        super().__init__()
        self.label = label

    def filter(self, record: logging.LogRecord) -> bool:
        if not getattr(record, "mrchaos_stage", None):
            record.msg = f"[{self.label}] {record.msg}"
            record.mrchaos_stage = self.label
        return True


@contextmanager
def _tagged(label: str) -> Iterator[None]:
    handlers = logging.getLogger().handlers
    tag = _StageTag(label)
    for h in handlers:
        h.addFilter(tag)
    try:
        yield
    finally:
        for h in handlers:
            h.removeFilter(tag)


def train_config(cfg: TrainConfig, run_dir: Path, resume: bool = False, n_eval: int | None = None) -> dict:
    """Train one config in ``run_dir`` by its ``algo`` (PPO, supervision or the re-ranker) and
    evaluate it greedily on ``n_eval`` Random objects (None: 200 after PPO, 100 after supervision;
    0: none); the result, with a one-line ``summary``."""
    if cfg.algo == "ppo":
        from mrchaos.learn.ppo import Trainer

        trainer = Trainer(cfg, run_dir, resume=resume)
        res = dict(trainer.run())
        summary = f"{run_dir}: {res['iteration']} iterations, {res['frames']} frames"
        if res["stopped"]:
            return res | {"summary": summary + " (stopped by signal)"}
        n = 200 if n_eval is None else n_eval
        if n > 0:
            res |= trainer.finish(n)
        return res | {"summary": summary + _greedy(res)}
    from mrchaos.learn.bc import train_bc
    from mrchaos.learn.rerank import train_rerank

    train = train_bc if cfg.algo == "bc" else train_rerank
    res = dict(train(cfg, run_dir, resume=resume, n_eval=100 if n_eval is None else n_eval))
    summary = f"{run_dir}: supervised on {res['samples']} labelled steps ({res['what']}), final loss {res['loss']:.3f}"
    return res | {"stopped": False, "summary": summary + _greedy(res)}


def _greedy(res: dict) -> str:
    if "rela" not in res:
        return "; not evaluated"
    return (
        f"; greedy on {res['n']} Random objects: Rela {res['rela']:.3f}  Final {res['final']:.3f}  "
        f"IoU {res['iou']:.3f}  strict Rela {res['strict_rela']:.3f}"
    )


#: How one stage is trained: (config, its folder, resume) -> its result (a JSON-able dict, with
#: ``stopped`` true where a signal cut it short).
StageRunner = Callable[[TrainConfig, Path, bool], dict]


def run_recipe(
    recipe: Recipe, train: StageRunner = train_config, resume: bool = False, until: str | None = None
) -> list[dict]:
    """Run the stages in order; a finished stage (``stage.json``) is not run again, a started one
    resumes from its last checkpoint. Returns each stage's result; stops after a stage that a
    signal cut short, or after stage ``until`` (a long recipe split over sessions: ``--resume``
    goes on from there). Once every stage has finished, the run's ``checkpoints/last.pt`` is the
    last stage's (:func:`finish_recipe`)."""
    names = [s.name for s in recipe.stages]
    if until is not None and until not in names:
        raise ConfigError(f"{recipe.run_dir}: no stage {until!r} to stop after (its stages: {', '.join(names)})")
    recipe.run_dir.mkdir(parents=True, exist_ok=True)
    path = recipe.run_dir / "config.yaml"
    text = yaml.safe_dump(recipe.to_dict(), sort_keys=False)
    if not resume and (path.exists() or any(s.run_dir.exists() for s in recipe.stages)):
        raise ConfigError(
            f"{recipe.run_dir} already holds a run; continue it with --resume {recipe.run_dir} or name=..."
        )
    write_atomic(path, text)
    results = []
    for i, stage in enumerate(recipe.stages, 1):
        label = f"{recipe.name} {i}/{len(recipe.stages)} {stage.name}"
        if stage.done:
            log.info("stage %s finished before; not run again", label)
            results.append(json.loads(stage.marker.read_text()))
            continue
        started = (stage.run_dir / "checkpoints" / "last.pt").exists()
        with _tagged(label):
            if stage.continues:
                start = "continuing the run"
            else:
                start = "resuming" if started else f"starting from {stage.config.init_from or 'scratch'}"
            log.info("%s in %s", start, stage.run_dir)
            res = train(stage.config, stage.run_dir, started)
        results.append(res)
        if res.get("stopped"):
            log.info("stage %s stopped; continue with --resume %s", label, recipe.run_dir)
            break
        write_atomic(stage.marker, json.dumps(res, indent=1, default=str) + "\n")
        if stage.name == until and i < len(recipe.stages):
            log.info("stopped after stage %s as asked; continue with --resume %s", label, recipe.run_dir)
            break
    else:
        finish_recipe(recipe)
    return results


def finish_recipe(recipe: Recipe) -> Path:
    """Copy the last stage's checkpoint to the run's own ``checkpoints/last.pt``, so that the run
    folder names the recipe's policy wherever a run is accepted (``init_from``, the bench,
    ``tools/ship_policy.py``); its path."""
    src = recipe.stages[-1].run_dir / "checkpoints" / "last.pt"
    dst = recipe.run_dir / "checkpoints" / "last.pt"
    dst.parent.mkdir(parents=True, exist_ok=True)
    write_atomic(dst, src.read_bytes())
    return dst
