"""Vanishing-point modes of the pipeline: depth-free planes from lines (vp.depth_free) and
the `--orientation` flag of `rectified-colmap extract`."""

import cv2
import numpy as np
import pytest

from rectified_colmap import camera as cam_utils
from rectified_colmap_research import synth
from rectified_colmap.config import ExtractConf, VpConf
from rectified_colmap.features import (
    detect_sift,
    keypoints_in_mask,
    rectification_budgets,
    split_budget,
)
from rectified_colmap.pipeline import extract_image
from rectified_colmap.planes import Patch
from rectified_colmap.rectify import rectifications_within_area, viewing_coverage, viewing_masks
from rectified_colmap.vp.fusion import VpResult, manhattan_from_image
from rectified_colmap.vp.line_planes import (
    depth_free_planes,
    line_support_patches,
    whole_image_patches,
)
from rectified_colmap.vp.segments import Segments
from tests.scenes import REPLACING

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


def _depth_free_conf():
    # one view per line-support patch, in the replacing mode whose budget shares these
    # tests check (no plane hypotheses, no tilt neighbours, no features on top)
    conf = ExtractConf.from_dict(REPLACING)
    conf.vp.depth_free = True
    # These tests are about the planes lines give; the rule that leaves near-frontal
    # patches to plain SIFT (tested in test_pipeline.py) would drop most of this view's.
    conf.rectify.min_rectify_angle_deg = 0.0
    return conf


def test_depth_free_patches_have_gt_normals_and_face_the_camera(views):
    """On rendered streets, line-support patches carry the normal of the GT planes they
    cover (median angle to the GT normals of the patch's pixels < 3 deg for >= 85% of the
    patch area; a few small patches at plane junctions take a wrong axis), face the camera,
    and cover a useful part of the images. Two of the 8 views (ground targets: tiled ground
    and smooth walls, few sharp lines) have no two axes that pass the chance-level test
    (vp.manhattan.axis_log10_nfa): no frame, no patches."""
    conf = _depth_free_conf()
    good, total, coverage, frameless = 0, 0, [], 0
    for r, camera in views:
        gray = cv2.cvtColor(r.image, cv2.COLOR_RGB2GRAY)
        planes, res = depth_free_planes(gray, camera, (H, W), conf.vp, conf.planes.min_area_frac)
        if res.directions is None:  # streets are Manhattan scenes, but not always sharply
            assert planes.patches == []
            frameless += 1
            continue
        rays = cam_utils.grid_rays(camera, W, H)
        cov = 0.0
        for p in planes.patches:
            assert np.isclose(abs(p.normal @ planes.directions[p.axis]), 1.0)
            assert (planes.labels[p.mask] // 2 == p.axis).all()
            assert (rays[p.mask] @ p.normal < 0).all()  # seen from the front
            n = r.normals[p.mask]
            n = n[np.isfinite(n).all(1)]
            if len(n) < 50:  # mostly sky
                continue
            ang = np.degrees(np.arccos(np.clip(n @ p.normal, -1, 1)))
            good += len(ang) * (np.median(ang) < 3.0)
            total += len(ang)
            cov += p.area_frac
        coverage.append(cov)
    assert frameless <= 2
    assert total > 0.1 * len(views) * H * W
    assert good / total > 0.85, good / total
    assert np.mean(coverage) > 0.1, coverage


def test_depth_free_extraction_rectifies_patches(views):
    """extract_image without depth but with vp.depth_free: some features come from
    rectified patches, and their count stays within the budget."""
    conf = _depth_free_conf()
    conf.sift.max_num_features = 1024
    r, camera = views[4]  # a textured facade view
    res = extract_image(r.image, camera, None, conf)
    assert res.planes is not None and res.rectifications
    assert (res.features.patch >= 0).sum() > 50
    assert len(res.features) <= 2 * 1024  # second orientations at most double it


def test_depth_free_without_lines_is_exactly_plain_sift():
    """A scene without straight lines (blurred noise): no frame, so the output is exactly
    plain COLMAP SIFT with the same options."""
    rng = np.random.default_rng(0)
    noise = cv2.GaussianBlur(rng.random((H, W)).astype(np.float32), (0, 0), 6)
    gray = np.uint8(np.clip((noise - noise.min()) / np.ptp(noise) * 255, 0, 255))
    camera = synth.pinhole_camera(W, H, 0.9 * W)
    conf = _depth_free_conf()
    assert manhattan_from_image(gray, camera, conf.vp).directions is None
    res = extract_image(gray, camera, None, conf)
    plain = detect_sift(gray, conf.sift, conf.sift.max_num_features)
    assert not res.rectifications and not res.planes.patches
    np.testing.assert_array_equal(res.features.keypoints, plain.keypoints)
    np.testing.assert_array_equal(res.features.descriptors, plain.descriptors)


def test_depth_free_off_is_plain_sift(views):
    """vp.depth_free off (the default): no depth means plain SIFT, no planes."""
    r, camera = views[0]
    res = extract_image(r.image, camera, None, ExtractConf())
    assert res.planes is None and not res.rectifications


def test_line_support_needs_both_in_plane_families():
    """Exact geometry: a fronto-parallel wall (normal -z) drawn as a grid of horizontal
    (VP x) and vertical (VP y) lines in its left half, plus only horizontal lines in the
    right half. One patch of axis z, facing the camera, on the left half only."""
    camera = synth.pinhole_camera(W, H, 400.0)
    F = np.eye(3)
    xs = np.arange(20, 220, 12.0)
    ys = np.arange(20, 340, 12.0)
    hor = [[[20, y], [220, y]] for y in ys] + [[[260, y], [460, y]] for y in ys]
    ver = [[[x, 20], [x, 340]] for x in xs]
    xy = np.array(hor + ver, float)
    labels = np.array([0] * len(hor) + [1] * len(ver))
    seg = Segments(
        xy,
        np.linalg.norm(xy[:, 1] - xy[:, 0], axis=1),
        np.zeros((len(xy), 3)),
        np.zeros((len(xy), 3)),
        labels,
    )

    class MF:
        observed = np.array([True, True, False])

    res = VpResult(F, np.ones(3, bool), np.ones(3), F, seg, manhattan=MF())
    patches, lab = line_support_patches(res, camera, (H // 2, W // 2), VpConf(), 0.005)
    assert len(patches) == 1
    p = patches[0]
    assert p.axis == 2 and np.allclose(p.normal, [0, 0, -1])
    cols = np.flatnonzero(p.mask.any(0)) * 2 + 1  # work grid -> image columns
    assert cols.min() < 40 and 200 < cols.max() < 250  # the left half, not the right
    assert (lab[p.mask] == 5).all() and (lab[~p.mask] == -1).all()


def test_cli_orientation_flag_sets_vp_conf(monkeypatch, tmp_path):
    """--orientation maps to vp.enabled / vp.depth_free."""
    import rectified_colmap.extraction as ex
    from rectified_colmap.cli import main

    seen = {}

    class Summary:
        ok = True

        def report(self):
            return ""

    def fake_extract(*args, conf=None, **kw):
        seen["conf"] = conf
        return Summary()

    monkeypatch.setattr(ex, "extract", fake_extract)
    expect = {
        "depth": (False, False),
        "depth+vp": (True, False),
        "vp": (True, True),
        None: (ExtractConf().vp.enabled, ExtractConf().vp.depth_free),
    }
    for flag, (enabled, free) in expect.items():
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
        assert (seen["conf"].vp.enabled, seen["conf"].vp.depth_free) == (enabled, free)


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
    for enabled in (False, True):
        conf = ExtractConf()
        conf.vp.enabled = enabled
        conf.sift.max_num_features = 512
        conf.rectify.min_rectify_angle_deg = 0.0  # every patch: their normals are checked
        res = extract_image(r.image, camera, None, conf, normals=bad)
        e = []
        for rect in res.rectifications:
            n = r.normals[res.planes.patches[rect.patch_index].mask]
            n = n[np.isfinite(n).all(1)]
            e.append(np.median(np.degrees(np.arccos(np.clip(n @ rect.normal, -1, 1)))))
        assert e
        errs[enabled] = np.median(e)
    assert errs[False] > 8.0 and errs[True] < 1.0, errs


# -- depth-free whole-image warps (the paper's VP baseline, vp.depth_free_regions='whole') --


def _frame_result(F, trusted):
    """A VpResult carrying frame F (rows) with the given trusted axes, no segments."""
    seg = Segments(
        np.zeros((0, 2, 2)), np.zeros(0), np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0, int)
    )
    return VpResult(F, np.asarray(trusted, bool), np.ones(3), F, seg)


def test_whole_image_patches_are_the_half_spaces_of_the_vanishing_lines():
    """Exact geometry: for a frame whose three vanishing lines cross a wide pinhole image,
    each trusted axis gives two patches, exactly the cells on either side of its vanishing
    line l = K^-T F[k] (sign of l . (x, y, 1) at the cell centre), each with the normal
    facing those cells; every cell lies in one patch per trusted axis; labels pick the
    patch seen most frontally."""
    f, h, w = 240.0, 90, 120  # work grid of a 480x360 image, half FOV 45 deg
    camera = synth.pinhole_camera(W, H, f)
    F = _rot(np.cross([0, 0, 1], [1, 1, 1]), np.degrees(np.arccos(1 / np.sqrt(3)))).T
    F = F @ _rot([0.3, -0.2, 1.0], 7.0).T  # every axis ~55 deg from the view, no ties
    K = camera.calibration_matrix()
    xs, ys = np.meshgrid((np.arange(w) + 0.5) * W / w, (np.arange(h) + 0.5) * H / h)
    pix = np.stack([xs, ys, np.ones_like(xs)], -1)  # COLMAP pixel centres of the grid
    rays = cam_utils.grid_rays(camera, w, h)
    for trusted in ([True, True, True], [True, False, True]):
        patches, labels = whole_image_patches(
            _frame_result(F, trusted), camera, (h, w), VpConf(), 0.005
        )
        assert sorted(
            (p.axis, tuple(np.sign(p.normal @ F[p.axis]).astype(int).ravel())) for p in patches
        ) == sorted((k, (s,)) for k in np.flatnonzero(trusted) for s in (-1, 1))
        count = np.zeros((h, w), int)
        for p in patches:
            side = pix @ (np.linalg.inv(K).T @ F[p.axis])  # l . x, l the vanishing line
            expect = side < 0 if p.normal @ F[p.axis] > 0 else side > 0
            assert (p.mask == expect).all()
            assert (rays[p.mask] @ p.normal < 0).all()  # seen from the front
            assert 0.05 < p.area_frac < 0.95
            count += p.mask
        assert (count == sum(trusted)).all()  # overlapping: one warp per trusted axis
        cosines = np.stack([np.where(p.mask, -(rays @ p.normal), -np.inf) for p in patches])
        best = np.array([2 * p.axis + (p.normal @ F[p.axis] < 0) for p in patches])
        np.testing.assert_array_equal(labels, best[np.argmax(cosines, 0)])


def test_depth_free_regions_is_validated():
    with pytest.raises(ValueError, match="depth_free_regions"):
        ExtractConf.from_dict({"vp": {"depth_free_regions": "half"}})
    with pytest.raises(ValueError, match="depth_free_regions"):
        VpConf(depth_free_regions="all")


def test_budgets_of_overlapping_rectifications():
    """The total stays the budget; plain SIFT's share only depends on the union of the
    covered cells (half of it under keep_plain), overlapping warps split the rectified
    share by their own areas; disjoint patches get the former first-cover rule."""
    h, w, total = 40, 60, 1000
    left = np.zeros((h, w), bool)
    left[:, :30] = True
    top = np.zeros((h, w), bool)
    top[:10] = True
    for keep_plain in (True, False):
        b = rectification_budgets(np.stack([left, np.ones((h, w), bool)]), total, keep_plain)
        assert total - len(b) <= b.sum() <= total
        assert b[0] == (total // 2 if keep_plain else 0)
        assert abs(b[2] - 2 * b[1]) <= 2  # own areas 1/2 and 1 of the image
        masks = np.stack([left, top & ~left])  # disjoint: the former rule
        cover = viewing_coverage(masks)
        areas = np.bincount(cover.ravel() + 1, minlength=3).astype(float)
        if keep_plain:
            areas[0] += areas[1:].sum() / 2
            areas[1:] /= 2
        np.testing.assert_array_equal(
            rectification_budgets(masks, total, keep_plain), split_budget(total, areas)
        )


def test_overlapping_patches_keep_their_resolution():
    """The total-area budget scales with the overlap: two identical (fully overlapping)
    patches are planned at the size of one alone."""
    camera = synth.pinhole_camera(W, H, 0.9 * W)
    mask = np.ones((H // 4, W // 4), bool)
    patch = Patch(mask, 0, np.array([0.8, 0.0, -0.6]), 1.0)
    conf = ExtractConf()
    one = rectifications_within_area(camera, [patch], [0], conf.rectify)
    two = rectifications_within_area(camera, [patch, patch], [0, 1], conf.rectify)
    assert len(one) == 1 and len(two) == 2
    assert one[0].size == two[0].size == two[1].size


def test_whole_image_warps_end_to_end(views):
    """extract_image with depth_free_regions='whole' on a street view: the warps overlap,
    each one has features over its own region (also where another warp covers the
    cells), none outside its half-space, and plain SIFT keeps half of the budget."""
    conf = _depth_free_conf()
    conf.vp.depth_free_regions = "whole"
    conf.sift.max_num_features = 1024
    # The budget shares of rectification_budgets, without the near-duplicate removal and
    # plain-SIFT fill (tested in test_dedup.py), which would change plain SIFT's count.
    conf.dedup.enabled = False
    r, camera = views[4]
    res = extract_image(r.image, camera, None, conf)
    assert len(res.rectifications) >= 3
    masks = viewing_masks(
        camera,
        res.rectifications,
        res.planes.patches,
        res.planes.labels.shape,
        conf.rectify.max_viewing_angle_deg,
    )
    assert (masks.sum(0) >= 2).mean() > 0.3  # overlapping warps
    feats = res.features
    plain = feats.patch < 0
    assert 0.3 * 1024 < plain.sum() < 1024  # ~half the budget (+ second orientations)
    assert len(feats) <= 2 * 1024
    in_other = 0
    for i, rect in enumerate(res.rectifications):
        mine = feats.patch == rect.patch_index
        assert mine.sum() > 10
        inside = keypoints_in_mask(feats.keypoints[mine], masks[i], (W, H))
        assert inside.mean() > 0.95  # map back into its own (cropped) region
        others = masks[np.arange(len(masks)) != i].any(0)
        in_other += keypoints_in_mask(feats.keypoints[mine], others, (W, H)).sum()
    assert in_other > 50  # overlapping regions get features from several warps
