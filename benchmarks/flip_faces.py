"""How often a flip policy lays each chiral piece on the target's face.

Final and Rela barely see a wrongly faced parallelogram (most of its slot is covered either way), so
this counts the choice itself: greedy episodes on a figure set, and for every placement of a chiral
piece whether the action's face (`ActionGrid.mirrored`) matches the target's.

    python benchmarks/flip_faces.py runs/mrchaos104_mirrored.json ../shared/figures/mrchaos104.json
"""

from __future__ import annotations

import argparse

import numpy as np

from mrchaos.bench.benchmark import Bench, resolve_policy
from mrchaos.figures.formats import load_figures
from mrchaos.learn.evaluate import evaluate


def face_counts(figures: str, policy: str) -> tuple[int, int, int, int]:
    """(right on turned-over targets, turned-over placements, right on face-up targets, face-up placements)."""
    bench = Bench([load_figures(figures)], ["H-Normal", "H-Hard", "H-Fiendish"], 0, 0, flip=True)
    spec = resolve_policy(policy)
    env = bench.make_env(spec)
    actor = bench.actor(spec, env)
    chiral = env.piece_set.chiral
    nw = env.batch_size[0]
    placed: dict[tuple[int, int], np.ndarray] = {}

    def on_step(start: int, t: int, nxt) -> None:
        placed[(start, t)] = nxt["info", "piece"][:, 0].numpy().copy()

    counts = np.zeros(4, dtype=int)
    for groups in bench.targets.values():
        for _, poses, mirrored, _ in groups:
            placed.clear()
            res = evaluate(env, poses, actor, record_steps=True, on_step=on_step, mirrored=mirrored)
            for s in res.steps:
                ep = s["episode"]
                piece = placed[(ep[0] // nw * nw, s["t"])][: len(ep)]
                sel = (piece >= 0) & chiral[np.maximum(piece, 0)]
                want = mirrored[ep[sel], piece[sel]]
                got = env.grid.mirrored(s["action"][sel])
                counts += [(got & want).sum(), want.sum(), (~got & ~want).sum(), (~want).sum()]
    env.close()
    return tuple(int(c) for c in counts)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("figures", nargs="+", help="figure sets (mirror one with tools/mirror_figures.py)")
    ap.add_argument("--policy", default="mrchaos-flip")
    args = ap.parse_args()
    for path in args.figures:
        over, n_over, up, n_up = face_counts(path, args.policy)
        print(
            f"{path}: {args.policy} turns a chiral piece over for {over} of {n_over} turned-over targets "
            f"and keeps it face up for {up} of {n_up} face-up targets"
        )


if __name__ == "__main__":
    main()
