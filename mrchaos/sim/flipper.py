"""The flip fixture: a motorised hinged plate that turns a piece over for the robot.

A suction cup from above cannot turn a piece over. The fixture stands on the table beside the
camera's view (on the -x side): a plate on a hinge along y, held level at the height where a
half turn brings a piece's far face down onto the table just past the hinge (the *pad*). The
arm sets the piece on the plate; the plate's own suction (a weld, like the cup's) holds it; a
position actuator swings the plate half a turn over the hinge; the suction lets go, the piece
drops the last millimetres onto the pad, mirrored, and the plate swings back. The arm then
picks the piece up again. MuJoCo decides what happens throughout; :meth:`Flipper.flip` reports
a piece that did not end flat, upside down, where the half turn puts it.

Geometry: a point (x, z) on the plate goes to (2 hx - x, 2 h - z), where hx is the hinge's x and
h its height, and a body at yaw phi ends turned over at yaw -phi (orientation Rz(-phi) Ry(pi)).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import mujoco
import mujoco.batch
import numpy as np

from mrchaos.core.geometry import angle_gap, fit_pose
from mrchaos.core.raster import View
from mrchaos.figures.pieces import Piece, PieceSet
from mrchaos.sim.executor import min_jerk, weld_here

__all__ = ["FlipperConfig", "FlipperGeometry", "Flipper", "attach_flipper", "flipper_geometry", "landing_error"]


@dataclass(frozen=True)
class FlipperConfig:
    """The flip fixture's build and motion (metres, seconds).

    Attributes:
        y: the plate's centre line in y.
        gap: how far above the pad a piece of the thickest kind is let go.
        plate_thickness: of the plate.
        margin: the pad's near edge stays this far outside the camera's view.
        swing: duration of each half turn (minimum-jerk).
        settle: pause after the release, and after the return.
        kp, damping: the hinge actuator's stiffness (N m / rad) and damping (N m s / rad).
        tolerance: a flipped piece further than this (m) from where the half turn puts it (lost
            off the pad), or tilted more than ``tilt`` (rad) from lying upside down, failed; the
            arm picks a piece up from wherever it lies, so a smaller slide costs nothing.
        tilt: see ``tolerance``.
    """

    y: float = -0.05
    gap: float = 0.001
    plate_thickness: float = 0.004
    margin: float = 0.03
    swing: float = 0.8
    settle: float = 0.25
    kp: float = 20.0
    damping: float = 1.0
    tolerance: float = 0.02
    tilt: float = math.radians(3.0)


@dataclass(frozen=True)
class FlipperGeometry:
    """Where the fixture stands for one piece set and view: hinge line x, plate centre (x, y),
    hinge height, plate side length and the plate's top surface height."""

    hinge_x: float
    y: float
    height: float
    side: float
    top: float

    @property
    def plate_centre(self) -> np.ndarray:
        """(x, y) of the plate's centre, where the arm sets a piece down."""
        return np.array([self.hinge_x - self.side / 2, self.y])

    def flipped_pose(self, pose: np.ndarray) -> np.ndarray:
        """Planar pose (..., 3) of a piece on the plate -> where the half turn lays it on the pad
        (its yaw as a turned-over piece)."""
        pose = np.asarray(pose, dtype=np.float64)
        return np.stack([2 * self.hinge_x - pose[..., 0], pose[..., 1], -pose[..., 2]], -1)


def flipper_geometry(piece_set: PieceSet, view: View, cfg: FlipperConfig = FlipperConfig()) -> FlipperGeometry:
    """The fixture's placement: a plate wide enough for the set's largest piece, its pad just
    outside the view, hinged so that a half turn lays the thickest piece ``gap`` above the pad."""
    side = 2 * max(p.radius for p in piece_set.pieces) + 0.02
    hinge_x = -view.extent / 2 - cfg.margin - side
    thick = max(p.thickness for p in piece_set.pieces)
    height = cfg.gap + thick + cfg.plate_thickness / 2
    return FlipperGeometry(hinge_x, cfg.y, height, side, height + cfg.plate_thickness / 2)


def attach_flipper(
    spec: mujoco.MjSpec,
    piece_bodies: list[str],
    geometry: FlipperGeometry,
    cfg: FlipperConfig = FlipperConfig(),
    weld_solref: tuple[float, float] = (0.004, 1.0),
) -> None:
    """Add the fixture to a scene spec: a bracket, the hinged plate with its position actuator,
    and one weld per piece (the plate's suction, off by default)."""
    g = geometry
    bracket = spec.worldbody.add_body(name="flipper_bracket", pos=[g.hinge_x, g.y, g.height])
    bracket.add_geom(
        name="flipper_bracket_visual",
        type=mujoco.mjtGeom.mjGEOM_CYLINDER,
        size=[0.004, g.side / 2, 0],
        quat=[math.cos(math.pi / 4), math.sin(math.pi / 4), 0, 0],
        contype=0,
        conaffinity=0,
        group=2,
        density=0,
        rgba=[0.3, 0.3, 0.3, 1],
    )
    plate = bracket.add_body(name="flipper_plate")
    plate.add_joint(
        name="flipper_hinge",
        type=mujoco.mjtJoint.mjJNT_HINGE,
        axis=[0, 1, 0],
        range=[-0.1, math.pi + 0.1],
        damping=0.0,
        armature=0.001,
    )
    plate.add_geom(
        name="flipper_plate",
        type=mujoco.mjtGeom.mjGEOM_BOX,
        size=[g.side / 2, g.side / 2, cfg.plate_thickness / 2],
        pos=[-g.side / 2, 0, 0],
        mass=0.05,
        group=3,
        contype=1,
        conaffinity=1,
        friction=[0.8, 0.005, 0.0001],
        rgba=[0.7, 0.7, 0.75, 1],
    )
    plate.add_site(name="flipper_plate_centre", pos=[-g.side / 2, 0, cfg.plate_thickness / 2], size=[0.003, 0, 0])
    spec.add_actuator(
        name="flipper_hinge",
        trntype=mujoco.mjtTrn.mjTRN_JOINT,
        target="flipper_hinge",
        gaintype=mujoco.mjtGain.mjGAIN_FIXED,
        gainprm=[cfg.kp] + [0] * 9,
        biastype=mujoco.mjtBias.mjBIAS_AFFINE,
        biasprm=[0, -cfg.kp, -cfg.damping] + [0] * 7,
        ctrlrange=[-0.1, math.pi + 0.1],
    )
    for name in piece_bodies:
        spec.add_equality(
            name=f"flipper_{name}",
            type=mujoco.mjtEq.mjEQ_WELD,
            objtype=mujoco.mjtObj.mjOBJ_BODY,
            name1="flipper_plate",
            name2=name,
            active=False,
            solref=list(weld_solref),
        )


class Flipper:
    """Drives the fixture in the worlds of a persistent ``mujoco.batch.Batch``.

    Args:
        batch: the worlds.
        model: their model, holding the fixture (see :func:`attach_flipper`).
        piece_bodies: body id of every piece, in piece-set order.
        geometry: where the fixture stands.
        cfg: its motion and tolerances.
    """

    def __init__(
        self,
        batch: mujoco.batch.Batch,
        model: mujoco.MjModel,
        piece_bodies: np.ndarray,
        geometry: FlipperGeometry,
        cfg: FlipperConfig = FlipperConfig(),
    ) -> None:
        self.batch, self.geometry, self.cfg = batch, geometry, cfg
        self.piece_bodies = np.asarray(piece_bodies)
        self.dt = model.opt.timestep
        self.plate = model.body("flipper_plate").id
        self.actuator = model.actuator("flipper_hinge").id
        self.welds = np.array([model.equality(f"flipper_{model.body(b).name}").id for b in self.piece_bodies])
        self.ctrl = batch.bind("ctrl")
        self.eq_active = batch.bind("eq_active")
        self.xpos = batch.bind("xpos")
        self.xquat = batch.bind("xquat")
        #: simulated seconds summed over worlds (for throughput figures).
        self.simulated_seconds = 0.0

    def _swing(self, rows: np.ndarray, start: float, end: float, seconds: float) -> None:
        n = max(1, round(seconds / self.dt))
        control = np.repeat(self.ctrl[rows][:, None], n, 1)
        control[:, :, self.actuator] = start + (end - start) * min_jerk(n)[None]
        self.batch.rollout(
            nstep=n, control=control, control_spec=int(mujoco.mjtState.mjSTATE_CTRL), record=["qpos"], ids=rows
        )
        self.ctrl[rows] = control[:, -1]
        self.simulated_seconds += n * self.dt * len(rows)

    def flip(self, rows: np.ndarray, piece: np.ndarray, on_plate: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Turn ``piece[i]`` of world ``rows[i]``, lying on the plate at planar ``on_plate[i]``, over onto
        the pad. Returns where it should now lie, (m, 3) turned-over poses, and (m,) bool success:
        it lies upside down and flat, within the tolerance of that pose."""
        cfg = self.cfg
        body = self.piece_bodies[piece]
        eq = self.welds[piece]
        weld_here(self.batch, rows, eq, self.plate, body)
        self._swing(rows, 0.0, math.pi, cfg.swing)
        self.eq_active[rows, eq] = 0.0
        self._swing(rows, math.pi, math.pi, cfg.settle)
        self._swing(rows, math.pi, 0.0, cfg.swing)
        self._swing(rows, 0.0, 0.0, cfg.settle)
        self.batch.forward(ids=rows)
        expect = self.geometry.flipped_pose(on_plate)
        q = self.xquat[rows, body]
        up = 1 - 2 * (q[:, 1] ** 2 + q[:, 2] ** 2)  # the body's z axis, world z component
        near = np.linalg.norm(self.xpos[rows, body][:, :2] - expect[:, :2], axis=1) < cfg.tolerance
        return expect, near & (up < -math.cos(cfg.tilt))


def landing_error(
    piece: Piece, footprints: np.ndarray, pose: np.ndarray, mirrored: bool = True
) -> tuple[np.ndarray, np.ndarray]:
    """How far convex pieces landed from commanded centroid poses (m, 3): (m,) distance (m) and (m,) angle
    (rad, modulo the piece's symmetry), infinite where a piece does not lie flat on the given face.

    ``footprints`` (m, V', 2) are the pieces' top-down outlines (padded, as the worlds keep them);
    a tilted piece's outline is a hull with more corners than the piece, so it does not fit.
    """
    import shapely

    dist, angle = np.full(len(pose), np.inf), np.full(len(pose), np.inf)
    for i, fp in enumerate(footprints):
        hull = shapely.MultiPoint(fp).convex_hull
        v = np.asarray(hull.exterior.coords)[:-1] if hull.geom_type == "Polygon" else np.zeros((0, 2))
        if len(v) != len(piece.outline):
            continue
        fit = fit_pose(piece.outline, v, piece.mirrored_outline())
        if fit.mirrored == mirrored and fit.residual < 1e-4:
            dist[i] = np.linalg.norm(fit.pose[:2] - pose[i, :2])
            angle[i] = angle_gap(fit.pose[2], pose[i, 2], piece.symmetry_period)
    return dist, angle
