"""hloc feature file exporter: the schema hloc reads, round trip, resume, and kill -9 at
random moments (together with the COLMAP database writer)."""

from __future__ import annotations

import logging
import os
import signal
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np
import pycolmap
import pytest

from rectified_colmap.features import Features, similarity_frames
from rectified_colmap.io import hloc_h5
from rectified_colmap.io.colmap_db import ColmapDatabase
from rectified_colmap.io.hloc_h5 import HlocFeatureWriter, list_names, read, validate


def random_features(n: int, seed: int, size=(1500, 1000)) -> Features:
    rng = np.random.default_rng(seed)
    xy = rng.random((n, 2)) * size
    shapes = similarity_frames(rng.uniform(1, 8, n), rng.uniform(-np.pi, np.pi, n))
    return Features(
        xy, shapes, rng.integers(0, 256, (n, 128), dtype=np.uint8), np.full(n, -1, np.int32)
    )


NAMES = ["db/1045.jpg", "query/night/nexus5x/IMG_1.jpg", "top.png", "db/1046.jpg"]


def hloc_list_h5_names(path: Path) -> list[str]:
    """What hloc.utils.io.list_h5_names does: the parents of all datasets."""
    names = []
    with h5py.File(path, "r", libver="latest") as fd:

        def visit(_, obj):
            if isinstance(obj, h5py.Dataset):
                names.append(obj.parent.name.strip("/"))

        fd.visititems(visit)
    return list(set(names))


def hloc_pair_inputs(path: Path, name: str) -> dict[str, np.ndarray]:
    """What match_features.FeaturePairsDataset does with one image (torch -> numpy)."""
    with h5py.File(path, "r") as fd:
        grp = fd[name]
        data = {k: np.asarray(grp[k].__array__(), dtype=np.float32) for k in grp.keys()}
        size = tuple(grp["image_size"])[::-1]
        np.empty((1,) + size)  # torch.empty((1,)+size) needs integers
    return data


@pytest.mark.parametrize("as_half", [True, False])
def test_schema_mirrors_hloc_readers(tmp_path, as_half):
    path = tmp_path / "feats-rectsift.h5"
    feats = {name: random_features(100 + 7 * i, i) for i, name in enumerate(NAMES)}
    with HlocFeatureWriter(path, as_half=as_half) as w:
        for name, f in feats.items():
            w.write(name, f, (1500, 1000))
    assert sorted(hloc_list_h5_names(path)) == sorted(NAMES)
    assert validate(path, NAMES) == len(NAMES)
    with h5py.File(path, "r") as fd:
        for name, f in feats.items():
            g = fd[name]
            assert set(g.keys()) == set(hloc_h5.DATASETS)
            assert all(g[k].dtype.kind in "fiu" for k in g.keys())  # numeric only
            kp = g["keypoints"]
            assert kp.dtype == np.float32 and kp.shape == (len(f), 2)
            assert kp.attrs["uncertainty"] == 1.0
            # triangulation.import_features / localize_sfm: keypoints + 0.5 = COLMAP
            np.testing.assert_allclose(kp[()] + 0.5, f.keypoints, atol=2e-4)
            d = g["descriptors"][()]
            assert d.shape == (128, len(f))
            assert d.dtype == (np.float16 if as_half else np.float32)
            np.testing.assert_allclose(np.linalg.norm(d.astype(np.float64), axis=0), 1, atol=2e-3)
            ref = f.descriptors / np.linalg.norm(f.descriptors.astype(float), axis=1, keepdims=True)
            np.testing.assert_allclose(d.T, ref, atol=1e-3 if as_half else 1e-6)
            size = g["image_size"][()]
            assert size.dtype.kind == "i" and list(size) == [1500, 1000]
            np.testing.assert_allclose(g["scales"][()], f.scales, rtol=1e-6)
            np.testing.assert_allclose(g["oris"][()], np.rad2deg(f.orientations), atol=1e-4)
            assert g["scores"].shape == (len(f),)
    # match_features + NN-ratio: dot products of unit descriptors are cosines
    a = hloc_pair_inputs(path, NAMES[0])
    b = hloc_pair_inputs(path, NAMES[0])
    sim = a["descriptors"].T @ b["descriptors"]
    np.testing.assert_allclose(np.diag(sim), 1, atol=2e-3)
    assert (np.argmax(sim, 1) == np.arange(sim.shape[0])).all()


def test_read_round_trip_and_resume(tmp_path):
    path = tmp_path / "out" / "f.h5"
    f0, f1 = random_features(50, 0), random_features(60, 1)
    w = HlocFeatureWriter(path, as_half=False)
    w.write("a/b.jpg", f0, (1500, 1000))
    assert w.has("a/b.jpg") and not path.exists()  # staged, target untouched
    r = read(path, "a/b.jpg")  # staged data can be read
    np.testing.assert_allclose(r["keypoints"], f0.keypoints, atol=1e-4)
    w.close()
    assert path.exists() and not hloc_h5.staging_dir(path).exists()
    r = read(path, "a/b.jpg")
    np.testing.assert_allclose(r["keypoints"], f0.keypoints, atol=1e-4)
    assert r["uncertainty"] == 1.0 and list(r["image_size"]) == [1500, 1000]

    # a run that dies without close(): its staged images are merged by the next open
    w = HlocFeatureWriter(path)
    assert w.has("a/b.jpg") and w.names() == ["a/b.jpg"]
    with pytest.raises(ValueError, match="already has features"):
        w.write("a/b.jpg", f1, (10, 10))
    w.write("c.jpg", f1, (1500, 1000))
    w.write("a/b.jpg", f1, (1500, 1000), overwrite=True)
    del w
    assert list_names(path) == ["a/b.jpg", "c.jpg"]
    with HlocFeatureWriter(path) as w:
        assert not hloc_h5.staging_dir(path).exists()
        assert w.names() == ["a/b.jpg", "c.jpg"]
    assert validate(path) == 2
    r = read(path, "a/b.jpg")
    assert r["keypoints"].shape == (60, 2)
    np.testing.assert_allclose(r["keypoints"], f1.keypoints, atol=2e-4)


def test_errors_name_the_file(tmp_path):
    path = tmp_path / "f.h5"
    with HlocFeatureWriter(path) as w:
        for bad in ["/abs.jpg", "a//b.jpg", "../up.jpg", "a\\b.jpg", ""]:
            with pytest.raises(ValueError, match="relative path"):
                w.write(bad, random_features(5, 0), (10, 10))
        w.write("dir/x.jpg", random_features(5, 0), (10, 10))
        with pytest.raises(ValueError, match="clashes"):
            w.write("dir", random_features(5, 0), (10, 10))
        f = random_features(5, 0)
        f.descriptors = f.descriptors.astype(np.float32)
        with pytest.raises(ValueError, match="f.h5.*uint8"):
            w.write("y.jpg", f, (10, 10))
        with pytest.raises(ValueError, match="image size"):
            w.write("y.jpg", random_features(5, 0), (0, 10))
    bad = tmp_path / "bad.h5"
    bad.write_bytes(b"not hdf5" * 100)
    with pytest.raises(ValueError, match="bad.h5"):
        HlocFeatureWriter(bad)
    with pytest.raises(KeyError):
        read(path, "nothing.jpg")


def test_empty_features(tmp_path):
    path = tmp_path / "f.h5"
    with HlocFeatureWriter(path) as w:
        w.write("e.jpg", Features.empty(), (10, 10))
    r = read(path, "e.jpg")
    assert r["keypoints"].shape == (0, 2) and r["descriptors"].shape == (128, 0)
    assert validate(path) == 1


# -- kill -9 at random moments, both formats -----------------------------------------------

KILL_SCRIPT = r"""
import sys
import numpy as np
import pycolmap
from rectified_colmap.features import Features, similarity_frames
from rectified_colmap.io.colmap_db import ColmapDatabase
from rectified_colmap.io.hloc_h5 import HlocFeatureWriter

def feats(i):
    rng = np.random.default_rng(i)
    n = 1500 + 10 * i
    return Features(rng.random((n, 2)) * 1000, similarity_frames(
        rng.uniform(1, 8, n), rng.uniform(-3, 3, n)),
        rng.integers(0, 256, (n, 128), dtype=np.uint8), np.full(n, -1, np.int32))

db_path, h5_path, n = sys.argv[1], sys.argv[2], int(sys.argv[3])
names = [f"d{i % 3}/im{i:03d}.jpg" for i in range(n)]
db = ColmapDatabase(db_path)
w = HlocFeatureWriter(h5_path)
cam = None
for i, name in enumerate(names):
    found = db.find_image(name)
    if found is None:
        if cam is None:
            cam = db.add_camera(pycolmap.Camera(model="SIMPLE_PINHOLE", width=1000,
                                                height=1000, params=[800, 500, 500]), True)
        found = (db.add_image(name, cam), cam)
    cam = found[1]
    if db.has_features(found[0]) and w.has(name):
        continue
    f = feats(i)
    if not db.has_features(found[0]):
        db.write_features(found[0], f)
    if not w.has(name):
        w.write(name, f, (1000, 1000))
    if i % 5 == 4:  # merge often: kills land in merges too
        w.close()
        w = HlocFeatureWriter(h5_path)
    print(i, flush=True)
w.close()
db.close()
print("done", flush=True)
"""


def staging_tmp(stage: Path) -> bool:
    try:
        return any(e.name.endswith(".tmp") for e in os.scandir(stage))
    except FileNotFoundError:  # the writer removed the staging directory meanwhile
        return False


def test_kill9_at_random_moments_then_resume(tmp_path):
    script = tmp_path / "writer.py"
    script.write_text(KILL_SCRIPT)
    db_path, h5_path, n = tmp_path / "k.db", tmp_path / "k.h5", 40
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).parents[2]))
    args = [sys.executable, str(script), str(db_path), str(h5_path), str(n)]
    rng = np.random.default_rng(1)
    merging = Path(str(h5_path) + ".merging")
    stage = hloc_h5.staging_dir(h5_path)
    progress, caught = [], []
    # two kills aimed at the dangerous moments (inside a merge, inside a staging write),
    # then kills after a random number of images plus a random delay
    for mode in ["merge", "stage", "random", "random", "random", "random", "random"]:
        proc = subprocess.Popen(
            args, env=env, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True
        )
        if mode == "random":
            for _ in range(rng.integers(1, 6)):
                proc.stdout.readline()
            time.sleep(rng.uniform(0, 0.05))
        else:
            t0 = time.monotonic()
            while time.monotonic() - t0 < 20 and proc.poll() is None:
                if merging.exists() if mode == "merge" else staging_tmp(stage):
                    break
                time.sleep(2e-4)
        proc.send_signal(signal.SIGKILL)
        proc.wait()
        caught.append(
            merging.exists() if mode == "merge" else staging_tmp(stage) if mode == "stage" else None
        )
        # both files are valid right after the kill
        if h5_path.exists():
            validate(h5_path)
        progress.append(len(list_names(h5_path)))  # staged files are readable too
        con = sqlite3.connect(db_path)
        assert con.execute("PRAGMA integrity_check").fetchone()[0] == "ok"
        con.close()
    logging.getLogger(__name__).info("kills: images done %s, caught %s", progress, caught)
    assert progress[-1] < n, "the writer finished before the last kill"
    out = subprocess.run(args, env=env, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0 and "done" in out.stdout, out.stderr[-2000:]

    names = [f"d{i % 3}/im{i:03d}.jpg" for i in range(n)]
    assert not hloc_h5.staging_dir(h5_path).exists()
    assert not Path(str(h5_path) + ".merging").exists()
    assert validate(h5_path, names) == n
    assert sorted(hloc_list_h5_names(h5_path)) == sorted(names)  # each exactly once
    with h5py.File(h5_path, "r") as fd:
        for i, name in enumerate(names):
            assert fd[name]["keypoints"].shape == (1500 + 10 * i, 2)
    rng_i = np.random.default_rng(7)
    with ColmapDatabase(db_path) as db:
        ids = db.image_names()
        assert sorted(ids.values()) == sorted(names)
        assert db.image_ids_with_features() == set(ids)
        for image_id, name in ids.items():
            i = int(name[-7:-4])
            assert len(db.read_keypoints(image_id)) == 1500 + 10 * i
    for i in rng_i.choice(n, 5, replace=False):  # content survives the merges
        r = read(h5_path, names[i])
        ref = np.random.default_rng(int(i)).random((1500 + 10 * int(i), 2)) * 1000
        np.testing.assert_allclose(r["keypoints"], ref, atol=1e-3)
    with pycolmap.Database.open(db_path) as pdb:
        assert pdb.num_images() == n and pdb.num_keypoints() == sum(1500 + 10 * i for i in range(n))
