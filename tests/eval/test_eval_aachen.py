"""The hloc-free parts of the Aachen pipeline: query lists, pairs, the pycolmap 4.2
two-view-geometry fix, result files, hloc checks (generation by signature, clear errors),
camera databases, the mini Aachen, LightGlue orientations. Real hloc: test_hloc_integration."""

import sys
from types import SimpleNamespace

import numpy as np
import pycolmap
import pytest

from rectified_colmap.eval.aachen import (
    HlocError,
    check_results,
    convert_oris_for_lightglue,
    filter_pairs,
    group_by_camera,
    hloc_generation,
    import_hloc,
    localization_errors,
    make_mini_aachen,
    read_query_list,
    recall,
    set_two_view_config,
    write_camera_database,
    write_query_list,
)
from rectified_colmap.eval.localize import QueryResult, build_reference, write_poses
from rectified_colmap.eval.pairs import read_pair_list, write_pair_list


def test_query_list_roundtrip_and_grouping(tmp_path):
    a = pycolmap.Camera(
        model="SIMPLE_RADIAL", width=1600, height=1200, params=[1469.2, 800, 600, -0.035]
    )
    b = pycolmap.Camera(model="PINHOLE", width=640, height=480, params=[500, 505, 320, 240])
    cams = {
        "query/night/nexus5x/IMG_2.jpg": a,
        "query/day/x.jpg": b,
        "query/night/nexus5x/IMG_1.jpg": a,
    }
    write_query_list(tmp_path / "q.txt", cams)
    back = read_query_list(tmp_path / "q.txt")
    assert list(back) == list(cams)
    assert back["query/day/x.jpg"].model.name == "PINHOLE"
    np.testing.assert_allclose(back["query/night/nexus5x/IMG_1.jpg"].params, a.params)
    groups = group_by_camera(back)
    assert [(g[0], g[2]) for g in groups] == [
        ("SIMPLE_RADIAL", ["query/night/nexus5x/IMG_1.jpg", "query/night/nexus5x/IMG_2.jpg"]),
        ("PINHOLE", ["query/day/x.jpg"]),
    ]
    (tmp_path / "bad.txt").write_text("a.jpg PINHOLE 640 480 500 320 240\n")
    with pytest.raises(ValueError, match="bad.txt:1: 3 params do not fit model PINHOLE"):
        read_query_list(tmp_path / "bad.txt")


def test_pairs_filtering_and_io(tmp_path):
    pairs = [
        ("db/1.jpg", "db/2.jpg"),
        ("db/2.jpg", "db/1.jpg"),
        ("db/1.jpg", "db/9.jpg"),
        ("query/q.jpg", "db/2.jpg"),
        ("db/3.jpg", "db/3.jpg"),
    ]
    model = {"db/1.jpg", "db/2.jpg", "db/3.jpg"}
    assert filter_pairs(pairs, model) == [("db/1.jpg", "db/2.jpg")]
    assert filter_pairs(pairs, model, both=False) == [
        ("db/1.jpg", "db/2.jpg"),
        ("query/q.jpg", "db/2.jpg"),
    ]
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
    assert set_two_view_config(db_path) == 3
    assert set_two_view_config(db_path) == 0  # nothing UNDEFINED any more
    assert triangulate(tmp_path / "after") > 300
    with pytest.raises(FileNotFoundError, match="nope.db: database not found"):
        set_two_view_config(tmp_path / "nope.db")


def test_results_file(tmp_path):
    T = pycolmap.Rigid3d(pycolmap.Rotation3d(), np.array([0.0, 1, 2]))
    res = {
        "query/night/a.jpg": QueryResult("query/night/a.jpg", T),
        "query/day/b.jpg": QueryResult("query/day/b.jpg", None),
    }
    write_poses(tmp_path / "r.txt", res)
    n, missing = check_results(tmp_path / "r.txt", list(res))
    assert n == 1 and missing == ["b.jpg"]
    (tmp_path / "bad.txt").write_text("zzz.jpg 1 0 0 0 0 0 0\n")
    with pytest.raises(ValueError, match="bad.txt:1: 'zzz.jpg' is not a query"):
        check_results(tmp_path / "bad.txt", list(res))
    (tmp_path / "bad2.txt").write_text("a.jpg 2 0 0 0 0 0 0\n")
    with pytest.raises(ValueError, match="not unit"):
        check_results(tmp_path / "bad2.txt", list(res))


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


def test_camera_database_feeds_extract(tmp_path, texture):
    """Database images get the given intrinsics (the reference model's), not a guess."""
    import cv2

    from rectified_colmap.extraction import extract

    (tmp_path / "img" / "db").mkdir(parents=True)
    cams = {}
    for k, f in enumerate((300.0, 410.0)):
        name = f"db/{k}.png"
        cv2.imwrite(str(tmp_path / "img" / name), texture(240, 320, seed=k))
        cams[name] = pycolmap.Camera(
            model="PINHOLE", width=320, height=240, params=[f, f + 1, 160, 120]
        )
    cams["db/2.png"] = cams["db/0.png"]
    cv2.imwrite(str(tmp_path / "img" / "db/2.png"), texture(240, 320, seed=2))
    assert write_camera_database(tmp_path / "c.db", cams) == 2
    s = extract(
        tmp_path / "img",
        database=tmp_path / "c.db",
        hloc_features=tmp_path / "f.h5",
        depth_model=None,
        progress=False,
    )
    assert sorted(s.done) == sorted(cams) and not s.failed
    with pycolmap.Database.open(tmp_path / "c.db") as db:
        got = {im.name: db.read_camera(im.camera_id) for im in db.read_all_images()}
        assert all(db.num_keypoints_for_image(im.image_id) > 0 for im in db.read_all_images())
    for name, cam in cams.items():
        np.testing.assert_allclose(got[name].params, cam.params)


def test_mini_aachen_layout_and_errors(tmp_path, texture):
    """make_mini_aachen from a posed scene: layout, downscaled cameras, held-out queries,
    ground truth; localization_errors/recall on a result file."""
    import cv2

    from rectified_colmap.eval.localize import format_pose

    scene = tmp_path / "scene"
    (scene / "images").mkdir(parents=True)
    rec = pycolmap.Reconstruction()
    for k in range(1, 8):
        name = f"{k:04d}.jpg"
        cv2.imwrite(str(scene / "images" / name), texture(400, 600, seed=k))
        cam = pycolmap.Camera(
            model="PINHOLE", width=600, height=400, params=[500, 502, 300.5, 199.5], camera_id=k
        )
        rec.add_camera_with_trivial_rig(cam)
        rec.add_image_with_trivial_frame(
            pycolmap.Image(name=name, camera_id=k, image_id=k),
            pycolmap.Rigid3d(pycolmap.Rotation3d(), np.array([0.5 * k, 0, 0])),
        )
    (scene / "sparse").mkdir()
    rec.write(str(scene / "sparse"))
    p = make_mini_aachen(scene, tmp_path / "mini", max_size=300)
    # sorted names, every third from the second: 0002, 0005 are queries
    queries = read_query_list(p["queries"])
    assert list(queries) == ["query/day/0002.jpg", "query/day/0005.jpg"]
    q = queries["query/day/0002.jpg"]
    assert (q.width, q.height) == (300, 200)
    np.testing.assert_allclose(q.params, [250, 251, 150.25, 99.75])
    ref = pycolmap.Reconstruction(str(p["reference_sfm"]))
    assert sorted(im.name for im in ref.images.values()) == [
        f"db/{k:04d}.jpg" for k in (1, 3, 4, 6, 7)
    ]
    assert cv2.imread(str(p["images"] / "db/0001.jpg")).shape[:2] == (200, 300)
    assert len(read_pair_list(p["loc_pairs"])) == 2 * 5
    gt = p["ground_truth"].read_text().splitlines()
    assert [line.split()[0] for line in gt] == list(queries)
    # a result file: one query 0.1 m off, the other missing
    off = pycolmap.Rigid3d(pycolmap.Rotation3d(), np.array([1.0 + 0.1, 0, 0]))
    (tmp_path / "r.txt").write_text(format_pose("0002.jpg", off) + "\n")
    err = localization_errors(tmp_path / "r.txt", p["ground_truth"])
    assert err["0002.jpg"] == pytest.approx((0.1, 0.0), abs=1e-6)
    assert err["0005.jpg"] == (np.inf, np.inf)
    assert recall(err) == [0.5, 0.5, 0.5]
    assert recall(err, failed=["query/day/0002.jpg"]) == [0.0, 0.0, 0.0]


def test_oris_for_lightglue(tmp_path):
    import h5py

    with h5py.File(tmp_path / "a.h5", "w") as f:
        g = f.create_group("db/x.jpg")
        g["keypoints"] = np.zeros((3, 2), np.float32)
        g["oris"] = np.array([0, 90, -180], np.float32)
        g["scales"] = np.ones(3, np.float32)
    assert convert_oris_for_lightglue(tmp_path / "a.h5", tmp_path / "b.h5") == 1
    with h5py.File(tmp_path / "b.h5") as f:
        np.testing.assert_allclose(f["db/x.jpg/oris"][()], [0, np.pi / 2, -np.pi], atol=1e-6)
        np.testing.assert_array_equal(f["db/x.jpg/scales"][()], 1)
    with pytest.raises(ValueError, match="new file"):
        convert_oris_for_lightglue(tmp_path / "a.h5", tmp_path / "a.h5")
