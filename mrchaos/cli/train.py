"""``mrchaos-train CONFIG.yaml [key=value ...]`` and ``mrchaos-train --resume runs/<name>``."""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from mrchaos.cli.guard import run_command


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="mrchaos-train",
        description="Train a tangram policy: PPO, supervision "
        "(algo: bc; BC, dense targets, DAgger, expert iteration), or the afterstate re-ranker "
        "around a trained spatial policy (algo: rerank).",
    )
    ap.add_argument("config", nargs="?", help="YAML experiment (e.g. conf/full.yaml)")
    ap.add_argument("overrides", nargs="*", help="dotted overrides, e.g. optim.lr=1e-4 env.num_worlds=64")
    ap.add_argument("--resume", metavar="RUN_DIR", help="continue the run in this folder from its last checkpoint")
    ap.add_argument("--eval", type=int, default=200, help="Random objects for the final greedy evaluation (0: skip)")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s %(message)s")
    return run_command("mrchaos-train", lambda: _train(ap, args))


def _train(ap: argparse.ArgumentParser, args: argparse.Namespace) -> int:
    from mrchaos.learn.checkpoint import CheckpointError
    from mrchaos.learn.config import ConfigError, load_config
    from mrchaos.learn.ppo import Trainer, resume_config

    if args.resume:
        run_dir = Path(args.resume)
        cfg = resume_config(run_dir)
        if args.overrides or args.config:
            extra = ([args.config] if args.config else []) + args.overrides
            cfg = load_config(run_dir / "config.yaml", extra)
        if not (run_dir / "checkpoints" / "last.pt").exists():
            raise CheckpointError(f"{run_dir}: no checkpoints/last.pt to resume from")
        if cfg.algo != "ppo":
            return _supervise(cfg, run_dir, resume=True)
        trainer = Trainer(cfg, run_dir, resume=True)
    else:
        if not args.config:
            ap.error("a config file is required (or --resume RUN_DIR)")
        cfg = load_config(args.config, args.overrides)
        run_dir = Path(cfg.runs_dir) / cfg.name
        if (run_dir / "checkpoints" / "last.pt").exists():
            raise ConfigError(
                f"{run_dir} already holds a run; continue it with --resume {run_dir} or pick another name=..."
            )
        if cfg.algo != "ppo":
            return _supervise(cfg, run_dir)
        trainer = Trainer(cfg, run_dir)
    result = trainer.run()
    print(
        f"{run_dir}: {result['iteration']} iterations, {result['frames']} frames"
        + (" (stopped by signal)" if result["stopped"] else "")
    )
    if args.eval > 0 and not result["stopped"]:
        ev = trainer.finish(args.eval)
        print(
            f"greedy on {ev['n']} Random objects: Rela {ev['rela']:.3f}  Final {ev['final']:.3f}  "
            f"IoU {ev['iou']:.3f}  strict Rela {ev['strict_rela']:.3f}"
        )
    return 0


def _supervise(cfg, run_dir: Path, resume: bool = False) -> int:
    """A supervised run (algo: bc) or a re-ranker run (algo: rerank)."""
    from mrchaos.learn.bc import train_bc
    from mrchaos.learn.rerank import train_rerank

    res = (train_bc if cfg.algo == "bc" else train_rerank)(cfg, run_dir, resume=resume)
    print(
        f"{run_dir}: supervised on {res['samples']} labelled steps ({res['what']}), final loss "
        f"{res['loss']:.3f}; greedy on {res['n']} Random objects: Rela {res['rela']:.3f} "
        f"Final {res['final']:.3f}"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
