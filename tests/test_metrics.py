import math

import numpy as np
import pytest
import torch

from mrchaos.core.geometry import rigid_transform
from mrchaos.core.raster import View, rasterize
from mrchaos.env.metrics import (
    coverage_counts,
    final_coverage,
    gate_angle,
    gate_penetration,
    iou,
    piece_coverage,
    rela,
    shape_reward,
    strict_rela,
)
from mrchaos.figures.pieces import tangram7

PS = tangram7()
P = len(PS)
TW = PS.twin_matrix()


def blank() -> torch.Tensor:
    return torch.full((1, 40, 40), -1, dtype=torch.int8)


def cover(cur, tgt):
    c, a = coverage_counts(cur, tgt, P)
    return piece_coverage(c, a, TW)[0]


def test_piece_on_target_scores_one():
    tgt = blank()
    tgt[0, 5:15, 5:15] = 2
    assert cover(tgt.clone(), tgt)[2].item() == 1.0


def test_known_shift_scores_known_fraction():
    tgt = blank()
    tgt[0, 5:15, 5:15] = 2  # 100 px
    cur = blank()
    cur[0, 5:15, 8:18] = 2  # 3 columns off: 70 px on target
    assert cover(cur, tgt)[2].item() == pytest.approx(0.7)
    cur2 = blank()
    cur2[0, 7:15, 5:15] = 2
    cur2[0, 5:7, 5:15] = 4  # piece 4 hides two rows
    assert cover(cur2, tgt)[2].item() == pytest.approx(0.8)


def test_rasterised_shift_by_whole_pixels():
    view = View()
    sq = PS.pieces[2].outline
    tgt = rasterize(rigid_transform(sq, np.array([0.01, 0.0, 0.0]))[None, None], view).ids
    cur = rasterize(rigid_transform(sq, np.array([0.01 + 4 * view.pixel, 0.0, 0.0]))[None, None], view).ids
    rows = int((tgt[0] >= 0).any(1).sum())
    cols = int((tgt[0] >= 0).any(0).sum())
    c, a = coverage_counts(cur, tgt, 1)
    assert a[0, 0].item() == rows * cols
    assert c[0, 0, 0].item() / a[0, 0].item() == pytest.approx((cols - 4) / cols)


def test_swapped_twins_score_one():
    tgt = blank()
    tgt[0, 0:10, 0:10] = 0
    tgt[0, 20:30, 20:30] = 1
    cur = blank()
    cur[0, 0:10, 0:10] = 1
    cur[0, 20:30, 20:30] = 0
    cov = cover(cur, tgt)
    assert cov[0].item() == 1.0 and cov[1].item() == 1.0
    assert strict_rela(cur, tgt, PS.twins, P)[0].item() == pytest.approx(2 / 7)


def test_both_twins_on_one_slot_rela_vs_strict():
    tgt = blank()
    tgt[0, 0:10, 0:10] = 5
    tgt[0, 20:30, 20:30] = 6
    # Step 1: small triangle 1 on slot 5. Step 2: small triangle 2 on the same slot, on top.
    step1 = blank()
    step1[0, 0:10, 0:10] = 5
    step2 = blank()
    step2[0, 0:10, 0:10] = 6
    r1, r2 = cover(step1, tgt)[5].item(), cover(step2, tgt)[6].item()
    assert r1 == 1.0 and r2 == 1.0  # the paper's per-step reward: both pay
    assert rela(torch.tensor([[r1, r2]]))[0].item() == 1.0
    # Strict Rela on the final scene: one slot, one twin -> only one of the two scores.
    s = strict_rela(step2, tgt, PS.twins, P)[0].item()
    assert s == pytest.approx(1 / 7)


def test_empty_scene_scores_zero():
    tgt = blank()
    tgt[0, 0:10, 0:10] = 2
    cur = blank()
    assert cover(cur, tgt).sum().item() == 0.0
    sil = tgt >= 0
    assert final_coverage(cur, sil)[0].item() == 0.0
    assert iou(cur, sil)[0].item() == 0.0
    assert strict_rela(cur, tgt, PS.twins, P)[0].item() == 0.0


def test_final_ignores_spill_but_iou_does_not():
    tgt = blank()
    tgt[0, 0:10, 0:10] = 2
    cur = blank()
    cur[0, 0:10, 0:10] = 2
    cur[0, 20:30, 20:30] = 3  # a piece spilled outside
    sil = tgt >= 0
    assert final_coverage(cur, sil)[0].item() == 1.0
    assert iou(cur, sil)[0].item() == pytest.approx(0.5)


def test_shaping_and_gates():
    cov = torch.tensor([0.3, 0.75, 1.0, 0.3])
    shaped = torch.tensor([True, True, True, False])
    assert shape_reward(cov, shaped).tolist() == pytest.approx([0.0, 0.5, 1.0, 0.3])
    r = torch.ones(3)
    assert gate_penetration(r, torch.tensor([0.0, 0.0019, 0.0021])).tolist() == [1.0, 1.0, 0.0]
    theta = torch.tensor([0.0, math.radians(15), math.radians(25), math.radians(90), math.radians(170)])
    tgt = torch.zeros(5)
    period = torch.tensor([2 * math.pi, 2 * math.pi, 2 * math.pi, math.pi / 2, 0.0])
    assert gate_angle(torch.ones(5), theta, tgt, period).tolist() == [1.0, 1.0, 0.0, 1.0, 1.0]


def test_counts_fast_path_equals_generic():
    g = torch.Generator().manual_seed(0)
    cur = torch.randint(-1, P, (700, 30, 30), generator=g, dtype=torch.int64).to(torch.int8)
    tgt = torch.randint(-1, P, (700, 30, 30), generator=g, dtype=torch.int64).to(torch.int8)
    c1, a1 = coverage_counts(cur, tgt, P)
    c2, a2 = coverage_counts(cur.long(), tgt.long(), P)
    assert torch.equal(c1, c2) and torch.equal(a1, a2)
    brute = ((cur[3] == 2) & (tgt[3] == 4)).sum()
    assert c1[3, 2, 4] == brute
