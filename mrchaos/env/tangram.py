"""``TangramEnv``: N batched MuJoCo tangram worlds as one TorchRL environment.

Task description:
    Place the pieces of a piece set one at a time so that the assembly covers the silhouette
    prompt. In the set's order (``env.order: fixed``, the paper's task) each step places piece t;
    with ``env.order: free`` the policy chooses which piece goes next as well as where. Each step
    places the piece at the action's pose (teleport placement followed by MuJoCo settling, or the
    robot, see :mod:`mrchaos.sim.worlds`).
Observation:
    ``observation`` uint8 (N, 2, H, W): the silhouette I_s stacked on the current
    top-down view I_tc. The step index is not observed. With free order also ``remaining``
    bool (N, P), the pieces not yet placed, and ``action_mask`` bool (N, P + X + Y + O), TorchRL's
    mask of a ``MultiCategorical`` action (one entry per outcome of each component): the piece
    component allows the first unplaced piece of each twin group (twins are one choice); the grid
    components are never masked. A finished world's action is ignored, so nothing is masked there.
Action:
    ``action`` int64 (N, 3): indices into the (x, y, theta) grid (``MultiCategorical``); with
    ``env.grid.flip`` the theta index also says whether a chiral piece goes down turned over.
    With free order (N, 4): (piece, x, y, theta); an action on a masked piece is an error. On a
    refined grid (``env.grid.fine_xy``, ``fine_theta``) a last index picks the offset inside the
    coarse cell (:class:`mrchaos.env.actions.ActionGrid`).
Reward:
    the coverage of piece t's target slot by piece t (twins take the better slot),
    with the reference's shaping, penetration and angle switches from config; every
    term is in ``info.reward_terms`` (see :mod:`mrchaos.env.rewards`).
Randomizations:
    targets from the target sampler (chaos objects, cache, figures) or given at reset, chiral pieces
    face up or turned over (``task.chaos.mirror_prob``, figures' mirror flags); optional action
    noise and camera jitter; the number k of pieces pre-assembled at reset.
Success:
    the episode terminates after the last piece (or after ``horizon`` placements);
    ``info`` carries the per-piece coverage, the whole-figure Final and IoU, the strict Rela of
    finished episodes, and of the step's placement: the piece, whether it went down turned over
    (``mirrored``), whether it was set down onto a placed piece and the robot's failures.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, MultiCategorical, Unbounded
from torchrl.envs import EnvBase

from mrchaos.core.raster import Raster, View, rasterize
from mrchaos.env.actions import ActionGrid
from mrchaos.env.dense import CounterfactualGrid
from mrchaos.env.metrics import (
    best_slot_coverage,
    exclusive_slot_coverage,
    final_from_joint,
    iou_from_joint,
    joint_counts,
    strict_rela_from_joint,
)
from mrchaos.env.observation import ObservationConfig, downsample, silhouette_image, view_image
from mrchaos.env.rewards import REWARD_TERMS, RewardConfig, reward_terms
from mrchaos.figures.figure import Figure
from mrchaos.figures.pieces import get_piece_set
from mrchaos.sim.flipper import FlipperConfig
from mrchaos.sim.robot import RobotConfig
from mrchaos.sim.scene import SceneConfig
from mrchaos.sim.worlds import PhysicsConfig, Worlds
from mrchaos.tasks.sampler import TargetBatch, TargetSampler, TaskConfig

__all__ = [
    "EnvConfig",
    "NoiseConfig",
    "TangramEnv",
    "OracleTargets",
    "ROBOT_FAILURES",
    "ORDERS",
    "FREE_ORDER_KEYS",
    "free_order_inputs",
]

#: Failure flags of robot placement in the step info (always False with teleport placement).
ROBOT_FAILURES = ("unreachable", "missed", "dropped", "collision", "flip_failed")
#: Assembly orders: the set's own, or chosen by the policy at every step.
ORDERS = ("fixed", "free")
#: What free order adds to the observation, beside the image: the pieces left and the action mask.
FREE_ORDER_KEYS = ("remaining", "action_mask")


def free_order_inputs(remaining: torch.Tensor, choosable: torch.Tensor, grid: ActionGrid) -> dict[str, torch.Tensor]:
    """What a free-order policy reads beside the image, for stored states: ``remaining`` (N, P) and
    the ``action_mask`` whose piece part is ``choosable`` (N, P) and whose x, y and orientation
    parts allow everything (as the env's own observation does in a world still assembling)."""
    rest = torch.ones(len(choosable), int(sum(grid.nvec)), dtype=torch.bool, device=choosable.device)
    return {"remaining": remaining, "action_mask": torch.cat([choosable.bool(), rest], 1)}


#: Where the env's wall-clock time goes (seconds, see :meth:`TangramEnv.timings`).
TIMERS = ("physics", "images", "reward")


@dataclass
class NoiseConfig:
    """Randomisations of a step: Gaussian noise on the placement pose (std, m and rad) and a
    per-step shift of the observed view (std, m; rewards use the true view)."""

    action_xy: float = 0.0
    action_theta: float = 0.0
    camera_jitter: float = 0.0


@dataclass
class EnvConfig:
    """Everything that defines the environment, grouped as its parts are.

    Attributes:
        num_worlds: batch size N.
        piece_set: registered piece-set name.
        view: the camera footprint (m) and image size (px).
        grid: the (x, y, theta) action grid.
        observation: how the current view is encoded (see :mod:`mrchaos.env.observation`).
        camera: "raster" (fast orthographic rasteriser) or "mujoco" (MuJoCo's renderer).
        placement: "teleport" (pieces are set down at the pose) or "robot" (the UR5e picks
            and places them, see :mod:`mrchaos.sim.executor`).
        physics: placement physics (see :class:`mrchaos.sim.worlds.PhysicsConfig`).
        robot: the UR5e, used with ``placement: robot``; ``robot.model`` empty for the
            package's own MJCF, or MuJoCo Menagerie's ``universal_robots_ur5e/ur5e.xml``.
        flipper: the flip fixture the robot turns pieces over on, in the scene with
            ``placement: robot`` and ``grid.flip``.
        reward: the training reward's switches (see :mod:`mrchaos.env.rewards`).
        noise: action noise and camera jitter.
        task: where targets come from (the config's top-level ``task`` group).
        order: "fixed" (pieces go down in the set's order, the paper's task) or "free" (the
            action also chooses the piece; see the module docstring).
    """

    num_worlds: int = 16
    piece_set: str = "tangram7"
    view: View = field(default_factory=View)
    grid: ActionGrid = field(default_factory=ActionGrid)
    observation: ObservationConfig = field(default_factory=ObservationConfig)
    camera: str = "raster"
    placement: str = "teleport"
    physics: PhysicsConfig = field(default_factory=PhysicsConfig)
    robot: RobotConfig = field(default_factory=RobotConfig)
    flipper: FlipperConfig = field(default_factory=FlipperConfig)
    reward: RewardConfig = field(default_factory=RewardConfig)
    noise: NoiseConfig = field(default_factory=NoiseConfig)
    task: TaskConfig = field(default_factory=TaskConfig)
    order: str = "fixed"

    def __post_init__(self) -> None:
        if self.order not in ORDERS:
            raise ValueError(f"env.order must be one of {ORDERS}, got {self.order!r}")
        if self.camera not in ("raster", "mujoco"):
            raise ValueError(f"env.camera must be 'raster' or 'mujoco', got {self.camera!r}")
        if self.placement not in ("teleport", "robot"):
            raise ValueError(f"env.placement must be 'teleport' or 'robot', got {self.placement!r}")
        if self.num_worlds < 1:
            raise ValueError(f"env.num_worlds must be >= 1, got {self.num_worlds}")
        if self.camera == "mujoco" and self.observation.supersample > 1:
            raise ValueError(
                "env.observation.supersample needs env.camera: raster (MuJoCo's renderer draws "
                "env.view.size pixels; raise env.view.size instead)"
            )


@dataclass
class OracleTargets:
    """The privileged answer for every world's next placement: which piece and its exact
    centroid pose (its own slot), and whether it lies turned over. Only oracles and tests may read it."""

    piece: np.ndarray  # (N,) int64
    pose: np.ndarray  # (N, 3) x, y, theta
    mirrored: np.ndarray  # (N,) bool


class TangramEnv(EnvBase):
    """Batched tangram assembly (see the module docstring for the task).

    Args:
        cfg: environment config.
        seed: seed of the env's ``torch.Generator`` (and the numpy generator derived from it).
        figures: optional figures for the target sampler (instead of ``cfg.task.figure_sets``).
        device: the env's device; it steps on the CPU.

    Public surface beyond TorchRL's: :meth:`reset_to` (given targets), :meth:`place_poses`
    (continuous poses), :meth:`perturb`, :meth:`current`, :meth:`oracle_targets`,
    :meth:`choosable`, :meth:`rng_state` / :meth:`set_rng_state`, :meth:`film` /
    :meth:`take_snapshots`, :meth:`timings`, and the read-only ``piece_set``, ``view``, ``grid``,
    ``num_pieces``, ``free_order``, ``next_piece`` (the step: with fixed order, the piece placed
    next) and ``scene_model``.
    """

    batch_locked = True

    def __init__(
        self,
        cfg: EnvConfig | None = None,
        seed: int | None = 0,
        figures: list[Figure] | None = None,
        device: str | torch.device = "cpu",
    ):
        cfg = cfg if cfg is not None else EnvConfig()  # a fresh default: the env keeps and reads it
        super().__init__(device=device, batch_size=torch.Size([cfg.num_worlds]))
        self.cfg = cfg
        self.piece_set = get_piece_set(cfg.piece_set)
        self.view = cfg.view
        self.grid = cfg.grid
        self.obs_cfg = cfg.observation
        # The observed images' own resolution (finer than the metrics' with supersample > 1).
        self._obs_view = View(self.view.extent, self.view.size * self.obs_cfg.supersample)
        self.free_order = cfg.order == "free"
        # One height level of the view per piece thickness (the thinnest piece's).
        self._thickness = min(p.thickness for p in self.piece_set.pieces)
        robot = cfg.robot if cfg.placement == "robot" else None
        flipper = cfg.flipper if cfg.grid.flip else None
        self._worlds = Worlds(
            self.piece_set, cfg.num_worlds, cfg.physics, SceneConfig(), self.view, robot, flipper=flipper
        )
        self._sampler = TargetSampler(self.piece_set, cfg.task, figures, self.view, flip=cfg.grid.flip)
        self._camera = None
        if cfg.camera == "mujoco":
            from mrchaos.sim.camera import MujocoCamera

            self._camera = MujocoCamera(self._worlds, self.view)

        n, p = cfg.num_worlds, len(self.piece_set)
        self.num_pieces = p
        areas = np.array([pc.area for pc in self.piece_set.pieces])
        self._shaped = torch.as_tensor(areas > areas.min() + 1e-12)
        self._period = torch.as_tensor([pc.symmetry_period for pc in self.piece_set.pieces], dtype=torch.float32)
        self._twins = self.piece_set.twin_matrix()
        self._twin_rep = self.piece_set.twin_group_of()
        self._chiral = self.piece_set.chiral
        # Per-world episode state.
        self._target = np.zeros((n, p, 3))
        self._mirrored = np.zeros((n, p), dtype=bool)
        self._target_ids = torch.full((n, self.view.size, self.view.size), -1, dtype=torch.int8)
        self._silhouette = torch.zeros((n, self.view.size, self.view.size), dtype=torch.uint8)
        self.next_piece = np.zeros(n, dtype=np.int64)
        self._last_placed = np.full(n, -1, dtype=np.int64)  # the piece a push moves
        self.end_piece = np.full(n, p, dtype=np.int64)
        self.target_source = np.zeros(n, dtype=np.int64)
        self.target_figure = np.full(n, -1, dtype=np.int64)
        self._done = torch.zeros((n, 1), dtype=torch.bool)
        # Summed slot coverage of the placed pieces at the last observation (exclusive slots).
        self._held = torch.zeros(n)
        self._timings = dict.fromkeys(TIMERS, 0.0)
        self._counterfactual: CounterfactualGrid | None = None  # built on first use
        self._make_specs()
        self._set_seed(seed)

    # ------------------------------------------------------------------ specs
    def _make_specs(self) -> None:
        n, p, s = self.cfg.num_worlds, self.num_pieces, self.view.size
        bs = self.batch_size
        scalar = lambda: Unbounded(shape=(n, 1), dtype=torch.float32)  # noqa: E731
        flag = lambda: Categorical(2, shape=(n, 1), dtype=torch.bool)  # noqa: E731
        info = Composite(
            coverage=Unbounded(shape=(n, p), dtype=torch.float32),
            step_coverage=scalar(),
            final=scalar(),
            iou=scalar(),
            strict_rela=scalar(),
            physics=flag(),
            penetration=scalar(),
            onto_piece=flag(),
            piece=Unbounded(shape=(n, 1), dtype=torch.int64),
            mirrored=flag(),
            reward_terms=Composite({k: scalar() for k in REWARD_TERMS}, shape=bs),
            **{k: flag() for k in ROBOT_FAILURES},
            shape=bs,
        )
        obs = {"observation": Bounded(0, 255, shape=(n, 2, s, s), dtype=torch.uint8)}
        nvec = list(self.grid.nvec)
        if self.free_order:
            nvec = [p, *nvec]
            obs["remaining"] = Categorical(2, shape=(n, p), dtype=torch.bool)
            obs["action_mask"] = Categorical(2, shape=(n, sum(nvec)), dtype=torch.bool)
        self.observation_spec = Composite(**obs, info=info, shape=bs)
        self.action_spec = MultiCategorical(nvec, shape=(n, len(nvec)), dtype=torch.int64)
        self.reward_spec = Unbounded(shape=(n, 1), dtype=torch.float32)
        self.full_done_spec = Composite(done=flag(), terminated=flag(), truncated=flag(), shape=bs)

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

    def rng_state(self) -> dict:
        """The env's random state (its torch generator and the numpy one drawn from it), for checkpoints."""
        return {"torch": self.rng.get_state(), "numpy": self._np_rng.bit_generator.state}

    def set_rng_state(self, state: dict) -> None:
        """Restore what :meth:`rng_state` returned."""
        self.rng.set_state(state["torch"])
        self._np_rng.bit_generator.state = state["numpy"]

    # ------------------------------------------------------------------ reset
    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        n, p = self.cfg.num_worlds, self.num_pieces
        rows = np.arange(n)
        k = np.zeros(n, dtype=np.int64)
        horizon = np.full(n, p, dtype=np.int64)
        targets = None
        if tensordict is not None:
            mask = tensordict.get("_reset", None)
            if mask is not None:
                rows = np.flatnonzero(mask.reshape(n, -1).any(-1).cpu().numpy())
            if "preassembled" in tensordict.keys():
                k = tensordict.get("preassembled").reshape(n).cpu().numpy().astype(np.int64)
            if "horizon" in tensordict.keys():
                horizon = tensordict.get("horizon").reshape(n).cpu().numpy().astype(np.int64)
            if "targets" in tensordict.keys():
                targets = tensordict.get("targets").cpu().numpy().astype(np.float64)
                if targets.shape != (n, p, 3):
                    raise ValueError(f"reset targets must have shape ({n}, {p}, 3), got {targets.shape}")
                mirrored = np.zeros((n, p), dtype=bool)
                if "target_mirrored" in tensordict.keys():
                    mirrored = tensordict.get("target_mirrored").cpu().numpy().astype(bool).reshape(n, p)
        if ((k < 0) | (k >= p)).any():
            raise ValueError(f"preassembled must be in [0, {p - 1}], got {k.tolist()}")
        if len(rows):
            if targets is None:
                tasks = self._sampler.sample(len(rows), self._np_rng)
            else:
                tasks = TargetBatch(targets[rows], np.full(len(rows), 2), rows.copy(), mirrored[rows])
            self._reset_rows(rows, tasks, k[rows], horizon[rows])
        return self._observe(fresh=True)

    def reset_to(self, targets: np.ndarray, mirrored: np.ndarray | None = None) -> TensorDictBase:
        """Reset every world to the given target poses (N, P, 3) instead of sampled ones (for evaluation);
        ``mirrored`` (N, P) bool marks pieces whose target lies turned over."""
        td = TensorDict(targets=torch.as_tensor(np.asarray(targets, dtype=np.float64)), batch_size=self.batch_size)
        if mirrored is not None:
            td.set("target_mirrored", torch.as_tensor(np.asarray(mirrored, dtype=bool)))
        return self.reset(td)

    def _reset_rows(self, rows: np.ndarray, tasks: TargetBatch, k: np.ndarray, horizon: np.ndarray) -> None:
        self._target[rows] = tasks.poses
        self._mirrored[rows] = tasks.mirrored
        self.target_source[rows] = tasks.source
        self.target_figure[rows] = tasks.figure
        ps = self.piece_set
        polys = ps.footprints(tasks.poses, tasks.mirrored)
        ids = rasterize(polys, self.view, parts=ps.raster_parts).ids
        self._target_ids[rows] = ids
        fine = self.obs_cfg.supersample
        seen = ids if fine == 1 else rasterize(polys, self._obs_view, parts=ps.raster_parts).ids
        self._silhouette[rows] = downsample(silhouette_image(seen), fine)
        mirrored = tasks.mirrored
        assert mirrored is not None  # TargetBatch fills it
        pre = [(np.flatnonzero(k > j), tasks.poses[k > j, j], mirrored[k > j, j]) for j in range(self.num_pieces)]
        self._worlds.reset(rows, [(rows[sub], poses, mirrored) for sub, poses, mirrored in pre])
        self.next_piece[rows] = k
        self._last_placed[rows] = k - 1
        self.end_piece[rows] = np.where(horizon > 0, np.minimum(k + horizon, self.num_pieces), self.num_pieces)
        self._done[rows] = False

    # ------------------------------------------------------------------ step
    def _check_action(self, action: torch.Tensor) -> np.ndarray:
        n = self.cfg.num_worlds
        names = ("piece",) * self.free_order + ("x", "y", "θ") + ("fine",) * self.grid.refined
        if action.shape != (n, len(names)):
            what = "(" + ", ".join(names) + ")"
            raise ValueError(f"action must have shape ({n}, {len(names)}) {what}, got {tuple(action.shape)}")
        if action.dtype not in (torch.int64, torch.int32, torch.int16, torch.uint8):
            raise TypeError(f"action must be an integer tensor of grid indices, got {action.dtype}")
        a = action.cpu().numpy().astype(np.int64)
        hi = np.array([self.num_pieces, *self.grid.nvec] if self.free_order else self.grid.nvec)
        bad = (a < 0) | (a >= hi)
        if bad.any():
            r, c = np.argwhere(bad)[0]
            raise ValueError(f"action out of range: world {r} component {names[c]} = {a[r, c]}, valid 0..{hi[c] - 1}")
        return a

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        a = self._check_action(tensordict.get("action"))
        piece = self._upcoming()
        if self.free_order:
            piece = self._chosen(a[:, 0])
            a = a[:, 1:]
        chosen = piece if self.free_order else None
        if not self.grid.flip:
            return self.place_poses(self.piece_set.to_centroid(piece, self.grid.to_pose(a)), piece=chosen)
        # Turned over, a piece that is not chiral is the same set of poses: only chiral ones flip.
        mirrored = self.grid.mirrored(a) & self._chiral[piece]
        return self.place_poses(
            self.piece_set.to_centroid(piece, self.grid.to_pose(a), mirrored), mirrored, piece=chosen
        )

    def choosable(self) -> np.ndarray:
        """(N, P) bool: the pieces a free-order action may choose now, the first unplaced piece of
        each twin group (all False in a finished world)."""
        placed = self._worlds.placed
        p = self.num_pieces
        # Twins go down in set order, so a group's first unplaced member is its lowest index.
        earlier_twin_unplaced = np.zeros_like(placed)
        for i in range(p):
            same = np.flatnonzero(self._twin_rep[:i] == self._twin_rep[i])
            if len(same):
                earlier_twin_unplaced[:, i] = (~placed[:, same]).any(1)
        live = (self.next_piece < self.end_piece)[:, None]
        return ~placed & ~earlier_twin_unplaced & live

    def _chosen(self, piece: np.ndarray) -> np.ndarray:
        """The free-order pieces of an action, checked against :meth:`choosable` (finished worlds'
        choices are ignored: they place nothing)."""
        ok = self.choosable()
        live = self.next_piece < self.end_piece
        rows = np.arange(self.cfg.num_worlds)
        bad = live & ~ok[rows, piece]
        if bad.any():
            r = int(np.flatnonzero(bad)[0])
            k = int(piece[r])
            name = self.piece_set.names[k]
            if self._worlds.placed[r, k]:
                why = "it is already placed"
            else:
                first = int(np.flatnonzero((self._twin_rep == self._twin_rep[k]) & ~self._worlds.placed[r])[0])
                why = f"twins are one choice: its twin {first} ({self.piece_set.names[first]}) goes first"
            allowed = np.flatnonzero(ok[r]).tolist()
            raise ValueError(f"action on a masked piece: world {r} chose piece {k} ({name}), {why}; allowed {allowed}")
        return np.where(live, piece, self._upcoming())

    def _upcoming(self) -> np.ndarray:
        """(N,) the piece each world places next in fixed order (the last one once its episode is over)."""
        return np.minimum(self.next_piece, self.num_pieces - 1)

    def _piece_arg(self, piece: np.ndarray | None, what: str) -> np.ndarray:
        """The piece of every world for ``what``: given (free order), or the set's next one (fixed
        order, where a given piece must be that one in every world still assembling)."""
        if piece is None:
            if self.free_order:
                raise ValueError(f"{what} needs the piece of every world with env.order: free")
            return self._upcoming()
        piece = np.asarray(piece, dtype=np.int64).reshape(self.cfg.num_worlds)
        if ((piece < 0) | (piece >= self.num_pieces)).any():
            raise ValueError(f"{what}: pieces must be in 0..{self.num_pieces - 1}, got {piece.tolist()}")
        live = self.next_piece < self.end_piece
        if not self.free_order and (piece != self._upcoming())[live].any():
            raise ValueError(f"{what}: with env.order: fixed the piece is the set's next one ({self._upcoming()})")
        return piece

    def place_poses(
        self, poses: np.ndarray, mirrored: np.ndarray | None = None, piece: np.ndarray | None = None
    ) -> TensorDictBase:
        """Place a piece of every world at continuous centroid poses (N, 3), turned over where
        ``mirrored`` (N,) bool; return the step's outputs. The piece is ``piece`` (N,) (free order
        needs it; it is not checked against the action mask) or the set's next one.

        This is the step without the action grid: the exact oracle and the robot
        placement use it. Worlds whose episode is over are left unchanged.
        """
        if mirrored is not None:
            mirrored = np.asarray(mirrored, dtype=bool).reshape(self.cfg.num_worlds)
        piece = self._piece_arg(piece, "place_poses").copy()
        if not self.free_order:
            piece = self.next_piece.copy()  # past the end in finished worlds, as the info has always said
        n = self.cfg.num_worlds
        poses = np.asarray(poses, dtype=np.float64).reshape(n, 3)
        if not np.isfinite(poses).all():
            raise ValueError("placement poses contain NaN or inf")
        commanded = poses.copy()
        noise = self.cfg.noise
        if noise.action_xy > 0 or noise.action_theta > 0:
            eps = torch.randn((n, 3), generator=self.rng, dtype=torch.float64).numpy()
            poses = poses + eps * [noise.action_xy, noise.action_xy, noise.action_theta]
        rows = np.flatnonzero(self.next_piece < self.end_piece)
        physics = np.zeros(n, dtype=bool)
        penetration = np.zeros(n)
        onto = np.zeros(n, dtype=bool)
        failures = {k: np.zeros(n, dtype=bool) for k in ROBOT_FAILURES}
        turned = np.zeros(n, dtype=bool)
        if len(rows):
            if mirrored is not None:
                turned[rows] = mirrored[rows]
            t0 = time.perf_counter()
            res = self._worlds.place(rows, piece[rows], poses[rows], None if mirrored is None else mirrored[rows])
            self._timings["physics"] += time.perf_counter() - t0
            physics[rows], penetration[rows], onto[rows] = res.physics, res.penetration, res.onto
            if res.robot is not None:
                for k in ROBOT_FAILURES:
                    failures[k][rows] = getattr(res.robot, k)
            self.next_piece[rows] += 1
            self._last_placed[rows] = piece[rows]
        return self._observe(
            fresh=False, placement=_Placement(piece, rows, commanded, physics, penetration, onto, failures, turned)
        )

    def off_table(self) -> np.ndarray:
        """(N, P) bool: the placed pieces that do not lie flat on the table (stacked on another, or
        leaning on one): the stacking the paper expects a free order to reduce."""
        return self._worlds.off_table()

    def perturb(self, rows: np.ndarray, distance: float) -> None:
        """Push one placed piece of each world in ``rows`` away, ``distance`` metres in a random direction.

        The piece is the most recently placed one; physics moves it (and whatever it hits).
        The next observation shows the result; the episode goes on from there.
        """
        rows = np.asarray(rows, dtype=np.int64)
        rows = rows[self._last_placed[rows] >= 0]
        if len(rows) == 0:
            return
        angle = torch.rand(len(rows), generator=self.rng, dtype=torch.float64).numpy() * 2 * math.pi
        self._worlds.push(rows, self._last_placed[rows], np.c_[np.cos(angle), np.sin(angle)] * distance)

    def current(self) -> TensorDictBase:
        """Observation and info of every world as they are now (no step, no reward)."""
        out = self._observe(fresh=True)
        return out.exclude("done", "terminated", "truncated")

    # ------------------------------------------------------------------ privileged and tooling
    def oracle_targets(self, piece: np.ndarray | None = None) -> OracleTargets:
        """The next piece of every world (``piece`` (N,), needed with free order) and its exact
        target pose: the solution, for oracles and tests."""
        piece = self._piece_arg(piece, "oracle_targets")
        rows = np.arange(self.cfg.num_worlds)
        return OracleTargets(piece, self._target[rows, piece].copy(), self._mirrored[rows, piece].copy())

    def counterfactual(
        self, rows: np.ndarray | None = None, piece: np.ndarray | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """What placing every world's next piece (``piece`` (N,), needed with free order) at each
        grid action would earn, if it touched nothing, and how much of that footprint would lie on
        placed pieces: (N, T, Y, X) coverage and overlap in [0, 1], T = ``grid.norient`` (see
        :mod:`mrchaos.env.dense`; with the flip, the turned-over orientations follow the face-up
        ones). ``rows`` asks for those worlds only (their rows, in that order). Privileged, like
        :meth:`oracle_targets`."""
        if self._counterfactual is None:
            self._counterfactual = CounterfactualGrid(self.piece_set, self.grid)
        r = np.arange(self.cfg.num_worlds) if rows is None else np.asarray(rows)
        return self._counterfactual.coverage(
            self._piece_arg(piece, "counterfactual")[r],
            self._target[r],
            self._worlds.footprint[r],
            self._worlds.placed[r],
            self._twins,
            self._mirrored[r],
        )

    @property
    def worlds(self) -> Worlds:
        """The simulated worlds themselves, for white-box tests that inspect physics state.
        Modules drive the env through its methods instead (a test keeps it so)."""
        return self._worlds

    @property
    def scene_model(self):
        """The MuJoCo model of the scene (for renderers)."""
        return self._worlds.model

    def film(self, fps: float) -> None:
        """With robot placement, keep scene snapshots at ``fps`` per simulated second (0: stop)."""
        if self._worlds.executor is None:
            raise ValueError("filming the scene needs robot placement (env.placement: robot)")
        self._worlds.executor.capture_fps = fps

    def take_snapshots(self) -> dict[int, list[np.ndarray]]:
        """Scene states (qpos) kept since the last call, by world; empty unless filming."""
        if self._worlds.executor is None:
            return {}
        return self._worlds.executor.take_snapshots()

    def timings(self) -> dict[str, float]:
        """Seconds spent so far in physics, images and reward (and the share of placements that ran physics)."""
        return {**self._timings, "physics_share": self._worlds.physics_share}

    # ------------------------------------------------------------------ outputs
    def _render(self) -> tuple[Raster, Raster]:
        """The true view (for rewards) and the observed one (camera jitter applied; drawn
        ``supersample`` times finer)."""
        n = self.cfg.num_worlds
        need_height = self.obs_cfg.needs_height
        if self._camera is not None:
            raster = self._camera.render(np.arange(n))
            return raster, raster
        raster = self._worlds.raster(self.view, need_height=need_height)
        shift = None
        if self.cfg.noise.camera_jitter > 0:
            shift = torch.randn((n, 2), generator=self.rng, dtype=torch.float64).numpy() * self.cfg.noise.camera_jitter
        if shift is None and self._obs_view == self.view:
            return raster, raster
        return raster, self._worlds.raster(self._obs_view, shift=shift, need_height=need_height)

    def _step_reward(
        self, p: _Placement, acted: torch.Tensor, coverage: torch.Tensor, slot: torch.Tensor, held: torch.Tensor
    ) -> dict[str, torch.Tensor]:
        """The named reward terms of the worlds that placed a piece (``acted``; 0 elsewhere), (N,) each."""
        n = self.cfg.num_worlds
        t = torch.as_tensor(p.piece)
        ar = torch.arange(n)
        raw = coverage[ar, t]
        if self.cfg.reward.twin_slots == "exclusive":
            # What the placement added to the assembly: a can stacked on another hides
            # it and takes its slot, which adds nothing.
            raw = (held - self._held).clamp(min=0.0)
        slot_theta = torch.as_tensor(self._target[np.arange(n), slot[ar, t].numpy(), 2], dtype=torch.float32)
        terms = reward_terms(
            self.cfg.reward,
            raw,
            self._shaped[t],
            torch.as_tensor(p.penetration, dtype=torch.float32),
            torch.as_tensor(p.commanded[:, 2], dtype=torch.float32),
            slot_theta,
            self._period[t],
        )
        return {k: torch.where(acted, v, torch.zeros(())) for k, v in terms.items()}

    def _observe(self, fresh: bool, placement: _Placement | None = None) -> TensorDictBase:
        """Observation, info, reward (unless ``fresh``, i.e. a reset) and done flags of every world."""
        n, p = self.cfg.num_worlds, self.num_pieces
        t0 = time.perf_counter()
        raster, seen = self._render()
        view = downsample(view_image(seen, self.obs_cfg, self._thickness), self.obs_cfg.supersample)
        t1 = time.perf_counter()
        joint = joint_counts(raster.ids, self._target_ids, p)
        counts, area = joint[:, 1:, 1:], joint[:, :, 1:].sum(1)
        slots = exclusive_slot_coverage if self.cfg.reward.twin_slots == "exclusive" else best_slot_coverage
        coverage, slot = slots(counts, area, self._twins)  # (N, P) each
        held = (coverage * torch.as_tensor(self._worlds.placed)).sum(1)
        zeros = torch.zeros(n)
        terms = dict.fromkeys(REWARD_TERMS, zeros)
        pieces = torch.zeros(n, dtype=torch.int64)
        strict = zeros
        if placement is not None and len(placement.acted) > 0:
            acted = torch.zeros(n, dtype=torch.bool)
            acted[torch.as_tensor(placement.acted)] = True
            terms = self._step_reward(placement, acted, coverage, slot, held)
            pieces = torch.as_tensor(placement.piece)
            ended = acted & torch.as_tensor(self.next_piece >= self.end_piece)
            self._done = self._done | ended[:, None]
        over = self._done[:, 0]
        if over.any():
            # The strict metric of every finished episode, from its view as it is now.
            rows = over.nonzero()[:, 0]
            strict = zeros.clone()
            strict[rows] = strict_rela_from_joint(joint[rows], self.piece_set.twins, p)
        self._held = held
        self._timings["images"] += t1 - t0
        self._timings["reward"] += time.perf_counter() - t1
        info = self._info(coverage, terms, joint, strict, pieces, placement)
        done = self._done.clone()
        out = TensorDict(
            observation=torch.stack([self._silhouette, view], dim=1),
            **(self._free_order_keys() if self.free_order else {}),
            info=info,
            done=done,
            terminated=done.clone(),
            truncated=torch.zeros(n, 1, dtype=torch.bool),
            batch_size=self.batch_size,
        )
        if not fresh:
            out.set("reward", terms["reward"].float()[:, None])
        return out

    def _free_order_keys(self) -> dict[str, torch.Tensor]:
        """``remaining`` and ``action_mask`` of free order (see the module docstring); the action
        spec's mask follows, so that ``rand_action`` draws allowed pieces."""
        n = self.cfg.num_worlds
        pieces = self.choosable()
        pieces[~pieces.any(1)] = True  # a finished world places nothing: nothing to mask
        grid = np.ones((n, sum(self.grid.nvec)), dtype=bool)
        mask = torch.as_tensor(np.concatenate([pieces, grid], 1))
        self.action_spec.update_mask(mask)
        return {"remaining": torch.as_tensor(~self._worlds.placed), "action_mask": mask}

    def _info(
        self,
        coverage: torch.Tensor,
        terms: dict[str, torch.Tensor],
        joint: torch.Tensor,
        strict: torch.Tensor,
        pieces: torch.Tensor,
        placement: _Placement | None,
    ) -> TensorDict:
        """The step's info: per-piece coverage, the step's terms, whole-figure metrics and placement flags."""
        n = self.cfg.num_worlds
        col = lambda x, dtype=torch.float32: torch.as_tensor(x, dtype=dtype)[:, None]  # noqa: E731
        no = torch.zeros(n, 1, dtype=torch.bool)
        return TensorDict(
            coverage=coverage,
            step_coverage=col(terms["coverage"]),
            final=final_from_joint(joint)[:, None],
            iou=iou_from_joint(joint)[:, None],
            strict_rela=col(strict),
            physics=no if placement is None else col(placement.physics, torch.bool),
            penetration=torch.zeros(n, 1) if placement is None else col(placement.penetration),
            onto_piece=no if placement is None else col(placement.onto, torch.bool),
            piece=pieces[:, None],
            mirrored=no if placement is None else col(placement.mirrored, torch.bool),
            reward_terms=TensorDict({k: col(v) for k, v in terms.items()}, batch_size=self.batch_size),
            **{k: no if placement is None else col(placement.failures[k], torch.bool) for k in ROBOT_FAILURES},
            batch_size=self.batch_size,
        )


@dataclass
class _Placement:
    """What a step's placement did, per world: the piece, which worlds acted, the commanded
    pose, whether physics ran, penetration depth, whether it was set down onto a placed piece,
    robot failures and whether the piece went down turned over (its face: the flip's outcome, so
    that a reader of the info need not decode the action)."""

    piece: np.ndarray
    acted: np.ndarray
    commanded: np.ndarray
    physics: np.ndarray
    penetration: np.ndarray
    onto: np.ndarray
    failures: dict[str, np.ndarray]
    mirrored: np.ndarray
