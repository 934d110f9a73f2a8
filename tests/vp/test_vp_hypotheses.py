"""Plane hypotheses from pairs of vanishing points (vp.hypotheses): exact geometry on
projected line sets (non-orthogonal families, wrong intrinsics), the pairing and merging
rules, the whole-image patches, and the pipeline option."""

import numpy as np
import pytest

from rectified_colmap.camera import calibration_matrix, grid_rays, make_camera
from rectified_colmap.depth import DepthMap
from rectified_colmap.config import ExtractConf, VpConf
from rectified_colmap.geometry import axis_angle_rotation, line_angle_deg
from rectified_colmap.pipeline import extract_image
from rectified_colmap.planes import HYPOTHESIS_AXIS, REST_AXIS, Patch
from rectified_colmap_research.synth.lines import project_segments
from rectified_colmap.vp.hypotheses import (
    VanishingPoints,
    free_vanishing_points,
    hypothesis_patches,
    plane_hypotheses,
)
from rectified_colmap.vp.segments import segments_on_sphere
from tests.conftest import look_at, plane_view, textured_image


def facade_texture(size=512, period=32, seed=5):
    """Blob texture crossed by a grid of dark lines (window rows and columns)."""
    img = textured_image(size, size, seed) // 2 + 100
    for k in range(period // 2, size, period):
        img[k - 1 : k + 2, :] = 20
        img[:, k - 1 : k + 2] = 20
    return img


def cam(f=400.0, w=480, h=320):
    return make_camera("PINHOLE", [f, f, w / 2, h / 2], w, h)


def plane_segments(rng, dirs, n_per=60, extent=4.0, length=(0.6, 1.6)):
    """3D segments (N, 2, 3) on the world plane z = 0 along each direction of ``dirs``."""
    out = []
    for d in dirs:
        c = np.concatenate([rng.uniform(-extent, extent, (n_per, 2)), np.zeros((n_per, 1))], 1)
        half = rng.uniform(*length, (n_per, 1)) / 2
        out.append(np.stack([c - half * d, c + half * d], 1))
    return np.concatenate(out)


def sorted_segments(camera, xy):
    order = np.argsort(-np.linalg.norm(xy[:, 1] - xy[:, 0], axis=-1), kind="stable")
    return segments_on_sphere(camera, xy[order])


DIRS = np.array([[1.0, 0.0, 0.0], [np.cos(np.deg2rad(50)), np.sin(np.deg2rad(50)), 0.0]])


def oblique_view(seed):
    rng = np.random.default_rng(seed)
    R, t = look_at([7.0, -5.0, 3.0], [0.0, 0.0, 0.0])
    return rng, R, t


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_two_non_orthogonal_families_give_the_plane(seed):
    """Families 50 degrees apart (no Manhattan frame): both VPs and the plane's normal are
    recovered from exactly projected segments."""
    rng, R, t = oblique_view(seed)
    camera = cam()
    seg = sorted_segments(camera, project_segments(camera, R, t, plane_segments(rng, DIRS)))
    vps = free_vanishing_points(seg, VpConf())
    assert len(vps.directions) == 2  # nothing else in the image
    truth = DIRS @ R.T  # camera frame
    err = line_angle_deg(vps.directions[:, None], truth[None])  # (found, true)
    assert err.min(1).max() < 0.01 and set(err.argmin(1)) == {0, 1}
    assert vps.support.sum() == pytest.approx(1.0)
    normals, scores = plane_hypotheses(vps, VpConf())
    n_true = R @ np.array([0.0, 0.0, 1.0])
    assert len(normals) == 1 and scores[0] == pytest.approx(vps.support.min())
    assert line_angle_deg(normals[0], n_true) < 0.01
    assert normals[0][2] < 0  # faces the camera


def test_vanishing_line_does_not_depend_on_the_focal_guess():
    """With a wrong focal length the normal is wrong, but its vanishing line K^-T n is the
    true one: the warp built from it with the same K still sends the line to infinity."""
    rng, R, t = oblique_view(3)
    true_cam, guess = cam(400.0), cam(700.0)
    xy = project_segments(true_cam, R, t, plane_segments(rng, DIRS))
    normals, _ = plane_hypotheses(free_vanishing_points(sorted_segments(guess, xy)))
    n_true = R @ np.array([0.0, 0.0, 1.0])
    assert line_angle_deg(normals[0], n_true) > 5  # the normal itself is off...

    def vanishing_line(camera, n):
        line = np.linalg.inv(calibration_matrix(camera)).T @ n
        return line / np.linalg.norm(line)

    # ...its image line is exact
    assert (
        line_angle_deg(vanishing_line(guess, normals[0]), vanishing_line(true_cam, n_true)) < 1e-3
    )


def test_pairing_and_merging_rules():
    z = np.array([0.0, 0.0, 1.0])
    a, b = np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0])
    close = np.array([np.cos(np.deg2rad(10)), np.sin(np.deg2rad(10)), 0.0])  # 10 deg from a
    vps = VanishingPoints(
        np.stack([a, close, b, z]), np.array([0.4, 0.3, 0.2, 0.1]), np.ones(4, int)
    )
    normals, scores = plane_hypotheses(vps, VpConf())
    # (a, close): one family split in two (10 < 20 deg), no plane. (a, b) and (close, b) give
    # normals 0 deg apart: merged into the better-scored one (0.2 both: the first kept).
    # (a, z), (close, z) -> normals +-y and one 10 deg from it: merged. (b, z) -> x.
    assert scores.tolist() == [0.2, 0.1, 0.1]
    assert line_angle_deg(normals[0], z) < 1e-9 and normals[0][2] == -1.0
    assert line_angle_deg(normals[1], b) < 1e-9 and line_angle_deg(normals[2], a) < 1e-9
    wide = VpConf(hypothesis_merge_angle_deg=5.0)  # (close, z) now stays apart from (a, z)
    assert len(plane_hypotheses(vps, wide)[0]) == 4
    assert len(plane_hypotheses(VanishingPoints(a[None], np.ones(1), np.ones(1, int)))[0]) == 0


def test_hypothesis_patches_cover_the_front_side_and_skip_existing():
    camera = cam()
    n1 = np.array([0.0, 0.0, -1.0])  # frontal: every cell sees it
    n2 = np.array([np.sin(np.deg2rad(70)), 0.0, -np.cos(np.deg2rad(70))])
    n3 = np.array([0.0, np.sin(np.deg2rad(60)), -np.cos(np.deg2rad(60))])
    h, w = 40, 60
    rays = grid_rays(camera, w, h)
    conf = VpConf(line_hypotheses=2)
    existing = [Patch(np.ones((h, w), bool), 0, n1, 1.0)]
    patches = hypothesis_patches(np.stack([n1, n2, n3]), camera, (h, w), existing, conf)
    assert [p.axis for p in patches] == [HYPOTHESIS_AXIS] * 2  # n1: frontal, and it exists
    assert np.array_equal(patches[0].normal, n2) and np.array_equal(patches[1].normal, n3)
    for p in patches:
        assert np.array_equal(p.mask, rays @ p.normal < 0)
        assert p.area_frac == pytest.approx(p.mask.mean())
    assert hypothesis_patches(np.stack([n2]), camera, (h, w), [], VpConf(line_hypotheses=0)) == []


def test_a_hypothesis_of_a_plane_held_in_part_covers_the_rest():
    """A hypothesis within the merge angle of the image's patches of its orientation covers
    the front-facing cells they do not (REST_AXIS), not counted against line_hypotheses;
    a second hypothesis of that plane adds nothing; one over no cell left gives none."""
    camera = cam()
    h, w = 40, 60
    rays = grid_rays(camera, w, h)
    n2 = np.array([np.sin(np.deg2rad(70)), 0.0, -np.cos(np.deg2rad(70))])
    n3 = np.array([0.0, np.sin(np.deg2rad(60)), -np.cos(np.deg2rad(60))])
    tilted = axis_angle_rotation(np.array([0.0, 1.0, 0.0]), np.deg2rad(1.0)) @ n2  # 1 degree
    near = np.zeros((h, w), bool)
    near[:, : w // 3] = True  # the depth's patch: the plane's near third
    existing = [Patch(near, 1, -tilted, near.mean())]  # the other sign: axes are sign-free
    conf = VpConf(line_hypotheses=1)
    normals = np.stack([n2, tilted, n3])
    patches = hypothesis_patches(normals, camera, (h, w), existing, conf)
    assert [p.axis for p in patches] == [REST_AXIS, HYPOTHESIS_AXIS]
    rest, other = patches
    np.testing.assert_array_equal(rest.normal, n2)
    np.testing.assert_array_equal(rest.mask, (rays @ n2 < 0) & ~near)
    assert 0 < rest.mask.sum() < (rays @ n2 < 0).sum()
    np.testing.assert_array_equal(other.normal, n3)  # one hypothesis, as line_hypotheses says
    whole = [Patch(np.ones((h, w), bool), 1, tilted, 1.0)]
    patches = hypothesis_patches(normals, camera, (h, w), whole, conf)
    assert [p.axis for p in patches] == [HYPOTHESIS_AXIS]  # nothing of n2's plane is left


def test_pipeline_adds_the_plane_the_depth_missed():
    """A facade with lines seen at ~65 degrees, given a wrong (frontal) normal map as a bad
    network would: with line_hypotheses the rectification uses the lines' plane; without,
    the image gets no view of a plane (the frontal patch is not worth rectifying), only
    blind ones (planes.BLIND_AXIS: plain SIFT leaves budget unused here)."""
    K = np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])
    R, t = look_at([4.0, -2.0, 2.0], [0.0, 0.0, 0.0])
    img, depth = plane_view(facade_texture(), 8.0 / 512, K, R, t, (640, 480))
    camera = make_camera("PINHOLE", [500.0, 500.0, 320.0, 240.0], 640, 480)
    base = ExtractConf.from_dict({"vp": {"line_hypotheses": 0}})
    frontal = DepthMap(np.ones((240, 320), np.float32), "depth")  # a plane at z = 1: normal -z
    plain = extract_image(img, camera, frontal, base)
    assert {plain.planes.patches[r.patch_index].axis for r in plain.rectifications} == {-3}
    conf = ExtractConf.from_dict({"vp": {"line_hypotheses": 2}})
    res = extract_image(img, camera, frontal, conf)
    n_true = R @ np.array([0.0, 0.0, 1.0])
    errs = [line_angle_deg(r.normal, n_true) for r in res.rectifications]
    assert errs and min(errs) < 2.0
    assert all(res.planes.patches[r.patch_index].axis == -1 for r in res.rectifications)
    rect = res.features.subset(res.features.patch >= 0)
    assert len(rect) > 100
    # mapped back onto the facade: rectified keypoints land on textured pixels (a few sit on
    # the texture's outer edge against the black background, as plain SIFT's do)
    x, y = np.floor(rect.keypoints).astype(int).T
    assert np.isfinite(depth[np.clip(y, 0, 479), np.clip(x, 0, 639)]).mean() > 0.95
