"""The root of mrchaos's own errors: bad input a user can fix, reported as one line.

It imports nothing, so the command-line programs can name the errors they catch even
when a heavy dependency (mujoco, torchrl) fails to import.
"""

from __future__ import annotations

__all__ = ["MrchaosError", "first_line"]


class MrchaosError(Exception):
    """An error in what the user gave (a file, a key, a value); its message names the culprit."""


def first_line(e: BaseException, limit: int = 200) -> str:
    """The first line of an exception's message, at most ``limit`` characters ("" when it has none)."""
    text = str(e).strip()
    return text.splitlines()[0][:limit] if text else ""
