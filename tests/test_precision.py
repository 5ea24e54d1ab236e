"""Precision past the grid: the refined action (a fourth, fine index inside the coarse cell)."""

import math
from pathlib import Path

import numpy as np
import pytest
import torch
from tensordict import TensorDict

from mrchaos.core.geometry import angle_gap
from mrchaos.core.raster import View
from mrchaos.env.actions import ActionGrid
from mrchaos.env.tangram import EnvConfig, TangramEnv
from mrchaos.learn.policy import PolicyConfig, build_actor_critic
from mrchaos.tasks.sampler import CacheConfig, TaskConfig

FINE = ActionGrid(fine_xy=5, fine_theta=9)


def _random_actions(grid: ActionGrid, n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.stack([rng.integers(0, k, n) for k in grid.nvec], 1)


def test_a_refined_action_has_a_fourth_index_and_its_poses_are_a_finer_grid():
    assert FINE.nvec == (51, 51, 8, 225) and FINE.size == 51 * 51 * 8 * 225
    assert ActionGrid().nvec == (51, 51, 8) and not ActionGrid().refined
    pose = FINE.to_pose(_random_actions(FINE, 4000))
    # Positions fall on a grid five times finer than 4 mm, angles on one nine times finer than 45°.
    step = 0.2 / 50 / 5
    assert np.allclose(np.round(pose[:, :2] / step) * step, pose[:, :2], atol=1e-12)
    dt = 2 * math.pi / 8 / 9
    k = (pose[:, 2] + math.pi) / dt
    assert np.allclose(k, np.round(k), atol=1e-9)
    # The middle offset is the coarse pose itself: the refined poses hold the coarse ones.
    coarse = _random_actions(ActionGrid(), 100)
    middle = np.concatenate([coarse, np.full((100, 1), FINE.nfine // 2)], 1)
    assert np.allclose(FINE.to_pose(middle), ActionGrid().to_pose(coarse))


def test_nearest_inverts_to_pose_and_is_never_farther_than_the_coarse_grid():
    a = _random_actions(FINE, 2000, seed=1)
    assert (FINE.nearest(FINE.to_pose(a)) == a).all()
    rng = np.random.default_rng(2)
    pose = np.stack([rng.uniform(-0.1, 0.1, 2000), rng.uniform(-0.1, 0.1, 2000), rng.uniform(-4, 4, 2000)], 1)
    fine = FINE.to_pose(FINE.nearest(pose))
    coarse = ActionGrid().to_pose(ActionGrid().nearest(pose))
    assert (np.abs(fine[:, :2] - pose[:, :2]) <= np.abs(coarse[:, :2] - pose[:, :2]) + 1e-12).all()
    assert np.abs(fine[:, :2] - pose[:, :2]).max() <= 0.004 / 5 / 2 + 1e-12
    gap = angle_gap(fine[:, 2], pose[:, 2], 2 * math.pi)
    assert (gap <= angle_gap(coarse[:, 2], pose[:, 2], 2 * math.pi) + 1e-12).all()
    assert gap.max() <= math.pi / 4 / 9 / 2 + 1e-9


def test_the_refined_action_s_pose_is_where_the_env_puts_the_piece():
    n = 6
    env = TangramEnv(EnvConfig(num_worlds=n, grid=FINE, task=TaskConfig(cache=CacheConfig(size=64))), seed=0)
    env.reset()
    assert env.action_spec.shape == (n, 4)
    a = _random_actions(FINE, n, seed=3)
    a[:, :2] = np.clip(a[:, :2], 15, 35)  # inside the table, clear of the view's edge
    env.step(TensorDict(action=torch.as_tensor(a), batch_size=[n]))
    want = env.piece_set.to_centroid(np.zeros(n, dtype=np.int64), FINE.to_pose(a))
    q = env.worlds.qpos[:, 0:7]
    # The first piece on an empty table is set down without physics, exactly where commanded.
    assert np.allclose(q[:, :2], want[:, :2], atol=1e-9)
    yaw = 2 * np.arctan2(q[:, 6], q[:, 3])
    assert np.allclose(angle_gap(yaw, want[:, 2], 2 * math.pi), 0, atol=1e-9)
    with pytest.raises(ValueError, match=r"shape \(6, 4\) \(x, y, θ, fine\)"):
        env.step(TensorDict(action=torch.zeros(n, 3, dtype=torch.long), batch_size=[n]))
    with pytest.raises(ValueError, match="component fine = 225"):
        env.step(TensorDict(action=torch.as_tensor(np.c_[a[:, :3], np.full(n, 225)]), batch_size=[n]))
    env.close()


@pytest.mark.parametrize(
    "kw, msg",
    [
        ({"fine_xy": 4}, "env.grid.fine_xy must be odd"),
        ({"fine_theta": 0}, "env.grid.fine_theta must be odd and >= 1"),
        ({"fine_xy": 3, "nx": 1}, "needs at least 2 cells"),
    ],
)
def test_bad_refinements_give_a_one_line_error(kw, msg):
    with pytest.raises(ValueError, match=msg) as e:
        ActionGrid(**kw)
    assert "\n" not in str(e.value)


def _refined_policy(window: int = 1):
    torch.manual_seed(0)
    env = TangramEnv(EnvConfig(num_worlds=3, grid=FINE, task=TaskConfig(cache=CacheConfig(size=64))), seed=0)
    ac = build_actor_critic(PolicyConfig(mode_window=window), FINE, env.view, env.action_spec)
    # Non-zero fine weights, so that the offsets' scores differ from cell to cell.
    fine = next(m for m in ac.modules() if type(m).__name__ == "FineHead")
    torch.nn.init.normal_(fine.conv.weight, std=0.5)
    return env, ac


def test_the_refined_policy_samples_four_indices_the_env_takes_and_scores_them_jointly():
    env, ac = _refined_policy(window=3)
    policy = ac.get_policy_operator()
    td = env.reset()
    out = policy(td.clone())
    a = out["action"]
    assert a.shape == (3, 4) and (a >= 0).all() and (a < torch.tensor(FINE.nvec)).all()
    env.step(out)  # the env accepts the policy's refined actions
    dist = policy.get_dist(td.clone())
    # The joint log-probability is the coarse one plus the two offsets' at that cell.
    xy, t = dist.fine_logits(a[:, :3])
    want = (
        torch.log_softmax(dist.scores, -1).gather(-1, (a[:, 2] * 51 * 51 + a[:, 1] * 51 + a[:, 0])[:, None])[:, 0]
        + torch.log_softmax(xy, -1).gather(-1, (a[:, 3] % 25)[:, None])[:, 0]
        + torch.log_softmax(t, -1).gather(-1, (a[:, 3] // 25)[:, None])[:, 0]
    )
    assert torch.allclose(dist.log_prob(a), want, atol=1e-5)
    assert torch.allclose(out["action_log_prob"], want, atol=1e-4)
    # The mode and the planner's candidates carry each coarse action's most probable offset.
    mode = dist.mode
    xy, t = dist.fine_logits(mode[:, :3])
    assert (mode[:, 3] == xy.argmax(-1) + 25 * t.argmax(-1)).all()
    top = dist.top_actions(4)
    assert top.shape == (3, 4, 4) and (top[:, 0] == mode).all()
    # A sample over a batch of offsets: every offset of a cell reachable, their probabilities sum to 1.
    total = sum(dist.log_prob(torch.cat([mode[:, :3], torch.full((3, 1), f)], 1)).exp() for f in range(FINE.nfine))
    coarse_p = torch.softmax(dist.scores, -1).gather(-1, (mode[:, 2] * 2601 + mode[:, 1] * 51 + mode[:, 0])[:, None])[
        :, 0
    ]
    assert torch.allclose(total, coarse_p, rtol=1e-4)
    env.close()


def test_the_fine_head_learns_from_the_joint_log_probability_and_the_entropy_counts_it():
    env, ac = _refined_policy()
    policy = ac.get_policy_operator()
    td = env.reset()
    dist = policy.get_dist(td.clone())
    a = dist.sample()
    lp = dist.log_prob(a)
    ent = dist.entropy()
    coarse_only = super(type(dist), dist).entropy()
    assert (ent > coarse_only).all()  # the offsets add their own uncertainty
    (lp.sum() + ent.sum()).backward()
    fine = next(m for m in ac.modules() if type(m).__name__ == "FineHead")
    assert fine.conv.weight.grad is not None and fine.conv.weight.grad.abs().sum() > 0
    env.close()


def test_a_refined_grid_needs_the_spatial_policy_in_the_set_s_order():
    with pytest.raises(ValueError, match="needs the spatial policy in the set's order"):
        build_actor_critic(PolicyConfig(name="paper"), FINE, View())
    with pytest.raises(ValueError, match="in free order"):
        build_actor_critic(PolicyConfig(), FINE, View(), pieces=7)


def test_the_re_ranker_refuses_a_refined_grid_at_load_and_expert_iteration_takes_it():
    from mrchaos.learn.config import ConfigError, config_from_dict

    with pytest.raises(ConfigError, match="the re-ranker covers the coarse grid only") as e:
        config_from_dict({"env": {"grid": {"fine_xy": 3}}, "algo": "rerank"}, "test")
    assert "\n" not in str(e.value)
    for targets in ("oracle", "dense"):
        config_from_dict({"env": {"grid": {"fine_xy": 3}}, "algo": "bc", "bc": {"targets": targets}}, "test")
    over = {"algo": "bc", "bc": {"targets": "dense"}, "exit": {"rounds": 1}}
    assert config_from_dict({"env": {"grid": {"fine_xy": 3}}, **over}, "test").exit.rounds == 1


def test_the_planner_on_a_refined_grid_plans_refined_actions_and_its_ious_are_the_env_s():
    """Candidates are the policy's best coarse cells, each with its most probable offset; the
    planner's recorded IoU of the chosen last placement is what replaying its plan scores."""
    from mrchaos.learn.evaluate import evaluate
    from mrchaos.learn.planner import Lookahead
    from mrchaos.tasks.chaos import ChaosConfig, generate

    env, ac = _refined_policy()
    policy = ac.get_policy_operator()
    targets, _, _ = generate(env.piece_set, 3, np.random.default_rng(5), ChaosConfig(angle_step=0.0), env.view)
    with torch.no_grad():
        lab, chosen = Lookahead(policy, 3).label(env, targets)  # 3 worlds: one target at a time
        first = policy.get_dist(env.reset_to(targets).select("observation").clone())
    p = env.num_pieces
    assert chosen.shape == (3, p, 4) and lab.candidates.shape == (3 * p, 3, 4)
    # Rows go target by target, step by step. Step 0's candidates are the policy's top 3 with
    # their offsets, the mode first.
    assert (lab.candidates[::p] == first.top_actions(3)).all() and (lab.candidates[::p, 0] == first.mode).all()
    assert (chosen < np.array(FINE.nvec)).all() and len(np.unique(chosen[..., 3])) > 1
    played = evaluate(env, targets, Lookahead.replay(chosen, env))
    last = lab.iou[p - 1 :: p].max(1).values  # the chosen last placement's IoU, per target
    assert torch.allclose(torch.as_tensor(played.iou, dtype=torch.float32), last, atol=1e-5)
    env.close()


def test_dense_demonstrations_on_a_refined_grid_carry_the_oracle_s_offset_and_the_fine_head_fits_it():
    from mrchaos.env.oracle import oracle_actions
    from mrchaos.learn.bc import demonstrations
    from mrchaos.tasks.chaos import ChaosConfig, generate

    env, ac = _refined_policy()
    targets, _, _ = generate(env.piece_set, 3, np.random.default_rng(4), ChaosConfig(angle_step=0.0), env.view)
    data = demonstrations(env, targets, dense=True)
    assert data["label"].shape == (21, 8, 51, 51) and data["fine_label"].shape == (21, 4)
    # States go step by step: the first three are the empty tables, labelled with the oracle's action.
    env.reset_to(targets)
    assert (data["fine_label"][:3] == oracle_actions(env)).all()
    policy = ac.get_policy_operator()
    opt = torch.optim.Adam(ac.parameters(), lr=3e-3)
    obs = TensorDict(observation=data["observation"], batch_size=[21])
    losses = []
    for _ in range(40):
        nll = -policy.get_dist(obs.clone()).fine_log_prob(data["fine_label"]).mean()
        opt.zero_grad()
        nll.backward()
        opt.step()
        losses.append(nll.item())
    assert losses[-1] < 0.5 * losses[0], losses[::10]
    env.close()


def _tiny_cutlery(tmp_path: Path, *overrides: str) -> list[str]:
    """mrchaos-train's arguments for conf/cutlery_dense.yaml on a tiny net, no DAgger, no evaluation."""
    root = Path(__file__).resolve().parents[1]
    tiny = ["bc.dagger_rounds=0", "env.num_worlds=4", "bc.minibatch_size=4", "policy.channels=[8,16,16]"]
    tiny += ["policy.hidden=32", "policy.context=8", "precision=fp32"]
    return [str(root / "conf" / "cutlery_dense.yaml"), f"runs_dir={tmp_path}", *tiny, *overrides, "--eval=0"]


def test_a_supervised_run_on_a_refined_grid_trains_the_fine_head(tmp_path):
    """The recipe end to end: its shards keep the oracle's offsets and its epochs fit them (the
    fine head starts at zero, so any weight away from zero was learnt)."""
    from mrchaos.cli.train import main as train_main
    from mrchaos.learn.checkpoint import load_checkpoint

    assert train_main(_tiny_cutlery(tmp_path, "bc.objects=4", "bc.epochs=2")) == 0
    run = tmp_path / "cutlery_dense"
    shard = torch.load(run / "data" / "round_0.pt", weights_only=True)
    assert shard["fine_label"].shape == (12, 4)
    model = load_checkpoint(run / "checkpoints" / "last.pt")["model"]
    fine = [v for k, v in model.items() if "conv" in k and k.endswith("weight") and v.shape[0] == 9 + 8 * 3]
    assert len(fine) == 1 and fine[0].abs().sum() > 0


def test_an_expert_iteration_round_on_a_refined_grid_keeps_the_offsets_and_the_planner_s_candidates(tmp_path):
    """The cutlery recipe's exit stage end to end: its shard holds the planner's refined candidates
    and their IoUs beside the dense targets and the oracle's offsets."""
    from mrchaos.cli.train import main as train_main

    over = ["bc.objects=3", "bc.epochs=1", "exit.rounds=1", "exit.objects=2", "exit.k=2", "exit.epochs=1"]
    assert train_main(_tiny_cutlery(tmp_path, *over, "exit.dense=1.0")) == 0
    shard = torch.load(tmp_path / "cutlery_dense" / "data" / "round_1.pt", weights_only=True)
    n = 2 * 3  # objects x pieces
    assert shard["candidates"].shape == (n, 2, 4) and shard["fine_label"].shape == (n, 4)
    assert shard["label"].shape[0] == n and not shard["iou"].isnan().any()
    assert (shard["iou"] >= 0).all() and (shard["iou"] <= 1).all()
