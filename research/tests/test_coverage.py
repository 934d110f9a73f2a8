"""rectified_colmap_research.evaluation.coverage: the residual transition tilt of a planar
pair's views, exact on planes seen by rotated cameras."""

import numpy as np
import pytest

from rectified_colmap.geometry import axis_angle_rotation
from rectified_colmap_research.evaluation.coverage import (
    View,
    anisotropy,
    asift_views,
    coverage,
    covered_scales,
    plain_view,
    residual_tilts,
    view_contains,
)

K = np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])
GRID = np.stack(np.meshgrid(np.arange(40.0, 600, 40), np.arange(40.0, 440, 40)), -1).reshape(-1, 2)


def oblique_pair(deg: float):
    """Camera 0 faces the plane z = 10 (frontal); camera 1 is camera 0 turned by ``deg``
    about y and moved so that it still sees the plane's centre: (G image 0 -> image 1,
    R of camera 1, n). Points x1 ~ K (R - t n^T / d) K^-1 x0 with t = R c (c: camera 1's
    centre in camera 0's frame)."""
    R = axis_angle_rotation(np.array([0.0, 1.0, 0.0]), np.deg2rad(deg))
    c = np.array([10.0 * np.sin(np.deg2rad(deg)), 0.0, 10.0 - 10.0 * np.cos(np.deg2rad(deg))])
    t = -R @ c
    n, d = np.array([0.0, 0.0, 1.0]), 10.0
    G = K @ (R + np.outer(t, n) / d) @ np.linalg.inv(K)
    return G / G[2, 2], R


def test_the_plain_pair_has_the_pairs_own_transition_tilt():
    stretch = np.diag([3.0, 1.0, 1.0])  # an affine pair: anisotropy 3 everywhere
    tilts, which = residual_tilts(stretch, GRID, [plain_view()], [plain_view()])
    assert tilts == pytest.approx(np.full(len(GRID), 3.0))
    assert (which == 0).all()


def test_a_view_that_undoes_the_pair_brings_the_tilt_to_one():
    stretch = np.diag([3.0, 1.0, 1.0])
    undo = View(np.diag([1 / 3.0, 1.0, 1.0]), kind="undo")
    tilts, which = residual_tilts(stretch, GRID, [plain_view()], [plain_view(), undo])
    assert tilts == pytest.approx(np.ones(len(GRID)))
    assert (which[:, 1] == 1).all()
    assert coverage(tilts) == 1.0


def test_the_true_rectification_of_an_oblique_image_leaves_no_tilt():
    """Camera 1 at 60 degrees sees the plane with tilt up to 2 and more; its view rotated
    back to camera 0's orientation (K R^T K^-1, what a rectified view with the true normal
    is) sees it frontal: A is then a similarity, anisotropy 1 (to rounding)."""
    G, R = oblique_pair(60.0)
    plain = residual_tilts(G, GRID, [plain_view()], [plain_view()])[0]
    assert np.median(plain) > 2.0
    back = View(K @ R.T @ np.linalg.inv(K), kind="true")
    tilts, _ = residual_tilts(G, GRID, [plain_view()], [plain_view(), back])
    assert np.abs(tilts - 1.0).max() < 1e-9


def test_only_views_that_contain_a_point_count():
    G, R = oblique_pair(60.0)
    back = K @ R.T @ np.linalg.inv(K)
    # the rotated-back view's pixels of image 1's points; a mask over its left half only
    xy1 = np.c_[GRID, np.ones(len(GRID))] @ G.T
    uv = np.c_[xy1[:, :2] / xy1[:, 2:], np.ones(len(GRID))] @ back.T
    uv = uv[:, :2] / uv[:, 2:]
    shift = 1.0 - uv.min(0)  # the view's pixels start at 0: move its origin
    back = np.array([[1, 0, shift[0]], [0, 1, shift[1]], [0, 0, 1.0]]) @ back
    uv += shift
    size = (int(np.ceil(uv[:, 0].max())) + 1, int(np.ceil(uv[:, 1].max())) + 1)
    mask = np.zeros((size[1], size[0]), bool)
    mask[:, : size[0] // 2] = True
    half = View(back, size, mask, kind="half")
    inside = view_contains(half, xy1[:, :2] / xy1[:, 2:])
    assert inside.any() and not inside.all()
    assert (inside == (np.floor(uv[:, 0]) < size[0] // 2)).all()
    tilts, which = residual_tilts(G, GRID, [plain_view()], [plain_view(), half])
    assert np.abs(tilts[inside] - 1.0).max() < 1e-9
    plain = residual_tilts(G, GRID, [plain_view()], [plain_view()])[0]
    assert (tilts[~inside] == plain[~inside]).all() and (which[~inside, 1] == 0).all()
    nothing = View(back, (1, 1), np.zeros((1, 1), bool))
    tilts, which = residual_tilts(G, GRID, [nothing], [nothing])
    assert np.isinf(tilts).all() and (which == -1).all()


def test_asift_views_sample_tilt_and_longitude():
    views = asift_views()
    A = np.array([v.H[:2, :2] for v in views])
    tilt = anisotropy(A)
    assert tilt[0] == pytest.approx(1.0)
    assert sorted(set(np.round(tilt, 6))) == pytest.approx([2 ** (k / 2) for k in range(6)])
    # at tilt t, longitudes 72 / t degrees apart, from 0 up to below 180
    t4 = [v for v, t in zip(views, tilt) if abs(t - 4.0) < 1e-6]
    assert len(t4) == 10
    # ASIFT's claim: an affine pair with tilt 3, at any longitude, has views of the two
    # images that leave a residual tilt below sqrt 2 between them
    for deg in (0.0, 17.0, 45.0, 90.0, 133.0):
        c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
        rot = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
        pair = rot.T @ np.diag([1 / 3.0, 1.0, 1.0]) @ rot
        tilts, _ = residual_tilts(pair, GRID[:3], views, views)
        assert tilts.max() < 2**0.5


def test_covered_scales_take_the_covering_pair_nearest_the_same_scale():
    """An affine pair with tilt 3: the plain images do not cover it; a view of image 1
    that undoes the tilt at 1/4 of the scale does (scale change 4 whichever way), and one
    that undoes it at half the scale is preferred; a view at the same scale that leaves
    the tilt counts for nothing."""
    stretch = np.diag([3.0, 1.0, 1.0])
    quarter = View(np.diag([1 / 12.0, 1 / 4.0, 1.0]))
    half = View(np.diag([1 / 6.0, 1 / 2.0, 1.0]))
    same = View(np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]]))  # a quarter turn
    plain = [plain_view()]
    assert np.isinf(covered_scales(stretch, GRID, plain, plain)).all()
    assert covered_scales(stretch, GRID, plain, [quarter]) == pytest.approx(np.full(len(GRID), 4.0))
    both = covered_scales(stretch, GRID, plain, [same, quarter, half])
    assert both == pytest.approx(np.full(len(GRID), 2.0))


def test_the_script_rows_and_report_tell_covered_from_solved(tmp_path):
    """view_coverage.py on an affine pair with tilt 3 over a 640 x 480 image: the plain
    images leave 3, a view of image 1 that undoes it 1; the records make the pair lost, and
    the report lists it among the covered pairs that were lost."""
    from types import SimpleNamespace

    from scripts_util import load_script

    from rectified_colmap.eval.homography import HomographyPair

    vc = load_script("view_coverage")
    stretch = np.diag([3.0, 1.0, 1.0])
    pair = HomographyPair("p", "a.jpg", "b.jpg", stretch, (640, 480), (1920, 480))
    pair.info.update(split="check", tilt_bin="2-4", scale_bin="<2x")
    undo = View(np.diag([1 / 3.0, 1.0, 1.0]), kind="depth")
    sets = {
        "plain": ([plain_view()], [plain_view()]),
        "default": ([plain_view()], [plain_view(), undo]),
    }
    sets["asift"] = (asift_views(), asift_views())
    row = vc.pair_row(pair, sets, 40.0)
    assert row["points"] == 16 * 12
    assert row["plain_tilt"] == pytest.approx(3.0) and row["default_tilt"] == pytest.approx(1.0)
    assert row["default_best"] == "plain+depth" and row["default_scale"] == pytest.approx(1.0)
    records = tmp_path / "records.csv"
    records.write_text("pair,method,direction,success\np,m,0->1,False\np,m,1->0,False\n")
    row.update({m: "p" in names for m, names in vc.solved_pairs([records]).items()})
    md = vc.report([row], ["m"], SimpleNamespace(data=tmp_path, split=None, conf="rectsift"))
    assert "| covered | 0 | 1 |" in md and "| p | check |" in md
