"""The benchmark scripts' orchestration (their figures are measured by running them, not here)."""

import json
import sys
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture
def workstation(monkeypatch):
    monkeypatch.syspath_prepend(str(ROOT / "benchmarks"))
    import workstation

    calls = []

    def fake(variant, iterations, overrides):
        calls.append((variant, overrides))
        return {"params": 1, "steps_per_s": 100.0 + len(calls), "collect_s": 1.0, "update_s": 2.0}

    monkeypatch.setattr(workstation, "learning_throughput", fake)
    yield workstation, calls
    sys.modules.pop("workstation", None)


def test_the_workstation_check_runs_the_cpu_parts_and_says_what_it_skipped(workstation, tmp_path, capsys, monkeypatch):
    ws, calls = workstation
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    monkeypatch.setattr(ws.os, "cpu_count", lambda: 2)
    assert ws.main(["--out", str(tmp_path), "--iterations", "1"]) == 0
    out = capsys.readouterr().out
    assert "skipped (no CUDA device): cuda tests, smoke on cuda" in out
    report = json.loads((tmp_path / "workstation.json").read_text())
    assert report["parts"]["cuda tests"]["status"] == "skipped"
    rows = report["parts"]["throughput"]["result"] + report["parts"]["more throughput"]["result"]
    # Both nets, sync and multisync up to the machine's 2 cores, on the CPU alone; the default net's
    # sweep and the context net's ends first.
    assert [(r["net"], r["collector"], r["workers"]) for r in rows] == [
        ("spatial", "sync", 1),
        ("spatial", "multisync", 1),
        ("spatial", "multisync", 2),
        ("spatial-context", "sync", 1),
        ("spatial-context", "multisync", 2),
        ("spatial-context", "multisync", 1),
    ]
    assert report["skipped_settings"] == []
    assert all("device=cpu" in o for _, o in calls)
    # bf16 x compile: the grid's setting is reused from the throughput rows, the other three measured.
    settings = report["parts"]["update settings"]["result"]
    assert [(r["precision"], r["compile"]) for r in settings] == [
        ("bf16", True),
        ("fp32", False),
        ("fp32", True),
        ("bf16", False),
    ]
    assert len(calls) == len(rows) + 3
    assert "| cpu | spatial | multisync | 2 |" in (tmp_path / "workstation.md").read_text()


def test_a_failing_part_is_recorded_and_fails_the_check(workstation, tmp_path, monkeypatch):
    ws, _ = workstation
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    monkeypatch.setattr(ws.os, "cpu_count", lambda: 1)

    def broken(*a, **k):
        raise RuntimeError("device mismatch")

    monkeypatch.setattr(ws, "update_settings", broken)
    assert ws.main(["--out", str(tmp_path), "--iterations", "1"]) == 1
    report = json.loads((tmp_path / "workstation.json").read_text())
    assert report["parts"]["update settings"] == {
        "status": "failed",
        "why": "RuntimeError: device mismatch",
        "seconds": report["parts"]["update settings"]["seconds"],
    }
    assert report["parts"]["throughput"]["status"] == "ok"


def test_the_workstation_check_starts_nothing_past_its_budget(workstation, tmp_path, capsys, monkeypatch):
    ws, calls = workstation
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    monkeypatch.setattr(ws.os, "cpu_count", lambda: 2)
    assert ws.main(["--out", str(tmp_path), "--minutes", "0"]) == 0
    assert calls == []
    report = json.loads((tmp_path / "workstation.json").read_text())
    assert "cpu spatial sync x1" in report["skipped_settings"] and len(report["skipped_settings"]) == 6 + 4
    assert "over the 0-minute budget, not measured: cpu spatial sync x1" in capsys.readouterr().out


def test_the_face_is_open_only_where_the_last_slots_also_tile_with_the_piece_turned_over(monkeypatch):
    """benchmarks/flip_faces.py's tiling search: a rectangle of the parallelogram and two small
    triangles tiles with either face, the classic square's last four slots with its own face only,
    and a figure's mirror image gives the same answer."""
    monkeypatch.syspath_prepend(str(ROOT / "benchmarks"))
    import flip_faces

    from mrchaos.figures.figure import mirror_figure
    from mrchaos.figures.library import builtin_figures

    figs = {f.id: f for f in builtin_figures()}
    assert flip_faces.face_open(figs["rectangle"]) == {3: True}
    assert flip_faces.face_open(figs["square"]) == {3: False}
    assert flip_faces.face_open(mirror_figure(figs["square"])) == {3: False}
    assert flip_faces.face_open(mirror_figure(figs["rectangle"])) == {3: True}
    sys.modules.pop("flip_faces", None)


@pytest.mark.slow
def test_the_fit_test_labels_once_and_benches_every_network(tmp_path, monkeypatch, capsys):
    """benchmarks/fit_test.py: the second network trains on the first one's labelled states (a
    copy, not a new labelling), and every network gets a row on every bench set."""
    monkeypatch.syspath_prepend(str(ROOT / "benchmarks"))
    monkeypatch.chdir(ROOT)
    import fit_test

    out = tmp_path / "fit"
    args = ["--objects", "3", "--epochs", "1", "--eval", "2", "--nets", "today,coords", "--out", str(out)]
    assert fit_test.main([*args, "env.num_worlds=4", "bc.minibatch_size=8"]) == 0
    shards = [torch.load(out / n / "data" / "round_0.pt", weights_only=True) for n in ("today", "coords")]
    assert torch.equal(shards[0]["label"], shards[1]["label"]) and len(shards[0]["label"]) == 21
    res = json.loads((out / "results.json").read_text())
    assert set(res) == {"oracle", "today", "coords", "target_entropy"}
    for name in ("oracle", "today", "coords"):
        assert list(res[name]["sets"]) == list(fit_test.SETS)
    assert res["oracle"]["sets"]["tile"]["rela"] > 80
    assert "| coords |" in capsys.readouterr().out
    sys.modules.pop("fit_test", None)


@pytest.mark.slow
def test_the_fit_test_on_cutlery_labels_each_observation_once(tmp_path, monkeypatch, capsys):
    """Another task's fit test benches its own sets, and a grey-level candidate labels its own
    states (the states hold the observation) while the binary ones share theirs."""
    monkeypatch.syspath_prepend(str(ROOT / "benchmarks"))
    monkeypatch.chdir(ROOT)
    import fit_test

    out = tmp_path / "fit"
    args = ["--config", "conf/cutlery_dense.yaml", "--mode", "scatter", "--objects", "3", "--epochs", "1"]
    args += ["--eval", "2", "--nets", "today,grey2,coords", "--out", str(out)]
    assert fit_test.main([*args, "env.num_worlds=4", "bc.minibatch_size=8"]) == 0
    shards = {n: torch.load(out / n / "data" / "round_0.pt", weights_only=True) for n in ("today", "grey2", "coords")}
    assert len(shards["today"]["label"]) == 9  # three pieces a cutlery object
    assert torch.equal(shards["today"]["observation"], shards["coords"]["observation"])
    assert not torch.equal(shards["today"]["observation"], shards["grey2"]["observation"])
    res = json.loads((out / "results.json").read_text())
    for name in ("oracle", "today", "grey2", "coords"):
        assert list(res[name]["sets"]) == list(fit_test.TASK_SETS)
    assert res["oracle"]["sets"]["random"]["rela"] > 50
    assert "| grey2 |" in capsys.readouterr().out
    sys.modules.pop("fit_test", None)
