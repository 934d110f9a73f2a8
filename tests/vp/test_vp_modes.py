"""Vanishing points in the pipeline: line frames correcting the depth planes' orientation,
the views of overlapping patches, and the `--orientation` flag of `rectified-colmap extract`."""

import cv2
import numpy as np
import pytest

from rectified_colmap_research import synth
from rectified_colmap.budget import view_pixel_budget
from rectified_colmap.config import ExtractConf
from rectified_colmap.depth import DepthMap
from rectified_colmap.pipeline import (
    extract_image,
    image_planes,
    views_and_features,
    with_vanishing_points,
)
from rectified_colmap.planes import HYPOTHESIS_AXIS, Patch, detect_planes
from rectified_colmap.sift import plain_sift
from rectified_colmap.views import (
    plan_views,
    rectifications_within_budget,
    shared_cells,
    water_fill,
)
from tests.scenes import SINGLE_VIEW

W, H = 480, 360


def _views(seeds=range(4)):
    out = []
    for seed in seeds:
        rng = np.random.default_rng(seed)
        scene = synth.street(rng)
        camera = synth.pinhole_camera(W, H, 0.9 * W)
        target = ("facade", "ground")[seed % 2]
        p0, p1, _ = synth.view_pair(scene, rng, 50, 90, target=target, camera=camera)
        for pose in (p0, p1):
            out.append((synth.render(scene, camera, pose), camera))
    return out


@pytest.fixture(scope="module")
def views():
    return _views()


def test_cli_orientation_flag_sets_vp_conf(monkeypatch, tmp_path):
    """--orientation maps to vp.enabled; the retired depth-free choice is an error."""
    import rectified_colmap.extraction as ex
    from rectified_colmap.cli import main

    seen = {}

    class Summary:
        ok = True

        def report(self):
            return ""

    def fake_extract(image_dir, database, hloc_features, conf, *args, **kw):
        seen["conf"] = conf
        return Summary()

    monkeypatch.setattr(ex, "extract", fake_extract)
    expect = {"depth": False, "depth+vp": True, None: ExtractConf().vp.enabled}
    for flag, enabled in expect.items():
        argv = [
            "extract",
            "--image_path",
            str(tmp_path),
            "--hloc_features",
            str(tmp_path / "f.h5"),
            "--depth_model",
            "none",
            "--no_progress",
        ]
        argv += ["--orientation", flag] if flag else []
        assert main(argv) == 0
        assert seen["conf"].vp.enabled == enabled
    assert main(argv + ["--orientation", "vp"]) == 2


def _rot(axis, deg):
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    t = np.deg2rad(deg)
    return np.eye(3) + np.sin(t) * K + (1 - np.cos(t)) * K @ K


def test_vp_fusion_in_pipeline_corrects_rotated_normals(views):
    """GT normals rotated by 12 deg (a mediocre network): with vp.enabled the rectified
    patches' normals come back within 1 deg of the GT normals of their pixels; without,
    they stay ~12 deg off."""
    r, camera = views[4]
    bad = r.normals @ _rot([1, 2, 0.5], 12.0).T  # NaN (sky) stays NaN
    errs = {}
    gray = cv2.cvtColor(r.image, cv2.COLOR_RGB2GRAY)
    for enabled in (False, True):
        conf = ExtractConf.from_dict(SINGLE_VIEW)  # the depth planes' own views
        conf.vp.enabled = enabled
        conf.rectify.min_rectify_angle_deg = 0.0  # every patch: their normals are checked
        planes = detect_planes(bad, conf.planes, np.random.default_rng(0))
        planes = with_vanishing_points(gray, camera, planes, conf, np.random.default_rng(0), {})
        pixels = view_pixel_budget(gray.shape, conf)
        views = plan_views(gray, camera, planes.patches, planes.labels.shape, conf.rectify, pixels)
        e = []
        for rect in views.rects:
            n = r.normals[views.patches[rect.patch_index].mask]
            n = n[np.isfinite(n).all(1)]
            e.append(np.median(np.degrees(np.arccos(np.clip(n @ rect.normal, -1, 1)))))
        assert e
        errs[enabled] = np.median(e)
    assert errs[False] > 8.0 and errs[True] < 1.0, errs


def test_no_plane_hypotheses_where_plain_sift_fills_its_budget(views):
    """Where plain SIFT fills its budget the plane hypotheses are not built (their views
    would all be dropped, pipeline.patches_with_room): ``extract_image`` gives exactly the
    features and views of the path that builds them and drops them; where the budget has
    room, they are built."""
    r, camera = views[5]  # two plane hypotheses
    gray = cv2.cvtColor(r.image, cv2.COLOR_RGB2GRAY)
    depth = DepthMap(r.depth, "metric")
    for n, full in ((300, True), (20000, False)):
        conf = ExtractConf()
        conf.sift.max_num_features = n
        plain = plain_sift(gray, conf.sift)
        assert (len(plain) >= n) == full
        rng = np.random.default_rng(0)
        planes, _ = image_planes(camera, depth, conf, rng, {})
        built = with_vanishing_points(gray, camera, planes, conf, rng, {})
        assert any(p.axis == HYPOTHESIS_AXIS for p in built.patches)
        rng = np.random.default_rng(0)
        planes, _ = image_planes(camera, depth, conf, rng, {})
        kept = with_vanishing_points(gray, camera, planes, conf, rng, {}, len(plain))
        assert any(p.axis == HYPOTHESIS_AXIS for p in kept.patches) != full
        shape = planes.labels.shape
        views, f = views_and_features(gray, camera, built.patches, shape, plain, conf)
        res = extract_image(r.image, camera, depth, conf)
        np.testing.assert_array_equal(res.features.keypoints, f.keypoints)
        np.testing.assert_array_equal(res.features.descriptors, f.descriptors)
        assert len(res.rectifications) == len(views.rects) > 0
        for a, b in zip(res.rectifications, views.rects):
            np.testing.assert_array_equal(a.R, b.R)
            np.testing.assert_array_equal(a.K, b.K)
            assert a.size == b.size and a.patch_index == b.patch_index


@pytest.mark.filterwarnings("error::RuntimeWarning")  # no inf x 0 for a claim of weight 0
@pytest.mark.parametrize("seed", range(5))
def test_water_fill_is_the_largest_common_cap(seed):
    """Shares min(need, c x weight) summing to the total, c the largest such: the same c as
    a bisection finds; claims under their cap keep their need; nothing is given when
    everything fits beyond the needs."""
    rng = np.random.default_rng(seed)
    needs = rng.uniform(1, 100, 9) ** 2
    weights = rng.uniform(0.1, 3, 9)
    total = 0.4 * needs.sum()
    share = water_fill(needs, weights, total)
    assert share.sum() == pytest.approx(total)
    assert np.all(share <= needs + 1e-9)
    lo, hi = 0.0, needs.max() / weights.min()
    for _ in range(200):
        c = 0.5 * (lo + hi)
        lo, hi = (c, hi) if np.minimum(needs, c * weights).sum() < total else (lo, c)
    np.testing.assert_allclose(share, np.minimum(needs, lo * weights), rtol=1e-9)
    capped = share < needs
    assert capped.any() and (~capped).any()
    np.testing.assert_allclose(share[capped] / weights[capped], lo, rtol=1e-9)
    np.testing.assert_array_equal(water_fill(needs, weights, 2 * needs.sum()), needs)
    np.testing.assert_allclose(water_fill([4.0, 10.0, 10.0], [0.0, 1.0, 1.0], 10.0), [0, 5, 5])


def _oblique_views(patches, budget):
    camera = synth.pinhole_camera(W, H, 0.9 * W)
    conf = ExtractConf().rectify
    return rectifications_within_budget(camera, patches, list(range(len(patches))), conf, budget)


def _pixels(views):
    return np.array([r.size[0] * r.size[1] for r in views], float)


def test_a_large_view_takes_no_pixels_of_a_small_one():
    """A small patch and a large, strongly oblique one over the budget: the small view
    keeps its full size (its cells' claim is more than it needs), the large one takes the
    rest (one scale for all views, the rule before, shrank both alike)."""
    small = np.zeros((H // 4, W // 4), bool)
    small[:20, :30] = True
    frontal = Patch(small, 0, np.array([0.0, 0.0, -1.0]), float(small.mean()))
    oblique = Patch(~small, 1, np.array([0.9, 0.0, -0.436]), float((~small).mean()))
    free = _oblique_views([frontal, oblique], 1e12)
    need = _pixels(free)
    budget = need[0] + 0.3 * need[1]
    assert budget < 0.5 * need.sum()  # one scale for all would halve the small view too
    views = _oblique_views([frontal, oblique], budget)
    got = _pixels(views)
    assert got.sum() <= budget
    assert views[0].size == free[0].size and views[0].K[0, 0] == pytest.approx(free[0].K[0, 0])
    assert 0.28 * need[1] < got[1] <= budget - need[0]


def test_views_over_the_same_cells_share_their_claim():
    """Two views of one half of the image (a plane and a hypothesis over the same cells)
    and one of the other half, all needing more than the budget: the two together get
    what the one gets (each half of it), and the budget is spent."""
    left = np.zeros((H // 4, W // 4), bool)
    left[:, : W // 8] = True
    a = Patch(left, 0, np.array([0.8, 0.0, -0.6]), 0.5)
    b = Patch(left, 1, np.array([0.0, 0.8, -0.6]), 0.5)
    c = Patch(~left, 2, np.array([-0.8, 0.0, -0.6]), 0.5)
    budget = 0.2 * _pixels(_oblique_views([a, b, c], 1e12)).min()
    got = _pixels(_oblique_views([a, b, c], budget))
    assert got.sum() <= budget and got.sum() > 0.97 * budget
    assert got[2] == pytest.approx(got[0] + got[1], rel=0.05)
    assert got[0] == pytest.approx(got[1], rel=0.05)
    np.testing.assert_allclose(
        shared_cells(np.stack([left, left, ~left])), [left.sum() / 2, left.sum() / 2, (~left).sum()]
    )


def test_views_share_the_pixel_budget():
    """All views of an image together stay within the pixel budget: two views of the same
    patch get half the pixels each that one alone gets, and a budget beyond the views'
    own size leaves them at full resolution."""
    camera = synth.pinhole_camera(W, H, 0.9 * W)
    mask = np.ones((H // 4, W // 4), bool)
    patch = Patch(mask, 0, np.array([0.8, 0.0, -0.6]), 1.0)
    conf = ExtractConf().rectify
    budget = 0.5 * W * H
    one = rectifications_within_budget(camera, [patch], [0], conf, budget)
    two = rectifications_within_budget(camera, [patch, patch], [0, 1], conf, budget)
    assert len(one) == 1 and len(two) == 2
    pixels = [r.size[0] * r.size[1] for r in one + two]
    assert pixels[0] <= budget and pixels[1] + pixels[2] <= budget
    assert abs(pixels[1] / pixels[0] - 0.5) < 0.05
    free = rectifications_within_budget(camera, [patch], [0], conf, 1e12)
    f = free[0].K[0, 0]
    assert abs(one[0].K[0, 0] / f - np.sqrt(budget / (free[0].size[0] * free[0].size[1]))) < 0.02
