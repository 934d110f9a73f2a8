import numpy as np
import pycolmap
import pytest

from rectified_colmap.config import SiftConf
from rectified_colmap.budget import split_budget
from rectified_colmap.features import Features, keypoints_in_mask, similarity_frames
from rectified_colmap.sift import (
    coarse_first_pays,
    count_detections,
    halved,
    opencv_sift,
    detect_sift,
    patch_first_octave,
)
from tests.conftest import textured_image


def test_similarity_frames_match_pycolmap_affine_shape():
    img = textured_image(160, 200, 1)
    opts = pycolmap.FeatureExtractionOptions()
    opts.num_threads = 1
    kps, _ = pycolmap.FeatureExtractor.create(opts, pycolmap.Device.cpu).extract_from_uint8_array(
        img
    )
    m = np.asarray(pycolmap.keypoints_to_matrix(kps))
    ours = similarity_frames(m[:, 2].astype(float), m[:, 3].astype(float))
    theirs = np.array([[[k.a11, k.a12], [k.a21, k.a22]] for k in kps])
    np.testing.assert_allclose(ours, theirs, atol=1e-4)


def test_detect_sift_is_plain_colmap_sift():
    img = textured_image(160, 200, 2)
    f = detect_sift(img, SiftConf())
    opts = pycolmap.FeatureExtractionOptions()
    kps, desc = pycolmap.FeatureExtractor.create(
        opts, pycolmap.Device.cpu
    ).extract_from_uint8_array(img)
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
    np.testing.assert_array_equal(
        keypoints_in_mask(xy, mask, (10, 10)), [True, False, True, False, False]
    )


def test_features_container():
    f = Features(
        np.array([[1.0, 2.0]]),
        similarity_frames(np.array([2.0]), np.array([0.3])),
        np.zeros((1, 128), np.uint8),
        np.array([3], np.int32),
    )
    np.testing.assert_allclose(f.scales, [2.0])
    np.testing.assert_allclose(f.orientations, [0.3])
    g = Features.concatenate([f, Features.empty(), f])
    assert len(g) == 2 and g.patch.tolist() == [3, 3]


def _sift_matrix(img, n, first_octave=-1, num_octaves=4):
    opts = pycolmap.FeatureExtractionOptions()
    opts.num_threads = 1
    opts.sift.max_num_features = n
    opts.sift.first_octave = first_octave
    opts.sift.num_octaves = num_octaves
    kps, desc = pycolmap.FeatureExtractor.create(
        opts, pycolmap.Device.cpu
    ).extract_from_uint8_array(img)
    return np.asarray(pycolmap.keypoints_to_matrix(kps), np.float64), np.asarray(desc.data)


def test_colmap_budget_keeps_coarsest_levels_whole():
    """The rule coarse_first relies on: a budget-n output is the tail (coarsest DoG levels)
    of the unbounded output, and holds more than n points unless it is all of it."""
    img = textured_image(300, 400, 5)
    full, _ = _sift_matrix(img, 10**6)
    assert count_detections(full) < len(full)  # some points have two orientations
    for n in (50, 200, 800):
        part, _ = _sift_matrix(img, n)
        np.testing.assert_array_equal(part, full[len(full) - len(part) :])
        assert count_detections(part) > n
        assert len(part) < len(full)


def test_coarse_first_skips_the_first_octave_when_the_budget_allows():
    img = textured_image(300, 400, 5)
    coarse, coarse_desc = _sift_matrix(img, 10**6, 0, 3)
    found = count_detections(coarse)
    assert 100 < found < 2000
    # budget filled by the coarser octaves: exactly one call on them
    n = found // 3
    f = detect_sift(img, SiftConf(), n, coarse_first=True)
    ref, ref_desc = _sift_matrix(img, n, 0, 3)
    np.testing.assert_allclose(f.keypoints, ref[:, :2])
    np.testing.assert_array_equal(f.descriptors, ref_desc)
    # budget beyond them: the first octave alone with what is left, finest first
    n = found + 500
    f = detect_sift(img, SiftConf(), n, coarse_first=True)
    fine, fine_desc = _sift_matrix(img, n - found, -1, 1)
    np.testing.assert_allclose(f.keypoints, np.concatenate([fine, coarse])[:, :2])
    np.testing.assert_array_equal(f.descriptors, np.concatenate([fine_desc, coarse_desc]))


def _agreement(a, b):
    """Fraction of keypoints of Features a with one of b within 0.5 px and 5% in scale."""
    d = np.linalg.norm(a.keypoints[:, None] - b.keypoints[None], axis=-1)  # (Na, Nb)
    near = (d < 0.5) & (np.abs(np.log(a.scales[:, None] / b.scales[None])) < 0.05)
    return float(near.any(1).mean())


@pytest.mark.parametrize("n", [200, 1500])
def test_coarse_first_finds_about_the_points_of_one_call(n):
    img = textured_image(300, 400, 6)
    ref = detect_sift(img, SiftConf(), n)
    f = detect_sift(img, SiftConf(), n, coarse_first=True)
    assert abs(len(f) - len(ref)) < 0.15 * len(ref)
    assert _agreement(f, ref) > 0.8 and _agreement(ref, f) > 0.8


def test_coarse_first_pays_from_pixels_per_feature_after_downscaling():
    conf = SiftConf(coarse_first_pixels_per_feature=500.0, max_image_size=3200)
    assert coarse_first_pays((2048, 3072), 8192, conf)  # 6.3 MP >= 4.1 MP
    assert not coarse_first_pays((1024, 1536), 8192, conf)  # 1.6 MP
    assert coarse_first_pays((1024, 1536), 1024, conf)
    assert coarse_first_pays((1024, 1000), 1024, conf) == (1024 * 1000 >= 500 * 1024)
    # 12000 x 8000 is seen by SIFT at 3200 x 2133 (6.8 MP): pays up to 13653 features
    assert coarse_first_pays((8000, 12000), 13600, conf)
    assert not coarse_first_pays((8000, 12000), 13700, conf)
    conf.coarse_first = False
    assert not coarse_first_pays((2048, 3072), 8192, conf)


def test_patch_first_octave_from_pixels_per_feature_after_downscaling():
    conf = SiftConf(
        patch_octave0_pixels_per_feature=150.0,
        coarse_first_pixels_per_feature=500.0,
        max_image_size=3200,
    )
    assert patch_first_octave((1024, 1536), 8192, conf) == 0  # 192 px / feature
    assert patch_first_octave((360, 480), 8192, conf) == -1  # 21 px / feature
    assert patch_first_octave((780, 1063), 8192, conf) == -1  # 101 px / feature
    assert patch_first_octave((360, 480), 1024, conf) == 0  # 169 px / feature
    # from 500 px / feature coarse-first decides in each patch (first_octave stays -1)
    assert patch_first_octave((1024, 1536), 3146, conf) == 0  # 499.99 px / feature
    assert patch_first_octave((1024, 1536), 3145, conf) == -1  # 500.1 px / feature
    assert patch_first_octave((1024, 1536), 1024, conf) == -1
    # 12000 x 8000 is seen by SIFT at 3200 x 2133: 150-500 px / feature at 13653-45502
    assert patch_first_octave((8000, 12000), 45500, conf) == 0
    assert patch_first_octave((8000, 12000), 45600, conf) == -1
    assert patch_first_octave((8000, 12000), 13600, conf) == -1
    assert patch_first_octave((8000, 12000), 13700, conf) == 0
    conf.coarse_first = False  # no coarse-first: octave 0 from the threshold up
    assert patch_first_octave((1024, 1536), 1024, conf) == 0
    # never below the configured octave; inf: always the configured octave
    assert patch_first_octave((1024, 1536), 8192, SiftConf(patch_first_octave=1)) == 1
    conf.patch_first_octave = 1
    assert patch_first_octave((360, 480), 8192, conf) == 1
    assert (
        patch_first_octave((1024, 1536), 8192, SiftConf(patch_octave0_pixels_per_feature=1e9)) == -1
    )


def test_plain_path_uses_coarse_first_only_where_it_pays():
    """An image without planes: coarse-first SIFT where the coarser octaves fill the budget
    on an image of at least sift.pool_coarse_first_min_pixels, else (or with
    sift.coarse_first off) exactly one COLMAP call."""
    from rectified_colmap import camera as cam_utils
    from rectified_colmap.config import ExtractConf
    from rectified_colmap.pipeline import extract_image
    from tests.scenes import SINGLE_VIEW

    img = textured_image(300, 400, 7)
    camera = cam_utils.make_camera("PINHOLE", [400, 400, 200, 150], 400, 300)
    conf = ExtractConf.from_dict(SINGLE_VIEW)  # no views from the texture's lines
    # the default: a 0.12 MP image is under the pixel threshold, the call is exact
    assert conf.sift.pool_coarse_first_min_pixels > 400 * 300
    conf.sift.max_num_features = 150
    out = extract_image(img, camera, None, conf).features
    np.testing.assert_array_equal(out.keypoints, detect_sift(img, conf.sift, 150).keypoints)
    conf.sift.pool_coarse_first_min_pixels = 400 * 300
    for n, pays in ((150, True), (2000, False)):
        conf.sift.max_num_features = n
        assert coarse_first_pays(img.shape, n, conf.sift) == pays
        out = extract_image(img, camera, None, conf).features
        ref = detect_sift(img, conf.sift, n, coarse_first=pays)
        np.testing.assert_array_equal(out.keypoints, ref.keypoints)
        if pays:  # not the exact call's output
            exact = detect_sift(img, conf.sift, n)
            assert len(exact) != len(out) or not np.array_equal(exact.keypoints, out.keypoints)
    conf.sift.coarse_first = False
    conf.sift.max_num_features = 150
    out = extract_image(img, camera, None, conf).features
    np.testing.assert_array_equal(out.keypoints, detect_sift(img, conf.sift, 150).keypoints)


def test_count_detections_counts_points_not_orientations():
    m = np.array([[1, 2, 3, 0.1], [1, 2, 3, 0.5], [1, 2, 4, 0.1], [5, 2, 4, 0.1]], float)
    assert count_detections(m) == 3
    assert count_detections(np.zeros((0, 4))) == 0


def test_opencv_sift_is_colmap_sift_from_the_upsampled_octave():
    """OpenCV's SIFT with precise upscaling (sift.opencv_sift, the views' backend "opencv")
    finds COLMAP's keypoints (first octave -1) at the same position and scale, with the same
    descriptor in COLMAP's RootSIFT byte scale where the orientation agrees."""
    img = textured_image(300, 400, 5)
    ref, ref_desc = _sift_matrix(img, 10**6)
    m, desc = opencv_sift(img, SiftConf(), 10**6)
    assert desc.dtype == np.uint8 and desc.shape == (len(m), 128)
    at = np.linalg.norm(ref[:, None, :2] - m[None, :, :2], axis=2) < 0.01
    at &= np.abs(m[None, :, 2] / ref[:, None, 2] - 1) < 1e-3
    same = at.any(1)
    assert same.mean() > 0.7, same.mean()
    turn = np.abs(np.angle(np.exp(1j * (m[None, :, 3] - ref[:, None, 3]))))
    j = np.where(at, turn, np.inf).argmin(1)  # of the same point, the closest orientation
    both = same & (turn[np.arange(len(ref)), j] < np.deg2rad(2.0))
    assert both.sum() > 0.3 * len(ref)
    a = ref_desc[both].astype(float)
    b = desc[j[both]].astype(float)
    cosine = (a * b).sum(1) / np.linalg.norm(a, axis=1) / np.linalg.norm(b, axis=1)
    assert np.median(cosine) > 0.98, np.median(cosine)
    # COLMAP's byte scale: the square root of an L1-normalized histogram, x 512
    np.testing.assert_allclose(((desc.astype(float) / 512) ** 2).sum(1), 1.0, atol=0.05)


def test_opencv_sift_from_octave_0_is_its_upsampled_octave_of_the_halved_image():
    """First octave 0 (sift.opencv_sift on views of 1.2-4 MP images): OpenCV's SIFT of the
    exactly halved image, keypoints doubled back in COLMAP's convention. On an image made
    of 2 x 2 blocks, halving is exact: the result is exactly twice the keypoints of the
    small image from octave -1, with the same descriptors."""
    small = textured_image(150, 200, 5)
    big = np.repeat(np.repeat(small, 2, axis=0), 2, axis=1)
    np.testing.assert_array_equal(halved(big), small)
    m, desc = opencv_sift(big, SiftConf(), 10**6, first_octave=0)
    ref, ref_desc = opencv_sift(small, SiftConf(), 10**6)
    assert len(m) > 100
    np.testing.assert_allclose(m[:, :3], 2.0 * ref[:, :3], rtol=0, atol=1e-9)
    np.testing.assert_array_equal(m[:, 3], ref[:, 3])
    np.testing.assert_array_equal(desc, ref_desc)
    # an odd size: the last column and row are padded, so pixel x still maps to 2 x
    odd = textured_image(151, 203, 6)
    half = halved(odd)
    assert half.shape == (76, 102)
    blocks = odd[:150, :202].reshape(75, 2, 101, 2).mean((1, 3))
    np.testing.assert_allclose(half[:-1, :-1], blocks, atol=0.51)
    with pytest.raises(ValueError, match="first octave"):
        opencv_sift(small, SiftConf(), 10, first_octave=1)


def test_opencv_sift_from_octave_0_finds_colmaps_keypoints():
    """OpenCV's SIFT from octave 0 (the halved image upsampled) against COLMAP's from octave
    0: most keypoints at the same place and scale (halving and OpenCV's upsampling blur the
    finest detail a little differently: measured 69 % within 0.5 px on a photo), the same
    descriptor where the orientation agrees."""
    img = textured_image(300, 400, 5)
    ref, ref_desc = _sift_matrix(img, 10**6, first_octave=0)
    m, desc = opencv_sift(img, SiftConf(), 10**6, first_octave=0)
    assert 0.7 * len(ref) < len(m) < 1.3 * len(ref), (len(m), len(ref))
    dist = np.linalg.norm(ref[:, None, :2] - m[None, :, :2], axis=2)
    j = dist.argmin(1)
    near = dist[np.arange(len(ref)), j] < 0.5
    assert near.mean() > 0.5, near.mean()
    assert np.median(m[j[near], 2] / ref[near, 2]) == pytest.approx(1.0, abs=0.02)
    turn = np.abs(np.angle(np.exp(1j * (m[j, 3] - ref[:, 3]))))
    both = near & (turn < np.deg2rad(2.0))
    assert both.sum() > 0.2 * len(ref)
    a, b = ref_desc[both].astype(float), desc[j[both]].astype(float)
    cosine = (a * b).sum(1) / np.linalg.norm(a, axis=1) / np.linalg.norm(b, axis=1)
    assert np.median(cosine) > 0.97, np.median(cosine)


def test_opencv_sift_budget_keeps_the_largest_points_and_two_orientations():
    img = textured_image(300, 400, 5)
    conf = SiftConf()
    full, _ = opencv_sift(img, conf, 10**6)
    assert count_detections(full) > 300
    for n in (50, 300):
        part, desc = opencv_sift(img, conf, n)
        assert len(desc) == len(part)
        points, counts = np.unique(part[:, :3], axis=0, return_counts=True)
        assert len(points) == n and counts.max() <= conf.max_num_orientations
        dropped = ~(full[:, None, :3] == points[None]).all(2).any(1)
        assert part[:, 2].min() >= full[dropped, 2].max()
    one, _ = opencv_sift(img, SiftConf(max_num_orientations=1), 10**6)
    assert len(np.unique(one[:, :3], axis=0)) == len(one) == count_detections(full)
