"""The action grid's ceiling: the oracle, snapping every true pose to the nearest grid action, for
each task under several grids (finer positions, finer angles).

It reads the solution, so it measures what a grid allows, not what a policy learns. Printed per
task, grid and family: Final, IoU and Rela (%), and the share of placements set down onto a
placed piece (the snapping error overlaps the neighbour). "Poses" counts the distinct actions;
"outputs" what a policy scores for one state (a spatial head's coarse cells, plus the fine
offsets of the one cell it chose on a refined grid). Dense labelling costs in proportion to the
outputs a target covers.

    python benchmarks/oracle_ceiling.py                          # every task, the grids below
    python benchmarks/oracle_ceiling.py --tasks cutlery --random-objects 400
    python benchmarks/oracle_ceiling.py --figures ../shared/figures/mrchaos104.json --tasks tangram
    python benchmarks/oracle_ceiling.py --tasks tangram --grids 0,3 --placement robot   # the UR5e places

The same ceiling for one grid from the command line: ``mrchaos-bench --task cutlery --policy
oracle --grid nx=101 --grid ntheta=24``.
"""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

from mrchaos.bench.benchmark import Bench, resolve_policy
from mrchaos.env.actions import ActionGrid
from mrchaos.figures.formats import load_figures
from mrchaos.learn.config import config_from_dict
from mrchaos.tasks.presets import get_preset

#: Grids measured per task ({} is the task's own): finer flat grids, and the coarse grid refined
#: by a fourth, fine index (``fine_xy``, ``fine_theta``). Tangram's figures lie on 45° steps, so
#: only its positions get finer; soda's cans are round (one angle).
GRIDS: dict[str, list[dict]] = {
    "tangram": [{}, {"nx": 101, "ny": 101}, {"nx": 201, "ny": 201}, {"fine_xy": 3}, {"fine_xy": 5}],
    "cutlery": [
        {},
        {"nx": 101, "ny": 101},
        {"ntheta": 24},
        {"nx": 101, "ny": 101, "ntheta": 24},
        {"nx": 201, "ny": 201, "ntheta": 72},
        {"fine_xy": 3, "fine_theta": 3},
        {"fine_xy": 5, "fine_theta": 9},
    ],
    "soda": [{}, {"nx": 101, "ny": 101}, {"fine_xy": 3}, {"fine_xy": 5}],
}


def task_grid(task: str, settings: dict) -> ActionGrid:
    """The action grid a task gets with ``settings`` laid over its preset."""
    cfg = config_from_dict({"env": {"grid": settings}, "task": {"preset": task}}, f"{task} grid").env_config()
    return cfg.grid


def ceiling(
    task: str, settings: dict, random_objects: int, seed: int, figure_sets=None, placement: str = "teleport"
) -> dict:
    """The oracle's results on the task's families under one grid (``Bench.run``'s dict)."""
    families = list(get_preset(task).families)
    bench = Bench(figure_sets, families, random_objects, seed, placement=placement, task=task, grid=settings)
    return bench.run([resolve_policy("oracle")])["policies"]["oracle"]["families"]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--tasks", default="tangram,cutlery,soda")
    ap.add_argument("--random-objects", type=int, default=200)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--figures", type=Path, action="append", help="tangram figure sets (default: the built-in library)")
    ap.add_argument("--grids", help="indices into each task's grids (comma-separated; default: all)")
    ap.add_argument("--placement", choices=("teleport", "robot"), default="teleport")
    args = ap.parse_args()
    tasks = args.tasks.split(",")
    pick = None if args.grids is None else [int(i) for i in args.grids.split(",")]
    for task in tasks:
        if task not in GRIDS:
            ap.error(f"--tasks: unknown task {task!r}; tasks: {', '.join(GRIDS)}")
        if pick is not None and max(pick) >= len(GRIDS[task]):
            ap.error(f"--grids: {task} has grids 0 to {len(GRIDS[task]) - 1}, got {args.grids}")
    sets = [load_figures(p) for p in args.figures] if args.figures else None
    print(
        "| task | grid | position step (mm) | angle step (°) | poses | outputs | family | Final | IoU | Rela "
        "| onto a piece (%) |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for task in tasks:
        for i, settings in enumerate(GRIDS[task]):
            if pick is not None and i not in pick:
                continue
            t0 = time.perf_counter()
            grid = task_grid(task, settings)
            fams = ceiling(
                task, settings, args.random_objects, args.seed, sets if task == "tangram" else None, args.placement
            )
            name = ", ".join(f"{k}={v}" for k, v in settings.items()) or "the task's own"
            step = 2 * grid.half_range / (grid.nx - 1) / grid.fine_xy * 1000
            angle = 360 / grid.ntheta / grid.fine_theta
            outputs = grid.nx * grid.ny * grid.norient + (grid.nfine if grid.refined else 0)
            for fam, s in fams.items():
                onto = 100 * s["contacts"]["onto_piece"] if "contacts" in s else math.nan
                print(
                    f"| {task} | {name} | {step:.2f} | {angle:g} | {grid.size:,} | {outputs:,} | {fam} | "
                    f"{100 * s['final']['mean']:.1f} | {100 * s['iou']['mean']:.1f} | "
                    f"{100 * s['rela']['mean']:.1f} | {onto:.1f} |",
                    flush=True,
                )
            print(f"<!-- {task} {name}: {time.perf_counter() - t0:.0f} s -->", flush=True)


if __name__ == "__main__":
    main()
