"""How often a flip policy lays each chiral piece on the target's face, and whether the face can be read.

Final and Rela barely see a wrongly faced parallelogram (most of its slot is covered either way), so
this counts the choice itself: greedy episodes on a figure set, and for every placement of a chiral
piece whether the face it went down on (the step's `info.mirrored`) matches the target's.

    python benchmarks/flip_faces.py runs/mrchaos104_mirrored.json ../shared/figures/mrchaos104.json

It also says whether the silhouette shows the face at all:

- the share of each chiral piece's outline that lies on the silhouette's outline (a piece inside a
  crowd shows none of its shape);
- whether the slots still empty when the chiral piece is placed (it and every later piece, in the
  set's order) can also be tiled exactly with it turned over: there the silhouette does not decide
  the face and any reader is right on about half of the targets;
- with ``--exact-before``, the policy's choice when every earlier piece was placed by the grid
  oracle (its own mistakes taken out of the chiral piece's surroundings).
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence

import numpy as np
from shapely import affinity
from shapely.geometry import Polygon
from shapely.ops import unary_union

from mrchaos.bench.benchmark import Bench, resolve_policy
from mrchaos.env.oracle import oracle_actions
from mrchaos.figures.figure import Figure, FigureSet
from mrchaos.figures.formats import load_figures
from mrchaos.learn.evaluate import evaluate
from mrchaos.learn.planner import Lookahead

#: Seams between touching pieces of a drawn figure are closed by this much (m), slivers of a
#: remainder thinner than twice ``_SLIVER`` are dropped, and a piece may stick out of the region
#: by ``_OUTSIDE`` of its area: drawn figures are exact to about a tenth of a millimetre.
_SEAM, _SLIVER, _OUTSIDE = 2e-4, 3e-4, 0.01


def face_choices(
    figures: FigureSet | None,
    policy: str,
    chaos: int = 0,
    seed: int = 7,
    lookahead: int = 1,
    exact_before: bool = False,
) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """Every placement of a chiral piece: (wanted turned over, chose turned over, target id), on a
    figure set, or (``figures`` None) on ``chaos`` chaos objects of ``seed`` whose chiral pieces lie
    turned over half the time, as a flip policy's training objects do (for choosing settings). With
    ``lookahead`` > 1 the policy plays inside the bench's test-time planner; with ``exact_before``
    the grid oracle places every piece before the first chiral one."""
    if figures is None:
        bench = Bench(None, ["Random"], chaos, seed, flip=True, random_mirror=0.5, lookahead=lookahead)
    else:
        families = ["H-Normal", "H-Hard", "H-Fiendish"]
        bench = Bench([figures], families, 0, 0, flip=True, lookahead=lookahead)
    spec = resolve_policy(policy)
    env = bench.make_env(spec)
    actor = bench.actor(spec, env)
    if exact_before and env.free_order:
        raise SystemExit(f"flip_faces: --exact-before needs a policy in the set's order; {policy} chooses its pieces")
    chiral = env.piece_set.chiral
    first_chiral = int(np.flatnonzero(chiral)[0]) if exact_before else 0
    nw = env.batch_size[0]
    placed: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]] = {}

    def on_step(start: int, t: int, nxt) -> None:
        placed[(start, t)] = (nxt["info", "piece"][:, 0].numpy().copy(), nxt["info", "mirrored"][:, 0].numpy().copy())

    want_all, got_all, ids_all = [], [], []
    for groups in bench.targets.values():
        for _, poses, mirrored, ids in groups:
            placed.clear()
            act = actor.actor(env, poses, mirrored) if isinstance(actor, Lookahead) else actor
            if first_chiral:
                act = _oracle_first(act, first_chiral, len(env.piece_set))
            res = evaluate(env, poses, act, record_steps=True, on_step=on_step, mirrored=mirrored)
            assert res.steps is not None  # record_steps
            for s in res.steps:
                ep = s["episode"]
                piece, turned = (v[: len(ep)] for v in placed[(ep[0] // nw * nw, s["t"])])
                sel = (piece >= 0) & chiral[np.maximum(piece, 0)]
                want_all.append(mirrored[ep[sel], piece[sel]])
                got_all.append(turned[sel])
                ids_all += [ids[e] for e in ep[sel]]
    env.close()
    return np.concatenate(want_all), np.concatenate(got_all), ids_all


def _oracle_first(actor, steps: int, pieces: int):
    """``actor`` with the grid oracle's action on each episode's first ``steps`` steps (an actor is
    called once per step of every batch of episodes, ``pieces`` steps each)."""
    calls = [0]

    def act(env, td):
        t = calls[0] % pieces
        calls[0] += 1
        return oracle_actions(env) if t < steps else actor(env, td)

    return act


def outline_exposure(figures: FigureSet) -> np.ndarray:
    """For every chiral piece of every figure: the share of its outline on the silhouette's outline."""
    out = []
    for f in figures.figures:
        polys = [Polygon(f.piece_polygon(i)) for i in range(len(f.poses))]
        # Close the seams between touching pieces (0.2 mm), then measure within 0.5 mm of the outline.
        sil = _union(polys)
        near = sil.boundary.buffer(5e-4)
        out += [
            polys[i].exterior.intersection(near).length / polys[i].exterior.length
            for i in np.flatnonzero(f.piece_set.chiral)
        ]
    return np.array(out)


def _union(polys: Sequence[Polygon]):
    return unary_union([q.buffer(_SEAM, join_style="mitre") for q in polys]).buffer(-_SEAM, join_style="mitre")


def _orientations(shape: Polygon) -> list[Polygon]:
    """The shape turned by every multiple of 45 degrees, repeats (symmetries) left out."""
    out: list[Polygon] = []
    for k in range(8):
        s = affinity.rotate(shape, 45 * k, origin=shape.centroid)
        if not any(s.symmetric_difference(o).area < 1e-7 for o in out):
            out.append(s)
    return out


def _tiles(region, shapes: list[list[Polygon]], budget: list[int]) -> bool:
    """Whether ``region`` is tiled exactly by one of each of ``shapes`` (each given in its
    orientations). Some piece must have a vertex on the region's lowest corner, so only those
    placements are tried, each turned in 45-degree steps from its slot (complete where, as in the
    tangram's figures, the pieces lie at 45-degree steps to one another); ``budget`` caps the search."""
    parts = [g for g in getattr(region, "geoms", [region]) if g.geom_type == "Polygon" and g.area > 2e-6]
    if not shapes or not parts:
        return not shapes and not parts
    budget[0] -= 1
    if budget[0] < 0:
        raise RuntimeError("tiling search over budget")
    corners = np.asarray(min(parts, key=lambda p: p.bounds[1]).simplify(5e-4).exterior.coords)[:-1]
    v = corners[np.lexsort((corners[:, 0], corners[:, 1]))[0]]
    tried: set[tuple[float, int]] = set()
    for i, options in enumerate(shapes):
        kind = (round(options[0].area, 7), len(options[0].exterior.coords))
        if kind in tried:  # twins and equal pieces: one choice
            continue
        tried.add(kind)
        for s in options:
            for a in np.asarray(s.exterior.coords)[:-1]:
                t = affinity.translate(s, v[0] - a[0], v[1] - a[1])
                if t.difference(region).area < _OUTSIDE * t.area:
                    rest = region.difference(t).buffer(-_SLIVER, join_style="mitre").buffer(_SLIVER, join_style="mitre")
                    if _tiles(rest, shapes[:i] + shapes[i + 1 :], budget):
                        return True
    return False


def face_open(figure: Figure, budget: int = 20000) -> dict[int, bool | None]:
    """For each chiral piece of ``figure``: whether the slots still empty when it is placed (its own
    and every later piece's, in the set's order) also tile exactly with it turned over, so that the
    silhouette does not decide its face. None where the figure's own face does not tile them either
    (the drawing's seams are wider than the tolerances) or the search ran over ``budget``."""
    polys = [Polygon(figure.piece_polygon(i)) for i in range(len(figure.poses))]
    out: dict[int, bool | None] = {}
    for i in np.flatnonzero(figure.piece_set.chiral):
        later = [_orientations(polys[j]) for j in range(i + 1, len(polys))]
        region = _union(polys[i:])
        turned = affinity.scale(polys[i], xfact=-1, origin=polys[i].centroid)
        try:
            own = _tiles(region, [_orientations(polys[i])] + later, [budget])
            out[int(i)] = _tiles(region, [_orientations(turned)] + later, [budget]) if own else None
        except RuntimeError:
            out[int(i)] = None
    return out


def _report(label: str, want: np.ndarray, got: np.ndarray) -> str:
    return (
        f"{label} turns a chiral piece over for {(got & want).sum()} of {want.sum()} turned-over targets "
        f"and keeps it face up for {(~got & ~want).sum()} of {(~want).sum()} face-up targets"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("figures", nargs="*", help="figure sets (mirror one with tools/mirror_figures.py)")
    ap.add_argument("--policy", default="mrchaos-flip")
    ap.add_argument("--chaos", type=int, default=0, help="also N held-out chaos objects, half their chiral pieces over")
    ap.add_argument("--seed", type=int, default=7, help="seed of the --chaos objects")
    ap.add_argument("--lookahead", type=int, default=1, help="candidates per step of the test-time planner (1: none)")
    ap.add_argument("--exact-before", action="store_true", help="the grid oracle places the earlier pieces")
    args = ap.parse_args()
    label = args.policy + (f" + lookahead {args.lookahead}" if args.lookahead > 1 else "")
    label += " (pieces before it exact)" if args.exact_before else ""
    if args.chaos:
        want, got, _ = face_choices(None, args.policy, args.chaos, args.seed, args.lookahead, args.exact_before)
        print(f"{args.chaos} chaos objects (seed {args.seed}): {_report(label, want, got)}")
    for path in args.figures:
        figures = load_figures(path)
        e = outline_exposure(figures)
        print(
            f"{path}: the silhouette's outline holds {np.median(e):.0%} of a chiral piece's outline (median; "
            f"10 % of pieces show {np.quantile(e, 0.1):.0%} or less, {np.mean(e < 0.25):.0%} show under a quarter)"
        )
        opened = {f.id: face_open(f) for f in figures.figures}
        open_ids = {fid for fid, d in opened.items() if any(d.values())}
        unknown = sum(any(v is None for v in d.values()) for d in opened.values())
        print(
            f"{path}: in {len(open_ids)} of {len(opened)} figures the slots left when the chiral piece is placed "
            f"also tile with it turned over ({unknown} not decided: seams too wide or search too long)"
        )
        want, got, ids = face_choices(figures, args.policy, lookahead=args.lookahead, exact_before=args.exact_before)
        print(f"{path}: {_report(label, want, got)}")
        amb = np.array([i in open_ids for i in ids], dtype=bool)
        right = got == want
        print(
            f"{path}: right on {right[~amb].sum()} of {(~amb).sum()} targets the silhouette decides, "
            f"{right[amb].sum()} of {amb.sum()} it leaves open"
        )


if __name__ == "__main__":
    main()
