"""``mrchaos-train CONFIG.yaml [key=value ...]`` and ``mrchaos-train --resume runs/<name>``.

CONFIG is one experiment or a staged recipe (``conf/recipes/``, :mod:`mrchaos.learn.stages`),
whose overrides take ``stage:key=value`` for one stage and ``key=value`` for all."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from mrchaos.cli.guard import run_command
from mrchaos.cli.logs import configure_logging


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
    ap.add_argument(
        "--eval",
        type=int,
        help="Random objects for the final greedy evaluation (default 200 after PPO, 100 after supervision; 0: skip)",
    )
    ap.add_argument(
        "--until",
        metavar="STAGE",
        help="a staged recipe: stop after this stage (--resume RUN_DIR goes on from there)",
    )
    ap.add_argument("-v", "--verbose", action="store_true", help="also print the libraries' INFO lines")
    args = ap.parse_args(argv)
    configure_logging(args.verbose)
    return run_command("mrchaos-train", lambda: _train(ap, args))


def _train(ap: argparse.ArgumentParser, args: argparse.Namespace) -> int:
    from mrchaos.learn.checkpoint import CheckpointError
    from mrchaos.learn.config import ConfigError, load_config
    from mrchaos.learn.ppo import resume_config
    from mrchaos.learn.stages import is_recipe, load_recipe, resume_recipe, run_recipe, train_config

    def train(cfg, run_dir: Path, resume: bool) -> dict:
        return train_config(cfg, run_dir, resume, n_eval=args.eval)

    if args.resume:
        run_dir = Path(args.resume)
        extra = ([args.config] if args.config else []) + args.overrides
        if is_recipe(run_dir / "config.yaml"):
            return _report(run_recipe(resume_recipe(run_dir, extra), train, resume=True, until=args.until))
        cfg = resume_config(run_dir)
        if extra:
            cfg = load_config(run_dir / "config.yaml", extra)
        if not (run_dir / "checkpoints" / "last.pt").exists():
            raise CheckpointError(f"{run_dir}: no checkpoints/last.pt to resume from")
        return _report([train(cfg, run_dir, True)])
    if not args.config:
        ap.error("a config file is required (or --resume RUN_DIR)")
    if args.until and not is_recipe(args.config):
        ap.error("--until names a stage of a staged recipe")
    if is_recipe(args.config):
        return _report(run_recipe(load_recipe(args.config, args.overrides), train, until=args.until))
    cfg = load_config(args.config, args.overrides)
    run_dir = Path(cfg.runs_dir) / cfg.name
    if (run_dir / "checkpoints" / "last.pt").exists():
        raise ConfigError(
            f"{run_dir} already holds a run; continue it with --resume {run_dir} or pick another name=..."
        )
    return _report([train(cfg, run_dir, False)])


def _report(results: list[dict]) -> int:
    for res in results:
        print(res["summary"])
    return 0


if __name__ == "__main__":
    sys.exit(main())
