"""Counterfactual coverage of every grid action against the env's own reward and exact polygon areas."""

from __future__ import annotations

import numpy as np
import shapely
import torch
from tensordict import TensorDict

from mrchaos.core.geometry import rigid_transform
from mrchaos.env import EnvConfig, TangramEnv
from mrchaos.env.actions import ActionGrid
from mrchaos.env.oracle import oracle_actions
from mrchaos.tasks.chaos import ChaosConfig
from mrchaos.tasks.sampler import MixConfig, TaskConfig


def _env(n: int = 32, seed: int = 3) -> TangramEnv:
    return TangramEnv(EnvConfig(num_worlds=n, task=TaskConfig(mix=MixConfig(chaos=1.0, cache=0.0))), seed=seed)


def test_dense_targets_agree_with_the_env_reward_at_sampled_free_actions():
    env = _env()
    ps, n = env.piece_set, 32
    g = torch.Generator().manual_seed(0)
    dense, real, exact = [], [], []
    env.reset()
    for _ in range(4):
        cov, overlap = env.counterfactual()
        assert cov.shape == overlap.shape == (n, 8, 51, 51)
        answer = env.oracle_targets()
        a = oracle_actions(env)  # near the slot (graded coverage), and random shifts around it
        a[:, :2] = (a[:, :2] + torch.randint(-3, 4, (n, 2), generator=g)).clamp(0, 50)
        ar = torch.arange(n)
        pred, free = cov[ar, a[:, 2], a[:, 1], a[:, 0]], overlap[ar, a[:, 2], a[:, 1], a[:, 0]] == 0
        pose = ps.to_centroid(answer.piece, env.grid.to_pose(a.numpy()))
        out = env.step(TensorDict(action=a, batch_size=[n]))["next"]
        got = out["info", "step_coverage"][:, 0]
        ok = free & ~out["info", "physics"][:, 0]
        for w in np.flatnonzero(ok.numpy()):
            i = answer.piece[w]
            best = np.nan  # exact areas for pieces without twins (a twin's slot is not exposed)
            if ps.twin_matrix()[i].sum() == 1:
                poly = shapely.Polygon(rigid_transform(ps.pieces[i].outline, pose[w]))
                slot = shapely.Polygon(rigid_transform(ps.pieces[i].outline, answer.pose[w]))
                best = poly.intersection(slot).area / slot.area
            dense.append(float(pred[w]))
            real.append(float(got[w]))
            exact.append(best)
    dense, real, exact = map(np.array, (dense, real, exact))
    assert len(dense) > 60 and (real > 0.5).sum() > 10 and (real < 0.5).sum() > 10  # graded, not all-or-nothing
    # Both are rasters of the same areas at 2 mm and 2.2 mm pixels: they agree to a few percent.
    assert np.abs(dense - real).mean() < 0.05 and np.abs(dense - real).max() < 0.15
    m = ~np.isnan(exact)
    assert np.abs(dense[m] - exact[m]).mean() < 0.035


def test_footprints_on_placed_pieces_are_reported_as_overlap():
    env = _env(n=4)
    env.reset()
    a = oracle_actions(env)
    env.step(TensorDict(action=a, batch_size=[4]))  # piece 0 on its slot
    cov, overlap = env.counterfactual()  # for piece 1, placed where piece 0 now lies
    ar = torch.arange(4)
    assert (overlap[ar, a[:, 2], a[:, 1], a[:, 0]] > 0.3).all()
    assert (cov.flatten(1).max(1).values > 0.8).all()  # its own slot is still there to cover
    assert (overlap >= 0).all() and (overlap <= 1).all() and (cov >= 0).all() and (cov <= 1).all()
    # Some worlds only, in the order asked: their rows of the whole batch's answer.
    rows = np.array([3, 1])
    cov_r, overlap_r = env.counterfactual(rows)
    assert torch.equal(cov_r, cov[rows]) and torch.equal(overlap_r, overlap[rows])


def test_dense_targets_with_the_flip_grade_both_faces_like_the_env_reward():
    """With the flip, the turned-over orientations follow the face-up ones and a turned-over
    slot is covered by the turned-over actions; sampled free actions of either face agree with
    the env's own reward."""
    n = 32
    task = TaskConfig(mix=MixConfig(chaos=1.0, cache=0.0), chaos=ChaosConfig(mirror_prob=1.0))
    env = TangramEnv(EnvConfig(num_worlds=n, grid=ActionGrid(flip=True), task=task), seed=5)
    ntheta = env.grid.ntheta
    g = torch.Generator().manual_seed(1)
    dense, real, chiral_gap = [], [], []
    env.reset()
    for _ in range(env.num_pieces):
        cov, overlap = env.counterfactual()
        assert cov.shape == overlap.shape == (n, 2 * ntheta, 51, 51)
        answer = env.oracle_targets()
        a = oracle_actions(env)
        ar = torch.arange(n)
        chiral = env.piece_set.chiral[answer.piece]
        assert (env.grid.mirrored(a.numpy()) == (answer.mirrored & chiral)).all()
        if chiral.any():
            other = a.clone()
            other[:, 2] = (a[:, 2] + ntheta) % (2 * ntheta)  # the same place and angle, the other face
            right, wrong = cov[ar, a[:, 2], a[:, 1], a[:, 0]], cov[ar, other[:, 2], other[:, 1], other[:, 0]]
            chiral_gap += (right - wrong)[torch.as_tensor(chiral)].tolist()
        else:  # a piece that is not chiral goes down as itself whichever face is asked for
            assert torch.equal(cov[:, :ntheta], cov[:, ntheta:])
        # Random faces and shifts around the slot, so that both faces and graded coverage are sampled.
        a[:, :2] = (a[:, :2] + torch.randint(-2, 3, (n, 2), generator=g)).clamp(0, 50)
        a[:, 2] = a[:, 2] % ntheta + ntheta * torch.randint(0, 2, (n,), generator=g)
        pred, free = cov[ar, a[:, 2], a[:, 1], a[:, 0]], overlap[ar, a[:, 2], a[:, 1], a[:, 0]] == 0
        out = env.step(TensorDict(action=a, batch_size=[n]))["next"]
        ok = (free & ~out["info", "physics"][:, 0]).numpy()
        dense += pred[ok].tolist()
        real += out["info", "step_coverage"][:, 0][ok].tolist()
    dense, real = np.array(dense), np.array(real)
    assert len(dense) > 60 and (real > 0.5).sum() > 10 and (real < 0.5).sum() > 10
    assert np.abs(dense - real).mean() < 0.05 and np.abs(dense - real).max() < 0.15
    # On its own face the parallelogram covers its turned-over slot; on the other it misses a good part.
    assert len(chiral_gap) == n and min(chiral_gap) > 0.1
