"""``mrchaos-bench``: the paper's Table I for policies and baselines on every family."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from mrchaos.cli.guard import run_command
from mrchaos.cli.logs import configure_logging

#: The tangram policy benched when no --policy is given: the one that places, chooses the order
#: and turns pieces over (the paper's method is ``mrchaos``, by name).
DEFAULT_POLICY = "mrchaos-generalist"


def main(argv: list[str] | None = None) -> int:
    # The parser is built after the dependencies import: its help reads the registries (tasks,
    # their families, shipped policies), so that it cannot drift from them.
    return run_command("mrchaos-bench", lambda: _bench(_parsed(argv)))


def _parsed(argv: list[str] | None) -> argparse.Namespace:
    args = _parser().parse_args(argv)
    configure_logging(args.verbose, progress=False)
    return args


def _parser() -> argparse.ArgumentParser:
    from mrchaos.learn.checkpoint import SHIPPED
    from mrchaos.tasks.presets import PRESETS

    ap = argparse.ArgumentParser(prog="mrchaos-bench", description=__doc__)
    ap.add_argument("--task", default="tangram", help=f"one of {', '.join(PRESETS)} (default: tangram)")
    ap.add_argument(
        "--families",
        default="all",
        help="'all' or comma-separated families of the task: "
        + "; ".join(f"{','.join(f.lower() for f in p.families)} ({name})" for name, p in PRESETS.items()),
    )
    ap.add_argument(
        "--policy",
        action="append",
        help="random, oracle, a shipped policy ("
        + ", ".join(SHIPPED)
        + f"), or a checkpoint / run folder (repeatable; default: {DEFAULT_POLICY}, "
        "or mrchaos-<task>)",
    )
    ap.add_argument(
        "--figures",
        action="append",
        help="interchange JSON or folder of KILOGRAM SVGs (repeatable; "
        "default: the built-in library, or the task's authored goals)",
    )
    ap.add_argument("-v", "--verbose", action="store_true", help="also print mrchaos's and the libraries' INFO lines")
    ap.add_argument("--random-objects", type=int, default=200)
    ap.add_argument("--placement", default="teleport", choices=["teleport", "robot"])
    ap.add_argument(
        "--robot-model",
        default="",
        help="UR5e MJCF for --placement robot (default: the package's own; "
        "or MuJoCo Menagerie's universal_robots_ur5e/ur5e.xml)",
    )
    ap.add_argument(
        "--perturb",
        type=int,
        metavar="STEP",
        help="push the piece placed at this step (0-based) "
        "away mid-episode, as in the paper's Fig. 6C, and report coverage before and after",
    )
    ap.add_argument("--perturb-distance", type=float, default=0.05, help="length of the push (m)")
    ap.add_argument("--record", type=Path, help="write a rerun recording of every episode")
    ap.add_argument("--video", type=Path, help="with --placement robot: the first episode as a .gif or .mp4")
    ap.add_argument(
        "--scenes",
        type=int,
        default=1,
        help="with --placement robot and --record or --video: episodes "
        "per policy and family whose scene is rendered (a few frames per placement)",
    )
    ap.add_argument(
        "--flip",
        action="store_true",
        help="evaluate figures that need a chiral piece turned over "
        "(skipped otherwise); random and oracle get the action grid's flip, a checkpoint keeps its "
        "own grid. "
        "Implied when a policy was trained with the flip",
    )
    ap.add_argument(
        "--random-mirror",
        type=float,
        default=0.0,
        metavar="P",
        help="turn each Random object's chiral pieces over with probability P (with --flip), "
        "as a flip policy's training objects are",
    )
    ap.add_argument(
        "--order",
        choices=["fixed", "free"],
        default="fixed",
        help="fixed: pieces go down in the set's order (the paper's task); free: the policy chooses "
        "which piece goes next (random and oracle draw it among the pieces left). A checkpoint plays in "
        "the order it was trained with; implied when every checkpoint benched was trained with free order",
    )
    ap.add_argument(
        "--grid",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="an action-grid setting for random and oracle, laid over the task's (repeatable; "
        "e.g. --grid nx=101 --grid ntheta=24: a finer grid's ceiling); a checkpoint keeps its own grid",
    )
    ap.add_argument("--out", type=Path, default=Path("runs/bench"))
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--worlds", type=int, default=64, help="worlds evaluated at once")
    ap.add_argument(
        "--lookahead",
        type=int,
        default=1,
        metavar="K",
        help="plan around each checkpoint policy: at every step, try its K best actions, complete each "
        "greedily in the simulator and keep the one whose end has the highest IoU with the "
        "silhouette (no solution is read; 1: the greedy policy alone)",
    )
    ap.add_argument(
        "--mode-window",
        type=int,
        metavar="W",
        help="read each spatial checkpoint's deterministic action as the one whose WxW neighbourhood "
        "holds the most probability (odd; 1: the most probable action; default: the checkpoint's "
        "own policy.mode_window)",
    )
    return ap


def _bench(args: argparse.Namespace) -> int:
    t0 = time.perf_counter()
    from mrchaos.bench.benchmark import (
        Bench,
        format_table,
        parse_families,
        resolve_policy,
        write_outputs,
    )
    from mrchaos.figures.formats import load_figures

    families = parse_families(args.families, args.task)
    default = DEFAULT_POLICY if args.task == "tangram" else f"mrchaos-{args.task}"
    specs = [resolve_policy(p) for p in (args.policy or [default])]
    flip = args.flip or any(s.flips for s in specs)
    if flip and not args.flip:
        # A policy that can turn pieces over is asked to: skipping the figures it was trained
        # for would hide the result its checkpoint exists for.
        print(
            "--flip implied by "
            + ", ".join(s.name for s in specs if s.flips)
            + ": figures that need a piece turned over are evaluated",
            file=sys.stderr,
        )
    # Every checkpoint plays in the order it was trained with; --order sets the baselines' (random,
    # oracle). Free-order checkpoints alone imply it; beside fixed-order ones the baselines keep the
    # set's order.
    free = [s.name for s in specs if s.order == "free"]
    checkpoints = [s for s in specs if s.kind == "checkpoint"]
    order = args.order
    if free and order == "fixed":
        if all(s.order == "free" for s in checkpoints):
            order = "free"
            print("--order free implied by " + ", ".join(free), file=sys.stderr)
        else:
            print("free order for " + ", ".join(free) + "; the other policies keep the set's", file=sys.stderr)
    sets = [load_figures(p) for p in args.figures] if args.figures else None  # None: the task's own goals
    if args.video and args.video.suffix.lower() not in (".gif", ".mp4"):
        raise ValueError(f"{args.video}: --video must end in .gif or .mp4")
    film = args.placement == "robot" and (args.record or args.video)
    if args.video and args.placement != "robot":
        raise ValueError("--video films the robot: it needs --placement robot")
    if film:
        from mrchaos.sim.opengl import choose_backend

        choose_backend()  # fail before the evaluation, not after it
    bench = Bench(
        sets,
        families,
        args.random_objects,
        args.seed,
        args.placement,
        args.worlds,
        robot_model=args.robot_model,
        perturb_after=args.perturb,
        perturb_distance=args.perturb_distance,
        scenes=max(args.scenes, 1 if args.video else 0) if film else 0,
        task=args.task,
        flip=flip,
        lookahead=args.lookahead,
        mode_window=args.mode_window,
        random_mirror=args.random_mirror,
        order=order,
        grid=_grid_settings(args.grid),
    )
    for fid, why in bench.skipped:
        print(f"skipped {fid}: {why}", file=sys.stderr)
    recorder = None
    if args.record:
        from mrchaos.loggers.rerun_logger import EpisodeRecorder

        env = bench.make_env(specs[0])
        recorder = EpisodeRecorder(args.record, bench.piece_set.names, (env.grid.xs, env.grid.ys), env.view.extent)
        env.close()
    results = bench.run(specs, recorder)
    if recorder is not None:
        recorder.close()
    results["sources"] = [fs.source for fs in bench.figure_sets]
    results["random_objects"] = args.random_objects
    write_outputs(results, families, args.out)
    _contact_sheet(bench, specs, args.out)
    if args.video:
        from mrchaos.sim.animation import write_video

        write_video(bench.video_frames, args.video, fps=bench.scene_fps * 2)
        print(f"wrote {args.video} ({len(bench.video_frames)} frames, twice real time)")
    print(format_table(results, families))
    if any(results["needs_flip"].values()):
        print(
            "figures that needed a piece turned over: "
            + ", ".join(f"{fam} {k}" for fam, k in results["needs_flip"].items())
        )
    if bench.skipped:
        print(f"({len(bench.skipped)} figures skipped: see results.md)")
    print(f"wrote {args.out}/results.{{json,csv,md}} and contact_sheet.png in {time.perf_counter() - t0:.0f} s")
    return 0


def _grid_settings(items: list[str]) -> dict:
    """``--grid KEY=VALUE`` options as a mapping, each value read as YAML (``nx=101`` is an int)."""
    import yaml

    out = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise ValueError(f"--grid takes KEY=VALUE (an env.grid key), got {item!r}")
        out[key.strip()] = yaml.safe_load(value)
    return out


def _contact_sheet(bench, specs, out: Path, per_family: int = 6) -> None:
    """Silhouette against final assembly for a sample of each family, first policy (paper's Fig. 6)."""
    from mrchaos.figures.sheet import pair_sheet, save_png

    pairs = []
    for fam, groups in bench.targets.items():
        ids = [i for *_, group_ids in groups for i in group_ids]
        res = bench.episodes.get((specs[0].name, fam))
        if res is None:
            continue
        pick = np.linspace(0, len(ids) - 1, min(per_family, len(ids))).round().astype(int)
        for i in pick:
            pairs.append((res.silhouettes[i] > 0, res.final_views[i], f"{fam} {ids[i]} F{100 * res.final[i]:.0f}"))
    if pairs:
        save_png(pair_sheet(pairs, columns=per_family), out / "contact_sheet.png")


if __name__ == "__main__":
    sys.exit(main())
