"""The afterstate re-ranker: footprints drawn where the env puts the piece, a re-ranker that starts
as the policy, a seconds-long run on a tiny expert-iteration run's data, the bench playing it, and
its errors."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest
import torch

from mrchaos.bench.benchmark import Bench, resolve_policy
from mrchaos.cli.train import main as train_main
from mrchaos.env.actions import ActionGrid
from mrchaos.env.oracle import oracle_actions
from mrchaos.env.tangram import FREE_ORDER_KEYS, EnvConfig, TangramEnv
from mrchaos.learn.checkpoint import CheckpointError, load_checkpoint, save_checkpoint
from mrchaos.learn.evaluate import evaluate, policy_actor
from mrchaos.learn.planner import Lookahead
from mrchaos.learn.policy import PolicyConfig, build_actor_critic
from mrchaos.learn.rerank import AfterstateRanker, Reranked, candidate_footprints, planner_states, reranked_actor
from mrchaos.tasks.chaos import ChaosConfig, generate

ROOT = Path(__file__).resolve().parents[1]
TINY_NET = ["policy.channels=[8,16,16]", "policy.hidden=64", "policy.context=8", "precision=fp32"]


def test_a_candidate_footprint_is_where_the_env_puts_the_piece() -> None:
    env = TangramEnv(EnvConfig(num_worlds=6), seed=3)
    env.reset()
    for t in range(3):
        before = env.current()["observation"][:, 1] > 0
        a = oracle_actions(env)
        foot = candidate_footprints(env.piece_set, env.grid, env.view, a[:, None], torch.full((6,), t))[:, 0]
        after = env.step(env.current().set("action", a))["next"]["observation"][:, 1] > 0
        new = after & ~before
        # The same polygon rasterised twice: equal up to the pixels its edges cut.
        assert (foot ^ new).sum((1, 2)).max() <= 0.08 * new.sum((1, 2)).min()


def test_free_order_candidates_with_the_flip_name_the_piece_and_the_face_the_env_places() -> None:
    """With free order and the flip a candidate is (piece, x, y, orientation and face): the footprint
    drawn for it is the piece, on the face, that the env then places; the re-ranked actor proposes
    only pieces the state allows, and the env places the piece its choice names."""
    env = TangramEnv(EnvConfig(num_worlds=6, order="free", grid=ActionGrid(flip=True)), seed=3)
    chiral = int(np.flatnonzero(env.piece_set.chiral)[0])
    targets, _, mirrored = generate(env.piece_set, 6, np.random.default_rng(4), ChaosConfig(mirror_prob=1.0), env.view)
    assert mirrored[:, chiral].all()
    td = env.reset_to(targets, mirrored)
    # The turned-over piece first, at the oracle's action: its orientation index names the back face.
    before = td["observation"][:, 1] > 0
    a = oracle_actions(env, np.full(6, chiral))
    assert (a[:, 0] == chiral).all() and env.grid.mirrored(a[:, 1:].numpy()).all()
    foot = candidate_footprints(env.piece_set, env.grid, env.view, a[:, None])[:, 0]
    face_up = a.clone()
    face_up[:, 3] -= env.grid.ntheta
    wrong = candidate_footprints(env.piece_set, env.grid, env.view, face_up[:, None])[:, 0]
    td = env.step(td.set("action", a))["next"]
    new = (td["observation"][:, 1] > 0) & ~before
    # The same polygon rasterised twice: equal up to the pixels its edges cut; the other face is not.
    assert ((foot ^ new).sum((1, 2)) <= 0.08 * new.sum((1, 2))).all()
    assert ((wrong ^ new).sum((1, 2)) > 0.3 * new.sum((1, 2))).all()

    torch.manual_seed(0)
    cfg = PolicyConfig(name="spatial", channels=[8, 16, 16], hidden=64, context=8, mode_window=3)
    policy = build_actor_critic(cfg, env.grid, env.view, env.action_spec, pieces=env.num_pieces).get_policy_operator()
    actor = Reranked(policy, AfterstateRanker(8, env.view.size), 4)
    for _ in range(2):
        td = td.select("observation", *FREE_ORDER_KEYS)
        cand, scores = actor.scores(env, td)
        assert cand.shape == (6, 4, 4)
        rows = np.arange(6)[:, None]
        assert env.choosable()[rows, cand[..., 0].numpy()].all()
        choice = actor(env, td)
        assert torch.equal(choice, cand[torch.arange(6), scores.argmax(1)])
        left = td["remaining"].clone()
        td = env.step(td.set("action", choice))["next"]
        placed = left & ~td["remaining"]
        assert placed.sum(1).eq(1).all() and placed[torch.arange(6), choice[:, 0]].all()
    env.close()


@pytest.fixture(scope="module")
def exit_run(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("runs")
    code = train_main(
        [
            str(ROOT / "conf" / "exit.yaml"),
            f"runs_dir={root}",
            "name=exit",
            "init_from=null",
            "bc.epochs=1",
            "bc.objects=8",
            "exit.rounds=2",
            "exit.objects=4",
            "exit.k=3",
            "exit.epochs=1",
            "env.num_worlds=12",
            "bc.minibatch_size=32",
            *TINY_NET,
            "--eval=0",
        ]
    )
    assert code == 0
    return root / "exit"


def test_planner_states_are_whole_episodes_with_their_steps(exit_run: Path) -> None:
    shards = planner_states(exit_run)
    assert len(shards) == 2  # the demonstrations have no planner judgement
    for s in shards:
        n = len(s["iou"])
        assert n == 4 * 7 and s["candidates"].shape == (n, 3, 3) and not s["iou"].isnan().any()
        assert sorted(np.bincount(s["step"].numpy()).tolist()) == [4] * 7


def test_a_seconds_long_rerank_run_and_the_bench_plays_it(exit_run: Path, tmp_path: Path) -> None:
    args = [
        str(ROOT / "conf" / "rerank.yaml"),
        f"runs_dir={tmp_path}",
        f"init_from={exit_run}",
        f"rerank.data=[{exit_run}]",
        "rerank.k=3",
        "rerank.width=8",
        "rerank.epochs=4",
        "rerank.lr=3e-3",
        "rerank.batch=16",
        "env.num_worlds=20",
    ]
    assert train_main(args) == 0
    run = tmp_path / "rerank"
    with open(run / "metrics.csv") as f:
        rows = list(csv.DictReader(f))
    assert [int(r["epoch"]) for r in rows] == [1, 2, 3, 4]
    assert float(rows[-1]["loss"]) < float(rows[0]["loss"])
    assert all(0 <= float(r[k]) <= 1 for r in rows for k in ("train_agreement", "held_agreement"))
    st = load_checkpoint(run / "checkpoints" / "last.pt")
    assert "ranker" in st and st["config"]["rerank"]["k"] == 3
    # The same weights as the policy it re-ranks (frozen), and a config that records its network.
    assert all(
        torch.equal(v, load_checkpoint(exit_run / "checkpoints" / "last.pt")["model"][k])
        for k, v in st["model"].items()
    )

    spec = resolve_policy(str(run))
    bench = Bench(None, ["Random"], random_objects=4, seed=2, num_worlds=4)
    env = bench.make_env(spec)
    actor = bench.actor(spec, env)
    assert isinstance(actor, Reranked)
    td = env.reset()
    cand, scores = actor.scores(env, td)
    a = actor(env, td)
    assert torch.equal(a, cand[torch.arange(4), scores.argmax(1)])
    # With its image path silenced it is the policy itself: the mode is the first candidate.
    torch.nn.init.zeros_(actor.ranker.head[-1].weight)
    torch.nn.init.zeros_(actor.ranker.head[-1].bias)
    assert torch.equal(actor(env, td), policy_actor(actor.policy)(env, td))
    res = bench.run([spec])
    assert 0 < res["policies"]["rerank"]["families"]["Random"]["rela"]["mean"] <= 1
    with pytest.raises(Exception, match="lookahead 4 is more than its 3 candidates"):
        Bench(None, ["Random"], random_objects=4, num_worlds=4, lookahead=4).actor(spec, env)
    # The planner around the re-ranked policy: with one candidate, the re-ranked policy itself.
    _, poses, mirrored, _ = bench.targets["Random"][0]
    greedy = evaluate(env, poses, actor, mirrored=mirrored)
    planned = evaluate(env, poses, Lookahead(actor.policy, 1, actor).actor(env, poses, mirrored), mirrored=mirrored)
    assert np.array_equal(greedy.rela, planned.rela)
    three = Bench(None, ["Random"], random_objects=4, seed=2, num_worlds=6, lookahead=3).actor(spec, env)
    assert isinstance(three, Lookahead) and three.reranked is not None

    # Weights that do not fit are named as such.
    bad = dict(st, ranker={"prior": torch.ones(())})
    save_checkpoint(tmp_path / "bad.pt", bad)
    with pytest.raises(CheckpointError, match="re-ranker weights do not fit"):
        reranked_actor(load_checkpoint(tmp_path / "bad.pt"), actor.policy, env.view)
    env.close()


def test_rerank_config_errors(tmp_path: Path, capsys) -> None:
    conf = str(ROOT / "conf" / "rerank.yaml")
    assert train_main([conf, f"runs_dir={tmp_path}", "init_from=null"]) != 0
    assert "set init_from" in capsys.readouterr().err
    assert train_main([conf, f"runs_dir={tmp_path}", "rerank.k=1"]) != 0
    assert "rerank.k must be >= 2" in capsys.readouterr().err
    (tmp_path / "empty").mkdir()
    assert train_main([conf, f"runs_dir={tmp_path}", "name=r2", f"rerank.data=[{tmp_path / 'empty'}]"]) != 0
    assert "not a run folder" in capsys.readouterr().err
