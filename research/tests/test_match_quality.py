"""research/scripts/match_quality.py: matches sorted by the features they join (plain
SIFT's, found exactly in the baseline's file, or added), on a scene whose correspondences
and errors are known exactly."""

import numpy as np
import pytest
from scripts_util import load_script

from rectified_colmap.eval.config import EvalConf
from rectified_colmap.eval.pairs import Pair, write_pairs_with_gt
from rectified_colmap.features import Features
from rectified_colmap.geometry import axis_angle_rotation
from rectified_colmap.io.hloc_h5 import HlocFeatureWriter

diag = load_script("match_quality")

K = np.array([[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]])


def test_match_kinds_count_the_added_features_of_a_match():
    m = np.array([[0, 0], [2, 1], [1, 3], [3, 5], [4, 2]])
    added0 = np.array([False, False, False, True, True])  # features 3, 4 of image 0 added
    added1 = np.array([False, False, True, True, True, True])
    assert diag.match_kinds(m, added0, added1).tolist() == [0, 0, 1, 2, 2]
    assert diag.match_kinds(np.zeros((0, 2)), added0, added1).tolist() == []


def _scene(rng, n):
    """Camera 1 = rotation of 10 degrees about y and a sideways step; n points in front of
    both: their pixels (n, 2) in each image (COLMAP convention)."""
    R = axis_angle_rotation(np.array([0.0, 1.0, 0.0]), np.deg2rad(10.0))
    t = np.array([-1.0, 0.0, 0.1])
    X = np.c_[rng.uniform(-3, 3, (n, 2)), rng.uniform(6, 12, n)]
    x0 = X @ K.T
    x1 = (X @ R.T + t) @ K.T
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return x0[:, :2] / x0[:, 2:], x1[:, :2] / x1[:, 2:], T


def _features(xy, desc):
    n = len(xy)
    return Features(xy, np.tile(np.eye(2) * 2.0, (n, 1, 1)), desc, np.full(n, -1, np.int32))


def _files(tmp_path, rng):
    """Plain: 60 exact correspondences. The method: plain's features and, on top, 30
    correspondences moved by ~1 px in image 1 and 20 wrong ones (image 1's points reversed
    and shifted 40 px)."""
    p0, p1, T = _scene(rng, 110)
    desc = rng.integers(0, 256, (110, 128), dtype=np.uint8)
    moved = p1.copy()
    moved[60:90] += rng.normal(size=(30, 2)) * 0.7
    moved[90:] = moved[90:][::-1] + 40.0  # far from their points: wrong
    (tmp_path / "scene").mkdir()
    for method, n in (("sift", 60), ("rectsift", 110)):
        with HlocFeatureWriter(tmp_path / "features" / "scene" / f"{method}.h5") as w:
            w.write("a.jpg", _features(p0[:n], desc[:n]), (640, 480))
            w.write("b.jpg", _features(moved[:n], desc[:n]), (640, 480))
    pair = Pair("a.jpg", "b.jpg", K, K, T)
    write_pairs_with_gt(tmp_path / "scene" / "pairs_with_gt.txt", [pair])
    return pair


def test_pair_matches_sorts_kinds_and_finds_the_worse_located_ones(tmp_path):
    pair = _files(tmp_path, np.random.default_rng(0))
    conf = EvalConf(ransac_runs=2)
    root = tmp_path / "features" / "scene"
    r = diag.pair_matches(pair, root / "rectsift.h5", root / "sift.h5", conf)
    assert np.bincount(r["kind"], minlength=3).tolist() == [60, 0, 50]
    plain, rect = r["error"][r["kind"] == 0], r["error"][r["kind"] == 2]
    assert plain.max() < 1e-3  # exact correspondences (float32 in the file)
    assert np.median(rect[:30]) > 0.1 and (rect[30:] > 3.0).mean() > 0.8
    assert r["success"] == r["success_plain"] == r["success_base"] == 1.0
    rows = diag.kind_table([r], conf.epipolar_threshold)
    assert rows[2].startswith("| plain-plain | 60 | 100% | 0.00 / 0.00 |")
    assert rows[3] == "| plain-added | 0 | - | - | - |"
    assert rows[4].startswith("| added-added | 50 |")


def test_main_prints_the_table_and_names_a_missing_file(tmp_path, capsys):
    _files(tmp_path, np.random.default_rng(1))
    args = ["--data", str(tmp_path), "--features", str(tmp_path / "features")]
    assert diag.main([*args, "--ransac_runs", "1"]) == 0
    out = capsys.readouterr().out
    assert "| added-added | 50 |" in out and "sift 100.0 %" in out
    # the other way round every match is plain-plain: rectsift's 110 hold sift's 60
    diag.added.cache_clear()
    assert diag.main([*args, "--method", "sift", "--baseline", "rectsift"]) == 0
    assert "| plain-plain | 60 |" in capsys.readouterr().out
    with pytest.raises(SystemExit, match="feature file not found"):
        diag.main([*args, "--method", "nothing"])
