"""The UR5e: kinematics, the MJCF model, suction, pick-and-place accuracy, failures and perturbation."""

from __future__ import annotations

import math

import mujoco
import numpy as np
import pytest

from mrchaos.core.raster import View
from mrchaos.figures.pieces import get_piece_set
from mrchaos.sim.kinematics import UR5E, fk, ik
from mrchaos.sim.robot import Robot, RobotConfig
from mrchaos.sim.scene import SceneConfig, build_model
from mrchaos.sim.worlds import PhysicsConfig, Worlds

TANGRAM = get_piece_set("tangram7")


def _yaw_of(quat: np.ndarray) -> np.ndarray:
    w, x, y, z = quat.T
    return np.arctan2(2 * (w * z + x * y), 1 - 2 * (y**2 + z**2))


def _wrap(a: np.ndarray, period: float) -> np.ndarray:
    return (a + period / 2) % period - period / 2


def test_ik_inverts_fk_on_random_configurations() -> None:
    rng = np.random.default_rng(0)
    q = rng.uniform(-math.pi, math.pi, (200, 6))
    target = fk(q)
    sol, ok = ik(target, q + rng.normal(0, 0.05, q.shape))
    assert ok.mean() > 0.95  # only near-singular draws may fail
    err = np.abs(fk(sol[ok]) - target[ok]).max()
    assert err < 1e-9


def test_mjcf_forward_kinematics_matches_the_dh_table() -> None:
    cfg = RobotConfig()
    model = build_model(TANGRAM, SceneConfig(), View(), cfg)
    robot = Robot(model, cfg)
    assert robot.exact
    # The DH base is the mount, z up; the tool is the cup's length beyond the flange.
    assert np.allclose(robot.base[:3, 3], cfg.mount, atol=1e-9)
    assert np.allclose(robot.base[:3, 2], [0, 0, 1], atol=1e-9)
    assert np.isclose(np.linalg.norm(robot.tool[:3, 3]), cfg.tool_length, atol=1e-9)
    q = np.random.default_rng(1).uniform(-math.pi, math.pi, (20, 6))
    dh = robot.base @ fk(q, UR5E) @ robot.tool
    mj = np.stack([robot.tcp_pose(qi) for qi in q])
    assert np.abs(dh - mj).max() < 1e-9


def test_calibration_finds_a_moved_and_turned_base() -> None:
    """Another mount (a different base frame in the model) is found from the model alone."""
    cfg = RobotConfig(mount=(0.05, -0.45, 0.0), mount_yaw=0.7)
    model = build_model(TANGRAM, SceneConfig(), View(), cfg)
    robot = Robot(model, cfg)
    assert robot.exact
    pos = np.array([[0.0, 0.0, 0.05], [0.1, -0.1, 0.02], [0.3, 0.1, 0.1]])
    yaw = np.array([0.0, 1.0, -2.0])
    q, ok = robot.solve(pos, yaw, np.repeat(robot.solve(pos[:1], yaw[:1], np.zeros((1, 6)))[0], 3, 0))
    assert ok.all()
    for qi, p, y in zip(q, pos, yaw, strict=True):
        tcp = robot.tcp_pose(qi)
        assert np.abs(tcp[:3, 3] - p).max() < 1e-6
        assert tcp[2, 2] < -0.9999  # tool pointing down
        assert abs(_wrap(math.atan2(tcp[1, 0], tcp[0, 0]) - y, 2 * math.pi)) < 1e-6


def test_a_model_off_the_dh_table_is_solved_by_refinement(tmp_path) -> None:
    """Another UR5e model (like Menagerie's, which differs from the DH table by up to a
    millimetre) is calibrated approximately and each solution refined on its own kinematics."""
    from mrchaos.sim.robot import default_robot_model

    text = default_robot_model().read_text()
    assert 'name="wrist_1_link" pos="-0.3922 0 0"' in text
    path = tmp_path / "ur5e_long_forearm.xml"
    path.write_text(text.replace('name="wrist_1_link" pos="-0.3922 0 0"', 'name="wrist_1_link" pos="-0.3932 0 0.0004"'))
    cfg = RobotConfig(model=str(path))
    robot = Robot(build_model(TANGRAM, SceneConfig(), View(), cfg), cfg)
    assert not robot.exact
    pos = np.array([[0.0, 0.0, 0.05], [0.1, -0.1, 0.02], [-0.1, 0.1, 0.1]])
    q, ok = robot.solve(pos, np.array([0.0, 1.0, -2.0]), np.tile([0.0, -1.57, 1.57, -1.57, -1.57, 0.0], (3, 1)))
    assert ok.all()
    for qi, p in zip(q, pos, strict=True):
        assert np.abs(robot.tcp_pose(qi)[:3, 3] - p).max() < 1e-5


def test_home_keyframe_holds_the_ready_pose() -> None:
    cfg = RobotConfig()
    model = build_model(TANGRAM, SceneConfig(), View(), cfg)
    data = mujoco.MjData(model)
    mujoco.mj_resetDataKeyframe(model, data, model.key("home").id)
    mujoco.mj_forward(model, data)
    assert np.allclose(data.site("tcp").xpos, cfg.ready, atol=1e-6)
    # The position actuators hold it: one simulated second later the TCP has not sagged.
    mujoco.mj_step(model, data, nstep=round(1.0 / model.opt.timestep))
    assert np.abs(data.site("tcp").xpos - cfg.ready).max() < 2e-3


@pytest.fixture(scope="module")
def robot_worlds() -> Worlds:
    return Worlds(TANGRAM, 20, PhysicsConfig(nthread=2), robot=RobotConfig())


def test_every_piece_lands_within_2mm_and_2deg_on_an_empty_table(robot_worlds: Worlds) -> None:
    w, rng = robot_worlds, np.random.default_rng(7)
    rows = np.arange(w.n)
    half = View().extent / 2 - 0.03
    worst_mm, worst_deg = 0.0, 0.0
    for k, piece in enumerate(TANGRAM.pieces):
        w.reset(rows)
        pose = np.c_[rng.uniform(-half, half, (w.n, 2)), rng.uniform(-math.pi, math.pi, w.n)]
        res = w.place(rows, np.full(w.n, k), pose)
        fails = {f: getattr(res.robot, f) for f in ("unreachable", "missed", "dropped", "collision")}
        assert not any(v.any() for v in fails.values()), (piece.name, fails)
        w.batch.forward()
        body = w.model.body(piece.name).id
        xy = w.batch.bind("xpos")[:, body, :2]
        yaw = _yaw_of(w.batch.bind("xquat")[:, body])
        err_mm = 1000 * np.linalg.norm(xy - pose[:, :2], axis=1)
        err_deg = np.degrees(np.abs(_wrap(yaw - pose[:, 2], piece.symmetry_period)))
        assert err_mm.max() < 2.0, (piece.name, err_mm.max())
        assert err_deg.max() < 2.0, (piece.name, err_deg.max())
        # Flat on the table, not tilted or left hanging.
        z = w.batch.bind("xpos")[:, body, 2]
        assert np.abs(z - piece.thickness / 2).max() < 1e-3
        worst_mm, worst_deg = max(worst_mm, err_mm.max()), max(worst_deg, err_deg.max())
    print(f"worst placement error {worst_mm:.2f} mm, {worst_deg:.2f} deg")


def test_no_contact_means_no_suction(robot_worlds: Worlds) -> None:
    """With the piece moved from under the cup after planning, suction finds nothing to hold."""
    w = robot_worlds
    rows = np.arange(4)
    w.reset(rows)
    k = 0
    ex = w.executor
    body = w.model.body(TANGRAM.names[k]).id
    # Lower the cup's reach: it stops 5 cm above the piece, as if the piece were thinner.
    saved = ex.thickness.copy()
    ex.thickness[k] = saved[k] + 0.10
    try:
        pose = np.tile([0.0, 0.0, 0.0], (len(rows), 1))
        before = w.batch.bind("xpos")[rows, body].copy()
        res = w.place(rows, np.full(len(rows), k), pose)
    finally:
        ex.thickness[:] = saved
    assert res.robot.missed.all()
    assert not (w.batch.bind("eq_active")[rows][:, ex.welds]).any()
    w.batch.forward()
    after = w.batch.bind("xpos")[rows, body]
    assert np.abs(after[:, :2] - before[:, :2]).max() < 1e-3  # the piece stayed in its staging slot


def test_touching_another_piece_is_reported_as_a_collision(robot_worlds: Worlds) -> None:
    """A piece lying on top of the one to pick is what the cup meets first."""
    w = robot_worlds
    rows = np.arange(3)
    w.reset(rows)
    big, small = 0, 2
    on_top = np.tile(w._staging[small], (len(rows), 1))
    w._write_flat(rows, np.full(len(rows), big), on_top, np.full(len(rows), w._thick[small] + w._thick[big] / 2))
    res = w.place(rows, np.full(len(rows), small), np.tile([0.05, 0.05, 0.0], (len(rows), 1)))
    assert res.robot.collision.all()
    # Placing on a free table afterwards reports nothing.
    w.reset(rows)
    res = w.place(rows, np.full(len(rows), small), np.tile([0.05, 0.05, 0.0], (len(rows), 1)))
    assert not res.robot.collision.any()


def test_robot_env_specs_and_an_episode() -> None:
    import torch
    from torchrl.envs.utils import check_env_specs

    from mrchaos.env.tangram import EnvConfig, TangramEnv

    env = TangramEnv(EnvConfig(num_worlds=2, placement="robot"), seed=0)
    check_env_specs(env, seed=0)
    td = env.rollout(len(TANGRAM), break_when_any_done=False)
    assert td["next", "done"][:, -1].all()
    for k in ("unreachable", "missed", "dropped", "collision"):
        assert td["next", "info", k].dtype == torch.bool
    env.close()


def test_perturbation_moves_the_piece_and_the_episode_goes_on() -> None:
    from mrchaos.env.oracle import oracle_actions
    from mrchaos.env.tangram import EnvConfig, TangramEnv
    from mrchaos.learn.evaluate import evaluate
    from mrchaos.tasks.chaos import ChaosConfig, generate

    env = TangramEnv(EnvConfig(num_worlds=8), seed=0)
    targets = generate(TANGRAM, 8, np.random.default_rng(3), ChaosConfig())[0]
    clean = evaluate(env, targets, lambda e, td: oracle_actions(e))
    pushed = evaluate(env, targets, lambda e, td: oracle_actions(e), perturb_after=2, perturb_distance=0.05)
    pt = pushed.perturbation
    assert pt is not None and set(pt) == {
        "final_before",
        "final_after",
        "final_end",
        "coverage_before",
        "coverage_after",
    }
    # A 5 cm push takes the piece off its slot: its coverage drops, and so does Final.
    assert (pt["coverage_after"] < pt["coverage_before"] - 0.3).mean() > 0.7
    assert pt["final_after"].mean() < pt["final_before"].mean()
    # The oracle goes on placing the later pieces, but does not fix the pushed one.
    assert np.allclose(pt["final_end"], pushed.final)
    assert pushed.final.mean() < clean.final.mean() - 0.02
    assert pushed.final.mean() > pt["final_after"].mean()
    env.close()


@pytest.mark.parametrize("suffix", [".gif", ".mp4"])
def test_video_files_hold_the_frames(tmp_path, suffix) -> None:
    import cv2

    from mrchaos.sim.animation import write_video

    frames = [np.full((48, 64, 3), 40 * i, dtype=np.uint8) for i in range(5)]
    path = write_video(frames, tmp_path / f"ep{suffix}", fps=5)
    cap = cv2.VideoCapture(str(path))
    n = 0
    while cap.read()[0]:
        n += 1
    assert n == 5
    assert not list(tmp_path.glob("*.partial*"))
    with pytest.raises(ValueError, match="must end in .gif or .mp4"):
        write_video(frames, tmp_path / "ep.avi")
