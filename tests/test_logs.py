"""The commands are quiet by default: mrchaos's progress lines, no library's INFO lines unless -v."""

import logging

import pytest
import torchrl  # noqa: F401 - installs its own INFO handler on import, the noise being silenced

from mrchaos.cli.logs import configure_logging


@pytest.fixture(autouse=True)
def _restore_logging():
    levels = {n: logging.getLogger(n).level for n in ("", "mrchaos", "torchrl", "OpenGL")}
    yield
    for n, level in levels.items():
        logging.getLogger(n).setLevel(level)


def _emit(caplog) -> str:
    caplog.clear()
    logging.getLogger("torchrl").info("NOISE-torchrl")
    logging.getLogger("OpenGL.acceleratesupport").info("NOISE-opengl")
    logging.getLogger("mrchaos.learn.bc").info("PROGRESS")
    logging.getLogger("OpenGL.acceleratesupport").warning("WARNED")
    return caplog.text


def test_library_info_lines_are_silent_unless_verbose(caplog):
    configure_logging(verbose=False)
    text = _emit(caplog)
    assert "NOISE" not in text and "PROGRESS" in text and "WARNED" in text
    assert not logging.getLogger("torchrl").isEnabledFor(logging.INFO)
    configure_logging(verbose=False, progress=False)  # the bench: its own tables only
    text = _emit(caplog)
    assert "NOISE" not in text and "PROGRESS" not in text and "WARNED" in text
    configure_logging(verbose=True)
    text = _emit(caplog)
    assert "NOISE-opengl" in text and "PROGRESS" in text
    assert logging.getLogger("torchrl").isEnabledFor(logging.INFO)


def test_torchrl_imported_after_the_set_up_stays_quiet():
    """torchrl reads its level when first imported, which a command does after setting up."""
    import os
    import subprocess
    import sys

    code = (
        "from mrchaos.cli.logs import configure_logging\n"
        "configure_logging()\n"
        "import torch\n"
        "from torchrl.data import LazyTensorStorage, ReplayBuffer\n"
        "ReplayBuffer(storage=LazyTensorStorage(4)).extend(torch.zeros(4, 1))\n"
        "import logging\n"
        "logging.getLogger('torchrl').warning('WARNED')\n"
    )
    env = {k: v for k, v in os.environ.items() if k != "RL_LOGGING_LEVEL"}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    text = out.stdout + out.stderr
    assert "LazyTensorStorage" not in text and "INFO" not in text
    assert "WARNED" in text
