"""Robot-mode placement speed on this machine: the UR5e picks and places every piece.

For each batch size N, N worlds assemble seeded chaos targets (all seven pieces, the
targets' own poses) with the executor, and the script prints placements per second
(wall clock), the simulated seconds per placement, the real-time factor per world, and the
failure counts; the teleport placement of the same targets is timed for comparison.

Then ``--flips`` random flips: the parallelogram is turned over on the flip fixture
(:mod:`mrchaos.sim.flipper`) and placed at a random pose on an empty table, ``--flip-worlds``
at a time; printed are the share that land flat, mirrored, within 2 mm and 2 degrees of the
command, the error's median and maximum, and the wall and simulated time a flip costs.

    python benchmarks/robot_throughput.py [--worlds 1 16] [--episodes 2] [--threads 2] [--flips 100]
"""

from __future__ import annotations

import argparse
import math
import resource
import time

import numpy as np

from mrchaos.figures.pieces import tangram7
from mrchaos.sim.flipper import FlipperConfig, landing_error
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
            for f in ("unreachable", "missed", "dropped", "collision", "flip_failed"):
                fails[f] = fails.get(f, 0) + int(getattr(res.robot, f).sum())
    return time.perf_counter() - t0, fails


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--worlds", type=int, nargs="+", default=[1, 16])
    ap.add_argument("--episodes", type=int, default=2, help="whole assemblies timed per batch size")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--flips", type=int, default=100, help="random flips of the parallelogram (0: none)")
    ap.add_argument("--flip-worlds", type=int, default=50, help="flips run at once")
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
        print(
            f"{n:>4} {placements / wall:>13.2f} {placements / tele:>11.0f} {sim:>16.2f} "
            f"{sim * placements / wall:>12.2f}  {fails}"
        )
    if args.flips:
        _flips(ps, args.flips, args.flip_worlds, args.threads)
    print(f"peak RSS {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MiB")


def _flips(ps, total: int, n: int, threads: int) -> None:
    """Random flips of the parallelogram to random poses on an empty table, n at a time."""
    k = ps.names.index("parallelogram")
    worlds = Worlds(ps, n, PhysicsConfig(nthread=threads), robot=RobotConfig(), flipper=FlipperConfig())
    rng = np.random.default_rng(0)
    dist, angle, failed, wall, plain_wall = [], [], [], 0.0, 0.0
    rows = np.arange(n)
    for _ in range(math.ceil(total / n)):
        pose = np.c_[rng.uniform(-0.07, 0.07, (n, 2)), rng.uniform(-math.pi, math.pi, n)]
        worlds.reset(rows)
        t0 = time.perf_counter()
        res = worlds.place(rows, np.full(n, k), pose, np.zeros(n, dtype=bool))
        plain_wall += time.perf_counter() - t0
        worlds.reset(rows)
        sim0 = worlds.executor.simulated_seconds + worlds.flipper.simulated_seconds
        t0 = time.perf_counter()
        res = worlds.place(rows, np.full(n, k), pose, np.ones(n, dtype=bool))
        wall += time.perf_counter() - t0
        r = res.robot
        failed.append(r.unreachable | r.missed | r.dropped | r.collision | r.flip_failed)
        d, a = landing_error(ps.pieces[k], worlds.footprint[:, k], pose)
        dist.append(d), angle.append(a)
    sim = worlds.executor.simulated_seconds + worlds.flipper.simulated_seconds - sim0
    dist, angle, failed = map(np.concatenate, (dist, angle, failed))
    dist, angle, failed = dist[:total], angle[:total], failed[:total]
    good = ~failed & (dist < 0.002) & (angle < math.radians(2.0))
    fin = np.isfinite(dist)
    batches = math.ceil(total / n)
    print(
        f"flips: {good.sum()} of {total} land flat, mirrored, within 2 mm and 2 deg ({failed.sum()} flagged); "
        f"error median {1e3 * np.median(dist[fin]):.2f} mm, max {1e3 * dist[fin].max():.2f} mm, "
        f"{np.degrees(angle[fin].max()):.2f} deg"
    )
    print(
        f"a flipped placement: {wall / batches:.2f} s wall per call of {n} worlds against "
        f"{plain_wall / batches:.2f} s "
        f"for the same placement face up; {sim / n:.1f} simulated s per world (last call)"
    )


if __name__ == "__main__":
    main()
