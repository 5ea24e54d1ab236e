"""The UR5e arm with a suction cup: its place in the scene, and its kinematics there.

:func:`attach_robot` adds the robot to a scene spec by attaching the robot's own MJCF
file (the package's ``data/robots/ur5e.xml`` by default, or MuJoCo Menagerie's
``universal_robots_ur5e/ur5e.xml`` when ``RobotConfig.model`` points at it), then puts a
suction cup on its flange, one weld equality per piece (the suction, off by default),
a touch sensor on the cup's lip and a contact sensor per piece that reports the arm
touching it. :class:`Robot` finds all of that in the compiled model and solves for joint
angles that put the cup's tip at a planar pose, pointing down.

Frames: the tool centre point (TCP) is the cup's lip, ``tool_length`` along the flange's
z axis; a tool yaw of 0 means the flange's x axis along the world's x axis.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

import mujoco
import numpy as np

from mrchaos.sim.kinematics import DH, UR5E, fk, ik, pose_matrix

__all__ = ["RobotConfig", "Robot", "attach_robot", "default_robot_model"]

_JOINTS = (
    "shoulder_pan_joint",
    "shoulder_lift_joint",
    "elbow_joint",
    "wrist_1_joint",
    "wrist_2_joint",
    "wrist_3_joint",
)


def default_robot_model() -> Path:
    """The package's UR5e MJCF file."""
    return Path(str(resources.files("mrchaos") / "data" / "robots" / "ur5e.xml"))


@dataclass(frozen=True)
class RobotConfig:
    """Where the robot stands and how its tool is built.

    Attributes:
        model: path of a UR5e MJCF file; empty for the package's own. MuJoCo Menagerie's
            ``universal_robots_ur5e/ur5e.xml`` (``robot_descriptions`` fetches it) works too.
        mount: (x, y, z) of the robot's base on the table (m): beside the workspace, on the
            staging side, so every piece and every target is in reach with the tool down.
        mount_yaw: base rotation about z (rad).
        tool_length: flange to suction lip (m).
        cup_radius: radius of the suction lip (m); small enough for the smallest piece.
        ready: (x, y, z) of the TCP between placements (m), outside the camera's view.
        weld_solref: time constant and damping ratio of the suction weld.
    """

    model: str = ""
    mount: tuple[float, float, float] = (0.16, -0.40, 0.0)
    mount_yaw: float = math.pi / 2
    tool_length: float = 0.10
    cup_radius: float = 0.010
    ready: tuple[float, float, float] = (0.30, -0.20, 0.25)
    weld_solref: tuple[float, float] = (0.004, 1.0)

    def model_path(self) -> Path:
        """The robot MJCF file to attach."""
        path = Path(self.model) if self.model else default_robot_model()
        if not path.is_file():
            raise FileNotFoundError(f"robot model {path}: no such file (robot.model in the config)")
        return path


_PREFIX = "ur5e/"


def _yaw_quat(yaw: float) -> list[float]:
    return [math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)]


def attach_robot(spec: mujoco.MjSpec, piece_bodies: list[str], cfg: RobotConfig = RobotConfig()) -> None:
    """Attach the robot, its suction cup, the suction welds and the sensors to a scene spec.

    Call :func:`set_home` on the compiled model's spec afterwards (done by
    :func:`mrchaos.sim.scene.build_model`) so the ``home`` keyframe holds the arm's ready pose.
    """
    path = cfg.model_path()
    try:
        robot = mujoco.MjSpec.from_file(str(path))
    except Exception as e:  # MuJoCo's own message names the line
        raise ValueError(f"robot model {path}: {e}") from None
    missing = [j for j in _JOINTS if robot.joint(j) is None]
    if missing or robot.body("base") is None:
        raise ValueError(f"robot model {path}: not a UR arm with Menagerie's names (missing {missing or 'base'})")
    frame = spec.worldbody.add_frame(pos=list(cfg.mount), quat=_yaw_quat(cfg.mount_yaw))
    frame.attach_body(robot.body("base"), _PREFIX, "")
    # The flange: the package model and newer Menagerie files mark it with a site; older
    # Menagerie files end at wrist_3_link, whose flange is 0.1 m along its y axis.
    site = spec.site(_PREFIX + "attachment_site")
    if site is not None:
        parent, pos, quat = site.parent, list(site.pos), list(site.quat)
    else:
        parent, pos, quat = spec.body(_PREFIX + "wrist_3_link"), [0.0, 0.1, 0.0], [-1.0, 1.0, 0.0, 0.0]
    cup = parent.add_body(name="suction_cup", pos=pos, quat=quat)
    shaft = cfg.tool_length - 0.02
    cup.add_geom(
        name="cup_shaft",
        type=mujoco.mjtGeom.mjGEOM_CYLINDER,
        size=[0.02, shaft / 2, 0],
        pos=[0, 0, shaft / 2],
        contype=2,
        conaffinity=1,
        group=3,
        density=0,
        rgba=[0.2, 0.2, 0.2, 1],
    )
    cup.add_geom(
        name="cup_lip",
        type=mujoco.mjtGeom.mjGEOM_CYLINDER,
        size=[cfg.cup_radius, 0.01, 0],
        pos=[0, 0, cfg.tool_length - 0.01],
        contype=2,
        conaffinity=1,
        group=3,
        density=0,
        rgba=[0.1, 0.1, 0.1, 1],
        friction=[1.0, 0.005, 0.0001],
    )
    cup.add_geom(
        name="cup_visual",
        type=mujoco.mjtGeom.mjGEOM_CYLINDER,
        size=[0.02, cfg.tool_length / 2, 0],
        pos=[0, 0, cfg.tool_length / 2],
        contype=0,
        conaffinity=0,
        group=2,
        density=0,
        rgba=[0.15, 0.15, 0.15, 1],
    )
    cup.add_site(name="tcp", pos=[0, 0, cfg.tool_length], size=[0.003, 0, 0])
    # Contacts on the lip's face count as a seal; the site is the face's thin slab.
    cup.add_site(
        name="cup_touch",
        type=mujoco.mjtGeom.mjGEOM_BOX,
        pos=[0, 0, cfg.tool_length],
        size=[cfg.cup_radius + 0.002, cfg.cup_radius + 0.002, 0.002],
    )
    spec.add_sensor(
        name="cup_touch", type=mujoco.mjtSensor.mjSENS_TOUCH, objtype=mujoco.mjtObj.mjOBJ_SITE, objname="cup_touch"
    )
    for name in piece_bodies:
        spec.add_equality(
            name=f"suction_{name}",
            type=mujoco.mjtEq.mjEQ_WELD,
            objtype=mujoco.mjtObj.mjOBJ_BODY,
            name1="suction_cup",
            name2=name,
            active=False,
            solref=list(cfg.weld_solref),
        )
        spec.add_sensor(
            name=f"arm_contact_{name}",
            type=mujoco.mjtSensor.mjSENS_CONTACT,
            objtype=mujoco.mjtObj.mjOBJ_XBODY,
            objname=_PREFIX + "base",
            reftype=mujoco.mjtObj.mjOBJ_BODY,
            refname=name,
            intprm=[1, 0, 1],
        )
    for key in list(spec.keys):
        if key.name != "home":
            spec.delete(key)


class Robot:
    """The robot in a compiled scene: addresses, calibrated kinematics and TCP inverse kinematics.

    The analytic UR inverse is exact for the package's model. For another UR5e model
    (Menagerie's differs from the DH table by up to a millimetre) the DH base is found
    by calibration and each analytic solution is refined by damped least squares on the
    model's own forward kinematics.
    """

    def __init__(self, model: mujoco.MjModel, cfg: RobotConfig = RobotConfig(), dh: DH = UR5E) -> None:
        self.model, self.cfg, self.dh = model, cfg, dh
        self.joint_ids = np.array([model.joint(_PREFIX + j).id for j in _JOINTS])
        self.qadr = model.jnt_qposadr[self.joint_ids]
        self.dofadr = model.jnt_dofadr[self.joint_ids]
        self.actuators = np.array([self._actuator_of(j) for j in self.joint_ids])
        self.tcp_site = model.site("tcp").id
        self.cup_body = model.body("suction_cup").id
        self.lower = model.jnt_range[self.joint_ids, 0]
        self.upper = model.jnt_range[self.joint_ids, 1]
        self._data = mujoco.MjData(model)
        self._calibrate()

    def _actuator_of(self, joint: int) -> int:
        ids = np.flatnonzero(
            (self.model.actuator_trnid[:, 0] == joint) & (self.model.actuator_trntype == mujoco.mjtTrn.mjTRN_JOINT)
        )
        if len(ids) != 1:
            raise ValueError(f"robot model: joint {self.model.joint(joint).name} needs exactly one position actuator")
        return int(ids[0])

    # ------------------------------------------------------------ kinematics
    def tcp_pose(self, q: np.ndarray) -> np.ndarray:
        """TCP pose (4, 4) in the world for arm joint angles q (6,), from the model."""
        d = self._data
        d.qpos[self.qadr] = q
        mujoco.mj_kinematics(self.model, d)
        return pose_matrix(d.site_xpos[self.tcp_site].copy(), d.site_xmat[self.tcp_site].reshape(3, 3).copy())

    def _calibrate(self) -> None:
        """Find the DH base frame and the flange-to-TCP transform in this model.

        The base's yaw about the first joint's axis is searched on a grid, then the TCP
        offset follows from one configuration; the rest are checked against the model.
        """
        rng = np.random.default_rng(0)
        qs = rng.uniform(-1.5, 1.5, (6, 6))
        qs[:, 2] = rng.uniform(0.5, 2.0, 6)
        s = np.stack([self.tcp_pose(q) for q in qs])
        f = fk(qs, self.dh)
        d = self._data
        d.qpos[self.qadr] = 0.0
        mujoco.mj_kinematics(self.model, d)
        j1, j2 = self.joint_ids[:2]
        z = d.xaxis[j1].copy()
        # Frame 1's origin is where the first two axes meet; frame 0 lies d1 below it.
        meet = d.xanchor[j1] + z * ((d.xanchor[j2] - d.xanchor[j1]) @ z)
        origin = meet - z * self.dh.d[0]
        x0 = np.cross(z, [0.0, 1.0, 0.0] if abs(z[1]) < 0.9 else [1.0, 0.0, 0.0])
        x0 /= np.linalg.norm(x0)
        y0 = np.cross(z, x0)
        best: tuple[float, np.ndarray | None, np.ndarray | None] = (np.inf, None, None)
        for yaw in np.linspace(0, 2 * np.pi, 720, endpoint=False):
            x = math.cos(yaw) * x0 + math.sin(yaw) * y0
            base = pose_matrix(origin, np.stack([x, np.cross(z, x), z], -1))
            tool = np.linalg.inv(base @ f[0]) @ s[0]
            err = np.abs(base @ f @ tool - s)[:, :3, :].max()
            if err < best[0]:
                best = (err, base, tool)
        # Zoom in on the grid's best yaw until the base is exact or stops improving.
        step = 2 * np.pi / 720
        for _ in range(8):
            if best[0] < 1e-11:
                break
            centre = best[1]
            for yaw in np.linspace(-step, step, 101):
                c, sn = math.cos(yaw), math.sin(yaw)
                base = centre @ np.array([[c, -sn, 0, 0], [sn, c, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]])
                tool = np.linalg.inv(base @ f[0]) @ s[0]
                err = np.abs(base @ f @ tool - s)[:, :3, :].max()
                if err < best[0]:
                    best = (err, base, tool)
            step /= 50
        err, best_base, best_tool = best
        if best_base is None or best_tool is None or err > 0.01:
            raise ValueError(
                f"robot model {self.cfg.model_path()}: its kinematics are not a UR5e's "
                f"(best calibration error {err:.3g})"
            )
        self.base: np.ndarray = best_base
        self.tool: np.ndarray = best_tool
        self.exact: bool = bool(err < 1e-9)
        self._base_inv: np.ndarray = np.linalg.inv(best_base)
        self._tool_inv: np.ndarray = np.linalg.inv(best_tool)

    def solve(self, pos: np.ndarray, yaw: np.ndarray, ref: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Joint angles (n, 6) putting the TCP at world ``pos`` (n, 3), pointing down, turned by ``yaw`` (n,).

        ``ref`` (n, 6) picks the branch (nearest solution). Returns ``(q, ok)``.
        """
        pos = np.atleast_2d(pos)
        yaw = np.atleast_1d(yaw)
        c, s = np.cos(yaw), np.sin(yaw)
        rot = np.zeros((len(yaw), 3, 3))
        # Tool z down; tool x along the world direction `yaw`.
        rot[:, 0, 0], rot[:, 1, 0] = c, s
        rot[:, 0, 1], rot[:, 1, 1] = s, -c
        rot[:, 2, 2] = -1.0
        target = self._base_inv @ pose_matrix(pos, rot) @ self._tool_inv
        q, ok = ik(target, ref, self.dh)
        ok &= ((q >= self.lower) & (q <= self.upper)).all(-1)
        if not self.exact:
            for i in np.flatnonzero(ok):
                q[i], ok[i] = self._refine(q[i], pose_matrix(pos[i], rot[i]))
        return q, ok

    def _refine(self, q: np.ndarray, target: np.ndarray, iters: int = 20) -> tuple[np.ndarray, bool]:
        """Damped least squares on the model's kinematics, from the analytic solution."""
        m, d = self.model, self._data
        jacp, jacr = np.zeros((3, m.nv)), np.zeros((3, m.nv))
        for _ in range(iters):
            cur = self.tcp_pose(q)
            dp = target[:3, 3] - cur[:3, 3]
            r = target[:3, :3] @ cur[:3, :3].T
            dr = 0.5 * np.array([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]])
            if np.abs(dp).max() < 1e-6 and np.abs(dr).max() < 1e-5:
                return q, True
            mujoco.mj_comPos(m, d)  # the Jacobian needs the joint axes in the com frame
            mujoco.mj_jacSite(m, d, jacp, jacr, self.tcp_site)
            jac = np.r_[jacp[:, self.dofadr], jacr[:, self.dofadr]]
            err = np.r_[dp, dr]
            q = q + jac.T @ np.linalg.solve(jac @ jac.T + 1e-6 * np.eye(6), err)
        return q, bool(np.abs(dp).max() < 1e-4)
