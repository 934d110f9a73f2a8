"""scripts/resize_scenes.py: a scene resized with its intrinsics; the ground truth still holds."""

import cv2
import numpy as np
import pycolmap
from scripts_util import load_script

from rectified_colmap.eval.pairs import Pair, read_pairs_with_gt, write_pairs_with_gt


def test_resized_scene_projects_the_same_points(tmp_path):
    """A 3D point projects at s x its old pixel (COLMAP convention) in the resized scene,
    through the resized model's camera and through the pair file's K."""
    rs = load_script("resize_scenes")
    scene = tmp_path / "s"
    (scene / "images").mkdir(parents=True)
    rec = pycolmap.Reconstruction()
    cam = pycolmap.Camera(
        model="PINHOLE", width=64, height=48, params=[60.0, 61.0, 31.0, 25.0], camera_id=1
    )
    rec.add_camera_with_trivial_rig(cam)
    poses = [pycolmap.Rigid3d(pycolmap.Rotation3d(), np.array([0.0, 0, 0]))]
    poses.append(
        pycolmap.Rigid3d(pycolmap.Rotation3d(np.array([0, 0.2, 0])), np.array([1.0, 0, 0]))
    )
    for k, pose in enumerate(poses, 1):
        rec.add_image_with_trivial_frame(
            pycolmap.Image(name=f"{k}.jpg", camera_id=1, image_id=k), pose
        )
        cv2.imwrite(str(scene / "images" / f"{k}.jpg"), np.full((48, 64, 3), 40 * k, np.uint8))
    (scene / "sparse").mkdir()
    rec.write(str(scene / "sparse"))
    K = cam.calibration_matrix()
    T = np.eye(4)
    T[:3] = (poses[1] * poses[0].inverse()).matrix()
    write_pairs_with_gt(
        scene / "pairs_with_gt.txt", [Pair("images/1.jpg", "images/2.jpg", K, K, T)]
    )

    assert (
        rs.main(["--data", str(tmp_path), "--size", "160x96", "--output", str(tmp_path / "o")]) == 0
    )
    out = tmp_path / "o" / "s"
    assert cv2.imread(str(out / "images" / "2.jpg")).shape == (96, 160, 3)
    new = pycolmap.Reconstruction(str(out / "sparse"))
    X = np.array([0.3, -0.2, 4.0])
    s = np.array([160 / 64, 96 / 48])
    old_xy = cam.img_from_cam(X[None])[0]
    new_cam = new.cameras[1]
    np.testing.assert_allclose(new_cam.img_from_cam(X[None])[0], s * old_xy, atol=1e-9)
    (pair,) = read_pairs_with_gt(out / "pairs_with_gt.txt")
    for Kp in (pair.K0, pair.K1):
        p = Kp @ X
        np.testing.assert_allclose(p[:2] / p[2], s * old_xy, atol=1e-6)
    np.testing.assert_allclose(pair.T_0to1, T, atol=1e-9)
