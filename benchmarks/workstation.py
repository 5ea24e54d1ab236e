"""One check of a GPU workstation: does ``device=cuda`` train, resume and bench, and how does
learning throughput scale with the collector's workers, on the GPU and on the CPU alone?

    python benchmarks/workstation.py [--out runs/workstation] [--iterations 2] [--max-workers 8]

In order, each part timed:

1. the tests marked ``cuda`` (``tests/test_cuda.py``);
2. ``conf/smoke.yaml`` trained with ``device=cuda`` to its end, resumed for one more iteration,
   then benched (``mrchaos-bench`` on its Random family);
3. end-to-end PPO throughput (``benchmarks/train_throughput.py``'s measure: ``conf/full.yaml``,
   4096 frames an iteration, after one warm-up) of the default net and the context net, with the
   ``sync`` collector and with ``multisync`` at 1, 2, 4 and 8 workers (up to the machine's
   cores), on the GPU and on the CPU alone, with the collection/update split;
4. the update's precision and compilation: bf16 on and off, ``torch.compile`` on and off (the
   default net, ``sync``, on the GPU if there is one).

Writes ``workstation.json`` and ``workstation.md`` into ``--out`` and prints the table. On a machine
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
from mrchaos.learn.config import load_config  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
NETS = ("spatial", "spatial-context")


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


def throughput(device: str, iterations: int, worker_counts: list[int], cores: int) -> list[dict[str, Any]]:
    """Learning throughput of each net, by collector and worker count, on one device."""
    out = []
    for net in NETS:
        settings = [("sync", 1)] + [("multisync", w) for w in worker_counts]
        for kind, workers in settings:
            # sync steps the env in this process on every core; multisync gives each worker one
            # core, and the update uses all of them while the workers wait.
            extra = (
                [f"threads={cores}", f"env.physics.nthread={cores}"]
                if kind == "sync"
                else [f"threads={cores}", f"collector.workers={workers}", "collector.worker_threads=1"]
            )
            r = learning_throughput(net, iterations, [f"device={device}", f"collector.kind={kind}", *extra])
            out.append({"device": device, "net": net, "collector": kind, "workers": workers, **r})
            print(f"  {device:>4} {net:>15} {kind:>9} x{workers}: {r['steps_per_s']:.0f} steps/s", flush=True)
    return out


def update_settings(device: str, iterations: int, cores: int, measured: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """The default net's throughput (``sync``) with bf16 and compilation on and off; the shipped
    setting (``conf/full.yaml``: bf16, compiled) is taken from the throughput part's row."""
    shipped = load_config(ROOT / "conf" / "full.yaml")
    out = []
    for precision in ("fp32", "bf16"):
        for compiled in (False, True):
            same = [
                r
                for r in measured
                if (r["device"], r["net"], r["collector"]) == (device, "spatial", "sync")
                and (precision, compiled) == (shipped.precision, shipped.compile)
            ]
            if same:
                r = {k: same[0][k] for k in ("params", "steps_per_s", "collect_s", "update_s")}
            else:
                overrides = [f"device={device}", f"precision={precision}", f"compile={str(compiled).lower()}"]
                threads = [f"threads={cores}", f"env.physics.nthread={cores}"]
                r = learning_throughput("spatial", iterations, [*overrides, *threads])
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
    rows = report["parts"].get("throughput", {}).get("result") or []
    if rows:
        lines += [
            "",
            "End-to-end PPO learning throughput, `conf/full.yaml` (4096 frames an iteration):",
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
    ap.add_argument("--iterations", type=int, default=2, help="measured iterations per setting (after one warm-up)")
    ap.add_argument("--max-workers", type=int, default=8, help="the most multisync workers to try")
    args = ap.parse_args(argv)
    cores = os.cpu_count() or 1
    cuda = torch.cuda.is_available()
    workers = [w for w in (1, 2, 4, 8) if w <= min(args.max_workers, cores)]
    devices = ["cuda", "cpu"] if cuda else ["cpu"]
    measured: list[dict[str, Any]] = []

    def grid() -> list[dict[str, Any]]:
        for d in devices:
            measured.extend(throughput(d, args.iterations, workers, cores))
        return measured

    parts: list[tuple[str, bool, Callable[[], Any]]] = [
        ("cuda tests", cuda, cuda_tests),
        ("smoke on cuda", cuda, smoke_on_cuda),
        ("throughput", True, grid),
        ("update settings", True, lambda: update_settings(devices[0], args.iterations, cores, measured)),
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
    args.out.mkdir(parents=True, exist_ok=True)
    write_atomic(args.out / "workstation.json", json.dumps(report, indent=1) + "\n")
    md = markdown(report)
    write_atomic(args.out / "workstation.md", md)
    print(md)
    print(f"wrote {args.out / 'workstation.json'} and workstation.md in {report['seconds']:.0f} s")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
