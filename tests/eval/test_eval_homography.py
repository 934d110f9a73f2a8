"""Homography evaluation: conventions, exact errors, the sign of H, the CLI."""

import json

import numpy as np
import pytest

from rectified_colmap.conventions import to_opencv_homography
from rectified_colmap.eval.homography import (
    HomographyConf,
    HomographyPair,
    apply_homography,
    colmap_homography_from_opencv,
    estimate_homography,
    evaluate_homography_pairs,
    homography_errors,
    read_homography_pairs,
    visible_grid,
)


def test_opencv_to_colmap_homography_is_the_inverse_of_conventions():
    rng = np.random.default_rng(0)
    G = np.eye(3) + 0.1 * rng.standard_normal((3, 3))
    np.testing.assert_allclose(
        colmap_homography_from_opencv(to_opencv_homography(G)), G, atol=1e-12
    )
    # A pure scaling by 2 about OpenCV's origin: pixel centre 0 -> 0, i.e. COLMAP 0.5 -> 0.5.
    S = colmap_homography_from_opencv(np.diag([2.0, 2.0, 1.0]))
    np.testing.assert_allclose(
        apply_homography(S, np.array([[0.5, 0.5], [1.5, 0.5]])), [[0.5, 0.5], [2.5, 0.5]]
    )


def pair_with(H, size0=(200, 100), size1=(200, 100)):
    return HomographyPair("p", "a", "b", H, size0, size1)


def test_errors_exact_for_known_offsets_and_visible_part_only():
    H = np.array([[1.0, 0, 50], [0, 1, 0], [0, 0, 1]])  # image 0 shifted right by 50
    pair = pair_with(H)
    assert homography_errors(H, pair) == (0.0, 0.0)
    off = np.array([[1.0, 0, 53], [0, 1, 4], [0, 0, 1]])  # 5 px off everywhere
    ce, ve = homography_errors(off, pair)
    assert ce == pytest.approx(5.0) and ve == pytest.approx(5.0)
    # Only image-0 points landing inside image 1 count: x < 150.
    g = visible_grid(pair, 10)
    assert g[:, 0].max() < 150 and len(g) == 15 * 10
    assert homography_errors(None, pair) == (np.inf, np.inf)
    # An estimate mapping some visible points behind the camera fails.
    flip = np.array([[1.0, 0, 0], [0, 1, 0], [-0.02, 0, 1]])
    assert homography_errors(flip, pair)[1] == np.inf


def test_sign_of_the_file_homography_does_not_matter(tmp_path):
    H = np.array([[1.0, 0.1, 5], [0, 1.2, 3], [1e-4, 0, 1]])
    f = tmp_path / "pairs.json"
    f.write_text(
        json.dumps(
            [{"im0": "a", "im1": "b", "H": (-H).tolist(), "size0": [200, 100], "size1": [200, 100]}]
        )
    )
    (p,) = read_homography_pairs(f)
    x = np.array([[10.0, 20.0], [150.0, 60.0]])
    np.testing.assert_allclose(
        apply_homography(p.H, x), apply_homography(colmap_homography_from_opencv(H), x)
    )
    assert np.isfinite(apply_homography(p.H, x)).all()


GROUND_TILT = np.deg2rad(3.0)
GROUND_D = 20 * np.sin(GROUND_TILT)


def ground_row(z):
    """The image-0 row (COLMAP) that sees the ground at depth z (facing_cameras_over_ground)."""
    return 240 + 500 * (GROUND_D / z - np.sin(GROUND_TILT)) / np.cos(GROUND_TILT)


def facing_cameras_over_ground():
    """(H, region0): two cameras facing each other over a ground plane (camera 0's frame:
    the plane n . X = d), H with w = depth in camera 1 / depth in camera 0. Image 0's centre
    and origin see the plane 20 m and more away, behind camera 1 (8 m ahead, facing back),
    so they map to w < 0; region0 (the ground 2-6 m ahead) is in front of both."""
    K = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])
    n = np.array([0.0, np.cos(GROUND_TILT), np.sin(GROUND_TILT)])
    R, t = np.diag([-1.0, 1.0, -1.0]), np.array([0.0, 0.0, 8.0])
    H = K @ (R + np.outer(t, n) / GROUND_D) @ np.linalg.inv(K)
    region0 = np.array(
        [[220.0, ground_row(6)], [420, ground_row(6)], [420, ground_row(2)], [220, ground_row(2)]]
    )
    assert (np.array([[320.0, 240, 1], [0, 0, 1]]) @ H[2] < 0).all()  # centre, origin
    assert (np.c_[region0, np.ones(4)] @ H[2] > 0).all()
    return H, region0


def ground_pair_file(path, H, file_sign, **regions):
    """``path``: a pair file of one 640 x 480 pair (COLMAP pixels), its H ``file_sign`` x
    H / H[2, 2], and the given regions (key -> (K, 2) polygon)."""
    item = {
        "im0": "a",
        "im1": "b",
        "H": (file_sign * H / H[2, 2]).tolist(),
        "convention": "colmap",
        "size0": [640, 480],
        "size1": [640, 480],
    }
    path.write_text(json.dumps([item | {k: [r.tolist()] for k, r in regions.items()}]))
    return path


@pytest.mark.parametrize("region_key", ["region0", "region1"])
@pytest.mark.parametrize("file_sign", [1.0, -1.0])
def test_sign_from_the_region_where_the_centre_sees_the_plane_behind_camera_1(
    tmp_path, region_key, file_sign
):
    # the centre maps to w < 0 and cannot set the sign; the region must
    H, region0 = facing_cameras_over_ground()
    region = region0 if region_key == "region0" else apply_homography(H, region0)
    f = ground_pair_file(tmp_path / "pairs.json", H, file_sign, **{region_key: region})
    (p,) = read_homography_pairs(f)
    np.testing.assert_allclose(p.H, H / abs(H[2, 2]), rtol=1e-9)
    np.testing.assert_allclose(p.region0[0], region0, atol=1e-6)
    g = visible_grid(p, 20)
    assert len(g) > 50  # with the centre's sign, no point of the region was visible
    assert homography_errors(p.H, p)[1] == 0.0  # the corners: some lie beyond the horizon


@pytest.mark.parametrize("file_sign", [1.0, -1.0])
def test_sign_from_the_overlap_where_most_of_region0_lies_behind_camera_1(tmp_path, file_sign):
    """region0 the ground as image 0 sees it up to 40 m (three of its five vertices beyond
    camera 1, so they map to w < 0 and their majority gave the wrong sign), region1 the
    ground camera 1 sees (the 2-6 m strip): the sign comes from the points region0 and
    region1 share, whatever the file's."""
    H, near = facing_cameras_over_ground()
    row = ground_row
    region0 = np.array(
        [[100.0, row(2)], [540, row(2)], [600, row(20)], [320, row(40)], [40, row(20)]]
    )
    assert np.sum(np.sign(np.c_[region0, np.ones(5)] @ H[2])) < 0  # the vertices' majority
    region1 = apply_homography(H, near)
    f = tmp_path / "pairs.json"
    (p,) = read_homography_pairs(
        ground_pair_file(f, H, file_sign, region0=region0, region1=region1)
    )
    np.testing.assert_allclose(p.H, H / abs(H[2, 2]), rtol=1e-9)
    assert len(visible_grid(p, 20)) > 50
    # without region1 the vertices decide (the old rule), and they decide wrongly here
    with pytest.raises(ValueError, match="region0 maps behind camera 1"):
        read_homography_pairs(ground_pair_file(f, H, file_sign, region0=region0))


def test_an_exact_estimate_is_solved_where_image_0s_origin_sees_the_plane_behind_camera_1():
    # OpenCV's estimate has H[2, 2] = 1: w > 0 at image 0's origin, the wrong sign here, so
    # every visible point mapped behind camera 1 and a perfect estimate failed.
    H, region0 = facing_cameras_over_ground()
    pair = HomographyPair("p", "a", "b", H, (640, 480), (640, 480), [region0], None)
    rng = np.random.default_rng(0)
    lo, hi = region0.min(0), region0.max(0)
    x0 = lo + (hi - lo) * rng.random((200, 2))
    x1 = apply_homography(H, x0)
    x1[:40] += rng.uniform(30, 60, (40, 2))  # outliers
    H_est, inl = estimate_homography(x0, x1, HomographyConf())
    assert inl[40:].all() and not inl[:40].any()
    np.testing.assert_allclose(H_est / H_est[2, 2], H / H[2, 2], rtol=1e-6, atol=1e-6)
    assert (np.c_[x0[inl], np.ones(inl.sum())] @ H_est[2] > 0).all()
    assert homography_errors(H_est, pair)[1] < 1e-3  # px
    H_rev, _ = estimate_homography(x1, x0, HomographyConf())  # image 1 -> image 0
    assert homography_errors(H_rev, pair.reverse())[1] < 1e-3


def synthetic_features(H, n=300, seed=0, outliers=50):
    rng = np.random.default_rng(seed)
    x0 = rng.uniform([10, 10], [190, 90], (n, 2))
    x1 = apply_homography(H, x0) + rng.normal(0, 0.3, (n, 2))
    desc = rng.standard_normal((n, 128)).astype(np.float32)
    desc1 = desc + 0.05 * rng.standard_normal(desc.shape).astype(np.float32)
    x1[:outliers] = rng.uniform([0, 0], [200, 100], (outliers, 2))  # wrong positions
    return {
        "a": {"keypoints": x0, "descriptors": desc.T},
        "b": {"keypoints": x1, "descriptors": desc1.T},
    }


def test_evaluate_pairs_counts_gt_matches_and_solves_both_directions():
    H = np.array([[0.9, 0.05, 12], [-0.03, 1.1, 4], [2e-4, 1e-4, 1]])
    pair = pair_with(H)
    feats = synthetic_features(H)
    recs = evaluate_homography_pairs([pair], {"m": feats}, HomographyConf())
    assert [r["direction"] for r in recs] == ["0->1", "1->0"]
    for r in recs:
        assert r["num_matches"] == 300 and r["num_gt"] == 250
        assert r["success"] and r["visible_err"] < 1.0 and r["corner_err"] < 3.0
    bad = synthetic_features(H, outliers=298)
    (r,) = evaluate_homography_pairs([pair], {"m": bad}, HomographyConf(), False)
    assert r["num_gt"] == 2 and not r["success"]


def test_cli_evaluate_homography(tmp_path):
    from rectified_colmap.cli import main
    from rectified_colmap.features import Features
    from rectified_colmap.io.hloc_h5 import HlocFeatureWriter

    H = np.array([[0.9, 0.05, 12], [-0.03, 1.1, 4], [2e-4, 1e-4, 1]])
    feats = synthetic_features(H)
    h5 = tmp_path / "f.h5"
    with HlocFeatureWriter(h5) as w:
        for name, f in feats.items():
            kp = f["keypoints"]
            # Descriptors as uint8 RootSIFT-like bytes: positive, distinct per keypoint.
            d = f["descriptors"].T
            d = np.clip(np.abs(d) * 60, 0, 255).astype(np.uint8)
            w.write(
                name,
                Features(
                    kp, np.tile(np.eye(2), (len(kp), 1, 1)), d, np.full(len(kp), -1, np.int32)
                ),
                (200, 100),
            )
    pairs = tmp_path / "pairs.json"
    pairs.write_text(
        json.dumps(
            [
                {
                    "pair": "syn",
                    "im0": "a",
                    "im1": "b",
                    "H": to_opencv_homography(H).tolist(),
                    "size0": [200, 100],
                    "size1": [200, 100],
                }
            ]
        )
    )
    out = tmp_path / "out"
    assert (
        main(
            [
                "evaluate-homography",
                "--pairs",
                str(pairs),
                "--features",
                f"m={h5}",
                "--output_dir",
                str(out),
            ]
        )
        == 0
    )
    text = (out / "summary.md").read_text()
    assert "| m | 2 | 2 | 1 of 1 |" in text


# -- regions (plane pairs: only the plane's part of image 0 is governed by H) ---------------
def test_points_in_region_exact():
    from rectified_colmap.eval.homography import points_in_region

    square = np.array([[10.0, 10], [20, 10], [20, 20], [10, 20]])
    ell = np.array([[0.0, 0], [30, 0], [30, 10], [10, 10], [10, 30], [0, 30]])  # concave L
    pts = np.array([[15.0, 15], [5, 5], [25, 5], [5, 25], [25, 25], [-1, 5], [15, 31]])
    np.testing.assert_array_equal(points_in_region(pts, [square]), [1, 0, 0, 0, 0, 0, 0])
    np.testing.assert_array_equal(points_in_region(pts, [ell]), [0, 1, 1, 1, 0, 0, 0])
    np.testing.assert_array_equal(points_in_region(pts, [ell, square]), [1, 1, 1, 1, 0, 0, 0])
    np.testing.assert_array_equal(points_in_region(pts, [ell[::-1]]), [0, 1, 1, 1, 0, 0, 0])
    assert points_in_region(pts, None).all()


def test_masked_visible_grid_exact():
    H = np.array([[1.0, 0, 50], [0, 1, 0], [0, 0, 1]])  # image 0 shifted right by 50
    rect = np.array([[40.0, 20], [170, 20], [170, 60], [40, 60]])
    pair = HomographyPair("p", "a", "b", H, (200, 100), (200, 100), [rect], None)
    g = visible_grid(pair, 10)
    # x in 45..145 (inside the rectangle AND landing in image 1: x + 50 <= 200), y 25..55
    xs, ys = np.arange(45, 150, 10), np.arange(25, 60, 10)
    np.testing.assert_array_equal(g, np.stack(np.meshgrid(xs, ys), -1).reshape(-1, 2))
    # the errors average over exactly those points: an estimate off by 3 px in x for x < 100
    # only (a piecewise map cannot be a homography; use one that scales x instead)
    S = np.array([[1.1, 0, 50], [0, 1, 0], [0, 0, 1]])
    _, ve = homography_errors(S, pair)
    assert ve == pytest.approx(np.mean(0.1 * g[:, 0]))
    _, ve_all = homography_errors(S, pair_with(H))
    assert ve_all == pytest.approx(np.mean(0.1 * visible_grid(pair_with(H), 10)[:, 0]))
    assert ve_all < ve  # the unmasked grid has more points at small x


def test_pair_file_without_region_is_unchanged(tmp_path):
    H = np.array([[0.9, 0.05, 12], [-0.03, 1.1, 4], [2e-4, 1e-4, 1]])
    item = {
        "pair": "evd",
        "im0": "a",
        "im1": "b",
        "H": to_opencv_homography(H).tolist(),
        "size0": [200, 100],
        "size1": [200, 100],
        "source": "EVD",
    }
    f = tmp_path / "pairs.json"
    f.write_text(json.dumps([item]))
    (p,) = read_homography_pairs(f)
    assert p.region0 is None and p.region1 is None and p.info == {"source": "EVD"}
    np.testing.assert_allclose(p.H, H, atol=1e-12)
    old = HomographyPair("evd", "a", "b", p.H, (200, 100), (200, 100))  # as before regions
    np.testing.assert_array_equal(visible_grid(p, 10), visible_grid(old, 10))
    # the grid of before: every grid point that H maps into image 1
    xs, ys = np.arange(5, 200, 10), np.arange(5, 100, 10)
    g = np.stack(np.meshgrid(xs, ys), -1).reshape(-1, 2)
    m = apply_homography(H, g)
    inside = (m[:, 0] >= 0) & (m[:, 0] <= 200) & (m[:, 1] >= 0) & (m[:, 1] <= 100)
    np.testing.assert_array_equal(visible_grid(p, 10), g[inside])
    feats = synthetic_features(H)
    a = evaluate_homography_pairs([p], {"m": feats}, HomographyConf())
    b = evaluate_homography_pairs([old], {"m": feats}, HomographyConf())
    assert a == b and a[0]["num_gt"] == 250


def test_region_restricts_gt_matches_in_both_directions(tmp_path):
    from rectified_colmap.eval.homography import points_in_region

    H = np.array([[0.9, 0.05, 12], [-0.03, 1.1, 4], [2e-4, 1e-4, 1]])
    left = [[0.0, 0.0], [99.5, 0.0], [99.5, 99.5], [0.0, 99.5]]  # OpenCV pixels: x < 100
    f = tmp_path / "pairs.json"
    f.write_text(
        json.dumps(
            [
                {
                    "im0": "a",
                    "im1": "b",
                    "H": to_opencv_homography(H).tolist(),
                    "size0": [200, 100],
                    "size1": [200, 100],
                    "region0": [left],
                    "band": "extreme",
                }
            ]
        )
    )
    (p,) = read_homography_pairs(f)
    np.testing.assert_allclose(p.region0[0], np.array(left) + 0.5)  # -> COLMAP pixels
    np.testing.assert_allclose(p.region1[0], apply_homography(H, p.region0[0]))
    assert p.info == {"band": "extreme"}
    assert p.reverse().region0 is p.region1 and p.reverse().region1 is p.region0
    feats = synthetic_features(H)
    x0 = feats["a"]["keypoints"]
    good = np.arange(len(x0)) >= 50  # synthetic_features: the first 50 are outliers
    expect = int((good & points_in_region(x0, p.region0)).sum())
    assert 0 < expect < 250
    recs = evaluate_homography_pairs([p], {"m": feats}, HomographyConf())
    for r in recs:  # 1->0: image 1's points in region1 are the same matches
        assert r["num_gt"] == expect and r["success"] and r["num_matches"] == 300
    full = visible_grid(pair_with(p.H), 10)  # the region (COLMAP x in 0.5..100) cuts x >= 105
    np.testing.assert_array_equal(visible_grid(p, 10), full[full[:, 0] < 100])
    # the reverse grid lies in region1
    rev = visible_grid(p.reverse(), 10)
    assert points_in_region(rev, p.region1).all() and len(rev) > 50


def test_region_reader_errors(tmp_path):
    f = tmp_path / "pairs.json"
    base = {"im0": "a", "im1": "b", "H": np.eye(3).tolist(), "size0": [9, 9], "size1": [9, 9]}
    for region, msg in (([[[0, 0], [1, 1]]], "at least 3"), ([[0, 1, 2]], "polygons")):
        f.write_text(json.dumps([dict(base, region0=region)]))
        with pytest.raises(ValueError, match=msg):
            read_homography_pairs(f)
    behind = dict(base, H=[[1, 0, 0], [0, 1, 0], [-0.2, 0, 1]], region0=[[[0, 0], [9, 0], [9, 9]]])
    f.write_text(json.dumps([behind]))
    with pytest.raises(ValueError, match="behind"):
        read_homography_pairs(f)
    explicit = dict(behind, region1=[[[0, 0], [1, 0], [1, 1]]])
    f.write_text(json.dumps([explicit]))
    (p,) = read_homography_pairs(f)
    np.testing.assert_allclose(p.region1[0], np.array([[0, 0], [1, 0], [1, 1]]) + 0.5)


def test_group_markdown_counts_pairs_and_cases():
    from rectified_colmap.eval.homography import homography_group_markdown

    def rec(pair, direction, method, success, num_gt):
        return dict(pair=pair, direction=direction, method=method, success=success, num_gt=num_gt)

    records = [
        rec("a", "0->1", "m", True, 10),
        rec("a", "1->0", "m", False, 4),
        rec("b", "0->1", "m", False, 0),
        rec("b", "1->0", "m", False, 2),
        rec("c", "0->1", "m", True, 30),
        rec("c", "1->0", "m", True, 40),
    ]
    text = homography_group_markdown(records, {"a": "x", "b": "x"})
    assert "| x | m | 1 of 2 | 1 of 4 | 3 / 4.0 |" in text
    assert "| - | m | 1 of 1 | 2 of 2 | 35 / 35.0 |" in text


def test_region_ransac_estimates_from_the_region_only():
    """Matches of two planes: 200 of another plane on the right (x >= 100), 80 of the
    ground-truth plane on the left, the region: RANSAC on all matches picks the other plane,
    region_ransac the right one."""
    rng = np.random.default_rng(3)
    H_a = np.array([[0.9, 0.05, 12], [-0.03, 1.1, 4], [2e-4, 1e-4, 1]])
    H_b = np.array([[1.0, 0.0, 30], [0.0, 1.0, -5], [0, 0, 1]])
    xa = rng.uniform([5, 5], [95, 95], (80, 2))
    xb = rng.uniform([105, 5], [195, 95], (200, 2))
    x0 = np.vstack([xa, xb])
    x1 = np.vstack([apply_homography(H_a, xa), apply_homography(H_b, xb)])
    desc = rng.standard_normal((len(x0), 128)).astype(np.float32)
    feats = {
        "a": {"keypoints": x0, "descriptors": desc.T},
        "b": {"keypoints": x1, "descriptors": desc.T},
    }
    left = [np.array([[0.0, 0], [100, 0], [100, 100], [0, 100]])]
    pair = HomographyPair("p", "a", "b", H_a, (200, 100), (200, 100), left, None)
    (r,) = evaluate_homography_pairs([pair], {"m": feats}, HomographyConf(), False)
    assert r["num_gt"] == 80 and r["num_inliers"] >= 200 and not r["success"]
    (r,) = evaluate_homography_pairs(
        [pair], {"m": feats}, HomographyConf(region_ransac=True), False
    )
    assert r["num_gt"] == 80 and r["num_inliers"] == 80 and r["visible_err"] < 1e-6
    # without a region the option changes nothing
    whole = pair_with(H_b)
    a = evaluate_homography_pairs([whole], {"m": feats}, HomographyConf(), False)
    b = evaluate_homography_pairs([whole], {"m": feats}, HomographyConf(region_ransac=True), False)
    assert a == b
