"""How much Rela lies within a policy's top-k actions: a diagnostic that reads the solution.

At every step an oracle picks, among the policy's k highest-scoring grid actions, the one whose
counterfactual coverage (``TangramEnv.counterfactual``) is highest among footprints that lie at
most 2 % on placed pieces; k = 1 is the greedy policy the bench measures. A high top-k figure says
the right placement is among the policy's few best guesses, so a re-ranker that does not read the
solution (lookahead, a value of the after-state) could recover it. Not a competitor's number.

    python tools/topk_ceiling.py mrchaos-dense-ppo [--figures ../shared/figures/mrchaos104.json] [--k 1 2 3 5 10]
"""

from __future__ import annotations

import argparse

import torch

from mrchaos.bench.benchmark import Bench, resolve_policy
from mrchaos.env.tangram import TangramEnv
from mrchaos.figures.formats import load_figures
from mrchaos.learn.evaluate import evaluate
from mrchaos.learn.policy import unravel_actions

# The overlap above which physics, not the counterfactual raster, decides a placement (as bc.overlap_limit).
OVERLAP_LIMIT = 0.02


def topk_oracle(policy, k: int):
    """An actor that lets the solution choose among the policy's top ``k`` actions."""

    def act(env: TangramEnv, td) -> torch.Tensor:
        with torch.no_grad():
            top = policy.get_dist(td.select("observation").clone()).top_modes(k)
        cov, overlap = env.counterfactual()
        worth = torch.where(overlap.flatten(1) <= OVERLAP_LIMIT, cov.flatten(1), -1.0)
        best = top.gather(1, worth.gather(1, top).argmax(1, keepdim=True)).squeeze(1)
        _, ny, nx = cov.shape[1:]
        return unravel_actions(best, nx, ny)

    return act


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("policy", help="a shipped name, a run folder or a checkpoint of the spatial policy")
    ap.add_argument("--figures", help="a figure file for the human families (default: Random only)")
    ap.add_argument("--k", type=int, nargs="+", default=[1, 2, 3, 5, 10])
    ap.add_argument("--random-objects", type=int, default=200)
    args = ap.parse_args()
    families = ["Random", "H-Normal", "H-Hard", "H-Fiendish"] if args.figures else ["Random"]
    bench = Bench([load_figures(args.figures)] if args.figures else None, families, args.random_objects, seed=0)
    spec = resolve_policy(args.policy)
    if spec.state is None or spec.state["policy"].get("name") != "spatial":
        raise SystemExit(f"{args.policy}: the diagnostic needs a spatial policy checkpoint")
    env = bench.make_env(spec)
    policy = bench.policy_operator(spec, env)
    print("Rela / Final, %, when the solution picks among the policy's top k actions")
    for k in args.k:
        cells = []
        for fam, groups in bench.targets.items():
            for _, poses, mirrored, _ in groups:
                res = evaluate(env, poses, topk_oracle(policy, k), mirrored=mirrored)
                cells.append(f"{fam} {100 * res.rela.mean():.1f} / {100 * res.final.mean():.1f}")
        print(f"top-{k}: " + "   ".join(cells), flush=True)
    env.close()


if __name__ == "__main__":
    main()
