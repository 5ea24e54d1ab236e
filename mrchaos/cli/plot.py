"""``mrchaos-plot RUN_DIR [RUN_DIR ...] [--out PNG]``: learning curves like the paper's Fig. 4b."""

from __future__ import annotations

import argparse
import csv
import sys
from pathlib import Path

from mrchaos.cli.guard import run_command


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
        ep, rela = ep[ok], rela[ok]
        k = max(1, min(window, len(rela) // 5))
        # Trailing mean: each point averages the k iterations up to it (no edge artefacts).
        smooth = np.convolve(rela, np.ones(k) / k, mode="valid")
        line, = ax.plot(ep[k - 1 :], smooth, label=Path(run).name)
        ax.plot(ep, rela, color=line.get_color(), alpha=0.2, lw=0.8)
        stages = [r["stage"] for r in rows]
        eps_all = [r["episodes"] for r in rows]
        for i in range(1, len(stages)):
            if stages[i] != stages[i - 1]:
                ax.axvline(eps_all[i], color=line.get_color(), ls="--", lw=1)
                ax.text(eps_all[i], 0.03, " stage 2", color=line.get_color(), fontsize=8)
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

    def body() -> int:
        plot_runs(args.runs, out)
        print(f"wrote {out}")
        return 0

    return run_command("mrchaos-plot", body, dependencies=("numpy", "matplotlib"))


if __name__ == "__main__":
    sys.exit(main())
