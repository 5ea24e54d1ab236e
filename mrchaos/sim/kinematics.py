"""Kinematics of UR-type arms from standard Denavit-Hartenberg parameters, batched in numpy.

The analytic inverse follows the usual decomposition of a UR arm: the wrist centre fixes
the shoulder pan, the tool axis fixes the second wrist joint, and the three parallel joints
in between form a planar 2R arm plus an orientation. There are up to eight solutions; the
one nearest a reference configuration is kept, so consecutive waypoints stay on one branch.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["DH", "UR5E", "fk", "ik", "pose_matrix"]


@dataclass(frozen=True)
class DH:
    """Standard DH parameters of a 6-joint UR arm (metres, radians).

    Attributes:
        d: link offsets d1..d6.
        a: link lengths a1..a6.
        alpha: link twists alpha1..alpha6.
        lower, upper: joint limits.
    """

    d: tuple[float, ...]
    a: tuple[float, ...]
    alpha: tuple[float, ...]
    lower: tuple[float, ...] = (-2 * math.pi,) * 6
    upper: tuple[float, ...] = (2 * math.pi,) * 6


#: The UR5e (Universal Robots' published DH table); the elbow is limited to +-pi as on the robot.
UR5E = DH(
    d=(0.1625, 0.0, 0.0, 0.1333, 0.0997, 0.0996),
    a=(0.0, -0.425, -0.3922, 0.0, 0.0, 0.0),
    alpha=(math.pi / 2, 0.0, 0.0, math.pi / 2, -math.pi / 2, 0.0),
    lower=(-2 * math.pi, -2 * math.pi, -math.pi, -2 * math.pi, -2 * math.pi, -2 * math.pi),
    upper=(2 * math.pi, 2 * math.pi, math.pi, 2 * math.pi, 2 * math.pi, 2 * math.pi),
)


def _link(theta: np.ndarray, d: float, a: float, alpha: float) -> np.ndarray:
    """(..., 4, 4) transforms Rz(theta) Tz(d) Tx(a) Rx(alpha)."""
    c, s = np.cos(theta), np.sin(theta)
    ca, sa = math.cos(alpha), math.sin(alpha)
    t = np.zeros(theta.shape + (4, 4))
    t[..., 0, 0], t[..., 0, 1], t[..., 0, 2], t[..., 0, 3] = c, -s * ca, s * sa, a * c
    t[..., 1, 0], t[..., 1, 1], t[..., 1, 2], t[..., 1, 3] = s, c * ca, -c * sa, a * s
    t[..., 2, 1], t[..., 2, 2], t[..., 2, 3] = sa, ca, d
    t[..., 3, 3] = 1.0
    return t


def fk(q: np.ndarray, dh: DH = UR5E) -> np.ndarray:
    """Flange poses (..., 4, 4) in the DH base frame for joint angles (..., 6)."""
    q = np.asarray(q, dtype=np.float64)
    t = np.broadcast_to(np.eye(4), q.shape[:-1] + (4, 4)).copy()
    for i in range(6):
        t = t @ _link(q[..., i], dh.d[i], dh.a[i], dh.alpha[i])
    return t


def pose_matrix(pos: np.ndarray, rot: np.ndarray) -> np.ndarray:
    """(..., 4, 4) homogeneous transforms from positions (..., 3) and rotations (..., 3, 3)."""
    t = np.zeros(pos.shape[:-1] + (4, 4))
    t[..., :3, :3] = rot
    t[..., :3, 3] = pos
    t[..., 3, 3] = 1.0
    return t


def _wrap_near(q: np.ndarray, ref: np.ndarray, lower: np.ndarray, upper: np.ndarray) -> np.ndarray:
    """The 2*pi-equivalent of q nearest ref, kept inside the limits where possible."""
    out = ref + (q - ref + np.pi) % (2 * np.pi) - np.pi
    out = np.where(out > upper, out - 2 * np.pi, out)
    return np.where(out < lower, out + 2 * np.pi, out)


def ik(
    target: np.ndarray, ref: np.ndarray, dh: DH = UR5E, weights: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Joint angles reaching flange poses ``target`` (..., 4, 4), nearest ``ref`` (..., 6).

    Returns ``(q, ok)``: q (..., 6) and ok (...,) False where no solution exists inside
    the joint limits (q is then ``ref``).
    """
    target = np.asarray(target, dtype=np.float64)
    ref = np.broadcast_to(np.asarray(ref, dtype=np.float64), target.shape[:-2] + (6,))
    d1, d4, d6 = dh.d[0], dh.d[3], dh.d[5]
    a2, a3 = dh.a[1], dh.a[2]
    lower, upper = np.array(dh.lower), np.array(dh.upper)
    w = np.array([1.0, 1.0, 1.0, 0.5, 0.5, 0.2]) if weights is None else np.asarray(weights)
    rot, p = target[..., :3, :3], target[..., :3, 3]
    z6 = rot[..., :, 2]
    wc = p - d6 * z6  # origin of frame 5
    r = np.hypot(wc[..., 0], wc[..., 1])
    phi = np.arctan2(wc[..., 1], wc[..., 0])
    with np.errstate(invalid="ignore", divide="ignore"):
        shoulder = np.arccos(np.clip(d4 / r, -1.0, 1.0))
        reach_ok = r > abs(d4)
        sols, oks = [], []
        for s1 in (1.0, -1.0):
            t1 = phi + np.pi / 2 + s1 * shoulder
            c1, sn1 = np.cos(t1), np.sin(t1)
            z1 = np.stack([sn1, -c1, np.zeros_like(c1)], -1)
            c5 = np.clip((z6 * z1).sum(-1), -1.0, 1.0)
            for s5 in (1.0, -1.0):
                t5 = s5 * np.arccos(c5)
                sin5 = np.sin(t5)
                x6, y6 = rot[..., :, 0], rot[..., :, 1]
                # z1 seen from frame 6 is (s5 c6, -s5 s6, c5); near s5 = 0 the wrist is singular
                # and theta6 is free: keep the reference's.
                sing = np.abs(sin5) < 1e-9
                t6 = np.where(
                    sing,
                    ref[..., 5],
                    np.arctan2(
                        -(z1 * y6).sum(-1) / np.where(sing, 1, sin5), (z1 * x6).sum(-1) / np.where(sing, 1, sin5)
                    ),
                )
                # Frame 4 in frame 1, from the flange pose and the known wrist joints.
                t01 = _link(t1, d1, 0.0, dh.alpha[0])
                t45 = _link(t5, dh.d[4], 0.0, dh.alpha[4])
                t56 = _link(t6, d6, 0.0, dh.alpha[5])
                t14 = np.linalg.inv(t01) @ target @ np.linalg.inv(t45 @ t56)
                px, py = t14[..., 0, 3], t14[..., 1, 3]
                c3 = (px * px + py * py - a2 * a2 - a3 * a3) / (2 * a2 * a3)
                ok3 = np.abs(c3) <= 1.0
                for s3 in (1.0, -1.0):
                    t3 = s3 * np.arccos(np.clip(c3, -1.0, 1.0))
                    t2 = np.arctan2(py, px) - np.arctan2(a3 * np.sin(t3), a2 + a3 * np.cos(t3))
                    t234 = np.arctan2(t14[..., 1, 0], t14[..., 0, 0])
                    t4 = t234 - t2 - t3
                    q = np.stack([t1, t2, t3, t4, t5, t6], -1)
                    q = _wrap_near(q, ref, lower, upper)
                    inside = ((q >= lower) & (q <= upper)).all(-1)
                    sols.append(q)
                    oks.append(reach_ok & ok3 & inside & np.isfinite(q).all(-1))
    all_q = np.stack(sols, -2)  # (..., 8, 6)
    all_ok = np.stack(oks, -1)  # (..., 8)
    cost = (w * (all_q - ref[..., None, :]) ** 2).sum(-1)
    cost = np.where(all_ok, cost, np.inf)
    best = cost.argmin(-1)
    q = np.take_along_axis(all_q, best[..., None, None], -2)[..., 0, :]
    ok = np.asarray(all_ok.any(-1))
    return np.where(ok[..., None], q, ref), ok
