"""How the commands log: mrchaos's own progress lines, and no library's INFO lines unless ``-v``.

torchrl installs its own INFO handler on import, and PyOpenGL announces its accelerator at INFO
once the root logger takes INFO, so a command that only set the root level would print both on
every run. Here libraries log at WARNING and above unless the user asks for more.
"""

from __future__ import annotations

import logging
import os

__all__ = ["configure_logging", "NOISY"]

#: Libraries whose INFO lines are silenced unless verbose (their warnings still show).
NOISY = ("torchrl", "OpenGL", "OpenGL_accelerate", "matplotlib", "PIL", "urllib3", "git")


def configure_logging(verbose: bool = False, progress: bool = True) -> None:
    """Set up the command's logging. ``progress``: mrchaos's own INFO lines (a training run's
    rounds and stages) are shown; ``verbose``: every library's INFO lines too."""
    level = logging.INFO if verbose else logging.WARNING
    root = logging.getLogger()
    if not root.handlers:  # a host's own handlers (pytest's, an embedding program's) are kept
        logging.basicConfig(format="%(asctime)s %(name)s %(levelname)s %(message)s")
    root.setLevel(level)
    logging.getLogger("mrchaos").setLevel(logging.INFO if verbose or progress else logging.WARNING)
    # torchrl sets its logger's and its handler's level from this variable when first imported,
    # which a command does after this call: set here, it holds for that import too.
    os.environ.setdefault("RL_LOGGING_LEVEL", logging.getLevelName(level))
    for name in NOISY:
        # torchrl's own handler would print its INFO lines whatever the root's level is.
        logging.getLogger(name).setLevel(level)
