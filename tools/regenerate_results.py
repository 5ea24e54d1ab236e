"""Re-run every benchmark behind a published result table and rewrite its files.

Each table the documentation shows lives in ``docs/results/<name>/``: ``results.json`` and
``results.md`` as ``mrchaos-bench`` wrote them, and ``command.txt``, the exact commands (any figure
set the bench needs made, then the bench). The pages include ``results.md`` (``pymdownx.snippets``),
so a reshipped policy updates its tables by one command:

    python tools/regenerate_results.py                 # every table
    python tools/regenerate_results.py table1 builtin  # some of them
    python tools/regenerate_results.py --list

Tables on the paper's figures need ``--figures-dir`` (default ``../shared/figures``). Figure ids of
that set are not committed: the skipped figures are kept as a count.
"""

from __future__ import annotations

import argparse
import json
import shlex
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "docs" / "results"

#: The Table I policies of the tangram, in the order the README lists them.
TANGRAM_POLICIES = [
    "mrchaos-rerank", "mrchaos-exit", "mrchaos-dense-ppo", "mrchaos-dense", "mrchaos-bc-chaos", "mrchaos",
    "mrchaos-wo-local", "mrchaos-wo-global", "bc", "mrchaos-paper", "random", "oracle",
]  # fmt: skip

#: Where the mirrored figure set is written (``tools/mirror_figures.py``): under ``runs/``, which is
#: not committed, since it is made from data that is not.
MIRRORED = "runs/results/mrchaos104_mirrored.json"

#: Every published table: its name and the ``mrchaos-bench`` arguments that make it.
#: ``{figures}`` stands for ``--figures-dir``; ``{mirrored}`` for the paper's figures reflected in x,
#: which the script makes first (the command is recorded beside the bench's).
TABLES: dict[str, list[str]] = {
    # README and docs/benchmark.md: Table I on the paper's 104 figures and 200 Random objects.
    "table1": ["--families", "all", "--figures", "{figures}/mrchaos104.json"]
    + [a for p in TANGRAM_POLICIES for a in ("--policy", p)],
    # docs/getting-started.md: the main job, on the built-in library (no external data).
    "builtin": ["--families", "all", "--policy", "mrchaos-dense-ppo", "--policy", "mrchaos", "--policy", "oracle"],
    # docs/training.md: the windowed mode, off for the policies shipped with it and on for two shipped without.
    "window1": ["--families", "all", "--figures", "{figures}/mrchaos104.json", "--mode-window", "1",
                "--policy", "mrchaos-dense-ppo", "--policy", "mrchaos-dense"],
    "window3": ["--families", "all", "--figures", "{figures}/mrchaos104.json", "--mode-window", "3",
                "--policy", "mrchaos-bc-chaos", "--policy", "mrchaos"],
    # docs/training.md: the lookahead planner around the shipped policies (not the paper's protocol).
    "lookahead3": ["--families", "all", "--figures", "{figures}/mrchaos104.json", "--lookahead", "3"]
    + [a for p in ("mrchaos-rerank", "mrchaos-exit", "mrchaos-dense-ppo", "mrchaos-dense", "mrchaos-bc-chaos",
                   "mrchaos") for a in ("--policy", p)],
    # docs/benchmark.md: the other tasks, their authored goals and 200 chaos objects.
    # The baselines on the shipped cutlery policy's refined grid (its action space).
    "cutlery": ["--task", "cutlery", "--policy", "mrchaos-cutlery", "--policy", "oracle", "--policy", "random",
                "--grid", "fine_xy=3", "--grid", "fine_theta=3"],
    "soda": ["--task", "soda", "--policy", "mrchaos-soda", "--policy", "oracle", "--policy", "random"],
    # docs/robot-and-flip.md: the shipped mrchaos placed by teleport and by the simulated UR5e.
    "placement_teleport": ["--families", "all", "--placement", "teleport", "--policy", "mrchaos"],
    "placement_robot": ["--families", "all", "--placement", "robot", "--policy", "mrchaos"],
    # docs/robot-and-flip.md: the flip policy beside one that cannot flip, on the figures as
    # published and reflected in x (every one of them then needs the parallelogram turned over).
    "flip": ["--families", "all", "--figures", "{figures}/mrchaos104.json", "--policy", "mrchaos-flip",
             "--policy", "mrchaos"],
    "flip_mirrored": ["--families", "all", "--figures", "{mirrored}", "--flip", "--policy", "mrchaos-flip",
                      "--policy", "mrchaos"],
    # docs/free-order.md: the free-order policy beside its fixed-order twin (the same recipe and
    # data) and two set's-order policies (mrchaos-dense-ppo of about its minutes), placed by
    # teleport and by the simulated UR5e (collisions and stacking).
    "free": ["--families", "all", "--figures", "{figures}/mrchaos104.json", "--policy", "mrchaos-free",
             "--policy", "mrchaos-fixed-twin", "--policy", "mrchaos-dense", "--policy", "mrchaos-dense-ppo"],
    "free_robot": ["--families", "all", "--figures", "{figures}/mrchaos104.json", "--placement", "robot",
                   "--policy", "mrchaos-free", "--policy", "mrchaos-fixed-twin"],
    # README Table I's first row and docs/free-order.md: the generalist (free order, the flip, the
    # re-ranker) alone, as the main job benches it, on the figures as published, reflected in x, and
    # placed by the simulated UR5e. Apart from table1: its implied flip would change the oracle's row.
    "generalist": ["--families", "all", "--figures", "{figures}/mrchaos104.json", "--policy", "mrchaos-generalist"],
    "generalist_mirrored": ["--families", "all", "--figures", "{mirrored}", "--flip", "--policy", "mrchaos-generalist"],
    "generalist_robot": ["--families", "all", "--figures", "{figures}/mrchaos104.json", "--placement", "robot",
                         "--policy", "mrchaos-generalist"],
}  # fmt: skip


def commands(name: str, figures_dir: str) -> list[list[str]]:
    """The command lines of table ``name``: any figure set it needs made, then its bench."""
    args = TABLES[name]
    made = []
    if "{mirrored}" in args:
        made.append(["python", "tools/mirror_figures.py", f"{figures_dir}/mrchaos104.json", MIRRORED])
    bench = ["mrchaos-bench", *(a.replace("{figures}", figures_dir).replace("{mirrored}", MIRRORED) for a in args)]
    return [*made, bench]


def _scrub(out: Path) -> None:
    """Keep the skipped figures as a count: their ids name figures of a data set not committed here."""
    data = json.loads((out / "results.json").read_text())
    data["skipped"] = len(data.get("skipped") or [])
    data.pop("sources", None)
    (out / "results.json").write_text(json.dumps(data, indent=1) + "\n")
    # The pages include the file under their own heading: no title, no figure ids.
    md = [ln for ln in (out / "results.md").read_text().splitlines() if not ln.startswith(("- ", "# "))]
    (out / "results.md").write_text("\n".join(md).rstrip("\n") + "\n")


def regenerate(name: str, figures_dir: str) -> None:
    """Run table ``name``'s commands and write its files into ``docs/results/<name>/``."""
    *made, bench = commands(name, figures_dir)
    for cmd in made:
        (ROOT / MIRRORED).parent.mkdir(parents=True, exist_ok=True)
        subprocess.run([sys.executable, *cmd[1:]] if cmd[0] == "python" else cmd, check=True, cwd=ROOT)
    with tempfile.TemporaryDirectory() as tmp:
        subprocess.run([*bench, "--out", tmp], check=True, cwd=ROOT)
        out = RESULTS / name
        out.mkdir(parents=True, exist_ok=True)
        for f in ("results.json", "results.md"):
            (out / f).write_bytes((Path(tmp) / f).read_bytes())
    _scrub(out)
    (out / "command.txt").write_text("".join(shlex.join(c) + "\n" for c in (*made, bench)))
    print(f"wrote {out}")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("tables", nargs="*", help=f"tables to regenerate (default: all of {', '.join(TABLES)})")
    ap.add_argument("--figures-dir", default="../shared/figures", help="where the paper's figure files lie")
    ap.add_argument("--list", action="store_true", help="print each table's command and stop")
    args = ap.parse_args()
    unknown = [t for t in args.tables if t not in TABLES]
    if unknown:
        print(f"regenerate_results: unknown table(s) {unknown}; tables: {', '.join(TABLES)}", file=sys.stderr)
        return 2
    for name in args.tables or list(TABLES):
        if args.list:
            print(f"{name}: " + " && ".join(shlex.join(c) for c in commands(name, args.figures_dir)))
        else:
            regenerate(name, args.figures_dir)
    return 0


if __name__ == "__main__":
    sys.exit(main())
