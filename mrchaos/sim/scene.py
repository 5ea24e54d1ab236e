"""The MuJoCo scene of a piece set: table, one free prism body per piece, cameras, staging area.

The MJCF follows MuJoCo Menagerie's conventions: ``visual`` and ``collision``
default classes, sites named for what they mark, and a ``home`` keyframe in which
every piece waits in the staging area beside the table, outside the camera view.
The scene is generated from the piece set, so a new part set needs no scene edits.

World frame: the table top is z = 0, the workspace is centred on the origin, and
the cameras look straight down from 0.25 m.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import mujoco
import numpy as np

from mrchaos.core.geometry import polygon_area
from mrchaos.core.raster import View
from mrchaos.figures.pieces import PieceSet
from mrchaos.sim.flipper import FlipperConfig, attach_flipper, flipper_geometry
from mrchaos.sim.robot import Robot, RobotConfig, attach_robot

__all__ = ["SceneConfig", "build_scene_xml", "build_model", "staging_poses", "CAMERA_HEIGHT"]

#: Height of the reference camera above the table (m).
CAMERA_HEIGHT = 0.25
#: Vertical field of view of the reference camera (deg).
CAMERA_FOVY = 55.37


@dataclass(frozen=True)
class SceneConfig:
    """Physical parameters of the scene.

    Attributes:
        timestep: physics step (s).
        friction: sliding friction of piece-piece and piece-table contacts.
        density: piece density (kg/m^3), plywood-like.
        staging_x: x of the staging row's first slot (m), outside the camera view.
        staging_pitch: spacing of staging slots along y (m).
        sleep_tolerance: MuJoCo puts resting pieces to sleep below this velocity, so
            the pieces waiting in the staging area and those settled cost nothing
            until something touches them (about 5x faster settling here).
    """

    timestep: float = 0.002
    friction: float = 0.5
    density: float = 600.0
    staging_x: float = 0.32
    staging_pitch: float = 0.09
    sleep_tolerance: float = 1e-4


def staging_poses(piece_set: PieceSet, cfg: SceneConfig = SceneConfig(), view: View | None = None) -> np.ndarray:
    """(P, 3) planar poses of the staging slots: pieces in two columns beside the table, outside
    the camera ``view``."""
    p = len(piece_set)
    rows = math.ceil(p / 2)
    # Slots grow with the pieces (lying at angle 0) when the configured pitch is too tight.
    lo = np.min([pc.outline.min(0) for pc in piece_set.pieces], 0)
    hi = np.max([pc.outline.max(0) for pc in piece_set.pieces], 0)
    pitch_x = max(cfg.staging_pitch, hi[0] - lo[0] + 0.01)
    pitch_y = max(cfg.staging_pitch, hi[1] - lo[1] + 0.01)
    x0 = max(cfg.staging_x, view.extent / 2 - lo[0] + 0.02) if view is not None else cfg.staging_x
    out = np.zeros((p, 3))
    for i in range(p):
        col, row = divmod(i, rows)
        out[i] = [x0 + col * pitch_x, (row - (rows - 1) / 2) * pitch_y, 0.0]
    return out


def _prism_vertices(outline: np.ndarray, thickness: float) -> np.ndarray:
    lo = np.c_[outline, np.full(len(outline), -thickness / 2)]
    hi = np.c_[outline, np.full(len(outline), thickness / 2)]
    return np.concatenate([lo, hi])


def _fmt(a: np.ndarray) -> str:
    return " ".join(f"{v:.7g}" for v in np.asarray(a).ravel())


def _quat_z(theta: float) -> np.ndarray:
    return np.array([math.cos(theta / 2), 0.0, 0.0, math.sin(theta / 2)])


def build_scene_xml(piece_set: PieceSet, cfg: SceneConfig = SceneConfig(), view: View = View()) -> str:
    """MJCF text of the scene."""
    colours = [
        "0.89 0.10 0.11",
        "0.22 0.49 0.72",
        "0.30 0.69 0.29",
        "0.60 0.31 0.64",
        "1.00 0.50 0.00",
        "0.65 0.34 0.16",
        "0.97 0.51 0.75",
        "0.6 0.6 0.6",
    ]
    meshes, bodies = [], []
    stage = staging_poses(piece_set, cfg, view)
    home_qpos = []
    for i, p in enumerate(piece_set.pieces):
        rgba = colours[i % len(colours)] + " 1"
        x, y, th = stage[i]
        z = p.thickness / 2
        # One convex mesh per part (MuJoCo collides convex hulls); a convex piece has one,
        # named after the piece. Mass is shared by area.
        areas = np.array([polygon_area(q) for q in p.convex_parts])
        geoms = []
        for j, (part, a) in enumerate(zip(p.convex_parts, areas, strict=True)):
            name = p.name if j == 0 else f"{p.name}_part{j}"
            meshes.append(f'    <mesh name="{name}" vertex="{_fmt(_prism_vertices(part, p.thickness))}"/>')
            geoms.append(
                f'      <geom name="{name}" class="collision" type="mesh" mesh="{name}" '
                f'mass="{p.mass * a / areas.sum():.6g}"/>'
            )
            geoms.append(f'      <geom name="{name}_visual" class="visual" type="mesh" mesh="{name}" rgba="{rgba}"/>')
        body_geoms = "\n".join(geoms)
        bodies.append(
            f'''    <body name="{p.name}" pos="{x:.6g} {y:.6g} {z:.6g}">
      <freejoint name="{p.name}"/>
{body_geoms}
      <site name="{p.name}_top" pos="0 0 {p.thickness / 2:.6g}" size="0.002"/>
    </body>'''
        )
        home_qpos.append(_fmt(np.r_[x, y, z, _quat_z(th)]))
    half = view.extent / 2
    # Perspective camera of the reference: a 4:3 image whose centre crop is the observation.
    return f'''<mujoco model="mrchaos_{piece_set.name}">
  <compiler angle="radian" autolimits="true"/>
  <option timestep="{cfg.timestep}" integrator="implicitfast" cone="elliptic" impratio="10"
          sleep_tolerance="{cfg.sleep_tolerance}">
    <flag sleep="enable"/>
  </option>
  <visual>
    <global offwidth="640" offheight="480"/>
    <map znear="0.01" zfar="2"/>
  </visual>
  <default>
    <default class="visual">
      <geom contype="0" conaffinity="0" group="2" density="0"/>
    </default>
    <default class="collision">
      <geom group="3" friction="{cfg.friction} 0.005 0.0001" condim="4" solref="0.004 1" solimp="0.95 0.99 0.001"/>
    </default>
  </default>
  <asset>
    <texture name="grid" type="2d" builtin="checker" rgb1="0.85 0.85 0.85" rgb2="0.8 0.8 0.8" width="64" height="64"/>
    <material name="table" texture="grid" texrepeat="8 8"/>
{chr(10).join(meshes)}
  </asset>
  <worldbody>
    <light name="top" pos="0 0 1.5" dir="0 0 -1" directional="true"/>
    <geom name="table" class="collision" type="box" size="0.6 0.45 0.02" pos="0.15 0 -0.02" material="table"
          group="0" contype="1" conaffinity="1"/>
    <site name="workspace_centre" pos="0 0 0" size="0.003"/>
    <site name="view_corner_min" pos="{-half:.6g} {-half:.6g} 0" size="0.002"/>
    <site name="view_corner_max" pos="{half:.6g} {half:.6g} 0" size="0.002"/>
    <site name="staging_area" pos="{cfg.staging_x:.6g} 0 0" size="0.003"/>
    <camera name="overhead" pos="0 0 {CAMERA_HEIGHT}" xyaxes="1 0 0 0 1 0" fovy="{CAMERA_FOVY}"/>
    <camera name="overhead_ortho" pos="0 0 {CAMERA_HEIGHT}" xyaxes="1 0 0 0 1 0" projection="orthographic"
            fovy="{view.extent:.6g}"/>
{chr(10).join(bodies)}
  </worldbody>
  <keyframe>
    <key name="home" qpos="{" ".join(home_qpos)}"/>
  </keyframe>
</mujoco>
'''


def build_model(
    piece_set: PieceSet,
    cfg: SceneConfig = SceneConfig(),
    view: View = View(),
    robot: RobotConfig | None = None,
    flipper: FlipperConfig | None = None,
) -> mujoco.MjModel:
    """Compile the scene of a piece set, with the UR5e and its suction cup when ``robot`` is given,
    and the flip fixture (:mod:`mrchaos.sim.flipper`) when ``flipper`` is given too.

    With a robot, the ``home`` keyframe holds the arm at its ready pose (TCP at
    ``robot.ready``, pointing down), with the actuators commanding that pose.
    """
    if robot is None:
        return mujoco.MjModel.from_xml_string(build_scene_xml(piece_set, cfg, view))
    spec = mujoco.MjSpec.from_string(build_scene_xml(piece_set, cfg, view))
    attach_robot(spec, list(piece_set.names), robot)
    if flipper is not None:
        attach_flipper(
            spec, list(piece_set.names), flipper_geometry(piece_set, view, flipper), flipper, robot.weld_solref
        )
    model = spec.compile()
    arm = Robot(model, robot)
    # Elbow up, wrist down: the branch of the UR's usual home posture.
    q, ok = arm.solve(
        np.array([robot.ready]), np.array([0.0]), np.array([[0.0, -1.5708, 1.5708, -1.5708, -1.5708, 0.0]])
    )
    if not ok[0]:
        raise ValueError(f"robot.ready {robot.ready} is out of the arm's reach from robot.mount {robot.mount}")
    key = spec.key("home")
    qpos = np.array(key.qpos, dtype=np.float64)
    qpos[arm.qadr] = q[0]
    ctrl = np.zeros(model.nu)
    ctrl[arm.actuators] = q[0]
    key.qpos, key.ctrl = qpos.tolist(), ctrl.tolist()
    return spec.compile()
