"""How the pieces of each target set join: chaos generators against figure sets, no policy.

For each chaos mode (seeded objects) and each figure set: the median share of outline that
lies along another piece, the share of pieces that share at least 25 mm of edge with one
neighbour, the median number of blocks (pieces linked by at least 5 mm of shared outline) and
the share of objects that are one block (:mod:`mrchaos.figures.joints`), and what a chaos mode
costs to generate. With ``--sheets DIR`` it also draws a contact sheet of each generator::

    python benchmarks/object_stats.py --n 200 --figures ../shared/figures/mrchaos104.json --sheets docs
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from mrchaos.core.raster import View
from mrchaos.figures.formats import load_figures
from mrchaos.figures.joints import summarize_joints
from mrchaos.figures.library import builtin_figures
from mrchaos.figures.pieces import tangram7
from mrchaos.figures.sheet import draw_polygons, save_png, tile_sheet
from mrchaos.tasks.chaos import MODES, ChaosConfig, generate


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--n", type=int, default=200, help="objects per chaos mode")
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--figures", action="append", default=[], help="figure files to measure beside the library")
    ap.add_argument("--sheets", help="a folder for one contact sheet per generator (chaos_<mode>.png)")
    ap.add_argument("--mirror-prob", type=float, default=0.0, help="task.chaos.mirror_prob of the chaos objects")
    args = ap.parse_args(argv)
    ps, view = tangram7(), View()
    rows = []
    for mode in MODES:
        cfg = ChaosConfig(mode=mode, mirror_prob=args.mirror_prob)
        t0 = time.perf_counter()
        poses, _, mirrored = generate(ps, args.n, np.random.default_rng(args.seed), cfg, view)
        cost = (time.perf_counter() - t0) / args.n * 1e3
        rows.append((f"chaos `{mode}`", summarize_joints(ps, poses, mirrored), f"{cost:.1f} ms"))
        if args.sheets:
            tiles = [draw_polygons(list(ps.footprints(poses[b], mirrored[b])), 160, view) for b in range(24)]
            path = Path(args.sheets) / f"chaos_{mode}.png"
            save_png(tile_sheet(tiles, [f"{mode} {b}" for b in range(24)], columns=8), path)
            print(f"wrote {path}")
    sets = [("built-in library", builtin_figures())]
    sets += [(Path(f).name, load_figures(f).figures) for f in args.figures]
    for name, figs in sets:
        figs = [f for f in figs if f.piece_set.name == ps.name]
        poses, mirrored = np.stack([f.poses for f in figs]), np.stack([f.mirrored for f in figs])
        rows.append((name, summarize_joints(ps, poses, mirrored), ""))
    print(f"{args.n} objects per chaos mode (seed {args.seed}, mirror_prob {args.mirror_prob})")
    print(
        "| set | n | outline touching another piece (median) | pieces sharing >= 25 mm of edge "
        "| blocks (median) | objects that are one block | generation |"
    )
    print("|---|---|---|---|---|---|---|")
    for name, s, cost in rows:
        print(
            f"| {name} | {s.n} | {s.touching:.2f} | {100 * s.edge_share:.0f} % | {s.blocks:g} | "
            f"{100 * s.one_block:.1f} % | {cost} |"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
