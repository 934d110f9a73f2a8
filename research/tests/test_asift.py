"""rectified_colmap_research.evaluation.asift: OpenCV's ASIFT in this package's format."""

import cv2
import numpy as np
import pytest
from rectified_colmap_research.evaluation.asift import (
    asift_features,
    features_from_opencv,
    opencv_sift_to_rootsift_bytes,
)

from rectified_colmap.conventions import to_opencv_points
from rectified_colmap.eval.matching import match_ratio
from rectified_colmap.io.hloc_h5 import rootsift_unit
from rectified_colmap_research.synth.planar import textured_image


def test_descriptors_become_colmap_rootsift_bytes():
    rng = np.random.default_rng(0)
    d = rng.uniform(0, 200, (50, 128)).astype(np.float32)
    d[0] = 0.0
    b = opencv_sift_to_rootsift_bytes(d)
    assert b.dtype == np.uint8 and b.shape == d.shape
    assert not b[0].any()  # zero stays zero
    # the unit vector is the root of the L1-normalised descriptor, up to the bytes' rounding
    root = np.sqrt(d[1:] / d[1:].sum(1, keepdims=True))
    np.testing.assert_allclose(rootsift_unit(b[1:]), root, atol=2.5 / 512)
    np.testing.assert_allclose(np.linalg.norm(b[1:].astype(float), axis=1), 512, atol=3)
    np.testing.assert_array_equal(opencv_sift_to_rootsift_bytes(3.0 * d), b)  # scale-free


def test_keypoints_take_colmap_convention_and_similarity_frames():
    kps = [cv2.KeyPoint(10.0, 20.0, 8.0, 90.0), cv2.KeyPoint(0.0, 0.0, 2.0, 0.0)]
    f = features_from_opencv(kps, np.ones((2, 128), np.float32))
    np.testing.assert_allclose(to_opencv_points(f.keypoints), [[10, 20], [0, 0]])
    np.testing.assert_allclose(f.scales, [4.0, 1.0])
    np.testing.assert_allclose(f.orientations, [np.pi / 2, 0.0], atol=1e-12)
    assert (f.patch == -1).all()
    assert len(features_from_opencv([], None)) == 0


def test_asift_matches_a_strong_tilt_where_its_keypoints_say():
    """A texture and the same texture compressed 4x along x (a tilt of 4: 76 degrees): ASIFT
    matches them, and its matches agree with the true map in COLMAP's convention."""
    img0 = textured_image(240, 240, 0)
    A = np.array([[0.25, 0.0, 0.0], [0.0, 1.0, 0.0]])  # OpenCV pixel centres
    img1 = cv2.warpAffine(img0, A, (60, 240), flags=cv2.INTER_AREA)
    f0, f1 = asift_features(img0, 2000), asift_features(img1, 2000)
    m = match_ratio(rootsift_unit(f0.descriptors), rootsift_unit(f1.descriptors), 0.8, True)
    x0 = to_opencv_points(f0.keypoints[m[:, 0]])
    x1 = to_opencv_points(f1.keypoints[m[:, 1]])
    err = np.linalg.norm(x0 @ A[:, :2].T + A[:, 2] - x1, axis=1)
    assert (err < 2).sum() >= 100 and np.mean(err < 2) > 0.8  # plain SIFT: 0 correct
    with pytest.raises(ValueError, match="uint8"):
        asift_features(img0.astype(np.float32))
