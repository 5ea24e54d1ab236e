"""mrchaos: robotic tangram assembly from silhouettes, learnt on chaos objects."""

import os as _os

# MuJoCo picks its OpenGL backend when first imported; without a display, offscreen
# rendering needs OSMesa (or EGL), so choose it before anything imports mujoco.
if "MUJOCO_GL" not in _os.environ and not _os.environ.get("DISPLAY"):
    _os.environ["MUJOCO_GL"] = "osmesa"

__version__ = "0.1.0"
