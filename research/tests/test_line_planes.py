"""research/rectified_colmap_research/line_planes.py: depth-free planes from lines (the
training's normal labels, the VP-only rows of scripts/eval_vp.py), and the pipeline on them."""

import cv2
import numpy as np
import pytest
from rectified_colmap_research.line_planes import (
    LinePlaneConf,
    depth_free_planes,
    extract_depth_free,
    line_support_patches,
    manhattan_from_image,
    whole_image_patches,
)

from rectified_colmap import camera as cam_utils
from rectified_colmap_research import synth
from rectified_colmap.config import ExtractConf, VpConf
from rectified_colmap.features import keypoints_in_mask
from rectified_colmap.sift import detect_sift
from rectified_colmap.views import viewing_masks
from rectified_colmap.vp.fusion import VpResult
from rectified_colmap.vp.segments import Segments

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


def test_depth_free_patches_have_gt_normals_and_face_the_camera(views):
    """On rendered streets, line-support patches carry the normal of the GT planes they
    cover (median angle to the GT normals of the patch's pixels < 3 deg for >= 85% of the
    patch area; a few small patches at plane junctions take a wrong axis), face the camera,
    and cover a useful part of the images. Two of the 8 views (ground targets: tiled ground
    and smooth walls, few sharp lines) have no two axes that pass the chance-level test
    (rectified_colmap.vp.manhattan.axis_log10_nfa): no frame, no patches."""
    conf = ExtractConf()
    good, total, coverage, frameless = 0, 0, [], 0
    for r, camera in views:
        gray = cv2.cvtColor(r.image, cv2.COLOR_RGB2GRAY)
        planes, res = depth_free_planes(gray, camera, (H, W), conf.vp)
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


def test_depth_free_extraction_rectifies_patches_on_top_of_plain_sift(views):
    """The pipeline without depth, planes from lines: features from rectified views on top
    of every plain SIFT feature, within the budget's cap."""
    conf = ExtractConf()
    conf.sift.max_num_features = 1024
    conf.rectify.min_rectify_angle_deg = 0.0  # the line planes' views are the point here
    r, camera = views[4]  # a textured facade view
    res = extract_depth_free(r.image, camera, conf)
    assert res.planes is not None and res.rectifications
    feats = res.features
    plain = detect_sift(cv2.cvtColor(r.image, cv2.COLOR_RGB2GRAY), conf.sift)
    np.testing.assert_array_equal(feats.keypoints[feats.patch < 0], plain.keypoints)
    assert 50 < (feats.patch >= 0).sum() <= 0.5 * len(plain) + 1


def test_depth_free_without_lines_is_exactly_plain_sift():
    """A scene without straight lines (blurred noise): no frame, so without plane
    hypotheses (which need no frame) the output is exactly plain COLMAP SIFT, with blind
    views (planes.BLIND_AXIS) on top only where plain SIFT left budget unused."""
    from rectified_colmap.planes import BLIND_AXIS

    rng = np.random.default_rng(0)
    noise = cv2.GaussianBlur(rng.random((H, W)).astype(np.float32), (0, 0), 6)
    gray = np.uint8(np.clip((noise - noise.min()) / np.ptp(noise) * 255, 0, 255))
    camera = synth.pinhole_camera(W, H, 0.9 * W)
    no_second = {"vp": {"line_hypotheses": 0}, "dedup": {"lookalikes_in_unused_budget": False}}
    conf = ExtractConf.from_dict(no_second)
    assert manhattan_from_image(gray, camera, conf.vp).directions is None
    res = extract_depth_free(gray, camera, conf)
    plain = detect_sift(gray, conf.sift, conf.sift.max_num_features)
    assert not res.rectifications and not res.planes.patches
    np.testing.assert_array_equal(res.features.keypoints, plain.keypoints)
    np.testing.assert_array_equal(res.features.descriptors, plain.descriptors)
    assert len(plain) < conf.sift.max_num_features  # so the default adds blind views
    res = extract_depth_free(gray, camera, ExtractConf.from_dict({"vp": {"line_hypotheses": 0}}))
    assert res.rectifications
    assert {p.axis for p in res.planes.patches} == {BLIND_AXIS}
    kept = res.features.subset(res.features.patch < 0)
    np.testing.assert_array_equal(kept.keypoints, plain.keypoints)


def test_manhattan_from_image_trusts_a_rendered_street():
    from rectified_colmap_research.synth.lines import axis_errors_deg, render_street, street_camera
    from rectified_colmap_research.vp_drawing import draw_directions, draw_segments

    rng = np.random.default_rng(4)
    camera = synth.pinhole_camera(640, 432, 500.0)
    R = street_camera(rng, yaw=35, pitch=-5, roll=3)
    img = render_street(camera, R, rng, clutter=0.2)
    res = manhattan_from_image(img, camera, VpConf())
    assert res.directions is not None and res.snapped.sum() >= 2
    assert axis_errors_deg(res.directions, R.T).max() < 0.5
    assert draw_segments(img, res).shape == (432, 640, 3)
    assert draw_directions(img, camera, res, np.eye(3)).shape == (432, 640, 3)


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
    patches, lab = line_support_patches(res, camera, (H // 2, W // 2), LinePlaneConf(), 0.005)
    assert len(patches) == 1
    p = patches[0]
    assert p.axis == 2 and np.allclose(p.normal, [0, 0, -1])
    cols = np.flatnonzero(p.mask.any(0)) * 2 + 1  # work grid -> image columns
    assert cols.min() < 40 and 200 < cols.max() < 250  # the left half, not the right
    assert (lab[p.mask] == 5).all() and (lab[~p.mask] == -1).all()


def _rot(axis, deg):
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    t = np.deg2rad(deg)
    return np.eye(3) + np.sin(t) * K + (1 - np.cos(t)) * K @ K


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
            _frame_result(F, trusted), camera, (h, w), LinePlaneConf(), 0.005
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


def test_line_plane_conf_is_validated():
    with pytest.raises(ValueError, match="regions"):
        LinePlaneConf(regions="half")


def test_whole_image_warps_end_to_end(views):
    """The pipeline on whole-image warps (regions 'whole') of a street view: the warps
    overlap, each has features over its own region (also where another warp covers the
    cells), none outside its half-space."""
    conf = ExtractConf()
    conf.sift.max_num_features = 1024
    conf.rectify.min_rectify_angle_deg = 0.0
    r, camera = views[4]
    res = extract_depth_free(r.image, camera, conf, LinePlaneConf(regions="whole"))
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
    in_other = 0
    for i, rect in enumerate(res.rectifications):
        mine = feats.patch == rect.patch_index
        if mine.sum() == 0:
            continue  # cut by the budget (smallest scales first) or crowding
        inside = keypoints_in_mask(feats.keypoints[mine], masks[i], (W, H))
        assert inside.mean() > 0.95  # map back into its own (cropped) region
        others = masks[np.arange(len(masks)) != i].any(0)
        in_other += keypoints_in_mask(feats.keypoints[mine], others, (W, H)).sum()
    assert in_other > 20  # overlapping regions get features from several warps
