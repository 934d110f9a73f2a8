"""Homography evaluation: conventions, exact errors, oracle plane normals, the CLI."""

import json

import numpy as np
import pytest

from rectified_colmap.conventions import to_opencv_homography
from rectified_colmap.eval.homography import (
    HomographyConf,
    HomographyPair,
    apply_homography,
    colmap_homography_from_opencv,
    evaluate_homography_pairs,
    homography_errors,
    plane_normals_from_homography,
    read_homography_pairs,
    visible_grid,
)


def rot(axis, deg):
    import cv2

    return cv2.Rodrigues(np.asarray(axis, float) * np.deg2rad(deg) / np.linalg.norm(axis))[0]


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
