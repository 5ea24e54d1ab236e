"""The two-stage curriculum as a TorchRL ``Transform``.

Stage 1 ("local"): each reset pre-assembles k ~ U{0..j-1} pieces at their target
poses and the episode ends after one placement, so the agent learns to place one
piece well in context. Stage 2 ("global"): whole episodes from k = 0. The switch
happens when the stage-1 reward has stopped improving: the best iteration of the
last W is no better than the best before them plus epsilon.

The stage is a scalar tensor buffer: the trainer's env reads it, collector worker processes
share its memory, and Ray actors are sent it (:func:`mrchaos.learn.collection.publish_stage`).
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from torchrl.envs import Transform

__all__ = ["CurriculumTransform", "LOCAL", "GLOBAL"]

LOCAL, GLOBAL = 1, 2


class CurriculumTransform(Transform):
    """Writes ``preassembled`` and ``horizon`` into every reset, by stage.

    Args:
        num_pieces: j, pieces per episode.
        stages: "both", "local" or "global".
        window: W iterations.
        epsilon: required improvement over the window.
        min_iters: earliest switch.
        seed: seed of the transform's own generator (the k draws).
        stage: the scalar tensor to hold the stage in (the trainer's, which worker processes
            share; default: one of its own).
    """

    def __init__(
        self,
        num_pieces: int,
        stages: str = "both",
        window: int = 20,
        epsilon: float = 0.01,
        min_iters: int = 20,
        seed: int = 0,
        stage: torch.Tensor | None = None,
    ) -> None:
        super().__init__(in_keys=[], out_keys=[])
        if stages not in ("both", "local", "global"):
            raise ValueError(f"curriculum stages must be 'both', 'local' or 'global', got {stages!r}")
        self.num_pieces = num_pieces
        self.stages = stages
        self.window = window
        self.epsilon = epsilon
        self.min_iters = min_iters
        if stage is None:
            stage = torch.tensor(GLOBAL if stages == "global" else LOCAL)
        self.register_buffer("stage", stage)
        self.register_buffer("switched_at", torch.tensor(-1))
        self.history: list[float] = []
        self.rng = torch.Generator().manual_seed(seed)

    @property
    def is_local(self) -> bool:
        return int(self.stage) == LOCAL

    def _reset_env_preprocess(self, tensordict: TensorDictBase | None) -> TensorDictBase:
        parent = self.parent
        n = parent.batch_size[0]
        if tensordict is None:
            from tensordict import TensorDict

            tensordict = TensorDict(batch_size=parent.batch_size)
        if self.is_local:
            k = torch.randint(0, self.num_pieces, (n,), generator=self.rng)
            horizon = torch.ones(n, dtype=torch.int64)
        else:
            k = torch.zeros(n, dtype=torch.int64)
            horizon = torch.zeros(n, dtype=torch.int64)
        tensordict.set("preassembled", k)
        tensordict.set("horizon", horizon)
        return tensordict

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        tensordict_reset.exclude("preassembled", "horizon", inplace=True)
        return tensordict_reset

    def update(self, iteration: int, mean_reward: float) -> bool:
        """Record one iteration's stage-1 mean reward; switch to stage 2 when it plateaus. Returns True on
        the switch."""
        if not self.is_local or self.stages != "both":
            return False
        self.history.append(float(mean_reward))
        h = self.history
        if len(h) < max(self.min_iters, self.window + 1):
            return False
        if max(h[-self.window :]) <= max(h[: -self.window]) + self.epsilon:
            self.stage.fill_(GLOBAL)
            self.switched_at.fill_(iteration)
            return True
        return False

    def force_switch(self, iteration: int) -> bool:
        """Switch to stage 2 now (a time cap); returns True if it switched."""
        if not self.is_local or self.stages != "both":
            return False
        self.stage.fill_(GLOBAL)
        self.switched_at.fill_(iteration)
        return True

    def extra_state(self) -> dict:
        """Everything needed to resume the curriculum (besides the buffers)."""
        return {"history": list(self.history), "rng": self.rng.get_state()}

    def load_extra_state(self, state: dict) -> None:
        self.history = list(state["history"])
        self.rng.set_state(state["rng"])
