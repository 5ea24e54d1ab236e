"""``TangramEnv``: N batched MuJoCo tangram worlds as one TorchRL environment.

Task description:
    Place the pieces of a piece set one at a time, in the set's order, so that the
    assembly covers the silhouette prompt. Each step places piece t at the action's
    pose (teleport placement followed by MuJoCo settling, see :mod:`mrchaos.worlds`).
Observation:
    ``observation`` uint8 (N, 2, H, W): the silhouette I_s stacked on the current
    top-down view I_tc. The step index is not observed.
Action:
    ``action`` int64 (N, 3): indices into the (x, y, theta) grid (``MultiCategorical``).
Reward:
    the coverage of piece t's target slot by piece t (twins take the better slot),
    with the reference's shaping, penetration and angle switches from config.
Randomizations:
    targets from the task sampler (chaos objects, cache, figures); optional action
    noise and camera jitter; the number k of pieces pre-assembled at reset.
Success:
    the episode terminates after the last piece (or after ``horizon`` placements);
    ``info`` carries the per-piece coverage and the whole-figure Final and IoU.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, MultiCategorical, Unbounded
from torchrl.envs import EnvBase

from mrchaos.actions import ActionGrid
from mrchaos.metrics import (
    best_slot_coverage,
    exclusive_slot_coverage,
    final_from_joint,
    gate_angle,
    gate_penetration,
    iou_from_joint,
    joint_counts,
    shape_reward,
)
from mrchaos.observation import ObservationConfig, silhouette_image, view_image
from mrchaos.pieces import get_piece_set
from mrchaos.raster import View, rasterize
from mrchaos.robot import RobotConfig
from mrchaos.scene import SceneConfig
from mrchaos.task import TaskConfig, TaskSampler
from mrchaos.worlds import PhysicsConfig, Worlds

__all__ = ["EnvConfig", "TangramEnv", "ROBOT_FAILURES"]

#: Failure flags of robot placement in the step info (always False with teleport placement).
ROBOT_FAILURES = ("unreachable", "missed", "dropped", "collision")


@dataclass
class EnvConfig:
    """Everything that defines the environment.

    Attributes:
        num_worlds: batch size N.
        piece_set: registered piece-set name.
        view_extent, view_size: camera footprint (m) and image size (px).
        grid_nx, grid_ny, grid_ntheta, grid_half_range: the action grid.
        view_mode, height_levels: current-view encoding (see :mod:`mrchaos.observation`).
        camera: "raster" (fast orthographic rasteriser) or "mujoco" (MuJoCo's renderer).
        placement: "teleport" (pieces are set down at the pose) or "robot" (the UR5e picks
            and places them, see :mod:`mrchaos.executor`).
        robot_model: UR5e MJCF for robot placement; empty for the package's own, or
            MuJoCo Menagerie's ``universal_robots_ur5e/ur5e.xml``.
        settle_steps, release_gap, push_depth, nthread: placement physics (see
            :class:`mrchaos.worlds.PhysicsConfig`).
        reward_shaping, shaping_threshold: coverage below the threshold pays 0 and
            [threshold, 1] is rescaled, for every piece larger than the smallest.
        penetration_gate, penetration_limit: pay 0 when the placed piece ends more than
            the limit (m) inside another.
        twin_slots: "shared" (the paper's: a piece scores the best slot of its twin group,
            even one a twin already fills) or "exclusive" (twins claim slots one each, in
            placement order; for sets of many interchangeable pieces such as soda cans).
        angle_gate, angle_tolerance_deg: pay only when the commanded angle is within the
            tolerance of the covered slot's angle, modulo the piece's symmetry.
        action_noise_xy, action_noise_theta: std of Gaussian noise on the placement pose (m, rad).
        camera_jitter: std of a per-step shift of the observed view (m); rewards use the true view.
        task: where targets come from.
    """

    num_worlds: int = 16
    piece_set: str = "tangram7"
    view_extent: float = 0.26
    view_size: int = 120
    grid_nx: int = 51
    grid_ny: int = 51
    grid_ntheta: int = 8
    grid_half_range: float = 0.10
    view_mode: str = "binary"
    height_levels: int = 3
    camera: str = "raster"
    placement: str = "teleport"
    robot_model: str = ""
    settle_steps: int = 20
    release_gap: float = 0.002
    push_depth: float = 0.001
    nthread: int = 0
    twin_slots: str = "shared"
    reward_shaping: bool = False
    shaping_threshold: float = 0.5
    penetration_gate: bool = False
    penetration_limit: float = 0.002
    angle_gate: bool = False
    angle_tolerance_deg: float = 20.0
    action_noise_xy: float = 0.0
    action_noise_theta: float = 0.0
    camera_jitter: float = 0.0
    task: TaskConfig = field(default_factory=TaskConfig)

    def __post_init__(self) -> None:
        if self.camera not in ("raster", "mujoco"):
            raise ValueError(f"env.camera must be 'raster' or 'mujoco', got {self.camera!r}")
        if self.twin_slots not in ("shared", "exclusive"):
            raise ValueError(f"env.twin_slots must be 'shared' or 'exclusive', got {self.twin_slots!r}")
        if self.placement not in ("teleport", "robot"):
            raise ValueError(f"env.placement must be 'teleport' or 'robot', got {self.placement!r}")
        if self.num_worlds < 1:
            raise ValueError(f"env.num_worlds must be >= 1, got {self.num_worlds}")


class TangramEnv(EnvBase):
    """Batched tangram assembly (see the module docstring for the task).

    Args:
        cfg: environment config.
        seed: seed of the env's ``torch.Generator`` (and the numpy generator derived from it).
        figures: optional figures for the task sampler (instead of ``cfg.task.figure_sets``).
    """

    batch_locked = True

    def __init__(self, cfg: EnvConfig = EnvConfig(), seed: int | None = 0, figures=None, device: str = "cpu"):
        super().__init__(device=device, batch_size=torch.Size([cfg.num_worlds]))
        self.cfg = cfg
        self.piece_set = get_piece_set(cfg.piece_set)
        self.view = View(cfg.view_extent, cfg.view_size)
        self.grid = ActionGrid(cfg.grid_nx, cfg.grid_ny, cfg.grid_ntheta, cfg.grid_half_range)
        thickness = min(p.thickness for p in self.piece_set.pieces)
        self.obs_cfg = ObservationConfig(cfg.view_mode, cfg.height_levels, thickness)
        physics = PhysicsConfig(
            settle_steps=cfg.settle_steps, release_gap=cfg.release_gap, push_depth=cfg.push_depth, nthread=cfg.nthread
        )
        robot = RobotConfig(model=cfg.robot_model) if cfg.placement == "robot" else None
        self.worlds = Worlds(self.piece_set, cfg.num_worlds, physics, SceneConfig(), self.view, robot)
        self.sampler = TaskSampler(self.piece_set, cfg.task, figures, cfg.view_extent)
        self._camera = None
        if cfg.camera == "mujoco":
            from mrchaos.camera import MujocoCamera

            self._camera = MujocoCamera(self.worlds, self.view)

        n, p = cfg.num_worlds, len(self.piece_set)
        self.num_pieces = p
        areas = np.array([pc.area for pc in self.piece_set.pieces])
        self._shaped = torch.as_tensor(areas > areas.min() + 1e-12)
        self._period = torch.as_tensor([pc.symmetry_period for pc in self.piece_set.pieces], dtype=torch.float32)
        self._twins = self.piece_set.twin_matrix()
        # Per-world episode state.
        self.target = np.zeros((n, p, 3))
        self.target_ids = torch.full((n, cfg.view_size, cfg.view_size), -1, dtype=torch.int8)
        self.silhouette = torch.zeros((n, cfg.view_size, cfg.view_size), dtype=torch.uint8)
        self.next_piece = np.zeros(n, dtype=np.int64)
        self.end_piece = np.full(n, p, dtype=np.int64)
        self.task_source = np.zeros(n, dtype=np.int64)
        self.task_figure = np.full(n, -1, dtype=np.int64)
        self._view = torch.zeros((n, cfg.view_size, cfg.view_size), dtype=torch.uint8)
        self._done = torch.zeros((n, 1), dtype=torch.bool)
        # Summed slot coverage of the placed pieces at the last observation (exclusive slots).
        self._held = torch.zeros(n)
        self._make_specs()
        self._set_seed(seed)

    # ------------------------------------------------------------------ specs
    def _make_specs(self) -> None:
        n, p, s = self.cfg.num_worlds, self.num_pieces, self.cfg.view_size
        bs = self.batch_size
        info = Composite(
            coverage=Unbounded(shape=(n, p), dtype=torch.float32),
            step_coverage=Unbounded(shape=(n, 1), dtype=torch.float32),
            final=Unbounded(shape=(n, 1), dtype=torch.float32),
            iou=Unbounded(shape=(n, 1), dtype=torch.float32),
            physics=Categorical(2, shape=(n, 1), dtype=torch.bool),
            penetration=Unbounded(shape=(n, 1), dtype=torch.float32),
            piece=Unbounded(shape=(n, 1), dtype=torch.int64),
            **{k: Categorical(2, shape=(n, 1), dtype=torch.bool) for k in ROBOT_FAILURES},
            shape=bs,
        )
        self.observation_spec = Composite(
            observation=Bounded(0, 255, shape=(n, 2, s, s), dtype=torch.uint8),
            info=info,
            shape=bs,
        )
        self.action_spec = MultiCategorical(list(self.grid.nvec), shape=(n, 3), dtype=torch.int64)
        self.reward_spec = Unbounded(shape=(n, 1), dtype=torch.float32)
        self.full_done_spec = Composite(
            done=Categorical(2, shape=(n, 1), dtype=torch.bool),
            terminated=Categorical(2, shape=(n, 1), dtype=torch.bool),
            truncated=Categorical(2, shape=(n, 1), dtype=torch.bool),
            shape=bs,
        )

    def close(self, *, raise_if_closed: bool = True) -> None:
        if self._camera is not None:
            self._camera.close()
        super().close(raise_if_closed=raise_if_closed)

    # ------------------------------------------------------------------ seeding
    def _set_seed(self, seed: int | None) -> None:
        self.rng = torch.Generator()
        if seed is None:
            self.rng.seed()
        else:
            self.rng.manual_seed(int(seed))
        self._np_rng = np.random.default_rng(int(torch.randint(0, 2**62, (1,), generator=self.rng)))

    # ------------------------------------------------------------------ reset
    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        n, p = self.cfg.num_worlds, self.num_pieces
        rows = np.arange(n)
        k = np.zeros(n, dtype=np.int64)
        horizon = np.full(n, p, dtype=np.int64)
        if tensordict is not None:
            mask = tensordict.get("_reset", None)
            if mask is not None:
                rows = np.flatnonzero(mask.reshape(n, -1).any(-1).numpy())
            if "preassembled" in tensordict.keys():
                k = tensordict.get("preassembled").reshape(n).numpy().astype(np.int64)
            if "horizon" in tensordict.keys():
                horizon = tensordict.get("horizon").reshape(n).numpy().astype(np.int64)
        if ((k < 0) | (k >= p)).any():
            raise ValueError(f"preassembled must be in [0, {p - 1}], got {k.tolist()}")
        if len(rows):
            self._reset_rows(rows, k[rows], horizon[rows])
        return self._observe(fresh=True)

    def _reset_rows(self, rows: np.ndarray, k: np.ndarray, horizon: np.ndarray) -> None:
        tasks = self.sampler.sample(len(rows), self._np_rng)
        self.target[rows] = tasks.poses
        self.task_source[rows] = tasks.source
        self.task_figure[rows] = tasks.figure
        ps = self.piece_set
        ids = rasterize(ps.footprints(tasks.poses), self.view, parts=ps.part_piece if ps.parts_per_piece > 1 else None).ids
        self.target_ids[rows] = ids
        self.silhouette[rows] = silhouette_image(ids)
        pre = [(np.flatnonzero(k > j), tasks.poses[k > j, j]) for j in range(self.num_pieces)]
        self.worlds.reset(rows, [(rows[sub], poses) for sub, poses in pre])
        self.next_piece[rows] = k
        self.end_piece[rows] = np.where(horizon > 0, np.minimum(k + horizon, self.num_pieces), self.num_pieces)
        self._done[rows] = False

    # ------------------------------------------------------------------ step
    def _check_action(self, action: torch.Tensor) -> np.ndarray:
        n = self.cfg.num_worlds
        if action.shape != (n, 3):
            raise ValueError(f"action must have shape ({n}, 3), got {tuple(action.shape)}")
        if action.dtype not in (torch.int64, torch.int32, torch.int16, torch.uint8):
            raise TypeError(f"action must be an integer tensor of grid indices, got {action.dtype}")
        a = action.cpu().numpy().astype(np.int64)
        hi = np.array(self.grid.nvec)
        bad = (a < 0) | (a >= hi)
        if bad.any():
            r, c = np.argwhere(bad)[0]
            raise ValueError(
                f"action out of range: world {r} component {'xyθ'[c]} = {a[r, c]}, valid 0..{hi[c] - 1}"
            )
        return a

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        a = self._check_action(tensordict.get("action"))
        piece = np.minimum(self.next_piece, self.num_pieces - 1)
        return self.place_poses(self.piece_set.to_centroid(piece, self.grid.to_pose(a)))

    def place_poses(self, poses: np.ndarray) -> TensorDictBase:
        """Place the next piece of every world at continuous centroid poses (N, 3); return the step's outputs.

        This is the step without the action grid: the exact oracle and the robot
        placement use it. Worlds whose episode is over are left unchanged.
        """
        n = self.cfg.num_worlds
        poses = np.asarray(poses, dtype=np.float64).reshape(n, 3)
        if not np.isfinite(poses).all():
            raise ValueError("placement poses contain NaN or inf")
        commanded = poses.copy()
        if self.cfg.action_noise_xy > 0 or self.cfg.action_noise_theta > 0:
            noise = torch.randn((n, 3), generator=self.rng, dtype=torch.float64).numpy()
            poses = poses + noise * [self.cfg.action_noise_xy, self.cfg.action_noise_xy, self.cfg.action_noise_theta]
        rows = np.flatnonzero(self.next_piece < self.end_piece)
        piece = self.next_piece.copy()
        physics = np.zeros(n, dtype=bool)
        penetration = np.zeros(n)
        failures = {k: np.zeros(n, dtype=bool) for k in ROBOT_FAILURES}
        if len(rows):
            res = self.worlds.place(rows, piece[rows], poses[rows])
            physics[rows], penetration[rows] = res.physics, res.penetration
            if res.robot is not None:
                for k in ROBOT_FAILURES:
                    failures[k][rows] = getattr(res.robot, k)
            self.next_piece[rows] += 1
        return self._observe(fresh=False, piece=piece, acted=rows, commanded=commanded, physics=physics,
                             penetration=penetration, failures=failures)

    def perturb(self, rows: np.ndarray, distance: float) -> None:
        """Push one placed piece of each world in ``rows`` away, ``distance`` metres in a random direction.

        The piece is the most recently placed one; physics moves it (and whatever it hits).
        The next observation shows the result; the episode goes on from there.
        """
        rows = np.asarray(rows, dtype=np.int64)
        rows = rows[self.next_piece[rows] > 0]
        if len(rows) == 0:
            return
        angle = torch.rand(len(rows), generator=self.rng, dtype=torch.float64).numpy() * 2 * math.pi
        self.worlds.push(rows, self.next_piece[rows] - 1, np.c_[np.cos(angle), np.sin(angle)] * distance)

    def current(self) -> TensorDictBase:
        """Observation and info of every world as they are now (no step, no reward)."""
        out = self._observe(fresh=True)
        return out.exclude("done", "terminated", "truncated")

    # ------------------------------------------------------------------ outputs
    def _observe(
        self,
        fresh: bool,
        piece: np.ndarray | None = None,
        acted: np.ndarray | None = None,
        commanded: np.ndarray | None = None,
        physics: np.ndarray | None = None,
        penetration: np.ndarray | None = None,
        failures: dict[str, np.ndarray] | None = None,
    ) -> TensorDictBase:
        """Observation, info, reward (unless ``fresh``, i.e. a reset) and done flags of every world."""
        n, p = self.cfg.num_worlds, self.num_pieces
        reward = torch.zeros(n, 1)
        w = self.worlds
        if self._camera is not None:
            raster = self._camera.render(np.arange(n))
        else:
            raster = w.raster(self.view, need_height=self.obs_cfg.needs_height)
        joint = joint_counts(raster.ids, self.target_ids, p)
        counts, area = joint[:, 1:, 1:], joint[:, :, 1:].sum(1)
        slots = exclusive_slot_coverage if self.cfg.twin_slots == "exclusive" else best_slot_coverage
        coverage, slot = slots(counts, area, self._twins)  # (N, P) each
        held = (coverage * torch.as_tensor(w.placed)).sum(1)
        view = raster
        if self.cfg.camera_jitter > 0 and self._camera is None:
            shift = torch.randn((n, 2), generator=self.rng, dtype=torch.float64).numpy() * self.cfg.camera_jitter
            view = w.raster(self.view, shift=shift, need_height=self.obs_cfg.needs_height)
        self._view = view_image(view, self.obs_cfg)

        step_cov = torch.zeros(n, 1)
        pieces = torch.zeros(n, 1, dtype=torch.int64)
        if piece is not None and acted is not None and len(acted):
            t = torch.as_tensor(piece)
            ar = torch.arange(n)
            raw = coverage[ar, t]
            if self.cfg.twin_slots == "exclusive":
                # What the placement added to the assembly: a can stacked on another hides
                # it and takes its slot, which adds nothing.
                raw = (held - self._held).clamp(min=0.0)
            r = raw.clone()
            if self.cfg.reward_shaping:
                r = shape_reward(r, self._shaped[t], self.cfg.shaping_threshold)
            if self.cfg.penetration_gate:
                r = gate_penetration(r, torch.as_tensor(penetration, dtype=torch.float32), self.cfg.penetration_limit)
            if self.cfg.angle_gate:
                tgt_theta = torch.as_tensor(self.target[np.arange(n), slot[ar, t].numpy(), 2], dtype=torch.float32)
                r = gate_angle(r, torch.as_tensor(commanded[:, 2], dtype=torch.float32), tgt_theta,
                               self._period[t], math.radians(self.cfg.angle_tolerance_deg))
            mask = torch.zeros(n, dtype=torch.bool)
            mask[torch.as_tensor(acted)] = True
            reward = torch.where(mask, r, torch.zeros(()))[:, None]
            step_cov = torch.where(mask, raw, torch.zeros(()))[:, None]
            pieces = t[:, None]
            done_now = torch.as_tensor(self.next_piece >= self.end_piece)[:, None]
            self._done = self._done | (done_now & mask[:, None])
        obs = torch.stack([self.silhouette, self._view], dim=1)
        info = TensorDict(
            coverage=coverage,
            step_coverage=step_cov.float(),
            final=final_from_joint(joint)[:, None],
            iou=iou_from_joint(joint)[:, None],
            physics=torch.zeros(n, 1, dtype=torch.bool) if physics is None else torch.as_tensor(physics)[:, None],
            penetration=torch.zeros(n, 1) if penetration is None
            else torch.as_tensor(penetration, dtype=torch.float32)[:, None],
            piece=pieces,
            **{k: torch.as_tensor(failures[k])[:, None] if failures else torch.zeros(n, 1, dtype=torch.bool)
               for k in ROBOT_FAILURES},
            batch_size=self.batch_size,
        )
        done = self._done.clone()
        self._held = held
        out = TensorDict(
            observation=obs,
            info=info,
            done=done,
            terminated=done.clone(),
            truncated=torch.zeros(n, 1, dtype=torch.bool),
            batch_size=self.batch_size,
        )
        if not fresh:
            out.set("reward", reward.float())
        return out
