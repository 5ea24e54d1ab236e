"""The OpenGL backend is chosen only for rendering, the user's MUJOCO_GL wins, and failures are one line."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from mrchaos.sim.opengl import RenderingUnavailable, choose_backend


def _python(code: str, **env: str | None) -> subprocess.CompletedProcess:
    full = {k: v for k, v in os.environ.items() if k not in ("MUJOCO_GL", "PYOPENGL_PLATFORM", "DISPLAY")}
    full.update({k: v for k, v in env.items() if v is not None})
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=full, timeout=300)


def test_import_leaves_a_user_mujoco_gl_alone():
    r = _python(
        "import os, mrchaos, mrchaos.env.tangram, mrchaos.bench.benchmark; print(os.environ['MUJOCO_GL'])",
        MUJOCO_GL="egl",
    )
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "egl"


def test_import_sets_no_backend_when_none_is_given():
    r = _python(
        "import os, mrchaos, mrchaos.env.tangram, mrchaos.bench.benchmark, mrchaos.learn.ppo; "
        "print(os.environ.get('MUJOCO_GL', '-'), os.environ.get('PYOPENGL_PLATFORM', '-'))"
    )
    assert r.returncode == 0, r.stderr
    assert r.stdout.split() == ["-", "-"]


def test_backend_order_egl_then_osmesa():
    libs = {"EGL": "libEGL.so.1", "OSMesa": "libOSMesa.so.8"}
    assert choose_backend({}, libs.get) == "egl"
    assert choose_backend({}, {"OSMesa": "libOSMesa.so.8"}.get) == "osmesa"
    assert choose_backend({"MUJOCO_GL": "osmesa"}, libs.get) == "osmesa"  # the user's choice wins
    assert choose_backend({"DISPLAY": ":0"}, libs.get) == "glfw"


def test_no_backend_is_one_line_naming_what_to_install():
    with pytest.raises(RenderingUnavailable) as e:
        choose_backend({}, lambda name: None)
    msg = str(e.value)
    assert "\n" not in msg and "libegl1" in msg and "libosmesa6" in msg
    with pytest.raises(RenderingUnavailable, match="switches MuJoCo rendering off"):
        choose_backend({"MUJOCO_GL": "disable"}, lambda name: "x")


def test_rendering_with_no_usable_backend_raises_the_one_line_error():
    code = (
        "import mujoco\nfrom mrchaos.sim.opengl import RenderingUnavailable, make_renderer\n"
        "m = mujoco.MjModel.from_xml_string('<mujoco><worldbody><geom size=\"0.1\"/></worldbody></mujoco>')\n"
        "try:\n    make_renderer(m, 8, 8)\nexcept RenderingUnavailable as e:\n    print('ERR', e)\n"
    )
    r = _python(code, MUJOCO_GL="disable")
    assert r.returncode == 0, r.stderr
    assert r.stdout.startswith("ERR MUJOCO_GL=disable") and r.stdout.count("\n") == 1


def test_bench_without_a_backend_exits_2_with_one_line(tmp_path):
    code = (
        "import sys\nfrom mrchaos.cli.bench import main\n"
        f"sys.exit(main(['--policy', 'oracle', '--random-objects', '1', '--families', 'random', "
        f"'--placement', 'robot', '--video', {str(tmp_path / 'v.gif')!r}, '--out', {str(tmp_path)!r}]))"
    )
    r = _python(code, MUJOCO_GL="disable")
    assert r.returncode == 2, r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("mrchaos-bench: error: MUJOCO_GL=disable"), r.stderr


def test_a_dependency_failing_on_import_is_one_line_naming_it():
    # A MUJOCO_GL value mujoco rejects makes `import mujoco` raise inside torchrl's import.
    code = "import sys\nfrom mrchaos.cli.bench import main\nsys.exit(main(['--policy', 'oracle']))"
    r = _python(code, MUJOCO_GL="no-such-backend")
    assert r.returncode == 2
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "importing mujoco failed" in lines[0] and "Traceback" not in r.stderr, r.stderr
