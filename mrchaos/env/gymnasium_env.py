"""A single-world ``gymnasium`` version of the tangram environment, for users of other RL libraries.

import gymnasium as gym
env = gym.make("mrchaos.gym_env:Tangram-v0")          # or gym.make("mrchaos/Tangram-v0")
                                                      # after ``import mrchaos.env.gymnasium_env``
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import gymnasium as gym
import numpy as np
import torch
from tensordict import TensorDict

from mrchaos.env.tangram import EnvConfig, TangramEnv

__all__ = ["TangramGymEnv"]


class TangramGymEnv(gym.Env):
    """One world of :class:`mrchaos.env.tangram.TangramEnv` behind the gymnasium API.

    Observation: ``Box(0, 255, (2, H, W), uint8)``; action: ``MultiDiscrete(grid)``;
    ``info`` holds the per-piece coverage, the step's raw coverage, Final and IoU.
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 1}

    def __init__(self, config: EnvConfig | None = None, render_mode: str | None = None, **overrides: Any) -> None:
        cfg = replace(config or EnvConfig(), num_worlds=1, **overrides)
        self.env = TangramEnv(cfg, seed=0)
        s = cfg.view.size
        self.observation_space = gym.spaces.Box(0, 255, (2, s, s), np.uint8)
        self.action_space = gym.spaces.MultiDiscrete(np.array(self.env.grid.nvec))
        self.render_mode = render_mode
        self._last: np.ndarray | None = None

    def _info(self, td: TensorDict) -> dict:
        info = td["info"]
        return {
            "coverage": info["coverage"][0].numpy(),
            "step_coverage": float(info["step_coverage"][0, 0]),
            "final": float(info["final"][0, 0]),
            "iou": float(info["iou"][0, 0]),
        }

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        if seed is not None:
            self.env.set_seed(seed)
        td = TensorDict(batch_size=[1])
        if options and "preassembled" in options:
            td["preassembled"] = torch.tensor([int(options["preassembled"])])
        out = self.env.reset(td)
        self._last = out["observation"][0].numpy()
        return self._last, self._info(out)

    def step(self, action):
        a = torch.as_tensor(np.asarray(action), dtype=torch.int64).reshape(1, 3)
        out = self.env.step(TensorDict(action=a, batch_size=[1]))["next"]
        self._last = out["observation"][0].numpy()
        return (
            self._last,
            float(out["reward"][0, 0]),
            bool(out["terminated"][0, 0]),
            bool(out["truncated"][0, 0]),
            self._info(out),
        )

    def render(self):
        """Silhouette (blue) and current view (grey) as an RGB image."""
        if self._last is None:
            return None
        sil, view = self._last[0] > 0, self._last[1] > 0
        rgb = np.full(sil.shape + (3,), 255, np.uint8)
        rgb[sil] = (170, 200, 240)
        rgb[view] = (60, 60, 60)
        return rgb

    def close(self) -> None:
        self.env.close()


gym.register(id="mrchaos/Tangram-v0", entry_point=TangramGymEnv)
gym.register(id="Tangram-v0", entry_point=TangramGymEnv)
