import json
import math

import numpy as np
import pytest

from mrchaos.core.geometry import rigid_transform
from mrchaos.figures.families import FamilyRule, confusion_table
from mrchaos.figures.figure import Figure, FigureError
from mrchaos.figures.formats import load_figures, load_json, save_figures
from mrchaos.figures.kilogram import svg_to_figure
from mrchaos.figures.pieces import tangram7


def test_mrchaos104_loads_valid(mrchaos104):
    assert len(mrchaos104.figures) == 104 and not mrchaos104.rejected
    assert not any(f.has_mirrored for f in mrchaos104.figures)
    for f in mrchaos104.figures:
        assert f.family in ("H-Normal", "H-Hard", "H-Fiendish")
        sil = f.silhouette().sum().item() * (0.26 / 120) ** 2
        assert abs(sil - 0.01) < 0.0006  # overlap-free up to the digitisation's small overlaps


def test_family_rule_agrees_with_labels(mrchaos104):
    table, text = confusion_table(mrchaos104.figures, FamilyRule())
    print(text)
    assert table.sum() == 104
    assert np.trace(table) >= 90


def test_json_round_trip(tmp_path, mrchaos104):
    figs = mrchaos104.figures[:5]
    out = tmp_path / "set.json"
    save_figures(figs, out, name="five")
    back = load_json(out)
    assert [f.id for f in back.figures] == [f.id for f in figs]
    for a, b in zip(figs, back.figures, strict=True):
        assert np.allclose(a.polygons(), b.polygons(), atol=2e-6)
        assert a.family == b.family


def _write(tmp_path, data, name="bad.json"):
    p = tmp_path / name
    p.write_text(data if isinstance(data, str) else json.dumps(data))
    return p


def _good_entry(fid="f"):
    ps = tangram7()
    poses = np.array(
        [
            [-0.05, 0.05, 0],
            [0.05, 0.05, 0],
            [-0.05, -0.05, 0],
            [0.05, -0.05, 0],
            [0.0, 0.0, 0],
            [-0.09, 0.0, 0],
            [0.09, 0.0, 0],
        ],
        float,
    )
    poses[:, :2] *= 1.0
    f = Figure(fid, ps, poses)
    pieces = [{"piece": n, "vertices": f.piece_polygon(i).tolist()} for i, n in enumerate(ps.names)]
    return {"id": fid, "pieces": pieces}


def test_malformed_files_name_file_and_figure(tmp_path):
    with pytest.raises(FigureError, match="bad.json.*not valid JSON"):
        load_json(_write(tmp_path, "{nope"))
    with pytest.raises(FigureError, match="no such figure file"):
        load_figures(tmp_path / "missing.json")
    with pytest.raises(FigureError, match="'figures' list"):
        load_json(_write(tmp_path, {"x": 1}))

    def rejected(entry):
        fs = load_json(_write(tmp_path, {"figures": [entry]}))
        assert not fs.figures and len(fs.rejected) == 1
        fid, why = fs.rejected[0]
        assert "bad.json" in why and repr(entry.get("id", "")) in why or fid in why
        return why

    e = _good_entry("f1")
    assert "overlap" not in rejected({**e, "pieces": e["pieces"][:6]})  # wrong piece count
    assert "missing" in rejected({**e, "pieces": e["pieces"][:6]})
    e2 = json.loads(json.dumps(_good_entry("f2")))
    e2["pieces"][2]["vertices"][0][0] = float("nan")
    assert "NaN" in rejected(e2)
    e3 = json.loads(json.dumps(_good_entry("f3")))
    e3["pieces"][4]["vertices"] = e3["pieces"][2]["vertices"]  # square's outline for the medium triangle
    assert "medium_triangle" in rejected(e3)
    e4 = json.loads(json.dumps(_good_entry("f4")))
    e4["pieces"][1]["vertices"] = e4["pieces"][0]["vertices"]  # two large triangles on one spot
    assert "overlap" in rejected(e4)
    e5 = json.loads(json.dumps(_good_entry("f5")))
    e5["pieces"][2]["vertices"] = (np.array(e5["pieces"][2]["vertices"]) + [0.2, 0]).tolist()
    assert "outside" in rejected(e5)


def test_the_good_entry_is_valid(tmp_path):
    fs = load_json(_write(tmp_path, {"figures": [_good_entry()]}))
    assert len(fs.figures) == 1, fs.rejected


def test_mirrored_parallelogram_is_flagged():
    ps = tangram7()
    par = ps.pieces[3]
    polys = [
        rigid_transform(p.outline, np.array([0.3 * (i - 3) / 3, 0.0, 0.0])) * [0.3, 1] for i, p in enumerate(ps.pieces)
    ]
    from mrchaos.figures.figure import figure_from_polygons

    polys = [rigid_transform(p.outline, np.array([0.0, 0.0, 0.0])) for p in ps.pieces]
    polys[3] = rigid_transform(par.mirrored_outline(), np.array([0.0, 0.0, 0.3]))
    fig = figure_from_polygons(ps, polys, "m")
    assert fig.has_mirrored and fig.mirrored.tolist() == [False, False, False, True, False, False, False]


def test_kilogram_samples_import(kilogram_dir):
    fs = load_figures(kilogram_dir)
    assert len(fs.figures) == 3 and not fs.rejected
    for f in fs.figures:
        norm = [np.asarray(p) for p in f.meta["normalised_polygons"]]
        for i in range(7):
            rebuilt = f.piece_polygon(i)
            dev = np.linalg.norm(rebuilt[:, None] - norm[i][None], axis=-1).min(1).max()
            distorted = ("large_triangle_1", "large_triangle_2", "medium_triangle")
            if f.id == "page-A" and f.piece_set.names[i] in distorted and dev > 0.5e-3:
                # The book's digitisation distorts these two triangles (edges 107.7/109.1/154.6 and
                # 66.4/67.8/93.2 SVG units against 106.15/106.15/150.12 and 75.06/75.06/106.15):
                # no exact piece is within 0.5 mm, so the importer keeps the best fit.
                assert 0.5e-3 < dev < 6e-3
                continue
            assert dev < 0.5e-3, (f.id, f.piece_set.names[i], dev)
        if f.id == "page-A":
            errs = np.array(f.meta["fit_error_m"])
            assert (errs > 0.5e-3).sum() == 2 and (errs < 1e-5).sum() == 5
        f.validate()


def test_kilogram_rejects_non_tangram(tmp_path):
    svg = tmp_path / "six.svg"
    polys = "".join(f'<polygon points="{i * 10},0 {i * 10 + 5},0 {i * 10},5"/>' for i in range(6))
    svg.write_text(f'<svg xmlns="http://www.w3.org/2000/svg">{polys}</svg>')
    with pytest.raises(FigureError, match="six.svg.*not a standard tangram: 6 polygons"):
        svg_to_figure(svg)
    svg.write_text("<svg><polygon points='1 2 3'")
    with pytest.raises(FigureError, match="malformed SVG"):
        svg_to_figure(svg)
    # Seven triangles: shapes do not match the tangram's.
    polys = "".join(f'<polygon points="{i * 10},0 {i * 10 + 5},0 {i * 10},5"/>' for i in range(7))
    svg.write_text(f'<svg xmlns="http://www.w3.org/2000/svg">{polys}</svg>')
    with pytest.raises(FigureError, match="not a standard tangram"):
        svg_to_figure(svg)


def test_kilogram_transforms_and_y_flip(tmp_path):
    """A figure written to SVG with a rotate+scale transform and y down imports back to the same shape."""
    ps = tangram7()
    fig = Figure(
        "t",
        ps,
        np.array(
            [
                [-0.05, 0.05, 0],
                [0.05, 0.05, math.pi / 2],
                [-0.05, -0.05, 0.3],
                [0.05, -0.05, 0.1],
                [0.0, 0.0, 0],
                [-0.09, 0.0, 1.0],
                [0.09, 0.0, 2.0],
            ]
        ),
    )
    body = ""
    for i in range(7):
        pts = fig.piece_polygon(i) * [1000, -1000]  # mm, y down
        pts = pts @ np.array([[0, -1], [1, 0]])  # rotate by -90 deg, undone by rotate(90) below
        points = " ".join(f"{x / 2:.6f},{y / 2:.6f}" for x, y in pts)
        body += '<g transform="scale(2)"><polygon transform="rotate(90)" points="' + points + '"/></g>'
    svg = tmp_path / "t.svg"
    svg.write_text(f'<svg xmlns="http://www.w3.org/2000/svg">{body}</svg>')
    back = svg_to_figure(svg)
    allv = np.concatenate([fig.piece_polygon(i) for i in range(7)])
    centre = (allv.min(0) + allv.max(0)) / 2
    tw = ps.twin_matrix()
    for i in range(7):  # twins may trade places
        assert any(
            np.allclose(back.piece_polygon(i), fig.piece_polygon(j) - centre, atol=1e-6) for j in np.flatnonzero(tw[i])
        )
