"""research: the oracle's inputs (rectified_colmap_research.evaluation.oracle)."""

import cv2
import numpy as np
import pytest

from rectified_colmap_research.evaluation.oracle import plane_normals_from_homography


def rot(axis, deg):
    return cv2.Rodrigues(np.asarray(axis, float) * np.deg2rad(deg) / np.linalg.norm(axis))[0]


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_plane_normals_from_homography_recover_the_truth(seed):
    rng = np.random.default_rng(seed)
    K0 = np.array([[700.0, 0, 320], [0, 700, 240], [0, 0, 1]])
    K1 = np.array([[600.0, 0, 300], [0, 600, 250], [0, 0, 1]])
    # Plane facing camera 0 with a random tilt; camera 1 rotated 40-70 degrees about it.
    n0 = rot(rng.standard_normal(3), rng.uniform(10, 40)) @ np.array([0, 0, -1.0])
    d = 5.0  # plane: n0 . X = -d (n0 faces the camera)
    P = np.array([0, 0, 5.0])
    P = P * d / -(n0 @ P)  # a point of the plane on the optical axis
    R = rot([0, 1, 0.2], rng.uniform(40, 70) * rng.choice([-1, 1]))
    C1 = P - R.T @ np.array([0, 0, 1.0]) * 6.0  # camera 1 looks at P from 6 m
    t = -R @ C1
    # X1 = R X0 + t; plane n0 . X0 = -d  =>  X1 = (R - t n0^T / d) X0.
    H = K1 @ (R - np.outer(t, n0) / d) @ np.linalg.inv(K0)
    x0 = rng.uniform([100, 100], [540, 380], (50, 2))
    e0, e1 = plane_normals_from_homography(H, K0, K1, x0)
    np.testing.assert_allclose(e0, n0, atol=1e-6)
    np.testing.assert_allclose(e1, R @ n0, atol=1e-6)
