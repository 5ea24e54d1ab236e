"""End-to-end PPO learning throughput (collection + updates) on this machine, per policy.

Runs a few iterations of ``conf/full.yaml`` (256 worlds, 4096 frames per iteration,
3 epochs of 512-sample minibatches) for each policy in a scratch run directory
and prints env-steps per second with the split between collection (env + policy
forward) and update (GAE + PPO epochs), from the run's own metrics.

Then, for the default (spatial) policy, collection alone through each collector kind:
``sync`` (one env of 256 worlds in this process, ``--threads`` threads) beside ``multisync``
(worker processes) and ``ray`` (Ray actors on a local cluster), each with ``--workers``
workers of 256 worlds on one thread. Training on the GPU: add ``device=cuda``.

    python benchmarks/train_throughput.py [key=value ...] [--iterations 4] [--threads 2] [--workers 2]
        [--variants paper paper-fullres spatial spatial-context] [--collectors sync multisync ray]

(Config overrides come first: after ``--variants`` or ``--collectors`` they would be read as names.)
"""

from __future__ import annotations

import argparse
import csv
import importlib.util
import tempfile
import time
from pathlib import Path

from mrchaos.learn.config import COLLECTOR_KINDS, load_config
from mrchaos.learn.policy import count_parameters
from mrchaos.learn.ppo import Trainer

ROOT = Path(__file__).resolve().parents[1]

VARIANTS = {
    "paper": ["policy.name=paper", "policy.pool=2", "policy.channels=[32,64,64]"],
    "paper-fullres": ["policy.name=paper", "policy.pool=1", "policy.channels=[32,64,64]"],
    "spatial": ["policy.name=spatial", "policy.pool=1", "policy.channels=[16,32,32]"],
    # The net of the shipped mrchaos-dense and mrchaos-dense-ppo (conf/dense.yaml).
    "spatial-context": ["policy.name=spatial", "policy.pool=1", "policy.channels=[16,32,32]", "policy.context=32"],
}


def _config(tmp: str, overrides: list[str]):
    return load_config(
        ROOT / "conf" / "full.yaml",
        [
            # No time budget here, so no learning-rate anneal over one (the rate does not change the speed).
            f"runs_dir={tmp}",
            "name=bench",
            "collector.max_minutes=0",
            "optim.lr_final=null",
            "logger.backends=[]",
            "logger.progress=false",
            "checkpoint.every=100000",
            "task.cache.path=null",
            "task.cache.size=1024",
            *overrides,
        ],
    )


def collection_throughput(kind: str, workers: int, threads: int, batches: int, overrides: list[str]) -> float:
    """World-steps per second of collection alone (after one warm-up batch) with one collector kind."""
    with tempfile.TemporaryDirectory() as tmp:
        extra = (
            [f"threads={threads}", f"env.physics.nthread={threads}"]
            if kind == "sync"
            else [f"collector.workers={workers}", "collector.worker_threads=1", "threads=1"]
        )
        cfg = _config(tmp, [f"collector.kind={kind}", "collector.total_frames=-1", *extra, *overrides])
        trainer = Trainer(cfg, Path(tmp) / "bench")
        try:
            it = iter(trainer.collector)
            next(it)
            t = time.perf_counter()
            frames = sum(next(it).numel() for _ in range(batches))
            return frames / (time.perf_counter() - t)
        finally:
            trainer.collector.shutdown()
            if kind == "ray":
                import ray

                ray.shutdown()


def learning_throughput(variant: str, iterations: int, overrides: list[str]) -> dict[str, float]:
    """End-to-end PPO throughput of one policy variant: world-steps per second and the mean
    collection and update seconds of a 4096-frame iteration, after one warm-up iteration."""
    with tempfile.TemporaryDirectory() as tmp:
        cfg = _config(tmp, [*VARIANTS[variant], f"collector.total_frames={4096 * (iterations + 1)}", *overrides])
        trainer = Trainer(cfg, Path(tmp) / "bench")
        trainer.run()
        with open(Path(tmp) / "bench" / "metrics.csv") as f:
            rows = list(csv.DictReader(f))[1:]  # drop the warm-up iteration
        c = sum(float(r["collect_s"]) for r in rows)
        u = sum(float(r["update_s"]) for r in rows)
        return {
            "params": count_parameters(trainer.actor_critic),
            "steps_per_s": 4096 * len(rows) / (c + u),
            "collect_s": c / len(rows),
            "update_s": u / len(rows),
        }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--iterations", type=int, default=4, help="measured iterations (after one warm-up)")
    ap.add_argument("--threads", type=int, default=2)
    # choices: a key=value written after --variants or --collectors is refused at once, not
    # taken for a name and found wrong minutes later.
    ap.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    ap.add_argument(
        "--collectors",
        nargs="*",
        default=list(COLLECTOR_KINDS),
        choices=COLLECTOR_KINDS,
        help="collector kinds to time collection alone with (none: skip)",
    )
    ap.add_argument("--workers", type=int, default=2, help="workers of multisync and ray")
    ap.add_argument("overrides", nargs="*")
    args = ap.parse_args()
    print(f"{'policy':>14} {'params':>9} {'steps/s':>8} {'collect':>8} {'update':>8}   (per 4096-frame iteration)")
    threads = [f"threads={args.threads}", f"env.physics.nthread={args.threads}"]
    for name in args.variants:
        r = learning_throughput(name, args.iterations, [*threads, *args.overrides])
        print(f"{name:>14} {r['params']:>9,} {r['steps_per_s']:>8.0f} {r['collect_s']:>7.2f}s {r['update_s']:>7.2f}s")
    if args.collectors:
        print(f"\ncollection alone, spatial policy, {args.iterations} batches of 4096 world-steps:")
        print(f"{'collector':>14} {'workers':>8} {'steps/s':>8}")
    for kind in args.collectors:
        if kind == "ray" and importlib.util.find_spec("ray") is None:
            print(f"{kind:>14}   (skipped: pip install -e '.[ray]')")
            continue
        sps = collection_throughput(kind, args.workers, args.threads, args.iterations, args.overrides)
        workers = 1 if kind == "sync" else args.workers
        print(f"{kind:>14} {workers:>8} {sps:>8.0f}")


if __name__ == "__main__":
    main()
