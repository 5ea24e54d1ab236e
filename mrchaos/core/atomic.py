"""Atomic file writes: a file is either its old self or wholly new, never half written.

Checkpoints, run files, chaos caches, figure sets and pictures all go through
:func:`write_atomic`, which writes a temporary file beside the target and renames it.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import BinaryIO

__all__ = ["write_atomic"]


def write_atomic(path: str | os.PathLike, data: bytes | str | Callable[[BinaryIO], object]) -> None:
    """Write a file so that readers see either the old or the complete new content. ``data`` is
    the content, or a function that writes it to an open binary file (large data, e.g.
    ``lambda f: torch.save(obj, f)``, goes to disk without a copy in memory)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    umask = os.umask(0)
    os.umask(umask)
    try:
        os.chmod(tmp, 0o666 & ~umask)  # mkstemp makes owner-only files; keep the usual mode
        with os.fdopen(fd, "wb") as f:
            if callable(data):
                data(f)
            else:
                f.write(data.encode() if isinstance(data, str) else data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
