"""scripts/eval_sparse_sfm.py: the pose alignment and errors, the subsets, the database
subsets and the table exactly; one small run of the COLMAP command line on a rendered
street (skipped without ``colmap``)."""

import argparse
import json
import shutil
import sqlite3

import cv2
import numpy as np
import pycolmap
import pytest

from rectified_colmap_research.evaluation import colmap_sfm
from scripts_util import load_script

from rectified_colmap.errors import run_script
from rectified_colmap.io.colmap_db import create_database
from tests.scenes import street_orbit

script = load_script("eval_sparse_sfm")


def _rotvec(v_deg) -> np.ndarray:
    """(..., 3) rotation vectors in degrees -> (..., 3, 3) rotation matrices (Rodrigues)."""
    v = np.deg2rad(np.asarray(v_deg, np.float64))
    flat = [cv2.Rodrigues(x.reshape(3, 1))[0] for x in v.reshape(-1, 3)]
    return np.array(flat).reshape(v.shape[:-1] + (3, 3))


def _about_z(deg) -> np.ndarray:
    """(N, 1) angles in degrees -> (N, 3, 3) rotations about the z axis."""
    return _rotvec(np.asarray(deg, np.float64) * [0.0, 0.0, 1.0])


def _random_rotations(rng, n) -> np.ndarray:
    """n rotations drawn uniformly (QR of Gaussian matrices, signs fixed: Haar measure)."""
    q, r = np.linalg.qr(rng.normal(size=(n, 3, 3)))
    q = q * np.sign(np.diagonal(r, axis1=1, axis2=2))[:, None, :]
    q[np.linalg.det(q) < 0, :, 0] *= -1
    return q


def _cameras(rng, n, centres=None):
    """n random cam_from_world rotations and centres (random, or the given ones)."""
    R = _random_rotations(rng, n)
    c = rng.normal(size=(n, 3)) * [3.0, 2.0, 1.0] if centres is None else np.asarray(centres)
    return R, c


def _similar(R_ref, c_ref, s, R, t):
    """The cameras in a world where ``x_ref = s R x + t``."""
    return R_ref @ R, (c_ref - t) @ R / s


# x, then y, then z turns about fixed axes
SIM = (2.5, _rotvec([0, 0, 110]) @ _rotvec([0, -70, 0]) @ _rotvec([30, 0, 0]), [4, -1, 7])


def test_a_similarity_transform_of_the_reference_has_no_error():
    rng = np.random.default_rng(0)
    for centres in (None, np.outer(np.arange(5.0), [1.0, 0.5, 0.0])):  # also on a line
        R_ref, c_ref = _cameras(rng, 7 if centres is None else 5, centres)
        rot, pos = script.pose_errors(*_similar(R_ref, c_ref, *SIM), R_ref, c_ref)
        np.testing.assert_allclose(rot, 0, atol=1e-5)
        np.testing.assert_allclose(pos, 0, atol=1e-9)
    rot, pos = script.pose_errors(*_similar(R_ref[:2], c_ref[:2], *SIM), R_ref[:2], c_ref[:2])
    assert np.allclose(rot, 0, atol=1e-5) and np.allclose(pos, 0, atol=1e-9)


def test_rotation_perturbations_come_back_exactly():
    """World-frame turns in +-pairs about two axes (their chordal mean is no turn): each
    camera's rotation error is its angle, the centres stay exact."""
    rng = np.random.default_rng(1)
    R_ref, c_ref = _cameras(rng, 5)
    R_est, c_est = _similar(R_ref, c_ref, *SIM)
    a, b = [1.0, 2.0, 2.0], [0.0, 1.0, -3.0]
    vecs = np.array([a, a, b, b, a]) / np.linalg.norm([a, a, b, b, a], axis=1, keepdims=True)
    angles = np.array([7.0, -7.0, 30.0, -30.0, 0.0])
    P = _rotvec(vecs * angles[:, None])
    rot, pos = script.pose_errors(R_ref @ P @ SIM[1], c_est, R_ref, c_ref)
    np.testing.assert_allclose(rot, np.abs(angles), atol=1e-5)
    np.testing.assert_allclose(pos, 0, atol=1e-9)


def test_position_perturbations_that_leave_the_fit_unchanged_come_back_exactly():
    """Reference centres on a square, lifted by +d on one diagonal and -d on the other: the
    least-squares scale and translation are the unperturbed ones, so every camera is off by
    exactly d."""
    a, d = 2.0, 0.3
    square = np.array([[a, 0, 0], [-a, 0, 0], [0, a, 0], [0, -a, 0]], float)
    R_ref, _ = _cameras(np.random.default_rng(2), 4, square)
    R_est, c_est = _similar(R_ref, square, *SIM)
    lifted = square + np.array([[0, 0, d], [0, 0, d], [0, 0, -d], [0, 0, -d]])
    rot, pos = script.pose_errors(R_est, c_est, R_ref, lifted)
    np.testing.assert_allclose(pos, d, atol=1e-9)
    np.testing.assert_allclose(rot, 0, atol=1e-5)
    assert script.centre_spread(square) == pytest.approx(a)


def test_nearest_view_angle():
    R = _about_z([[0], [10], [30], [70]])
    # nearest: 10, 10, 20, 40 -> median 15
    assert script.nearest_neighbour_deg(R) == pytest.approx(15.0)
    assert np.isnan(script.nearest_neighbour_deg(R[:1]))


def test_subsets():
    names = [f"{i:04d}.jpg" for i in (5, 3, 9, 0, 1, 2, 4, 6, 7, 8)]
    assert script.subset_names(names, "0::1") == sorted(names)
    assert script.subset_names(names, "0::2") == [f"{i:04d}.jpg" for i in (0, 2, 4, 6, 8)]
    assert script.subset_names(names, "1::2") == [f"{i:04d}.jpg" for i in (1, 3, 5, 7, 9)]
    assert script.subset_names(names, "0::3") == [f"{i:04d}.jpg" for i in (0, 3, 6, 9)]
    assert script.subset_label("0::1") == "all" and script.subset_label("1::2") == "1::2"
    for bad in ("2", "0:2", "a::2", "0::0", "-1::2"):
        with pytest.raises(ValueError):
            script.parse_subset(bad)


def test_find_sets(tmp_path):
    """Strecha scenes with their GT camera and subsets; real-pool sets with a model, every
    second image only from --real_subset_min_images on, with the --ImageReader flags."""
    rec = pycolmap.Reconstruction()
    cam = pycolmap.Camera(model="PINHOLE", width=40, height=30, params=[50, 51, 20, 15])
    cam.camera_id = 1
    rec.add_camera_with_trivial_rig(cam)
    (tmp_path / "strecha" / "s1" / "images").mkdir(parents=True)
    (tmp_path / "strecha" / "s1" / "sparse").mkdir()
    rec.write_text(str(tmp_path / "strecha" / "s1" / "sparse"))
    (tmp_path / "strecha" / "no_model" / "images").mkdir(parents=True)
    for name, n in (("big", 4), ("small", 3), ("single", 5)):
        (tmp_path / "real" / name / "images").mkdir(parents=True)
        for i in range(n):
            (tmp_path / "real" / name / "images" / f"{i}.jpg").write_bytes(b"")
        if name != "single":
            (tmp_path / "real" / name / "colmap_sparse").mkdir()
    args = argparse.Namespace(
        strecha=str(tmp_path / "strecha"),
        real_pool=str(tmp_path / "real"),
        subsets=["0::1", "0::3"],
        real_subsets=["0::2"],
        real_subset_min_images=4,
        reader=["--ImageReader.single_camera", "1"],
        sets=None,
    )
    sets = {s.name: s for s in script.find_sets(args)}
    assert list(sets) == ["s1", "big", "small"]
    assert sets["s1"].ground_truth and sets["s1"].subsets == ["0::1", "0::3"]
    assert "50.000000,51.000000,20.000000,15.000000" in sets["s1"].camera
    assert sets["big"].subsets == ["0::1", "0::2"] and sets["small"].subsets == ["0::1"]
    assert sets["big"].camera == ["--ImageReader.single_camera", "1"]
    assert not sets["big"].ground_truth
    args.sets = ["small", "nope"]
    with pytest.raises(ValueError, match="no such set nope"):
        script.find_sets(args)


def test_colmap_flags():
    flags = script.colmap_flags(["--Mapper.a", "0", "--ImageReader.single_camera=1"])
    assert flags == {
        "Mapper": ["--Mapper.a", "0"],
        "ImageReader": ["--ImageReader.single_camera", "1"],
    }
    for bad in (
        ["--foo", "1"],
        ["--Mapper", "1"],
        ["--Mapper.a"],
        ["--Mapper.a", "--Mapper.b", "1"],
    ):
        with pytest.raises(ValueError):
            script.colmap_flags(bad)


def test_run_allows_the_mappers_no_model_failure(tmp_path):
    """colmap mapper exits 1 when it finds no model: 0 registered images, not an error."""
    log = tmp_path / "log.txt"
    cmd = ["sh", "-c", "echo 'ERROR: failed to create sparse model'; exit 1"]
    assert colmap_sfm.run(cmd, log, allow="failed to create sparse model") >= 0
    with pytest.raises(RuntimeError, match="sh -c failed"):
        colmap_sfm.run(cmd, log)
    with pytest.raises(RuntimeError):  # the allowed text must be in this command's output
        colmap_sfm.run(["sh", "-c", "exit 1"], log, allow="failed to create sparse model")


def test_keep_images(tmp_path):
    """A subset's database: the other images, their features, matches and unused cameras go."""
    db = tmp_path / "d.db"
    create_database(db)
    with sqlite3.connect(db) as con:
        for cid in (1, 2, 3):
            con.execute(
                "INSERT INTO cameras VALUES (?, 1, 10, 10, ?, 0)",
                (cid, np.zeros(4).tobytes()),
            )
        for iid, cid in ((1, 1), (2, 2), (3, 3), (4, 3)):
            con.execute(
                "INSERT INTO images (image_id, name, camera_id) VALUES (?, ?, ?)",
                (iid, f"{iid}.jpg", cid),
            )
            for table in ("keypoints", "descriptors"):
                con.execute(f"INSERT INTO {table} (image_id, rows, cols) VALUES (?, 0, 0)", (iid,))
        con.execute("INSERT INTO matches (pair_id, rows, cols) VALUES (1, 0, 0)")
    script.keep_images(db, ["1.jpg", "3.jpg"])
    with sqlite3.connect(db) as con:
        assert [r[0] for r in con.execute("SELECT name FROM images ORDER BY name")] == [
            "1.jpg",
            "3.jpg",
        ]
        assert [r[0] for r in con.execute("SELECT image_id FROM keypoints")] == [1, 3]
        assert [r[0] for r in con.execute("SELECT image_id FROM descriptors")] == [1, 3]
        assert [r[0] for r in con.execute("SELECT camera_id FROM cameras")] == [1, 3]
        assert con.execute("SELECT COUNT(*) FROM matches").fetchone()[0] == 0


def test_copy_database_keeps_what_is_still_in_the_wal_file(tmp_path):
    """COLMAP's databases are in WAL mode: while any connection is open, another process's
    writes stay in the -wal file, which a file copy misses (the first full run lost the
    features of the last images so); the backup API copies them."""
    db = tmp_path / "d.db"
    create_database(db)
    writer = sqlite3.connect(db)
    assert writer.execute("PRAGMA journal_mode=WAL").fetchone()[0] == "wal"
    holder = sqlite3.connect(db)  # another reader, left open
    holder.execute("SELECT COUNT(*) FROM images").fetchone()
    with writer:
        writer.execute("INSERT INTO cameras VALUES (1, 1, 10, 10, NULL, 0)")
        writer.execute("INSERT INTO images (image_id, name, camera_id) VALUES (1, 'a.jpg', 1)")
    writer.close()
    assert (tmp_path / "d.db-wal").stat().st_size > 0
    shutil.copy(db, tmp_path / "file_copy.db")
    script.copy_database(db, tmp_path / "copy.db")
    holder.close()
    for name, n in (("file_copy.db", 0), ("copy.db", 1)):
        con = sqlite3.connect(tmp_path / name)
        assert con.execute("SELECT COUNT(*) FROM images").fetchone()[0] == n, name
        con.close()


def _row(method, run, registered, points, **kw):
    r = {
        "set": "A",
        "subset": "all",
        "reference": "GT",
        "method": method,
        "images": 10,
        "neighbour_deg": 10.0,
        "run": run,
        "verified_matches": 5000 if method == "sift" else 5500,
        "verified_pairs": 45,
        "registered": registered,
        "points": points,
        "models": 1,
        "rel_rot_err_med_deg": 0.1,
        "rot_err_med_deg": 0.2,
        "rot_err_max_deg": 0.5,
        "pos_err_med": 0.01,
        "pos_err_max": 0.02,
    }
    return {**r, **kw}


def test_table():
    rows = [
        _row("sift", 0, 10, 1000),
        _row("sift", 1, 10, 1000),
        _row("rectsift", 0, 9, 1040, rot_err_max_deg=0.7),
        _row("rectsift", 1, 10, 1060, rot_err_max_deg=0.9),
        _row("sift", 0, 3, 300, subset="0::3", images=4, verified_matches=100, neighbour_deg=30.0),
        _row(
            "rectsift",
            0,
            0,
            0,
            subset="0::3",
            images=4,
            verified_matches=90,
            **{
                k: float("nan")
                for k in (
                    "rel_rot_err_med_deg",
                    "rot_err_med_deg",
                    "rot_err_max_deg",
                    "pos_err_med",
                    "pos_err_max",
                )
            },
            models=0,
        ),
    ]
    # rows come per method; the table groups them per subset, the first method first
    rows = [rows[i] for i in (0, 1, 4, 2, 3, 5)]
    table = script.markdown(script.summarize(rows))
    lines = table.splitlines()
    assert lines[2] == (
        "| A (GT) | all | 10.0 | sift | 10/10 | 1 | 1000 | 5000 | 45 | 0.10 | 0.20 / 0.50 "
        "| 1.00 / 2.00 |"
    )
    assert lines[3] == (
        "|  |  |  | rectsift | 9.5 (9-10)/10 | 1 | 1050 (+5.0%) | 5500 (+10.0%) | 45 | 0.10 "
        "| 0.20 / 0.80 | 1.00 / 2.00 |"
    )
    assert lines[4].startswith("| A (GT) | 0::3 | 30.0 | sift | 3/4 |")
    assert lines[5] == (
        "|  |  |  | rectsift | 0/4 | 0 | 0 (-100.0%) | 90 (-10.0%) | 45 | - | - / - | - / - |"
    )
    assert lines[6].startswith("| **total** | 2 subsets |  | sift | 13/14 |  | 1300 |")
    assert lines[7].startswith("| **total** | 2 subsets |  | rectsift | 9.5/14 |  | 1050 |")


def test_missing_data_folder_is_one_line(tmp_path, capsys):
    args = ["--output_dir", str(tmp_path / "o"), "--strecha", str(tmp_path / "nope")]
    rc = run_script(lambda: script.main([*args, "--real_pool", "none"]), "eval_sparse_sfm")
    err = capsys.readouterr().err
    assert rc == 2 and err.count("\n") == 1 and "nope: no such folder" in err, err
    assert err.startswith("eval_sparse_sfm: error: --strecha ")
    assert not (tmp_path / "o").exists()


@pytest.mark.skipif(shutil.which("colmap") is None, reason="colmap command line not installed")
def test_rendered_street_end_to_end(tmp_path):
    """A rendered walk written as a Strecha-style scene: COLMAP SIFT and rectified-colmap's
    plain SIFT (--conf sift, same cameras from the COLMAP database) register every image
    with poses near the truth; every second image is a second subset."""
    views = street_orbit(1, num=6, width=480, height=360)
    scene = tmp_path / "data" / "street"
    (scene / "images").mkdir(parents=True)
    (scene / "sparse").mkdir()
    rec = pycolmap.Reconstruction()
    camera = views[0]["camera"]
    camera.camera_id = 1
    rec.add_camera_with_trivial_rig(camera)
    for i, v in enumerate(views):
        name = f"{i:02d}.png"
        cv2.imwrite(str(scene / "images" / name), v["image"][..., ::-1])
        image = pycolmap.Image(name=name, camera_id=1, image_id=i + 1)
        rec.add_image_with_trivial_frame(image, v["pose"])
    rec.write_text(str(scene / "sparse"))
    out = tmp_path / "out"
    args = ["--output_dir", str(out), "--strecha", str(tmp_path / "data"), "--real_pool", "none"]
    args += ["--methods", "sift", "--variant", "plain=sift", "--subsets", "0::1", "0::2"]
    args += ["--Mapper.ba_refine_focal_length=0"]  # passed on to colmap mapper
    assert script.main(args) == 0
    rows = json.loads((out / "sparse_sfm.json").read_text())
    assert [(r["method"], r["subset"], r["images"]) for r in rows] == [
        ("sift", "all", 6),
        ("sift", "0::2", 3),
        ("plain", "all", 6),
        ("plain", "0::2", 3),
    ]
    for r in rows[::2]:
        assert r["registered"] == 6 and r["verified_pairs"] >= 5
        assert r["rot_err_med_deg"] < 0.5 and r["pos_err_med"] < 0.02, r
    with sqlite3.connect(out / "street" / "plain" / "features.db") as con:
        assert con.execute("SELECT COUNT(*) FROM cameras").fetchone()[0] == 1
    assert "| street (GT) | all |" in (out / "sparse_sfm.md").read_text()
    # run again: features and COLMAP's models are reused, the models scored again
    (out / "street" / "all" / "sift" / "log.txt").unlink()
    assert script.main(args) == 0
    assert json.loads((out / "sparse_sfm.json").read_text()) == rows
    assert not (out / "street" / "all" / "sift" / "log.txt").exists()  # no COLMAP call
    # other mapper flags: the matched databases are reused, only the mapper runs again
    assert script.main([*args, "--Mapper.init_min_tri_angle", "8"]) == 0
    log = (out / "street" / "all" / "sift" / "log.txt").read_text()
    assert "$ colmap mapper" in log and "exhaustive_matcher" not in log
    again = json.loads((out / "sparse_sfm.json").read_text())
    flags = "--Mapper.ba_refine_focal_length 0 --Mapper.init_min_tri_angle 8"
    assert [r["mapper_flags"] for r in again] == [flags] * 4
    assert [r["match_s"] for r in again] == [r["match_s"] for r in rows]
    assert again[0]["registered"] == 6
