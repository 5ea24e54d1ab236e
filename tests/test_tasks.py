"""Beyond tangram: the cutlery and soda piece sets, their goals, generators, rewards and bench."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest
import shapely
import torch

from mrchaos.core.geometry import rigid_transform
from mrchaos.core.raster import View, rasterize
from mrchaos.env.metrics import best_slot_coverage, exclusive_slot_coverage
from mrchaos.env.oracle import oracle_poses
from mrchaos.env.tangram import TangramEnv
from mrchaos.figures.pieces import Piece, get_piece_set, tangram7
from mrchaos.learn.config import config_from_dict
from mrchaos.tasks.chaos import generate
from mrchaos.tasks.presets import PRESETS

PACKAGE = Path(__file__).resolve().parents[1] / "mrchaos"


def _env(task: str, piece_set: str | None = None, n: int = 10) -> TangramEnv:
    # Fresh chaos objects, not a cache: the tests set their own targets, and building a cache is slow.
    env = {"num_worlds": n, **({"piece_set": piece_set} if piece_set else {})}
    cfg = config_from_dict({"env": env, "task": {"preset": task, "mix": {"chaos": 1.0, "cache": 0.0}}})
    return TangramEnv(cfg.env_config(), seed=0)


def _goals(task: str):
    return PRESETS[task].goal_figures(_view(task))


def _view(task: str) -> View:
    return config_from_dict({"task": {"preset": task}}).env.view


#: The tasks whose goals we authored (tangram's are the built-in library).
AUTHORED = sorted(t for t, p in PRESETS.items() if p.authored)


def test_cutlery_outlines_are_the_union_of_convex_parts() -> None:
    ps = get_piece_set("cutlery")
    assert ps.names == ("knife", "spoon", "fork")
    for p in ps.pieces:
        outline = shapely.Polygon(p.outline)
        assert not outline.equals(outline.convex_hull), p.name  # really non-convex
        union = shapely.union_all([shapely.Polygon(q) for q in p.parts])
        assert union.symmetric_difference(outline).area < 1e-9
        length = np.ptp(p.outline[:, 0])
        assert 0.170 <= length <= 0.210, (p.name, length)
        assert p.symmetry == 1
    assert ps.pieces[0].chiral and not ps.pieces[1].chiral and not ps.pieces[2].chiral
    with pytest.raises(ValueError, match="not convex"):
        Piece("bent", np.array([[0, 0], [2, 0], [2, 2], [1, 0.5], [0, 2]]) * 0.01, 0.004)


def test_soda_cans_are_interchangeable_66mm_discs() -> None:
    for n in (3, 4, 5, 6):
        ps = get_piece_set(f"soda{n}")
        assert len(ps) == n and ps.kind == "soda" and ps.twins == (tuple(range(n)),)
        for p in ps.pieces:
            assert p.symmetry == 0
            assert abs(p.area - np.pi * 0.033**2) < 1e-9  # the disc's area


def test_the_rasteriser_draws_the_true_outline() -> None:
    """Parts rasterised as one piece match a pixel-centre test against the exact outline."""
    ps = get_piece_set("cutlery")
    view = View(extent=0.40)
    rng = np.random.default_rng(0)
    poses = np.c_[rng.uniform(-0.05, 0.05, (8, 3, 2)), rng.uniform(-np.pi, np.pi, (8, 3, 1))]
    xs, ys = view.pixel_centres()
    gx, gy = np.meshgrid(xs, ys)
    for i, p in enumerate(ps.pieces):
        alone = np.zeros((len(poses), len(ps)), dtype=bool)
        alone[:, i] = True
        ids = rasterize(ps.footprints(poses), view, visible=alone, parts=ps.part_piece).ids.numpy()
        for b in range(len(poses)):
            inside = shapely.contains_xy(shapely.Polygon(rigid_transform(p.outline, poses[b, i])), gx, gy)
            # Only pixel centres within rounding of an edge may differ.
            assert (inside ^ (ids[b] == i)).sum() <= 2, (b, p.name)
            assert ((ids[b] >= 0) == (ids[b] == i)).all()


@pytest.mark.parametrize("task", sorted(PRESETS))
def test_exact_oracle_assembles_every_goal(task: str) -> None:
    goals = _goals(task)
    assert len(goals) >= 8
    for g in goals:
        assert g.overlap_area() < 1e-9, g.id
    for name in dict.fromkeys(g.piece_set.name for g in goals):
        sub = [g for g in goals if g.piece_set.name == name]
        env = _env(task, name, n=len(sub))
        env.reset_to(np.stack([g.poses for g in sub]))
        for _ in range(len(env.piece_set)):
            out = env.place_poses(*oracle_poses(env))
        final = out["info", "final"][:, 0]
        assert (final >= 0.99).all(), {g.id: float(f) for g, f in zip(sub, final, strict=True)}
        env.close()


@pytest.mark.parametrize("set_name", ["cutlery", "soda6", "soda3"])
def test_chaos_generators_make_separate_pieces_inside_the_view(set_name: str) -> None:
    task = "cutlery" if set_name == "cutlery" else "soda"
    cfg = config_from_dict({"task": {"preset": task}})
    ps = get_piece_set(set_name)
    poses, modes, _ = generate(ps, 24, np.random.default_rng(1), cfg.task.chaos, cfg.env.view)
    assert set(modes.tolist()) == {0, 1}
    half = cfg.env.view.extent / 2
    for obj in poses:
        polys = [shapely.Polygon(rigid_transform(p.outline, q)) for p, q in zip(ps.pieces, obj, strict=True)]
        assert all(np.abs(np.asarray(pl.exterior.coords)).max() <= half for pl in polys)
        assert shapely.union_all(polys).area == pytest.approx(sum(pl.area for pl in polys), rel=1e-6)


def test_exclusive_slots_pay_one_can_per_slot() -> None:
    # Two twins both on slot 0 (slot 1 empty): shared slots pay both, exclusive slots one.
    counts = torch.tensor([[[90, 0], [80, 0]]])
    area = torch.tensor([[100, 100]])
    twins = np.ones((2, 2), dtype=bool)
    assert best_slot_coverage(counts, area, twins)[0].tolist() == [[pytest.approx(0.9), pytest.approx(0.8)]]
    assert exclusive_slot_coverage(counts, area, twins)[0].tolist() == [[pytest.approx(0.9), 0.0]]


def test_stacking_cans_on_one_slot_earns_nothing() -> None:
    env = _env("soda", "soda3", n=2)
    goal = next(g for g in _goals("soda") if g.id == "soda-row3")
    env.reset_to(np.stack([goal.poses] * 2))
    first = env.place_poses(goal.poses[[0, 0]])
    assert (first["reward"] > 0.95).all()
    # World 0 puts the second can on the first can's slot; world 1 on its own free slot.
    second = env.place_poses(goal.poses[[0, 1]])
    assert second["reward"][0].item() < 0.1
    assert second["reward"][1].item() > 0.95
    env.close()


def test_no_tangram_piece_names_in_shared_code() -> None:
    names = tangram7().names
    pattern = re.compile(r"\b(" + "|".join(names) + r")\b")
    hits = [
        f"{path.name}:{i}"
        for path in PACKAGE.rglob("*.py")
        if path.name != "pieces.py"
        for i, line in enumerate(path.read_text().splitlines(), 1)
        if pattern.search(line)
    ]
    assert not hits, hits


def test_bench_runs_a_task(tmp_path, capsys) -> None:
    from mrchaos.cli.bench import main as bench_main

    out = tmp_path / "soda"
    rrd = tmp_path / "soda.rrd"  # the Random family mixes 3 to 6 cans in one recording
    assert (
        bench_main(
            ["--task", "soda", "--policy", "oracle", "--random-objects", "8", "--out", str(out), "--record", str(rrd)]
        )
        == 0
    )
    assert rrd.stat().st_size > 10_000
    res = json.loads((out / "results.json").read_text())
    assert res["task"] == "soda" and res["counts"] == {"Authored": 10, "Random": 8}
    fam = res["policies"]["oracle"]["families"]
    assert fam["Authored"]["final"]["mean"] > 0.85 and fam["Random"]["final"]["mean"] > 0.85
    assert "Authored Rela" in capsys.readouterr().out
    assert bench_main(["--task", "forks", "--policy", "oracle"]) == 2
    assert bench_main(["--task", "soda", "--families", "h-hard", "--policy", "oracle"]) == 2


@pytest.mark.parametrize("task", AUTHORED)
def test_shipped_task_policy_beats_random_on_every_piece_set(task: str, tmp_path) -> None:
    # The default policy of --task is the shipped mrchaos-<task>; soda's Random family draws
    # soda3 ... soda6, so the soda6-trained policy must act on every can count.
    from mrchaos.cli.bench import main as bench_main

    out = tmp_path / task
    assert bench_main(["--task", task, "--random-objects", "8", "--worlds", "8", "--out", str(out)]) == 0
    assert (
        bench_main(
            [
                "--task",
                task,
                "--policy",
                "random",
                "--random-objects",
                "8",
                "--worlds",
                "8",
                "--out",
                str(tmp_path / "random"),
            ]
        )
        == 0
    )
    trained = json.loads((out / "results.json").read_text())
    rand = json.loads((tmp_path / "random" / "results.json").read_text())["policies"]["random"]["families"]
    assert list(trained["policies"]) == [f"mrchaos-{task}"]
    fam = trained["policies"][f"mrchaos-{task}"]["families"]
    for name in ("Authored", "Random"):
        assert fam[name]["final"]["mean"] > rand[name]["final"]["mean"] + 0.1, (name, fam[name], rand[name])
    if task == "soda":
        from mrchaos.bench.benchmark import Bench

        bench = Bench([], ["Random"], 8, 0, "teleport", 8, task="soda")  # the same seeded Random family
        assert [group[0] for group in bench.targets["Random"]] == ["soda3", "soda4", "soda5", "soda6"]
