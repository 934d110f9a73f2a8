"""Users' data: reruns only add, concurrent runs never lose or duplicate, foreign
databases are kept, every failure is one clear line (issue: "Never lose or silently change
a user's data")."""

import os
import shutil
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import cv2
import h5py
import numpy as np
import pycolmap
import pytest

from rectified_colmap.cli import main
from rectified_colmap.extraction import extract
from rectified_colmap.io import hloc_h5
from rectified_colmap.io.colmap_db import PROVENANCE_TABLE, ColmapDatabase
from tests.conftest import images_with_features, look_at, plane_view, textured_image

K = np.array([[300.0, 0, 160], [0, 300, 120], [0, 0, 1]])
PARAMS = "300,300,160,120"
CAM = ["--camera_model", "PINHOLE", "--camera_params", PARAMS]
NAMES = [f"sub/{i}.png" for i in range(5)]
REPO = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def images(tmp_path_factory):
    """Five overlapping views (320x240) of a textured plane, in a sub-folder."""
    root = tmp_path_factory.mktemp("safety") / "images"
    (root / "sub").mkdir(parents=True)
    tex = textured_image(500, 500, 3)
    for i, name in enumerate(NAMES):
        R, t = look_at([0.6 * i - 1.2, -3.0, 2.5], [0, 0, 0])
        img, _ = plane_view(tex, 0.01, K, R, t, (320, 240))
        cv2.imwrite(str(root / name), img)
    return root


def run(images, *args, depth_model="none"):
    return main(
        [
            "extract",
            "--image_path",
            str(images),
            "--depth_model",
            depth_model,
            "--no_progress",
            *CAM,
            *map(str, args),
        ]
    )


def db_state(path) -> dict:
    """Everything a user keeps in a database, checked for consistency on the way:
    SQLite integrity, each image once with features, no camera without an image."""
    con = sqlite3.connect(path)
    try:
        assert con.execute("PRAGMA integrity_check").fetchone()[0] == "ok"
        names = [r[0] for r in con.execute("SELECT name FROM images")]
        assert len(names) == len(set(names))
        assert (
            con.execute(
                "SELECT COUNT(*) FROM images WHERE image_id NOT IN (SELECT image_id FROM keypoints)"
            ).fetchone()[0]
            == 0
        )
        assert (
            con.execute(
                "SELECT COUNT(*) FROM images WHERE image_id NOT IN "
                "(SELECT image_id FROM descriptors)"
            ).fetchone()[0]
            == 0
        )
        assert (
            con.execute(
                "SELECT COUNT(*) FROM cameras WHERE camera_id NOT IN (SELECT camera_id FROM images)"
            ).fetchone()[0]
            == 0
        )
        feats = {
            n: (k, d)
            for n, k, d in con.execute(
                "SELECT i.name, k.data, d.data FROM images i JOIN keypoints k USING(image_id) "
                "JOIN descriptors d USING(image_id)"
            )
        }
        matches = con.execute("SELECT pair_id, data FROM matches ORDER BY 1").fetchall()
        geoms = con.execute(
            "SELECT pair_id, config, data FROM two_view_geometries ORDER BY 1"
        ).fetchall()
    finally:
        con.close()
    return {"features": feats, "matches": matches, "geometries": geoms}


def no_leftovers(*outputs):
    for out in outputs:
        out = Path(out)
        stray = [
            p.name
            for p in out.parent.iterdir()
            if p.name.startswith(out.name) and p.name != out.name
        ]
        assert stray == [], stray


def same_features_in_both(db, h5):
    """The hloc file describes exactly the database's features (keypoints to float32
    precision, descriptor bytes to float16 storage)."""
    with ColmapDatabase(db) as d:
        for image_id, name in d.image_names().items():
            a = d.read_features(image_id)
            b = hloc_h5.read_features(h5, name)
            np.testing.assert_allclose(b.keypoints, a.keypoints, atol=1e-3)
            np.testing.assert_allclose(b.scales, a.scales, rtol=1e-3)
            diff = np.abs(b.descriptors.astype(int) - a.descriptors.astype(int))
            assert diff.max() <= 1 and (diff == 0).mean() > 0.999


def match(db):
    pycolmap.match_exhaustive(db)
    return db_state(db)


def test_rerun_adding_hloc_file_keeps_database_and_matches(images, tmp_path, caplog):
    db, h5 = tmp_path / "db.db", tmp_path / "f.h5"
    assert run(images, "--database", db) == 0
    before = match(db)
    assert sum(1 for g in before["geometries"] if g[1] >= 2) >= 6  # verified pairs
    s = extract(
        images,
        database=db,
        hloc_features=h5,
        reader={"camera_model": "PINHOLE", "camera_params": PARAMS},
        depth={"model": "none"},
        run={"progress": False},
    )
    assert s.ok and s.done == [] and sorted(s.copied) == NAMES
    assert db_state(db) == before  # keypoints, descriptors, matches untouched
    assert hloc_h5.list_names(h5) == NAMES
    hloc_h5.validate(h5, NAMES)
    same_features_in_both(db, h5)
    assert s.foreign == {}  # our own features: nothing to report
    no_leftovers(db, h5)
    # and again: nothing to do at all
    s = extract(
        images,
        database=db,
        hloc_features=h5,
        reader={"camera_model": "PINHOLE", "camera_params": PARAMS},
        depth={"model": "none"},
        run={"progress": False},
    )
    assert sorted(s.skipped) == NAMES and not s.copied and not s.done


def test_hloc_first_then_database_gets_the_same_features(images, tmp_path):
    db, h5 = tmp_path / "db.db", tmp_path / "f.h5"
    assert run(images, "--hloc_features", h5) == 0
    with h5py.File(h5, "r") as f:
        before = {n: f[n]["keypoints"][()] for n in NAMES}
    s = extract(
        images,
        database=db,
        hloc_features=h5,
        reader={"camera_model": "PINHOLE", "camera_params": PARAMS},
        depth={"model": "none"},
        run={"progress": False},
    )
    assert s.ok and s.done == [] and sorted(s.copied) == NAMES
    with h5py.File(h5, "r") as f:
        for n in NAMES:
            np.testing.assert_array_equal(f[n]["keypoints"][()], before[n])
    same_features_in_both(db, h5)
    state = match(db)  # COLMAP's matcher reads what we copied
    assert sum(1 for g in state["geometries"] if g[1] >= 2) >= 6
    with ColmapDatabase(db) as d:
        assert d.ours() == set(d.image_names())


def test_foreign_features_are_kept_and_reported_once(images, tmp_path, caplog):
    db, h5 = tmp_path / "colmap.db", tmp_path / "f.h5"
    opts = pycolmap.FeatureExtractionOptions()
    opts.num_threads = 1
    pycolmap.extract_features(
        db, images, image_names=NAMES, extraction_options=opts, device=pycolmap.Device.cpu
    )
    before = match(db)
    caplog.clear()
    s = extract(
        images,
        database=db,
        hloc_features=h5,
        reader={"camera_model": "PINHOLE", "camera_params": PARAMS},
        depth={"model": "none"},
        run={"progress": False},
    )
    assert s.ok and s.done == [] and s.foreign == {str(db): len(NAMES)}
    assert db_state(db) == before
    said = [r for r in caplog.records if "another extractor" in r.getMessage()]
    assert len(said) == 1 and said[0].levelname == "WARNING" and "sub/0.png" in said[0].getMessage()
    same_features_in_both(db, h5)
    with h5py.File(h5, "r") as f:  # marked as not ours in the hloc file too
        assert all(f[n].attrs.get(hloc_h5.EXTRACTOR_ATTR) is None for n in NAMES)
    # --overwrite replaces them, and says how many matches that deletes
    caplog.clear()
    n_matches, n_geoms = len(before["matches"]), len(before["geometries"])
    assert run(images, "--database", db, "--hloc_features", h5, "--overwrite") == 0
    warned = [
        r.getMessage()
        for r in caplog.records
        if r.levelname == "WARNING" and "--overwrite" in r.getMessage()
    ]
    assert len(warned) == 1
    assert f"{n_matches} match and {n_geoms} two-view geometry rows" in warned[0]
    after = db_state(db)
    assert after["matches"] == [] and after["geometries"] == []
    assert sorted(after["features"]) == NAMES
    with ColmapDatabase(db) as d:
        assert d.ours() == set(d.image_names())
    with h5py.File(h5, "r") as f:
        assert all(f[n].attrs[hloc_h5.EXTRACTOR_ATTR] == "rectified-colmap" for n in NAMES)


def test_empty_database_file_is_initialised(images, tmp_path):
    db = tmp_path / "touched.db"
    db.touch()
    assert run(images, "--database", db) == 0
    assert sorted(db_state(db)["features"]) == NAMES
    with pycolmap.Database.open(db) as pdb:
        assert pdb.num_images() == len(NAMES) and pdb.num_keypoints() > 0


# ---------------------------------------------------------------------------------------
# Concurrency: real processes, started together (after their imports) on the same files.

_RACER = """
import sys, time
from rectified_colmap.cli import main
start = float(sys.argv[1])
while time.time() < start:
    time.sleep(0.001)
sys.exit(main(sys.argv[2:]))
"""


def race(images, tmp_path, runs: list[list[str]]) -> list[tuple[int, str]]:
    start = time.time() + 2.5  # after the imports: the runs really start together
    procs = []
    for k, names in enumerate(runs):
        lst = tmp_path / f"list{k}_{time.monotonic_ns()}.txt"
        lst.write_text("\n".join(names) + "\n")
        args = [
            "extract",
            "--image_path",
            str(images),
            "--image_list",
            str(lst),
            "--database",
            str(tmp_path / "db.db"),
            "--hloc_features",
            str(tmp_path / "f.h5"),
            "--depth_model",
            "none",
            "--no_progress",
            *CAM,
        ]
        procs.append(
            subprocess.Popen(
                [sys.executable, "-c", _RACER, str(start), *args],
                cwd=REPO,
                stdout=subprocess.PIPE,
                stderr=subprocess.STDOUT,
                text=True,
            )
        )
    return [(p.wait(timeout=300), p.stdout.read()) for p in procs]


@pytest.mark.slow
@pytest.mark.parametrize("existing", [False, True], ids=["new-files", "existing-files"])
def test_concurrent_runs_lose_duplicate_and_corrupt_nothing(images, tmp_path, existing):
    lists = {
        "same": [NAMES, NAMES, NAMES],
        "disjoint": [NAMES[:2], NAMES[2:4], NAMES[4:]],
        "overlapping": [NAMES[:3], NAMES[1:4], NAMES[2:]],
    }
    reference = None
    for round_ in range(2):
        for kind, runs in lists.items():
            work = tmp_path / f"{kind}{round_}"
            work.mkdir()
            if existing:  # files that already hold one image and a user's matches
                assert (
                    run(
                        images,
                        "--database",
                        work / "db.db",
                        "--hloc_features",
                        work / "f.h5",
                        "--image_list",
                        _list(work, NAMES[4:]),
                    )
                    == 0
                )
            results = race(images, work, runs)
            for code, out in results:
                assert code == 0, out
                assert "Traceback" not in out, out
            state = db_state(work / "db.db")
            assert sorted(state["features"]) == NAMES, kind
            assert hloc_h5.list_names(work / "f.h5") == NAMES
            hloc_h5.validate(work / "f.h5", NAMES)
            no_leftovers(work / "db.db", work / "f.h5")
            # deterministic: every race gives the same features as every other
            feats = {n: v for n, v in state["features"].items()}
            reference = reference or feats
            assert feats == reference, kind
            waited = sum("waiting for it to finish" in out for _, out in results)
            assert waited <= len(runs) - 1


def _list(folder: Path, names: list[str]) -> Path:
    path = folder / "first.txt"
    path.write_text("\n".join(names))
    return path


# ---------------------------------------------------------------------------------------
# Checks before writing: one line naming the file and the cause, no traceback, no file.


@pytest.mark.parametrize(
    "args,expect",
    [
        (
            ["--camera_model", "PINHOLE", "--camera_params", "300,300,160"],
            "PINHOLE takes 4 params, got 3",
        ),
        (["--camera_model", "NOPE", "--camera_params", "1"], "unknown camera model 'NOPE'"),
        (["--depth_model", "no-such-model"], "'no-such-model'"),
        (["--depth_model", "{tmp}/corrupt.onnx"], "corrupt.onnx: onnxruntime cannot load"),
        (["--depth_model", "{tmp}/missing.onnx"], "missing.onnx: depth model file does not"),
        (["--depth_path", "{tmp}/nodepth"], "nodepth: depth folder does not exist"),
        (["--image_list", "{tmp}/nolist.txt"], "nolist.txt: cannot read the image list"),
    ],
    ids=[
        "param-count",
        "camera-model",
        "model-name",
        "corrupt-model",
        "missing-model",
        "depth-folder",
        "image-list",
    ],
)
def test_bad_arguments_fail_before_anything_is_written(images, tmp_path, args, expect):
    (tmp_path / "corrupt.onnx").write_bytes(b"not a protobuf")
    args = [a.replace("{tmp}", str(tmp_path)) for a in args]
    db, h5 = tmp_path / "out" / "db.db", tmp_path / "out" / "f.h5"
    cmd = [
        sys.executable,
        "-m",
        "rectified_colmap.cli",
        "extract",
        "--image_path",
        str(images),
        "--database",
        str(db),
        "--hloc_features",
        str(h5),
        "--no_progress",
    ]
    if "--camera_model" not in args:
        cmd += CAM
    out = subprocess.run(cmd + args, cwd=REPO, capture_output=True, text=True, timeout=120)
    assert out.returncode == 2, out.stderr
    errors = [ln for ln in out.stderr.splitlines() if " ERROR] " in ln]
    assert len(errors) == 1 and expect in errors[0], out.stderr
    assert "Traceback" not in out.stderr
    assert not (tmp_path / "out").exists()  # nothing created


def _unprivileged() -> list[str] | None:
    """A command prefix under which file permissions apply (root ignores them)."""
    if os.geteuid() != 0:
        return []
    setpriv = shutil.which("setpriv")
    if setpriv is None:
        return None
    probe = subprocess.run(
        [setpriv, "--bounding-set=-dac_override,-dac_read_search", "true"], capture_output=True
    )
    return (
        [setpriv, "--bounding-set=-dac_override,-dac_read_search"]
        if probe.returncode == 0
        else None
    )


@pytest.mark.parametrize(
    "case", ["read-only-database", "wal-in-read-only-folder", "read-only-hloc-folder"]
)
def test_read_only_outputs_are_refused_in_one_line(images, tmp_path, case):
    prefix = _unprivileged()
    if prefix is None:
        pytest.skip("running as root without setpriv: permissions cannot be enforced")
    folder = tmp_path / "ro"
    folder.mkdir()
    db = folder / "db.db"
    assert run(images, "--database", db, "--image_list", _list(tmp_path, NAMES[:1])) == 0
    before = db_state(db)
    if case == "wal-in-read-only-folder":
        with sqlite3.connect(db) as con:
            con.execute("PRAGMA journal_mode=WAL")
    target = ["--database", str(db)]
    if case == "read-only-hloc-folder":
        target = ["--hloc_features", str(folder / "f.h5")]
    if case == "read-only-database":
        db.chmod(0o444)
    else:
        folder.chmod(0o555)
    try:
        out = subprocess.run(
            prefix
            + [
                sys.executable,
                "-m",
                "rectified_colmap.cli",
                "extract",
                "--image_path",
                str(images),
                *target,
                "--depth_model",
                "none",
                "--no_progress",
                *CAM,
            ],
            cwd=REPO,
            capture_output=True,
            text=True,
            timeout=120,
        )
    finally:
        folder.chmod(0o755)
        db.chmod(0o644)
    errors = [ln for ln in out.stderr.splitlines() if " ERROR] " in ln]
    assert out.returncode == 2 and len(errors) == 1, out.stderr
    expect = "file is read-only" if case == "read-only-database" else "is not writable"
    assert expect in errors[0] and str(folder) in errors[0], errors
    assert db_state(db) == before


# ---------------------------------------------------------------------------------------
# Per-image problems: named (relative to --image_path), listed, the run goes on.


def test_per_image_problems_are_named_listed_and_leave_no_rows(images, tmp_path, caplog):
    root = tmp_path / "images"
    shutil.copytree(images, root)
    depths = tmp_path / "depths"
    (depths / "sub").mkdir(parents=True)
    bad_depth = {
        "sub/0.png": np.full((240, 320), np.nan),
        "sub/1.png": np.zeros((240, 320)),
        "sub/2.png": -np.ones((240, 320)),
    }
    for name, d in bad_depth.items():
        np.save(depths / f"{name}.npy", d.astype(np.float32))
    (depths / "sub" / "3.png.npy").write_bytes(b"corrupt")  # fails this image
    jpg = cv2.imencode(".jpg", cv2.imread(str(root / "sub/4.png")))[1].tobytes()
    (root / "sub" / "cut.jpg").write_bytes(jpg[: len(jpg) * 2 // 3])
    db, h5 = tmp_path / "db.db", tmp_path / "f.h5"
    caplog.clear()
    s = extract(
        root,
        database=db,
        hloc_features=h5,
        depth={"path": depths, "model": "none"},
        run={"progress": False},
    )  # no camera flags: focal lengths are guessed
    assert not s.ok and list(s.failed) == ["sub/3.png"]
    assert "3.png.npy" in s.failed["sub/3.png"]
    for name in bad_depth:
        assert any("unusable depth from the depth file" in w for w in s.warnings[name])
    assert any("truncated JPEG" in w for w in s.warnings["sub/cut.jpg"])
    report = s.report()
    assert "FAILED sub/3.png" in report and "WARNING sub/cut.jpg: truncated" in report
    # the failed image left nothing behind: no image row, no camera row
    state = db_state(db)
    assert sorted(state["features"]) == sorted(set(NAMES + ["sub/cut.jpg"]) - {"sub/3.png"})
    assert "sub/3.png" not in hloc_h5.list_names(h5)
    guesses = [r.getMessage() for r in caplog.records if "no focal length" in r.getMessage()]
    assert len(guesses) == 1 and "6 image(s)" in guesses[0] and "sub/0.png" in guesses[0]
    # exit code of the same run through the CLI (nothing left to do but the failed image)
    assert (
        main(
            [
                "extract",
                "--image_path",
                str(root),
                "--database",
                str(db),
                "--depth_path",
                str(depths),
                "--depth_model",
                "none",
                "--no_progress",
            ]
        )
        == 1
    )


def test_embedded_model_licence_matches_its_metadata():
    import onnx

    from rectified_colmap.depth.registry import REGISTRY, model_path

    entry = REGISTRY["rectsift-lite0"]
    meta = {
        p.key: p.value
        for p in onnx.load(model_path(entry.name), load_external_data=False).metadata_props
    }
    assert meta["rectified_colmap.licence"].split()[0] == entry.licence


def test_database_records_only_our_features(tmp_path):
    from rectified_colmap.features import Features

    feats = Features(
        np.array([[10.5, 20.5]]),
        np.eye(2)[None] * 2.0,
        np.full((1, 128), 45, np.uint8),
        np.array([-1], np.int32),
    )
    cam = pycolmap.Camera(model="PINHOLE", width=100, height=80, params=[90, 90, 50, 40])
    with ColmapDatabase(tmp_path / "d.db") as db:
        mine, cam_id, _ = db.write_image("a.png", feats, cam)
        theirs, _, _ = db.write_image("b.png", feats, camera_id=cam_id, extractor=None)
        assert db.ours() == {mine}
        db.write_features(theirs, feats, overwrite=True)
        assert db.ours() == {mine, theirs}
        back = db.read_features(mine)
    np.testing.assert_array_equal(back.keypoints, feats.keypoints)
    np.testing.assert_array_equal(back.shapes, feats.shapes)
    np.testing.assert_array_equal(back.descriptors, feats.descriptors)
    with sqlite3.connect(tmp_path / "d.db") as con:
        assert con.execute(f"SELECT COUNT(*) FROM {PROVENANCE_TABLE}").fetchone()[0] == 2


def test_second_writer_waits_naming_the_holder(tmp_path, caplog):
    """A process holding an output makes another wait, told which pid holds it; the lock
    file is gone afterwards and a kill -9 of the holder releases it."""
    from rectified_colmap.io.lock import OutputLock, lock_path

    out = tmp_path / "db.db"
    holder = subprocess.Popen(
        [
            sys.executable,
            "-c",
            "import sys, time\nfrom rectified_colmap.io.lock import "
            "OutputLock\nwith OutputLock(sys.argv[1]):\n    print('held', flush=True)\n"
            "    time.sleep(float(sys.argv[2]))",
            str(out),
            "1.5",
        ],
        cwd=REPO,
        stdout=subprocess.PIPE,
        text=True,
    )
    assert holder.stdout.readline().strip() == "held"
    t0 = time.monotonic()
    with OutputLock(out):
        waited = time.monotonic() - t0
        assert lock_path(out).read_text().strip() == str(os.getpid())
    assert holder.wait(timeout=30) == 0
    assert waited > 0.3
    said = [r.getMessage() for r in caplog.records if "waiting" in r.getMessage()]
    assert said == [f"{out} is being written by process {holder.pid}; waiting for it to finish"]
    assert not lock_path(out).exists()
    # kill -9 of a holder: the kernel releases the lock
    holder = subprocess.Popen(
        [
            sys.executable,
            "-c",
            "import sys, time\nfrom rectified_colmap.io.lock import "
            "OutputLock\nwith OutputLock(sys.argv[1]):\n    print('held', flush=True)\n"
            "    time.sleep(60)",
            str(out),
        ],
        cwd=REPO,
        stdout=subprocess.PIPE,
        text=True,
    )
    assert holder.stdout.readline().strip() == "held"
    holder.kill()
    holder.wait(timeout=30)
    with OutputLock(out, poll_seconds=0.05):
        pass


@pytest.mark.slow
def test_kill_9_mid_run_leaves_valid_files_and_resumes_to_a_clean_result(images, tmp_path):
    root = tmp_path / "images"
    root.mkdir()
    names = [f"{k:02d}_{i}.png" for k in range(3) for i in range(5)]
    for name in names:
        shutil.copy(images / f"sub/{name[-5]}.png", root / name)
    clean, killed = tmp_path / "clean", tmp_path / "killed"
    cmd = [
        sys.executable,
        "-m",
        "rectified_colmap.cli",
        "extract",
        "--image_path",
        str(root),
        "--depth_model",
        "none",
        "--no_progress",
        *CAM,
    ]

    def out(folder):
        return ["--database", str(folder / "db.db"), "--hloc_features", str(folder / "f.h5")]

    assert subprocess.run(cmd + out(clean), cwd=REPO, capture_output=True).returncode == 0
    for kill_after in (1, 5, 10):
        proc = subprocess.Popen(
            cmd + out(killed), cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL
        )
        while proc.poll() is None and images_with_features(killed / "db.db") < kill_after:
            time.sleep(0.005)
        proc.kill()
        proc.wait()
        state = db_state(killed / "db.db")  # valid, every image once, no orphan rows
        assert set(state["features"]) <= set(names)
        # the hloc file (merged on the next open) never holds an image twice or half
        with hloc_h5.HlocFeatureWriter(killed / "f.h5") as w:
            assert set(w.names()) <= set(names)
        if (killed / "f.h5").exists():
            hloc_h5.validate(killed / "f.h5")
    assert subprocess.run(cmd + out(killed), cwd=REPO, capture_output=True).returncode == 0
    assert db_state(killed / "db.db")["features"] == db_state(clean / "db.db")["features"]
    for name in names:
        a, b = hloc_h5.read(clean / "f.h5", name), hloc_h5.read(killed / "f.h5", name)
        for key in hloc_h5.DATASETS:
            np.testing.assert_array_equal(a[key], b[key])
    no_leftovers(killed / "db.db", killed / "f.h5")
