"""The benchmark: the paper's Table I for any set of policies on every family.

Families: **Random** (seeded chaos objects, as in training) and the human-designed
**H-Normal / H-Hard / H-Fiendish** (a figure set's own labels, else the
perimeter rule). Each policy places all j pieces of every target in order,
greedily. Reported per family: Rela and Final (the paper's metrics) and IoU and
strict Rela (ours), with a 95 % interval (1.96 standard errors) and the count.
"""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from mrchaos.core.atomic import write_atomic
from mrchaos.core.errors import MrchaosError
from mrchaos.env.oracle import oracle_actions, random_pieces
from mrchaos.env.tangram import ORDERS, TangramEnv
from mrchaos.figures.families import FamilyRule, family_of
from mrchaos.figures.figure import Figure, FigureSet
from mrchaos.figures.pieces import get_piece_set, piece_set_names
from mrchaos.learn.checkpoint import (
    SHIPPED,
    CheckpointError,
    check_header,
    checkpoint_path,
    load_checkpoint,
    policy_env,
)
from mrchaos.learn.config import config_from_dict
from mrchaos.learn.evaluate import (
    EpisodeResults,
    concat_results,
    evaluate,
    policy_actor,
)
from mrchaos.learn.planner import Lookahead
from mrchaos.learn.rerank import reranked_actor
from mrchaos.tasks.chaos import generate
from mrchaos.tasks.presets import TaskPreset, get_preset

__all__ = [
    "BenchError",
    "PolicySpec",
    "resolve_policy",
    "parse_families",
    "Bench",
    "piece_breakdown",
    "piece_coverage",
    "chosen_order",
]

METRICS = ("rela", "final", "iou", "strict_rela")
#: A placement covering less than this share of its slot counts as misplaced in the per-piece table.
MISPLACED_BELOW = 0.5


class BenchError(MrchaosError, ValueError):
    """Bad benchmark input: one clear line, exit code 2."""


@dataclass
class PolicySpec:
    """A policy to evaluate: a baseline by name or a checkpoint."""

    name: str
    label: str
    kind: str  # "random", "oracle" or "checkpoint"
    path: str | None = None
    state: dict | None = field(default=None, repr=False)

    @property
    def flips(self) -> bool:
        """Whether the policy was trained to choose the face of chiral pieces (a checkpoint whose
        action grid has the flip); the baselines get the flip only from the bench's own switch."""
        return self.state is not None and bool(policy_env(self.state).get("grid", {}).get("flip", False))

    @property
    def order(self) -> str:
        """The assembly order a checkpoint was trained with ("fixed" for the baselines and for
        checkpoints from before free order)."""
        return "fixed" if self.state is None else str(policy_env(self.state).get("order", "fixed"))


def resolve_policy(spec: str) -> PolicySpec:
    """A baseline (random, oracle), a shipped policy's name (:data:`mrchaos.learn.checkpoint.SHIPPED`),
    or a checkpoint / run path."""
    if spec == "random":
        return PolicySpec("random", "random (uniform actions)", "random")
    if spec == "oracle":
        return PolicySpec("oracle", "oracle (nearest grid; reads the solution)", "oracle")
    try:
        p = checkpoint_path(spec)
    except CheckpointError as e:
        raise BenchError(f"policy {spec!r}: {e} (or random, oracle)") from None
    name = spec if spec in SHIPPED else Path(spec).name
    label = SHIPPED[spec][1] if spec in SHIPPED else f"{name} ({p})"
    return PolicySpec(name, label, "checkpoint", str(p), load_checkpoint(p))


def check_task(task: str) -> TaskPreset:
    """The preset of ``task``, or :class:`BenchError` naming the known ones."""
    try:
        return get_preset(task)
    except KeyError as e:
        raise BenchError(e.args[0]) from None


def parse_families(text: str, task: str = "tangram") -> list[str]:
    """'all' or a comma-separated list of the task's families: random, h-normal, h-hard,
    h-fiendish for the tangram, authored and random for the others."""
    known = {f.lower(): f for f in check_task(task).families}
    if text.strip().lower() == "all":
        return list(known.values())
    out = []
    for part in text.split(","):
        key = part.strip().lower()
        if key not in known:
            raise BenchError(f"unknown family {part.strip()!r}; use 'all' or some of {sorted(known)}")
        out.append(known[key])
    return out


def summarise(values: np.ndarray) -> dict[str, float]:
    """Mean, standard error and 95 % half-interval of per-episode values."""
    n = len(values)
    mean = float(np.mean(values)) if n else float("nan")
    se = float(np.std(values, ddof=1) / math.sqrt(n)) if n > 1 else float("nan")
    return {"mean": mean, "se": se, "ci95": 1.96 * se if n > 1 else float("nan"), "n": n}


class Bench:
    """Evaluates policies on families.

    Args:
        figure_sets: figure sets to evaluate on (grouped by family); None for the task's own
            goals (for tangram, the built-in library).
        families: families to run.
        random_objects: Random objects (seeded; the same set every run).
        seed: seed of the Random objects.
        random_mirror: the chance that a Random object's chiral piece lies turned over (needs ``flip``).
        placement: "teleport" or "robot" (the UR5e picks and places every piece).
        num_worlds: worlds evaluated at once.
        robot_model: UR5e MJCF for robot placement ("" for the package's own).
        perturb_after: push the piece placed at this step away (the paper's Fig. 6C); None: no push.
        perturb_distance: how far the push moves it (m).
        scenes: with robot placement, how many episodes per policy and family are filmed
            (rendered scene frames for the recording and the video).
        scene_fps: film frames per simulated second.
        task: a preset of :data:`mrchaos.tasks.presets.PRESETS`: "tangram" (families Random, H-Normal,
            H-Hard, H-Fiendish), "cutlery" or "soda" (families Authored and Random).
        flip: evaluate figures that need a chiral piece turned over instead of skipping them; the
            baselines get an action grid with the flip (a checkpoint keeps its own grid).
        lookahead: candidates per step of a test-time planner around checkpoint policies (1: none).
        mode_window: overrides the checkpoints' ``policy.mode_window`` (how the spatial policy's
            deterministic action is read); None keeps each checkpoint's own.
        order: "fixed" (the set's order) or "free" (the policy chooses the piece too): random and
            oracle draw each piece among the allowed ones; a checkpoint keeps the order it was
            trained with, and a fixed-order one cannot play free order.
        grid: action-grid settings (``env.grid`` keys, e.g. ``{"nx": 101, "ntheta": 24}``) for the
            baselines, random and oracle, laid over the task's: a finer grid's ceiling. A checkpoint
            keeps the grid it was trained on.
    """

    def __init__(
        self,
        figure_sets: list[FigureSet] | None,
        families: list[str],
        random_objects: int = 200,
        seed: int = 0,
        placement: str = "teleport",
        num_worlds: int = 64,
        robot_model: str = "",
        perturb_after: int | None = None,
        perturb_distance: float = 0.05,
        scenes: int = 0,
        scene_fps: float = 4.0,
        task: str = "tangram",
        flip: bool = False,
        lookahead: int = 1,
        mode_window: int | None = None,
        random_mirror: float = 0.0,
        order: str = "fixed",
        grid: dict[str, Any] | None = None,
    ) -> None:
        if order not in ORDERS:
            raise BenchError(f"--order must be one of {ORDERS}, got {order!r}")
        self.order = order
        if placement not in ("teleport", "robot"):
            raise BenchError(f"placement must be 'teleport' or 'robot', got {placement!r}")
        if scenes and placement != "robot":
            raise BenchError("filming the scene (--video, scene frames in --record) needs --placement robot")
        if lookahead < 1:
            raise BenchError(f"--lookahead must be >= 1, got {lookahead}")
        if lookahead > 1 and (placement != "teleport" or perturb_after is not None):
            # Its completions are simulated without the robot's motion or the push, so they would
            # not predict what the evaluated episode does.
            raise BenchError("--lookahead plans with teleport placement and no --perturb")
        if lookahead > num_worlds:
            raise BenchError(f"--lookahead {lookahead} needs at least as many --worlds, got {num_worlds}")
        #: candidates per step of the test-time planner around checkpoint policies (1: greedy).
        self.lookahead = lookahead
        if mode_window is not None and (mode_window < 1 or mode_window % 2 == 0):
            raise BenchError(f"--mode-window must be odd and >= 1, got {mode_window}")
        self.mode_window = mode_window
        self.placement, self.robot_model = placement, robot_model
        self.perturb_after, self.perturb_distance = perturb_after, perturb_distance
        self.scenes, self.scene_fps = scenes, scene_fps
        #: frames of the first filmed episode (first policy, first family), for a video.
        self.video_frames: list[np.ndarray] = []
        self.families = families
        self.seed = seed
        self.num_worlds = num_worlds
        self.task = task
        self.flip = flip
        self.preset = check_task(task)
        self.piece_set = get_piece_set(self.preset.piece_set)
        if perturb_after is not None and not 0 <= perturb_after < len(self.piece_set):
            raise BenchError(f"--perturb must be a step in [0, {len(self.piece_set) - 1}], got {perturb_after}")
        #: the baselines' action-grid keys laid over the task's (``flip`` adds the flip).
        self.grid = dict(grid or {})
        if "flip" in self.grid:
            raise BenchError("the bench's grid settings take no flip key: the flip is its own switch (--flip)")
        # Checked here, so that a bad key fails before any policy is evaluated.
        config_from_dict({"env": {"grid": self.grid}, "task": {"preset": task}}, "the bench's --grid settings")
        self.env_config = config_from_dict({"task": {"preset": task}}, f"task {task}").env_config()
        if not 0.0 <= random_mirror <= 1.0:
            raise BenchError(f"--random-mirror must be a probability in [0, 1], got {random_mirror}")
        if random_mirror and not flip:
            raise BenchError("--random-mirror turns Random objects' chiral pieces over: it needs --flip")
        self.random_mirror = random_mirror
        if random_mirror:
            chaos = dataclasses.replace(self.env_config.task.chaos, mirror_prob=random_mirror)
            task_cfg = dataclasses.replace(self.env_config.task, chaos=chaos)
            self.env_config = dataclasses.replace(self.env_config, task=task_cfg)
        kinds = {ps.kind for ps in map(get_piece_set, self.preset.random_sets)}
        if figure_sets is None:
            goals = self.preset.goal_figures(self.env_config.view)
            figure_sets = [FigureSet(task, goals, source=f"the {task} task's goals")]
        self.figure_sets = figure_sets
        rule = FamilyRule()
        #: family -> groups of (piece set name, target poses, mirrored flags, episode ids); a family
        #: may mix piece sets of one family (soda goals of 3 to 6 cans).
        self.targets: dict[str, list[tuple[str, np.ndarray, np.ndarray, list[str]]]] = {}
        #: family -> how many of its figures need a piece turned over (evaluated only with ``flip``).
        self.needs_flip: dict[str, int] = {}
        self.skipped = [(fid, why) for fs in figure_sets for fid, why in fs.rejected]
        figs: list[Figure] = []
        for fs in figure_sets:
            for f in fs.figures:
                if f.piece_set.kind not in kinds:
                    self.skipped.append((f.id, f"{f.where}: piece set {f.piece_set.name} is not one of this task's"))
                elif f.has_mirrored and not flip:
                    self.skipped.append(
                        (
                            f.id,
                            f"{f.where}: needs a mirrored chiral piece (a suction robot cannot "
                            "flip it; evaluate it with --flip)",
                        )
                    )
                else:
                    figs.append(f)
        rng = np.random.default_rng(seed)
        for fam in families:
            if fam == "Random":
                sets = self.preset.random_sets
                counts = [random_objects // len(sets) + (i < random_objects % len(sets)) for i in range(len(sets))]
                groups = []
                for name, k in zip(sets, counts, strict=True):
                    if k > 0:
                        poses, _, mirrored = generate(
                            get_piece_set(name), k, rng, self.env_config.task.chaos, self.env_config.view
                        )
                        groups.append(
                            (
                                name,
                                poses,
                                mirrored,
                                [f"random-{i}" if len(sets) == 1 else f"random-{name}-{i}" for i in range(k)],
                            )
                        )
                if groups:
                    self.targets[fam] = groups
                continue
            chosen = [f for f in figs if (fam == "Authored" if self.preset.authored else family_of(f, rule) == fam)]
            groups = []
            for name in dict.fromkeys(f.piece_set.name for f in chosen):
                sub = [f for f in chosen if f.piece_set.name == name]
                groups.append(
                    (name, np.stack([f.poses for f in sub]), np.stack([f.mirrored for f in sub]), [f.id for f in sub])
                )
            if groups:
                self.targets[fam] = groups
                self.needs_flip[fam] = sum(f.has_mirrored for f in chosen)

    def make_env(self, spec: PolicySpec, piece_set: str | None = None) -> TangramEnv:
        """The env a policy is evaluated in: the task's settings, then the checkpoint's
        :data:`mrchaos.learn.checkpoint.POLICY_ENV_GROUPS` (the view, grid and image it was trained on)."""
        env: dict = {
            "num_worlds": self.num_worlds,
            "placement": self.placement,
            "robot": {"model": self.robot_model},
            "piece_set": piece_set or self.piece_set.name,
        }
        if spec.state is not None:
            env.update(policy_env(spec.state))
            if self.order == "free" and env.get("order", "fixed") == "fixed":
                raise BenchError(f"{spec.path}: trained with fixed order, it does not choose pieces (--order free)")
        else:
            env["order"] = self.order
            env["grid"] = {**self.grid, "flip": True} if self.flip else dict(self.grid)
        cfg = config_from_dict({"env": env, "task": {"preset": self.task}}, f"bench env ({spec.name})").env_config()
        return TangramEnv(dataclasses.replace(cfg, task=cfg.task.given_targets()), seed=self.seed)

    def actor(self, spec: PolicySpec, env: TangramEnv):
        g = torch.Generator().manual_seed(self.seed)
        if spec.kind == "oracle":
            if env.free_order:
                return lambda e, td: oracle_actions(e, random_pieces(e, g))
            return lambda e, td: oracle_actions(e)
        if spec.kind == "random":
            nvec = torch.tensor(env.grid.nvec)

            def uniform(e: TangramEnv, td) -> torch.Tensor:
                a = (torch.rand((e.batch_size[0], len(nvec)), generator=g) * nvec).long()
                if e.free_order:
                    a = torch.cat([torch.as_tensor(random_pieces(e, g))[:, None], a], 1)
                return a

            return uniform
        policy = self.policy_operator(spec, env)
        assert spec.state is not None  # a checkpoint's spec carries its state
        try:
            reranked = reranked_actor(spec.state, policy, env.view)
        except CheckpointError as e:
            raise CheckpointError(f"{spec.path}: {e}") from None
        if reranked is not None:
            if self.lookahead > reranked.k:
                raise BenchError(f"{spec.path}: --lookahead {self.lookahead} is more than its {reranked.k} candidates")
            return Lookahead(policy, self.lookahead, reranked) if self.lookahead > 1 else reranked
        if self.lookahead > 1:
            if spec.state["policy"].get("name") != "spatial":
                raise BenchError(f"{spec.path}: --lookahead needs a spatial policy (one score per grid action)")
            return Lookahead(policy, self.lookahead)
        return policy_actor(policy)

    def policy_operator(self, spec: PolicySpec, env: TangramEnv):
        """A checkpoint's policy module, rebuilt for ``env`` in eval mode, after checking that the
        checkpoint fits the env (its piece set, view and grid)."""
        from mrchaos.learn.policy import PolicyConfig, build_actor_critic

        st, path = spec.state, spec.path
        assert st is not None and path is not None  # a checkpoint's spec carries both
        # A policy acts on any piece set of the family it was trained on (e.g. any can count).
        trained = st.get("piece_set")
        same_kind = trained in piece_set_names() and get_piece_set(trained).kind == env.piece_set.kind
        check_header(st, path, env, piece_set=env.piece_set.name if same_kind else None)
        if self.mode_window is not None and st["policy"].get("name") != "spatial":
            raise BenchError(f"{spec.path}: --mode-window needs a spatial policy (one score per grid action)")
        try:
            pcfg = PolicyConfig(**st["policy"])
            if self.mode_window is not None:
                pcfg = dataclasses.replace(pcfg, mode_window=self.mode_window)
            pieces = env.num_pieces if env.free_order else 0
            ac = build_actor_critic(pcfg, env.grid, env.view, env.action_spec, pieces)
            ac.load_state_dict(st["model"])
        except (TypeError, ValueError, RuntimeError, KeyError) as e:
            raise CheckpointError(f"{spec.path}: cannot rebuild its policy ({str(e)[:200]})") from None
        return ac.eval().get_policy_operator()

    def run(self, specs: list[PolicySpec], record=None) -> dict:
        """Results: {policy: {family: {metric: summary}}} plus per-episode arrays for sheets."""
        results: dict = {"policies": {}, "counts": {}, "skipped": self.skipped, "seed": self.seed}
        self.episodes: dict[tuple[str, str], EpisodeResults] = {}
        for spec in specs:
            per_fam = {}
            # One env, actor and renderer per piece set, built when first needed.
            envs: dict[str, tuple[TangramEnv, Any, Any]] = {}
            try:
                for fam, groups in self.targets.items():
                    parts = []
                    for set_name, poses, mirrored, ids in groups:
                        if set_name not in envs:
                            envs[set_name] = self._policy_env(spec, set_name)
                        parts.append(self._episodes(spec, fam, ids, poses, mirrored, *envs[set_name], record))
                    res = concat_results(parts)
                    self.episodes[(spec.name, fam)] = res
                    per_fam[fam] = self.summary(res)
                    results["counts"][fam] = len(res.rela)
            finally:
                for env, _, renderer in envs.values():
                    if renderer is not None:
                        renderer.close()
                    env.close()
            label = spec.label
            if self.mode_window is not None and spec.kind == "checkpoint":
                label += f", mode window {self.mode_window}"
            if self.lookahead > 1 and spec.kind == "checkpoint":
                label += f" + lookahead {self.lookahead}"
            if self.order == "free" and spec.kind != "checkpoint":
                label += ", random order"
            if self.grid and spec.kind != "checkpoint":
                label += ", grid " + " ".join(f"{k}={v}" for k, v in self.grid.items())
            results["policies"][spec.name] = {"label": label, "families": per_fam}
        results["task"] = self.task
        results["piece_names"] = list(self.piece_set.names)
        results["placement"] = self.placement
        results["flip"] = self.flip
        if self.grid:
            results["grid"] = dict(self.grid)
        results["random_mirror"] = self.random_mirror
        results["lookahead"] = self.lookahead
        results["mode_window"] = self.mode_window
        results["needs_flip"] = {fam: self.needs_flip.get(fam, 0) for fam in results["counts"]}
        if any(pol["families"][f].get("chosen_order") for pol in results["policies"].values() for f in pol["families"]):
            results["order"] = "free"  # fixed-order results keep their earlier keys, unchanged
        if self.perturb_after is not None:
            results["perturb"] = {"after_step": self.perturb_after, "distance_m": self.perturb_distance}
        return results

    def _policy_env(self, spec: PolicySpec, set_name: str) -> tuple:
        """The env of one piece set for a policy, its actor and (when filming) a scene renderer."""
        env = self.make_env(spec, set_name)
        renderer = None
        if self.scenes:
            from mrchaos.sim.animation import SceneRenderer

            renderer = SceneRenderer(env.scene_model)
            env.film(self.scene_fps)
        return env, self.actor(spec, env), renderer

    def _episodes(
        self,
        spec: PolicySpec,
        fam: str,
        ids: list[str],
        poses: np.ndarray,
        mirrored: np.ndarray,
        env: TangramEnv,
        act,
        renderer,
        record,
    ) -> EpisodeResults:
        """One episode per target of a group, filmed and recorded as asked."""
        film = self._filmer(env, renderer, spec.name, fam, ids, record) if renderer else None
        if isinstance(act, Lookahead):
            act = act.actor(env, poses, mirrored)
        res = evaluate(
            env,
            poses,
            act,
            record_steps=record is not None,
            perturb_after=self.perturb_after,
            perturb_distance=self.perturb_distance,
            on_step=film,
            mirrored=mirrored,
        )
        if record is not None:
            record.log_episodes(spec.name, fam, ids, res, env.piece_set.names)
        return res

    def summary(self, res: EpisodeResults) -> dict:
        """A family's summaries: every metric, robot failures per placement, the push's effect."""
        out: dict = {m: summarise(getattr(res, m)) for m in METRICS}
        out["by_piece"] = piece_breakdown(piece_coverage(res.step_coverage, res.order))
        fixed = (res.order == np.arange(res.order.shape[1])) | (res.order < 0)
        if not fixed.all():
            out["chosen_order"] = chosen_order(res.order)
        if res.contacts is not None:
            # Per placement and per placed piece (episodes of a family may differ in piece count).
            placed = float(np.isfinite(res.step_coverage).sum())
            out["contacts"] = {k: float(v.sum() / placed) for k, v in res.contacts.items()}
        if self.placement == "robot":
            # Failures per placement: each episode places every piece once.
            assert res.failures is not None  # evaluate counts them for every placement
            out["robot_failures"] = {k: float(v.mean() / len(self.piece_set)) for k, v in res.failures.items()}
        if res.perturbation is not None:
            out["perturbation"] = {k: summarise(v) for k, v in res.perturbation.items()}
        return out

    def _filmer(self, env: TangramEnv, renderer, policy: str, family: str, ids: list[str], record):
        """An ``on_step`` hook that renders the robot's snapshots of the first ``scenes`` episodes."""
        first_video = not self.video_frames

        def on_step(start: int, t: int, nxt) -> None:
            for w, states in sorted(env.take_snapshots().items()):
                ep = start + w
                if ep >= min(self.scenes, len(ids)):
                    continue
                frames = [renderer.render(q) for q in states]
                if record is not None:
                    record.log_scene(policy, family, ids[ep], t, frames)
                if first_video and ep == 0:
                    self.video_frames.extend(frames)

        return on_step


def piece_coverage(step_coverage: np.ndarray, order: np.ndarray) -> np.ndarray:
    """(n, P) each piece's coverage when placed, from each step's coverage and the piece it placed
    (NaN where an episode has no such piece; the same array with fixed order)."""
    out = np.full(step_coverage.shape, np.nan, dtype=step_coverage.dtype)  # the same sums as before free order
    ep, step = np.nonzero(order >= 0)
    out[ep, order[ep, step]] = step_coverage[ep, step]
    return out


def chosen_order(order: np.ndarray) -> list[list[float]]:
    """(steps x P) the share of episodes that placed each piece at each step (free order)."""
    p = order.shape[1]
    return [[float((order[:, t] == i).mean()) for i in range(p)] for t in range(p)]


def piece_breakdown(step_coverage: np.ndarray, misplaced_below: float = MISPLACED_BELOW) -> dict[str, list[float]]:
    """Where Rela is lost, piece by piece: each piece's mean coverage when placed (pieces are placed
    in the set's order, so column t is piece t) and the share of its placements under
    ``misplaced_below``, i.e. in another slot or far off its own. Columns a smaller piece set of a
    mixed family lacks (NaN) are left out of that column's means."""
    valid = ~np.isnan(step_coverage)
    n = valid.sum(0)
    cov = np.where(valid, step_coverage, 0.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        coverage = cov.sum(0) / n
        misplaced = (valid & (cov < misplaced_below)).sum(0) / n
    return {"coverage": [float(v) for v in coverage], "misplaced": [float(v) for v in misplaced], "n": n.tolist()}


def format_piece_table(results: dict, families: list[str]) -> str:
    """Markdown: each piece's mean coverage when placed, and (in brackets) the share of its
    placements under MISPLACED_BELOW, per policy and family."""
    fams = [f for f in families if f in results["counts"]]
    if not fams or not results["policies"]:
        return ""  # every figure skipped: nothing was placed
    width = max(
        len(results["policies"][p]["families"][f]["by_piece"]["coverage"]) for p in results["policies"] for f in fams
    )
    names = list(results["piece_names"])[:width] + [f"piece {i}" for i in range(len(results["piece_names"]), width)]
    head = ["policy", "family"] + names
    lines = [
        f"**Coverage of each piece when placed, % (in brackets: % of its placements under "
        f"{100 * MISPLACED_BELOW:.0f} %)**",
        "",
        "| " + " | ".join(head) + " |",
        "|" + "---|" * len(head),
    ]
    for pol in results["policies"].values():
        for f in fams:
            b = pol["families"][f]["by_piece"]
            cells = [
                f"{100 * c:.1f} ({100 * m:.0f})" if k else ""
                for c, m, k in zip(b["coverage"], b["misplaced"], b["n"], strict=True)
            ]
            lines.append("| " + " | ".join([pol["label"], f] + cells + [""] * (width - len(cells))) + " |")
    return "\n".join(lines)


def format_order_table(results: dict, families: list[str]) -> str:
    """Markdown: which piece each free-order policy placed at each step (% of episodes), per family."""
    fams = [f for f in families if f in results["counts"]]
    names = list(results["piece_names"])
    blocks = []
    for pol in results["policies"].values():
        for f in fams:
            shares = pol["families"][f].get("chosen_order")
            if not shares:
                continue
            lines = [
                f"**Order chosen, {pol['label']}, {f}: % of episodes placing each piece at each step**",
                "",
                "| step | " + " | ".join(names[: len(shares[0])]) + " |",
                "|" + "---|" * (len(shares[0]) + 1),
            ]
            for t, row in enumerate(shares):
                lines.append(f"| {t + 1} | " + " | ".join(f"{100 * v:.0f}" for v in row) + " |")
            blocks.append("\n".join(lines))
    return "\n\n".join(blocks)


def format_table(results: dict, families: list[str], markdown: bool = False) -> str:
    """Table I layout (one row per policy, Rela and Final per family), then the strict metrics."""
    fams = [f for f in families if f in results["counts"]]
    blocks = []
    for title, metrics in (
        ("Table I (paper's metrics, %)", ("rela", "final")),
        ("Strict metrics (ours, %)", ("iou", "strict_rela")),
    ):
        short = {"rela": "Rela", "final": "Final", "iou": "IoU", "strict_rela": "sRela"}
        head = ["policy"] + [f"{f} {short[m]}" for f in fams for m in metrics]
        rows = []
        for pol in results["policies"].values():
            s = pol["families"]
            rows.append(
                [pol["label"]]
                + [f"{100 * s[f][m]['mean']:.1f} ± {100 * s[f][m]['ci95']:.1f}" for f in fams for m in metrics]
            )
        rows.append(["n (episodes)"] + sum([[str(results["counts"][f])] + [""] * (len(metrics) - 1) for f in fams], []))
        if markdown:
            lines = [f"**{title}**", "", "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
            lines += ["| " + " | ".join(r) + " |" for r in rows]
        else:
            widths = [max(len(r[i]) for r in rows + [head]) for i in range(len(head))]

            def fmt(r: list[str], widths: list[int] = widths) -> str:  # this table's widths
                return "  ".join(c.ljust(widths[i]) if i == 0 else c.rjust(widths[i]) for i, c in enumerate(r))

            lines = [title, fmt(head), "-" * (sum(widths) + 2 * len(widths))] + [fmt(r) for r in rows]
        blocks.append("\n".join(lines))
    free = any("chosen_order" in pol["families"][f] for pol in results["policies"].values() for f in fams)
    for name, pol in results["policies"].items():
        for fam in fams:
            s = pol["families"][fam]
            if "robot_failures" in s:
                rates = ", ".join(f"{k} {100 * v:.1f}" for k, v in s["robot_failures"].items())
                blocks.append(f"robot failures per placement (%), {name} on {fam}: {rates}")
            # The paper expects a free order to reduce these: shown where the robot places or a
            # policy chose its order.
            if "contacts" in s and ("robot_failures" in s or free):
                c = s["contacts"]
                blocks.append(
                    f"collisions and stacking (%), {name} on {fam}: set down onto a placed piece "
                    f"{100 * c['onto_piece']:.1f} of placements, off the table at the end "
                    f"{100 * c['off_table']:.1f} of pieces"
                )
            if "perturbation" in s:
                pt = {k: 100 * v["mean"] for k, v in s["perturbation"].items()}
                blocks.append(
                    f"push after step {results['perturb']['after_step']}, {name} on {fam}: pushed piece's "
                    f"coverage {pt['coverage_before']:.1f} -> {pt['coverage_after']:.1f} %, Final "
                    f"{pt['final_before']:.1f} -> {pt['final_after']:.1f} % at the push, "
                    f"{pt['final_end']:.1f} % at the end"
                )
    return "\n\n".join(blocks)


def write_outputs(results: dict, families: list[str], out: Path) -> None:
    """results.json, results.csv and results.md in ``out``."""
    out.mkdir(parents=True, exist_ok=True)
    write_atomic(out / "results.json", json.dumps(results, indent=1, default=float) + "\n")
    lines = ["policy,family,metric,mean,se,ci95,n"]
    for name, pol in results["policies"].items():
        for fam, ms in pol["families"].items():
            for m, s in ms.items():
                if m not in METRICS:
                    continue
                lines.append(f"{name},{fam},{m},{s['mean']:.6f},{s['se']:.6f},{s['ci95']:.6f},{s['n']}")
    write_atomic(out / "results.csv", "\n".join(lines) + "\n")
    md = [
        "# mrchaos-bench results",
        "",
        "Mean ± 95 % interval, in percent. Rela and Final are the paper's metrics; "
        "IoU and sRela (strict Rela) are ours.",
        "",
        format_table(results, families, markdown=True),
    ]
    pieces = format_piece_table(results, families)
    if pieces:
        md += ["", pieces]
    order = format_order_table(results, families)
    if order:
        md += ["", order]
    if any(results.get("needs_flip", {}).values()):
        md += [
            "",
            "Figures that need a chiral piece turned over (evaluated with --flip): "
            + ", ".join(f"{fam} {k}" for fam, k in results["needs_flip"].items()),
        ]
    if results["skipped"]:
        md += ["", f"Skipped {len(results['skipped'])} figures:"]
        md += [f"- {fid}: {why}" for fid, why in results["skipped"]]
    write_atomic(out / "results.md", "\n".join(md) + "\n")
