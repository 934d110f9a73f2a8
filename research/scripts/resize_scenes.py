#!/usr/bin/env python
"""Resized copies of Strecha-style scenes, intrinsics and ground truth rescaled with them.

For each scene of ``--data`` (``<scene>/images``, ``<scene>/sparse`` COLMAP model,
``<scene>/pairs_with_gt.txt``): the images resized to ``--size WxH`` (INTER_CUBIC up,
INTER_AREA down; JPEG quality 95), the model's cameras rescaled (pycolmap
``Camera.rescale``: COLMAP's convention, where pixel coordinates scale by a plain
multiplication) and the pair file's intrinsics scaled the same way; poses are unchanged.
Upscaled Strecha is the proxy for 3-24 MP photos (docs/benchmarks.md "The exact pool at
3-24 MP"): the same scenes and ground truth, with SIFT's pixels per feature of a large photo.

    python scripts/resize_scenes.py --data ../shared/data/strecha-dev --size 3072x2048 \\
        --output outputs/strecha-3072
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2
import numpy as np
import pycolmap

from rectified_colmap.errors import run_script
from rectified_colmap.eval.pairs import read_pairs_with_gt, write_pairs_with_gt


def parse_size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected WxH, got {text!r}") from None
    if w < 8 or h < 8:
        raise argparse.ArgumentTypeError(f"size {text!r} is too small")
    return w, h


def scale_matrix(sx: float, sy: float) -> np.ndarray:
    """Pixel scaling in COLMAP's convention (a plain multiplication), as a 3x3 matrix."""
    return np.diag([sx, sy, 1.0])


def resize_scene(scene: Path, out: Path, size: tuple[int, int]) -> int:
    """One scene resized into ``out``; returns the number of images."""
    rec = pycolmap.Reconstruction(str(scene / "sparse"))
    (out / "images").mkdir(parents=True, exist_ok=True)
    scales = {}
    for image in rec.images.values():
        img = cv2.imread(str(scene / "images" / image.name))
        if img is None:
            raise ValueError(f"{scene / 'images' / image.name}: cannot decode image")
        h, w = img.shape[:2]
        up = size[0] * size[1] > w * h
        img = cv2.resize(img, size, interpolation=cv2.INTER_CUBIC if up else cv2.INTER_AREA)
        cv2.imwrite(str(out / "images" / image.name), img, [cv2.IMWRITE_JPEG_QUALITY, 95])
        scales[f"images/{image.name}"] = (size[0] / w, size[1] / h)
    for camera in rec.cameras.values():
        camera.rescale(*size)
    (out / "sparse").mkdir(exist_ok=True)
    rec.write_text(str(out / "sparse"))
    pairs = read_pairs_with_gt(scene / "pairs_with_gt.txt")
    for p in pairs:
        p.K0 = scale_matrix(*scales[p.name0]) @ p.K0
        p.K1 = scale_matrix(*scales[p.name1]) @ p.K1
    write_pairs_with_gt(out / "pairs_with_gt.txt", pairs)
    return len(scales)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--data", type=Path, required=True, help="folder of scenes")
    p.add_argument("--size", type=parse_size, required=True, help="WxH, e.g. 3072x2048")
    p.add_argument("--output", type=Path, required=True)
    p.add_argument("--scenes", nargs="*", default=None, help="scene names (default: all)")
    args = p.parse_args(argv)
    if not args.data.is_dir():
        raise FileNotFoundError(f"{args.data}: not a folder")
    scenes = (
        [args.data / s for s in args.scenes]
        if args.scenes
        else sorted(d for d in args.data.iterdir() if (d / "sparse").is_dir())
    )
    if not scenes:
        raise ValueError(f"{args.data}: no scene (a folder with sparse/) in it")
    for scene in scenes:
        n = resize_scene(scene, args.output / scene.name, args.size)
        w, h = args.size
        print(f"{scene.name}: {n} images at {w}x{h} -> {args.output / scene.name}")
    return 0


if __name__ == "__main__":
    sys.exit(run_script(main, "resize_scenes"))
