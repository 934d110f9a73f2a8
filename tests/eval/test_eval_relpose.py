"""Relative-pose evaluation: pair files, matching, metrics, report, CLI.

Scenes are synthetic features: 3D points seen by posed cameras, each point with its own
random descriptor (+ noise), so the expected matches and poses are known exactly."""

import numpy as np
import pytest

from rectified_colmap.eval.config import EvalConf
from rectified_colmap.eval import report
from rectified_colmap.eval.matching import FeatureSource, match_ratio
from rectified_colmap.eval.pairs import (
    Pair,
    format_pair_line,
    parse_pair_line,
    read_pairs_with_gt,
    read_strong_viewpoint_changes,
    rotation_angle_deg,
    write_pairs_with_gt,
)
from rectified_colmap.eval.relpose import (
    evaluate_pairs,
    fundamental_from_pose,
    pose_errors,
    sampson_error,
)

K = np.array([[300.0, 0, 160], [0, 300.0, 120], [0, 0, 1]])


def rot(axis, deg):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    a = np.radians(deg)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(a) * k + (1 - np.cos(a)) * k @ k


def orbit_pose(deg, radius=6.0):
    """cam_from_world of a camera on a circle around the origin (y axis), looking at it."""
    R = rot([0, 1, 0], deg)  # world -> camera rotation
    c = np.array([np.sin(np.radians(deg)), 0, -np.cos(np.radians(deg))]) * radius
    return R, -R @ c


def synthetic_scene(angles, n_points=600, noise_px=0.3, distractors=200, seed=0):
    """-> (features by name, poses by name). Points in a 3x3x3 box around the origin."""
    rng = np.random.default_rng(seed)
    X = rng.uniform(-1.5, 1.5, (n_points, 3))
    base = rng.standard_normal((n_points, 128)).astype(np.float32)
    feats, poses = {}, {}
    for k, a in enumerate(angles):
        R, t = orbit_pose(a)
        Xc = X @ R.T + t
        x = Xc @ K.T
        x = x[:, :2] / x[:, 2:]
        vis = (Xc[:, 2] > 0) & (x[:, 0] > 0) & (x[:, 0] < 320) & (x[:, 1] > 0) & (x[:, 1] < 240)
        idx = np.nonzero(vis)[0]
        kp = x[idx] + rng.normal(0, noise_px, (len(idx), 2))
        d = base[idx] + 0.15 * rng.standard_normal((len(idx), 128)).astype(np.float32)
        kp = np.concatenate([kp, rng.uniform([0, 0], [320, 240], (distractors, 2))])
        d = np.concatenate([d, rng.standard_normal((distractors, 128)).astype(np.float32)])
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        name = f"cam{k}.jpg"
        feats[name] = {"keypoints": kp, "descriptors": d.T.copy(), "point_ids": idx}
        poses[name] = (R, t)
    return feats, poses


def make_pairs(poses, names):
    out = []
    for i, a in enumerate(names):
        for b in names[i + 1 :]:
            (Ra, ta), (Rb, tb) = poses[a], poses[b]
            T = np.eye(4)
            T[:3, :3] = Rb @ Ra.T
            T[:3, 3] = tb - Rb @ Ra.T @ ta
            out.append(Pair(a, b, K, K, T))
    return out


def test_pair_file_roundtrip_and_errors(tmp_path):
    T = np.eye(4)
    T[:3, :3] = rot([0.2, 1, 0.1], 37)
    T[:3, 3] = [1, 2, 3]
    p = Pair("a/0.jpg", "a/1.jpg", K, 2 * K, T)
    f = tmp_path / "pairs.txt"
    write_pairs_with_gt(f, [p, p])
    back = read_pairs_with_gt(f)
    assert len(back) == 2 and back[0].name1 == "a/1.jpg"
    np.testing.assert_allclose(back[0].T_0to1, T, atol=1e-8)
    np.testing.assert_allclose(back[0].K1, 2 * K)
    assert back[0].rotation_deg == pytest.approx(37, abs=1e-6)
    bad = format_pair_line(p).split()
    with pytest.raises(ValueError, match="38 fields"):
        parse_pair_line(" ".join(bad[:-1]), "x.txt:3")
    bad[2] = "90"
    with pytest.raises(ValueError, match="EXIF rotations"):
        parse_pair_line(" ".join(bad), "x.txt:3")
    (tmp_path / "empty.txt").write_text("# nothing\n")
    with pytest.raises(ValueError, match="empty.txt: no pairs"):
        read_pairs_with_gt(tmp_path / "empty.txt")


def test_svc_reader_bins_by_rotation(tmp_path):
    T = np.eye(4)
    T[:3, :3] = rot([0, 1, 0], 95)
    (tmp_path / "sceneA").mkdir()
    write_pairs_with_gt(
        tmp_path / "sceneA" / "pairs_with_gt.txt", [Pair("i/0.jpg", "i/1.jpg", K, K, T)]
    )
    (tmp_path / "junk").mkdir()
    pairs = read_strong_viewpoint_changes(tmp_path)
    assert [(p.name0, p.category) for p in pairs] == [("sceneA/i/0.jpg", "90-100")]


def test_match_ratio_exact_and_mutual():
    rng = np.random.default_rng(1)
    d1 = rng.standard_normal((300, 128)).astype(np.float32)
    perm = rng.permutation(300)[:100]
    d0 = d1[perm] + 0.05 * rng.standard_normal((100, 128)).astype(np.float32)
    m = match_ratio(d0, d1, 0.8)
    assert len(m) == 100 and np.array_equal(d1[m[:, 1]].argmax(1), d1[perm].argmax(1))
    np.testing.assert_array_equal(m[:, 1], perm)
    # an ambiguous descriptor (two equal neighbours) fails the ratio test
    d1b = np.concatenate([d1, d1[perm[:1]]])
    m2 = match_ratio(d0, d1b, 0.8)
    assert 0 not in m2[:, 0] and len(m2) == 99
    # mutual: two queries with the same nearest neighbour -> only the closer one survives
    q = np.stack([d1[5] + 0.01, d1[5] + 0.2])
    assert len(match_ratio(q, d1, 0.99, mutual=False)) == 2
    assert match_ratio(q, d1, 0.99, mutual=True).tolist() == [[0, 5]]


def test_sampson_and_pose_errors():
    R, t = rot([1, 2, 3], 30), np.array([1.0, 0.2, 0.1])
    F = fundamental_from_pose(K, K, R, t)
    X = np.random.default_rng(2).uniform(-1, 1, (50, 3)) + [0, 0, 5]
    x0 = X @ K.T
    X1 = X @ R.T + t
    x1 = X1 @ K.T
    x0, x1 = x0[:, :2] / x0[:, 2:], x1[:, :2] / x1[:, 2:]
    assert sampson_error(F, x0, x1).max() < 1e-6
    # moving x1 along the epipolar line keeps the error ~0; across it, it grows
    ep = np.concatenate([x0, np.ones((50, 1))], 1) @ F.T
    n = ep[:, :2] / np.linalg.norm(ep[:, :2], axis=1, keepdims=True)
    along = np.stack([-n[:, 1], n[:, 0]], 1)
    assert sampson_error(F, x0, x1 + 20 * along).max() < 1e-6
    assert sampson_error(F, x0, x1 + 20 * n).min() > 5
    r, te = pose_errors(rot([0, 0, 1], 3) @ R, -t, R, t)  # t sign flip is folded
    assert r == pytest.approx(3, abs=1e-6) and te == pytest.approx(0, abs=1e-5)
    assert rotation_angle_deg(rot([1, 0, 0], 170)) == pytest.approx(170)


def test_pose_auc_uniform_errors():
    e = np.linspace(0, 10, 100001)
    auc = report.pose_auc(e, (5, 10, 20))
    np.testing.assert_allclose(auc, [0.25, 0.5, 0.75], atol=1e-3)
    assert report.pose_auc(np.full(10, 180.0), (5,)) == [0.0]


def test_evaluate_pairs_synthetic(tmp_path):
    angles = [0, 20, 45, 85]  # pair rotations 20 45 85 25 65 40; the last one gets a wrong GT (70)
    feats, poses = synthetic_scene(angles)
    names = sorted(feats)
    pairs = make_pairs(poses, names)
    # a wrong ground truth for the last pair: rotated by 30 degrees more
    bad = pairs[-1]
    T = bad.T_0to1.copy()
    T[:3, :3] = rot([0, 1, 0], 30) @ T[:3, :3]
    pairs[-1] = Pair(bad.name0, bad.name1, K, K, T)
    recs = evaluate_pairs(pairs, {"synth": feats}, EvalConf(), num_workers=1, progress=False)
    assert len(recs) == len(pairs)
    for p, r in zip(pairs[:-1], recs[:-1]):
        common = len(np.intersect1d(feats[p.name0]["point_ids"], feats[p.name1]["point_ids"]))
        assert r["success"] and r["R_err"] < 0.5, r
        assert r["gt_rot"] == pytest.approx(rotation_angle_deg(p.R))
        assert 0.9 * common <= r["num_correct"] <= common + 5
        assert r["epipolar_success"]
    assert not recs[-1]["success"] and recs[-1]["R_err"] > 25
    assert recs[-1]["num_correct"] < 0.5 * recs[-1]["num_matches"]  # follows the (wrong) GT
    md = report.markdown_table(recs, 30.0)
    assert "| synth | 6 | 83.3 |" in md and "| 60-90 | 3 | 66.7 | " in md
    report.write_csv(tmp_path / "r.csv", recs)
    back = report.read_csv(tmp_path / "r.csv")
    assert [r["success"] for r in back] == [r["success"] for r in recs]


def test_evaluate_pairs_workers_and_h5(tmp_path):
    """Same numbers through an hloc h5 file and two worker processes."""
    import h5py

    feats, poses = synthetic_scene([0, 30, 60], n_points=300, distractors=50, seed=3)
    path = tmp_path / "feats.h5"
    with h5py.File(path, "w") as f:
        for n, d in feats.items():
            g = f.create_group(f"sub/{n}")
            g["keypoints"] = (d["keypoints"] - 0.5).astype(np.float32)  # hloc convention
            g["descriptors"] = d["descriptors"].astype(np.float16)
            g["image_size"] = np.array([320, 240])
    mapped = {f"sub/{n}": d for n, d in feats.items()}
    pairs = [
        Pair("sub/" + p.name0, "sub/" + p.name1, p.K0, p.K1, p.T_0to1)
        for p in make_pairs(poses, sorted(feats))
    ]
    a = evaluate_pairs(pairs, {"h5": path}, num_workers=2, progress=False)
    b = evaluate_pairs(pairs, {"mem": mapped}, num_workers=1, progress=False)
    assert [r["num_correct"] for r in a] == pytest.approx([r["num_correct"] for r in b], abs=3)
    assert all(r["success"] for r in a)
    assert FeatureSource(path)["sub/cam0.jpg"]["keypoints"] == pytest.approx(
        feats["cam0.jpg"]["keypoints"], abs=1e-3
    )
    with pytest.raises(ValueError, match="no features for 1 image"):
        evaluate_pairs(
            pairs + [Pair("sub/x.jpg", "sub/cam0.jpg", K, K, np.eye(4))],
            {"h5": path},
            progress=False,
        )


def test_cli_evaluate_pairs(tmp_path, capsys):
    pytest.importorskip("matplotlib")
    import h5py

    from rectified_colmap.cli import main

    feats, poses = synthetic_scene([0, 25, 50], n_points=300, distractors=50, seed=4)
    for method in ("a", "b"):
        with h5py.File(tmp_path / f"{method}.h5", "w") as f:
            for n, d in feats.items():
                g = f.create_group(n)
                g["keypoints"] = (d["keypoints"] - 0.5).astype(np.float32)
                g["descriptors"] = d["descriptors"].astype(np.float32)
    write_pairs_with_gt(tmp_path / "pairs.txt", make_pairs(poses, sorted(feats)))
    rc = main(
        [
            "evaluate-pairs",
            "--pairs",
            str(tmp_path / "pairs.txt"),
            "--features",
            f"a={tmp_path / 'a.h5'}",
            f"b={tmp_path / 'b.h5'}",
            "--output_dir",
            str(tmp_path / "out"),
            "--bin_deg",
            "30",
            "--no_progress",
        ]
    )
    assert rc == 0
    md = (tmp_path / "out" / "summary.md").read_text()
    assert "| a | 3 | 100.0 |" in md and "| b | 3 | 100.0 |" in md
    # three RANSAC runs per pair: the mean success column; zero runs: a one-line error
    args = ["evaluate-pairs", "--pairs", str(tmp_path / "pairs.txt"), "--no_plot"]
    args += ["--features", f"a={tmp_path / 'a.h5'}", "--no_progress", "--output_dir"]
    assert main(args + [str(tmp_path / "o3"), "--ransac_runs", "3"]) == 0
    md = (tmp_path / "o3" / "summary.md").read_text()
    assert "success, mean of 3 RANSAC runs %" in md and "| a | 3 | 100.0 | 100.0 |" in md
    assert main(args + [str(tmp_path / "o4"), "--ransac_runs", "0"]) == 2
    assert not (tmp_path / "o4").exists()
    png = (tmp_path / "out" / "success.png").read_bytes()
    assert png[:4] == b"\x89PNG" and len(png) > 5000
    rc = main(
        [
            "evaluate-pairs",
            "--pairs",
            str(tmp_path / "pairs.txt"),
            "--features",
            f"a={tmp_path / 'missing.h5'}",
            "--output_dir",
            str(tmp_path / "o2"),
        ]
    )
    assert rc == 2 and "is not a file" in capsys.readouterr().err


def test_svc_reader_from_model_and_pair_selection(tmp_path):
    import pycolmap

    rec = pycolmap.Reconstruction()
    cam = pycolmap.Camera(model="PINHOLE", width=320, height=240, params=[300, 300, 160, 120])
    cam.camera_id = 1
    rec.add_camera_with_trivial_rig(cam)
    for i, a in enumerate([0, 35, 100], 1):
        R, t = orbit_pose(a)
        rec.add_image_with_trivial_frame(
            pycolmap.Image(name=f"{i}.jpg", camera_id=1, image_id=i),
            pycolmap.Rigid3d(pycolmap.Rotation3d(R), t),
        )
    (tmp_path / "s1" / "sparse").mkdir(parents=True)
    rec.write_text(str(tmp_path / "s1" / "sparse"))
    (tmp_path / "s1" / "pairs.txt").write_text("1.jpg 3.jpg hard\n")
    pairs = read_strong_viewpoint_changes(tmp_path)
    assert len(pairs) == 1 and pairs[0].category == "hard"
    assert (pairs[0].name0, pairs[0].name1) == ("s1/1.jpg", "s1/3.jpg")
    assert pairs[0].rotation_deg == pytest.approx(100, abs=1e-6)
    (tmp_path / "s1" / "pairs.txt").unlink()
    cats = sorted(p.category for p in read_strong_viewpoint_changes(tmp_path))
    assert cats == ["100-110", "30-40", "60-70"]


def test_binomial_p_exact():
    from math import comb

    assert report.binomial_two_sided_p(0, 0) == 1.0
    assert report.binomial_two_sided_p(0, 5) == pytest.approx(2 / 32)
    assert report.binomial_two_sided_p(5, 5) == pytest.approx(2 / 32)
    assert report.binomial_two_sided_p(3, 6) == 1.0
    assert report.binomial_two_sided_p(1, 10) == pytest.approx(2 * (1 + comb(10, 1)) / 1024)


def test_paired_comparison_counts_discordant_pairs():
    def rec(method, i, rot, success, correct):
        return {
            "name0": f"a{i}",
            "name1": f"b{i}",
            "method": method,
            "gt_rot": rot,
            "success": success,
            "num_correct": correct,
        }

    recs = []
    for i in range(12):  # bin 0-10: both solve; bin 60-70: the method solves 6 more
        recs.append(rec("base", i, 5.0 if i < 6 else 65.0, i < 6, 100))
        recs.append(rec("new", i, 5.0 if i < 6 else 65.0, True, 100 + (i >= 6) * 50 - (i == 0)))
    recs.append(rec("base", 99, 65.0, True, 10))  # a pair the new method lacks: ignored
    rows = {r["bin"]: r for r in report.paired_comparison(recs, "base", 10.0)}
    allr, b0, b6 = rows[None], rows[(0.0, 10.0)], rows[(60.0, 70.0)]
    assert (allr["pairs"], allr["wins"], allr["losses"]) == (12, 6, 0)
    assert allr["p_success"] == pytest.approx(2 / 64)
    assert (b0["wins"], b0["losses"], b0["p_success"]) == (0, 0, 1.0)
    assert (b0["more"], b0["fewer"]) == (0, 1)
    assert (b6["more"], b6["fewer"], b6["median_ratio"]) == (6, 0, 1.5)
    md = report.paired_markdown(recs, "base", 10.0)
    assert "| new | all | 12 | 6 | 0 | **0.031** |" in md
    with pytest.raises(ValueError, match="baseline"):
        report.paired_comparison(recs, "nope")


def test_tables_by_viewpoint_change(tmp_path):
    def rec(method, i, rot, view, success, correct):
        return {
            "name0": f"a{i}",
            "name1": f"b{i}",
            "method": method,
            "gt_rot": rot,
            "viewpoint": view,
            "category": None,
            "success": success,
            "epipolar_success": success,
            "num_kp0": 10,
            "num_kp1": 10,
            "num_matches": correct,
            "num_inliers": correct,
            "num_correct": correct,
            "num_inliers_correct": correct,
            "R_err": 1.0,
            "t_err": 1.0,
            "pose_err": 1.0,
        }

    # small rotations, but pairs 4-7 see the scene from 45 degrees apart; pair 8 unknown
    recs = []
    for i in range(9):
        view = None if i == 8 else (45.0 if i >= 4 else 5.0)
        recs.append(rec("base", i, 3.0, view, True, 100))
        recs.append(rec("new", i, 3.0, view, True, 100 + 10 * (4 <= i < 8)))
    known = report.with_field(recs, "viewpoint")
    assert len(known) == 16
    rows = {r["bin"]: r for r in report.paired_comparison(known, "base", 10.0, "viewpoint")}
    assert (rows[(40.0, 50.0)]["more"], rows[(40.0, 50.0)]["pairs"]) == (4, 4)
    assert (rows[(0.0, 10.0)]["more"], rows[(0.0, 10.0)]["fewer"]) == (0, 0)
    md = report.markdown_table(known, 10.0, by="viewpoint")
    assert "| viewpoint change (deg) | pairs |" in md and "| 40-50 | 4 |" in md
    assert "viewpoint change (deg)" in report.paired_markdown(known, "base", 10.0, "viewpoint")

    report.write_outputs(recs, tmp_path, EvalConf(), plot=False)
    text = (tmp_path / "summary.md").read_text()
    assert "By viewpoint change (8 pairs with 3D points)" in text
    back = report.read_csv(tmp_path / "records.csv")
    assert [r["viewpoint"] for r in back[:2]] == [5.0, 5.0] and back[-1]["viewpoint"] is None
    # files without the column (older runs) read as unknown viewpoints
    lines = (tmp_path / "records.csv").read_text().splitlines()
    col = lines[0].split(",").index("viewpoint")
    strip = lambda line: ",".join(v for k, v in enumerate(line.split(",")) if k != col)  # noqa: E731
    (tmp_path / "old.csv").write_text("\n".join(strip(line) for line in lines) + "\n")
    assert all(r["viewpoint"] is None for r in report.read_csv(tmp_path / "old.csv"))
    report.write_outputs(report.read_csv(tmp_path / "old.csv"), tmp_path / "o", EvalConf(), False)
    assert "By viewpoint" not in (tmp_path / "o" / "summary.md").read_text()


def test_ransac_runs_take_the_median_and_count_successes():
    """With ``ransac_runs`` k, a pair's pose errors and inliers are the medians of the k
    single runs (seeds 0..k-1), ``success`` is the majority's and ``success_rate`` the
    fraction; on a marginal pair (about 9 correct matches among 30 wrong ones) the runs
    disagree, which one seed cannot show."""
    from dataclasses import replace

    from rectified_colmap.eval.relpose import evaluate_matches

    feats, poses = synthetic_scene([0, 40], distractors=0, seed=1)
    names = sorted(feats)
    pair = make_pairs(poses, names)[0]
    f0, f1 = feats[names[0]], feats[names[1]]
    _, i0, i1 = np.intersect1d(f0["point_ids"], f1["point_ids"], return_indices=True)
    k, mixed = 5, 0
    for n_true in (9, 10):
        rng = np.random.default_rng(1)
        wrong = rng.integers(0, [len(f0["keypoints"]), len(f1["keypoints"])], (30, 2))
        m = np.concatenate([np.stack([i0[:n_true], i1[:n_true]], 1), wrong])
        ev = lambda m=m, **kw: evaluate_matches(  # noqa: E731
            pair, f0["keypoints"], f1["keypoints"], m, replace(EvalConf(), **kw)
        )
        single = [ev(ransac_seed=s) for s in range(k)]
        both = ev(ransac_runs=k)
        assert both["R_err"] == pytest.approx(np.median([r["R_err"] for r in single]))
        assert both["t_err"] == pytest.approx(np.median([r["t_err"] for r in single]))
        assert both["num_inliers"] == int(np.median([r["num_inliers"] for r in single]))
        rate = np.mean([r["success"] for r in single])
        assert both["success_rate"] == pytest.approx(rate)
        assert both["success"] == (rate > 0.5)
        assert single[0]["success_rate"] == float(single[0]["success"])
        mixed += 0 < rate < 1
    assert mixed  # some pair's runs disagree
    rec = {"name0": "a", "name1": "b", "method": "m", "gt_rot": 40.0, "category": None}
    md = report.markdown_table([{**rec, **both}], ransac_runs=k)
    assert f"success, mean of {k} RANSAC runs %" in md
    assert "RANSAC runs" not in report.markdown_table([{**rec, **both}])
