"""Expert iteration and crash-safe supervision: the planner's labels, a seconds-long distillation
run, and a supervised run resumed after it was killed."""

import csv
from pathlib import Path

import numpy as np
import pytest
import torch
from tensordict import TensorDict

from mrchaos.bench.benchmark import Bench, resolve_policy
from mrchaos.cli.plot import main as plot_main
from mrchaos.cli.train import main as train_main
from mrchaos.env.tangram import TangramEnv
from mrchaos.learn import bc
from mrchaos.learn.checkpoint import load_checkpoint
from mrchaos.learn.config import load_config
from mrchaos.learn.planner import Lookahead
from mrchaos.learn.policy import build_actor_critic

ROOT = Path(__file__).resolve().parents[1]
TINY_NET = ["policy.channels=[8,16,16]", "policy.hidden=64", "policy.context=8", "precision=fp32"]


def test_a_label_names_the_candidate_the_planner_itself_ranked_first():
    bench = Bench(None, ["Random"], random_objects=4, seed=11, num_worlds=12)
    spec = resolve_policy("mrchaos-dense-ppo")
    env = bench.make_env(spec)
    _, poses, mirrored, _ = bench.targets["Random"][0]
    policy = bench.policy_operator(spec, env)
    planner = Lookahead(policy, 3)
    labels, chosen = planner.label(env, poses, mirrored)
    n, p = len(poses), env.num_pieces
    assert len(labels) == n * p and labels.candidates.shape == (n * p, 3, 3) and labels.extra is None
    assert np.array_equal(chosen, planner.plan(env, poses, mirrored))
    # Rows run (step, target) within the one chunk of 4 targets.
    rows = torch.arange(n * p)
    t, i = rows // n, rows % n
    assert torch.equal(labels.step, t)
    assert torch.equal(labels.candidates[rows, labels.best], torch.as_tensor(chosen[i.numpy(), t.numpy()]))
    # Each IoU, recomputed by playing the plan so far, that candidate, then the policy greedily.
    nx, ny, _ = env.grid.nvec
    for row in (0, n * 3 + 1, n * (p - 1) + 2):
        tt, ii = int(t[row]), int(i[row])
        for c in range(3):
            td = env.reset_to(
                np.repeat(poses[ii : ii + 1], env.batch_size[0], 0),
                np.repeat(mirrored[ii : ii + 1], env.batch_size[0], 0),
            )
            for s in range(p):
                if s < tt:
                    action = torch.as_tensor(chosen[ii, s]).expand(env.batch_size[0], 3)
                elif s == tt:
                    assert torch.equal(td["observation"][0], labels.observation[row])
                    action = labels.candidates[row, c].expand(env.batch_size[0], 3)
                else:
                    with torch.no_grad():
                        action = policy.get_dist(td.select("observation").clone()).mode
                nxt = env.step(td.set("action", action.clone()))["next"]
                td = TensorDict(observation=nxt["observation"], batch_size=env.batch_size)
            assert float(nxt["info", "iou"][0, 0]) == pytest.approx(float(labels.iou[row, c]), abs=1e-6)
        assert labels.iou[row, labels.best[row]] == labels.iou[row].max()


def _exit_run(tmp_path, *extra):
    return train_main(
        [
            str(ROOT / "conf" / "exit.yaml"),
            f"runs_dir={tmp_path}",
            "init_from=null",
            "bc.epochs=2",
            "bc.objects=24",
            "exit.rounds=2",
            "exit.objects=8",
            "exit.k=3",
            "exit.epochs=3",
            "env.num_worlds=24",
            "optim.lr=1e-3",
            "bc.minibatch_size=32",
            "exit.weight=5",
            "exit.dense=1",
            *TINY_NET,
            *extra,
        ]
    )


@pytest.mark.slow  # over 20 s on 2 cores: the default run stays near 10 minutes
def test_a_seconds_long_distillation_run_lowers_its_loss_and_checkpoints_every_round(tmp_path):
    assert _exit_run(tmp_path) == 0
    run = tmp_path / "exit"
    with open(run / "metrics.csv") as f:
        rows = list(csv.DictReader(f))
    assert [r["round"] for r in rows] == ["0", "0", "1", "1", "1", "2", "2", "2"]
    assert [r["kind"] for r in rows] == ["demo"] * 2 + ["exit"] * 6
    for r in ("1", "2"):
        mine = [x for x in rows if x["round"] == r]
        # The planner labelled every state of its 8 objects; its figures open the round.
        assert int(mine[0]["ranked"]) == 8 * 7 * int(r)
        assert 0 <= float(mine[0]["agreement"]) <= 1 and float(mine[0]["planner_rela"]) > 0
        assert float(mine[-1]["loss"]) < float(mine[0]["loss"])
    for r in range(3):
        st = load_checkpoint(run / "checkpoints" / f"round{r}.pt")
        assert st["supervision"]["round"] == r and st["kind"] == "mrchaos-policy"
    assert resolve_policy(str(run)).kind == "checkpoint"
    # mrchaos-plot draws such a run by round: the policy's Rela and the planner's.
    assert plot_main([str(run), "--out", str(tmp_path / "rounds.png")]) == 0
    assert (tmp_path / "rounds.png").stat().st_size > 1000
    assert sorted(p.name for p in (run / "data").iterdir()) == ["round_0.pt", "round_1.pt", "round_2.pt"]

    # The ranking loss alone fits the planner's choices on the states it labelled.
    shard = torch.load(run / "data" / "round_2.pt", weights_only=True)
    cfg = load_config(run / "config.yaml")
    env = TangramEnv(cfg.env_config(), seed=0)
    ac = build_actor_critic(cfg.policy, env.grid, env.view, env.action_spec)
    ac.load_state_dict(load_checkpoint(run / "checkpoints" / "last.pt")["model"])
    policy = ac.get_policy_operator()
    opt = torch.optim.Adam(ac.parameters(), lr=1e-3)
    td = TensorDict(observation=shard["observation"], batch_size=[len(shard["iou"])])
    losses = []
    for _ in range(40):
        loss = bc.ranking_loss(policy.get_dist(td), shard["candidates"], shard["iou"], 0.01).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
    assert losses[-1] < 0.9 * losses[0]


def test_a_supervised_run_killed_after_its_first_epoch_resumes_from_it(tmp_path, monkeypatch):
    args = [
        str(ROOT / "conf" / "dense.yaml"),
        "bc.objects=16",
        "bc.epochs=2",
        "bc.dagger_rounds=1",
        "bc.dagger_objects=8",
        "bc.dagger_epochs=2",
        "env.num_worlds=16",
        *TINY_NET,
    ]
    assert train_main([*args, f"runs_dir={tmp_path / 'whole'}"]) == 0

    fit = bc.SupervisedRun._fit_epoch
    calls = []

    def dies_on_the_second_epoch(self, *a):
        calls.append(1)
        if len(calls) == 2:
            raise KeyboardInterrupt  # as a kill between epochs: nothing of epoch 2 is written
        return fit(self, *a)

    monkeypatch.setattr(bc.SupervisedRun, "_fit_epoch", dies_on_the_second_epoch)
    assert train_main([*args, f"runs_dir={tmp_path / 'cut'}"]) != 0
    monkeypatch.setattr(bc.SupervisedRun, "_fit_epoch", fit)
    cut = tmp_path / "cut" / "dense"
    assert load_checkpoint(cut / "checkpoints" / "last.pt")["supervision"]["epoch"] == 1
    with open(cut / "metrics.csv") as f:
        assert len(list(csv.DictReader(f))) == 1
    config = (cut / "config.yaml").read_bytes()
    assert train_main(["--resume", str(cut)]) == 0
    assert (cut / "config.yaml").read_bytes() == config  # a plain resume keeps the file as it is
    whole = load_checkpoint(tmp_path / "whole" / "dense" / "checkpoints" / "last.pt")
    resumed = load_checkpoint(cut / "checkpoints" / "last.pt")
    # The same four epochs, the DAgger round's labels included, to the last bit.
    assert all(torch.equal(whole["model"][k], resumed["model"][k]) for k in whole["model"])
    with open(cut / "metrics.csv") as f, open(tmp_path / "whole" / "dense" / "metrics.csv") as g:
        a, b = list(csv.DictReader(f)), list(csv.DictReader(g))
    assert [r["loss"] for r in a] == [r["loss"] for r in b] and len(a) == 4


def test_a_resume_with_overrides_records_them_in_the_run_config(tmp_path):
    import dataclasses

    import yaml

    from mrchaos.learn.config import load_config, start_run

    cfg = load_config(ROOT / "conf" / "dense.yaml")
    start_run(cfg, tmp_path)
    shorter = dataclasses.replace(cfg, bc=dataclasses.replace(cfg.bc, dagger_rounds=1))
    start_run(shorter, tmp_path, resume=True)
    assert yaml.safe_load((tmp_path / "config.yaml").read_text())["bc"]["dagger_rounds"] == 1


def test_exit_config_errors(tmp_path, capsys):
    assert train_main([str(ROOT / "conf" / "exit.yaml"), f"runs_dir={tmp_path}", "exit.k=1"]) == 2
    assert "exit.k must be >= 2" in capsys.readouterr().err
    assert train_main([str(ROOT / "conf" / "full.yaml"), f"runs_dir={tmp_path}", "exit.rounds=1"]) == 2
    assert "set algo: bc" in capsys.readouterr().err
    # A truncated data shard names itself.
    assert _exit_run(tmp_path, "exit.rounds=0") == 0
    run = tmp_path / "exit"
    (run / "data" / "round_0.pt").write_bytes(b"not a shard")
    assert train_main(["--resume", str(run)]) == 2
    assert "round_0.pt: not a readable data shard" in capsys.readouterr().err
