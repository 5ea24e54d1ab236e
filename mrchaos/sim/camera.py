"""The MuJoCo camera path: the same top-down view, drawn by MuJoCo's own offscreen renderer.

It renders each world's segmentation and depth through the scene's orthographic
``overhead_ortho`` camera (or the reference's perspective ``overhead`` camera,
whose 4:3 image is cropped to its centre) and turns them into the
rasteriser's output, so the environment can use either. It costs milliseconds per
world (Mesa's EGL on a CPU machine), against microseconds for the rasteriser,
so it serves to check the rasteriser and for users who want rendered images.
"""

from __future__ import annotations

import atexit

import mujoco
import numpy as np
import torch

from mrchaos.core.raster import Raster, View
from mrchaos.sim.opengl import make_renderer
from mrchaos.sim.scene import CAMERA_HEIGHT

__all__ = ["MujocoCamera"]


class MujocoCamera:
    """Renders piece-id and height images of batched worlds with ``mujoco.Renderer``.

    Args:
        worlds: the :class:`mrchaos.sim.worlds.Worlds` to draw.
        view: image size (and, for the orthographic camera, the extent built into the scene).
        camera: "overhead_ortho" (matches the rasteriser) or "overhead" (the reference's
            perspective camera, 0.25 m above the table, 55.37 deg field of view).
    """

    def __init__(self, worlds, view: View = View(), camera: str = "overhead_ortho") -> None:
        self.worlds = worlds
        self.view = view
        self.camera = camera
        model = worlds.model
        self._perspective = camera == "overhead"
        w = view.size * 4 // 3 if self._perspective else view.size
        self.renderer = make_renderer(model, height=view.size, width=w)
        # geom id -> piece id (the body's index among the pieces), -1 for the table and the rest.
        names = worlds.piece_set.names
        self._geom_piece = np.full(model.ngeom + 1, -1, dtype=np.int64)
        for g in range(model.ngeom):
            body = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_BODY, model.geom_bodyid[g])
            if body in names:
                self._geom_piece[g] = names.index(body)
        self._data = mujoco.MjData(model)
        # Only geoms are seen: sites (markers) would cover pixels of the pieces.
        self._option = mujoco.MjvOption()
        self._option.sitegroup[:] = 0
        # The GL context must go before the interpreter tears OpenGL down.
        atexit.register(self.close)

    def _crop(self, img: np.ndarray) -> np.ndarray:
        if not self._perspective:
            return img
        off = (img.shape[1] - self.view.size) // 2
        return img[:, off : off + self.view.size]

    def render(self, rows: np.ndarray) -> Raster:
        """Raster of the given worlds (ids int8 and heights), in the rasteriser's layout."""
        model = self.worlds.model
        ids = np.full((len(rows), self.view.size, self.view.size), -1, dtype=np.int8)
        height = np.zeros((len(rows), self.view.size, self.view.size), dtype=np.float32)
        for k, r in enumerate(rows):
            self.worlds.batch.get_data(int(r), self._data)
            mujoco.mj_forward(model, self._data)
            self.renderer.update_scene(self._data, camera=self.camera, scene_option=self._option)
            self.renderer.enable_segmentation_rendering()
            seg = self._crop(self.renderer.render())
            self.renderer.disable_segmentation_rendering()
            self.renderer.enable_depth_rendering()
            depth = self._crop(self.renderer.render())
            self.renderer.disable_depth_rendering()
            geom = np.where(seg[..., 1] == int(mujoco.mjtObj.mjOBJ_GEOM), seg[..., 0], -1)
            ids[k] = self._geom_piece[geom]
            height[k] = np.where(ids[k] >= 0, CAMERA_HEIGHT - depth, 0.0)
        return Raster(torch.from_numpy(ids), torch.from_numpy(height))

    def close(self) -> None:
        """Free the GL context (idempotent)."""
        if self.renderer is not None:
            self.renderer.close()
            self.renderer = None
