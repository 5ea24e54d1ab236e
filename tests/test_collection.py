"""Collectors (sync, multisync, Ray), the curriculum stage carried with the policy weights,
the device wiring, and the loggers picked from YAML."""

import csv
from pathlib import Path

import pytest
import torch

from mrchaos.cli.train import main as train_main
from mrchaos.learn.checkpoint import load_checkpoint
from mrchaos.learn.collection import collector_devices, make_env, worker_config, worker_seed
from mrchaos.learn.config import ConfigError, load_config
from mrchaos.learn.curriculum import GLOBAL, LOCAL, CurriculumTransform
from tests.conftest import require_extra

ROOT = Path(__file__).resolve().parents[1]
SMOKE = ROOT / "conf" / "smoke.yaml"


def _quiet(tmp_path, *extra):
    return load_config(SMOKE, [f"runs_dir={tmp_path}", "logger.backends=[]", "logger.progress=false", *extra])


def _rows(run: Path) -> list[dict]:
    with open(run / "metrics.csv") as f:
        return list(csv.DictReader(f))


def test_worker_seeds_are_distinct_streams():
    seeds = [worker_seed(0, i) for i in range(8)] + [worker_seed(1, i) for i in range(8)]
    assert len(set(seeds)) == len(seeds) and 0 not in seeds and 1 not in seeds


def test_curriculum_reads_the_trainers_stage_at_every_reset():
    stage = torch.tensor(LOCAL)
    cur = CurriculumTransform(7, "both", stage=stage)
    assert cur.is_local and cur.stage is stage
    stage.fill_(GLOBAL)
    assert not cur.is_local
    assert cur.force_switch(3) is False  # already in stage 2


def test_device_wiring_keeps_the_env_on_the_cpu(tmp_path):
    cuda = _quiet(tmp_path, "device=cuda")
    dev = collector_devices(cuda)
    assert dev["env_device"] == torch.device("cpu")
    assert dev["policy_device"] == dev["storing_device"] == torch.device("cuda")
    ray = _quiet(tmp_path, "device=cuda", "collector.kind=ray")
    assert collector_devices(ray)["policy_device"] == torch.device("cpu")  # Ray actors reserve no GPU
    env = make_env(cuda, seed=0)
    assert env.device == torch.device("cpu") and env.base_env.device == torch.device("cpu")
    assert all(v.device == torch.device("cpu") for v in env.reset().values(True, True))
    env.close()

    from mrchaos.learn.ppo import Trainer

    trainer = Trainer(_quiet(tmp_path), tmp_path / "devices")
    c = trainer.collector
    assert c.env_device == torch.device("cpu") and c.policy_device == torch.device("cpu")
    data = next(iter(c))
    c.shutdown()
    assert data.device == torch.device("cpu")


def test_worker_config_resolves_the_cache_and_threads(tmp_path):
    cfg = _quiet(tmp_path, "task.cache.path=runs/cache.npz", "collector.worker_threads=3")
    w = worker_config(cfg)
    assert Path(w.task.cache.path).is_absolute() and w.task.cache.path.endswith("runs/cache.npz")
    assert w.env.physics.nthread == 3
    assert cfg.task.cache.path == "runs/cache.npz"  # the run's own config is left alone


def test_collector_config_is_checked(tmp_path):
    with pytest.raises(ConfigError, match="collector.kind"):
        _quiet(tmp_path, "collector.kind=async")
    with pytest.raises(ConfigError, match="logger.backends"):
        _quiet(tmp_path, "logger.backends=[tensorbored]")
    with pytest.raises(ValueError, match="multiple of collector.workers"):
        from mrchaos.learn.ppo import Trainer

        Trainer(_quiet(tmp_path, "collector.kind=multisync", "collector.workers=3"), tmp_path / "bad")


def test_old_logger_switches_load_as_backends(tmp_path):
    assert _quiet(tmp_path).logger.backends == []
    cfg = load_config(SMOKE, ["logger.rerun=false", "logger.csv=true"])
    assert cfg.logger.backends == []
    cfg = load_config(SMOKE, ["logger.backends=[tensorboard]", "logger.rerun=true"])
    assert cfg.logger.backends == ["rerun", "tensorboard"]


def _first_batch(tmp_path, name, *extra):
    from mrchaos.learn.ppo import Trainer

    trainer = Trainer(_quiet(tmp_path, *extra), tmp_path / name)
    try:
        return next(iter(trainer.collector))
    finally:
        trainer.collector.shutdown()


def test_multisync_workers_see_different_tasks_and_a_seeded_run_repeats(tmp_path):
    args = ("collector.kind=multisync", "collector.workers=2", "curriculum.stages=global")
    a = _first_batch(tmp_path, "a", *args)
    b = _first_batch(tmp_path, "b", *args)
    obs = a.reshape(-1, a.shape[-1])["observation"]  # (worlds of both workers, time, channels, H, W)
    first = obs[:, 0, 0].reshape(2, 16, *obs.shape[-2:])  # each worker's 16 silhouettes at its first step
    assert not torch.equal(first[0], first[1]), "two workers drew the same tasks"
    assert torch.equal(a["observation"], b["observation"])
    assert torch.equal(a["action"], b["action"])


def test_tensorboard_run_is_read_back(tmp_path):
    require_extra("tensorboard", "tensorboard")
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    rc = train_main(
        [
            str(SMOKE),
            f"runs_dir={tmp_path}",
            "logger.backends=[tensorboard,csv]",
            "collector.total_frames=512",
            "--eval",
            "0",
        ]
    )
    assert rc == 0
    rows = _rows(tmp_path / "smoke")
    acc = EventAccumulator(str(tmp_path / "smoke" / "tensorboard"))
    acc.Reload()
    assert "reward" in acc.Tags()["scalars"]
    events = acc.Scalars("reward")
    assert [e.step for e in events] == [int(r["iteration"]) for r in rows]
    assert [round(e.value, 5) for e in events] == [round(float(r["reward"]), 5) for r in rows]
    # TorchRL's CSV logger, beside metrics.csv.
    assert (tmp_path / "smoke" / "csv" / "scalars" / "reward.csv").exists()


@pytest.mark.slow  # over 20 s on 2 cores: the default run stays near 10 minutes
def test_ray_smoke_run_passes_the_curriculum_switch_and_checkpoints(tmp_path):
    """Two Ray actors on a local 2-CPU cluster: the stage-2 switch, made in the trainer, reaches
    them (their episodes grow from one step to seven)."""
    ray = require_extra("ray", "ray")
    try:
        rc = train_main(
            [
                str(SMOKE),
                f"runs_dir={tmp_path}",
                "collector.kind=ray",
                "collector.workers=2",
                "collector.total_frames=1280",
                "--eval",
                "0",
            ]
        )
    finally:
        ray.shutdown()
    assert rc == 0
    rows = _rows(tmp_path / "smoke")
    assert len(rows) == 10
    stages = [int(r["stage"]) for r in rows]
    assert stages[0] == LOCAL and stages[-1] == GLOBAL, stages
    episodes = [int(r["episodes"]) for r in rows]
    ended = [b - a for a, b in zip([0] + episodes, episodes, strict=False)]
    frames = 128
    for stage, e in zip(stages, ended, strict=True):
        if stage == LOCAL:
            assert e == frames  # one placement per episode
        else:
            assert e < frames // 2  # whole episodes: the actors follow the switch
    st = load_checkpoint(tmp_path / "smoke" / "checkpoints" / "last.pt")
    assert st["curriculum"]["stage"] == GLOBAL and st["iteration"] == 10


def test_dependencies_are_ranges_and_the_constraints_pin_them():
    import tomllib

    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    assert project["requires-python"] == ">=3.11"  # mujoco 4 needs 3.11
    deps = project["dependencies"] + [d for v in project["optional-dependencies"].values() for d in v]
    assert not [d for d in deps if "==" in d], "exact pins belong in constraints.txt"
    pins = {}
    for line in (ROOT / "constraints.txt").read_text().splitlines():
        line = line.split("#")[0].strip()
        if line:
            name, _, version = line.partition("==")
            assert version, f"constraints.txt: {line!r} is not an exact pin"
            pins[name.lower().replace("_", "-")] = version
    import re

    for d in project["dependencies"]:
        name = re.split(r"[<>=!~\[; ]", d, maxsplit=1)[0].lower()
        assert name in pins, f"{name} has no exact version in constraints.txt"
    assert pins["torch"] == "2.13.0"  # the CPU build on the project's machines
