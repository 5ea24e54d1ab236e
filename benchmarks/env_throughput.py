"""World-steps per second of ``TangramEnv`` on this machine, with a breakdown.

For N in {1, 16, 256} worlds and two action sources (uniform random actions, and
the nearest-grid oracle on chaos targets), it runs whole episodes and prints
world-steps/s, the share of placements that ran physics, the time split into
physics (MuJoCo settling), images (rasteriser), reward (pixel counts) and the
rest (Python, placement geometry, TorchRL), and the peak RSS.

    python benchmarks/env_throughput.py [--worlds 1 16 256] [--steps 7] [--episodes 4]
"""

from __future__ import annotations

import argparse
import resource
import time

import torch

from mrchaos.env.oracle import oracle_actions
from mrchaos.env.tangram import EnvConfig, TangramEnv
from mrchaos.sim.worlds import PhysicsConfig
from mrchaos.tasks.sampler import CacheConfig, TaskConfig


def run(n: int, policy: str, episodes: int, threads: int) -> dict:
    torch.set_num_threads(threads)
    env = TangramEnv(
        EnvConfig(num_worlds=n, physics=PhysicsConfig(nthread=threads), task=TaskConfig(cache=CacheConfig(size=512))),
        seed=0,
    )
    g = torch.Generator().manual_seed(0)
    nvec = torch.tensor(env.grid.nvec)
    td = env.reset()
    start = env.timings()
    steps = 0
    t0 = time.perf_counter()
    for _ in range(episodes * env.num_pieces):
        a = oracle_actions(env) if policy == "oracle" else (torch.rand((n, 3), generator=g) * nvec).long()
        td = env.step(td.set("action", a))
        nxt = td["next"]
        td = env.step_mdp(td)
        if nxt["done"].any():
            td = env.reset(td.set("_reset", nxt["done"].clone()))
        steps += n
    wall = time.perf_counter() - t0
    spent = env.timings()
    out = {"sps": steps / wall, "physics_share": spent["physics_share"], "wall": wall}
    for k in ("physics", "images", "reward"):
        out[k] = (spent[k] - start[k]) / wall
    out["other"] = 1 - sum(out[k] for k in ("physics", "images", "reward"))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--worlds", type=int, nargs="+", default=[1, 16, 256])
    ap.add_argument("--episodes", type=int, default=4)
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args()
    print(f"{'N':>5} {'policy':>7} {'steps/s':>9} {'physics%':>9} | time share: physics images reward other")
    for n in args.worlds:
        for policy in ("random", "oracle"):
            r = run(n, policy, args.episodes, args.threads)
            print(
                f"{n:>5} {policy:>7} {r['sps']:>9.0f} {100 * r['physics_share']:>8.1f}% | "
                f"{100 * r['physics']:>6.1f}% {100 * r['images']:>6.1f}% {100 * r['reward']:>6.1f}% "
                f"{100 * r['other']:>6.1f}%"
            )
    print(f"peak RSS {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MiB")


if __name__ == "__main__":
    main()
