"""Ship a trained run as a named package policy: ``python tools/ship_policy.py runs/full mrchaos``.

Keeps what evaluation needs (weights in fp16, policy and env config, layout
checks, training counters, the run's eval.json, a re-ranker's weights) and drops the optimiser and RNG
state, so the file stays small. Written to ``mrchaos/data/policies/<name>.pt``.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from mrchaos.learn.checkpoint import load_checkpoint, save_checkpoint
from mrchaos.learn.policy import PolicyConfig

KEEP = (
    "kind",
    "config",
    "policy",
    "piece_set",
    "obs_shape",
    "grid",
    "view_extent",
    "model",
    "ranker",
    "curriculum",
    "iteration",
    "frames",
    "episodes",
    "minutes",
)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("run", type=Path)
    ap.add_argument("name")
    ap.add_argument(
        "--mode-window",
        type=int,
        metavar="W",
        help="set the shipped spatial policy's policy.mode_window (how its deterministic action is "
        "read; choose it on objects the bench does not use)",
    )
    args = ap.parse_args()
    st = load_checkpoint(args.run / "checkpoints" / "last.pt")
    out = {k: st[k] for k in KEEP if k in st}
    out["curriculum"] = {k: out["curriculum"][k] for k in ("stage", "switched_at")}
    if args.mode_window is not None:
        # Checked like a config's (odd, spatial only), then written where the bench reads it.
        PolicyConfig(**{**out["policy"], "mode_window": args.mode_window})
        out["policy"] = {**out["policy"], "mode_window": args.mode_window}
        out["config"]["policy"] = {**out["config"]["policy"], "mode_window": args.mode_window}
    ev = args.run / "eval.json"
    if ev.exists():
        out["eval"] = json.loads(ev.read_text())
    dest = Path(__file__).resolve().parents[1] / "mrchaos" / "data" / "policies" / f"{args.name}.pt"
    save_checkpoint(dest, out, half=True)
    print(
        f"wrote {dest} ({dest.stat().st_size / 1e6:.1f} MB) from {args.run}: iteration {st['iteration']}, "
        f"{st['frames']} frames"
    )


if __name__ == "__main__":
    main()
