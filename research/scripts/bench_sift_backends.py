#!/usr/bin/env python
"""The views' two SIFT backends on the same pixels: COLMAP's (pycolmap) and OpenCV's made
COLMAP's (``rectified_colmap.sift.opencv_sift``), from first octave -1 and 0.

For each photo, resized to each ``--sizes`` entry, in this one process, one thread, one
backend after the other on the same image (each warmed once, then the best of
``--repeat`` calls in CPU seconds):

- ``colmap``: one pycolmap SIFT call (a warm ``Sift`` extractor, as the CLI keeps for a
  folder of same-size photos; views get a new one per size);
- ``opencv``: ``opencv_sift`` (first octave 0: the image halved, OpenCV from its
  upsampled octave);
- how alike they are: the share of COLMAP's keypoints with an OpenCV keypoint within 0.5
  px, and the median descriptor cosine where the orientations agree within 2 degrees.

The budget is large enough for every point (``--max_num_features``), so both run their
whole scale space: the per-pixel cost the views pay (docs/architecture.md, "Features").

    python research/scripts/bench_sift_backends.py \\
        --image_path ../shared/data/strecha-dev/fountain-P11/images --max_images 2
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from functools import partial
from pathlib import Path

for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(var, "1")

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from rectified_colmap.config import SiftConf  # noqa: E402
from rectified_colmap.errors import run_script  # noqa: E402
from rectified_colmap.io.images import list_images, read_image  # noqa: E402
from rectified_colmap.sift import Sift, opencv_sift  # noqa: E402


def best_cpu_seconds(fn, repeat: int):
    """(the result of ``fn()``, the least CPU seconds of ``repeat`` calls after a warm-up)."""
    out = fn()
    best = np.inf
    for _ in range(repeat):
        t = time.process_time()
        out = fn()
        best = min(best, time.process_time() - t)
    return out, best


def alike(ref: tuple[np.ndarray, np.ndarray], other: tuple[np.ndarray, np.ndarray]):
    """(share of ``ref``'s keypoints with one of ``other``'s within 0.5 px, median cosine of
    their descriptors where the orientations agree within 2 degrees) for SIFT outputs
    ((N, 4) [x, y, scale, orientation], (N, 128) uint8)."""
    (m0, d0), (m1, d1) = ref, other
    if len(m0) == 0 or len(m1) == 0:
        return 0.0, float("nan")
    nearest = cv2.BFMatcher(cv2.NORM_L2).match(
        np.ascontiguousarray(m0[:, :2], np.float32), np.ascontiguousarray(m1[:, :2], np.float32)
    )
    j = np.array([m.trainIdx for m in nearest])
    dist = np.array([m.distance for m in nearest])
    near = dist < 0.5
    turn = np.abs(np.angle(np.exp(1j * (m1[j, 3] - m0[:, 3]))))
    both = near & (turn < np.deg2rad(2.0))
    a, b = d0[both].astype(float), d1[j[both]].astype(float)
    cos = (a * b).sum(1) / np.maximum(np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1), 1e-12)
    return float(near.mean()), float(np.median(cos)) if len(cos) else float("nan")


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--image_path", type=Path, required=True)
    p.add_argument("--max_images", type=int, default=2)
    p.add_argument("--sizes", nargs="+", default=["640x480", "1536x1024"], help="WxH")
    p.add_argument("--first_octaves", nargs="+", type=int, default=[-1, 0])
    p.add_argument("--max_num_features", type=int, default=10**6)
    p.add_argument("--repeat", type=int, default=3)
    return p.parse_args(argv)


def main(argv=None) -> int:
    args = parse_args(argv)
    conf = SiftConf()
    sift = Sift()
    n = args.max_num_features
    rows = []
    for name in list_images(args.image_path)[: args.max_images]:
        gray = cv2.cvtColor(read_image(args.image_path / name), cv2.COLOR_RGB2GRAY)
        for size in args.sizes:
            w, h = (int(v) for v in size.lower().split("x"))
            img = np.ascontiguousarray(cv2.resize(gray, (w, h), interpolation=cv2.INTER_AREA))
            for fo in args.first_octaves:
                ref, t_colmap = best_cpu_seconds(
                    partial(sift.run, img, conf, n, fo, slot="patch"), args.repeat
                )
                out, t_opencv = best_cpu_seconds(
                    partial(opencv_sift, img, conf, n, fo), args.repeat
                )
                near, cos = alike(ref, out)
                kps = (len(ref[0]), len(out[0]))
                rows.append((name, size, fo, t_colmap, t_opencv, *kps, near, cos))
    print(
        "| image | WxH | first octave | COLMAP s | OpenCV s | COLMAP s / MP | OpenCV s / MP "
        "| speed-up | keypoints COLMAP / OpenCV | within 0.5 px | descriptor cosine |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for name, size, fo, tc, to, kc, ko, near, cos in rows:
        w, h = (int(v) for v in size.split("x"))
        mp = w * h / 1e6
        print(
            f"| {name} | {size} | {fo} | {tc:.3f} | {to:.3f} | {tc / mp:.3f} | {to / mp:.3f} | "
            f"{tc / to:.2f}x | {kc} / {ko} | {100 * near:.0f} % | {cos:.3f} |"
        )
    for fo in args.first_octaves:
        sel = [r for r in rows if r[2] == fo]
        if sel:
            ratio = np.median([r[3] / r[4] for r in sel])
            print(f"# first octave {fo}: median speed-up {ratio:.2f}x over {len(sel)} image sizes")
    return 0


if __name__ == "__main__":
    sys.exit(run_script(main, "bench_sift_backends"))
