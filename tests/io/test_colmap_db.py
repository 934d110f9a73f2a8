"""COLMAP database exporter: schema, round trip, rigs/frames, real matching, kill -9, and
(when the ``colmap`` 3.8 command line is installed) cross-version compatibility."""

from __future__ import annotations

import os
import shutil
import signal
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pycolmap
import pytest

from rectified_colmap import conventions
from rectified_colmap.features import Features, similarity_frames
from rectified_colmap.sift import detect_sift
from rectified_colmap.io.colmap_db import PROVENANCE_TABLE, ColmapDatabase, image_ids_to_pair_id

COLMAP = shutil.which("colmap")
needs_colmap = pytest.mark.skipif(COLMAP is None, reason="colmap command line not installed")


def random_features(n: int, seed: int, size=(320, 240)) -> Features:
    rng = np.random.default_rng(seed)
    xy = rng.random((n, 2)) * size
    shapes = similarity_frames(rng.uniform(1, 8, n), rng.uniform(-np.pi, np.pi, n))
    shapes[:, 0, 1] += rng.uniform(-0.5, 0.5, n)  # a real affine frame, not a similarity
    return Features(
        xy,
        shapes,
        rng.integers(0, 256, (n, 128), dtype=np.uint8),
        rng.integers(-1, 3, n).astype(np.int32),
    )


def pinhole(w=320, h=240, f=300.0) -> pycolmap.Camera:
    return pycolmap.Camera(model="SIMPLE_RADIAL", width=w, height=h, params=[f, w / 2, h / 2, 0.01])


def cache_options() -> pycolmap.DatabaseCacheOptions:
    opts = pycolmap.DatabaseCacheOptions()
    opts.load_all_images = True
    opts.min_num_matches = 0
    return opts


def schema(path: Path) -> set[str]:
    con = sqlite3.connect(path)
    try:
        return {r[0] for r in con.execute("SELECT sql FROM sqlite_master") if r[0]}
    finally:
        con.close()


def homography_views(texture, n: int = 3):
    """n overlapping 320x240 views of one texture, image i = warp(big, H_i) (OpenCV px)."""
    big = texture(300, 400, seed=3)
    Hs, ims = [], []
    for i in range(n):
        H = np.array(
            [[1, 0.04 * i, 10.0 * i], [-0.03 * i, 1 + 0.02 * i, 6.0 * i], [1.5e-4 * i, 0, 1]]
        )
        Hs.append(H)
        ims.append(cv2.warpPerspective(big, H, (320, 240), flags=cv2.INTER_LINEAR))
    return ims, Hs


# ---------------------------------------------------------------------------------------


def test_new_database_round_trip_through_pycolmap(tmp_path):
    path = tmp_path / "sub" / "db.db"
    feats = {f"db/im{i}.jpg": random_features(50 + 10 * i, i) for i in range(3)}
    with ColmapDatabase(path) as db:
        cam = pinhole()
        cam_id = db.add_camera(cam, prior_focal_length=True)
        cam2_id = db.add_camera(pinhole(160, 120, 150.0), prior_focal_length=False)
        ids = {
            name: db.add_image(name, cam_id if i < 2 else cam2_id) for i, name in enumerate(feats)
        }
        assert db.find_image("db/im2.jpg") == (ids["db/im2.jpg"], cam2_id)
        assert db.find_image("missing.jpg") is None
        got = db.get_camera(cam_id)
        assert got.model == cam.model and got.camera_id == cam_id
        assert got.has_prior_focal_length and not db.get_camera(cam2_id).has_prior_focal_length
        np.testing.assert_array_equal(got.params, cam.params)
        assert db.find_camera(cam, True) == cam_id and db.find_camera(cam, False) is None
        assert not db.has_features(ids["db/im0.jpg"])
        for name, f in feats.items():
            db.write_features(ids[name], f)
        assert db.image_ids_with_features() == set(ids.values())
        assert not db.uses_frames()
    before = schema(path)

    with pycolmap.Database.open(path) as pdb:
        assert pdb.num_images() == 3 and pdb.num_cameras() == 2
        assert pdb.num_frames() == 0 and pdb.num_rigs() == 0  # none: pycolmap makes them
        for name, f in feats.items():
            im = pdb.read_image_with_name(name)
            kp = pdb.read_keypoints(im.image_id)
            assert kp.shape == (len(f), 6)
            np.testing.assert_array_equal(kp, f.colmap_keypoints())
            d = pdb.read_descriptors(im.image_id)
            assert d.type == pycolmap.FeatureExtractorType.SIFT
            np.testing.assert_array_equal(d.data, f.descriptors)
        c = pdb.read_camera(cam_id)
        assert c.has_prior_focal_length and c.model.name == "SIMPLE_RADIAL"
        cache = pycolmap.DatabaseCache.create(pdb, cache_options())
        assert cache.num_images() == 3 and cache.num_frames() == 3
    assert schema(path) == before, "pycolmap 4.2.1 had to migrate our schema"


def test_overwrite_errors_and_stale_matches(tmp_path):
    path = tmp_path / "db.db"
    with ColmapDatabase(path) as db:
        cam_id = db.add_camera(pinhole(), True)
        a, b = db.add_image("a.jpg", cam_id), db.add_image("b.jpg", cam_id)
        db.write_features(a, random_features(30, 0))
        db.write_features(b, random_features(30, 1))
        with pytest.raises(ValueError, match="already has features"):
            db.write_features(a, random_features(20, 2))
        with pytest.raises(ValueError, match="db.db"):
            db.add_image("a.jpg", cam_id)  # duplicate name
        with pytest.raises(KeyError):
            db.add_image("c.jpg", 99)
        with pytest.raises(KeyError):
            db.write_features(12345, random_features(3, 0))
        bad = random_features(10, 3)
        bad.descriptors = bad.descriptors.astype(np.float32)
        with pytest.raises(ValueError, match="uint8"):
            db.write_features(b, bad, overwrite=True)
        assert len(db.read_keypoints(b)) == 30  # a failed write changes nothing
    # a match row between a and b, then overwrite a: the stale match must go
    with pycolmap.Database.open(path) as pdb:
        pdb.write_matches(a, b, np.array([[0, 1], [2, 3]], np.uint32))
    with ColmapDatabase(path) as db:
        new = random_features(20, 4)
        db.write_features(a, new, overwrite=True)
        np.testing.assert_array_equal(db.read_keypoints(a), new.colmap_keypoints())
        np.testing.assert_array_equal(db.read_descriptors(a), new.descriptors)
        con = db._con
        assert (
            con.execute(
                "SELECT COUNT(*) FROM matches WHERE pair_id = ?", (image_ids_to_pair_id(a, b),)
            ).fetchone()[0]
            == 0
        )
    not_db = tmp_path / "x.db"
    not_db.write_bytes(b"this is not sqlite" * 100)
    with pytest.raises(ValueError, match="x.db"):
        ColmapDatabase(not_db)


def test_rigs_and_frames_all_or_none(tmp_path):
    """Into a pycolmap database that uses rigs/frames, new images get them too."""
    path = tmp_path / "p.db"
    with pycolmap.Database.open(path) as pdb:
        cam = pinhole()
        cam.camera_id = pdb.write_camera(cam)
        rig = pycolmap.Rig()
        rig.add_ref_sensor(cam.sensor_id)
        rig_id = pdb.write_rig(rig)
        im = pycolmap.Image(name="first.jpg", camera_id=cam.camera_id)
        im.image_id = pdb.write_image(im)
        fr = pycolmap.Frame()
        fr.rig_id = rig_id
        fr.add_data_id(im.data_id)
        pdb.write_frame(fr)
    with ColmapDatabase(path) as db:
        assert db.uses_frames()
        cam2 = db.add_camera(pinhole(160, 120), False)
        ids = [db.add_image("second.jpg", cam.camera_id), db.add_image("third.jpg", cam2)]
        for i, image_id in enumerate(ids + [im.image_id]):
            db.write_features(image_id, random_features(20, i))
    with pycolmap.Database.open(path) as pdb:
        assert pdb.num_frames() == 3 and pdb.num_rigs() == 2
        assert (
            all(i.has_frame_id() for i in pdb.read_all_images())
            if hasattr(pycolmap.Image, "has_frame_id")
            else True
        )
        cache = pycolmap.DatabaseCache.create(pdb, cache_options())
        assert cache.num_images() == 3 and cache.num_frames() == 3 and cache.num_rigs() == 2


def write_views(db: ColmapDatabase, ims, camera: pycolmap.Camera, start: int = 0) -> list[int]:
    found = db.find_image("view0.png")
    cam_id = found[1] if found else db.add_camera(camera, True)
    ids = []
    for i, im in enumerate(ims, start):
        image_id = db.add_image(f"view{i}.png", cam_id)
        db.write_features(image_id, detect_sift(im))
        ids.append(image_id)
    return ids


def check_geometries(path: Path, ids: list[int], Hs: list[np.ndarray], min_inliers=100):
    """Every pair verified, with inliers that obey the known homographies (COLMAP px)."""
    with pycolmap.Database.open(path) as pdb:
        pair_ids, geoms = pdb.read_two_view_geometries()
        assert len(pair_ids) == len(ids) * (len(ids) - 1) // 2
        kps = {i: pdb.read_keypoints(i)[:, :2].astype(np.float64) for i in ids}
        for pair_id, g in zip(pair_ids, geoms):
            i1, i2 = pycolmap.pair_id_to_image_pair(pair_id)
            config = pycolmap.TwoViewGeometryConfiguration(g.config)
            assert config not in (
                pycolmap.TwoViewGeometryConfiguration.UNDEFINED,
                pycolmap.TwoViewGeometryConfiguration.DEGENERATE,
            )
            m = np.asarray(g.inlier_matches)
            assert len(m) >= min_inliers
            k1, k2 = ids.index(i1), ids.index(i2)
            H = Hs[k2] @ np.linalg.inv(Hs[k1])  # view k1 -> view k2, OpenCV pixels
            x1 = conventions.to_opencv_points(kps[i1][m[:, 0]])
            x2 = conventions.to_opencv_points(kps[i2][m[:, 1]])
            p = np.c_[x1, np.ones(len(x1))] @ H.T
            err = np.linalg.norm(p[:, :2] / p[:, 2:] - x2, axis=1)
            assert np.median(err) < 0.5 and np.mean(err < 2) > 0.9


def test_real_sift_matches_through_pycolmap(tmp_path, texture):
    ims, Hs = homography_views(texture)
    path = tmp_path / "db.db"
    with ColmapDatabase(path) as db:
        ids = write_views(db, ims, pinhole())
    opts = pycolmap.FeatureMatchingOptions()
    opts.num_threads = 2
    pycolmap.match_exhaustive(path, matching_options=opts, device=pycolmap.Device.cpu)
    check_geometries(path, ids, Hs)


# -- kill -9 -------------------------------------------------------------------------------

KILL_SCRIPT = r"""
import sys, numpy as np
sys.path.insert(0, sys.argv[3])
from test_colmap_db import random_features, pinhole
from rectified_colmap.io.colmap_db import ColmapDatabase
n = int(sys.argv[2])
with ColmapDatabase(sys.argv[1]) as db:
    cam = db.find_image("im000.jpg")
    cam_id = cam[1] if cam else db.add_camera(pinhole(), True)
    for i in range(n):
        name = f"im{i:03d}.jpg"
        found = db.find_image(name)
        image_id = found[0] if found else db.add_image(name, cam_id)
        if not db.has_features(image_id):
            db.write_features(image_id, random_features(2000 + i, i))
            print(i, flush=True)
print("done")
"""


def test_kill9_then_resume(tmp_path):
    script = tmp_path / "writer.py"
    script.write_text(KILL_SCRIPT)
    n = 60
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).parents[2]))
    args = [sys.executable, str(script), str(tmp_path / "k.db"), str(n), str(Path(__file__).parent)]
    rng = np.random.default_rng(0)
    done = []
    for _trial in range(4):
        proc = subprocess.Popen(
            args, env=env, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True
        )
        target = rng.integers(1, 12)  # images this run writes before the kill (about)
        for _ in range(target):
            proc.stdout.readline()
        time.sleep(rng.uniform(0, 0.01))
        proc.send_signal(signal.SIGKILL)
        proc.wait()
        con = sqlite3.connect(tmp_path / "k.db")  # valid after the kill
        assert con.execute("PRAGMA integrity_check").fetchone()[0] == "ok"
        done.append(con.execute("SELECT COUNT(*) FROM keypoints").fetchone()[0])
        con.close()
    print("images with features after each kill:", done)
    assert done[-1] < n, "the writer finished before it was killed: test proves nothing"
    out = subprocess.run(args, env=env, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0 and "done" in out.stdout, out.stderr[-2000:]
    with ColmapDatabase(tmp_path / "k.db") as db:
        names = db.image_names()
        assert sorted(names.values()) == [f"im{i:03d}.jpg" for i in range(n)]
        assert db.image_ids_with_features() == set(names)
        assert db.camera_ids() == [1]
        for image_id, name in names.items():
            i = int(name[2:5])
            np.testing.assert_array_equal(
                db.read_descriptors(image_id), random_features(2000 + i, i).descriptors
            )


# -- COLMAP 3.8 command line ------------------------------------------------------------


def run_colmap(*args):
    out = subprocess.run([COLMAP, *args], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stdout[-2000:] + out.stderr[-2000:]
    return out


def colmap_match(path: Path):
    run_colmap(
        "exhaustive_matcher",
        "--database_path",
        str(path),
        "--SiftMatching.use_gpu",
        "0",
        "--SiftMatching.num_threads",
        "2",
    )


@needs_colmap
def test_colmap38_reads_our_database(tmp_path, texture):
    """Our new database: COLMAP 3.8 matches it and copies every row (database_merger)."""
    ims, Hs = homography_views(texture)
    path = tmp_path / "ours.db"
    with ColmapDatabase(path) as db:
        ids = write_views(db, ims, pinhole())
    colmap_match(path)
    check_geometries(path, ids, Hs)  # written by 3.8, read by pycolmap 4.2.1
    empty = tmp_path / "empty.db"
    run_colmap("database_creator", "--database_path", str(empty))
    merged = tmp_path / "merged.db"
    run_colmap(
        "database_merger",
        "--database_path1",
        str(path),
        "--database_path2",
        str(empty),
        "--merged_database_path",
        str(merged),
    )
    with ColmapDatabase(path) as a, ColmapDatabase(merged) as b:
        assert a.image_names() == b.image_names()
        for i in ids:
            np.testing.assert_array_equal(a.read_keypoints(i), b.read_keypoints(i))
            np.testing.assert_array_equal(a.read_descriptors(i), b.read_descriptors(i))
        np.testing.assert_array_equal(a.get_camera(1).params, b.get_camera(1).params)


@needs_colmap
def test_colmap38_database_written_by_us(tmp_path, texture):
    """A database made by COLMAP 3.8: our features are read by 3.8, then pycolmap 4.2.1
    opens (migrates) it, reads the same features and 3.8's geometries."""
    ims, Hs = homography_views(texture, 4)
    path = tmp_path / "c38.db"
    run_colmap("database_creator", "--database_path", str(path))
    before = schema(path)
    with ColmapDatabase(path) as db:
        ids = write_views(db, ims[:3], pinhole())
        written = {i: (db.read_keypoints(i), db.read_descriptors(i)) for i in ids}
    # not migrated by us: COLMAP's tables as they were, plus our provenance table
    added = schema(path) - before
    assert len(added) == 1 and PROVENANCE_TABLE in added.pop()
    assert before <= schema(path)
    colmap_match(path)
    with pycolmap.Database.open(path) as pdb:
        for i in ids:
            np.testing.assert_array_equal(pdb.read_keypoints(i), written[i][0])
            d = pdb.read_descriptors(i)
            assert d.type == pycolmap.FeatureExtractorType.SIFT
            np.testing.assert_array_equal(d.data, written[i][1])
    check_geometries(path, ids, Hs[:3])
    # after 4.2.1's migration: we add a view, 3.8 matches the new pairs, 4.2.1 reads all
    assert not before <= schema(path)
    with ColmapDatabase(path) as db:
        ids += write_views(db, ims[3:], pinhole(), start=3)
    colmap_match(path)
    check_geometries(path, ids, Hs)
    with pycolmap.Database.open(path) as pdb:
        assert pdb.read_descriptors(ids[3]).type == pycolmap.FeatureExtractorType.SIFT
        cache = pycolmap.DatabaseCache.create(pdb, cache_options())
        assert cache.num_images() == 4
