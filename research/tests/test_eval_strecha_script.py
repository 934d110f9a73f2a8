"""scripts/eval_strecha.py: cameras of a scene (one for Strecha, one per photo elsewhere)."""

from pathlib import Path

import numpy as np
import pycolmap
import pytest
from scripts_util import load_script


def write_scene(path: Path, cams: dict[str, list[float]]) -> None:
    """A sparse model whose images (name -> PINHOLE params) each have their own camera id."""
    rec = pycolmap.Reconstruction()
    for k, (name, params) in enumerate(cams.items(), 1):
        cam = pycolmap.Camera(model="PINHOLE", width=640, height=480, params=params, camera_id=k)
        rec.add_camera_with_trivial_rig(cam)
        rec.add_image_with_trivial_frame(
            pycolmap.Image(name=name, camera_id=k, image_id=k),
            pycolmap.Rigid3d(pycolmap.Rotation3d(), np.array([float(k), 0, 0])),
        )
    (path / "sparse").mkdir(parents=True)
    rec.write(str(path / "sparse"))


def test_scene_cameras_groups_images_by_intrinsics(tmp_path):
    es = load_script("eval_strecha")
    a, b = [500.0, 500, 320, 240], [600.0, 601, 320, 240]
    write_scene(tmp_path / "s", {"2.jpg": a, "1.jpg": b, "3.jpg": a})
    groups = es.scene_cameras(tmp_path / "s")
    assert groups == {
        ("PINHOLE", "600,601,320,240"): ["images/1.jpg"],
        ("PINHOLE", "500,500,320,240"): ["images/2.jpg", "images/3.jpg"],
    }
    with pytest.raises(SystemExit, match="2 different cameras; expected one"):
        es.scene_camera(tmp_path / "s")
    write_scene(tmp_path / "one", {"1.jpg": a, "2.jpg": a})
    assert es.scene_camera(tmp_path / "one") == ("PINHOLE", "500,500,320,240")
