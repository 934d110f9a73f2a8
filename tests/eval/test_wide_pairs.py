"""Wide-baseline pairs from a reconstruction (rectified_colmap.eval.wide_pairs)."""

import numpy as np
import pytest


from rectified_colmap.eval.wide_pairs import (
    incidence,
    reconstruction_arrays,
    select_pairs,
    viewing_angles_deg,
    wide_pairs,
)
from tests.scenes import ring_reconstruction


def test_viewing_angles_exact():
    c0, c1 = np.array([-1.0, 0, 0]), np.array([1.0, 0, 0])
    z = np.array([1.0, np.sqrt(3.0), 1 / np.sqrt(3.0), 1e9])
    pts = np.c_[np.zeros(4), np.zeros(4), z]
    # the rays to (0, 0, z) meet at 2 atan(1 / z): 90, 60, 120 degrees, 0 at infinity
    np.testing.assert_allclose(viewing_angles_deg(c0, c1, pts), [90, 60, 120, 0], atol=1e-6)
    assert viewing_angles_deg(c0, c0, pts[:1])[0] == pytest.approx(0.0, abs=1e-6)
    assert viewing_angles_deg(c0, -c0, [[0.0, 0, 0]])[0] == pytest.approx(180.0)
    assert np.isnan(viewing_angles_deg(c0, c1, [c0])[0])  # a point at a camera centre


def test_incidence():
    seen = incidence([np.array([0, 1]), np.array([2]), np.array([0, 0, 2]), np.array([], int)], 3)
    np.testing.assert_array_equal(seen, [[1, 0, 1, 0], [1, 0, 0, 0], [0, 1, 1, 0]])
    assert incidence([], 2).shape == (2, 0)


def test_pairs_of_a_ring_of_cameras():
    rng = np.random.default_rng(0)
    points = rng.uniform(-0.05, 0.05, (60, 3))
    tracks = [[0, 1, 2]] * 40 + [[0, 1]] * 20  # (0, 1) share 60 points, the others 40
    rec = ring_reconstruction([0.0, 40.0, 90.0], tracks, points)
    names, centers, rotations, pts, seen = reconstruction_arrays(rec)
    assert names == ["im0.jpg", "im1.jpg", "im2.jpg"]
    np.testing.assert_allclose(
        centers[1], [10 * np.sin(np.radians(40)), 0, -10 * np.cos(np.radians(40))], atol=1e-9
    )
    assert seen.sum(1).tolist() == [60, 60, 40]

    pairs = wide_pairs(rec, min_covisible=30)
    got = {(p.name0, p.name1): p for p in pairs}
    assert set(got) == {("im0.jpg", "im1.jpg"), ("im0.jpg", "im2.jpg"), ("im1.jpg", "im2.jpg")}
    for (a, b), deg in {
        ("im0.jpg", "im1.jpg"): 40,
        ("im0.jpg", "im2.jpg"): 90,
        ("im1.jpg", "im2.jpg"): 50,
    }.items():
        p = got[(a, b)]
        assert p.rotation_deg == pytest.approx(deg, abs=1e-6)  # cameras turn about y
        assert p.viewpoint_deg == pytest.approx(deg, abs=0.7)  # points within 5 cm of the centre
    assert got[("im0.jpg", "im1.jpg")].num_covisible == 60
    assert got[("im1.jpg", "im2.jpg")].num_covisible == 40
    assert [p.viewpoint_deg for p in pairs] == sorted(p.viewpoint_deg for p in pairs)

    # thresholds: common points, then the viewpoint range
    assert [(p.name0, p.name1) for p in wide_pairs(rec, min_covisible=50)] == [
        ("im0.jpg", "im1.jpg")
    ]
    mid = wide_pairs(rec, min_covisible=1, min_viewpoint_deg=45, max_viewpoint_deg=60)
    assert [(p.name0, p.name1) for p in mid] == [("im1.jpg", "im2.jpg")]


def test_select_pairs_orders_names_and_ignores_unseen_images():
    centers = np.array([[0.0, 0, 0], [1.0, 0, 0], [5.0, 0, 0]])
    rotations = np.repeat(np.eye(3)[None], 3, 0)
    points = np.array([[0.5, 0, 2.0]] * 3)
    seen = np.array([[1, 1, 1], [1, 1, 1], [0, 0, 0]], bool)
    pairs = select_pairs(["b.jpg", "a.jpg", "c.jpg"], centers, rotations, points, seen, 3)
    assert len(pairs) == 1
    assert (pairs[0].name0, pairs[0].name1) == ("a.jpg", "b.jpg")
    assert pairs[0].viewpoint_deg == pytest.approx(2 * np.degrees(np.arctan(0.25)))
    assert pairs[0].rotation_deg == pytest.approx(0.0, abs=1e-6)
