"""Mirror a figure set (x -> -x): ``python tools/mirror_figures.py mrchaos104.json mrchaos104_mirrored.json``.

Every chiral piece changes face, so a set built face up (mrchaos104) becomes one that needs
the parallelogram turned over: what ``mrchaos-bench --flip`` and ``env.grid.flip`` are for.
Each mirrored figure keeps its original's family (its label, else the perimeter rule's
verdict on the original), so the two sets compare family by family. ``builtin`` as the
input mirrors the built-in library.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

from mrchaos.figures.families import family_of
from mrchaos.figures.figure import mirror_figure
from mrchaos.figures.formats import load_figures, save_figures
from mrchaos.figures.library import builtin_figures


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("figures", help="interchange JSON or KILOGRAM SVGs, or 'builtin' for the built-in library")
    ap.add_argument("out", type=Path, help="interchange JSON to write")
    args = ap.parse_args(argv)
    if args.figures == "builtin":
        figures, name = builtin_figures(), "builtin"
    else:
        fs = load_figures(args.figures)
        for fid, why in fs.rejected:
            print(f"skipping {fid}: {why}", file=sys.stderr)
        figures, name = fs.figures, fs.name
    mirrored = [dataclasses.replace(mirror_figure(f), family=family_of(f)) for f in figures]
    save_figures(
        mirrored, args.out, f"{name}-mirrored", description=f"{name} reflected in the y axis (tools/mirror_figures.py)"
    )
    need = sum(f.has_mirrored for f in mirrored)
    print(f"wrote {len(mirrored)} mirrored figures to {args.out}; {need} need a chiral piece turned over")
    return 0


if __name__ == "__main__":
    sys.exit(main())
