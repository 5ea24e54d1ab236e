"""MuJoCo's offscreen OpenGL backend, chosen when a picture is first drawn and not before.

MuJoCo reads ``MUJOCO_GL`` once, when it is first imported, and torchrl imports it long
before anyone knows whether rendering will be needed. The rasteriser path (the env's
default, training, the bench) draws nothing with OpenGL, so importing mrchaos touches no
OpenGL setting. Only :func:`make_renderer` does: it keeps a ``MUJOCO_GL`` the user has set,
uses GLFW where there is a display, and otherwise takes the first headless backend whose
library is on the machine: EGL (software Mesa on a CPU machine, the driver on an NVIDIA
one), then OSMesa. When none works it raises :class:`RenderingUnavailable`, one line that
names what to install.
"""

from __future__ import annotations

import ctypes.util
import os
from collections.abc import Callable, Mapping

from mrchaos.core.errors import MrchaosError, first_line

__all__ = ["HEADLESS_BACKENDS", "RenderingUnavailable", "choose_backend", "make_renderer"]

#: Headless backends in the order they are tried, with the shared library each one loads.
HEADLESS_BACKENDS: dict[str, str] = {"egl": "EGL", "osmesa": "OSMesa"}
_INSTALL = {
    "egl": "EGL (Debian: apt-get install libegl1 libegl-mesa0; NVIDIA machines: the driver's libEGL)",
    "osmesa": "OSMesa (Debian: apt-get install libosmesa6)",
}
_DISABLED = ("disable", "disabled", "off", "false", "0")


class RenderingUnavailable(MrchaosError, RuntimeError):
    """No OpenGL backend can draw MuJoCo images on this machine (the message says what to install)."""


def choose_backend(
    environ: Mapping[str, str] | None = None, find_library: Callable[[str], str | None] = ctypes.util.find_library
) -> str:
    """The backend to render with: the user's ``MUJOCO_GL``, ``glfw`` with a display, else EGL or OSMesa.

    Raises :class:`RenderingUnavailable` when rendering is switched off or no headless library exists.
    """
    env = os.environ if environ is None else environ
    user = env.get("MUJOCO_GL", "").strip().lower()
    if user in _DISABLED:
        raise RenderingUnavailable(f"MUJOCO_GL={user} switches MuJoCo rendering off; unset it or set MUJOCO_GL=egl")
    if user:
        return user
    if env.get("DISPLAY") or env.get("WAYLAND_DISPLAY"):
        return "glfw"
    for backend, lib in HEADLESS_BACKENDS.items():
        if find_library(lib):
            return backend
    raise RenderingUnavailable(
        "MuJoCo rendering needs headless OpenGL and found neither libEGL nor libOSMesa: install "
        + " or ".join(_INSTALL.values())
    )


def _context_class(backend: str) -> type:
    """mujoco's GLContext class for a backend, imported now."""
    # PyOpenGL raises AttributeError, not ImportError, when its platform library is
    # missing, so every failure to load is caught and explained here.
    try:
        if backend == "egl":
            from mujoco.egl import GLContext
        elif backend == "osmesa":
            from mujoco.osmesa import GLContext
        elif backend in ("glfw", "glx", "enable", "enabled", "on", "true", "1"):
            from mujoco.glfw import GLContext
        else:
            raise RenderingUnavailable(f"MUJOCO_GL={backend} is not a MuJoCo backend; use egl, osmesa or glfw")
    except RenderingUnavailable:
        raise
    except Exception as e:  # noqa: BLE001 - any loader failure means this backend is unusable
        hint = _INSTALL.get(backend, "a working OpenGL")
        raise RenderingUnavailable(
            f"MuJoCo's {backend} backend failed to load ({type(e).__name__}: {first_line(e)}); install {hint}"
        ) from e
    return GLContext


def make_renderer(model, height: int, width: int):
    """A ``mujoco.Renderer`` for ``model`` on the chosen backend, or :class:`RenderingUnavailable`."""
    import mujoco
    from mujoco.rendering.classic import gl_context

    backend = choose_backend()
    # mujoco.Renderer takes its context class from this module attribute, which mujoco
    # set from MUJOCO_GL at import time (often before MUJOCO_GL was known); point it at
    # the backend chosen now.
    gl_context.GLContext = _context_class(backend)
    try:
        return mujoco.Renderer(model, height=height, width=width)
    except Exception as e:  # noqa: BLE001 - a context that cannot open is reported, not traced
        raise RenderingUnavailable(
            f"MuJoCo could not open an OpenGL context with MUJOCO_GL={backend} ({first_line(e) or type(e).__name__}); "
            f"install {_INSTALL.get(backend, 'a working OpenGL')}, or set MUJOCO_GL to another backend"
        ) from e
