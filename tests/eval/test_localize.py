"""Offline localization on a rendered scene (two textured planes, known poses)."""

import numpy as np
import pycolmap
import pytest

from tests.conftest import look_at, plane_view, textured_image
from rectified_colmap.eval.localize import (
    QueryResult,
    accuracy_table,
    build_reference,
    format_pose,
    holdout_split,
    localize_queries,
    localize_with_model,
    pose_accuracy,
    pose_error,
    read_poses,
    write_poses,
)
from rectified_colmap.config import SiftConf
from rectified_colmap.sift import detect_sift
from rectified_colmap.io.hloc_h5 import HlocFeatureWriter

W, H, F = 320, 240, 260.0
K = np.array([[F, 0, W / 2], [0, F, H / 2], [0, 0, 1]])
# the wall y = 2 (facing -y) as a z = 0 plane: world = M @ local + o
M = np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]]).T
ORIGIN = np.array([0.0, 2.0, 1.5])


def render(tex_ground, tex_wall, R, t):
    img0, z0 = plane_view(tex_ground, 0.012, K, R, t, (W, H))
    img1, z1 = plane_view(tex_wall, 0.012, K, R @ M, R @ ORIGIN + t, (W, H))
    z0 = np.where(np.isfinite(z0), z0, np.inf)
    z1 = np.where(np.isfinite(z1), z1, np.inf)
    return np.where(z1 < z0, img1, img0).astype(np.uint8)


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """6 posed views of a ground + wall corner; plain SIFT in an hloc h5 file."""
    tmp = tmp_path_factory.mktemp("loc")
    tg, tw = textured_image(300, 300, 1), textured_image(300, 300, 2)
    assert np.allclose(M.T @ M, np.eye(3)) and np.linalg.det(M) > 0
    cam = pycolmap.Camera(model="PINHOLE", width=W, height=H, params=[F, F, W / 2, H / 2])
    poses, names = {}, []
    h5 = tmp / "feats.h5"
    with HlocFeatureWriter(h5) as writer:
        for k, x in enumerate(np.linspace(-1.0, 1.0, 6)):
            R, t = look_at((x, -2.2, 1.3 + 0.1 * k), (0.2 * x, 1.0, 0.6))
            name = f"images/{k:02d}.png"
            img = render(tg, tw, R, t)
            feats = detect_sift(img, SiftConf(max_num_features=2000))
            writer.write(name, feats, (W, H))
            poses[name] = pycolmap.Rigid3d(pycolmap.Rotation3d(R), t)
            names.append(name)
    return {"h5": h5, "poses": poses, "names": names, "camera": cam, "tmp": tmp}


def test_reference_and_localization(scene):
    names, poses, cam = scene["names"], scene["poses"], scene["camera"]
    db, queries = holdout_split(names, 3)
    assert queries == [names[1], names[4]] and len(db) == 4
    ref = build_reference(
        db, {n: cam for n in db}, {n: poses[n] for n in db}, scene["h5"], scene["tmp"] / "work"
    )
    assert ref.num_points3D() > 200
    # triangulated points lie on the two planes (ground z = 0 or wall y = 2)
    xyz = np.array([p.xyz for p in ref.points3D.values()])
    dist = np.minimum(np.abs(xyz[:, 2]), np.abs(xyz[:, 1] - 2.0))
    assert np.median(dist) < 0.01 and np.mean(dist < 0.05) > 0.9
    res = localize_queries(ref, {q: cam for q in queries}, scene["h5"])
    for q in queries:
        d, a = pose_error(res[q].cam_from_world, poses[q])
        assert d < 0.05 and a < 0.5, (q, d, a)
        assert res[q].num_inliers > 50
    acc = pose_accuracy(res, {q: poses[q] for q in queries})
    assert acc == [1.0, 1.0, 1.0]
    # a missing result counts as a failure
    assert pose_accuracy({queries[0]: res[queries[0]]}, {q: poses[q] for q in queries}) == [0.5] * 3


def test_localize_with_model_and_cli(scene, tmp_path, capsys):
    from rectified_colmap.cli import main

    rec = pycolmap.Reconstruction()
    cam = scene["camera"]
    cam.camera_id = 1
    rec.add_camera_with_trivial_rig(cam)
    for i, n in enumerate(scene["names"], 1):
        rec.add_image_with_trivial_frame(
            pycolmap.Image(name=n.split("/")[1], camera_id=1, image_id=i), scene["poses"][n]
        )
    model = tmp_path / "model"
    model.mkdir()
    rec.write_text(str(model))
    res, acc = localize_with_model(rec, scene["h5"], tmp_path / "w", name_prefix="images/")
    assert acc == [1.0, 1.0, 1.0] and len(res) == 2
    rc = main(
        [
            "localize",
            "--reference_model",
            str(model),
            "--features",
            f"sift={scene['h5']}",
            "--name_prefix",
            "images/",
            "--output_dir",
            str(tmp_path / "out"),
            "--no_progress",
        ]
    )
    assert rc == 0
    assert (
        "| sift | 2 | 100.0 | 100.0 | 100.0 |" in (tmp_path / "out" / "localization.md").read_text()
    )
    back = read_poses(tmp_path / "out" / "poses_sift.txt")
    assert set(back) == {"01.png", "04.png"}
    d, a = pose_error(back["04.png"], scene["poses"]["images/04.png"])
    assert d < 0.05 and a < 0.5
    rc = main(
        [
            "localize",
            "--reference_model",
            str(tmp_path / "nope"),
            "--features",
            f"sift={scene['h5']}",
            "--output_dir",
            str(tmp_path / "o"),
        ]
    )
    assert rc == 2 and "not a directory" in capsys.readouterr().err


def test_pose_format_roundtrip(tmp_path):
    R = pycolmap.Rotation3d(np.array([0.1, -0.2, 0.3, 0.9]) / np.linalg.norm([0.1, -0.2, 0.3, 0.9]))
    T = pycolmap.Rigid3d(R, np.array([1.0, 2.0, -3.0]))
    line = format_pose("q/night/a.jpg", T)
    vals = [float(v) for v in line.split()[1:]]
    assert vals[0] > 0 and np.isclose(vals[0], 0.9 / np.linalg.norm([0.1, -0.2, 0.3, 0.9]))
    n = write_poses(
        tmp_path / "r.txt",
        {"q/night/a.jpg": QueryResult("q/night/a.jpg", T), "q/b.jpg": QueryResult("q/b.jpg", None)},
    )
    assert n == 1
    back = read_poses(tmp_path / "r.txt")
    assert pose_error(back["a.jpg"], T) == pytest.approx((0, 0), abs=1e-6)
    assert "| m | 3 | 50.0 |" in accuracy_table(
        {"m": [0.5, 1, 1]}, ((1, 1), (2, 2), (3, 3)), {"m": 3}
    )
    with pytest.raises(ValueError, match="at least 2"):
        holdout_split(["a", "b"], 1)
