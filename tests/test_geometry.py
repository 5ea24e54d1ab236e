import math

import numpy as np
import shapely
from hypothesis import given, settings
from hypothesis import strategies as st

from mrchaos.core.geometry import (
    angle_gap,
    convex_penetration,
    fit_pose,
    polygon_area,
    rigid_transform,
)
from mrchaos.figures.pieces import (
    Piece,
    PieceSet,
    get_piece_set,
    register_piece_set,
    tangram7,
)

poses = st.tuples(st.floats(-0.2, 0.2), st.floats(-0.2, 0.2), st.floats(-math.pi, math.pi)).map(np.array)


def test_tangram7_facts(tangram):
    assert tangram.names == (
        "large_triangle_1",
        "large_triangle_2",
        "square",
        "parallelogram",
        "medium_triangle",
        "small_triangle_1",
        "small_triangle_2",
    )
    assert math.isclose(tangram.total_area, 0.01, rel_tol=1e-9)
    legs = {"large_triangle_1": 0.0707107, "medium_triangle": 0.05, "small_triangle_1": 0.0353553}
    for name, leg in legs.items():
        o = tangram.pieces[tangram.index(name)].outline
        edges = sorted(np.linalg.norm(np.roll(o, -1, 0) - o, axis=1))
        assert np.allclose(edges[:2], leg, atol=1e-6)
    sq = tangram.pieces[2]
    assert sq.symmetry == 4 and not sq.chiral
    par = tangram.pieces[3]
    assert par.symmetry == 2 and par.chiral
    assert sorted(np.round(np.linalg.norm(np.roll(par.outline, -1, 0) - par.outline, axis=1), 5)) == [
        0.03536,
        0.03536,
        0.05,
        0.05,
    ]
    assert all(tangram.pieces[i].symmetry == 1 for i in (0, 1, 4, 5, 6))
    assert all(p.thickness == 0.010 for p in tangram.pieces)
    tw = tangram.twin_matrix()
    assert tw[0, 1] and tw[5, 6] and not tw[0, 4] and tw.sum() == 7 + 4
    for p in tangram.pieces:  # centred, CCW
        assert polygon_area(p.outline) > 0
        assert np.allclose(p.outline.mean(0), 0, atol=1e-12)  # vertex mean = centroid for these shapes


def test_register_new_piece_set():
    disc = (
        np.stack(
            [
                np.cos(np.linspace(0, 2 * np.pi, 16, endpoint=False)),
                np.sin(np.linspace(0, 2 * np.pi, 16, endpoint=False)),
            ],
            1,
        )
        * 0.033
    )
    cans = tuple(Piece(f"can{i}", disc, 0.12, symmetry=0) for i in range(3))
    register_piece_set("cans3", lambda: PieceSet("cans3", cans, twins=((0, 1, 2),)))
    ps = get_piece_set("cans3")
    assert len(ps) == 3 and ps.twin_matrix().all()
    assert ps.pieces[0].symmetry_period == 0.0


@given(poses)
@settings(max_examples=60, deadline=None)
def test_rigid_motion_preserves_area(pose):
    for p in tangram7().pieces:
        assert math.isclose(polygon_area(rigid_transform(p.outline, pose)), p.area, rel_tol=1e-9)


@given(poses, st.booleans())
@settings(max_examples=60, deadline=None)
def test_fit_pose_recovers_pose(pose, mirror):
    par = tangram7().pieces[3]
    outline = par.mirrored_outline() if mirror else par.outline
    world = rigid_transform(outline, pose)
    # Any start vertex, any winding.
    world = np.roll(world, 2, axis=0)[::-1]
    fit = fit_pose(par.outline, world, par.mirrored_outline())
    assert fit.mirrored == mirror
    assert fit.residual < 1e-9
    assert np.allclose(fit.pose[:2], pose[:2], atol=1e-9)
    assert angle_gap(fit.pose[2], pose[2], math.pi) < 1e-7  # 180-degree symmetric


@given(poses, poses, st.integers(0, 6), st.integers(0, 6))
@settings(max_examples=150, deadline=None)
def test_penetration_agrees_with_shapely(pa, pb, i, j):
    ps = tangram7()
    pa = pa * np.array([0.3, 0.3, 1.0])
    pb = pb * np.array([0.3, 0.3, 1.0])
    a = rigid_transform(ps.pieces[i].outline, pa)
    b = rigid_transform(ps.pieces[j].outline, pb)
    depth = float(convex_penetration(a, b))
    inter = shapely.Polygon(a).intersection(shapely.Polygon(b)).area
    if depth > 1e-7:
        assert inter > 0
    if depth < -1e-7:
        assert inter == 0
    if inter > 1e-9:
        assert depth > 0


def test_penetration_depth_of_known_overlap():
    sq = tangram7().pieces[2].outline
    d = convex_penetration(sq, sq + [0.03, 0.0])
    assert math.isclose(float(d), np.ptp(sq[:, 0]) - 0.03, rel_tol=1e-9)
    assert float(convex_penetration(sq, sq + [0.05, 0.0])) < 0


def test_angle_gap_symmetry():
    assert math.isclose(float(angle_gap(0.1, 0.1 + math.pi / 2, math.pi / 2)), 0, abs_tol=1e-12)
    assert math.isclose(float(angle_gap(0.0, math.radians(30), 2 * math.pi)), math.radians(30))
    assert float(angle_gap(0.0, 1.0, 0.0)) == 0.0
