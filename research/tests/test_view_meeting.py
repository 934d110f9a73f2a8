"""rectified_colmap_research.evaluation.view_meeting: where two view sets meet, exactly."""

import numpy as np
import pytest
from rectified_colmap_research.evaluation.extreme_pairs import ViewParams, build_view
from rectified_colmap_research.evaluation.plane_pairs import transition_tilt
from rectified_colmap_research.evaluation.view_meeting import (
    asift_view_set,
    best_transition_tilt,
    best_view_pairs,
    met_fraction,
    overlap_points,
    view_set,
)

from rectified_colmap import camera as cam_utils
from rectified_colmap.config import RectifyConf
from rectified_colmap.eval.homography import HomographyPair, positive_homography
from rectified_colmap.planes import Patch
from rectified_colmap.rectify import plan_rectification

ANCHOR = np.array([450.0, 300.0])
SIZE = (640, 480)


def exact_view(tilt, direction_deg, rotation_deg=0.0, scale=1.0, focal=700.0):
    p = ViewParams(tilt, direction_deg, rotation_deg, scale, focal, SIZE, (320.0, 240.0))
    return build_view(ANCHOR, p)


def pair_of(v0, v1):
    H = positive_homography(v1.G @ np.linalg.inv(v0.G), SIZE)
    return HomographyPair("p", "a", "b", H, SIZE, SIZE)


def rectified_views(v, normal_error_deg=0.0):
    """The image's view set with one rectification of its whole image from the view's true
    plane normal (tilted by ``normal_error_deg`` about the camera's x axis)."""
    f, (W, H) = v.params.focal, SIZE
    camera = cam_utils.make_camera("PINHOLE", [f, f, W / 2, H / 2], W, H)
    a = np.radians(normal_error_deg)
    Rx = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
    patch = Patch(np.ones((48, 64), bool), 0, Rx @ v.normal, 1.0)
    rect = plan_rectification(camera, patch, 0, RectifyConf(max_viewing_angle_deg=89.0))
    return view_set(camera, [rect])


def test_plain_views_meet_with_the_homography_own_transition_tilt():
    v0, v1 = exact_view(1.0, 0.0), exact_view(4.0, 30.0, rotation_deg=90.0)
    pair = pair_of(v0, v1)
    xy = overlap_points(pair)
    assert len(xy) > 100
    plain = [(np.eye(3), None)]
    tau = best_transition_tilt(pair, plain, plain, xy)
    np.testing.assert_allclose(tau, transition_tilt(pair.H, xy), rtol=1e-9)
    assert np.median(tau) > 3.0 and met_fraction(pair, plain, plain) < 0.05


def test_exact_rectifications_of_both_oblique_views_meet_everywhere():
    v0, v1 = exact_view(5.0, 0.0, rotation_deg=90.0), exact_view(4.0, 110.0, scale=2.5)
    pair = pair_of(v0, v1)
    xy = overlap_points(pair)
    plain = [(np.eye(3), None)]
    assert (best_transition_tilt(pair, plain, plain, xy) > 2.0).all()
    tau = best_transition_tilt(pair, rectified_views(v0), rectified_views(v1), xy)
    # where both rectifications hold a point, the map between them is a similarity
    assert np.mean(np.abs(tau - 1.0) < 1e-6) > 0.9
    assert met_fraction(pair, rectified_views(v0), rectified_views(v1)) > 0.9


def test_an_orientation_error_leaves_a_residual_tilt():
    v0, v1 = exact_view(4.0, 90.0), exact_view(1.0, 0.0)
    pair = pair_of(v0, v1)
    xy = overlap_points(pair)
    exact = best_transition_tilt(pair, rectified_views(v0), [(np.eye(3), None)], xy)
    off = best_transition_tilt(pair, rectified_views(v0, 8.0), [(np.eye(3), None)], xy)
    held = np.isfinite(exact) & np.isfinite(off)
    assert np.median(exact[held]) < 1.3  # the other view is frontal: tilt 1 itself
    assert np.median(off[held]) > np.median(exact[held]) + 0.2


def test_masks_limit_what_a_view_holds():
    v0, v1 = exact_view(4.0, 0.0), exact_view(1.0, 0.0)
    pair = pair_of(v0, v1)
    views = rectified_views(v0)
    H, mask = views[1]
    empty = [(np.eye(3), None), (H, np.zeros_like(mask))]
    plain1 = [(np.eye(3), None)]
    assert met_fraction(pair, views, plain1) > 0.5
    assert met_fraction(pair, empty, plain1) < 0.05


def test_asift_view_set_follows_opencv_sampling():
    views = asift_view_set()
    # tilt sqrt(2): longitudes every 72 / sqrt(2) = 50.9 degrees in [0, 180): 4 views
    first = [H for H, _ in views[1:] if np.isclose(np.linalg.det(H[:2, :2]), 2**-0.5)]
    assert len(first) == 4
    assert all(m is None for _, m in views)
    v0, v1 = exact_view(3.0, 20.0), exact_view(1.0, 0.0)
    pair = pair_of(v0, v1)
    assert met_fraction(pair, views, [(np.eye(3), None)]) > 0.9


def test_best_view_pairs_name_the_views_and_the_scale_at_which_they_meet():
    """An affine pair with tilt 3 (a 640 x 480 image 0, image 1 three times as wide): the
    images alone meet nowhere; a view of image 1 that undoes the tilt at a quarter of the
    scale meets everywhere at a scale change of 4, and one that undoes it at half the
    scale is the one nearest 1; a quarter turn, at the same scale, leaves the tilt."""
    stretch = np.diag([3.0, 1.0, 1.0])
    pair = HomographyPair("p", "a", "b", stretch, SIZE, (1920, 480))
    xy = overlap_points(pair)
    plain = [(np.eye(3), None)]
    tau, which, scale = best_view_pairs(pair, plain, plain, xy)
    assert tau == pytest.approx(np.full(len(xy), 3.0)) and np.isinf(scale).all()
    assert (which == 0).all()
    quarter = (np.diag([1 / 12.0, 1 / 4.0, 1.0]), None)
    half = (np.diag([1 / 6.0, 1 / 2.0, 1.0]), None)
    turn = (np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]]), None)
    tau, which, scale = best_view_pairs(pair, plain, [turn, quarter], xy)
    assert tau == pytest.approx(np.ones(len(xy))) and scale == pytest.approx(np.full(len(xy), 4.0))
    assert (which[:, 1] == 1).all()
    tau, which, scale = best_view_pairs(pair, plain, [turn, quarter, half], xy)
    assert scale == pytest.approx(np.full(len(xy), 2.0))
    # a view whose mask holds nothing: no pair of views, no scale
    nothing = (np.eye(3), np.zeros((4, 4), bool))
    tau, which, scale = best_view_pairs(pair, [nothing], [nothing], xy)
    assert np.isinf(tau).all() and (which == -1).all() and np.isinf(scale).all()
