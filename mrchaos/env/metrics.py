"""Rewards and evaluation metrics, as pure functions of piece-id images.

Inputs are the rasteriser's id images: ``cur`` (B, H, W) int8, the piece seen at
each pixel of the current view (-1 empty), and ``tgt`` (B, H, W) int8, the piece
each pixel of the target belongs to (-1 outside the silhouette).

Paper metrics (MRChaos):
    * per-piece reward r_t = |p_t ∩ p'_t| / |p'_t|, twins taking the better slot;
    * Rela = mean over pieces of r_t, each measured when the piece was placed;
    * Final = |occupied ∩ silhouette| / |silhouette| on the final view.
Strict metrics (ours), because Final ignores spill outside the silhouette and
twins may both claim one slot under Rela:
    * IoU = |occupied ∩ silhouette| / |occupied ∪ silhouette| on the final view;
    * strict Rela = per-piece coverage on the final view with twin slots assigned
      one-to-one (the best assignment).
"""

from __future__ import annotations

import math

import numpy as np
import torch

__all__ = [
    "joint_counts",
    "final_from_joint",
    "iou_from_joint",
    "coverage_counts",
    "coverage_ratio",
    "best_slot_coverage",
    "piece_coverage",
    "shape_reward",
    "gate_penetration",
    "gate_angle",
    "rela",
    "final_coverage",
    "iou",
    "strict_rela",
    "strict_rela_from_joint",
]


def joint_counts(cur: torch.Tensor, tgt: torch.Tensor, num_pieces: int) -> torch.Tensor:
    """(B, P+1, P+1) int64 pixel counts of (seen piece + 1, target slot + 1); index 0 is empty/outside.

    Every metric of a view follows from it: coverage, Final, IoU, strict Rela.
    """
    p1 = num_pieces + 1
    b = cur.shape[0]
    if p1 * p1 > 256 or cur.dtype != torch.int8:
        code = (cur.long() + 1) * p1 + (tgt.long() + 1)
        code = code.reshape(b, -1) + torch.arange(b)[:, None] * (p1 * p1)
        return torch.bincount(code.reshape(-1), minlength=b * p1 * p1).view(b, p1, p1)
    # Fast path: a one-byte code per pixel (-1 wraps to 255, so +1 gives 0), widened
    # to int16 with a per-scene offset, then one bincount. Chunks keep offsets < 2**15.
    code = cur.view(torch.uint8) + 1
    code *= p1
    code += tgt.view(torch.uint8)
    code += 1
    chunk = 32767 // (p1 * p1)
    joints = []
    for s in range(0, b, chunk):
        part = code[s : s + chunk].reshape(min(chunk, b - s), -1).to(torch.int16)
        part += (torch.arange(part.shape[0], dtype=torch.int16) * (p1 * p1))[:, None]
        joints.append(torch.bincount(part.view(-1), minlength=part.shape[0] * p1 * p1))
    return torch.cat(joints).view(b, p1, p1)


def coverage_counts(cur: torch.Tensor, tgt: torch.Tensor, num_pieces: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Joint pixel counts.

    Returns:
        counts: (B, P, P) int64, pixels where piece i is seen on target slot j.
        area: (B, P) int64, pixels of each target slot.
    """
    joint = joint_counts(cur, tgt, num_pieces)
    return joint[:, 1:, 1:], joint[:, :, 1:].sum(1)


def final_from_joint(joint: torch.Tensor) -> torch.Tensor:
    """(B,) Final from a joint histogram: occupied target pixels over target pixels."""
    return joint[:, 1:, 1:].sum((1, 2)).float() / joint[:, :, 1:].sum((1, 2)).clamp(min=1).float()


def iou_from_joint(joint: torch.Tensor) -> torch.Tensor:
    """(B,) IoU of occupancy and silhouette from a joint histogram."""
    inter = joint[:, 1:, 1:].sum((1, 2))
    union = joint.sum((1, 2)) - joint[:, 0, 0]
    return inter.float() / union.clamp(min=1).float()


def coverage_ratio(counts: torch.Tensor, area: torch.Tensor) -> torch.Tensor:
    """(B, P, P) float64 |p_i ∩ p'_j| / |p'_j|; a slot with no target pixels scores 0."""
    ratio = counts.double() / area.clamp(min=1).double()[:, None, :]
    return torch.where(area[:, None, :] > 0, ratio, torch.zeros(()))


def best_slot_coverage(
    counts: torch.Tensor, area: torch.Tensor, twins: np.ndarray | torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """(B, P) float coverage of each piece over the slots it may fill, and (B, P) the best slot."""
    allowed = torch.as_tensor(np.asarray(twins), dtype=torch.bool)
    best, slot = torch.where(allowed, coverage_ratio(counts, area), torch.full((), -1.0, dtype=torch.float64)).max(-1)
    return best.clamp(min=0).float(), slot


def exclusive_slot_coverage(
    counts: torch.Tensor, area: torch.Tensor, twins: np.ndarray | torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Like :func:`best_slot_coverage`, but a slot covered by one piece is closed to its twins:
    pieces choose in id (placement) order, each the best slot still open. With many
    interchangeable pieces (cans) this keeps several pieces from scoring on one slot."""
    ratio = coverage_ratio(counts, area)  # (B, P, P)
    allowed = torch.as_tensor(np.asarray(twins), dtype=torch.bool)
    b, p = ratio.shape[:2]
    taken = torch.zeros(b, p, dtype=torch.bool)
    best = torch.zeros(b, p, dtype=torch.float64)
    slot = torch.zeros(b, p, dtype=torch.long)
    ar = torch.arange(b)
    for i in range(p):
        r = torch.where(allowed[i] & ~taken, ratio[:, i], torch.full((), -1.0, dtype=torch.float64))
        bi, si = r.max(-1)
        best[:, i], slot[:, i] = bi.clamp(min=0), si
        taken[ar, si] |= bi > 0
    return best.float(), slot


def piece_coverage(counts: torch.Tensor, area: torch.Tensor, twins: np.ndarray | torch.Tensor) -> torch.Tensor:
    """(B, P) float coverage of each piece: best over the slots it may fill of |p_i ∩ p'_j| / |p'_j|.

    ``twins`` is the piece set's (P, P) twin matrix. A slot with no target pixels scores 0.
    """
    return best_slot_coverage(counts, area, twins)[0]


def shape_reward(coverage: torch.Tensor, shaped: torch.Tensor, threshold: float = 0.5) -> torch.Tensor:
    """The reference training shaping: for shaped pieces, coverage below ``threshold`` pays 0 and
    [threshold, 1] is rescaled to [0, 1]. ``shaped`` is bool, broadcastable to ``coverage``."""
    rescaled = ((coverage - threshold) / (1.0 - threshold)).clamp(min=0.0)
    return torch.where(shaped, rescaled, coverage)


def gate_penetration(reward: torch.Tensor, penetration: torch.Tensor, limit: float = 0.002) -> torch.Tensor:
    """Zero the reward where the placed piece penetrates another by more than ``limit`` metres."""
    return torch.where(penetration > limit, torch.zeros_like(reward), reward)


def gate_angle(
    reward: torch.Tensor,
    theta: torch.Tensor,
    target_theta: torch.Tensor,
    period: torch.Tensor,
    tolerance: float = math.radians(20.0),
) -> torch.Tensor:
    """Zero the reward unless theta is within ``tolerance`` of the target angle modulo the piece's
    symmetry period (rad; 0 = continuous symmetry, always passes)."""
    safe = torch.where(period > 0, period, torch.full_like(period, 2 * math.pi))
    d = torch.remainder(theta - target_theta, safe)
    d = torch.minimum(d, safe - d)
    ok = (period <= 0) | (d <= tolerance + 1e-6)
    return torch.where(ok, reward, torch.zeros_like(reward))


def rela(step_rewards: torch.Tensor) -> torch.Tensor:
    """Relative coverage: mean over pieces (last dim) of the raw per-piece rewards."""
    return step_rewards.float().mean(-1)


def final_coverage(cur: torch.Tensor, silhouette: torch.Tensor) -> torch.Tensor:
    """(B,) |occupied ∩ silhouette| / |silhouette| of final views (paper's Final)."""
    occ = cur >= 0 if cur.dtype != torch.bool else cur
    inter = (occ & silhouette).flatten(1).sum(1).float()
    return inter / silhouette.flatten(1).sum(1).clamp(min=1).float()


def iou(cur: torch.Tensor, silhouette: torch.Tensor) -> torch.Tensor:
    """(B,) intersection over union of final occupancy and silhouette (penalises spill)."""
    occ = cur >= 0 if cur.dtype != torch.bool else cur
    inter = (occ & silhouette).flatten(1).sum(1).float()
    union = (occ | silhouette).flatten(1).sum(1).float()
    return inter / union.clamp(min=1)


def strict_rela(
    cur: torch.Tensor, tgt: torch.Tensor, twin_groups: tuple[tuple[int, ...], ...], num_pieces: int
) -> torch.Tensor:
    """(B,) mean per-piece coverage of the final view with twins assigned one-to-one.

    Each twin group takes the assignment of its slots that maximises its total
    coverage, so two twins on one slot cannot both score.
    """
    return strict_rela_from_joint(joint_counts(cur, tgt, num_pieces), twin_groups, num_pieces)


def strict_rela_from_joint(
    joint: torch.Tensor, twin_groups: tuple[tuple[int, ...], ...], num_pieces: int
) -> torch.Tensor:
    """:func:`strict_rela` from a joint histogram (:func:`joint_counts`)."""
    ratio = coverage_ratio(joint[:, 1:, 1:], joint[:, :, 1:].sum(1))
    total = torch.zeros(joint.shape[0], dtype=torch.float64)
    grouped = {i for g in twin_groups for i in g}
    for i in range(num_pieces):
        if i not in grouped:
            total += ratio[:, i, i]
    for group in twin_groups:
        total += _best_assignment(ratio, group)
    return (total / num_pieces).float()


def _best_assignment(ratio: torch.Tensor, group: tuple[int, ...]) -> torch.Tensor:
    """(B,) max over one-to-one assignments of the group's pieces to its slots of the summed coverage.

    A dynamic programme over the sets of slots taken (2^k states, k^2 2^k steps instead
    of k! permutations: 6 cans, 384 against 4,320), adding the pieces' terms in the same
    order as a sum over a permutation, so the result is the same to the last bit.
    """
    k = len(group)
    best: list[torch.Tensor | None] = [None] * (1 << k)
    best[0] = torch.zeros(ratio.shape[0], dtype=ratio.dtype)
    for taken in range(1, 1 << k):
        i = bin(taken).count("1") - 1  # the piece that takes the last slot of this set
        for j in range(k):
            if taken >> j & 1:
                prev, cur = best[taken ^ (1 << j)], best[taken]
                assert prev is not None  # every smaller set is filled before this one
                s = prev + ratio[:, group[i], group[j]]
                best[taken] = s if cur is None else torch.maximum(cur, s)
    out = best[-1]
    assert out is not None
    return out
