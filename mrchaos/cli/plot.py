"""``mrchaos-plot RUN [RUN ...] [--x episodes|frames|minutes ...] [--out PNG]``: learning curves like
the paper's Fig. 4b. A RUN is a run folder or a ``metrics.csv`` (e.g. the ones kept in ``docs/runs/``);
several ``--x`` give one panel each (Rela against minutes and against frames, say). Supervised runs
with expert-iteration rounds are plotted by round: the greedy policy's Rela and the planner's."""

from __future__ import annotations

import argparse
import csv
import math
import sys
from pathlib import Path

from mrchaos.cli.guard import run_command

AXES = {"episodes": "training episodes", "frames": "frames (world-steps)", "minutes": "training minutes"}


def _label(run: Path) -> str:
    run = Path(run)
    return run.stem if run.suffix == ".csv" else run.name


def _number(text: str) -> float:
    """A cell as a number; an empty or text cell (a supervised run's round kind) as NaN."""
    try:
        return float(text)
    except ValueError:
        return float("nan")


def read_metrics(run_dir: Path) -> list[dict[str, float]]:
    """The rows of a run's ``metrics.csv`` (``run_dir`` is the run folder or the file), as floats (NaN
    where a cell is empty or text)."""
    path = Path(run_dir)
    if path.suffix != ".csv":
        path = path / "metrics.csv"
    if not path.exists():
        raise FileNotFoundError(f"{run_dir}: no metrics.csv")
    with open(path) as f:
        rows = []
        for r in csv.DictReader(f):
            rows.append({k: _number(v) for k, v in r.items()})
    return rows


def plot_runs(run_dirs: list[Path], out: Path, window: int = 10, xs: tuple[str, ...] = ("episodes",)) -> None:
    """Relative coverage (smoothed) against episodes, frames or minutes, one panel per axis, stage switches marked."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    for x in xs:
        if x not in AXES:
            raise ValueError(f"--x must be one of {', '.join(AXES)}, got {x!r}")
    fig, axes = plt.subplots(1, len(xs), figsize=(7 * len(xs), 4), dpi=120, squeeze=False)
    runs = [(run, read_metrics(run)) for run in run_dirs]
    for ax, x in zip(axes[0], xs, strict=True):
        for run, rows in runs:
            if not rows or "rela" not in rows[0]:
                raise ValueError(f"{run}: metrics.csv has no rela column (a supervised run?)")
            if x not in rows[0]:
                raise ValueError(f"{run}: metrics.csv has no {x} column")
            t = np.array([r[x] for r in rows])
            rela = np.array([r["rela"] for r in rows])
            ok = ~np.isnan(rela)
            t_ok, rela = t[ok], rela[ok]
            k = max(1, min(window, len(rela) // 5))
            # Trailing mean: each point averages the k iterations up to it (no edge artefacts).
            smooth = np.convolve(rela, np.ones(k) / k, mode="valid")
            (line,) = ax.plot(t_ok[k - 1 :], smooth, label=_label(run))
            ax.plot(t_ok, rela, color=line.get_color(), alpha=0.2, lw=0.8)
            stages = [r["stage"] for r in rows]
            for i in range(1, len(stages)):
                if stages[i] != stages[i - 1]:
                    ax.axvline(t[i], color=line.get_color(), ls="--", lw=1)
                    ax.text(t[i], 0.03, " stage 2", color=line.get_color(), fontsize=8)
        ax.set_xlabel(AXES[x])
        ax.set_ylabel("relative coverage (Rela) of the batch's placements")
        ax.set_ylim(0, 1)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out)


def plot_rounds(run_dirs: list[Path], out: Path) -> None:
    """Expert-iteration runs: per round, the greedy policy's Rela on the round's objects and the
    planner's Rela around it (the policy the round's planner was built around)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4), dpi=120)
    ticks: set[int] = set()
    for run in run_dirs:
        # A round's planner figures stand on its first epoch's row only.
        rows = [r for r in read_metrics(run) if not math.isnan(r.get("planner_rela", math.nan))]
        if not rows:
            raise ValueError(f"{run}: metrics.csv has no expert-iteration round (no planner_rela)")
        rounds = [int(r["round"]) for r in rows]
        ticks.update(rounds)
        (line,) = ax.plot(rounds, [r["greedy_rela"] for r in rows], "o-", label=f"{_label(run)}: policy (greedy)")
        ax.plot(
            rounds,
            [r["planner_rela"] for r in rows],
            "s--",
            color=line.get_color(),
            label=f"{_label(run)}: planner around it",
        )
    ax.set_xticks(sorted(ticks))
    ax.set_xlabel("expert-iteration round (the policy of the round before)")
    ax.set_ylabel("Rela on the round's chaos objects")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="mrchaos-plot", description=__doc__)
    ap.add_argument("runs", nargs="+", type=Path, help="run folders or metrics.csv files")
    ap.add_argument("--x", nargs="+", default=["episodes"], choices=list(AXES), help="x axes, one panel each")
    ap.add_argument("--out", type=Path, help="PNG path (default: RUN_DIR/learning_curve.png)")
    args = ap.parse_args(argv)
    first = args.runs[0]
    out = args.out or (first.parent if first.suffix == ".csv" else first) / "learning_curve.png"

    def body() -> int:
        # Supervised runs with expert-iteration rounds are plotted by round.
        if all("planner_rela" in (read_metrics(r)[:1] or [{}])[0] for r in args.runs):
            plot_rounds(args.runs, out)
        else:
            plot_runs(args.runs, out, xs=tuple(args.x))
        print(f"wrote {out}")
        return 0

    return run_command("mrchaos-plot", body, dependencies=("numpy", "matplotlib"))


if __name__ == "__main__":
    sys.exit(main())
