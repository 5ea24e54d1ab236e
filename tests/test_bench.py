import json

import numpy as np
import pytest
import shapely

from mrchaos.bench.benchmark import Bench, BenchError, parse_families, piece_breakdown, resolve_policy
from mrchaos.cli.bench import main as bench_main
from mrchaos.core.geometry import rigid_transform
from mrchaos.learn.evaluate import evaluate
from mrchaos.learn.planner import Lookahead
from tests.conftest import MRCHAOS104


def _independent_metrics(env, targets, actor):
    """Rela and Final from exact polygon areas (shapely) of the settled footprints, not pixels."""
    snaps = []

    def spy(e, td):
        snaps.append((e.worlds.footprint.copy(), e.worlds.placed.copy(), e.next_piece.copy()))
        return actor(e, td)

    res = evaluate(env, targets, spy)
    snaps.append((env.worlds.footprint.copy(), env.worlds.placed.copy(), env.next_piece.copy()))
    ps = env.piece_set
    twins = ps.twin_matrix()
    n = len(targets)
    tpolys = rigid_transform(ps.padded_outlines()[None], targets)
    rela, final = np.zeros(n), np.zeros(n)
    for b in range(n):
        slots = [shapely.Polygon(tpolys[b, j]) for j in range(7)]
        sil = shapely.union_all(slots)
        covs = []
        for t in range(7):
            foot, placed, _ = snaps[t + 1]
            piece = shapely.Polygon(foot[b, t]).buffer(0)
            covs.append(max(piece.intersection(slots[j]).area / slots[j].area for j in np.flatnonzero(twins[t])))
        rela[b] = np.mean(covs)
        foot, placed, _ = snaps[-1]
        occ = shapely.union_all([shapely.Polygon(foot[b, i]).buffer(0) for i in range(7) if placed[b, i]])
        final[b] = occ.intersection(sil).area / sil.area
    return res, rela, final


@pytest.mark.parametrize("policy", ["oracle", "random"])
def test_bench_metrics_match_an_independent_computation(policy):
    bench = Bench([], ["Random"], random_objects=12, seed=3, num_worlds=12)
    spec = resolve_policy(policy)
    env = bench.make_env(spec)
    targets = bench.targets["Random"][0][1]
    res, rela, final = _independent_metrics(env, targets, bench.actor(spec, env))
    # Pixel counts (2.17 mm pixels) against exact areas: agree to a few percent per episode.
    assert np.abs(res.rela - rela).max() < 0.05
    assert np.abs(res.final - final).max() < 0.05
    assert abs(res.rela.mean() - rela.mean()) < 0.015 and abs(res.final.mean() - final.mean()) < 0.015
    if policy == "oracle":
        assert rela.mean() > 0.9
    else:
        assert rela.mean() < 0.2


def test_bench_cli_outputs(tmp_path, capsys):
    out = tmp_path / "bench"
    rec = tmp_path / "rec.rrd"
    args = [
        "--families",
        "random,h-hard",
        "--policy",
        "oracle",
        "--policy",
        "random",
        "--random-objects",
        "8",
        "--out",
        str(out),
        "--record",
        str(rec),
        "--worlds",
        "8",
    ]
    if MRCHAOS104.exists():
        args += ["--figures", str(MRCHAOS104)]
    assert bench_main(args) == 0
    text = capsys.readouterr().out
    assert "Table I" in text and "oracle (nearest grid; reads the solution)" in text
    res = json.loads((out / "results.json").read_text())
    assert set(res["policies"]) == {"oracle", "random"}
    assert res["counts"]["Random"] == 8
    o, r = res["policies"]["oracle"]["families"]["Random"], res["policies"]["random"]["families"]["Random"]
    assert o["final"]["mean"] > r["final"]["mean"] + 0.4
    assert (out / "results.csv").read_text().startswith("policy,family,metric")
    assert "Table I" in (out / "results.md").read_text()
    # The per-piece breakdown: piece means average to Rela; the oracle never misses a slot, random mostly does.
    for s in (o, r):
        assert len(s["by_piece"]["coverage"]) == len(res["piece_names"]) == 7
        assert np.isclose(np.mean(s["by_piece"]["coverage"]), s["rela"]["mean"], atol=1e-6)
    assert max(o["by_piece"]["misplaced"]) == 0 and min(r["by_piece"]["misplaced"]) > 0.5
    assert "Coverage of each piece when placed" in (out / "results.md").read_text()
    assert (out / "contact_sheet.png").stat().st_size > 1000
    assert rec.stat().st_size > 1000
    # The Random set is the same every run (seeded).
    again_args = [a if a != str(out) else str(tmp_path / "again") for a in args if a not in ("--record", str(rec))]
    assert bench_main(again_args) == 0
    again = json.loads((tmp_path / "again" / "results.json").read_text())
    assert again["policies"]["random"]["families"]["Random"] == res["policies"]["random"]["families"]["Random"]


def test_piece_breakdown_skips_the_columns_a_smaller_piece_set_lacks():
    # Two episodes of 3 pieces and one of 2 (a mixed family, NaN-padded as concat_results pads it).
    cov = np.array([[1.0, 0.2, 0.8], [0.6, 0.4, np.nan], [0.5, 1.0, 0.1]])
    b = piece_breakdown(cov)
    assert np.allclose(b["coverage"], [0.7, 1.6 / 3, 0.45])
    assert np.allclose(b["misplaced"], [0.0, 2 / 3, 0.5])
    assert b["n"] == [3, 3, 2]


def test_lookahead_of_one_is_greedy_and_more_never_ends_below_greedy_iou():
    bench = Bench(None, ["Random"], random_objects=10, seed=5, num_worlds=12)
    spec = resolve_policy("mrchaos-dense-ppo")
    env = bench.make_env(spec)
    _, poses, mirrored, _ = bench.targets["Random"][0]
    greedy = evaluate(env, poses, bench.actor(spec, env), mirrored=mirrored)
    planner = Bench(None, ["Random"], random_objects=1, num_worlds=12, lookahead=3).actor(spec, env)
    assert isinstance(planner, Lookahead) and planner.k == 3
    one = evaluate(env, poses, Lookahead(planner.policy, 1).actor(env, poses, mirrored), mirrored=mirrored)
    assert np.array_equal(one.step_coverage, greedy.step_coverage)
    # Candidate 0 of step t is the greedy completion of the plan so far, so each episode's
    # IoU can only rise from the greedy policy's (replays are deterministic).
    three = evaluate(env, poses, planner.actor(env, poses, mirrored), mirrored=mirrored)
    assert np.all(three.iou >= greedy.iou - 1e-6)
    assert three.iou.mean() > greedy.iou.mean()


def test_mode_window_overrides_the_checkpoint_and_lookahead_of_one_stays_greedy():
    # The shipped checkpoint reads its mode over 3 x 3; the override asks for 5 x 5.
    bench = Bench(None, ["Random"], random_objects=10, seed=5, num_worlds=12, mode_window=5)
    spec = resolve_policy("mrchaos-dense-ppo")
    env = bench.make_env(spec)
    _, poses, mirrored, _ = bench.targets["Random"][0]
    windowed = evaluate(env, poses, bench.actor(spec, env), mirrored=mirrored)
    plain = evaluate(
        env, poses, Bench(None, ["Random"], random_objects=1, num_worlds=12).actor(spec, env), mirrored=mirrored
    )
    assert not np.array_equal(windowed.step_coverage, plain.step_coverage)  # the override reached the policy
    one = evaluate(
        env, poses, Lookahead(bench.policy_operator(spec, env), 1).actor(env, poses, mirrored), mirrored=mirrored
    )
    assert np.array_equal(one.step_coverage, windowed.step_coverage)
    res = bench.run([spec, resolve_policy("oracle")])
    assert res["policies"]["mrchaos-dense-ppo"]["label"].endswith("mode window 5")
    assert "mode window" not in res["policies"]["oracle"]["label"] and res["mode_window"] == 5


def test_lookahead_bad_input(capsys):
    assert bench_main(["--policy", "mrchaos", "--lookahead", "0"]) == 2
    assert "--lookahead must be >= 1" in capsys.readouterr().err
    assert bench_main(["--policy", "mrchaos", "--lookahead", "2", "--placement", "robot"]) == 2
    assert "teleport" in capsys.readouterr().err
    assert bench_main(["--policy", "mrchaos-paper", "--lookahead", "2", "--random-objects", "2"]) == 2
    assert "needs a spatial policy" in capsys.readouterr().err
    assert bench_main(["--policy", "mrchaos", "--mode-window", "2"]) == 2
    assert "--mode-window must be odd" in capsys.readouterr().err
    assert bench_main(["--policy", "mrchaos-paper", "--mode-window", "3", "--random-objects", "2"]) == 2
    assert "--mode-window needs a spatial policy" in capsys.readouterr().err


def test_bench_bad_input(tmp_path, capsys):
    assert bench_main(["--families", "h-easy", "--policy", "oracle"]) == 2
    assert "unknown family 'h-easy'" in capsys.readouterr().err
    assert bench_main(["--policy", str(tmp_path / "nope.pt")]) == 2
    assert "no such checkpoint" in capsys.readouterr().err
    bad = tmp_path / "bad.pt"
    bad.write_bytes(b"corrupt")
    assert bench_main(["--policy", str(bad), "--random-objects", "2"]) == 2
    err = capsys.readouterr().err
    assert "bad.pt" in err and err.count("\n") == 1
    assert bench_main(["--policy", "oracle", "--figures", str(tmp_path / "missing.json")]) == 2
    assert "missing.json" in capsys.readouterr().err
    with pytest.raises(BenchError):
        parse_families("random,normal")


def test_invalid_figures_are_skipped_and_counted(tmp_path, capsys):
    good = {"id": "ok", "pieces": []}
    (tmp_path / "set.json").write_text(json.dumps({"figures": [good]}))
    assert (
        bench_main(
            [
                "--policy",
                "oracle",
                "--figures",
                str(tmp_path / "set.json"),
                "--random-objects",
                "2",
                "--out",
                str(tmp_path / "o"),
                "--worlds",
                "2",
            ]
        )
        == 0
    )
    captured = capsys.readouterr()
    assert "skipped ok" in captured.err and "1 figures skipped" in captured.out
    res = json.loads((tmp_path / "o" / "results.json").read_text())
    assert res["skipped"][0][0] == "ok"


def test_shipped_policy_loads_and_beats_random(tmp_path):
    out = tmp_path / "o"
    assert (
        bench_main(
            [
                "--families",
                "random",
                "--policy",
                "mrchaos",
                "--policy",
                "random",
                "--random-objects",
                "16",
                "--out",
                str(out),
                "--worlds",
                "16",
            ]
        )
        == 0
    )
    res = json.loads((out / "results.json").read_text())["policies"]
    final = {p: res[p]["families"]["Random"]["final"]["mean"] for p in ("mrchaos", "random")}
    assert final["mrchaos"] > final["random"] + 0.3


def test_mismatched_checkpoint_is_refused(tmp_path, capsys):
    from mrchaos.learn.checkpoint import load_checkpoint, save_checkpoint, shipped_path

    st = load_checkpoint(shipped_path("mrchaos.pt"))
    for key, value, msg in [("piece_set", "cans", "piece set"), ("obs_shape", [2, 64, 64], "observation shape")]:
        bad = dict(st, **{key: value})
        path = tmp_path / f"{key}.pt"
        save_checkpoint(path, bad)
        assert bench_main(["--policy", str(path), "--random-objects", "2", "--families", "random"]) == 2
        err = capsys.readouterr().err
        assert msg in err and f"{key}.pt" in err


def test_bench_robot_placement_films_and_perturbs(tmp_path, capsys, rendering):
    import shutil
    import subprocess

    from PIL import Image

    out, rec, video = tmp_path / "bench", tmp_path / "robot.rrd", tmp_path / "episode.gif"
    args = [
        "--families",
        "random",
        "--policy",
        "oracle",
        "--random-objects",
        "2",
        "--worlds",
        "2",
        "--placement",
        "robot",
        "--perturb",
        "3",
        "--out",
        str(out),
        "--record",
        str(rec),
        "--video",
        str(video),
    ]
    assert bench_main(args) == 0
    text = capsys.readouterr().out
    assert "robot failures per placement" in text and "push after step 3" in text
    res = json.loads((out / "results.json").read_text())
    assert res["placement"] == "robot"
    fam = res["policies"]["oracle"]["families"]["Random"]
    assert set(fam["robot_failures"]) == {"unreachable", "missed", "dropped", "collision", "flip_failed"}
    assert fam["robot_failures"]["missed"] == 0.0 and fam["robot_failures"]["unreachable"] == 0.0
    # The oracle places by the solution; the push costs it a piece's worth at most.
    assert fam["final"]["mean"] > 0.7
    pt = fam["perturbation"]
    assert pt["coverage_after"]["mean"] < pt["coverage_before"]["mean"]
    with Image.open(video) as im:
        assert im.n_frames > 7 * 5  # a few frames for every placement
    rerun = shutil.which("rerun")
    assert rerun, "the rerun CLI comes with rerun-sdk"
    printed = subprocess.run([rerun, "rrd", "print", str(rec)], capture_output=True, text=True, timeout=120).stdout
    assert "/oracle/Random/random-0/scene" in printed


def test_bench_robot_options_need_robot_placement(capsys):
    assert bench_main(["--policy", "oracle", "--random-objects", "2", "--video", "x.gif"]) == 2
    assert "--placement robot" in capsys.readouterr().err
    assert bench_main(["--policy", "oracle", "--random-objects", "2", "--perturb", "9"]) == 2
    assert "--perturb must be a step in [0, 6]" in capsys.readouterr().err


def test_every_shipped_policy_loads_by_name_and_fits_its_task():
    from mrchaos.bench.benchmark import Bench, resolve_policy
    from mrchaos.learn.checkpoint import SHIPPED

    tasks = {"mrchaos-cutlery": "cutlery", "mrchaos-soda": "soda"}
    for name in SHIPPED:
        spec = resolve_policy(name)  # raises if the file is not shipped
        bench = Bench(None, ["Random"], 1, 0, "teleport", 1, task=tasks.get(name, "tangram"))
        env = bench.make_env(spec)
        bench.actor(spec, env)  # rebuilds the network and checks it against the env
        env.close()


def test_supervised_chaos_policies_beat_the_ppo_policy_on_random(tmp_path):
    out = tmp_path / "s"
    assert (
        bench_main(
            [
                "--families",
                "random",
                "--policy",
                "mrchaos-dense",
                "--policy",
                "mrchaos-bc-chaos",
                "--policy",
                "mrchaos-dense-ppo",
                "--policy",
                "mrchaos",
                "--random-objects",
                "32",
                "--out",
                str(out),
                "--worlds",
                "32",
            ]
        )
        == 0
    )
    res = json.loads((out / "results.json").read_text())["policies"]
    final = {k: v["families"]["Random"]["final"]["mean"] for k, v in res.items()}
    supervised = min(final["mrchaos-dense"], final["mrchaos-bc-chaos"], final["mrchaos-dense-ppo"])
    assert supervised > 0.85 and supervised > final["mrchaos"] + 0.02, final


def test_help_names_every_shipped_policy_task_and_family(capsys):
    from mrchaos.learn.checkpoint import SHIPPED
    from mrchaos.tasks.presets import PRESETS

    with pytest.raises(SystemExit):
        bench_main(["--help"])
    text = " ".join(capsys.readouterr().out.split())  # argparse wraps lines
    names = [*SHIPPED, *PRESETS, *(f.lower() for p in PRESETS.values() for f in p.families)]
    missing = [n for n in names if n not in text.replace("- ", "-")]
    assert not missing, f"mrchaos-bench --help omits {missing}"


def test_a_finer_grid_gives_the_baselines_its_poses_and_leaves_a_checkpoint_its_own():
    bench = Bench(None, ["Random"], random_objects=1, num_worlds=2, task="cutlery", grid={"nx": 101, "ntheta": 24})
    env = bench.make_env(resolve_policy("oracle"))
    assert (env.grid.nx, env.grid.ny, env.grid.ntheta, env.grid.half_range) == (101, 51, 24, 0.16)
    env.close()
    env = bench.make_env(resolve_policy("mrchaos-cutlery"))
    assert env.grid.nvec[:3] == (51, 51, 8)
    env.close()
    res = Bench(None, ["Random"], random_objects=2, num_worlds=2, task="soda", grid={"fine_xy": 3}).run(
        [resolve_policy("oracle")]
    )
    assert res["policies"]["oracle"]["label"].endswith(", grid fine_xy=3") and res["grid"] == {"fine_xy": 3}


@pytest.mark.parametrize(
    "task, grid",
    [
        ("tangram", {"fine_xy": 3}),
        ("cutlery", {"fine_xy": 5, "fine_theta": 9}),
        ("soda", {"fine_xy": 3}),
        ("cutlery", {"nx": 101, "ny": 101, "ntheta": 24}),
    ],
)
def test_the_oracle_with_precision_ends_at_least_as_well_as_on_the_task_s_own_grid(task, grid):
    fams = {}
    for settings in ({}, grid):
        bench = Bench(None, ["Random"], random_objects=24, seed=2, num_worlds=24, task=task, grid=settings)
        fams[bool(settings)] = bench.run([resolve_policy("oracle")])["policies"]["oracle"]["families"]["Random"]
    coarse, fine = fams[False], fams[True]
    # Per object a finer snap may land a piece a hair differently, so the means are compared
    # with a small allowance, and the finer grid must not lose IoU.
    assert fine["final"]["mean"] >= coarse["final"]["mean"] - 0.002
    assert fine["iou"]["mean"] >= coarse["iou"]["mean"] - 0.002


def test_bench_grid_settings_bad_input(capsys):
    assert bench_main(["--policy", "oracle", "--grid", "nope=1"]) == 2
    err = capsys.readouterr().err
    assert "unknown key 'env.grid.nope'" in err and err.count("\n") == 1
    assert bench_main(["--policy", "oracle", "--grid", "nx"]) == 2
    assert "--grid takes KEY=VALUE" in capsys.readouterr().err
    assert bench_main(["--policy", "oracle", "--grid", "ntheta=0"]) == 2
    assert "action grid sizes must be >= 1" in capsys.readouterr().err
    with pytest.raises(BenchError, match="no flip key"):
        Bench(None, ["Random"], random_objects=1, grid={"flip": True})


def test_the_main_job_benches_the_generalist_in_free_order_with_the_flip(tmp_path, capsys):
    """``mrchaos-bench`` with no --policy: the shipped generalist, which chooses its pieces and
    turns them over (so the figures that need the flip are evaluated); ``mrchaos`` stays the
    paper's method by name."""
    out = tmp_path / "main"
    args = ["--families", "random", "--random-objects", "4", "--worlds", "4", "--out", str(out)]
    assert bench_main(args) == 0
    res = json.loads((out / "results.json").read_text())
    assert list(res["policies"]) == ["mrchaos-generalist"]
    spec = resolve_policy("mrchaos-generalist")
    assert spec.order == "free" and spec.flips
    assert "--flip implied by mrchaos-generalist" in capsys.readouterr().err
    assert resolve_policy("mrchaos").label.startswith("MRChaos (full curriculum")
