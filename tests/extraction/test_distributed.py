"""Beyond one process: shards + merge and Ray give exactly the single-process outputs."""

import os
import signal
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import pytest

from rectified_colmap.cli import main
from rectified_colmap.extraction.plan import parse_shard, shard_names, shard_of
from rectified_colmap.extraction import extract
from rectified_colmap.io import hloc_h5
from rectified_colmap.io.merge import merge_databases, merge_feature_files
from tests.conftest import images_with_features

REPO = Path(__file__).resolve().parents[2]
NUM_IMAGES = 6


def test_shards_partition_the_list_stably():
    names = [f"seq{k}/img_{i:04d}.jpg" for k in range(3) for i in range(200)]
    for count in (1, 2, 7):
        parts = [shard_names(names, i, count) for i in range(count)]
        assert sorted(sum(parts, [])) == sorted(names)  # every image in exactly one shard
        assert all(len(p) == len(set(p)) for p in parts)
        if count > 1:  # roughly balanced
            assert min(map(len, parts)) > 0.6 * len(names) / count
        # adding images never moves an existing one to another shard
        more = names + [f"new/{i}.jpg" for i in range(50)]
        for i in range(count):
            assert set(parts[i]) <= set(shard_names(more, i, count))
        assert all(shard_of(n, count) == i for i in range(count) for n in parts[i])
    assert parse_shard("3/8") == (3, 8) and parse_shard((0, 1)) == (0, 1)
    for bad in ("8/8", "-1/4", "1", "a/b", "1/0"):
        with pytest.raises(ValueError, match="--shard"):
            parse_shard(bad)


@pytest.fixture(scope="module")
def street(tmp_path_factory):
    """A small rendered street walk (exact pinhole intrinsics)."""
    from rectified_colmap.demo import render_walk

    root = tmp_path_factory.mktemp("street")
    names, camera, _ = render_walk(root / "images", num_images=NUM_IMAGES, width=320, height=240)
    params = ",".join(f"{p:.6f}" for p in camera.params)
    return root / "images", names, params


def _extract(street, out: Path, single_camera: bool = True, depth_model=None, **run):
    images, _, params = street
    reader = {"camera_model": "PINHOLE", "camera_params": params, "single_camera": single_camera}
    return extract(
        images,
        database=out / "db.db",
        hloc_features=out / "f.h5",
        reader=reader,
        depth=None if depth_model is None else {"model": depth_model},
        run={"progress": False, **run},
    )


@pytest.fixture(scope="module")
def single(street, tmp_path_factory):
    """The reference: one process, the embedded depth network."""
    out = tmp_path_factory.mktemp("single")
    s = _extract(street, out)
    assert s.ok and len(s.done) == NUM_IMAGES and len(s.plain) < NUM_IMAGES
    return out


def db_dump(path: Path) -> dict:
    """Everything but the row ids: per image name its camera row and feature bytes."""
    con = sqlite3.connect(path)
    try:
        rows = con.execute(
            "SELECT i.name, c.model, c.width, c.height, c.params, c.prior_focal_length, "
            "k.rows, k.cols, k.data, d.rows, d.data FROM images i JOIN cameras c USING "
            "(camera_id) JOIN keypoints k USING(image_id) JOIN descriptors d USING(image_id)"
        )
        out = {r[0]: r[1:] for r in rows}
        out["#cameras"] = con.execute("SELECT COUNT(*) FROM cameras").fetchone()[0]
        out["#ids"] = sorted(con.execute("SELECT name, image_id, camera_id FROM images"))
        return out
    finally:
        con.close()


def h5_dump(path: Path) -> dict:
    import h5py

    out = {}
    with h5py.File(path, "r") as f:
        for name in hloc_h5.list_names(path):
            g = f[name]
            out[name] = ({k: g[k][()].tobytes() for k in g}, dict(g.attrs))
    return out


def assert_same_outputs(a: Path, b: Path, ids: bool = True):
    da, db_ = db_dump(a / "db.db"), db_dump(b / "db.db")
    if not ids:
        da.pop("#ids"), db_.pop("#ids")
    assert da == db_
    assert h5_dump(a / "f.h5") == h5_dump(b / "f.h5")


def test_sharded_runs_merged_equal_one_run(street, single, tmp_path):
    shards = []
    for i in range(3):
        out = tmp_path / f"shard{i}"
        s = _extract(street, out, shard=f"{i}/3")
        assert s.ok
        shards.append(out)
    merged = tmp_path / "merged"
    assert (
        main(
            [
                "merge",
                "--single_camera",
                "--database_path",
                str(merged / "db.db"),
                "--hloc_features",
                str(merged / "f.h5"),
            ]
            + [str(p / f) for p in shards for f in ("db.db", "f.h5")]
        )
        == 0
    )
    assert_same_outputs(single, merged)  # ids included: names are merged in order
    # merging again adds nothing and changes nothing
    before = db_dump(merged / "db.db")
    s = merge_databases(merged / "db.db", [p / "db.db" for p in shards])
    assert s.added == [] and len(s.already) == NUM_IMAGES
    assert db_dump(merged / "db.db") == before
    assert merge_feature_files(merged / "f.h5", [p / "f.h5" for p in shards]).added == []


def test_an_empty_shard_leaves_valid_outputs_that_merge(street, single, tmp_path):
    """More shards than images: some shard gets no image. It still leaves a valid, empty
    database and hloc file, and merging every shard's outputs (what a job-array script
    lists) gives exactly one run's outputs."""
    _, names, _ = street
    count = NUM_IMAGES + 1
    empty = [i for i in range(count) if not shard_names(names, i, count)]
    assert empty  # pigeonhole
    shards = []
    for i in range(count):
        out = tmp_path / f"s{i}"
        assert _extract(street, out, shard=f"{i}/{count}").ok
        shards.append(out)
    for i in empty:
        assert hloc_h5.validate(shards[i] / "f.h5") == 0
        assert db_dump(shards[i] / "db.db")["#ids"] == []
    merged = tmp_path / "merged"
    args = ["merge", "--single_camera", "--database_path", str(merged / "db.db")]
    args += ["--hloc_features", str(merged / "f.h5")]
    assert main(args + [str(p / f) for p in shards for f in ("db.db", "f.h5")]) == 0
    assert_same_outputs(single, merged)
    # empty inputs alone merge into valid, empty outputs
    nothing = tmp_path / "nothing"
    assert merge_feature_files(nothing / "f.h5", [shards[i] / "f.h5" for i in empty]).added == []
    assert merge_databases(nothing / "db.db", [shards[i] / "db.db" for i in empty]).added == []
    assert hloc_h5.validate(nothing / "f.h5") == 0
    assert db_dump(nothing / "db.db")["#ids"] == []


def test_merge_keeps_per_image_cameras_and_refuses_conflicts(street, tmp_path, caplog):
    images, names, params = street
    kw = dict(depth_model="none", single_camera=False)
    one = tmp_path / "one"
    _extract(street, one, **kw)
    parts = [tmp_path / "a", tmp_path / "b"]
    for i, out in enumerate(parts):
        _extract(street, out, shard=f"{i}/2", **kw)
    merged = tmp_path / "m"
    merge_databases(merged / "db.db", [p / "db.db" for p in parts])
    merge_feature_files(merged / "f.h5", [p / "f.h5" for p in parts])
    assert_same_outputs(one, merged)
    assert db_dump(merged / "db.db")["#cameras"] == NUM_IMAGES  # one camera per image
    # a conflict: the same name with other features (here: another budget) is refused,
    # and nothing is written
    other = tmp_path / "other"
    extract(
        images,
        database=other / "db.db",
        hloc_features=other / "f.h5",
        conf={"sift": {"max_num_features": 200}},
        reader={"camera_model": "PINHOLE", "camera_params": params, "image_list": names[:1]},
        depth={"model": "none"},
        run={"progress": False},
    )
    target = tmp_path / "t"
    code = main(
        [
            "merge",
            "--database_path",
            str(target / "db.db"),
            str(one / "db.db"),
            str(other / "db.db"),
        ]
    )
    assert (
        code == 2
        and f"{names[0]!r} in {one / 'db.db'} and {other / 'db.db'}" in caplog.text
        and "nothing was merged" in caplog.text
    )
    assert not (target / "db.db").exists()
    with pytest.raises(ValueError, match="different features"):
        merge_feature_files(target / "f.h5", [one / "f.h5", other / "f.h5"])
    assert not (target / "f.h5").exists()
    # inputs that were already matched are refused (their pair ids would be wrong)
    import pycolmap

    pycolmap.match_exhaustive(one / "db.db")
    with pytest.raises(ValueError, match="before matching"):
        merge_databases(target / "db.db", [one / "db.db"])


try:
    import ray
except ImportError:
    ray = None
needs_ray = pytest.mark.skipif(
    ray is None, reason="Ray is optional: pip install 'rectified-colmap[ray]' (CI installs it)"
)


@needs_ray
@pytest.mark.slow
def test_ray_run_equals_one_run_and_a_killed_driver_resumes(street, single, tmp_path):
    out = tmp_path / "ray"
    s = _extract(street, out, ray_address="local", num_workers=2)
    assert s.ok and len(s.done) == NUM_IMAGES
    assert not ray.is_initialized()  # the local instance it started is stopped
    assert_same_outputs(single, out)
    # kill -9 of the driver (and its local Ray processes) mid-run; a rerun completes it
    images, _, params = street
    killed = tmp_path / "killed"
    cmd = [
        sys.executable,
        "-m",
        "rectified_colmap.cli",
        "extract",
        "--image_path",
        str(images),
        "--database_path",
        str(killed / "db.db"),
        "--hloc_features",
        str(killed / "f.h5"),
        "--camera_model",
        "PINHOLE",
        "--camera_params",
        params,
        "--single_camera",
        "--ray",
        "--num_workers",
        "2",
        "--no_progress",
    ]
    proc = subprocess.Popen(
        cmd, cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True
    )
    deadline = time.monotonic() + 240
    while (
        proc.poll() is None
        and time.monotonic() < deadline
        and images_with_features(killed / "db.db") < 2
    ):
        time.sleep(0.02)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    done = images_with_features(killed / "db.db")
    assert 0 < done < NUM_IMAGES, "the kill did not land mid-run"
    s = _extract(street, killed, ray_address="local", num_workers=2)
    assert s.ok and len(s.skipped) + len(s.copied) + len(s.done) == NUM_IMAGES
    assert_same_outputs(single, killed)


def test_ray_flag_without_ray_is_a_clear_error(street, tmp_path, monkeypatch):
    """Without Ray installed: one line, before anything is written."""
    monkeypatch.setitem(sys.modules, "ray", None)  # what an absent package looks like
    images, _, params = street
    with pytest.raises(RuntimeError, match=r"pip install 'rectified-colmap\[ray\]'"):
        extract(
            images,
            database=tmp_path / "db.db",
            depth={"model": "none"},
            run={"ray_address": "local", "progress": False},
        )
    assert not (tmp_path / "db.db").exists()


def test_identical_outputs_helper_sees_a_one_byte_change(single, tmp_path):
    """The comparison used above can fail: flip one descriptor byte of a copy."""
    import shutil

    copy = tmp_path / "copy"
    shutil.copytree(single, copy)
    con = sqlite3.connect(copy / "db.db")
    data = bytearray(con.execute("SELECT data FROM descriptors LIMIT 1").fetchone()[0])
    data[0] ^= 1
    con.execute(
        "UPDATE descriptors SET data = ? WHERE image_id = (SELECT MIN(image_id) FROM descriptors)",
        (bytes(data),),
    )
    con.commit()
    con.close()
    with pytest.raises(AssertionError):
        assert_same_outputs(single, copy)
