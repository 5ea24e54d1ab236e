"""``mrchaos-plot RUN_DIR [RUN_DIR ...] [--out PNG]``: learning curves like the paper's Fig. 4b."""

from __future__ import annotations

import argparse
import csv
import sys
from pathlib import Path


def read_metrics(run_dir: Path) -> list[dict[str, float]]:
    path = Path(run_dir) / "metrics.csv"
    if not path.exists():
        raise FileNotFoundError(f"{run_dir}: no metrics.csv")
    with open(path) as f:
        rows = []
        for r in csv.DictReader(f):
            rows.append({k: float(v) if v not in ("", "nan") else float("nan") for k, v in r.items()})
    return rows


def plot_runs(run_dirs: list[Path], out: Path, window: int = 10) -> None:
    """Relative coverage (smoothed) against training episodes, stage switches marked."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    fig, ax = plt.subplots(figsize=(7, 4), dpi=120)
    for run in run_dirs:
        rows = read_metrics(run)
        ep = np.array([r["episodes"] for r in rows])
        rela = np.array([r["rela"] for r in rows])
        ok = ~np.isnan(rela)
        k = max(1, min(window, ok.sum() // 5 or 1))
        smooth = np.convolve(np.nan_to_num(rela), np.ones(k) / k, mode="same")
        line, = ax.plot(ep[ok], smooth[ok], label=Path(run).name)
        stages = [r["stage"] for r in rows]
        for i in range(1, len(stages)):
            if stages[i] != stages[i - 1]:
                ax.axvline(ep[i], color=line.get_color(), ls="--", lw=1)
                ax.text(ep[i], ax.get_ylim()[1] * 0.02 + 0.02, " stage 2", color=line.get_color(), fontsize=8)
    ax.set_xlabel("training episodes")
    ax.set_ylabel("relative coverage (Rela)")
    ax.set_ylim(0, 1)
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="mrchaos-plot", description=__doc__)
    ap.add_argument("runs", nargs="+", type=Path)
    ap.add_argument("--out", type=Path, help="PNG path (default: RUN_DIR/learning_curve.png)")
    args = ap.parse_args(argv)
    out = args.out or args.runs[0] / "learning_curve.png"
    try:
        plot_runs(args.runs, out)
    except (FileNotFoundError, ValueError, KeyError) as e:
        print(f"mrchaos-plot: error: {e}", file=sys.stderr)
        return 2
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
