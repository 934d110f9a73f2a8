"""rectified_colmap.eval.aachen (no hloc): query lists, pair lists, result files, camera
databases, the mini Aachen and its errors. hloc itself: test_eval_hloc_compat; the real hloc
through scripts/aachen_hloc.py: tests/scripts/test_aachen_hloc_script.py."""

import numpy as np
import pycolmap
import pytest

from rectified_colmap.eval.aachen import (
    check_results,
    localization_errors,
    make_mini_aachen,
    read_query_list,
    recall,
    write_camera_database,
    write_query_list,
)
from rectified_colmap.eval.localize import QueryResult, write_poses
from rectified_colmap.eval.pairs import read_pair_list, write_pair_list


def test_query_list_roundtrip(tmp_path):
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
    (tmp_path / "bad.txt").write_text("a.jpg PINHOLE 640 480 500 320 240\n")
    with pytest.raises(ValueError, match="bad.txt:1: 3 params do not fit model PINHOLE"):
        read_query_list(tmp_path / "bad.txt")


def test_pair_list_io(tmp_path):
    pairs = [("db/1.jpg", "db/2.jpg"), ("db/2.jpg", "db/1.jpg")]
    write_pair_list(tmp_path / "p.txt", pairs)
    assert read_pair_list(tmp_path / "p.txt") == pairs
    with pytest.raises(ValueError, match="whitespace"):
        write_pair_list(tmp_path / "x.txt", [("a b.jpg", "c.jpg")])


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
        depth={"model": None},
        run={"progress": False},
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
