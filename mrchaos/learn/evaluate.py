"""Deterministic evaluation: whole episodes on given targets, with the paper's and the strict metrics.

Each world gets one target (a chaos object or a figure) and places all j pieces
with the policy's most likely action (or a baseline), in the set's order or, with free order,
in the order the actor chooses (recorded). Per episode it
returns Rela and Final (the paper's), IoU and strict Rela (ours), and the final
view for contact sheets and recordings.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch
from tensordict import TensorDict
from torchrl.envs.utils import ExplorationType, set_exploration_type

from mrchaos.env.tangram import FREE_ORDER_KEYS, ROBOT_FAILURES, EnvConfig, TangramEnv
from mrchaos.tasks.chaos import generate

__all__ = ["EpisodeResults", "evaluate", "evaluate_random", "concat_results", "policy_actor", "policy_device"]


@dataclass
class EpisodeResults:
    """Per-episode metrics (arrays of length n) and, optionally, per-step records."""

    rela: np.ndarray
    final: np.ndarray
    iou: np.ndarray
    strict_rela: np.ndarray
    step_coverage: np.ndarray  # (n, j) the coverage each step's piece reached
    order: np.ndarray  # (n, j) the piece each step placed (0..j-1 with fixed order)
    silhouettes: np.ndarray  # (n, H, W) uint8
    final_views: np.ndarray  # (n, H, W) uint8
    failures: dict[str, np.ndarray] | None = None  # robot failure counts per episode
    #: Per episode: placements set down onto a placed piece (``onto_piece``) and pieces that end
    #: off the table, stacked or leaning (``off_table``): the collisions and stacking of the paper.
    contacts: dict[str, np.ndarray] | None = None
    perturbation: dict[str, np.ndarray] | None = None  # Final and pushed-piece coverage around the push
    steps: list[dict] | None = None


Actor = Callable[[TangramEnv, TensorDict], torch.Tensor]


def policy_device(policy) -> torch.device:
    """The device a policy module's weights lie on (the CPU for one without weights)."""
    weights = next(iter(policy.parameters()), None) if isinstance(policy, torch.nn.Module) else None
    return weights.device if weights is not None else torch.device("cpu")


def policy_actor(policy) -> Actor:
    """Greedy actions of a TorchRL policy module, on the device its weights lie on (the env's
    observations go there and the actions come back to the env's device)."""
    device = policy_device(policy)

    def act(env: TangramEnv, td: TensorDict) -> torch.Tensor:
        with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
            # The image, and with free order the pieces left and the action mask.
            obs = td.select("observation", *FREE_ORDER_KEYS, strict=False).clone().to(device)
            return policy(obs)["action"].to(env.device)

    return act


def evaluate(
    env: TangramEnv,
    targets: np.ndarray,
    actor: Actor,
    record_steps: bool = False,
    perturb_after: int | None = None,
    perturb_distance: float = 0.05,
    on_step: Callable[[int, int, TensorDict], None] | None = None,
    mirrored: np.ndarray | None = None,
) -> EpisodeResults:
    """Run one episode per target on ``env`` (in chunks of its world count) and collect metrics.

    ``mirrored`` (n, P) bool marks target pieces that lie turned over (default: none).

    With ``perturb_after = t``, the piece placed at step t is pushed ``perturb_distance``
    metres away right after it lands (the paper's Fig. 6C); the policy goes on from what
    it then sees. ``on_step(start, t, next)`` sees every step's output (for recordings).
    """
    n, nw, p = len(targets), env.batch_size[0], env.num_pieces
    if perturb_after is not None and not 0 <= perturb_after < p:
        raise ValueError(f"perturb_after must be in [0, {p - 1}], got {perturb_after}")
    keys = ("rela", "final", "iou", "strict", "cov", "order", "sil", "view", "fail", "contact", "pert")
    out: dict[str, list] = {k: [] for k in keys}
    # What an actor reads: the image, and with free order the pieces left and the action mask.
    inputs = ["observation", *(FREE_ORDER_KEYS if env.free_order else ())]
    steps: list[dict] = []
    for start in range(0, n, nw):
        chunk = targets[start : start + nw]
        m = len(chunk)
        padded = np.concatenate([chunk, np.repeat(chunk[-1:], nw - m, 0)]) if m < nw else chunk
        faces = None
        if mirrored is not None:
            faces = mirrored[start : start + nw]
            faces = np.concatenate([faces, np.repeat(faces[-1:], nw - m, 0)]) if m < nw else faces
        td = env.reset_to(padded, faces)
        silhouettes = td["observation"][:m, 0].numpy().copy()
        cov: list[torch.Tensor] = []
        order: list[torch.Tensor] = []
        fail = {k: torch.zeros(nw, dtype=torch.int64) for k in ROBOT_FAILURES}
        onto = torch.zeros(nw, dtype=torch.int64)
        pert = {}
        for t in range(p):
            action = actor(env, td)
            nxt = env.step(td.set("action", action))["next"]
            cov.append(nxt["info", "step_coverage"][:, 0])
            order.append(nxt["info", "piece"][:, 0])
            for k in ROBOT_FAILURES:
                fail[k] += nxt["info", k][:, 0].long()
            onto += nxt["info", "onto_piece"][:, 0].long()
            if t == perturb_after:
                pert["final_before"] = nxt["info", "final"][:m, 0].numpy().copy()
                pushed = (torch.arange(m), order[t][:m])  # the piece this step placed
                pert["coverage_before"] = nxt["info", "coverage"][:m][pushed].numpy().copy()
                env.perturb(np.arange(nw), perturb_distance)
                now = env.current()
                pert["final_after"] = now["info", "final"][:m, 0].numpy().copy()
                pert["coverage_after"] = now["info", "coverage"][:m][pushed].numpy().copy()
                nxt = nxt.update(now)
            if on_step is not None:
                on_step(start, t, nxt)
            if record_steps:
                steps.append(
                    {
                        "episode": np.arange(start, start + m),
                        "t": t,
                        "observation": td["observation"][:m].numpy().copy(),
                        "action": action[:m].numpy().copy(),
                        "coverage": nxt["info", "coverage"][:m].numpy().copy(),
                        "reward": nxt["info", "step_coverage"][:m, 0].numpy().copy(),
                    }
                )
            td = nxt.select(*inputs)
        covs = torch.stack(cov, 1)[:m]
        out["cov"].append(covs.numpy())
        out["order"].append(torch.stack(order, 1)[:m].numpy())
        out["rela"].append(covs.mean(1).numpy())
        out["final"].append(nxt["info", "final"][:m, 0].numpy())
        out["iou"].append(nxt["info", "iou"][:m, 0].numpy())
        out["strict"].append(nxt["info", "strict_rela"][:m, 0].numpy())
        out["sil"].append(silhouettes)
        out["view"].append(nxt["observation"][:m, 1].numpy().copy())
        out["fail"].append({k: v[:m].numpy() for k, v in fail.items()})
        out["contact"].append({"onto_piece": onto[:m].numpy(), "off_table": env.off_table()[:m].sum(1)})
        if pert:
            pert["final_end"] = nxt["info", "final"][:m, 0].numpy().copy()
            out["pert"].append(pert)
    cat = {k: np.concatenate(v) for k, v in out.items() if k not in ("fail", "contact", "pert")}

    return EpisodeResults(
        rela=cat["rela"],
        final=cat["final"],
        iou=cat["iou"],
        strict_rela=cat["strict"],
        step_coverage=cat["cov"],
        order=cat["order"],
        silhouettes=cat["sil"],
        final_views=cat["view"],
        failures=_merge(out["fail"]),
        contacts=_merge(out["contact"]),
        perturbation=_merge(out["pert"]),
        steps=steps if record_steps else None,
    )


def evaluate_random(policy, env_cfg: EnvConfig, n: int = 200, seed: int = 2024) -> dict[str, float]:
    """Greedy whole episodes of ``policy`` (a TorchRL policy module, or an :data:`Actor`) on ``n``
    seeded Random (chaos) objects of ``env_cfg``'s task, without the training noise; mean Rela,
    Final, IoU and strict Rela."""
    noise = dataclasses.replace(env_cfg.noise, action_xy=0.0, action_theta=0.0, camera_jitter=0.0)
    cfg = dataclasses.replace(env_cfg, num_worlds=min(n, 100), noise=noise, task=env_cfg.task.given_targets())
    env = TangramEnv(cfg, seed=seed)
    targets, _, mirrored = generate(env.piece_set, n, np.random.default_rng(seed), cfg.task.chaos, cfg.view)
    actor = policy_actor(policy) if isinstance(policy, torch.nn.Module) else policy
    res = evaluate(env, targets, actor, mirrored=mirrored)
    env.close()
    return {
        "n": n,
        "rela": float(res.rela.mean()),
        "final": float(res.final.mean()),
        "iou": float(res.iou.mean()),
        "strict_rela": float(res.strict_rela.mean()),
    }


def _merge(dicts: list[dict[str, np.ndarray] | None]) -> dict[str, np.ndarray] | None:
    """Per-key concatenation; None when there is nothing, or a part has none."""
    given = [d for d in dicts if d is not None]
    if not given or len(given) < len(dicts):
        return None
    return {k: np.concatenate([d[k] for d in given]) for k in given[0]}


def concat_results(parts: list[EpisodeResults]) -> EpisodeResults:
    """Episodes of several evaluations (e.g. piece sets of one family) as one; per-step
    records are dropped (their episode indices are per part)."""
    if len(parts) == 1:
        return parts[0]

    # Episodes of different piece counts have coverage rows of different lengths.
    width = max(r.step_coverage.shape[1] for r in parts)
    cov = [
        np.pad(r.step_coverage, ((0, 0), (0, width - r.step_coverage.shape[1])), constant_values=np.nan) for r in parts
    ]
    order = [np.pad(r.order, ((0, 0), (0, width - r.order.shape[1])), constant_values=-1) for r in parts]
    arrays = {
        k: np.concatenate([getattr(r, k) for r in parts])
        for k in ("rela", "final", "iou", "strict_rela", "silhouettes", "final_views")
    }
    return EpisodeResults(
        rela=arrays["rela"],
        final=arrays["final"],
        iou=arrays["iou"],
        strict_rela=arrays["strict_rela"],
        step_coverage=np.concatenate(cov),
        order=np.concatenate(order),
        silhouettes=arrays["silhouettes"],
        final_views=arrays["final_views"],
        failures=_merge([r.failures for r in parts]),
        contacts=_merge([r.contacts for r in parts]),
        perturbation=_merge([r.perturbation for r in parts]),
    )
