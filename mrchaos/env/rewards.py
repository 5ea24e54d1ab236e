"""The step reward as named terms: what a placement earns, and each switch that changes it.

The reward of placing piece t is the coverage of its target slot (``coverage``; with
exclusive twin slots, what the placement adds to the assembly). The reference code's
three switches act on it one after another: ``shaping`` (coverage below a threshold pays
0 and the rest is rescaled, for every piece larger than the smallest), the penetration
gate (``penetration_ok``) and, in stage 1, the angle gate (``angle_ok``). Every term is
returned, enabled or not, so that each one can be logged; evaluation reads ``coverage``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from mrchaos.env.metrics import gate_angle, gate_penetration, shape_reward

__all__ = ["RewardConfig", "REWARD_TERMS", "reward_terms"]

#: The named terms in the order they are applied; ``reward`` is the last one.
REWARD_TERMS = ("coverage", "shaped", "penetration_ok", "angle_ok", "reward")
TWIN_SLOTS = ("shared", "exclusive")


@dataclass
class RewardConfig:
    """The training reward's switches (evaluation always reports raw coverage).

    Attributes:
        twin_slots: "shared" (the paper's: a piece scores the best slot of its twin group,
            even one a twin already fills) or "exclusive" (twins claim slots one each, in
            placement order, and a step pays what it adds; for many interchangeable pieces
            such as soda cans).
        shaping, shaping_threshold: coverage below the threshold pays 0 and
            [threshold, 1] is rescaled, for every piece larger than the smallest.
        penetration_gate, penetration_limit: pay 0 when the placed piece ends more than
            the limit (m) inside another.
        angle_gate, angle_tolerance_deg: pay only when the commanded angle is within the
            tolerance of the covered slot's angle, modulo the piece's symmetry.
    """

    twin_slots: str = "shared"
    shaping: bool = False
    shaping_threshold: float = 0.5
    penetration_gate: bool = False
    penetration_limit: float = 0.002
    angle_gate: bool = False
    angle_tolerance_deg: float = 20.0

    def __post_init__(self) -> None:
        if self.twin_slots not in TWIN_SLOTS:
            raise ValueError(f"env.reward.twin_slots must be one of {TWIN_SLOTS}, got {self.twin_slots!r}")


def reward_terms(
    cfg: RewardConfig,
    coverage: torch.Tensor,
    shaped: torch.Tensor,
    penetration: torch.Tensor,
    theta: torch.Tensor,
    slot_theta: torch.Tensor,
    period: torch.Tensor,
) -> dict[str, torch.Tensor]:
    """Every term of the step reward, (N,) each.

    Args:
        cfg: the switches.
        coverage: the placement's raw coverage.
        shaped: whether the placed piece takes the shaping (bool).
        penetration: how deep the placed piece ends inside another (m).
        theta, slot_theta: the commanded angle and the covered slot's angle (rad).
        period: the piece's symmetry period (rad; 0 = continuous symmetry).
    """
    r = coverage
    if cfg.shaping:
        r = shape_reward(r, shaped, cfg.shaping_threshold)
    out = {"coverage": coverage, "shaped": r}
    pen_ok = torch.ones_like(r)
    if cfg.penetration_gate:
        pen_ok = gate_penetration(pen_ok, penetration, cfg.penetration_limit)
    ang_ok = torch.ones_like(r)
    if cfg.angle_gate:
        ang_ok = gate_angle(ang_ok, theta, slot_theta, period, math.radians(cfg.angle_tolerance_deg))
    out["penetration_ok"], out["angle_ok"] = pen_ok, ang_ok
    # The gates zero the reward (where, not a product, so that NaN-free inputs stay bit-identical).
    out["reward"] = torch.where((pen_ok > 0) & (ang_ok > 0), r, torch.zeros_like(r))
    return out
