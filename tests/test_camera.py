"""The MuJoCo camera path against the rasteriser (needs headless OpenGL: Mesa's EGL or OSMesa)."""

import numpy as np
import pytest
import torch
from tensordict import TensorDict

from mrchaos.core.raster import rasterize
from mrchaos.env.tangram import EnvConfig, TangramEnv
from mrchaos.sim.camera import MujocoCamera
from mrchaos.tasks.sampler import CacheConfig, TaskConfig

pytestmark = pytest.mark.usefixtures("rendering")


def _scenes(n_worlds: int, seed: int) -> TangramEnv:
    env = TangramEnv(EnvConfig(num_worlds=n_worlds, task=TaskConfig(cache=CacheConfig(size=64))), seed=seed)
    env.reset()
    g = torch.Generator().manual_seed(seed)
    steps = int(torch.randint(1, 7, (1,), generator=g))
    nvec = torch.tensor(env.grid.nvec)
    for _ in range(steps):  # random placements: spread, stacked and tilted pieces
        a = (torch.rand((n_worlds, 3), generator=g) * nvec).long()
        env.step(TensorDict(action=a, batch_size=env.batch_size))
    return env


def test_rasteriser_and_mujoco_camera_agree_on_50_scenes():
    ious = []
    for seed in range(5):
        env = _scenes(10, seed)
        w = env.worlds
        ras = rasterize(w.footprint, env.view, visible=w.placed, heights=w.top)
        cam = MujocoCamera(w, env.view)
        ren = cam.render(np.arange(10))
        cam.close()
        a, b = ras.ids >= 0, ren.ids >= 0
        ious.append(((a & b).sum((1, 2)).float() / (a | b).sum((1, 2)).clamp(min=1).float()))
        # Same piece seen at (almost) every pixel.
        same = ((ras.ids == ren.ids) | (~a & ~b)).float().mean((1, 2))
        assert (same > 0.98).all()
    ious = torch.cat(ious)
    assert len(ious) == 50
    print(f"IoU rasteriser vs MuJoCo camera: mean {ious.mean():.4f}, min {ious.min():.4f}")
    assert (ious >= 0.97).all()
    assert ious.mean() > 0.99


def test_env_on_the_mujoco_camera():
    env = TangramEnv(EnvConfig(num_worlds=2, camera="mujoco", task=TaskConfig(cache=CacheConfig(size=16))), seed=0)
    td = env.reset()
    out = env.step(td.set("action", env.action_spec.rand()))["next"]
    assert out["observation"].shape == (2, 2, 120, 120)
    assert out["observation"][:, 1].max() == 255
    env.close()


def test_perspective_camera_renders():
    env = _scenes(2, 0)
    cam = MujocoCamera(env.worlds, env.view, camera="overhead")
    ren = cam.render(np.arange(2))
    cam.close()
    assert ren.ids.shape == (2, 120, 120) and (ren.ids >= 0).any()
