import numpy as np
import pycolmap
import pytest

from rectified_colmap.config import SiftConf
from rectified_colmap.features import (Features, detect_sift, keypoints_in_mask,
                                       similarity_frames, split_budget)
from tests.conftest import textured_image


def test_similarity_frames_match_pycolmap_affine_shape():
    img = textured_image(160, 200, 1)
    opts = pycolmap.FeatureExtractionOptions()
    opts.num_threads = 1
    kps, _ = pycolmap.FeatureExtractor.create(opts, pycolmap.Device.cpu) \
        .extract_from_uint8_array(img)
    m = np.asarray(pycolmap.keypoints_to_matrix(kps))
    ours = similarity_frames(m[:, 2].astype(float), m[:, 3].astype(float))
    theirs = np.array([[[k.a11, k.a12], [k.a21, k.a22]] for k in kps])
    np.testing.assert_allclose(ours, theirs, atol=1e-4)


def test_detect_sift_is_plain_colmap_sift():
    img = textured_image(160, 200, 2)
    f = detect_sift(img, SiftConf())
    opts = pycolmap.FeatureExtractionOptions()
    kps, desc = pycolmap.FeatureExtractor.create(opts, pycolmap.Device.cpu) \
        .extract_from_uint8_array(img)
    ref = np.asarray(pycolmap.keypoints_to_matrix(kps))
    assert len(f) == len(ref) > 50
    np.testing.assert_allclose(f.keypoints, ref[:, :2], atol=1e-4)
    np.testing.assert_array_equal(f.descriptors, desc.data)
    np.testing.assert_allclose(f.scales, ref[:, 2], rtol=1e-5)
    assert (f.patch == -1).all()
    assert f.colmap_keypoints().shape == (len(f), 6)
    assert f.colmap_keypoints().dtype == np.float32


def test_detect_sift_downscales_large_images_like_colmap():
    img = textured_image(200, 300, 3)
    big = np.kron(img, np.ones((2, 2), np.uint8))  # exact 2x upsampling
    conf = SiftConf(max_image_size=300)
    small = detect_sift(img, SiftConf())
    f = detect_sift(big, conf)
    # big is resized back to img by area averaging, so keypoints are img's, scaled by 2
    assert len(f) == len(small)
    np.testing.assert_allclose(f.keypoints, 2 * small.keypoints, atol=1e-3)
    np.testing.assert_allclose(f.scales, 2 * small.scales, rtol=1e-4)


def test_detect_sift_rejects_colour():
    with pytest.raises(ValueError, match="uint8"):
        detect_sift(np.zeros((10, 10, 3), np.uint8))


def test_split_budget_proportional_and_bounded():
    b = split_budget(8192, np.array([1000.0, 0.0, 3000.0, 10.0]))
    assert b.sum() <= 8192 and b.sum() > 8150
    assert b[1] == 0
    assert b[3] >= 60  # a small region still gets a minimum
    assert abs(b[2] / b[0] - 3) < 0.2


def test_keypoints_in_mask_uses_colmap_convention():
    mask = np.zeros((2, 2), bool)
    mask[0, 1] = True  # top-right cell of a 2x2 grid covering a 10x10 image
    xy = np.array([[5.01, 0.5], [4.99, 0.5], [9.99, 4.99], [9.99, 5.01], [-1, 1]])
    np.testing.assert_array_equal(keypoints_in_mask(xy, mask, (10, 10)),
                                  [True, False, True, False, False])


def test_features_container():
    f = Features(np.array([[1.0, 2.0]]), similarity_frames(np.array([2.0]), np.array([0.3])),
                 np.zeros((1, 128), np.uint8), np.array([3], np.int32))
    np.testing.assert_allclose(f.scales, [2.0])
    np.testing.assert_allclose(f.orientations, [0.3])
    g = Features.concatenate([f, Features.empty(), f])
    assert len(g) == 2 and g.patch.tolist() == [3, 3]
