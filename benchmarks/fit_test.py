"""The fit test: can a network learn a set of objects at all? Minutes, before any long run.

Labels a few thousand states of one chaos mode (dense counterfactual targets, as
``conf/dense.yaml``), trains each candidate (a network, or an observation encoding) on exactly
those states with the dense recipe's supervised loop (no DAgger), and benches it greedily, the
policy alone, on the tangram's:

* ``own``: objects it was trained on (does it fit what it was shown? the oracle is the ceiling);
* ``tile``: held-out edge-joined objects (seed 7);
* ``chaos``: held-out objects of today's chaos mix (scatter and attract, seed 7);
* ``library``: the built-in human figures (those that need no flip);

and on another task's (``--config conf/cutlery_dense.yaml``): ``own``, ``chaos`` (held-out objects
drawn as the training objects are, seed 7) and ``random`` (the bench's Random objects, seed 7).

It prints one row per candidate: Rela / IoU on each set, the last epoch's loss, parameters and
minutes per epoch on this machine; the oracle's row is the ceiling. Runs go to ``--out``
(one folder per candidate; the labelled states are shared by candidates that observe alike,
labelled once)::

    python benchmarks/fit_test.py --objects 430 --epochs 20 --nets today,attention,unet
    python benchmarks/fit_test.py --config conf/cutlery_dense.yaml --mode mix --nets today,grey4

Choose networks here, on held-out chaos and the library, never on mrchaos104.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import json
import logging
import shutil
import time
from pathlib import Path

import numpy as np
import torch

from mrchaos.bench.benchmark import Bench, resolve_policy
from mrchaos.core.atomic import write_atomic
from mrchaos.env.oracle import oracle_actions
from mrchaos.env.tangram import TangramEnv
from mrchaos.figures.library import builtin_figures
from mrchaos.figures.pieces import get_piece_set
from mrchaos.learn.bc import SupervisedRun, dense_target_logits
from mrchaos.learn.config import TrainConfig, load_config
from mrchaos.learn.evaluate import evaluate, policy_actor
from mrchaos.learn.policy import count_parameters
from mrchaos.tasks.chaos import generate

#: Candidates: overrides on top of the recipe's (conf/dense.yaml: the spatial net with its
#: 32-channel context path). "today" is the shipped policies' network; "grey<k>" today's network
#: on the grey-level observation drawn k times finer (env.observation.supersample).
NETS: dict[str, list[str]] = {
    "today": [],
    "coords": ["policy.coords=true"],
    "wide": ["policy.channels=[32,64,64]", "policy.context=64"],
    "attention": ["policy.global_view=attention"],
    "unet": ["policy.global_view=unet"],
    "unet32": ["policy.global_view=unet", "policy.global_width=32"],
    "attention4": ["policy.global_view=attention", "policy.global_layers=4"],
    "grey2": ["env.observation.supersample=2"],
    "grey4": ["env.observation.supersample=4"],
}

#: The bench sets of the tangram and of any other task.
SETS = ("own", "tile", "chaos", "library")
TASK_SETS = ("own", "chaos", "random")


def _eval_sets(cfg: TrainConfig, n: int) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """The bench's target sets: (poses, mirrored) of each. ``own`` is the first ``n`` training
    objects (the same draw as the run's demonstrations)."""
    piece_set = get_piece_set(cfg.env.piece_set)
    view = cfg.env.view
    own, _, own_m = generate(piece_set, cfg.bc.objects, np.random.default_rng(cfg.bc.seed), cfg.task.chaos, view)
    if cfg.task.preset != "tangram":
        held, _, held_m = generate(piece_set, n, np.random.default_rng(7), cfg.task.chaos, view)
        bench = Bench(None, ["Random"], random_objects=n, seed=7, task=cfg.task.preset)
        [(_, rand, rand_m, _)] = bench.targets["Random"]  # one piece set: the training's
        return {"own": (own[:n], own_m[:n]), "chaos": (held, held_m), "random": (rand, rand_m)}
    tile, _, tile_m = generate(
        piece_set, n, np.random.default_rng(7), dataclasses.replace(cfg.task.chaos, mode="tile"), view
    )
    mix = dataclasses.replace(cfg.task.chaos, mode="mix", attract_fraction=0.5, tile_fraction=0.0)
    chaos, _, chaos_m = generate(piece_set, n, np.random.default_rng(7), mix, view)
    lib = [f for f in builtin_figures() if not f.has_mirrored]
    return {
        "own": (own[:n], own_m[:n]),
        "tile": (tile, tile_m),
        "chaos": (chaos, chaos_m),
        "library": (np.stack([f.poses for f in lib]), np.stack([f.mirrored for f in lib])),
    }


def _bench(cfg: TrainConfig, actor, sets: dict) -> dict[str, dict[str, float]]:
    noise = dataclasses.replace(cfg.env.noise, action_xy=0.0, action_theta=0.0, camera_jitter=0.0)
    worlds = min(100, max(len(poses) for poses, _ in sets.values()))
    env_cfg = dataclasses.replace(cfg.env_config(), num_worlds=worlds, noise=noise, task=cfg.task.given_targets())
    return _score(TangramEnv(env_cfg, seed=2024), actor, sets)


def _score(env: TangramEnv, actor, sets: dict) -> dict[str, dict[str, float]]:
    """Rela and IoU (%) of ``actor`` on every set, greedy; closes ``env``."""
    out = {}
    for name, (poses, mirrored) in sets.items():
        res = evaluate(env, poses, actor, mirrored=mirrored)
        out[name] = {"rela": 100 * float(res.rela.mean()), "iou": 100 * float(res.iou.mean()), "n": len(poses)}
    env.close()
    return out


def _bench_policy(spec: str, sets: dict, task: str) -> dict[str, dict[str, float]]:
    """A trained policy (shipped or a run, re-ranked ones played as the bench plays them) on the
    same sets, greedy, with the bench's env for it."""
    bench = Bench(None, ["Random"], random_objects=1, seed=2024, num_worlds=100, task=task)
    policy = resolve_policy(spec)
    env = bench.make_env(policy)
    return _score(env, bench.actor(policy, env), sets)


def _target_entropy(shard: Path, temperature: float) -> float:
    """Mean entropy (nats) of the dense targets softmax(coverage / T) of a shard's states: the
    cross-entropy loss cannot go below it, so loss minus it is how far a network is from fitting."""
    lp = torch.log_softmax(dense_target_logits(torch.load(shard, weights_only=True)["label"], temperature), -1)
    return float(-(torch.where(lp > -torch.inf, lp.exp() * lp, 0.0)).sum(-1).mean())


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--config", default="conf/dense.yaml", help="the recipe the candidates share")
    ap.add_argument("--mode", default="tile", help="chaos mode of the training objects (tile, attract, mix, ...)")
    ap.add_argument("--objects", type=int, default=430, help="training objects (7 labelled states each)")
    ap.add_argument("--epochs", type=int, default=20)
    ap.add_argument("--eval", type=int, default=100, help="objects per bench set")
    ap.add_argument("--nets", default="today,attention,unet", help=f"comma-separated, of {sorted(NETS)}")
    ap.add_argument(
        "--policy",
        action="append",
        default=[],
        help="also bench a trained policy on the same sets (a shipped name or a run; repeatable)",
    )
    ap.add_argument("--out", default="runs/fit")
    ap.add_argument("overrides", nargs="*", help="key=value settings for every candidate")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    names = [n for n in args.nets.split(",") if n]  # none: only --policy rows
    unknown = [n for n in names if n not in NETS]
    if unknown:
        ap.error(f"unknown networks {unknown}; known: {sorted(NETS)}")
    out = Path(args.out)
    shared = [
        f"task.chaos.mode={args.mode}",
        f"bc.objects={args.objects}",
        f"bc.epochs={args.epochs}",
        "bc.dagger_rounds=0",
        *args.overrides,
    ]
    base = load_config(args.config, shared)
    sets = _eval_sets(base, args.eval)
    results: dict[str, dict] = {}
    summary = out / "results.json"
    if summary.exists():
        results = json.loads(summary.read_text())
    if "oracle" not in results:
        results["oracle"] = {"sets": _bench(base, lambda env, td: oracle_actions(env), sets)}
    for spec in args.policy:
        results[spec] = {"sets": _bench_policy(spec, sets, base.task.preset)}
        write_atomic(summary, json.dumps(results, indent=1) + "\n")
    for name in names:
        cfg = load_config(args.config, shared + NETS[name] + [f"name=fit_{name}"])
        # The states hold the observation: candidates that observe differently label their own.
        k = cfg.env.observation.supersample
        data = out / "data" / ("round_0.pt" if k == 1 else f"round_0_supersample{k}.pt")
        run_dir = out / name
        if data.exists() and not (run_dir / "data" / "round_0.pt").exists():
            (run_dir / "data").mkdir(parents=True, exist_ok=True)
            shutil.copy(data, run_dir / "data" / "round_0.pt")  # the same states for every network
        t0 = time.perf_counter()
        run = SupervisedRun(cfg, run_dir, resume=(run_dir / "checkpoints" / "last.pt").exists())
        run.run()
        if not data.exists():
            data.parent.mkdir(parents=True, exist_ok=True)
            shutil.copy(run_dir / "data" / "round_0.pt", data)
        with open(run_dir / "metrics.csv", newline="") as f:
            rows = list(csv.DictReader(f))
        # The first epoch's minutes include the labelling: time epochs from the first one's end.
        ticks = [float(r["minutes"]) for r in rows]
        per_epoch = (ticks[-1] - ticks[0]) / (len(ticks) - 1) if len(ticks) > 1 else ticks[0]
        results[name] = {
            "overrides": NETS[name],
            "parameters": count_parameters(run.ac),
            "loss": float(rows[-1]["sup"]),
            "first_loss": float(rows[0]["sup"]),
            "minutes_per_epoch": per_epoch,
            "wall_minutes": (time.perf_counter() - t0) / 60,
            "sets": _bench(cfg, policy_actor(run.policy), sets),
        }
        write_atomic(summary, json.dumps(results, indent=1) + "\n")
    data = out / "data" / "round_0.pt"
    if "target_entropy" not in results and data.exists():
        results["target_entropy"] = _target_entropy(data, base.bc.temperature)
        write_atomic(summary, json.dumps(results, indent=1) + "\n")
    if "target_entropy" in results:
        print(f"the labels' own entropy, the floor of the loss: {results['target_entropy']:.2f}")
    if names:
        print(
            f"fit test: {args.objects} {args.mode} objects ({len(get_piece_set(base.env.piece_set)) * args.objects} "
            f"states), {args.epochs} epochs; "
            f"Rela / IoU, greedy, the policy alone; {torch.get_num_threads()} threads"
        )
    else:
        print(f"trained policies on the fit test's sets ({args.mode} objects for 'own'); Rela / IoU, greedy, alone")
    names_of_sets = list(sets)
    print("| candidate | params | loss (first → last) | min/epoch | " + " | ".join(names_of_sets) + " |")
    print("|---|---|---|---|" + "---|" * len(names_of_sets))
    for name, r in results.items():
        if name == "target_entropy":
            continue
        cells = " | ".join(f"{r['sets'][s]['rela']:.1f} / {r['sets'][s]['iou']:.1f}" for s in names_of_sets)
        if "loss" not in r:  # the oracle, or a trained policy
            print(f"| {name} | | | | {cells} |")
        else:
            print(
                f"| {name} | {r['parameters']:,} | {r['first_loss']:.2f} → {r['loss']:.2f} | "
                f"{r['minutes_per_epoch']:.2f} | {cells} |"
            )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
