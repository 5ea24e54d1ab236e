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
