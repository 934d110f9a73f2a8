"""The hloc-free parts of the Aachen pipeline: query lists, pairs, the pycolmap 4.2
two-view-geometry fix, result files, and the script's hloc checks."""

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pycolmap
import pytest

from rectified_colmap.eval.aachen import (check_results, filter_pairs, group_by_camera,
                                          read_query_list, set_two_view_config,
                                          write_query_list)
from rectified_colmap.eval.localize import QueryResult, build_reference, write_poses
from rectified_colmap.eval.pairs import read_pair_list, write_pair_list

ROOT = Path(__file__).resolve().parents[1]


def load_script():
    spec = importlib.util.spec_from_file_location("aachen_hloc", ROOT / "scripts" / "aachen_hloc.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_query_list_roundtrip_and_grouping(tmp_path):
    a = pycolmap.Camera(model="SIMPLE_RADIAL", width=1600, height=1200,
                        params=[1469.2, 800, 600, -0.035])
    b = pycolmap.Camera(model="PINHOLE", width=640, height=480, params=[500, 505, 320, 240])
    cams = {"query/night/nexus5x/IMG_2.jpg": a, "query/day/x.jpg": b,
            "query/night/nexus5x/IMG_1.jpg": a}
    write_query_list(tmp_path / "q.txt", cams)
    back = read_query_list(tmp_path / "q.txt")
    assert list(back) == list(cams)
    assert back["query/day/x.jpg"].model.name == "PINHOLE"
    np.testing.assert_allclose(back["query/night/nexus5x/IMG_1.jpg"].params, a.params)
    groups = group_by_camera(back)
    assert [(g[0], g[2]) for g in groups] == [
        ("SIMPLE_RADIAL", ["query/night/nexus5x/IMG_1.jpg", "query/night/nexus5x/IMG_2.jpg"]),
        ("PINHOLE", ["query/day/x.jpg"])]
    (tmp_path / "bad.txt").write_text("a.jpg PINHOLE 640 480 500 320 240\n")
    with pytest.raises(ValueError, match="bad.txt:1: 3 params do not fit model PINHOLE"):
        read_query_list(tmp_path / "bad.txt")


def test_pairs_filtering_and_io(tmp_path):
    pairs = [("db/1.jpg", "db/2.jpg"), ("db/2.jpg", "db/1.jpg"), ("db/1.jpg", "db/9.jpg"),
             ("query/q.jpg", "db/2.jpg"), ("db/3.jpg", "db/3.jpg")]
    model = {"db/1.jpg", "db/2.jpg", "db/3.jpg"}
    assert filter_pairs(pairs, model) == [("db/1.jpg", "db/2.jpg")]
    assert filter_pairs(pairs, model, both=False) == [("db/1.jpg", "db/2.jpg"),
                                                      ("query/q.jpg", "db/2.jpg")]
    write_pair_list(tmp_path / "p.txt", pairs[:2])
    assert read_pair_list(tmp_path / "p.txt") == pairs[:2]
    with pytest.raises(ValueError, match="whitespace"):
        write_pair_list(tmp_path / "x.txt", [("a b.jpg", "c.jpg")])


def _posed_scene(n_cams=3, seed=0):
    """Random points seen by cameras on a line: exact keypoints, unique descriptors."""
    rng = np.random.default_rng(seed)
    X = rng.uniform([-2, -1.5, 4], [2, 1.5, 7], (400, 3))
    desc = rng.standard_normal((400, 128)).astype(np.float32)
    desc /= np.linalg.norm(desc, axis=1, keepdims=True)
    cam = pycolmap.Camera(model="PINHOLE", width=640, height=480, params=[500, 500, 320, 240])
    feats, poses = {}, {}
    for k in range(n_cams):
        T = pycolmap.Rigid3d(pycolmap.Rotation3d(np.array([0, 0.05 * k, 0, 1]) /
                                                 np.linalg.norm([0, 0.05 * k, 0, 1])),
                             np.array([-0.6 * k, 0, 0]))
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
            db.update_two_view_geometry(i, j, pycolmap.TwoViewGeometry(
                inlier_matches=np.asarray(g.inlier_matches, np.uint32)))

    def triangulate(out):
        # the posed model as build_reference makes it (one camera id per image)
        rec = pycolmap.Reconstruction()
        for i, n in enumerate(names, 1):
            c = pycolmap.Camera(model="PINHOLE", width=640, height=480, params=cam.params)
            c.camera_id = i
            rec.add_camera_with_trivial_rig(c)
            rec.add_image_with_trivial_frame(pycolmap.Image(name=n, camera_id=i, image_id=i),
                                             poses[n])
        out.mkdir()
        return pycolmap.triangulate_points(rec, db_path, tmp_path, out).num_points3D()

    assert triangulate(tmp_path / "before") == 0
    assert set_two_view_config(db_path) == 3
    assert set_two_view_config(db_path) == 0  # nothing UNDEFINED any more
    assert triangulate(tmp_path / "after") > 300
    with pytest.raises(FileNotFoundError, match="nope.db: database not found"):
        set_two_view_config(tmp_path / "nope.db")


def test_results_file(tmp_path):
    T = pycolmap.Rigid3d(pycolmap.Rotation3d(), np.array([0.0, 1, 2]))
    res = {"query/night/a.jpg": QueryResult("query/night/a.jpg", T),
           "query/day/b.jpg": QueryResult("query/day/b.jpg", None)}
    write_poses(tmp_path / "r.txt", res)
    n, missing = check_results(tmp_path / "r.txt", list(res))
    assert n == 1 and missing == ["b.jpg"]
    (tmp_path / "bad.txt").write_text("zzz.jpg 1 0 0 0 0 0 0\n")
    with pytest.raises(ValueError, match="bad.txt:1: 'zzz.jpg' is not a query"):
        check_results(tmp_path / "bad.txt", list(res))
    (tmp_path / "bad2.txt").write_text("a.jpg 2 0 0 0 0 0 0\n")
    with pytest.raises(ValueError, match="not unit"):
        check_results(tmp_path / "bad2.txt", list(res))


def test_script_hloc_checks(monkeypatch):
    mod = load_script()
    monkeypatch.setitem(sys.modules, "hloc", None)  # import hloc -> ImportError
    with pytest.raises(SystemExit, match="not on PyPI"):
        mod.require_hloc()

    def new_style(image_ids, reference, database_path, max_error=4.0):
        return (image_ids, reference, database_path, max_error)

    def old_style(database_path, pairs_path, verbose=False):
        return (database_path, pairs_path)

    avail = dict(image_ids=1, reference=2, database_path=3, pairs_path=4, features_path=5)
    assert mod.call_with(new_style, **avail) == (1, 2, 3, 4.0)
    assert mod.call_with(old_style, **avail) == (3, 4)
    with pytest.raises(SystemExit, match="needs"):
        mod.call_with(lambda other: 0, **avail)
