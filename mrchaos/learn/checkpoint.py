"""Checkpoints: atomic writes, ``weights_only`` loads, clear errors, and compatibility checks.

A checkpoint is a plain dict of tensors and builtin containers (so it loads with
``torch.load(weights_only=True)``)::

    {"format": 1, "kind": "mrchaos-policy", "config": {...}, "piece_set": "tangram7",
     "obs_shape": [2, 120, 120], "grid": [51, 51, 8], "model": state_dict, ...training state}
"""

from __future__ import annotations

import io
from importlib import resources
from pathlib import Path
from typing import Any

import torch

from mrchaos.core.atomic import write_atomic
from mrchaos.core.errors import MrchaosError, first_line
from mrchaos.learn.config import upgrade_config_dict

__all__ = [
    "CheckpointError",
    "SHIPPED",
    "shipped_path",
    "checkpoint_path",
    "save_checkpoint",
    "load_checkpoint",
    "policy_header",
    "check_header",
    "policy_env",
    "load_weights",
    "POLICY_ENV_GROUPS",
    "FORMAT",
]

#: Learnt policies shipped with the package: name -> (file, label). A label names the command that
#: makes the policy from scratch (a staged recipe where it takes several runs).
SHIPPED = {
    "mrchaos": ("mrchaos.pt", "MRChaos (full curriculum, spatial net)"),
    "mrchaos-paper": ("mrchaos-paper.pt", "MRChaos (full curriculum, paper net)"),
    "mrchaos-wo-local": ("mrchaos-wo-local.pt", "MRChaos w/o local"),
    "mrchaos-wo-global": ("mrchaos-wo-global.pt", "MRChaos w/o global"),
    "bc": ("bc.pt", "BC (trained on the built-in library)"),
    "mrchaos-bc-chaos": ("mrchaos-bc-chaos.pt", "BC on chaos objects (conf/bc_chaos.yaml)"),
    "mrchaos-dense": ("mrchaos-dense.pt", "dense counterfactual supervision on chaos (conf/dense.yaml)"),
    "mrchaos-dense-ppo": ("mrchaos-dense-ppo.pt", "PPO on top of mrchaos-dense (conf/recipes/dense_ppo.yaml)"),
    "mrchaos-exit": (
        "mrchaos-exit.pt",
        "expert iteration on top of mrchaos-dense (conf/recipes/rerank.yaml --until exit)",
    ),
    "mrchaos-generalist": (
        "mrchaos-generalist.pt",
        "free order, the flip and the re-ranker in one policy, on chaos objects only (conf/recipes/generalist.yaml)",
    ),
    "mrchaos-rerank": (
        "mrchaos-rerank.pt",
        "mrchaos-exit's top 5 re-ranked by an afterstate network (conf/recipes/rerank.yaml)",
    ),
    "mrchaos-flip": (
        "mrchaos-flip.pt",
        "the flip policy's top 5 re-ranked by an afterstate network (conf/recipes/flip.yaml)",
    ),
    "mrchaos-free": (
        "mrchaos-free.pt",
        "free order: dense supervision and 3 DAgger rounds, the policy picks the piece (conf/recipes/free.yaml)",
    ),
    "mrchaos-fixed-twin": (
        "mrchaos-fixed-twin.pt",
        "mrchaos-free's twin in the set's order (conf/recipes/free.yaml env.order=fixed)",
    ),
    "mrchaos-cutlery": (
        "mrchaos-cutlery.pt",
        "cutlery: dense targets, 3 DAgger rounds, 2 of expert iteration, refined grid (conf/recipes/cutlery.yaml)",
    ),
    "mrchaos-soda": ("mrchaos-soda.pt", "MRChaos on soda cans (conf/soda.yaml)"),
}


#: The env config groups a policy's weights depend on (its input image, its action head and the
#: assembly order it acts in);
#: an evaluation env takes them from the checkpoint.
POLICY_ENV_GROUPS = ("view", "grid", "observation", "order")

FORMAT = 1


class CheckpointError(MrchaosError, RuntimeError):
    """A missing, corrupt or incompatible checkpoint; the message names the file."""


def shipped_path(file: str) -> Path:
    """Where a shipped policy file lies in the installed package."""
    return Path(str(resources.files("mrchaos") / "data" / "policies" / file))


def checkpoint_path(spec: str) -> Path:
    """The checkpoint file of a shipped policy's name, a run folder (its ``checkpoints/last.pt``) or a file."""
    if spec in SHIPPED:
        path = shipped_path(SHIPPED[spec][0])
        if not path.exists():
            raise CheckpointError(f"{path}: the checkpoint of {spec!r} is not shipped with this version")
        return path
    p = Path(spec)
    if p.is_dir():
        p = p / "checkpoints" / "last.pt"
    if not p.exists():
        raise CheckpointError(f"{spec}: no such checkpoint or run, and not a shipped policy ({', '.join(SHIPPED)})")
    return p


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
        raise CheckpointError(f"{p}: not a readable checkpoint ({type(e).__name__}: {first_line(e, 160)})") from None
    if not isinstance(state, dict) or state.get("format") != FORMAT or "model" not in state:
        raise CheckpointError(f"{p}: not an mrchaos checkpoint (format {FORMAT})")
    if state.get("half"):
        state["model"] = {k: (v.float() if v.is_floating_point() else v) for k, v in state["model"].items()}
    return state


def policy_header(env, policy: dict[str, Any]) -> dict[str, Any]:
    """What a checkpoint says about the env its policy acts in, beside the policy's own config."""
    return {
        "kind": "mrchaos-policy",
        "policy": policy,
        "piece_set": env.piece_set.name,
        "obs_shape": [2, env.view.size, env.view.size],
        "grid": list(env.grid.nvec),
        "view_extent": env.view.extent,
    }


def check_header(state: dict[str, Any], path: str | Path, env, piece_set: str | None = None) -> None:
    """Raise :class:`CheckpointError` unless the checkpoint's policy fits ``env`` (piece set, image, grid).

    ``piece_set`` overrides the checkpoint's own (a policy acts on every set of its kind).
    """
    trained = piece_set or state.get("piece_set")
    if trained != env.piece_set.name:
        raise CheckpointError(f"{path}: trained on piece set {state.get('piece_set')!r}, not {env.piece_set.name!r}")
    obs_shape = [2, env.view.size, env.view.size]
    if list(state.get("obs_shape", [])) != obs_shape:
        raise CheckpointError(f"{path}: observation shape {state.get('obs_shape')} does not match {obs_shape}")
    if list(state.get("grid", [])) != list(env.grid.nvec):
        raise CheckpointError(f"{path}: action grid {state.get('grid')} does not match {list(env.grid.nvec)}")


def policy_env(state: dict[str, Any]) -> dict[str, Any]:
    """The env groups of :data:`POLICY_ENV_GROUPS` the checkpoint was trained with (nested, current keys)."""
    env = upgrade_config_dict(state.get("config", {})).get("env", {})
    return {k: env[k] for k in POLICY_ENV_GROUPS if k in env}


def load_weights(module: torch.nn.Module, path: str | Path, env) -> dict[str, Any]:
    """Load a checkpoint that fits ``env`` (:func:`check_header`) and its weights into ``module``
    (an actor-critic); returns the checkpoint. Weights of another network config raise
    :class:`CheckpointError`."""
    st = load_checkpoint(path)
    check_header(st, path, env)
    try:
        module.load_state_dict(st["model"])
    except (RuntimeError, KeyError, ValueError) as e:
        raise CheckpointError(f"{path}: weights do not fit this policy config ({str(e)[:200]})") from None
    return st
