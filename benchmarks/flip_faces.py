"""How often a flip policy lays each chiral piece on the target's face.

Final and Rela barely see a wrongly faced parallelogram (most of its slot is covered either way), so
this counts the choice itself: greedy episodes on a figure set, and for every placement of a chiral
piece whether the action's face (`ActionGrid.mirrored`) matches the target's.

    python benchmarks/flip_faces.py runs/mrchaos104_mirrored.json ../shared/figures/mrchaos104.json

It also says whether the silhouette shows the face at all: the share of each chiral piece's outline
that lies on the silhouette's outline (a piece inside a crowd shows none of its shape).
"""

from __future__ import annotations

import argparse

import numpy as np

from mrchaos.bench.benchmark import Bench, resolve_policy
from mrchaos.figures.formats import load_figures
from mrchaos.learn.evaluate import evaluate


def face_counts(figures: str | None, policy: str, chaos: int = 0, seed: int = 7) -> tuple[int, int, int, int]:
    """(right on turned-over targets, turned-over placements, right on face-up targets, face-up placements),
    on a figure set, or (``figures`` None) on ``chaos`` chaos objects of ``seed`` whose chiral pieces lie
    turned over half the time, as a flip policy's training objects do (for choosing settings)."""
    if figures is None:
        bench = Bench(None, ["Random"], chaos, seed, flip=True, random_mirror=0.5)
    else:
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


def outline_exposure(figures: str) -> np.ndarray:
    """For every chiral piece of every figure: the share of its outline on the silhouette's outline."""
    from shapely.geometry import Polygon
    from shapely.ops import unary_union

    out = []
    for f in load_figures(figures).figures:
        polys = [Polygon(f.piece_polygon(i)) for i in range(len(f.poses))]
        # Close the seams between touching pieces (0.2 mm), then measure within 0.5 mm of the outline.
        sil = unary_union([q.buffer(2e-4, join_style="mitre") for q in polys]).buffer(-2e-4, join_style="mitre")
        near = sil.boundary.buffer(5e-4)
        out += [
            polys[i].exterior.intersection(near).length / polys[i].exterior.length
            for i in np.flatnonzero(f.piece_set.chiral)
        ]
    return np.array(out)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("figures", nargs="*", help="figure sets (mirror one with tools/mirror_figures.py)")
    ap.add_argument("--policy", default="mrchaos-flip")
    ap.add_argument("--chaos", type=int, default=0, help="also N held-out chaos objects, half their chiral pieces over")
    ap.add_argument("--seed", type=int, default=7, help="seed of the --chaos objects")
    args = ap.parse_args()
    if args.chaos:
        over, n_over, up, n_up = face_counts(None, args.policy, args.chaos, args.seed)
        print(
            f"{args.chaos} chaos objects (seed {args.seed}): {args.policy} turns a chiral piece over for {over} of "
            f"{n_over} turned-over targets and keeps it face up for {up} of {n_up} face-up targets"
        )
    for path in args.figures:
        e = outline_exposure(path)
        print(
            f"{path}: the silhouette's outline holds {np.median(e):.0%} of a chiral piece's outline (median; "
            f"10 % of pieces show {np.quantile(e, 0.1):.0%} or less, {np.mean(e < 0.25):.0%} show under a quarter)"
        )
        over, n_over, up, n_up = face_counts(path, args.policy)
        print(
            f"{path}: {args.policy} turns a chiral piece over for {over} of {n_over} turned-over targets "
            f"and keeps it face up for {up} of {n_up} face-up targets"
        )


if __name__ == "__main__":
    main()
