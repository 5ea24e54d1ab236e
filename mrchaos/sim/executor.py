"""Robot-executed placement: the UR5e picks a piece with suction and places it, in every world at once.

For piece t of each world the executor (1) moves the cup above the piece where it lies,
(2) descends until the lip touches and switches suction on, a weld at the pose the
cup holds the piece in, (3) lifts, carries the piece above the target and turns it to
the commanded angle, (4) lowers it to just above the surface beneath, (5) switches
suction off and returns to the ready pose. Joint targets come from inverse kinematics
on Cartesian waypoints, interpolated with minimum-jerk timing, and are tracked by the
arm's position actuators; MuJoCo decides what happens to the pieces. All worlds of a
call run the same phase timeline in ``mujoco.batch`` rollouts.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import mujoco
import mujoco.batch
import numpy as np

from mrchaos.sim.robot import Robot

__all__ = ["ExecutorConfig", "Executor", "ExecutionResult", "min_jerk", "weld_here"]


@dataclass(frozen=True)
class ExecutorConfig:
    """Timing and margins of a pick-and-place (seconds, metres).

    Attributes:
        clearance: travel height of the piece's underside above the tallest piece in the world.
        press: the cup descends this far below the piece's top face, so the lip seals.
        release_gap: the piece is released with its underside this far above the surface.
        approach, descend, lift, transfer, lower, retract: durations of the motions.
        seal, release: pauses for the suction to seal and the piece to drop.
        waypoints: Cartesian waypoints per motion (inverse kinematics at each).
        max_joint_speed: a motion takes longer than its nominal duration when its
            minimum-jerk peak would exceed this joint speed (rad/s; the UR5e's limit is pi).
        drop_tolerance: a piece further than this from where the cup holds it was dropped.
    """

    clearance: float = 0.04
    press: float = 0.001
    release_gap: float = 0.002
    approach: float = 0.7
    descend: float = 0.25
    seal: float = 0.1
    lift: float = 0.25
    transfer: float = 0.9
    lower: float = 0.3
    release: float = 0.1
    retract: float = 0.7
    waypoints: int = 8
    max_joint_speed: float = 2.0
    drop_tolerance: float = 0.01


@dataclass
class ExecutionResult:
    """Outcome of a robot placement per world of the call (all (m,) bool).

    Attributes:
        unreachable: a waypoint had no inverse-kinematics solution; the arm did not move.
        missed: the lip never touched the piece, so suction did not attach.
        dropped: the piece was not on the cup when it reached the target.
        collision: the arm or cup touched a piece other than the one it carried.
        flip_failed: a piece to be turned over did not lie flat and upside down where the flip
            fixture's half turn puts it (see :mod:`mrchaos.sim.flipper`); all False otherwise.
    """

    unreachable: np.ndarray
    missed: np.ndarray
    dropped: np.ndarray
    collision: np.ndarray
    flip_failed: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.flip_failed is None:
            self.flip_failed = np.zeros_like(self.unreachable)


def min_jerk(n: int) -> np.ndarray:
    """(n,) progress in (0, 1] of a minimum-jerk motion sampled at n equal steps."""
    t = (np.arange(1, n + 1)) / n
    return 10 * t**3 - 15 * t**4 + 6 * t**5


def _quat_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    w1, x1, y1, z1 = np.moveaxis(a, -1, 0)
    w2, x2, y2, z2 = np.moveaxis(b, -1, 0)
    return np.stack(
        [
            w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
            w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
            w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
            w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
        ],
        -1,
    )


def _quat_conj(q: np.ndarray) -> np.ndarray:
    return q * np.array([1.0, -1.0, -1.0, -1.0])


def _rotate(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    qv = np.concatenate([np.zeros(v.shape[:-1] + (1,)), v], -1)
    return _quat_mul(_quat_mul(q, qv), _quat_conj(q))[..., 1:]


def weld_here(batch: mujoco.batch.Batch, rows: np.ndarray, eq: np.ndarray, holder: int, body: np.ndarray) -> None:
    """Switch on weld equality ``eq[i]`` of world ``rows[i]``, holding ``body[i]`` to ``holder`` at the
    relative pose they have now (a suction that takes hold)."""
    xpos, xquat = batch.bind("xpos"), batch.bind("xquat")
    p1, q1 = xpos[rows, holder], xquat[rows, holder]
    p2, q2 = xpos[rows, body], xquat[rows, body]
    inv = _quat_conj(q1)
    eq_data = batch.expand("eq_data")
    data = eq_data[rows, eq]
    data[:, 0:3] = 0.0  # anchor at the piece's origin
    data[:, 3:6] = _rotate(inv, p2 - p1)
    data[:, 6:10] = _quat_mul(inv, q2)
    data[:, 10] = 1.0
    eq_data[rows, eq] = data
    batch.bind("eq_active")[rows, eq] = 1.0


class Executor:
    """Pick-and-place by the UR5e in the worlds of a persistent ``mujoco.batch.Batch``.

    Args:
        batch: the worlds (the model must hold the robot, see :func:`mrchaos.sim.robot.attach_robot`).
        robot: the robot in that model.
        piece_bodies: body id of every piece, in piece-set order.
        thickness: (P,) piece thicknesses (m).
        period: (P,) rotational symmetry period of every piece (rad); the cup turns to the
            equivalent target angle nearest the piece's current one.
    """

    def __init__(
        self,
        batch: mujoco.batch.Batch,
        robot: Robot,
        piece_bodies: np.ndarray,
        thickness: np.ndarray,
        period: np.ndarray,
        cfg: ExecutorConfig = ExecutorConfig(),
    ) -> None:
        self.batch, self.robot, self.cfg = batch, robot, cfg
        m = robot.model
        self.dt = m.opt.timestep
        self.piece_bodies = np.asarray(piece_bodies)
        self.thickness = np.asarray(thickness, dtype=np.float64)
        self.period = np.asarray(period, dtype=np.float64)
        self.qpos = batch.bind("qpos")
        self.ctrl = batch.bind("ctrl")
        self.eq_active = batch.bind("eq_active")
        self.eq_data = batch.expand("eq_data")
        self.xpos = batch.bind("xpos")
        self.xquat = batch.bind("xquat")
        self.welds = np.array([m.equality(f"suction_{m.body(b).name}").id for b in self.piece_bodies])
        self.touch_adr = m.sensor_adr[m.sensor("cup_touch").id]
        self.contact_adr = np.array(
            [m.sensor_adr[m.sensor(f"arm_contact_{m.body(b).name}").id] for b in self.piece_bodies]
        )
        self.piece_qadr = m.jnt_qposadr[m.body_jntadr[self.piece_bodies]]
        self.ready = np.asarray(m.key("home").qpos)[robot.qadr]
        self.nu = m.nu
        kp = m.actuator_gainprm[robot.actuators, 0]
        self._lead = m.dof_damping[robot.dofadr] / kp
        self._spec = int(mujoco.mjtState.mjSTATE_CTRL)
        #: Snapshots of the state per simulated second kept for recordings (0: none), and
        #: the snapshots themselves: world -> list of qpos, emptied by :meth:`take_snapshots`.
        self.capture_fps = 0.0
        self.snapshots: dict[int, list[np.ndarray]] = {}
        #: simulated seconds summed over worlds (for throughput figures).
        self.simulated_seconds = 0.0

    # ------------------------------------------------------------- planning
    def _path(
        self, q0: np.ndarray, start: np.ndarray, end: np.ndarray, yaw0: np.ndarray, yaw1: np.ndarray, seconds: float
    ) -> tuple[np.ndarray, np.ndarray]:
        """Joint targets per substep (m, nstep, 6) of a straight TCP motion, and whether it is reachable."""
        k = self.cfg.waypoints
        qs, ok, q = [q0], np.ones(len(q0), dtype=bool), q0
        for s in np.linspace(0, 1, k + 1)[1:]:
            q, good = self.robot.solve(start + (end - start) * s, yaw0 + (yaw1 - yaw0) * s, q)
            ok &= good
            qs.append(q)
        return self._timed(np.stack(qs, 1), seconds), ok

    def _joint_path(self, q0: np.ndarray, q1: np.ndarray, seconds: float) -> np.ndarray:
        return self._timed(np.stack([q0, q1], 1), seconds)

    def _timed(self, way: np.ndarray, seconds: float) -> np.ndarray:
        """Minimum-jerk timing along piecewise-linear joint waypoints (m, K+1, 6) -> (m, nstep, 6).

        Every world of the call shares the timeline, so the slowest motion sets the duration.
        """
        travel = np.abs(np.diff(way, axis=1)).sum(1).max() if len(way) else 0.0
        seconds = max(seconds, 1.875 * travel / self.cfg.max_joint_speed)
        n = max(1, round(seconds / self.dt))
        u = min_jerk(n) * (way.shape[1] - 1)
        i = np.minimum(u.astype(int), way.shape[1] - 2)
        f = (u - i)[None, :, None]
        return way[:, i] * (1 - f) + way[:, i + 1] * f

    def _hold(self, q: np.ndarray, seconds: float) -> np.ndarray:
        return np.repeat(q[:, None], max(1, round(seconds / self.dt)), 1)

    def _run(self, rows: np.ndarray, arm: np.ndarray) -> np.ndarray:
        """Roll out arm joint targets (m, nstep, 6) in the worlds ``rows``; return sensordata (m, nstep, S)."""
        control = np.repeat(self.ctrl[rows][:, None], arm.shape[1], 1)
        # Joint damping resists motion: lead the position command by what it costs, as a
        # velocity feed-forward does on the real controller, so the arm does not lag the plan.
        vel = np.diff(arm, axis=1, prepend=arm[:, :1]) / self.dt
        control[:, :, self.robot.actuators] = arm + vel * self._lead
        record = ["sensordata", "qpos"] if self.capture_fps > 0 else ["sensordata"]
        out = self.batch.rollout(nstep=arm.shape[1], control=control, control_spec=self._spec, record=record, ids=rows)
        self.ctrl[rows] = control[:, -1]
        self.simulated_seconds += arm.shape[1] * self.dt * len(rows)
        if self.capture_fps > 0:
            k = max(1, math.ceil(arm.shape[1] * self.dt * self.capture_fps))
            idx = np.linspace(0, arm.shape[1] - 1, k + 1)[1:].round().astype(int)
            for i, r in enumerate(rows):
                self.snapshots.setdefault(int(r), []).extend(out["qpos"][i, idx])
        return out["sensordata"]

    def take_snapshots(self) -> dict[int, list[np.ndarray]]:
        """The snapshots captured since the last call, by world."""
        snaps, self.snapshots = self.snapshots, {}
        return snaps

    # ------------------------------------------------------------- suction
    def _suction_on(self, rows: np.ndarray, piece: np.ndarray) -> None:
        """Weld each piece to the cup at the relative pose they have now."""
        weld_here(self.batch, rows, self.welds[piece], self.robot.cup_body, self.piece_bodies[piece])

    def _suction_off(self, rows: np.ndarray, piece: np.ndarray) -> None:
        self.eq_active[rows, self.welds[piece]] = 0.0

    # ------------------------------------------------------------- placement
    def execute(
        self, rows: np.ndarray, piece: np.ndarray, pose: np.ndarray, floor: np.ndarray, travel: np.ndarray
    ) -> ExecutionResult:
        """Pick ``piece[i]`` in world ``rows[i]`` and place its centroid at planar ``pose[i]``.

        ``floor`` is the height of the surface under the target (m) and ``travel`` the
        height of the tallest piece in each world (m), for the carry height.
        """
        cfg, m = self.cfg, len(rows)
        body = self.piece_bodies[piece]
        thick = self.thickness[piece]
        # Where the piece lies now: its centroid and yaw, read from the state.
        self.batch.forward(ids=rows)
        src = self.xpos[rows, body]
        qw = self.xquat[rows, body]
        src_yaw = np.arctan2(2 * (qw[:, 0] * qw[:, 3] + qw[:, 1] * qw[:, 2]), 1 - 2 * (qw[:, 2] ** 2 + qw[:, 3] ** 2))
        over = 1 - 2 * (qw[:, 1] ** 2 + qw[:, 2] ** 2) < 0
        if over.any():  # lying turned over (Rz(yaw) Ry(pi)): its x axis points back along -yaw
            src_yaw = np.where(over, src_yaw - math.pi, src_yaw)
        period = self.period[piece]
        dst_yaw = pose[:, 2] + period * np.round((src_yaw - pose[:, 2]) / period)
        top = src[:, 2] + thick / 2
        z_travel = np.maximum(travel, top) + thick + cfg.clearance
        q0 = self.qpos[rows][:, self.robot.qadr]
        above_src = np.c_[src[:, :2], z_travel]
        at_src = np.c_[src[:, :2], top - cfg.press]
        above_dst = np.c_[pose[:, :2], z_travel]
        at_dst = np.c_[pose[:, :2], floor + cfg.release_gap + thick]

        # Plan everything first, so that an unreachable world keeps still throughout.
        approach, ok1 = self._path(q0, self._tcp(q0), above_src, src_yaw, src_yaw, cfg.approach)
        q_above = approach[:, -1]
        descend, ok2 = self._path(q_above, above_src, at_src, src_yaw, src_yaw, cfg.descend)
        q_grip = descend[:, -1]
        lift, ok3 = self._path(q_grip, at_src, above_src, src_yaw, src_yaw, cfg.lift)
        transfer, ok4 = self._path(lift[:, -1], above_src, above_dst, src_yaw, dst_yaw, cfg.transfer)
        lower, ok5 = self._path(transfer[:, -1], above_dst, at_dst, dst_yaw, dst_yaw, cfg.lower)
        q_rel = lower[:, -1]
        up, ok6 = self._path(q_rel, at_dst, above_dst, dst_yaw, dst_yaw, cfg.lift)
        home = self._joint_path(up[:, -1], np.broadcast_to(self.ready, q0.shape), cfg.retract)
        reachable = ok1 & ok2 & ok3 & ok4 & ok5 & ok6
        still = ~reachable

        def plan(*parts: np.ndarray) -> np.ndarray:
            arm = np.concatenate(parts, 1)
            arm[still] = q0[still, None]
            return arm

        contact = np.zeros(m, dtype=bool)
        others = np.ones((m, len(self.piece_bodies)), dtype=bool)
        others[np.arange(m), piece] = False

        def collided(sd: np.ndarray) -> np.ndarray:
            return np.asarray(((sd[:, :, self.contact_adr] > 0) & others[:, None]).any((1, 2)))

        sd = self._run(rows, plan(approach, descend, self._hold(q_grip, cfg.seal)))
        contact |= collided(sd)
        touch = sd[:, -max(1, round(cfg.seal / self.dt)) :, self.touch_adr].max(1) > 0
        grip = touch & reachable
        g = np.flatnonzero(grip)
        if len(g):
            self._suction_on(rows[g], piece[g])
        sd = self._run(rows, plan(lift, transfer, lower, self._hold(q_rel, cfg.release)))
        contact |= collided(sd)
        # The piece should hang under the cup where suction took it.
        self.batch.forward(ids=rows)
        held = np.linalg.norm(self.xpos[rows, body][:, :2] - pose[:, :2], axis=1) < cfg.drop_tolerance
        if len(g):
            self._suction_off(rows[g], piece[g])
        sd = self._run(rows, plan(self._hold(q_rel, cfg.release), up, home))
        contact |= collided(sd)
        return ExecutionResult(unreachable=still, missed=reachable & ~touch, dropped=grip & ~held, collision=contact)

    def _tcp(self, q: np.ndarray) -> np.ndarray:
        return np.stack([self.robot.tcp_pose(qi)[:3, 3] for qi in q])
