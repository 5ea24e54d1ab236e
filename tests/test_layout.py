"""The package's shape: every module imports on its own, layers import only downwards, no
import cycles (lazy imports included), and callers use the env's public surface."""

from __future__ import annotations

import ast
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "mrchaos"
#: Subpackages in the order data flows; a module may import its own layer and those before it.
LAYERS = ("core", "figures", "tasks", "sim", "env", "loggers", "learn", "bench", "cli")
#: Top-level modules and the layer they belong to (``gym_env`` is the kept gymnasium alias).
TOP_LEVEL = {"mrchaos": "core", "mrchaos.gym_env": "env"}
#: What callers outside the env must not read: its parts and its solution.
ENV_PARTS = {
    "worlds",
    "sampler",
    "target",
    "target_ids",
    "_worlds",
    "_sampler",
    "_target",
    "_target_ids",
    "_silhouette",
    "_np_rng",
}
#: Names whose attributes are not objects' parts: parsed command-line options (``args.worlds``).
NOT_OBJECTS = {"args"}


def _modules() -> dict[str, Path]:
    out = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        rel = path.relative_to(ROOT).with_suffix("")
        parts = rel.parts[:-1] if rel.name == "__init__" else rel.parts
        out[".".join(parts)] = path
    return out


MODULES = _modules()


def _layer(module: str) -> str:
    if module in TOP_LEVEL:
        return TOP_LEVEL[module]
    return module.split(".")[1]


def _imports(path: Path) -> set[str]:
    """Every mrchaos module a file imports, at the top or inside functions."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names = [node.module] + [f"{node.module}.{a.name}" for a in node.names]
        else:
            continue
        found.update(n for n in names if n in MODULES)
    return found


def test_every_subpackage_is_a_known_layer():
    layers = {_layer(m) for m in MODULES}
    assert layers <= set(LAYERS), layers - set(LAYERS)


def test_layers_import_only_downwards():
    bad = []
    for mod, path in MODULES.items():
        own = LAYERS.index(_layer(mod))
        for dep in _imports(path):
            if LAYERS.index(_layer(dep)) > own:
                bad.append(f"{mod} ({_layer(mod)}) imports {dep} ({_layer(dep)})")
    assert not bad, "\n".join(bad)


def test_no_import_cycles_lazy_imports_included():
    graph = {m: _imports(p) - {m} for m, p in MODULES.items()}
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(m: str) -> None:
        state[m] = 1
        stack.append(m)
        for d in sorted(graph[m]):
            if state.get(d) == 1:
                raise AssertionError("import cycle: " + " -> ".join(stack[stack.index(d) :] + [d]))
            if d not in state:
                visit(d)
        stack.pop()
        state[m] = 2

    for m in sorted(graph):
        if m not in state:
            visit(m)


#: Heavy libraries with no import-time settings of ours, loaded once before the forks. MuJoCo
#: and OpenGL are not among them: they read ``MUJOCO_GL`` when imported, which a module may set.
PRELOADED = ("numpy", "torch", "tensordict", "torchrl")

#: Run in a fresh interpreter: load the heavy libraries once, then import each module in its own
#: forked child, so a child holds nothing of mrchaos but what its module pulls in.
_FORK_EACH = """
import importlib, os, sys, traceback
for lib in {preloaded!r}:
    try:
        importlib.import_module(lib)
    except ImportError:
        pass
assert not any(m == "mrchaos" or m.startswith("mrchaos.") for m in sys.modules)
for name in {names!r}:
    pid = os.fork()
    if pid == 0:
        try:
            importlib.import_module(name)
        except BaseException:
            sys.stdout.write(name + ": " + traceback.format_exc().strip().splitlines()[-1] + "\\n")
            sys.stdout.flush()
            os._exit(1)
        os._exit(0)
    _, status = os.waitpid(pid, 0)
    print("done", name, os.waitstatus_to_exitcode(status), flush=True)
"""


def test_every_module_imports_on_its_own_in_a_fresh_interpreter():
    env = {k: v for k, v in os.environ.items() if k != "MUJOCO_GL"}
    names = sorted(MODULES)
    code = _FORK_EACH.format(preloaded=PRELOADED, names=names)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=600)
    assert out.returncode == 0, out.stderr[-2000:]
    lines = out.stdout.splitlines()
    done = {n: int(c) for _, n, c in (line.split() for line in lines if line.startswith("done "))}
    assert sorted(done) == names, set(names) - set(done)
    # A failing child writes its error line before its parent reports its exit code.
    failures = [line for line in lines if not line.startswith("done ")]
    failures += [f"{n}: exit {c}" for n, c in done.items() if c]
    assert not failures, "\n".join(failures)


def _env_part_reads(path: Path) -> list[str]:
    """Reads of the env's parts (``x.worlds``) and of other objects' private attributes (``x._y``)."""
    out = []
    for node in ast.walk(ast.parse(path.read_text())):
        if not isinstance(node, ast.Attribute):
            continue
        owner = node.value.id if isinstance(node.value, ast.Name) else None
        own = owner in ("self", "cls")
        if owner in NOT_OBJECTS:
            continue
        if node.attr in ENV_PARTS and not own:
            out.append(f"{path.relative_to(ROOT)}:{node.lineno}: .{node.attr}")
        elif node.attr.startswith("_") and not node.attr.startswith("__") and not own and owner is not None:
            out.append(f"{path.relative_to(ROOT)}:{node.lineno}: {owner}.{node.attr}")
    return out


@pytest.mark.parametrize("folder", ["mrchaos", "benchmarks", "tools"])
def test_callers_use_the_public_surface(folder):
    env_dir = PACKAGE / "env"
    files = [p for p in sorted((ROOT / folder).rglob("*.py")) if env_dir not in p.parents]
    bad = [hit for p in files for hit in _env_part_reads(p)]
    assert not bad, "\n".join(bad)
