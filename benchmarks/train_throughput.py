"""End-to-end PPO learning throughput (collection + updates) on this machine, per policy.

Runs a few iterations of ``conf/full.yaml`` (256 worlds, 4096 frames per iteration,
3 epochs of 512-sample minibatches) for each policy in a scratch run directory
and prints env-steps per second with the split between collection (env + policy
forward) and update (GAE + PPO epochs), from the run's own metrics.

    python benchmarks/train_throughput.py [--iterations 4] [--threads 2] [key=value ...]
"""

from __future__ import annotations

import argparse
import csv
import tempfile
from pathlib import Path

from mrchaos.learn.config import load_config
from mrchaos.learn.policy import count_parameters
from mrchaos.learn.ppo import Trainer

ROOT = Path(__file__).resolve().parents[1]

VARIANTS = {
    "paper": ["policy.name=paper", "policy.pool=2", "policy.channels=[32,64,64]"],
    "paper-fullres": ["policy.name=paper", "policy.pool=1", "policy.channels=[32,64,64]"],
    "spatial": ["policy.name=spatial", "policy.pool=1", "policy.channels=[16,32,32]"],
}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--iterations", type=int, default=4, help="measured iterations (after one warm-up)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--variants", nargs="+", default=list(VARIANTS))
    ap.add_argument("overrides", nargs="*")
    args = ap.parse_args()
    print(f"{'policy':>14} {'params':>9} {'steps/s':>8} {'collect':>8} {'update':>8}   (per 4096-frame iteration)")
    for name in args.variants:
        with tempfile.TemporaryDirectory() as tmp:
            frames = 4096 * (args.iterations + 1)
            cfg = load_config(ROOT / "conf" / "full.yaml", VARIANTS[name] + [
                f"runs_dir={tmp}", "name=bench", f"threads={args.threads}", f"env.physics.nthread={args.threads}",
                f"collector.total_frames={frames}", "collector.max_minutes=0", "logger.rerun=false",
                "logger.progress=false", "checkpoint.every=100000", "task.cache.path=null", "task.cache.size=1024",
                *args.overrides,
            ])
            trainer = Trainer(cfg, Path(tmp) / "bench")
            trainer.run()
            with open(Path(tmp) / "bench" / "metrics.csv") as f:
                rows = list(csv.DictReader(f))[1:]  # drop the warm-up iteration
            c = sum(float(r["collect_s"]) for r in rows)
            u = sum(float(r["update_s"]) for r in rows)
            n = sum(4096 for _ in rows)
            print(f"{name:>14} {count_parameters(trainer.actor_critic):>9,} {n / (c + u):>8.0f} "
                  f"{c / len(rows):>7.2f}s {u / len(rows):>7.2f}s")


if __name__ == "__main__":
    main()
