"""Planar polygon maths in metres: areas, rigid motions, convex overlap, pose fitting.

Everything here is vectorised numpy over leading batch dimensions, because chaos
generation and validation call it for thousands of polygon pairs at once. Exact
union/intersection areas (rare, for validation and tests) go through shapely.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = [
    "polygon_area",
    "polygon_centroid",
    "rigid_transform",
    "wrap_angle",
    "angle_gap",
    "convex_penetration",
    "fit_pose",
    "PoseFit",
]


def polygon_area(vertices: np.ndarray) -> float:
    """Signed area (shoelace) of a polygon (V, 2); positive when counter-clockwise."""
    v = np.asarray(vertices, dtype=np.float64)
    x, y = v[:, 0], v[:, 1]
    return 0.5 * float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))


def polygon_centroid(vertices: np.ndarray) -> np.ndarray:
    """Area centroid (2,) of a simple polygon (V, 2)."""
    v = np.asarray(vertices, dtype=np.float64)
    x, y = v[:, 0], v[:, 1]
    xn, yn = np.roll(x, -1), np.roll(y, -1)
    cross = x * yn - xn * y
    a = cross.sum() / 2.0
    return np.array([((x + xn) * cross).sum() / (6 * a), ((y + yn) * cross).sum() / (6 * a)])


def rigid_transform(vertices: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """Apply poses (..., 3) = (x, y, theta) to vertices (..., V, 2); broadcasts over leading dims."""
    pose = np.asarray(pose, dtype=np.float64)
    c, s = np.cos(pose[..., 2]), np.sin(pose[..., 2])
    vx, vy = vertices[..., 0], vertices[..., 1]
    x = c[..., None] * vx - s[..., None] * vy + pose[..., 0, None]
    y = s[..., None] * vx + c[..., None] * vy + pose[..., 1, None]
    return np.stack([x, y], axis=-1)


def step_angles(step: float) -> np.ndarray:
    """The rotations that are multiples of ``step`` (rad), from -pi upwards: a whole turn cut into
    round(2 pi / step) equal steps."""
    n = max(1, int(round(2 * math.pi / step)))
    return np.arange(n) * (2 * math.pi / n) - math.pi


def wrap_angle(theta: np.ndarray | float) -> np.ndarray:
    """Wrap angles to [-pi, pi)."""
    return (np.asarray(theta) + math.pi) % (2 * math.pi) - math.pi


def angle_gap(a: np.ndarray | float, b: np.ndarray | float, period: np.ndarray | float) -> np.ndarray:
    """Smallest absolute difference between angles a and b modulo ``period`` (rad).

    A period of 0 means continuous symmetry: the gap is always 0.
    """
    period = np.asarray(period, dtype=np.float64)
    safe = np.where(period > 0, period, 2 * math.pi)
    d = np.mod(np.asarray(a) - np.asarray(b), safe)
    d = np.minimum(d, safe - d)
    return np.where(period > 0, d, 0.0)


def _edge_normals(poly: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit outward-ish normals (..., V, 2) of a polygon's edges and a mask of real (non-zero) edges."""
    e = np.roll(poly, -1, axis=-2) - poly
    n = np.stack([e[..., 1], -e[..., 0]], axis=-1)
    length = np.linalg.norm(n, axis=-1, keepdims=True)
    valid = length[..., 0] > 1e-12
    return n / np.where(length > 1e-12, length, 1.0), valid


def convex_penetration(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Penetration depth (m) of convex polygons a (..., Va, 2) and b (..., Vb, 2).

    Separating-axis theorem over both polygons' edge normals: the result is the
    smallest overlap of the two projections over all axes, so it is > 0 exactly
    when the interiors intersect, <= 0 when they are separated or only touch, and
    it equals the distance one polygon must move to clear the other. Repeated
    vertices (padding) are ignored.
    """
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    lead = np.broadcast_shapes(a.shape[:-2], b.shape[:-2])
    # Flatten the lead dims so a single pair (lead == ()) takes the same masked path.
    a = np.broadcast_to(a, lead + a.shape[-2:]).reshape(-1, *a.shape[-2:])
    b = np.broadcast_to(b, lead + b.shape[-2:]).reshape(-1, *b.shape[-2:])
    # Bounding boxes first: most pairs of parts are far apart, and the x and y axes are
    # separating axes too, so a negative box overlap is a valid (<= 0) answer for them.
    box = np.minimum(a.max(-2), b.max(-2)) - np.maximum(a.min(-2), b.min(-2))
    out = box.min(-1)
    near = out > 0
    if near.any():
        out[near] = _sat_overlap(a[near], b[near])
    return out.reshape(lead)


def _sat_overlap(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(m,) smallest projection overlap of polygon pairs a (m, Va, 2), b (m, Vb, 2) over their edge normals."""
    na, va = _edge_normals(a)
    nb, vb = _edge_normals(b)
    axes = np.concatenate([na, nb], axis=-2)[:, :, None, :]  # (m, A, 1, 2)
    valid = np.concatenate([va, vb], axis=-1)
    # Elementwise products beat einsum/matmul on these tiny batched shapes.
    pa = a[:, None, :, 0] * axes[..., 0] + a[:, None, :, 1] * axes[..., 1]  # (m, A, Va)
    pb = b[:, None, :, 0] * axes[..., 0] + b[:, None, :, 1] * axes[..., 1]
    overlap = np.minimum(pa.max(-1), pb.max(-1)) - np.maximum(pa.min(-1), pb.min(-1))
    overlap = np.where(valid, overlap, np.inf)
    return overlap.min(-1)


class PoseFit:
    """Result of fitting a piece outline to a polygon: pose, mirror flag and RMS residual (m)."""

    __slots__ = ("pose", "mirrored", "residual")

    def __init__(self, pose: np.ndarray, mirrored: bool, residual: float) -> None:
        self.pose = pose
        self.mirrored = mirrored
        self.residual = residual

    def __repr__(self) -> str:
        return f"PoseFit(pose={self.pose.round(5).tolist()}, mirrored={self.mirrored}, residual={self.residual:.2e})"


def _procrustes_rotation(src: np.ndarray, dst: np.ndarray) -> tuple[float, float]:
    """Best rotation angle mapping centred src onto centred dst, and the RMS residual."""
    h = (src[:, 0] * dst[:, 1] - src[:, 1] * dst[:, 0]).sum()
    g = (src[:, 0] * dst[:, 0] + src[:, 1] * dst[:, 1]).sum()
    theta = math.atan2(h, g)
    c, s = math.cos(theta), math.sin(theta)
    rot = src @ np.array([[c, s], [-s, c]])
    return theta, float(np.sqrt(((rot - dst) ** 2).sum(-1).mean()))


def fit_pose(outline: np.ndarray, vertices: np.ndarray, mirrored_outline: np.ndarray | None = None) -> PoseFit:
    """Recover the pose (x, y, theta) that maps a centred ``outline`` onto world ``vertices``.

    Tries every cyclic correspondence of vertices (and, when given, the mirror
    image) and keeps the rotation with the smallest RMS vertex residual. The
    vertices may be clockwise; they must have as many points as the outline.
    """
    v = np.asarray(vertices, dtype=np.float64)
    if v.shape != outline.shape:
        raise ValueError(f"polygon has {len(v)} vertices, piece outline has {len(outline)}")
    if polygon_area(v) < 0:
        v = v[::-1]
    centre = polygon_centroid(v)
    dst = v - centre
    best = PoseFit(np.zeros(3), False, math.inf)
    candidates = [(outline, False)] + ([(mirrored_outline, True)] if mirrored_outline is not None else [])
    for src, mirrored in candidates:
        for shift in range(len(src)):
            theta, res = _procrustes_rotation(np.roll(src, shift, axis=0), dst)
            if res < best.residual - 1e-12:
                best = PoseFit(np.array([centre[0], centre[1], float(wrap_angle(theta))]), mirrored, res)
    return best
