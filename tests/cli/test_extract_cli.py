"""End-to-end `rectified-colmap extract` on plane views with known depth."""

import sqlite3
from pathlib import Path

import cv2
import h5py
import numpy as np
import pytest

from rectified_colmap.cli import main
from rectified_colmap.extraction import extract
from rectified_colmap.io import hloc_h5
from tests.conftest import look_at, plane_view, textured_image

K = np.array([[400.0, 0, 200], [0, 400, 150], [0, 0, 1]])
PARAMS = "400,400,200,150"


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    root = tmp_path_factory.mktemp("scene")
    images, depths = root / "images", root / "depths"
    (images / "sub").mkdir(parents=True)
    (depths / "sub").mkdir(parents=True)
    tex = textured_image(600, 600, 7)
    eyes = [[2.5, -4.0, 2.0], [-2.0, -4.0, 1.5], [0.5, -3.5, 3.5]]
    for i, eye in enumerate(eyes):
        R, t = look_at(eye, [0, 0, 0])
        img, z = plane_view(tex, 0.01, K, R, t, (400, 300))
        cv2.imwrite(str(images / "sub" / f"{i}.png"), img)
        np.save(depths / "sub" / f"{i}.png.npy", z)
    (images / "sub" / "broken.png").write_bytes(b"not an image at all")
    return images, depths


def _db_rows(db):
    with sqlite3.connect(db) as con:
        kp = dict(
            con.execute(
                "SELECT i.name, k.cols FROM keypoints k JOIN images i ON i.image_id = k.image_id"
            ).fetchall()
        )
        n = dict(
            con.execute(
                "SELECT i.name, k.rows FROM keypoints k JOIN images i ON i.image_id = k.image_id"
            ).fetchall()
        )
    return kp, n


def test_cli_extract_writes_both_formats_reports_bad_image_and_resumes(scene, tmp_path):
    images, depths = scene
    db, h5 = tmp_path / "db.db", tmp_path / "f.h5"
    args = [
        "extract",
        "--database_path",
        str(db),
        "--image_path",
        str(images),
        "--depth_path",
        str(depths),
        "--depth_model",
        "none",
        "--camera_model",
        "PINHOLE",
        "--camera_params",
        PARAMS,
        "--hloc_features",
        str(h5),
        "--no_progress",
    ]
    assert main(args) == 1  # broken.png failed, the rest went on
    cols, rows = _db_rows(db)
    assert sorted(cols) == ["sub/0.png", "sub/1.png", "sub/2.png"]
    assert set(cols.values()) == {6}
    assert hloc_h5.list_names(h5) == sorted(cols)
    with h5py.File(h5, "r") as f:
        g = f["sub/0.png"]
        assert g["keypoints"].shape[0] == rows["sub/0.png"]
        assert g["descriptors"].shape == (128, rows["sub/0.png"])
        np.testing.assert_array_equal(g["image_size"][()], [400, 300])
    # resume: nothing is redone, nothing duplicated
    mtime = h5.stat().st_mtime_ns
    summary = extract(
        images,
        database=db,
        hloc_features=h5,
        reader={"camera_model": "PINHOLE", "camera_params": PARAMS},
        depth={"path": depths, "model": "none"},
        run={"progress": False},
    )
    assert sorted(summary.skipped) == sorted(cols)
    assert list(summary.failed) == ["sub/broken.png"]
    assert "cannot decode" in summary.failed["sub/broken.png"]
    assert _db_rows(db) == (cols, rows)
    assert h5.stat().st_mtime_ns == mtime
    with sqlite3.connect(db) as con:
        # the broken image got neither a camera nor an image row
        assert con.execute("SELECT COUNT(*) FROM cameras").fetchone()[0] == 3
        assert con.execute("SELECT COUNT(*) FROM images").fetchone()[0] == 3


def test_extract_rectifies_with_depth_and_is_plain_without(scene, tmp_path):
    images, depths = scene
    names = ["sub/0.png", "sub/1.png"]
    kw = dict(
        reader={"image_list": names, "camera_model": "PINHOLE", "camera_params": PARAMS},
        run={"progress": False},
    )
    with_depth = extract(
        images, hloc_features=tmp_path / "r.h5", depth={"path": depths, "model": "none"}, **kw
    )
    without = extract(images, hloc_features=tmp_path / "p.h5", depth={"model": "none"}, **kw)
    assert with_depth.ok and without.ok
    assert with_depth.plain == [] and sorted(without.plain) == names
    from rectified_colmap.sift import detect_sift

    for name in names:
        plain = detect_sift(cv2.imread(str(images / name), cv2.IMREAD_GRAYSCALE))
        p = hloc_h5.read(tmp_path / "p.h5", name)
        np.testing.assert_allclose(p["keypoints"], plain.keypoints, atol=1e-3)
        r = hloc_h5.read(tmp_path / "r.h5", name)
        # rectified keypoints on top of plain SIFT's (at most +50 %): many, at least a fifth
        # of plain SIFT's count, are not where plain SIFT put one
        d = np.linalg.norm(r["keypoints"][:, None] - p["keypoints"][None], axis=2).min(1)
        assert (d > 0.5).sum() > 0.2 * len(p["keypoints"])


def test_single_camera_and_workers(scene, tmp_path):
    images, depths = scene
    db = tmp_path / "db.db"
    s = extract(
        images,
        database=db,
        reader={
            "image_list": ["sub/0.png", "sub/1.png", "sub/2.png"],
            "camera_model": "PINHOLE",
            "camera_params": PARAMS,
            "single_camera": True,
        },
        depth={"path": depths, "model": "none"},
        run={"num_workers": 2, "progress": False},
    )
    assert s.ok and len(s.done) == 3
    with sqlite3.connect(db) as con:
        assert con.execute("SELECT COUNT(DISTINCT camera_id) FROM images").fetchone()[0] == 1
        assert con.execute("SELECT COUNT(*) FROM cameras").fetchone()[0] == 1


def test_cli_rejects_params_without_model(scene, tmp_path, caplog):
    images, _ = scene
    assert (
        main(
            [
                "extract",
                "--database",
                str(tmp_path / "x.db"),
                "--image_path",
                str(images),
                "--camera_params",
                "1,2,3,4",
            ]
        )
        == 2
    )
    assert "--camera_params needs --camera_model" in caplog.text
    assert not (tmp_path / "x.db").exists()


@pytest.mark.parametrize("camera", ["params", "exif"])
def test_each_image_is_decoded_once(scene, tmp_path, monkeypatch, camera):
    """One decode of each image in a whole extraction: the camera's size comes from the
    file header, the worker decodes, the pictures reuse its pixels. A camera from EXIF is
    read by pycolmap (COLMAP's own EXIF rules), once per new camera, never without."""
    import pycolmap

    images, depths = scene
    names = ["sub/0.png", "sub/1.png", "sub/2.png"]
    decodes, exif = [], []
    imread, infer = cv2.imread, pycolmap.infer_camera_from_image

    def counting_imread(path, *args):
        decodes.append(Path(path).relative_to(images).as_posix())
        return imread(path, *args)

    def counting_infer(path, *args):
        exif.append(Path(path).relative_to(images).as_posix())
        return infer(path, *args)

    monkeypatch.setattr(cv2, "imread", counting_imread)
    monkeypatch.setattr(pycolmap, "infer_camera_from_image", counting_infer)
    cams = dict(camera_model="PINHOLE", camera_params=PARAMS) if camera == "params" else {}
    s = extract(
        images,
        database=tmp_path / "db.db",
        hloc_features=tmp_path / "f.h5",
        reader={"image_list": names, **cams},
        depth={"path": depths, "model": "none"},
        run={"visualize": tmp_path / "viz", "progress": False},
    )
    assert s.ok and sorted(s.done) == names
    assert len(list((tmp_path / "viz").glob("*.planes.png"))) == 3  # the pictures were drawn
    assert sorted(decodes) == names
    assert sorted(exif) == ([] if camera == "params" else names)
