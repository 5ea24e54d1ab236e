"""Cost of the world's hot paths on this machine, for the tangram or an extension task.

Prints, for a batch of scenes (default 256 of the seven tangram pieces; ``--task cutlery``
or ``--task soda`` uses that task's piece set, view and chaos workspace):
  * images: the target-id image (silhouette) and the current view's id image;
  * rewards: the joint pixel counts and per-piece coverage (all pieces);
  * chaos objects: generation cost per object for each generator;
and the process's peak resident memory.

    python benchmarks/world_throughput.py [--task tangram] [--batch 256] [--threads 2] [--repeats 20]
"""

from __future__ import annotations

import argparse
import resource
import time

import numpy as np
import torch

from mrchaos.core.raster import rasterize
from mrchaos.env.metrics import coverage_counts, piece_coverage
from mrchaos.figures.pieces import get_piece_set
from mrchaos.learn.config import config_from_dict
from mrchaos.tasks.chaos import attract, scatter
from mrchaos.tasks.presets import PRESETS


def _median_time(fn, repeats: int) -> float:
    fn()  # warm-up
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return float(np.median(times))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--task", default="tangram", choices=sorted(PRESETS))
    ap.add_argument("--batch", type=int, default=256)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=20)
    ap.add_argument("--chaos", type=int, default=256, help="objects per chaos timing")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    cfg = config_from_dict({"task": {"preset": args.task}})
    ps = get_piece_set(cfg.env.piece_set)
    view, chaos = cfg.env.view, cfg.task.chaos
    p = len(ps)
    rng = np.random.default_rng(0)
    b = args.batch
    target = scatter(ps, b, rng, chaos, view)
    current = target + np.concatenate([rng.normal(0, 0.004, (b, p, 2)), rng.normal(0, 0.1, (b, p, 1))], -1)
    tpoly, cpoly = ps.footprints(target), ps.footprints(current)
    parts = ps.raster_parts
    heights = np.tile(np.arange(1, p + 1) * 0.01, (b, 1))
    twins = ps.twin_matrix()

    def image(poly, h=None):
        return rasterize(poly, view, heights=h, parts=parts)

    t_tgt = _median_time(lambda: image(tpoly), args.repeats)
    t_cur = _median_time(lambda: image(cpoly, heights), args.repeats)
    tgt, cur = image(tpoly).ids, image(cpoly, heights).ids

    def rewards():
        c, a = coverage_counts(cur, tgt, p)
        return piece_coverage(c, a, twins)

    t_rew = _median_time(rewards, args.repeats)
    per = 1e6 / b
    print(f"{ps.name}: batch {b} scenes, {args.threads} torch threads, median of {args.repeats}")
    print(f"  target image (silhouette + ids)  {t_tgt * per:7.1f} us/scene")
    print(f"  current view image (ids)         {t_cur * per:7.1f} us/scene")
    print(f"  rewards (all pieces' coverage)   {t_rew * per:7.1f} us/scene")
    print(f"  per step (view + rewards)        {(t_cur + t_rew) * per:7.1f} us/scene   (target <= 100)")
    print(f"  episode start (+ target image)   {(t_tgt + t_cur + t_rew) * per:7.1f} us/scene")

    n = args.chaos
    for name, fn in (("scatter", scatter), ("attract", attract)):
        t = time.perf_counter()
        fn(ps, n, np.random.default_rng(1), chaos, view)
        print(f"  chaos {name:8s} {(time.perf_counter() - t) / n * 1e3:8.2f} ms/object  ({n} objects)")
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(f"  peak RSS {peak:.0f} MiB")


if __name__ == "__main__":
    main()
