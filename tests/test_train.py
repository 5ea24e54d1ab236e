import contextlib
import csv
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from mrchaos.cli.train import main as train_main
from mrchaos.core.raster import View
from mrchaos.env.tangram import EnvConfig, TangramEnv
from mrchaos.learn.checkpoint import (
    CheckpointError,
    check_header,
    load_checkpoint,
    save_checkpoint,
)
from mrchaos.learn.config import ConfigError, load_config
from mrchaos.tasks.sampler import MixConfig, TaskConfig

ROOT = Path(__file__).resolve().parents[1]
SMOKE = ROOT / "conf" / "smoke.yaml"


def _rows(run: Path) -> list[dict]:
    with open(run / "metrics.csv") as f:
        return list(csv.DictReader(f))


def test_all_shipped_configs_load():
    for path in sorted((ROOT / "conf").glob("*.yaml")):
        cfg = load_config(path)
        assert cfg.name
    full = load_config(ROOT / "conf" / "full.yaml")
    assert full.curriculum.stages == "both" and full.optim.lr == 2e-4
    assert load_config(ROOT / "conf" / "wo_local.yaml").curriculum.stages == "global"
    assert load_config(ROOT / "conf" / "wo_global.yaml").curriculum.stages == "local"


def test_config_errors(tmp_path):
    with pytest.raises(ConfigError, match="no such config file"):
        load_config(tmp_path / "none.yaml")
    with pytest.raises(ConfigError, match=r"unknown key 'optim.learning_rate'.*optim.lr"):
        load_config(SMOKE, ["optim.learning_rate=1e-3"])
    with pytest.raises(ConfigError, match=r"env.num_worlds: expected an integer"):
        load_config(SMOKE, ["env.num_worlds=many"])
    with pytest.raises(ConfigError, match="unknown key 'colector'"):
        load_config(SMOKE, ["colector.kind=sync"])
    bad = tmp_path / "bad.yaml"
    bad.write_text("env: [1, 2")
    with pytest.raises(ConfigError, match="bad.yaml: not valid YAML"):
        load_config(bad)
    cfg = load_config(SMOKE, ["optim.lr=0.001", "policy.channels=[4,8,8]", "curriculum.stages=global"])
    assert cfg.optim.lr == 0.001 and cfg.policy.channels == [4, 8, 8] and cfg.curriculum.stages == "global"


def test_cli_reports_config_errors(tmp_path, capsys):
    assert train_main([str(SMOKE), "bogus.key=1", f"runs_dir={tmp_path}"]) == 2
    assert "unknown key 'bogus'" in capsys.readouterr().err


def test_checkpoint_errors(tmp_path):
    p = tmp_path / "x.pt"
    with pytest.raises(CheckpointError, match="no such checkpoint"):
        load_checkpoint(p)
    p.write_bytes(b"not a checkpoint at all")
    with pytest.raises(CheckpointError, match="x.pt: not a readable checkpoint"):
        load_checkpoint(p)
    save_checkpoint(
        p,
        {"model": {"w": torch.ones(2)}, "piece_set": "tangram7", "obs_shape": [2, 120, 120], "grid": [51, 51, 8]},
        half=True,
    )
    st = load_checkpoint(p)
    assert st["model"]["w"].dtype == torch.float32
    soda = TangramEnv(EnvConfig(num_worlds=1, piece_set="soda3", task=TaskConfig(mix=MixConfig(chaos=1.0, cache=0.0))))
    with pytest.raises(CheckpointError, match="piece set 'tangram7', not 'soda3'"):
        check_header(st, p, soda)
    task = TaskConfig(mix=MixConfig(chaos=1.0, cache=0.0))
    small = TangramEnv(EnvConfig(num_worlds=1, view=View(size=64), task=task))
    with pytest.raises(CheckpointError, match="observation shape"):
        check_header(st, p, small)


def test_smoke_run_and_resume_after_kill(tmp_path):
    """conf/smoke.yaml runs end to end; a killed run resumes from its last checkpoint."""
    env = dict(os.environ)
    cmd = [
        sys.executable,
        "-m",
        "mrchaos.cli.train",
        str(SMOKE),
        f"runs_dir={tmp_path}",
        "collector.total_frames=100000",
        "checkpoint.every=1",
        "--eval",
        "0",
    ]
    proc = subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    run = tmp_path / "smoke"
    deadline = time.time() + 120
    while time.time() < deadline:
        if (run / "metrics.csv").exists() and len(_rows(run)) >= 4:
            break
        time.sleep(0.2)
    proc.kill()  # a hard kill: no chance to save
    proc.wait()
    assert (run / "checkpoints" / "last.pt").exists()
    saved = load_checkpoint(run / "checkpoints" / "last.pt")
    it0 = saved["iteration"]
    assert it0 >= 2

    rc = train_main(["--resume", str(run), "collector.total_frames=" + str(saved["frames"] + 256), "--eval", "0"])
    assert rc == 0
    after = load_checkpoint(run / "checkpoints" / "last.pt")
    assert after["iteration"] == it0 + 2  # continued: two more iterations of 128 frames
    assert after["frames"] == saved["frames"] + 256
    rows = _rows(run)
    # Iterations after the checkpoint were redone, not duplicated.
    assert [int(r["iteration"]) for r in rows] == list(range(1, it0 + 3))
    recordings = list(run.glob("recording*.rrd"))
    assert len(recordings) == 2  # the first run's and the resumed run's
    import shutil

    rerun = shutil.which("rerun")
    assert rerun, "the rerun CLI comes with rerun-sdk"
    # The killed process could not finish its file; the resumed one closed it properly.
    resumed = run / f"recording.resume{it0}.rrd"
    r = subprocess.run([rerun, "rrd", "verify", str(resumed)], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert (run / "recording.rrd").stat().st_size > 1000
    # Weights moved on from the resumed ones, and the optimiser state came along.
    k = next(iter(after["model"]))
    assert not torch.equal(after["model"][k], saved["model"][k])
    assert after["optim"]["state"]


def test_lr_anneals_linearly_over_the_frame_budget(tmp_path):
    with pytest.raises(ConfigError, match="optim.lr_final anneals over the run's budget"):
        load_config(SMOKE, ["optim.lr_final=0", "collector.total_frames=-1"])
    assert (
        train_main(
            [
                str(SMOKE),
                f"runs_dir={tmp_path}",
                "collector.total_frames=512",
                "optim.lr=1e-3",
                "optim.lr_final=2e-4",
                "--eval",
                "0",
            ]
        )
        == 0
    )
    # Each 128-frame iteration sets the rate for its update from the frames seen so far.
    lrs = [float(r["lr"]) for r in _rows(tmp_path / "smoke")]
    assert lrs == pytest.approx([1e-3 - 8e-4 * i / 4 for i in (1, 2, 3, 4)])
    saved = load_checkpoint(tmp_path / "smoke" / "checkpoints" / "last.pt")
    assert saved["optim"]["param_groups"][0]["lr"] == pytest.approx(2e-4)


def test_sigterm_saves_and_exits_cleanly(tmp_path):
    cmd = [
        sys.executable,
        "-m",
        "mrchaos.cli.train",
        str(SMOKE),
        f"runs_dir={tmp_path}",
        "collector.total_frames=100000",
        "checkpoint.every=1000",
        "--eval",
        "0",
    ]
    proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    run = tmp_path / "smoke"
    deadline = time.time() + 120
    while time.time() < deadline and not ((run / "metrics.csv").exists() and len(_rows(run)) >= 2):
        time.sleep(0.2)
    proc.send_signal(signal.SIGTERM)
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 0, err.decode()[-2000:]
    assert b"stopped by signal" in out
    st = load_checkpoint(run / "checkpoints" / "last.pt")
    assert st["iteration"] == len(_rows(run))


def test_existing_run_is_not_overwritten(tmp_path, capsys):
    run = tmp_path / "smoke" / "checkpoints"
    run.mkdir(parents=True)
    (run / "last.pt").write_bytes(b"precious")
    assert train_main([str(SMOKE), f"runs_dir={tmp_path}"]) == 2
    assert "--resume" in capsys.readouterr().err
    assert (run / "last.pt").read_bytes() == b"precious"


def test_plot(tmp_path):
    from mrchaos.cli.plot import main as plot_main

    run = tmp_path / "r"
    run.mkdir()
    (run / "metrics.csv").write_text(
        "iteration,frames,episodes,stage,rela\n1,10,5,1,0.1\n2,20,10,1,0.2\n3,30,15,2,0.25\n4,40,16,2,0.3\n"
    )
    assert plot_main([str(run)]) == 0
    assert (run / "learning_curve.png").stat().st_size > 1000
    # A metrics.csv given as a file, against minutes and frames (one panel each).
    csv_file = tmp_path / "kept.csv"
    csv_file.write_text(
        (run / "metrics.csv")
        .read_text()
        .replace("stage,rela", "stage,rela,minutes")
        .replace(",0.1\n", ",0.1,0.5\n")
        .replace(",0.2\n", ",0.2,1.0\n")
        .replace(",0.25\n", ",0.25,1.5\n")
        .replace(",0.3\n", ",0.3,2.0\n")
    )
    out = tmp_path / "two.png"
    assert plot_main([str(csv_file), str(run / "metrics.csv"), "--x", "minutes", "frames", "--out", str(out)]) != 0
    assert plot_main([str(csv_file), "--x", "minutes", "frames", "--out", str(out)]) == 0
    from PIL import Image

    assert Image.open(out).size[0] > 1.8 * Image.open(run / "learning_curve.png").size[0]


def test_behaviour_cloning_smoke(tmp_path, capsys):
    """conf/bc.yaml's pipeline on a tiny budget: demonstrations, NLL falls, a loadable policy checkpoint."""
    rc = train_main(
        [
            str(ROOT / "conf" / "bc.yaml"),
            f"runs_dir={tmp_path}",
            "bc.rotations=1",
            "bc.shifts=0",
            "bc.epochs=3",
            "env.num_worlds=32",
            "policy.channels=[8,16,16]",
            "policy.hidden=64",
        ]
    )
    assert rc == 0
    assert "supervised on" in capsys.readouterr().out
    with open(tmp_path / "bc" / "metrics.csv") as f:
        nll = [float(r["loss"]) for r in csv.DictReader(f)]
    assert len(nll) == 3 and nll[-1] < nll[0]
    st = load_checkpoint(tmp_path / "bc" / "checkpoints" / "last.pt")
    assert st["kind"] == "mrchaos-policy" and st["policy"]["name"] == "spatial"  # conf/bc.yaml: the default net
    from mrchaos.bench.benchmark import resolve_policy

    assert resolve_policy(str(tmp_path / "bc")).kind == "checkpoint"


def test_dense_supervision_with_the_flip_smoke(tmp_path, caplog):
    """conf/dense.yaml with the flip and turned-over chaos pieces: both faces labelled, a DAgger
    round on the policy's own assemblies, the loss falls, and the checkpoint's grid flips."""
    import logging

    caplog.set_level(logging.INFO, logger="mrchaos.learn.bc")
    rc = train_main(
        [
            str(ROOT / "conf" / "dense.yaml"),
            f"runs_dir={tmp_path}",
            "env.grid.flip=true",
            "task.chaos.mirror_prob=0.5",
            "bc.objects=48",
            "bc.epochs=3",
            "bc.dagger_rounds=1",
            "bc.dagger_objects=16",
            "bc.dagger_epochs=1",
            "env.num_worlds=16",
            "precision=fp32",
            "policy.channels=[8,16,16]",
            "policy.hidden=64",
            "optim.lr=1e-3",
            "optim.lr_final=1e-4",
        ]
    )
    assert rc == 0
    turned = [r.getMessage() for r in caplog.records if "with a piece turned over" in r.getMessage()]
    assert turned and " 0 with a piece turned over" not in turned[0]
    with open(tmp_path / "dense" / "metrics.csv") as f:
        rows = list(csv.DictReader(f))
    assert [r["round"] for r in rows] == ["0", "0", "0", "1"] and float(rows[2]["loss"]) < float(rows[0]["loss"])
    # optim.lr_final anneals over all four planned epochs, the DAgger round's included: each
    # epoch's last minibatch (48 objects x 7 steps in 2 minibatches of 256, then 64 + 112 = 448) runs at
    # the rate of its start plus its share.
    lrs = [float(r["lr"]) for r in rows]
    shares = (256 / 336,) * 3 + (256 / 448,)
    assert lrs == pytest.approx([1e-3 - 9e-4 * (e + f) / 4 for e, f in enumerate(shares)], abs=1e-6)  # 6 decimals
    from mrchaos.bench.benchmark import resolve_policy

    assert resolve_policy(str(tmp_path / "dense")).flips


def test_multisync_collector_smoke(tmp_path):
    """collector.kind=multisync: two worker processes follow the curriculum switch."""
    rc = train_main(
        [
            str(SMOKE),
            f"runs_dir={tmp_path}",
            "collector.kind=multisync",
            "collector.workers=2",
            "collector.total_frames=768",
            "--eval",
            "0",
        ]
    )
    assert rc == 0
    rows = _rows(tmp_path / "smoke")
    assert len(rows) == 6 and {r["stage"] for r in rows} <= {"1", "2"}


@pytest.mark.slow  # over 20 s on 2 cores: the default run stays near 10 minutes
def test_bf16_first_minibatch_ratios_are_one(tmp_path, monkeypatch):
    """Under bf16 autocast the update recomputes the collector's log-probabilities: ratio 1 before any step."""
    from mrchaos.learn import precision
    from mrchaos.learn.ppo import Trainer
    from mrchaos.learn.precision import autocast

    # Correctness, not speed: on a CPU without native bf16 oneDNN emulates it, and the run
    # would fall back to fp32; the numerics under test are the same either way.
    monkeypatch.setattr(precision, "cpu_has_bf16", lambda: True)

    cfg = load_config(
        SMOKE, [f"runs_dir={tmp_path}", "precision=bf16", "compile=true", "logger.backends=[]", "logger.progress=false"]
    )
    trainer = Trainer(cfg, tmp_path / "bf16")
    assert trainer.precision == "bf16"
    data = next(iter(trainer.collector))
    trainer.collector.shutdown()
    assert data["action_log_prob"].dtype == torch.float32
    with torch.no_grad(), autocast("bf16"):
        dist = trainer.policy.get_dist(data.reshape(-1)[: cfg.loss.minibatch_size].clone())
        new = dist.log_prob(data.reshape(-1)[: cfg.loss.minibatch_size]["action"])
    ratio = (new - data.reshape(-1)[: cfg.loss.minibatch_size]["action_log_prob"]).exp()
    assert (ratio - 1).abs().max() < 1e-3, float((ratio - 1).abs().max())
    # And the update runs and gives finite fp32 losses.
    losses = trainer.update(data)
    assert all(math.isfinite(v) for v in losses.values())


def test_bf16_falls_back_to_fp32_where_the_cpu_lacks_it(monkeypatch):
    """A CPU without native bf16 (oneDNN would emulate it, many times slower) trains in fp32."""
    from mrchaos.learn import precision

    monkeypatch.setattr(precision, "cpu_has_bf16", lambda: False)
    assert precision.resolve_precision("bf16", "cpu") == "fp32"
    assert isinstance(precision.autocast("bf16", "cpu"), contextlib.nullcontext)
    monkeypatch.setattr(precision, "cpu_has_bf16", lambda: True)
    assert precision.resolve_precision("bf16", "cpu") == "bf16"
    with pytest.raises(ValueError, match="precision"):
        precision.resolve_precision("fp16")


def test_collected_values_give_the_same_advantages_as_recomputing_them(tmp_path):
    """GAE on the collector's values (next values shifted along time) equals GAE with the value network."""
    from torchrl.objectives.value import GAE

    from mrchaos.learn.ppo import Trainer

    cfg = load_config(
        SMOKE, [f"runs_dir={tmp_path}", "logger.backends=[]", "logger.progress=false", "curriculum.stages=global"]
    )
    trainer = Trainer(cfg, tmp_path / "gae")
    it = iter(trainer.collector)
    next(it)
    data = next(it)  # episodes that span the batch boundary
    trainer.collector.shutdown()
    assert data["next", "done"].any() and not data["next", "done"].all()
    fast = data.clone()
    with torch.no_grad():
        trainer.values(fast)
        trainer.advantage(fast)
        slow = data.clone().exclude("state_value")
        GAE(
            gamma=cfg.loss.gamma,
            lmbda=cfg.loss.lmbda,
            value_network=trainer.value,
            average_gae=False,
            deactivate_vmap=True,
        )(slow)
    assert torch.allclose(fast["advantage"], slow["advantage"], atol=1e-4)
    assert torch.allclose(fast["value_target"], slow["value_target"], atol=1e-4)


def test_init_from_starts_ppo_from_another_runs_weights(tmp_path):
    from mrchaos.learn.ppo import Trainer

    quiet = [f"runs_dir={tmp_path}", "logger.backends=[]", "logger.progress=false"]
    first = Trainer(load_config(SMOKE, quiet), tmp_path / "a")
    first.save()
    first.collector.shutdown()
    second = Trainer(load_config(SMOKE, quiet + [f"init_from={tmp_path / 'a'}", "seed=1"]), tmp_path / "b")
    second.collector.shutdown()
    a, b = first.actor_critic.state_dict(), second.actor_critic.state_dict()
    assert all(torch.equal(a[k], b[k]) for k in a)
    with pytest.raises(CheckpointError, match="no such checkpoint"):
        Trainer(load_config(SMOKE, quiet + [f"init_from={tmp_path / 'none'}"]), tmp_path / "c")


def test_throughput_benchmark_config_loads_from_the_shipped_conf(tmp_path):
    """benchmarks/train_throughput.py runs conf/full.yaml without a budget; the config must still load
    (a learning-rate anneal in the conf once stopped it with a ConfigError)."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("train_throughput", ROOT / "benchmarks" / "train_throughput.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    cfg = mod._config(str(tmp_path), ["collector.total_frames=-1"])
    assert cfg.optim.lr_final is None and cfg.collector.max_minutes <= 0
