"""Robot-mode placement speed on this machine: the UR5e picks and places every piece.

For each batch size N, N worlds assemble seeded chaos targets (all seven pieces, the
targets' own poses) with the executor, and the script prints placements per second
(wall clock), the simulated seconds per placement, the real-time factor per world, and the
failure counts; the teleport placement of the same targets is timed for comparison.

    python benchmarks/robot_throughput.py [--worlds 1 16] [--episodes 2] [--threads 2]
"""

from __future__ import annotations

import argparse
import resource
import time

import numpy as np

from mrchaos.figures.pieces import tangram7
from mrchaos.sim.robot import RobotConfig
from mrchaos.sim.worlds import PhysicsConfig, Worlds
from mrchaos.tasks.chaos import ChaosConfig, generate


def _assemble(worlds: Worlds, targets: np.ndarray) -> tuple[float, dict[str, int]]:
    """Place every piece of ``targets`` (N, P, 3) in order; wall seconds and failure counts."""
    rows = np.arange(worlds.n)
    fails: dict[str, int] = {}
    worlds.reset(rows)
    t0 = time.perf_counter()
    for k in range(targets.shape[1]):
        res = worlds.place(rows, np.full(worlds.n, k), targets[:, k])
        if res.robot is not None:
            for f in ("unreachable", "missed", "dropped", "collision"):
                fails[f] = fails.get(f, 0) + int(getattr(res.robot, f).sum())
    return time.perf_counter() - t0, fails


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--worlds", type=int, nargs="+", default=[1, 16])
    ap.add_argument("--episodes", type=int, default=2, help="whole assemblies timed per batch size")
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args()
    ps = tangram7()
    print(f"robot placement, {args.threads} threads: whole assemblies of {len(ps)} pieces on seeded chaos targets")
    print(f"{'N':>4} {'placements/s':>13} {'teleport/s':>11} {'sim s/placement':>16} {'x real time':>12}  failures")
    for n in args.worlds:
        rng = np.random.default_rng(n)
        targets = [generate(ps, n, rng, ChaosConfig())[0] for _ in range(args.episodes + 1)]
        robot = Worlds(ps, n, PhysicsConfig(nthread=args.threads), robot=RobotConfig())
        teleport = Worlds(ps, n, PhysicsConfig(nthread=args.threads))
        _assemble(robot, targets[0])  # warm-up
        wall, fails = 0.0, {}
        for tg in targets[1:]:
            w, f = _assemble(robot, tg)
            wall += w
            for k, v in f.items():
                fails[k] = fails.get(k, 0) + v
        tele = sum(_assemble(teleport, tg)[0] for tg in targets[1:])
        placements = n * len(ps) * args.episodes
        sim = robot.executor.simulated_seconds / (n * len(ps) * (args.episodes + 1))
        print(f"{n:>4} {placements / wall:>13.2f} {placements / tele:>11.0f} {sim:>16.2f} "
              f"{sim * placements / wall:>12.2f}  {fails}")
    print(f"peak RSS {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MiB")


if __name__ == "__main__":
    main()
