"""Batched physical worlds: one MuJoCo simulation per world, and teleport placement into them.

A world holds every piece of the set as a free body. Pieces not yet placed wait
in the staging area outside the camera view. Placing piece t at (x, y, theta)
releases it 2 mm above the highest surface under its footprint and lets physics
settle for a few dozen substeps, so a piece dropped onto another rests on it,
tilted or stacked, never inside it. When the footprint is free, that settling
would only drop the piece flat onto the table, so the world is written directly
and its physics is skipped (the fast path); the share of each path is counted.

A piece may also be set down turned over (its mirror image, for a chiral piece): the
body is rotated half a turn about its own y axis, so its footprint is the outline mirrored
in x, and physics treats it as the real upside-down prism.

All worlds step together in one ``mujoco.batch.Batch`` on the machine's threads.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import mujoco
import mujoco.batch
import numpy as np
import shapely

from mrchaos.core.geometry import convex_penetration, rigid_transform
from mrchaos.core.raster import Raster, View, rasterize
from mrchaos.figures.pieces import PieceSet
from mrchaos.sim.executor import ExecutionResult, Executor, ExecutorConfig
from mrchaos.sim.flipper import Flipper, FlipperConfig, flipper_geometry
from mrchaos.sim.robot import Robot, RobotConfig
from mrchaos.sim.scene import SceneConfig, build_model, staging_poses

__all__ = ["PhysicsConfig", "Worlds", "PlacementResult"]


@dataclass(frozen=True)
class PhysicsConfig:
    """Placement physics.

    Attributes:
        settle_steps: physics substeps after a release onto other pieces.
        release_gap: the piece is released this far above the highest surface under it (m).
        free_tolerance: a footprint that penetrates others by at most this much (m) counts
            as free: grid rounding and the drawn figures' touching slots leave overlaps of a
            few micrometres between neighbours, which MuJoCo's contact would push apart (10 µm:
            at 1 µm the exact oracle ended under Final 0.99 on two mrchaos104 figures).
        push_depth: a footprint that overlaps others by at most this much (m) is set down
            on the same surface as them and contact pushes the pieces apart, as a sliver
            of overlap does when a real piece is lowered beside another; deeper overlaps
            release the piece above the highest surface under it.
        release_speed: downward speed of a released piece (m/s).
        nthread: threads of the batch (0 = all cores).
        flat_tilt: a piece tilted less than this (rad) is drawn with its flat outline.
    """

    settle_steps: int = 20
    release_gap: float = 0.002
    free_tolerance: float = 1e-5
    push_depth: float = 0.001
    release_speed: float = 0.05
    nthread: int = 0
    flat_tilt: float = math.radians(1.0)


@dataclass
class PlacementResult:
    """What a placement did, per world of the call.

    Attributes:
        physics: True where physics ran (the footprint was not free, or the robot placed it).
        penetration: how deep the placed piece ends inside another (m), >= 0.
        onto: True where the commanded footprint lay on a placed piece deeper than a sliver
            (``push_depth``): the piece was set down onto another, whatever then happened.
        robot: what the robot did, with robot placement; None with teleport.
    """

    physics: np.ndarray
    penetration: np.ndarray
    onto: np.ndarray
    robot: ExecutionResult | None = None


def _quat_yaw(theta: np.ndarray) -> np.ndarray:
    return np.stack([np.cos(theta / 2), np.zeros_like(theta), np.zeros_like(theta), np.sin(theta / 2)], -1)


def _quat_turned_over(theta: np.ndarray) -> np.ndarray:
    """Yaw theta after half a turn about the body's y axis: qz(theta) * qy(pi)."""
    return np.stack([np.zeros_like(theta), -np.sin(theta / 2), np.cos(theta / 2), np.zeros_like(theta)], -1)


def _quat_to_mat(q: np.ndarray) -> np.ndarray:
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
            np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
            np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


def _rows_of(mask: np.ndarray | None, idx: np.ndarray) -> np.ndarray | None:
    return None if mask is None else mask[idx]


class Worlds:
    """N worlds of one piece set, with teleport or robot placement and MuJoCo physics.

    With ``robot`` given, the scene holds the UR5e and :meth:`place` has it pick and
    place every piece (:class:`mrchaos.sim.executor.Executor`); otherwise pieces teleport.
    With ``flipper`` given too, the scene holds the flip fixture and the robot turns pieces
    over on it (:class:`mrchaos.sim.flipper.Flipper`) when a placement asks for a mirrored one.

    Attributes kept per world (numpy, updated by :meth:`reset` and :meth:`place`):
        placed: (N, P) bool, pieces on the table (not in the staging area).
        footprint: (N, P, 2V, 2) top-down outline of each piece (padded convex polygon).
        top: (N, P) height of each piece's highest point above the table (m).
    """

    def __init__(
        self,
        piece_set: PieceSet,
        n: int,
        physics: PhysicsConfig = PhysicsConfig(),
        scene: SceneConfig = SceneConfig(),
        view: View = View(),
        robot: RobotConfig | None = None,
        executor: ExecutorConfig = ExecutorConfig(),
        flipper: FlipperConfig | None = None,
    ) -> None:
        self.piece_set = piece_set
        self.n = n
        self.cfg = physics
        self.model = build_model(piece_set, scene, view, robot, flipper if robot is not None else None)
        # Sleeping islands need one MjData per world (persistent).
        self.batch = mujoco.batch.Batch(self.model, nsim=n, nthread=physics.nthread, persistent=True)
        self.qpos = self.batch.bind("qpos")
        self.qvel = self.batch.bind("qvel")
        p = len(piece_set)
        bodies = np.array([self.model.body(name).id for name in piece_set.names])
        self._qadr = self.model.jnt_qposadr[self.model.body_jntadr[bodies]]
        self._dadr = self.model.jnt_dofadr[self.model.body_jntadr[bodies]]
        # Geometry works on convex parts, K per piece (K = 1 for convex sets): (P*K, V, 2).
        self._parts = piece_set.padded_parts()
        self._parts_mirrored = piece_set.padded_parts(np.ones(p, dtype=bool))
        self._k = piece_set.parts_per_piece
        self._part_piece = piece_set.part_piece
        self._raster_parts = piece_set.raster_parts
        self._v = self._parts.shape[1]
        self._thick = np.array([pc.thickness for pc in piece_set.pieces])
        # Prism vertices of the parts in body frames, padded like the outlines: (P*K, 2V, 3).
        half_t = (self._thick[self._part_piece] / 2)[:, None, None] * np.ones((len(self._parts), self._v, 1))
        self._prism = np.concatenate(
            [np.concatenate([self._parts, -half_t], -1), np.concatenate([self._parts, half_t], -1)], 1
        )
        self._staging = staging_poses(piece_set, scene, view)
        self.placed = np.zeros((n, p), dtype=bool)
        #: (n, P*K, 2V, 2) footprints of the pieces' convex parts (see :meth:`raster`).
        self.footprint = np.zeros((n, p * self._k, 2 * self._v, 2))
        self.top = np.zeros((n, p))
        self.count_fast = 0
        self.count_physics = 0
        self.executor = None
        self.flipper = None
        if robot is not None:
            period = np.array([pc.symmetry_period for pc in piece_set.pieces])
            self.executor = Executor(self.batch, Robot(self.model, robot), bodies, self._thick, period, executor)
            if flipper is not None:
                self.flipper = Flipper(
                    self.batch, self.model, bodies, flipper_geometry(piece_set, view, flipper), flipper
                )
        self.batch.reset(keyframe=0)
        self._refresh(np.arange(n))

    # ----------------------------------------------------------------- state io
    def _write_flat(
        self,
        rows: np.ndarray,
        piece: np.ndarray,
        pose: np.ndarray,
        z: np.ndarray,
        vz: float = 0.0,
        mirrored: np.ndarray | None = None,
    ) -> None:
        cols = self._qadr[piece][:, None] + np.arange(7)
        quat = _quat_yaw(pose[:, 2])
        if mirrored is not None and mirrored.any():
            quat = np.where(mirrored[:, None], _quat_turned_over(pose[:, 2]), quat)
        q = np.concatenate([pose[:, :2], z[:, None], quat], 1)
        self.qpos[rows[:, None], cols] = q
        vcols = self._dadr[piece][:, None] + np.arange(6)
        self.qvel[rows[:, None], vcols] = 0.0
        self.qvel[rows, self._dadr[piece] + 2] = vz

    def _refresh(self, rows: np.ndarray) -> None:
        """Recompute footprints and top heights of the given worlds from qpos."""
        q = self.qpos[rows][:, self._qadr[:, None] + np.arange(7)][:, self._part_piece]  # (R, Q, 7)
        rot = _quat_to_mat(q[..., 3:])  # (R, Q, 3, 3)
        verts = np.einsum("rpij,pvj->rpvi", rot, self._prism) + q[..., None, :3]  # (R, Q, 2V, 3)
        self.top[rows] = verts[..., 2].max(-1).reshape(len(rows), -1, self._k).max(-1)
        up = rot[..., 2, 2]
        tilted = np.abs(up) < math.cos(self.cfg.flat_tilt)
        yaw = np.arctan2(rot[..., 1, 0], rot[..., 0, 0])
        parts = self._parts[None]
        over = up < 0  # lying turned over: the body's x axis points back along -yaw
        if over.any():
            yaw = np.where(over, np.arctan2(-rot[..., 1, 0], -rot[..., 0, 0]), yaw)
            parts = np.where(over[..., None, None], self._parts_mirrored[None], parts)
        flat = rigid_transform(parts, np.stack([q[..., 0], q[..., 1], yaw], -1))  # (R, Q, V, 2)
        fp = np.concatenate([flat, np.repeat(flat[..., -1:, :], self._v, axis=2)], 2)
        for r, i in zip(*np.nonzero(tilted), strict=True):
            hull = shapely.MultiPoint(verts[r, i, :, :2]).convex_hull
            pts = np.asarray(hull.exterior.coords)[:-1] if hull.geom_type == "Polygon" else verts[r, i, :, :2]
            pts = pts[: 2 * self._v]
            fp[r, i, : len(pts)] = pts
            fp[r, i, len(pts) :] = pts[-1]
        self.footprint[rows] = fp

    # ----------------------------------------------------------------- actions
    def reset(self, rows: np.ndarray, preassembled: list[tuple[np.ndarray, ...]] | None = None) -> None:
        """Return the worlds of ``rows`` to the home keyframe, then put pieces already assembled.

        ``preassembled[k]`` is ``(rows_k, poses_k)`` or ``(rows_k, poses_k, mirrored_k)``: the
        worlds whose count includes piece k, its target poses there, and whether it lies turned
        over; pass ``None`` for no pieces. Assembled pieces lie flat on the table (targets do
        not overlap, so no physics is needed).
        """
        rows = np.asarray(rows, dtype=np.int64)
        if len(rows) == 0:
            return
        self.batch.reset(ids=rows, keyframe=0)
        self.placed[rows] = False
        for k, (sub, poses, *mirrored) in enumerate(preassembled or []):
            if len(sub):
                piece = np.full(len(sub), k)
                self._write_flat(
                    sub, piece, poses, np.full(len(sub), self._thick[k] / 2), mirrored=mirrored[0] if mirrored else None
                )
                self.placed[sub, k] = True
        self._refresh(rows)

    def place(
        self, rows: np.ndarray, piece: np.ndarray, pose: np.ndarray, mirrored: np.ndarray | None = None
    ) -> PlacementResult:
        """Place ``piece[i]`` of world ``rows[i]`` at planar ``pose[i]`` and settle; ``mirrored[i]``
        sets it down turned over.

        Returns which worlds needed physics and how deep the piece ends inside another.
        """
        rows = np.asarray(rows, dtype=np.int64)
        piece = np.asarray(piece, dtype=np.int64)
        m = len(rows)
        cols = piece[:, None] * self._k + np.arange(self._k)  # (m, K) the piece's parts
        parts = self._parts[cols]
        if mirrored is not None and mirrored.any():
            parts = np.where(mirrored[:, None, None, None], self._parts_mirrored[cols], parts)
        foot = rigid_transform(parts, pose[:, None])  # (m, K, V, 2)
        others = self.placed[rows].copy()
        others[np.arange(m), piece] = False
        depth = self._piece_depth(foot, rows)  # (m, P)
        under = others & (depth > self.cfg.free_tolerance)
        if self.executor is not None:
            return self._place_robot(rows, piece, pose, under, depth, mirrored)
        onto = (under & (depth > self.cfg.push_depth)).any(1)
        free = ~under.any(1)
        half = self._thick[piece] / 2
        # Fast path: the piece lands flat on the table, exactly where a settle would put it.
        fr = np.flatnonzero(free)
        if len(fr):
            self._write_flat(rows[fr], piece[fr], pose[fr], half[fr], mirrored=_rows_of(mirrored, fr))
        # Physics path: drop from just above the highest surface the piece really lands on;
        # slivers of overlap (<= push_depth) do not hold it up, contact pushes them apart.
        ph = np.flatnonzero(~free)
        if len(ph):
            deep = under[ph] & (depth[ph] > self.cfg.push_depth)
            base = np.where(under[ph], self.top[rows[ph]] - self._thick[None, :], np.inf).min(1)  # their resting level
            floor = np.where(deep.any(1), np.where(deep, self.top[rows[ph]], 0.0).max(1), base.clip(min=0.0))
            gap = np.where(deep.any(1), self.cfg.release_gap, 0.0)
            # Released moving down, as from a gripper, which also keeps MuJoCo from
            # putting the piece to sleep before it has fallen.
            self._write_flat(
                rows[ph],
                piece[ph],
                pose[ph],
                floor + gap + half[ph],
                vz=-self.cfg.release_speed,
                mirrored=_rows_of(mirrored, ph),
            )
            self.batch.step(ids=rows[ph], nstep=self.cfg.settle_steps)
            bad = ~np.isfinite(self.qpos[rows[ph]]).all(1)
            if bad.any():  # a diverged world: fall back to the plain placement
                b = ph[bad]
                self._write_flat(rows[b], piece[b], pose[b], half[b], mirrored=_rows_of(mirrored, b))
        self.placed[rows, piece] = True
        # A fast-path world changed by one flat piece; physics worlds may have moved anything.
        if len(fr):
            r, k, c = rows[fr], piece[fr], cols[fr]
            self.footprint[r[:, None], c, : self._v] = foot[fr]
            self.footprint[r[:, None], c, self._v :] = foot[fr][:, :, -1:]
            self.top[r, k] = self._thick[k]
        if len(ph):
            self._refresh(rows[ph])
        self.count_fast += len(fr)
        self.count_physics += len(ph)
        penetration = np.zeros(m)
        if len(ph):  # a free footprint cannot end inside anything
            penetration[ph] = self._penetration(rows[ph], piece[ph])
        return PlacementResult(physics=~free, penetration=penetration, onto=onto)

    def push(self, rows: np.ndarray, piece: np.ndarray, displacement: np.ndarray, seconds: float = 0.6) -> None:
        """Shove ``piece[i]`` of world ``rows[i]`` along ``displacement[i]`` (m, planar), as a flick would.

        The piece is given the speed at which sliding friction on the table stops it after
        that distance; physics then runs for ``seconds``, so it may hit and move others.
        """
        rows = np.asarray(rows, dtype=np.int64)
        dist = np.linalg.norm(displacement, axis=1)
        mu = self.model.geom_friction[self.model.geom("table").id, 0]
        speed = np.sqrt(2 * mu * 9.81 * dist)
        direction = displacement / np.maximum(dist, 1e-12)[:, None]
        vcols = self._dadr[piece]
        self.qvel[rows, vcols] = direction[:, 0] * speed
        self.qvel[rows, vcols + 1] = direction[:, 1] * speed
        self.batch.step(ids=rows, nstep=max(1, round(seconds / self.model.opt.timestep)))
        self._refresh(rows)

    def _place_robot(
        self,
        rows: np.ndarray,
        piece: np.ndarray,
        pose: np.ndarray,
        under: np.ndarray,
        depth: np.ndarray,
        mirrored: np.ndarray | None,
    ) -> PlacementResult:
        """The robot places the pieces; the release height clears what lies under the target. A piece
        to go down mirrored is first set on the flip fixture, turned over, and picked up again."""
        deep = under & (depth > self.cfg.push_depth)
        floor = np.where(deep, self.top[rows], 0.0).max(1)
        travel = np.where(self.placed[rows], self.top[rows], 0.0).max(1)
        assert self.executor is not None  # robot placement builds it
        flip = None
        f = np.flatnonzero(mirrored) if mirrored is not None else np.zeros(0, dtype=np.int64)
        if len(f):
            if self.flipper is None:
                raise ValueError(
                    "turning a piece over with the robot needs the flip fixture in the scene "
                    "(env.grid.flip with env.placement: robot)"
                )
            g = self.flipper.geometry
            # Set down at the yaw that the half turn maps onto the target's.
            on_plate = np.c_[np.tile(g.plate_centre, (len(f), 1)), -pose[f, 2]]
            flip = self.executor.execute(rows[f], piece[f], on_plate, np.full(len(f), g.top), travel[f])
            _, turned = self.flipper.flip(rows[f], piece[f], on_plate)
            flip.flip_failed = ~turned
        res = self.executor.execute(rows, piece, pose, floor, travel)
        if flip is not None:
            for k in ("unreachable", "missed", "dropped", "collision"):
                getattr(res, k)[f] |= getattr(flip, k)
            assert res.flip_failed is not None  # ExecutionResult fills it
            res.flip_failed[f] = flip.flip_failed
        self.placed[rows, piece] = True
        self._refresh(rows)
        self.count_physics += len(rows)
        return PlacementResult(
            physics=np.ones(len(rows), dtype=bool),
            penetration=self._penetration(rows, piece),
            onto=np.asarray(deep.any(1)),  # (m,) bool: numpy types any() as bool or array
            robot=res,
        )

    def _penetration(self, rows: np.ndarray, piece: np.ndarray) -> np.ndarray:
        """Depth of the placed piece inside any other placed piece: planar overlap where the
        pieces' height ranges also overlap (flat prisms)."""
        m = len(rows)
        if m == 0:
            return np.zeros(0)
        ar = np.arange(m)
        foot = self.footprint[rows[:, None], piece[:, None] * self._k + np.arange(self._k)]  # (m, K, 2V, 2)
        depth2d = self._piece_depth(foot, rows)  # (m, P)
        top = self.top[rows]
        bottom = top - self._thick[None, :]
        zover = np.minimum(top, top[ar, piece][:, None]) - np.maximum(bottom, bottom[ar, piece][:, None])
        pen = np.minimum(depth2d, zover)
        others = self.placed[rows].copy()
        others[ar, piece] = False
        return np.where(others, pen, 0.0).max(1).clip(min=0.0)

    def _piece_depth(self, foot: np.ndarray, rows: np.ndarray) -> np.ndarray:
        """(m, P) penetration of parts ``foot`` (m, K, V', 2) into every piece of worlds ``rows``
        (the deepest over all pairs of parts)."""
        depth = convex_penetration(foot[:, :, None], self.footprint[rows][:, None])  # (m, K, Q)
        return depth.max(1).reshape(len(rows), -1, self._k).max(-1)

    def raster(
        self, view: View, rows: np.ndarray | None = None, shift: np.ndarray | None = None, need_height: bool = False
    ) -> Raster:
        """Top-down piece-id (and height) images of the placed pieces of worlds ``rows`` (default all),
        optionally shifted by (R, 2) metres (camera jitter)."""
        sel = slice(None) if rows is None else rows
        fp = self.footprint[sel]
        if shift is not None:
            fp = fp + shift[:, None, None, :]
        return rasterize(
            fp, view, visible=self.placed[sel], heights=self.top[sel], need_height=need_height, parts=self._raster_parts
        )

    def off_table(self) -> np.ndarray:
        """(N, P) bool: placed pieces that do not lie flat on the table, their top more than half a
        thickness above a flat piece's (stacked on another, or leaning on one)."""
        return self.placed & (self.top > 1.5 * self._thick[None, :])

    @property
    def physics_share(self) -> float:
        """Fraction of placements that ran physics."""
        total = self.count_fast + self.count_physics
        return self.count_physics / total if total else 0.0
