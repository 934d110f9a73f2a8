"""rectified_colmap_research.evaluation.match_sources: plain SIFT's matches kept, removed,
crowded out, and the new ones."""

import numpy as np
import pycolmap

from rectified_colmap_research.evaluation.match_sources import (
    MatchSources,
    correct_matches,
    nn_ratio_mutual,
    pair_sources,
    plain_index,
)
from rectified_colmap.eval.matching import match_ratio
from rectified_colmap.eval.relpose import fundamental_from_pose
from scripts_util import load_script


def _unit(x):
    return (x / np.linalg.norm(x, axis=1, keepdims=True)).astype(np.float32)


def test_nn_ratio_mutual_is_ratio_both_ways_and_mutual():
    rng = np.random.default_rng(0)
    d0 = _unit(rng.normal(size=(80, 16)))
    d1 = _unit(
        np.concatenate([d0[:40] + 0.15 * rng.normal(size=(40, 16)), rng.normal(size=(50, 16))])
    )
    # a twin of d0[0]: 0 -> 0 still passes the ratio test forwards, not backwards
    d0 = np.concatenate([d0, _unit(d0[[0]] + 0.01 * rng.normal(size=(1, 16)))])
    dist = np.linalg.norm(d0[:, None] - d1[None], axis=2)
    expected = set()
    for i in range(len(d0)):
        j, j2 = np.argsort(dist[i])[:2]
        i_, i2 = np.argsort(dist[:, j])[:2]
        if i_ == i and dist[i, j] < 0.8 * dist[i, j2] and dist[i, j] < 0.8 * dist[i2, j]:
            expected.add((i, int(j)))
    got = {tuple(m) for m in nn_ratio_mutual(d0, d1).tolist()}
    assert got == expected and len(got) > 20
    assert (0, 0) not in got and (0, 0) in {tuple(m) for m in match_ratio(d0, d1, mutual=True)}


def test_plain_index_needs_identical_keypoint_and_descriptor():
    rng = np.random.default_rng(1)
    plain = {
        "keypoints": rng.uniform(0, 100, (5, 2)),
        "descriptors": _unit(rng.normal(size=(5, 8))),
    }
    other = _unit(rng.normal(size=(1, 8)))
    feats = {
        # plain 3, an added feature at plain 1's keypoint (another orientation), plain 0
        "keypoints": plain["keypoints"][[3, 1, 0]],
        "descriptors": np.concatenate(
            [plain["descriptors"][[3]], other, plain["descriptors"][[0]]]
        ),
    }
    assert plain_index(feats, plain).tolist() == [3, -1, 0]


def _scene():
    """Plain SIFT's features of two images with 30 true matches, and a feature set that
    drops plain feature 0 of image 0, adds a near-copy of plain feature 2 of image 1
    elsewhere (crowding: its match fails the ratio test), and adds two new matches, one on
    its epipolar line (the camera moved along x: the rows) and one 50 px off it."""
    rng = np.random.default_rng(2)
    n, D = 40, 32
    d0 = _unit(rng.normal(size=(n, D)))
    d1 = _unit(
        np.concatenate([d0[:30] + 0.05 * rng.normal(size=(30, D)), rng.normal(size=(10, D))])
    )
    kp0 = rng.uniform(0, 500, (n, 2))
    kp1 = kp0 + [40.0, 0.0]
    kp1[30:] = rng.uniform(0, 500, (10, 2))
    plain = {"im0.jpg": {"keypoints": kp0, "descriptors": d0}}
    plain["im1.jpg"] = {"keypoints": kp1, "descriptors": d1}
    new = _unit(rng.normal(size=(2, D)))
    crowd = _unit(d1[[2]] + 0.001 * rng.normal(size=(1, D)))
    feats = {
        "im0.jpg": {
            "keypoints": np.concatenate([kp0[1:], [[10.0, 20.0], [30.0, 40.0]]]),
            "descriptors": np.concatenate([d0[1:], new]),
        },
        "im1.jpg": {
            "keypoints": np.concatenate([kp1, [[200.0, 20.0], [80.0, 90.0], [450.0, 450.0]]]),
            "descriptors": np.concatenate([d1, new, crowd]),
        },
    }
    expected = MatchSources(
        plain_matches=30,
        kept=28,
        lost_removed=1,
        lost_crowded=1,
        new_plain_plain=0,
        with_added=2,
        plain_correct=30,
        correct=29,
        with_added_correct=1,
    )
    return plain, feats, expected


def test_pair_sources_counts_each_kind_exactly():
    plain, feats, expected = _scene()
    (p0, p1), (f0, f1) = plain.values(), feats.values()
    n = len(p0["keypoints"])
    i0, i1 = plain_index(f0, p0), plain_index(f1, p1)
    assert (i0[:-2] == np.arange(1, n)).all() and (i0[-2:] == -1).all()
    F = fundamental_from_pose(np.eye(3), np.eye(3), np.eye(3), np.array([1.0, 0.0, 0.0]))
    mp = nn_ratio_mutual(p0["descriptors"], p1["descriptors"])
    mf = nn_ratio_mutual(f0["descriptors"], f1["descriptors"])
    ok_p = correct_matches(F, p0["keypoints"], p1["keypoints"], mp)
    ok_f = correct_matches(F, f0["keypoints"], f1["keypoints"], mf)
    got = pair_sources(mp, mf, i0, i1, (n, n), ok_p, ok_f)
    assert got == expected
    # without a geometry nothing is called correct; sums count correctness where known
    plain_only = pair_sources(mp, mf, i0, i1, (n, n))
    assert plain_only.correct is None and plain_only.kept == 28
    assert (plain_only + plain_only).correct is None
    total = plain_only + got
    assert total.kept == 56 and total.correct == 29 and total.plain_correct == 30
    assert (got + got).correct == 58


def test_match_sources_script_with_a_reference_model(tmp_path):
    """The script's run() on the same scene, correctness from a COLMAP model whose second
    camera is translated along x (epipolar lines are the rows of both images)."""
    plain, feats, expected = _scene()
    rec = pycolmap.Reconstruction()
    cam = pycolmap.Camera(model="PINHOLE", width=640, height=480, params=[500, 500, 320, 240])
    cam.camera_id = 1
    rec.add_camera_with_trivial_rig(cam)
    for k, name in enumerate(plain):
        im = pycolmap.Image(name=name, camera_id=1, image_id=k + 1)
        pose = pycolmap.Rigid3d(pycolmap.Rotation3d(np.eye(3)), np.array([-k * 1.0, 0.0, 0.0]))
        rec.add_image_with_trivial_frame(im, pose)
    rec.write(tmp_path)
    script = load_script("match_sources")

    def stored(fs):  # as feature files hold them: descriptors (D, N)
        return {k: dict(v, descriptors=v["descriptors"].T) for k, v in fs.items()}

    result = script.run(
        stored(plain),
        {"plus": stored(feats)},
        [("im0.jpg", "im1.jpg")],
        script.Reference(tmp_path),
        0.8,
    )
    assert result["totals"]["plus"] == expected
    assert result["keypoints"]["plus"] == 84 / 80
    table = script.markdown(result, 1)
    assert "| plus | 1.050x | 30 | 28 (93.3 %) | 1 | 1 | 0 | 2 (1) | 29 vs 30 |" in table


def test_match_sources_script_names_a_file_missing_an_image(tmp_path, capsys):
    from rectified_colmap.features import Features
    from rectified_colmap.io.hloc_h5 import HlocFeatureWriter

    rng = np.random.default_rng(3)
    feats = Features(
        rng.uniform(0, 100, (20, 2)),
        np.tile(np.eye(2), (20, 1, 1)) * 2.0,
        rng.integers(0, 256, (20, 128)).astype(np.uint8),
        np.full(20, -1, np.int32),
    )
    plain, other = tmp_path / "sift.h5", tmp_path / "plus.h5"
    with HlocFeatureWriter(plain) as w:
        w.write("a.jpg", feats, (100, 100))
        w.write("b.jpg", feats, (100, 100))
    with HlocFeatureWriter(other) as w:
        w.write("a.jpg", feats, (100, 100))
    script = load_script("match_sources")
    assert script.main(["--plain", str(plain), "--features", f"plus={other}"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(other) in err[0] and "b.jpg" in err[0]
    assert script.main(["--plain", str(tmp_path / "none.h5"), "--features", f"plus={other}"]) == 2
