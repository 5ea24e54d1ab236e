"""Pictures of the robot at work: scene snapshots rendered from a viewpoint, and video files.

The executor keeps the state (qpos) of chosen worlds a few times per simulated second;
:class:`SceneRenderer` draws such snapshots with MuJoCo's renderer from a camera that sees
the arm, the staging area and the workspace, and :func:`write_video` writes frames as a GIF
(Pillow) or an MP4 (OpenCV).
"""

from __future__ import annotations

import atexit
from pathlib import Path

import mujoco
import numpy as np

from mrchaos.sim.opengl import make_renderer

__all__ = ["SceneRenderer", "write_video"]


class SceneRenderer:
    """Renders RGB frames of scene states (qpos vectors) of one model.

    Args:
        model: the scene (with the robot).
        width, height: image size (px).
        lookat, distance, azimuth, elevation: the free camera (m, deg); the default sees
            the table from the side opposite the robot.
    """

    def __init__(
        self,
        model: mujoco.MjModel,
        width: int = 320,
        height: int = 240,
        lookat: tuple[float, float, float] = (0.12, -0.12, 0.08),
        distance: float = 1.25,
        azimuth: float = 120.0,
        elevation: float = -40.0,
    ) -> None:
        self.model = model
        self.renderer = make_renderer(model, height=height, width=width)
        self.data = mujoco.MjData(model)
        self.camera = mujoco.MjvCamera()
        self.camera.lookat[:] = lookat
        self.camera.distance, self.camera.azimuth, self.camera.elevation = distance, azimuth, elevation
        self.option = mujoco.MjvOption()
        self.option.sitegroup[:] = 0
        self.option.geomgroup[3] = 0  # collision shapes: the visual ones are drawn
        # The GL context must go before the interpreter tears OpenGL down.
        atexit.register(self.close)

    def render(self, qpos: np.ndarray) -> np.ndarray:
        """(H, W, 3) uint8 image of the scene in state qpos."""
        self.data.qpos[:] = qpos
        mujoco.mj_kinematics(self.model, self.data)
        self.renderer.update_scene(self.data, camera=self.camera, scene_option=self.option)
        return self.renderer.render().copy()

    def close(self) -> None:
        """Free the GL context (idempotent)."""
        if self.renderer is not None:
            self.renderer.close()
            self.renderer = None


def write_video(frames: list[np.ndarray], path: str | Path, fps: float = 10.0) -> Path:
    """Write RGB frames to ``path``: ``.gif`` with Pillow, ``.mp4`` with OpenCV (written via a temporary file)."""
    path = Path(path)
    if not frames:
        raise ValueError(f"{path}: no frames to write")
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.stem + ".partial" + path.suffix)
    suffix = path.suffix.lower()
    if suffix == ".gif":
        from PIL import Image

        images = [Image.fromarray(f) for f in frames]
        images[0].save(tmp, save_all=True, append_images=images[1:], duration=int(1000 / fps), loop=0)
    elif suffix == ".mp4":
        import cv2

        h, w = frames[0].shape[:2]
        writer = cv2.VideoWriter(str(tmp), cv2.VideoWriter.fourcc(*"mp4v"), fps, (w, h))
        if not writer.isOpened():
            raise OSError(f"{path}: OpenCV cannot write MP4 here; write a .gif instead")
        for f in frames:
            writer.write(cv2.cvtColor(f, cv2.COLOR_RGB2BGR))
        writer.release()
    else:
        raise ValueError(f"{path}: video must end in .gif or .mp4")
    tmp.replace(path)
    return path
