"""Checkpoints: atomic writes, ``weights_only`` loads, clear errors, and compatibility checks.

A checkpoint is a plain dict of tensors and builtin containers (so it loads with
``torch.load(weights_only=True)``)::

    {"format": 1, "kind": "mrchaos-policy", "config": {...}, "piece_set": "tangram7",
     "obs_shape": [2, 120, 120], "grid": [51, 51, 8], "model": state_dict, ...training state}
"""

from __future__ import annotations

import io
from pathlib import Path
from typing import Any

import torch

from mrchaos.errors import MrchaosError
from mrchaos.figure_io import write_atomic

__all__ = ["CheckpointError", "save_checkpoint", "load_checkpoint", "check_compatible", "FORMAT"]

FORMAT = 1


class CheckpointError(MrchaosError, RuntimeError):
    """A missing, corrupt or incompatible checkpoint; the message names the file."""


def save_checkpoint(path: str | Path, state: dict[str, Any], half: bool = False) -> None:
    """Write ``state`` atomically. ``half`` stores floating-point weights of ``state['model']`` as fp16."""
    state = dict(state, format=FORMAT)
    if half:
        state["model"] = {k: (v.half() if v.is_floating_point() else v) for k, v in state["model"].items()}
        state["half"] = True
    buf = io.BytesIO()
    torch.save(state, buf)
    write_atomic(path, buf.getvalue())


def load_checkpoint(path: str | Path) -> dict[str, Any]:
    """Load a checkpoint with ``weights_only=True``; fp16 weights come back as fp32."""
    p = Path(path)
    if not p.exists():
        raise CheckpointError(f"{p}: no such checkpoint")
    try:
        state = torch.load(p, map_location="cpu", weights_only=True)
    except Exception as e:  # torch raises many types for truncated or foreign files
        first = (str(e).strip().splitlines() or [""])[0][:160]
        raise CheckpointError(f"{p}: not a readable checkpoint ({type(e).__name__}: {first})") from None
    if not isinstance(state, dict) or state.get("format") != FORMAT or "model" not in state:
        raise CheckpointError(f"{p}: not an mrchaos checkpoint (format {FORMAT})")
    if state.get("half"):
        state["model"] = {k: (v.float() if v.is_floating_point() else v) for k, v in state["model"].items()}
    return state


def check_compatible(state: dict[str, Any], path: str | Path, piece_set: str, obs_shape, grid) -> None:
    """Raise :class:`CheckpointError` when the checkpoint was trained for another task layout."""
    if state.get("piece_set") != piece_set:
        raise CheckpointError(f"{path}: trained on piece set {state.get('piece_set')!r}, not {piece_set!r}")
    if list(state.get("obs_shape", [])) != list(obs_shape):
        raise CheckpointError(f"{path}: observation shape {state.get('obs_shape')} does not match {list(obs_shape)}")
    if list(state.get("grid", [])) != list(grid):
        raise CheckpointError(f"{path}: action grid {state.get('grid')} does not match {list(grid)}")
