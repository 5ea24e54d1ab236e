"""Staged recipes: stages resolved and chained, a run killed mid-recipe resumed where it stopped,
a real two-stage run whose second stage starts from the first's weights, and the shipped recipes."""

import json
from pathlib import Path

import pytest
import torch
import yaml

from mrchaos.cli.train import main as train_main
from mrchaos.learn.checkpoint import load_checkpoint
from mrchaos.learn.config import ConfigError
from mrchaos.learn.stages import is_recipe, load_recipe, resume_recipe, run_recipe

ROOT = Path(__file__).resolve().parents[1]
TINY_NET = ["policy.channels=[8,16,16]", "policy.hidden=64", "policy.context=8", "precision=fp32"]


def _recipe(tmp_path: Path, stages: list[dict], name: str = "chain", **extra) -> Path:
    path = tmp_path / f"{name}.yaml"
    path.write_text(yaml.safe_dump({"name": name, "runs_dir": str(tmp_path / "runs"), "stages": stages, **extra}))
    return path


THREE = [
    {"name": "a", "config": str(ROOT / "conf" / "dense.yaml")},
    {"name": "b", "config": str(ROOT / "conf" / "exit.yaml"), "overrides": {"exit.rounds": 2}},
    {
        "name": "c",
        "config": str(ROOT / "conf" / "rerank.yaml"),
        "init_from": "@a",
        "overrides": {"rerank.data": ["@b"]},
    },
]


def test_stages_chain_their_folders_and_weights_and_take_scoped_overrides(tmp_path):
    path = _recipe(tmp_path, THREE)
    assert is_recipe(path) and not is_recipe(ROOT / "conf" / "dense.yaml")
    rec = load_recipe(path, ["b:exit.k=3", "threads=1"])
    run = tmp_path / "runs" / "chain"
    assert rec.run_dir == run
    assert [s.run_dir for s in rec.stages] == [run / "a", run / "b", run / "c"]
    a, b, c = (s.config for s in rec.stages)
    # The first starts from scratch even though the stage configs name shipped policies elsewhere.
    assert a.init_from is None and b.init_from == str(run / "a") and c.init_from == str(run / "a")
    assert c.rerank.data == [str(run / "b")]
    assert b.exit.rounds == 2 and b.exit.k == 3 and a.exit.k != 3
    assert {s.config.threads for s in rec.stages} == {1}
    assert [s.config.name for s in rec.stages] == ["a", "b", "c"]
    assert load_recipe(path, ["name=other"]).run_dir == tmp_path / "runs" / "other"
    # The recipe's own overrides go to every stage, under each stage's.
    stages = [THREE[0], {**THREE[1], "overrides": {"policy.global_view": "none"}}, THREE[2]]
    rec = load_recipe(_recipe(tmp_path, stages, overrides={"policy.global_view": "unet", "threads": 3}))
    assert [s.config.policy.global_view for s in rec.stages] == ["unet", "none", "unet"]
    assert {s.config.threads for s in rec.stages} == {3}
    with pytest.raises(ConfigError, match="unknown recipe keys"):
        load_recipe(_recipe(tmp_path, THREE, epochs=3))


@pytest.mark.parametrize(
    "stages, overrides, message",
    [
        ([{"name": "a", "config": str(ROOT / "conf" / "exit.yaml"), "init_from": "mrchaos-dense"}], [], "from scratch"),
        (THREE, ["z:bc.epochs=1"], "no stage 'z'"),
        (THREE, ["a:name=x"], "belongs to the recipe"),
        ([{"name": "a", "config": str(ROOT / "conf" / "dense.yaml"), "init_from": "@b"}, THREE[1]], [], "from scratch"),
        ([THREE[0], {"name": "b", "config": str(ROOT / "conf" / "exit.yaml"), "init_from": "@q"}], [], "'@q'"),
        ([THREE[0], {"name": "a", "config": str(ROOT / "conf" / "exit.yaml")}], [], "distinct"),
        ([{"name": "a", "config": str(ROOT / "conf" / "dense.yaml"), "epochs": 3}], [], "unknown keys"),
        ([{"name": "a", "config": "missing.yaml"}], [], "no such config file"),
        (THREE, ["a:bc.nope=1"], "stage 'a'"),
        ([], [], "non-empty list"),
    ],
)
def test_bad_recipes_name_the_file_and_the_problem(tmp_path, stages, overrides, message):
    path = _recipe(tmp_path, stages)
    with pytest.raises(ConfigError, match=message) as err:
        load_recipe(path, overrides)
    assert str(path) in str(err.value) or message in ("no stage 'z'", "belongs to the recipe")


class _Killed(Exception):
    pass


def _fake_trainer(calls: list, kill: str | int | None = None):
    """Stands in for training: records each call, leaves a checkpoint holding the stage's name and
    its init_from, and is killed after that checkpoint in stage ``kill`` (a config's name, or the
    n-th call)."""

    def train(cfg, run_dir: Path, resume: bool) -> dict:
        calls.append((cfg.name, resume))
        (run_dir / "checkpoints").mkdir(parents=True, exist_ok=True)
        torch.save({"stage": cfg.name, "init_from": cfg.init_from}, run_dir / "checkpoints" / "last.pt")
        if kill in (cfg.name, len(calls)):
            raise _Killed
        return {"stopped": False, "summary": cfg.name}

    return train


def test_a_recipe_killed_in_its_second_stage_resumes_there_and_does_not_rerun_the_first(tmp_path):
    path = _recipe(tmp_path, THREE)
    calls: list = []
    with pytest.raises(_Killed):
        run_recipe(load_recipe(path), _fake_trainer(calls, kill="b"))
    assert calls == [("a", False), ("b", False)]
    run = tmp_path / "runs" / "chain"
    recorded = yaml.safe_load((run / "config.yaml").read_text())
    assert [s["name"] for s in recorded["stages"]] == ["a", "b", "c"]
    assert recorded["stages"][2]["config"]["rerank"]["data"] == [str(run / "b")]
    assert not (run / "checkpoints" / "last.pt").exists()
    # Starting it again is refused; --resume continues stage b from its checkpoint.
    with pytest.raises(ConfigError, match="--resume"):
        run_recipe(load_recipe(path), _fake_trainer([]))
    calls.clear()
    results = run_recipe(resume_recipe(run, ["c:rerank.epochs=1"]), _fake_trainer(calls), resume=True)
    assert calls == [("b", True), ("c", False)]
    assert [r["summary"] for r in results] == ["a", "b", "c"]
    assert yaml.safe_load((run / "config.yaml").read_text())["stages"][2]["config"]["rerank"]["epochs"] == 1
    assert json.loads((run / "a" / "stage.json").read_text())["summary"] == "a"
    # The run's own checkpoint is the last stage's.
    assert torch.load(run / "checkpoints" / "last.pt")["stage"] == "c"
    # A resumed finished recipe runs nothing.
    calls.clear()
    run_recipe(resume_recipe(run), _fake_trainer(calls), resume=True)
    assert calls == []


def test_a_stage_that_continues_another_resumes_its_run_with_new_settings(tmp_path):
    stages = [THREE[0], {"name": "more", "continues": "@a", "overrides": {"bc.dagger_rounds": 3}}]
    path = _recipe(tmp_path, stages)
    rec = load_recipe(path, ["more:bc.dagger_epochs=5"])
    a, more = rec.stages
    assert more.run_dir == a.run_dir and more.continues and more.marker != a.marker
    assert (more.config.bc.dagger_rounds, more.config.bc.dagger_epochs) == (3, 5)
    assert a.config.bc.dagger_rounds != 3 and more.config.bc.objects == a.config.bc.objects
    calls: list = []
    with pytest.raises(_Killed):
        run_recipe(rec, _fake_trainer(calls, kill=2))
    # The fake trainer records the config's name: the continued run keeps the first stage's.
    assert calls == [("a", False), ("a", True)] and a.done and not more.done
    calls.clear()
    run_recipe(resume_recipe(rec.run_dir), _fake_trainer(calls), resume=True)
    assert calls == [("a", True)] and more.done
    for bad, message in [
        ({"name": "x", "continues": "@nope"}, "earlier stage"),
        ({"name": "x", "continues": "@a", "init_from": "@a"}, "not init_from"),
        ({"name": "x", "continues": "@a", "config": "c.yaml"}, "a config or the stage it continues"),
    ]:
        with pytest.raises(ConfigError, match=message):
            load_recipe(_recipe(tmp_path, [THREE[0], bad]))


def test_until_stops_after_a_stage_and_resume_goes_on(tmp_path):
    path = _recipe(tmp_path, THREE)
    calls: list = []
    with pytest.raises(ConfigError, match="no stage 'z'"):
        run_recipe(load_recipe(path), _fake_trainer(calls), until="z")
    run_recipe(load_recipe(path), _fake_trainer(calls), until="a")
    run = tmp_path / "runs" / "chain"
    assert calls == [("a", False)] and not (run / "checkpoints" / "last.pt").exists()
    run_recipe(resume_recipe(run), _fake_trainer(calls), resume=True, until="b")
    run_recipe(resume_recipe(run), _fake_trainer(calls), resume=True)
    assert calls == [("a", False), ("b", False), ("c", False)] and (run / "checkpoints" / "last.pt").exists()


def test_a_moved_run_resumes_in_its_new_folder(tmp_path):
    calls: list = []
    with pytest.raises(_Killed):
        run_recipe(load_recipe(_recipe(tmp_path, THREE)), _fake_trainer(calls, kill="a"))
    moved = tmp_path / "elsewhere"
    (tmp_path / "runs" / "chain").rename(moved)
    rec = resume_recipe(moved)
    assert rec.stages[1].config.init_from == str(moved / "a")
    assert rec.stages[2].config.rerank.data == [str(moved / "b")]
    assert rec.stages[0].run_dir == moved / "a" and rec.stages[0].config.runs_dir == str(moved)


def test_a_two_stage_recipe_trains_the_second_stage_from_the_first_ones_weights(tmp_path, capsys):
    tiny = {k: yaml.safe_load(v) for k, v in (o.split("=", 1) for o in TINY_NET)}
    stages = [
        {
            "name": "dense",
            "config": str(ROOT / "conf" / "dense.yaml"),
            "overrides": {"bc.objects": 6, "bc.epochs": 1, "bc.dagger_rounds": 0, "env.num_worlds": 6, **tiny},
        },
        # No epochs and no rounds: its weights are exactly where it started.
        {
            "name": "keep",
            "config": str(ROOT / "conf" / "exit.yaml"),
            "overrides": {"exit.rounds": 0, "env.num_worlds": 6, **tiny},
        },
    ]
    path = _recipe(tmp_path, stages, name="two")
    assert train_main([str(path), "--eval=0"]) == 0
    run = tmp_path / "runs" / "two"
    first = load_checkpoint(run / "dense" / "checkpoints" / "last.pt")["model"]
    second = load_checkpoint(run / "keep" / "checkpoints" / "last.pt")["model"]
    final = load_checkpoint(run / "checkpoints" / "last.pt")["model"]
    assert first.keys() == second.keys()
    assert all(torch.equal(first[k], second[k]) and torch.equal(second[k], final[k]) for k in first)
    out = capsys.readouterr().out
    assert str(run / "dense") in out and str(run / "keep") in out and "not evaluated" in out
    # Resuming a finished recipe trains nothing and says so per stage.
    assert train_main(["--resume", str(run)]) == 0


@pytest.mark.parametrize("name", ["rerank", "flip", "dense_ppo", "free", "rerank_unet", "generalist", "cutlery"])
def test_the_shipped_recipes_resolve_from_scratch(name):
    rec = load_recipe(ROOT / "conf" / "recipes" / f"{name}.yaml")
    assert rec.stages[0].config.init_from is None
    folders = {str(s.run_dir) for s in rec.stages}
    for s in rec.stages[1:]:
        assert s.continues or s.config.init_from in folders
        assert all(d in folders for d in s.config.rerank.data)


def test_a_real_run_killed_in_its_second_stage_resumes_its_epochs_and_keeps_the_first(tmp_path, monkeypatch):
    """The same with the real trainer: stage two is killed after its first epoch; the resumed run
    trains only stage two's remaining epoch, from the checkpoint the kill left."""
    from mrchaos.learn import bc

    tiny = {k: yaml.safe_load(v) for k, v in (o.split("=", 1) for o in TINY_NET)}
    small = {"bc.objects": 6, "bc.dagger_rounds": 0, "env.num_worlds": 6, **tiny}
    stages = [
        {"name": "first", "config": str(ROOT / "conf" / "dense.yaml"), "overrides": {**small, "bc.epochs": 1}},
        {"name": "second", "config": str(ROOT / "conf" / "dense.yaml"), "overrides": {**small, "bc.epochs": 2}},
    ]
    path = _recipe(tmp_path, stages, name="killed")
    fit = bc.SupervisedRun._fit_epoch
    fitted: list[str] = []

    def fit_then_maybe_die(self, *args, **kwargs):
        fitted.append(self.cfg.name)
        if fitted.count("second") == 2 and kill:
            raise _Killed  # mid-stage, after its first epoch's checkpoint
        return fit(self, *args, **kwargs)

    kill = True
    monkeypatch.setattr(bc.SupervisedRun, "_fit_epoch", fit_then_maybe_die)
    with pytest.raises(_Killed):
        train_main([str(path), "--eval=0"])
    run = tmp_path / "runs" / "killed"
    assert fitted == ["first", "second", "second"]
    assert (run / "first" / "stage.json").exists() and not (run / "second" / "stage.json").exists()
    first_done = (run / "first" / "stage.json").stat().st_mtime_ns
    kill = False
    fitted.clear()
    assert train_main(["--resume", str(run), "--eval=0"]) == 0
    assert fitted == ["second"]  # its second epoch only; the first stage is not run again
    assert (run / "first" / "stage.json").stat().st_mtime_ns == first_done
    rows = (run / "second" / "metrics.csv").read_text().strip().splitlines()[1:]
    assert len(rows) == 2
