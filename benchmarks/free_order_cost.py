"""What free assembly order costs supervision, against the set's order, on this machine.

Two figures per order: the time to label a state with dense targets (``bc._dense_label`` for the
fixed order, :func:`mrchaos.learn.bc.free_label` over every choosable piece for the free one), on
chaos objects assembled by the oracle in random orders; and the time of one training step (forward,
loss, backward, Adam) on a minibatch, with ``conf/dense.yaml``'s network and precision.

    python benchmarks/free_order_cost.py [--worlds 128] [--batch 256] [--threads 2]
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch
from tensordict import TensorDict

from mrchaos.env.oracle import oracle_poses, random_pieces
from mrchaos.env.tangram import EnvConfig, TangramEnv
from mrchaos.learn.bc import _dense_label, free_label, free_supervised_loss, supervised_loss
from mrchaos.learn.config import load_config
from mrchaos.learn.policy import build_actor_critic
from mrchaos.learn.precision import autocast
from mrchaos.tasks.chaos import ChaosConfig, generate


def label_ms(order: str, worlds: int) -> float:
    """Milliseconds per labelled state over whole assemblies of ``worlds`` chaos objects."""
    env = TangramEnv(EnvConfig(num_worlds=worlds, order=order), seed=0)
    poses, _, mirrored = generate(env.piece_set, worlds, np.random.default_rng(0), ChaosConfig(), env.view)
    env.reset_to(poses, mirrored)
    g = torch.Generator().manual_seed(0)
    spent = 0.0
    for _ in range(env.num_pieces):
        t0 = time.perf_counter()
        if env.free_order:
            free_label(env, 0.02, 0.01)
        else:
            _dense_label(env, 0.02)
        spent += time.perf_counter() - t0
        piece = random_pieces(env, g) if env.free_order else None
        env.place_poses(*oracle_poses(env, piece), piece=piece)
    return 1000 * spent / (env.num_pieces * worlds)


def step_s(order: str, batch: int, repeats: int = 3) -> float:
    """Seconds per training step on a minibatch of random images and labels."""
    cfg = load_config("conf/dense.yaml")
    env = TangramEnv(EnvConfig(num_worlds=1, order=order), seed=0)
    p = env.num_pieces if env.free_order else 0
    ac = build_actor_critic(cfg.policy, env.grid, env.view, env.action_spec, p)
    policy = ac.get_policy_operator()
    opt = torch.optim.Adam(ac.parameters(), lr=1e-4)
    g, s = env.grid, env.view.size
    td = TensorDict(observation=torch.randint(0, 255, (batch, 2, s, s), dtype=torch.uint8), batch_size=[batch])
    if p:
        td.update(
            remaining=torch.ones(batch, p, dtype=torch.bool),
            action_mask=torch.ones(batch, p + sum(g.nvec), dtype=torch.bool),
        )
        label = torch.randint(0, p * g.norient * g.ny * g.nx, (batch, 256), dtype=torch.int32)
        coverage = torch.randint(0, 254, (batch, 256), dtype=torch.uint8)
        rest = torch.zeros(batch)
    else:
        dense = torch.randint(0, 254, (batch, g.norient, g.ny, g.nx), dtype=torch.uint8)
    spent = 0.0
    for i in range(repeats + 1):
        t0 = time.perf_counter()
        with autocast(cfg.precision, torch.device("cpu")):
            dist = policy.get_dist(td)
            if p:
                loss = free_supervised_loss(dist, label, coverage, rest, 0.01).mean()
            else:
                loss = supervised_loss(dist, dense, True, 0.01).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        if i:  # the first step warms the allocator up
            spent += time.perf_counter() - t0
    return spent / repeats


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--worlds", type=int, default=128)
    ap.add_argument("--batch", type=int, default=256)
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    for order in ("fixed", "free"):
        print(
            f"{order:5s} order: {label_ms(order, args.worlds):5.1f} ms to label a state ({args.worlds} worlds), "
            f"{step_s(order, args.batch):5.2f} s per training step on {args.batch} states"
        )


if __name__ == "__main__":
    main()
