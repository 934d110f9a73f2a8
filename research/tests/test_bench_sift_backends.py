"""research/scripts/bench_sift_backends.py: both backends on the same pixels, a table row per
image, size and first octave, and how alike their keypoints are."""

import cv2
import numpy as np
from scripts_util import load_script


def test_backend_table_compares_the_same_pixels(tmp_path, capsys):
    bench = load_script("bench_sift_backends")
    rng = np.random.default_rng(0)
    noise = cv2.GaussianBlur(rng.uniform(0, 255, (240, 320)).astype(np.float32), (0, 0), 2.0)
    img = cv2.normalize(noise, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)
    cv2.imwrite(str(tmp_path / "a.png"), cv2.cvtColor(img, cv2.COLOR_GRAY2BGR))
    assert bench.main(["--image_path", str(tmp_path), "--sizes", "320x240", "--repeat", "1"]) == 0
    rows = [r for r in capsys.readouterr().out.splitlines() if r.startswith("| a.png")]
    assert [r.split("|")[3].strip() for r in rows] == ["-1", "0"]
    for row in rows:
        cells = [c.strip() for c in row.split("|")]
        colmap_kp, opencv_kp = (int(v) for v in cells[9].split(" / "))
        assert colmap_kp > 50 and 0.6 * colmap_kp < opencv_kp < 1.4 * colmap_kp, row
        assert float(cells[10].rstrip(" %")) > 50, row  # COLMAP's keypoints OpenCV finds too
        assert float(cells[11]) > 0.97, row
