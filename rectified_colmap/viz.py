"""PNG visualisations of one image's planes, patches and keypoints (cv2 only).

``<out>/<name>.planes.png``: the image with the plane labels blended in (red/green/blue =
dominant direction, darker = antipode side), rectified regions outlined, keypoints as dots
(white = plain SIFT, yellow = found in a rectified patch).
``<out>/<name>.patches.png``: the rectified patches side by side.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pycolmap

from .conventions import to_opencv_points
from .rectify import warp_to_rectified

# label 2k + s -> BGR colour
_COLOURS = np.array(
    [[60, 60, 230], [30, 30, 120], [60, 200, 60], [30, 100, 30], [230, 120, 40], [120, 60, 20]],
    np.uint8,
)


def label_overlay(rgb: np.ndarray, labels: np.ndarray, alpha: float = 0.45) -> np.ndarray:
    """BGR image with labels (h, w) int8 (any grid covering the image) blended in."""
    H, W = rgb.shape[:2]
    lab = cv2.resize(labels.astype(np.int16), (W, H), interpolation=cv2.INTER_NEAREST)
    bgr = (
        cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)
        if rgb.ndim == 3
        else cv2.cvtColor(rgb, cv2.COLOR_GRAY2BGR)
    )
    colour = np.zeros_like(bgr)
    planar = lab >= 0
    colour[planar] = _COLOURS[lab[planar]]
    out = bgr.copy()
    out[planar] = (bgr[planar] * (1 - alpha) + colour[planar] * alpha).astype(np.uint8)
    out[~planar] = (bgr[~planar] * 0.6).astype(np.uint8)
    return out


def draw_planes(rgb: np.ndarray, result) -> np.ndarray:
    out = label_overlay(rgb, result.planes.labels)
    H, W = out.shape[:2]
    if result.coverage is not None:
        cover = cv2.resize(result.coverage, (W, H), interpolation=cv2.INTER_NEAREST)
        edges = (
            cv2.morphologyEx(
                (cover >= 0).astype(np.uint8), cv2.MORPH_GRADIENT, np.ones((3, 3), np.uint8)
            )
            > 0
        )
        out[edges] = (0, 255, 255)
    f = result.features
    if len(f):
        pts = np.round(to_opencv_points(f.keypoints)).astype(int)
        ok = (pts[:, 0] >= 0) & (pts[:, 0] < W) & (pts[:, 1] >= 0) & (pts[:, 1] < H)
        rect = f.patch >= 0
        out[pts[ok & ~rect, 1], pts[ok & ~rect, 0]] = (255, 255, 255)
        out[pts[ok & rect, 1], pts[ok & rect, 0]] = (0, 230, 255)
    return out


def draw_patches(
    gray: np.ndarray, camera: pycolmap.Camera, rects, height: int = 360
) -> np.ndarray | None:
    tiles = []
    for rect in rects:
        img = warp_to_rectified(gray, camera, rect)
        s = height / img.shape[0]
        tiles.append(
            cv2.resize(img, (max(1, round(img.shape[1] * s)), height), interpolation=cv2.INTER_AREA)
        )
        tiles.append(np.full((height, 4), 255, np.uint8))
    return np.concatenate(tiles[:-1], axis=1) if tiles else None


def save_visualizations(
    out_dir: Path, name: str, rgb: np.ndarray, camera: pycolmap.Camera, result
) -> list[Path]:
    """Write the PNGs of one image; returns their paths."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    stem = name.replace("/", "_")
    written = []
    if result.planes is not None:
        p = out_dir / f"{stem}.planes.png"
        cv2.imwrite(str(p), draw_planes(rgb, result))
        written.append(p)
    gray = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY) if rgb.ndim == 3 else rgb
    mosaic = draw_patches(gray, camera, result.rectifications)
    if mosaic is not None:
        p = out_dir / f"{stem}.patches.png"
        cv2.imwrite(str(p), mosaic)
        written.append(p)
    return written
