"""research/scripts/build_wide_pairs.py: a scene folder of wide-baseline pairs from a model."""

import numpy as np
from scripts_util import load_script
from tests.scenes import ring_reconstruction


def test_build_wide_pairs_script(tmp_path, caplog):
    import cv2

    from rectified_colmap.eval.pairs import read_pairs_with_gt
    from rectified_colmap.eval.wide_pairs import read_viewpoints

    mod = load_script("build_wide_pairs")

    rng = np.random.default_rng(1)
    tracks = [[0, 1, 2]] * 40 + [[0, 1]] * 20
    rec = ring_reconstruction([0.0, 40.0, 90.0], tracks, rng.uniform(-0.05, 0.05, (60, 3)))
    (tmp_path / "sparse").mkdir()
    rec.write(str(tmp_path / "sparse"))
    (tmp_path / "images").mkdir()
    for k in range(3):
        cv2.imwrite(str(tmp_path / "images" / f"im{k}.jpg"), rng.integers(0, 255, (480, 640, 3)))

    out = tmp_path / "out"
    argv = ["--model", str(tmp_path / "sparse"), "--image_path", str(tmp_path / "images")]
    argv += ["--output", str(out), "--name", "ring", "--min_viewpoint_deg", "45"]
    assert mod.main(argv) == 0
    scene = out / "ring"
    assert sorted(p.name for p in (scene / "images").iterdir()) == ["im0.jpg", "im1.jpg", "im2.jpg"]
    assert not (out / "ring.partial").exists() and not (scene / "stereo").exists()
    pairs = read_pairs_with_gt(scene / "pairs_with_gt.txt")
    names = [(p.name0, p.name1) for p in pairs]
    assert names == [("images/im1.jpg", "images/im2.jpg"), ("images/im0.jpg", "images/im2.jpg")]
    assert [round(p.rotation_deg) for p in pairs] == [50, 90]
    views = read_viewpoints(scene / "pairs.csv")
    assert set(views) == set(names) and 49 < views[names[0]] < 51

    # a missing model: a one-line error naming it, exit status 1
    bad = ["--model", str(tmp_path / "nope"), "--image_path", str(tmp_path / "images")]
    assert mod.main(bad + ["--output", str(out)]) == 1
    assert "nope: no such model folder" in caplog.text
