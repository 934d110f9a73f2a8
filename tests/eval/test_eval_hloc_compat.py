"""rectified_colmap.eval.hloc_compat: the pycolmap 4.2 two-view-geometry fix and what a
database holds, hloc checks (API generation by signature, clear errors, arguments by
signature). The real hloc: tests/scripts/ (both scripts end to end)."""

import sys
from types import SimpleNamespace

import numpy as np
import pycolmap
import pytest

from rectified_colmap.eval.hloc_compat import (
    HlocError,
    call_with,
    hloc_generation,
    import_hloc,
    set_two_view_config,
    two_view_counts,
)
from rectified_colmap.eval.localize import build_reference


def _posed_scene(n_cams=3, seed=0):
    """Random points seen by cameras on a line: exact keypoints, unique descriptors."""
    rng = np.random.default_rng(seed)
    X = rng.uniform([-2, -1.5, 4], [2, 1.5, 7], (400, 3))
    desc = rng.standard_normal((400, 128)).astype(np.float32)
    desc /= np.linalg.norm(desc, axis=1, keepdims=True)
    cam = pycolmap.Camera(model="PINHOLE", width=640, height=480, params=[500, 500, 320, 240])
    feats, poses = {}, {}
    for k in range(n_cams):
        T = pycolmap.Rigid3d(
            pycolmap.Rotation3d(
                np.array([0, 0.05 * k, 0, 1]) / np.linalg.norm([0, 0.05 * k, 0, 1])
            ),
            np.array([-0.6 * k, 0, 0]),
        )
        Xc = X @ np.asarray(T.rotation.matrix()).T + np.asarray(T.translation)
        xy = np.asarray(cam.img_from_cam(Xc))
        feats[f"db/{k}.jpg"] = {"keypoints": xy, "descriptors": desc.T.copy()}
        poses[f"db/{k}.jpg"] = T
    return cam, feats, poses


def test_undefined_geometries_are_ignored_then_fixed(tmp_path):
    """pycolmap 4.2.1 triangulates nothing from UNDEFINED geometries (hloc's); the fix
    restores the points."""
    cam, feats, poses = _posed_scene()
    names = sorted(feats)
    ref = build_reference(names, {n: cam for n in names}, poses, feats, tmp_path / "w")
    assert ref.num_points3D() > 300
    db_path = tmp_path / "w" / "reference.db"
    with pycolmap.Database.open(db_path) as db:  # what hloc writes: no configuration
        pair_ids, geoms = db.read_two_view_geometries()
        for pid, g in zip(pair_ids, geoms):
            i, j = pycolmap.pair_id_to_image_pair(pid)
            db.update_two_view_geometry(
                i,
                j,
                pycolmap.TwoViewGeometry(inlier_matches=np.asarray(g.inlier_matches, np.uint32)),
            )

    def triangulate(out):
        # the posed model as build_reference makes it (one camera id per image)
        rec = pycolmap.Reconstruction()
        for i, n in enumerate(names, 1):
            c = pycolmap.Camera(model="PINHOLE", width=640, height=480, params=cam.params)
            c.camera_id = i
            rec.add_camera_with_trivial_rig(c)
            rec.add_image_with_trivial_frame(
                pycolmap.Image(name=n, camera_id=i, image_id=i), poses[n]
            )
        out.mkdir()
        return pycolmap.triangulate_points(rec, db_path, tmp_path, out).num_points3D()

    assert triangulate(tmp_path / "before") == 0
    inliers = two_view_counts(db_path)
    assert inliers["undefined_pairs"] == 3 and inliers["verified_pairs"] == 0
    assert set_two_view_config(db_path) == 3
    assert set_two_view_config(db_path) == 0  # nothing UNDEFINED any more
    assert triangulate(tmp_path / "after") > 300
    after = two_view_counts(db_path)
    assert after["undefined_pairs"] == 0 and after["verified_pairs"] == 3
    assert after["verified_inliers"] > 3 * 300
    for fn in (set_two_view_config, two_view_counts):
        with pytest.raises(FileNotFoundError, match="nope.db: database not found"):
            fn(tmp_path / "nope.db")


def _fake_triangulation(import_features):
    def f(*args, **kwargs):
        return None

    return SimpleNamespace(
        create_db_from_model=f,
        import_features=import_features,
        import_matches=f,
        geometric_verification=f,
        run_triangulation=f,
    )


def test_hloc_api_generation_by_signature():
    """Both generations say version 1.5: the signature tells them apart."""

    def new(image_ids, db, features_path):
        pass

    def old(image_ids, database_path, features_path):
        pass

    def other(image_ids, connection, features_path):
        pass

    assert hloc_generation(_fake_triangulation(new)) == "db"
    assert hloc_generation(_fake_triangulation(old)) == "path"
    with pytest.raises(HlocError, match="neither `db` nor `database_path`"):
        hloc_generation(_fake_triangulation(other))
    broken = _fake_triangulation(new)
    del broken.geometric_verification
    with pytest.raises(HlocError, match="no \\['geometric_verification'\\]"):
        hloc_generation(broken)


def test_hloc_missing_dependency_is_named(monkeypatch):
    """hloc present but torch absent: the error names torch, not 'hloc is missing'."""
    pytest.importorskip("hloc", reason="hloc not installed (docs/hloc.md)")
    for name in [n for n in sys.modules if n == "hloc" or n.startswith("hloc.")]:
        monkeypatch.delitem(sys.modules, name)
    monkeypatch.setitem(sys.modules, "torch", None)
    with pytest.raises(HlocError, match="cannot be imported.*'torch'"):
        import_hloc()


def test_hloc_missing_is_named(monkeypatch):
    monkeypatch.setitem(sys.modules, "hloc", None)  # import hloc -> ImportError
    with pytest.raises(HlocError, match="hloc is not installed.*not on PyPI"):
        import_hloc()


def test_call_with_passes_what_the_signature_names():
    def new_style(image_ids, reference, database_path, max_error=4.0):
        return (image_ids, reference, database_path, max_error)

    def old_style(database_path, pairs_path, verbose=False):
        return (database_path, pairs_path)

    avail = {
        "image_ids": 1,
        "reference": 2,
        "database_path": 3,
        "pairs_path": 4,
        "features_path": 5,
    }
    assert call_with(new_style, **avail) == (1, 2, 3, 4.0)
    assert call_with(old_style, **avail) == (3, 4)
    with pytest.raises(HlocError, match="needs \\['other'\\]"):
        call_with(lambda other: 0, **avail)
