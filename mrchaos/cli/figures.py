"""``mrchaos-figures``: inspect, validate, convert and render figure sets; build chaos caches."""

from __future__ import annotations

import argparse
import sys
from collections import Counter
from pathlib import Path
from typing import TYPE_CHECKING

from mrchaos.cli.guard import run_command
from mrchaos.core.errors import MrchaosError

if TYPE_CHECKING:
    from mrchaos.figures.figure import FigureSet

# The commands import the figure stack (torch, shapely, OpenCV) when they run, so that a
# broken dependency is reported by run_command as one line instead of failing this import.
_FIGURE_STACK = ("numpy", "torch", "shapely", "cv2", "PIL")


def _load(paths: list[str] | None) -> list[FigureSet]:
    from mrchaos.figures.figure import FigureSet
    from mrchaos.figures.formats import load_figures
    from mrchaos.figures.library import builtin_figures

    if not paths:
        return [FigureSet("builtin", builtin_figures(), source="builtin")]
    return [load_figures(p) for p in paths]


def _report_rejected(sets: list[FigureSet]) -> int:
    n = 0
    for fs in sets:
        for fid, why in fs.rejected:
            print(f"rejected {fid}: {why}", file=sys.stderr)
            n += 1
    return n


def _valid_figures(paths: list[str] | None, purpose: str) -> list:
    """The valid figures of ``paths`` (rejected ones reported); an error when there are none."""
    sets = _load(paths)
    _report_rejected(sets)
    figs = [f for fs in sets for f in fs.figures]
    if not figs:
        raise MrchaosError(f"no valid figures to {purpose}")
    return figs


def cmd_sheet(args: argparse.Namespace) -> int:
    from mrchaos.figures.families import FamilyRule, family_of
    from mrchaos.figures.sheet import figure_sheet, save_png

    figs = _valid_figures(args.figures, "draw")
    rule = FamilyRule()
    for f in figs:
        f.family = family_of(f, rule)
    save_png(figure_sheet(figs, columns=args.columns, tile=args.tile), args.out)
    counts = Counter(f.family for f in figs)
    print(f"wrote {args.out}: {len(figs)} figures ({', '.join(f'{k} {v}' for k, v in sorted(counts.items()))})")
    return 0


def cmd_validate(args: argparse.Namespace) -> int:
    sets = _load(args.figures)
    for fs in sets:
        print(f"{fs.source}: {len(fs.figures)} valid, {len(fs.rejected)} rejected")
    return 1 if _report_rejected(sets) else 0


def cmd_families(args: argparse.Namespace) -> int:
    from mrchaos.figures.families import (
        FamilyRule,
        confusion_table,
        silhouette_perimeter_px,
    )

    sets = _load(args.figures)
    _report_rejected(sets)
    rule = FamilyRule()
    figs = [f for fs in sets for f in fs.figures]
    for f in figs:
        per = silhouette_perimeter_px(f.silhouette(rule.view).numpy())
        print(f"{f.id:24s} {per:7.1f} px  rule {rule.classify(per):10s}  given {f.family or '-'}")
    if any(f.family for f in figs):
        print(confusion_table(figs, rule)[1])
    return 0


def cmd_convert(args: argparse.Namespace) -> int:
    from mrchaos.figures.formats import save_figures

    figs = _valid_figures(args.figures, "write")
    save_figures(figs, args.out, name=args.name or Path(args.out).stem)
    print(f"wrote {args.out}: {len(figs)} figures")
    return 0


def cmd_chaos(args: argparse.Namespace) -> int:
    from mrchaos.figures.pieces import get_piece_set
    from mrchaos.tasks.chaos import MODES, ChaosCache, ChaosConfig

    cfg = ChaosConfig(mode=args.mode, tile_fraction=args.tile_fraction)
    cache = ChaosCache.build(get_piece_set(args.piece_set), args.n, args.seed, cfg)
    cache.save(args.out)
    counts = ", ".join(f"{int((cache.modes == m).sum())} {name}" for m, name in enumerate(MODES))
    print(f"wrote {args.out}: {len(cache)} objects ({counts}), seed {args.seed}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    from mrchaos.figures.pieces import piece_set_names

    p = argparse.ArgumentParser(prog="mrchaos-figures", description=__doc__)
    sub = p.add_subparsers(dest="command", required=True)
    fig_help = "interchange JSON, KILOGRAM .svg or folder of .svg (repeatable; default: built-in library)"

    s = sub.add_parser("sheet", help="render figures to a PNG contact sheet")
    s.add_argument("--figures", action="append", help=fig_help)
    s.add_argument("--out", default="library.png")
    s.add_argument("--columns", type=int, default=8)
    s.add_argument("--tile", type=int, default=200)
    s.set_defaults(fn=cmd_sheet)

    s = sub.add_parser("validate", help="load and validate figure sets")
    s.add_argument("figures", nargs="*", help=fig_help)
    s.set_defaults(fn=cmd_validate)

    s = sub.add_parser("families", help="perimeter and family of each figure; confusion table against given labels")
    s.add_argument("figures", nargs="*", help=fig_help)
    s.set_defaults(fn=cmd_families)

    s = sub.add_parser("convert", help="write figures as interchange JSON")
    s.add_argument("figures", nargs="+", help=fig_help)
    s.add_argument("--out", required=True)
    s.add_argument("--name")
    s.set_defaults(fn=cmd_convert)

    s = sub.add_parser("chaos", help="pre-generate a cache of chaos objects (.npz)")
    s.add_argument("--n", type=int, default=4096)
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--mode", default="mix", choices=["scatter", "attract", "tile", "mix"])
    s.add_argument("--tile-fraction", type=float, default=0.0, help="share of tile objects under --mode mix")
    s.add_argument(
        "--piece-set", default="tangram7", help=f"a registered piece set ({', '.join(piece_set_names())}, or your own)"
    )
    s.add_argument("--out", required=True)
    s.set_defaults(fn=cmd_chaos)
    return p


def main(argv: list[str] | None = None) -> int:
    # The parser is built after the dependencies import: its help reads the piece-set registry.
    def body() -> int:
        args = build_parser().parse_args(argv)
        return args.fn(args)

    return run_command("mrchaos-figures", body, dependencies=_FIGURE_STACK)


if __name__ == "__main__":
    sys.exit(main())
