"""How every mrchaos command fails: one line on stderr and exit code 2, never a traceback.

The commands import mujoco, torch and torchrl, which can fail at import time for reasons
outside mrchaos (a ``MUJOCO_GL`` naming a library that is not installed, a broken wheel).
:func:`run_command` imports them first, one by one, so such a failure is reported with
the package's name, and then runs the command, turning mrchaos's own errors (bad files,
keys, values) into the same one-line form. This module imports only the standard library
and :mod:`mrchaos.core.errors`, so the handler itself cannot fail on an import.
"""

from __future__ import annotations

import importlib
import os
import sys
from collections.abc import Callable, Sequence

from mrchaos.core.errors import MrchaosError, first_line

__all__ = ["DependencyError", "import_dependencies", "run_command", "TRAINING_STACK"]

#: What the env, the trainer and the bench import, in dependency order.
TRAINING_STACK = ("numpy", "torch", "mujoco", "tensordict", "torchrl", "shapely")


class DependencyError(MrchaosError, ImportError):
    """A required package failed to import; the message names it and, where known, the fix."""


def _hint(package: str) -> str:
    gl = os.environ.get("MUJOCO_GL", "").strip().lower()
    if package == "mujoco" and gl in ("osmesa", "egl"):
        lib = {
            "osmesa": "libOSMesa (apt-get install libosmesa6)",
            "egl": "libEGL (apt-get install libegl1 libegl-mesa0)",
        }
        return f"; MUJOCO_GL={gl} needs {lib[gl]}, or unset MUJOCO_GL to let mrchaos choose"
    return f"; reinstall it with: pip install -e . (or pip install --force-reinstall {package})"


def import_dependencies(packages: Sequence[str] = TRAINING_STACK) -> None:
    """Import each package, raising :class:`DependencyError` that names the first one that fails."""
    for name in packages:
        try:
            importlib.import_module(name)
        except Exception as e:  # noqa: BLE001 - whatever a dependency raises on import is reported
            raise DependencyError(f"importing {name} failed ({type(e).__name__}: {first_line(e)}){_hint(name)}") from e


def run_command(prog: str, body: Callable[[], int], dependencies: Sequence[str] = TRAINING_STACK) -> int:
    """Run a command's body after importing its dependencies; user errors become one line and exit 2."""
    try:
        import_dependencies(dependencies)
        return body()
    except (MrchaosError, ValueError, KeyError, OSError) as e:
        msg = e.args[0] if isinstance(e, KeyError) and e.args else e
        print(f"{prog}: error: {msg}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"{prog}: interrupted", file=sys.stderr)
        return 130
