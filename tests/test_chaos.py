import numpy as np
import pytest
import shapely

from mrchaos.core.geometry import convex_penetration, rigid_transform
from mrchaos.figures.figure import Figure
from mrchaos.figures.pieces import tangram7
from mrchaos.tasks.chaos import ChaosCache, ChaosConfig, attract, generate, scatter

PS = tangram7()


def _polys(poses):
    return rigid_transform(PS.padded_outlines()[None], poses)


def _no_overlap_in_view(poses, half=0.125):
    polys = _polys(poses)
    ia, ib = np.triu_indices(7, 1)
    assert (convex_penetration(polys[:, ia], polys[:, ib]) <= 1e-12).all()
    assert np.abs(polys).max() <= half + 1e-12


def test_scatter_no_overlap_in_view_and_seeded():
    a = scatter(PS, 200, np.random.default_rng(3))
    _no_overlap_in_view(a)
    assert np.allclose(a, scatter(PS, 200, np.random.default_rng(3)))
    assert not np.allclose(a, scatter(PS, 200, np.random.default_rng(4)))
    assert np.abs(a[..., :2]).max() <= 0.10
    # Angles on the 45-degree grid by default, continuous on request.
    k = a[..., 2] / (np.pi / 4)
    assert np.allclose(k, np.round(k))
    c = scatter(PS, 50, np.random.default_rng(3), ChaosConfig(angle_step=0.0))
    assert not np.allclose(c[..., 2] / (np.pi / 4), np.round(c[..., 2] / (np.pi / 4)))


def test_attract_makes_touching_clusters():
    poses = attract(PS, 48, np.random.default_rng(5))
    _no_overlap_in_view(poses)
    isolated = 0
    spread_before = np.ptp(_polys(scatter(PS, 48, np.random.default_rng(5))), axis=(1, 2)).mean()
    spread_after = np.ptp(_polys(poses), axis=(1, 2)).mean()
    assert spread_after < 0.8 * spread_before
    for b in range(48):
        f = Figure("x", PS, poses[b])
        sp = [shapely.Polygon(f.piece_polygon(i)) for i in range(7)]
        for i in range(7):
            if min(sp[i].distance(sp[j]) for j in range(7) if j != i) > 5e-4:
                isolated += 1
    assert isolated <= 2  # of 336 pieces


def test_generate_mix_and_modes():
    poses, modes, _ = generate(PS, 100, np.random.default_rng(0), ChaosConfig(mode="mix", attract_fraction=0.5))
    assert 30 < int(modes.sum()) < 70
    _no_overlap_in_view(poses)
    _, m, _ = generate(PS, 10, np.random.default_rng(0), ChaosConfig(mode="scatter"))
    assert (m == 0).all()
    with pytest.raises(ValueError, match="chaos mode"):
        ChaosConfig(mode="bogus")


def test_cache_round_trip_and_errors(tmp_path):
    cache = ChaosCache.build(PS, 20, seed=1)
    path = tmp_path / "c.npz"
    cache.save(path)
    back = ChaosCache.load(path, PS)
    assert len(back) == 20 and np.allclose(back.poses, cache.poses, atol=1e-6)
    s1, m1 = back.sample(5, np.random.default_rng(0))
    assert s1.shape == (5, 7, 3) and np.allclose(s1, back.sample(5, np.random.default_rng(0))[0])
    assert m1.shape == (5, 7) and not m1.any()
    path.write_bytes(b"garbage")
    with pytest.raises(ValueError, match="c.npz: not a valid chaos cache"):
        ChaosCache.load(path)
    with pytest.raises(ValueError, match="no such chaos cache"):
        ChaosCache.load(tmp_path / "none.npz")


def test_a_cache_built_for_a_wider_view_is_refused(tmp_path):
    from mrchaos.core.raster import View
    from mrchaos.tasks.sampler import CacheConfig, MixConfig, TargetSampler, TaskConfig

    path = tmp_path / "wide.npz"
    ChaosCache.build(PS, 16, seed=2, view=View(0.26)).save(path)
    cfg = TaskConfig(mix=MixConfig(chaos=0.0, cache=1.0), cache=CacheConfig(path=str(path)))
    assert len(TargetSampler(PS, cfg, view=View(0.26)).cache) == 16
    with pytest.raises(ValueError, match="wide.npz: chaos cache objects reach"):
        TargetSampler(PS, cfg, view=View(0.16))


TILE = ChaosConfig(mode="tile")


def _parts_clear(poses, mirrored):
    """Every pair of pieces' convex parts at most touches (mirrored parts where flagged)."""
    fp = PS.footprints(poses, mirrored)  # (n, 7, V, 2): tangram pieces are convex
    ia, ib = np.triu_indices(7, 1)
    return convex_penetration(fp[:, ia], fp[:, ib]).max()


def test_tile_objects_do_not_overlap_fit_the_view_and_are_seeded():
    poses, modes, mirrored = generate(PS, 40, np.random.default_rng(11), TILE)
    assert (modes == 2).all() and not mirrored.any()
    assert _parts_clear(poses, mirrored) <= 1e-7
    assert np.abs(PS.footprints(poses)).max() <= 0.13 - TILE.margin + 1e-9
    k = poses[..., 2] / (np.pi / 4)
    assert np.allclose(k, np.round(k))  # the grid's angles
    again, _, _ = generate(PS, 40, np.random.default_rng(11), TILE)
    assert np.array_equal(poses, again)
    assert not np.allclose(poses, generate(PS, 40, np.random.default_rng(12), TILE)[0])


def test_tile_objects_are_joined_edge_to_edge_like_human_figures():
    from mrchaos.figures.joints import summarize_joints

    poses, _, mirrored = generate(PS, 60, np.random.default_rng(3), TILE)
    tile = summarize_joints(PS, poses, mirrored)
    assert tile.edge_share >= 0.70  # pieces sharing >= 25 mm of edge with a neighbour
    assert tile.blocks <= 2  # the median object is one or two blocks
    attract_poses, _, _ = generate(PS, 60, np.random.default_rng(3), ChaosConfig(mode="attract"))
    attract = summarize_joints(PS, attract_poses)
    assert tile.touching > attract.touching + 0.15 and attract.blocks >= 3


def test_tile_turns_pieces_over_with_mirror_prob():
    cfg = ChaosConfig(mode="tile", mirror_prob=0.5)
    poses, _, mirrored = generate(PS, 30, np.random.default_rng(4), cfg)
    assert mirrored[:, 3].any() and not mirrored[:, [0, 1, 2, 4, 5, 6]].any()  # only the parallelogram
    assert _parts_clear(poses, mirrored) <= 1e-7
    # Drawn face up, the turned-over parallelograms would not fit their joints.
    assert _parts_clear(poses, np.zeros_like(mirrored)) > 1e-4


def test_mix_takes_a_share_of_each_generator_and_keeps_old_draws_without_tile():
    cfg = ChaosConfig(mode="mix", attract_fraction=0.3, tile_fraction=0.4)
    _, modes, _ = generate(PS, 60, np.random.default_rng(0), cfg)
    assert set(np.unique(modes)) == {0, 1, 2}
    # Without a tile share, the modes are the paper's draw: attract where a uniform is under 1/2.
    _, modes, _ = generate(PS, 50, np.random.default_rng(5), ChaosConfig(mode="mix"))
    assert np.array_equal(modes, np.random.default_rng(5).random(50) < 0.5)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(attract_fraction=0.7, tile_fraction=0.5), "at most 1"),
        (dict(tile_fraction=-0.1), "tile_fraction"),
        (dict(tile_compactness=-1.0), "tile_compactness"),
        (dict(tile_hole_prob=2.0), "tile_hole_prob"),
    ],
)
def test_bad_tile_settings_are_refused(kwargs, match):
    with pytest.raises(ValueError, match=match):
        ChaosConfig(**kwargs)


def test_tile_needs_the_grid_angles():
    with pytest.raises(ValueError, match="angle_step"):
        generate(PS, 2, np.random.default_rng(0), ChaosConfig(mode="tile", angle_step=0.0))


def test_tile_holes_only_when_allowed():
    import shapely

    def holes(cfg):
        poses, _, mirrored = generate(PS, 40, np.random.default_rng(8), cfg)
        n = 0
        for b in range(len(poses)):
            polys = [shapely.Polygon(q).buffer(1e-6, join_style="mitre") for q in PS.footprints(poses[b], mirrored[b])]
            u = shapely.union_all(polys)
            n += any(shapely.Polygon(r).area > 1e-6 for g in getattr(u, "geoms", [u]) for r in g.interiors)
        return n

    assert holes(ChaosConfig(mode="tile", tile_hole_prob=0.0)) == 0
    assert holes(ChaosConfig(mode="tile", tile_hole_prob=1.0, tile_compactness=10.0)) > 0


def test_a_cache_of_other_generators_is_refused(tmp_path):
    from mrchaos.tasks.sampler import CacheConfig, MixConfig, TargetSampler, TaskConfig

    path = tmp_path / "mix.npz"
    ChaosCache.build(PS, 12, seed=2).save(path)  # scatter and attract, no tile
    mix = MixConfig(chaos=0.0, cache=1.0)
    assert len(TargetSampler(PS, TaskConfig(mix=mix, cache=CacheConfig(path=str(path)))).cache) == 12
    for chaos in (ChaosConfig(mode="mix", tile_fraction=0.3), ChaosConfig(mode="tile")):
        with pytest.raises(ValueError, match="mix.npz: chaos cache holds scatter, attract objects"):
            TargetSampler(PS, TaskConfig(mix=mix, chaos=chaos, cache=CacheConfig(path=str(path))))
