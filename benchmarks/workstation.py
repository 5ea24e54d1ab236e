"""One check of a GPU workstation: does ``device=cuda`` train, resume and bench, and how does
learning throughput scale with the collector's workers, on the GPU and on the CPU alone?

    python benchmarks/workstation.py [--out runs/workstation] [--iterations 1] [--max-workers 8] [--minutes 7.5]

In order, each part timed:

1. the tests marked ``cuda`` (``tests/test_cuda.py``);
2. ``conf/smoke.yaml`` trained with ``device=cuda`` to its end, resumed for one more iteration,
   then benched (``mrchaos-bench`` on its Random family);
3. end-to-end PPO throughput (``benchmarks/train_throughput.py``'s measure: ``conf/full.yaml``,
   4096 frames an iteration, after one warm-up) of the default net and the context net, with the
   ``sync`` collector and with ``multisync`` at 1, 2, 4 and 8 workers (up to the machine's
   cores), on the GPU and on the CPU alone, with the collection/update split;
4. the update's precision and compilation: bf16 on and off, ``torch.compile`` on and off (the
   default net, ``sync``, on the GPU if there is one). Part 3 runs bf16 without compilation,
   which would take a third of each setting's time; part 4 says what compilation adds.

The measurements go in order of need and none starts that would end after ``--minutes`` (judged
by the longest so far); those left out are named. Writes ``workstation.json`` and
``workstation.md`` into ``--out`` and prints the table. On a machine
without CUDA it runs the CPU parts, says in one line which parts it skipped, and exits 0; a part
that fails is recorded with its error and the script exits 1.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
import traceback
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from train_throughput import learning_throughput  # noqa: E402

from mrchaos.core.atomic import write_atomic  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
NETS = ("spatial", "spatial-context")
#: The throughput grid's update settings: conf/full.yaml's bf16, without torch.compile, whose
#: compilation would take a third of each setting's time (compile's gain is measured apart).
GRID_PRECISION, GRID_COMPILE = "bf16", False
#: Fewer chaos objects than a run's cache: built for every setting, they only feed the tasks.
QUICK = ["task.cache.size=256"]


def _cpu_name() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def machine() -> dict[str, Any]:
    """What the figures were measured on."""
    cuda = torch.cuda.is_available()
    return {
        "cpu": _cpu_name(),
        "cores": os.cpu_count(),
        "gpu": torch.cuda.get_device_name(0) if cuda else None,
        "torch": torch.__version__,
        "cuda": torch.version.cuda if cuda else None,
    }


def _run(cmd: list[str], timeout: float) -> str:
    """Run a command in the repository; its last lines of output if it fails."""
    r = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=timeout)
    if r.returncode != 0:
        tail = "\n".join((r.stdout + r.stderr).strip().splitlines()[-15:])
        raise RuntimeError(f"{' '.join(cmd)} exited {r.returncode}:\n{tail}")
    return r.stdout


def cuda_tests() -> dict[str, Any]:
    """The tests marked ``cuda``."""
    out = _run(
        [sys.executable, "-m", "pytest", "-q", "-m", "cuda", "tests/test_cuda.py", "-p", "no:cacheprovider"], 300
    )
    return {"summary": out.strip().splitlines()[-1]}


def smoke_on_cuda() -> dict[str, Any]:
    """``conf/smoke.yaml`` with ``device=cuda``: trained to the end, resumed one iteration, benched."""
    with tempfile.TemporaryDirectory() as tmp:
        train = [sys.executable, "-m", "mrchaos.cli.train"]
        _run([*train, "conf/smoke.yaml", "device=cuda", f"runs_dir={tmp}", "--eval", "8"], 300)
        run = Path(tmp) / "smoke"
        # conf/smoke.yaml stops at 1280 frames of 128 an iteration: one more is 1408.
        _run([*train, "--resume", str(run), "collector.total_frames=1408", "--eval", "0"], 300)
        bench = [sys.executable, "-m", "mrchaos.cli.bench", "--families", "random", "--random-objects", "16"]
        out = _run([*bench, "--policy", str(run), "--out", str(Path(tmp) / "bench")], 300)
        rows = (run / "metrics.csv").read_text().strip().splitlines()
        return {"iterations": len(rows) - 1, "bench": [ln for ln in out.splitlines() if ln.startswith("|")][-3:]}


class Budget:
    """Starts no measurement that would end past the deadline, judged by the longest one so far,
    and keeps the labels of those it skipped."""

    def __init__(self, minutes: float) -> None:
        self.deadline = time.perf_counter() + 60 * minutes
        self.longest = 0.0
        self.skipped: list[str] = []

    def measure(self, label: str, fn: Callable[..., dict[str, Any]], *args: Any) -> dict[str, Any] | None:
        """``fn(*args)``, or None (and ``label`` kept) if it would likely end past the deadline."""
        if time.perf_counter() + self.longest > self.deadline:
            self.skipped.append(label)
            return None
        t = time.perf_counter()
        r = fn(*args)
        self.longest = max(self.longest, time.perf_counter() - t)
        return r


def _overrides(
    device: str,
    kind: str,
    workers: int,
    cores: int,
    precision: str = GRID_PRECISION,
    compiled: bool = GRID_COMPILE,
) -> list[str]:
    """The config overrides of one throughput setting (the grid's update settings unless told)."""
    # sync steps the env in this process on every core; multisync gives each worker one core, and
    # the update uses all of them while the workers wait.
    extra = (
        [f"threads={cores}", f"env.physics.nthread={cores}"]
        if kind == "sync"
        else [f"threads={cores}", f"collector.workers={workers}", "collector.worker_threads=1"]
    )
    update = [f"precision={precision}", f"compile={str(compiled).lower()}"]
    return [f"device={device}", f"collector.kind={kind}", *extra, *update, *QUICK]


Setting = tuple[str, str, str, int]  # device, net, collector kind, workers


def throughput_plan(devices: list[str], worker_counts: list[int]) -> tuple[list[Setting], list[Setting]]:
    """(device, net, collector, workers) settings in the order they are measured: first what the
    README's scale-out section needs (the default net's sweep on the first device, the context net
    at both ends, the CPU alone at both ends), then the rest, so that a tight budget drops the least."""
    first, most = devices[0], max(worker_counts)
    needed = [(first, "spatial", "sync", 1)] + [(first, "spatial", "multisync", w) for w in worker_counts]
    needed += [(first, "spatial-context", "sync", 1), (first, "spatial-context", "multisync", most)]
    for d in devices[1:]:
        needed += [(d, "spatial", "sync", 1), (d, "spatial", "multisync", most)]
    every = [
        (d, net, kind, w)
        for d in devices
        for net in NETS
        for kind, w in [("sync", 1)] + [("multisync", w) for w in worker_counts]
    ]
    return needed, [s for s in every if s not in needed]


def throughput(settings: list[Setting], iterations: int, cores: int, budget: Budget) -> list[dict[str, Any]]:
    """Learning throughput of each (device, net, collector, workers) setting the budget leaves time for."""
    out = []
    for device, net, kind, workers in settings:
        label = f"{device} {net} {kind} x{workers}"
        r = budget.measure(label, learning_throughput, net, iterations, _overrides(device, kind, workers, cores))
        if r is not None:
            out.append({"device": device, "net": net, "collector": kind, "workers": workers, **r})
            print(f"  {label}: {r['steps_per_s']:.0f} steps/s", flush=True)
    return out


def update_settings(
    device: str, iterations: int, cores: int, measured: list[dict[str, Any]], budget: Budget
) -> list[dict[str, Any]]:
    """The default net's throughput (``sync``) with bf16 and compilation on and off; the grid's own
    setting is taken from the throughput part's row."""
    grid_row = next(
        (r for r in measured if (r["device"], r["net"], r["collector"]) == (device, "spatial", "sync")), None
    )
    out = []
    # The shipped setting (conf/full.yaml: bf16, compiled) and the plain one first: a tight budget
    # drops the others.
    for precision, compiled in (("bf16", True), ("fp32", False), ("fp32", True), ("bf16", False)):
        r: dict[str, Any] | None
        if (precision, compiled) == (GRID_PRECISION, GRID_COMPILE) and grid_row is not None:
            r = {k: grid_row[k] for k in ("params", "steps_per_s", "collect_s", "update_s")}
        else:
            label = f"{device} spatial sync {precision} compile={compiled}"
            overrides = _overrides(device, "sync", 1, cores, precision, compiled)
            r = budget.measure(label, learning_throughput, "spatial", iterations, overrides)
        if r is not None:
            out.append({"device": device, "precision": precision, "compile": compiled, **r})
            print(f"  {device:>4} {precision} compile={compiled}: {r['steps_per_s']:.0f} steps/s", flush=True)
    return out


def markdown(report: dict[str, Any]) -> str:
    """The report as the tables the README's scale-out section shows."""
    m = report["machine"]
    lines = [
        f"Machine: {m['cpu']}, {m['cores']} cores; GPU: {m['gpu'] or 'none'}; torch {m['torch']}.",
        "",
        "| part | result | seconds |",
        "|---|---|---|",
    ]
    for name, part in report["parts"].items():
        lines.append(
            f"| {name} | {part['status']}{': ' + part['why'] if part.get('why') else ''} | {part['seconds']:.0f} |"
        )
    rows = [r for part in ("throughput", "more throughput") for r in report["parts"].get(part, {}).get("result") or []]
    if rows:
        lines += [
            "",
            "End-to-end PPO learning throughput, `conf/full.yaml` (4096 frames an iteration), bf16, not compiled:",
            "",
            "| device | net | collector | workers | steps/s | collect s/it | update s/it |",
            "|---|---|---|---|---|---|---|",
        ]
        lines += [
            f"| {r['device']} | {r['net']} | {r['collector']} | {r['workers']} | {r['steps_per_s']:.0f} | "
            f"{r['collect_s']:.2f} | {r['update_s']:.2f} |"
            for r in rows
        ]
    rows = report["parts"].get("update settings", {}).get("result") or []
    if rows:
        lines += [
            "",
            "The default net, `sync`, by precision and compilation:",
            "",
            "| device | precision | compile | steps/s | collect s/it | update s/it |",
            "|---|---|---|---|---|---|",
        ]
        lines += [
            f"| {r['device']} | {r['precision']} | {r['compile']} | {r['steps_per_s']:.0f} | {r['collect_s']:.2f} | "
            f"{r['update_s']:.2f} |"
            for r in rows
        ]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, default=ROOT / "runs" / "workstation")
    ap.add_argument("--iterations", type=int, default=1, help="measured iterations per setting (after one warm-up)")
    ap.add_argument("--max-workers", type=int, default=8, help="the most multisync workers to try")
    ap.add_argument("--minutes", type=float, default=7.5, help="start no measurement that would end later than this")
    args = ap.parse_args(argv)
    cores = os.cpu_count() or 1
    cuda = torch.cuda.is_available()
    workers = [w for w in (1, 2, 4, 8) if w <= min(args.max_workers, cores)]
    devices = ["cuda", "cpu"] if cuda else ["cpu"]
    measured: list[dict[str, Any]] = []
    budget = Budget(args.minutes)
    # The settings not needed first come last: measured only if the budget allows.
    needed, later = throughput_plan(devices, workers)

    def grid() -> list[dict[str, Any]]:
        measured.extend(throughput(needed, args.iterations, cores, budget))
        return measured

    def update() -> list[dict[str, Any]]:
        return update_settings(devices[0], args.iterations, cores, measured, budget)

    def rest() -> list[dict[str, Any]]:
        return throughput(later, args.iterations, cores, budget)

    parts: list[tuple[str, bool, Callable[[], Any]]] = [
        ("cuda tests", cuda, cuda_tests),
        ("smoke on cuda", cuda, smoke_on_cuda),
        ("throughput", True, grid),
        ("update settings", True, update),
        ("more throughput", True, rest),
    ]
    report: dict[str, Any] = {"machine": machine(), "parts": {}}
    print(f"workstation check on {report['machine']['cpu']} ({cores} cores), GPU: {report['machine']['gpu'] or 'none'}")
    skipped = [name for name, runs, _ in parts if not runs]
    if skipped:
        print(f"skipped (no CUDA device): {', '.join(skipped)}; the GPU rows of the throughput tables too")
    failed = False
    t_all = time.perf_counter()
    for name, runs, part in parts:
        t = time.perf_counter()
        entry: dict[str, Any] = {"status": "skipped", "why": "no CUDA device"} if not runs else {}
        if runs:
            print(f"{name}:", flush=True)
            try:
                entry = {"status": "ok", "result": part()}
            except Exception as e:  # one part's failure is a finding; the others still run
                failed = True
                entry = {"status": "failed", "why": f"{type(e).__name__}: {e}".splitlines()[0]}
                traceback.print_exc()
        entry["seconds"] = time.perf_counter() - t
        report["parts"][name] = entry
    report["seconds"] = time.perf_counter() - t_all
    report["skipped_settings"] = budget.skipped
    if budget.skipped:
        print(f"over the {args.minutes:g}-minute budget, not measured: {'; '.join(budget.skipped)}")
    args.out.mkdir(parents=True, exist_ok=True)
    write_atomic(args.out / "workstation.json", json.dumps(report, indent=1) + "\n")
    md = markdown(report)
    write_atomic(args.out / "workstation.md", md)
    print(md)
    print(f"wrote {args.out / 'workstation.json'} and workstation.md in {report['seconds']:.0f} s")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
