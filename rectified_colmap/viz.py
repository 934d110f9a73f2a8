"""PNG visualisations of one image's planes, patches and keypoints (cv2 only).

``<out>/<name>.planes.png``: the image with the plane labels blended in (red/green/blue =
dominant direction, darker = antipode side), rectified regions outlined, keypoints as dots
(white = plain SIFT, yellow = found in a rectified patch).
``<out>/<name>.patches.png``: the rectified patches side by side.

Vanishing points (a vp.fusion.VpResult, e.g. for scripts/bench_vp.py): ``draw_segments``
(segments coloured by frame row) and ``draw_directions`` (needles towards each direction's
VP); ``save_png`` writes a BGR image. Colours: red/green/blue = frame rows (or directions)
0/1/2; images in are grayscale (H, W) or RGB (H, W, 3) uint8, images out BGR (H, W, 3).
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pycolmap

from . import camera as cam_utils
from .conventions import pixel_centers, to_opencv_points
from .rectify import warp_to_rectified
from .vp.fusion import VpResult

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


# -- vanishing points ---------------------------------------------------------------------

_VP_BGR = np.array([[60, 60, 235], [60, 210, 60], [235, 130, 40]])  # red, green, blue


def _bgr(image: np.ndarray) -> np.ndarray:
    return (
        cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
        if image.ndim == 2
        else cv2.cvtColor(image, cv2.COLOR_RGB2BGR)
    )


def _cv_pt(xy: np.ndarray) -> tuple[int, int]:
    p = np.round(to_opencv_points(xy) * 16).astype(int)  # 4 fractional bits
    return int(p[0]), int(p[1])


def draw_segments(image: np.ndarray, result: VpResult) -> np.ndarray:
    """BGR image (darkened) with segments coloured by VP (red/green/blue = frame rows 0/1/2,
    grey = none)."""
    out = (_bgr(image) * 0.5).astype(np.uint8)
    seg = result.segments
    for xy, lab in zip(seg.xy, seg.labels):
        colour = (150, 150, 150) if lab < 0 else tuple(int(c) for c in _VP_BGR[lab])
        cv2.line(out, _cv_pt(xy[0]), _cv_pt(xy[1]), colour, 2, cv2.LINE_AA, shift=4)
    return out


def draw_directions(
    image: np.ndarray,
    camera: pycolmap.Camera,
    result: VpResult,
    depth_directions: np.ndarray | None = None,
    grid: int = 6,
) -> np.ndarray:
    """BGR image with, at a grid of anchors, needles pointing to each direction's VP:
    thick = fused directions (or the frame), thin white = the depth directions."""
    out = (_bgr(image) * 0.6).astype(np.uint8)
    W, H = camera.width, camera.height
    length = 0.04 * max(W, H)
    anchors = pixel_centers(grid, max(2, grid * H // W), W, H).reshape(-1, 2)
    rays = cam_utils.image_to_rays(camera, anchors)

    def needles(D, colours, thickness):
        for d, colour in zip(D, colours):
            tip = cam_utils.rays_to_image(camera, rays + 1e-3 * d)
            u = tip - anchors
            u /= np.maximum(np.linalg.norm(u, axis=1, keepdims=True), 1e-12)
            for p, q in zip(anchors - length * u, anchors + length * u):
                if np.isfinite(p).all() and np.isfinite(q).all():
                    cv2.line(out, _cv_pt(p), _cv_pt(q), colour, thickness, cv2.LINE_AA, shift=4)

    D = result.directions if result.directions is not None else result.frame
    if D is not None:
        needles(D, [tuple(int(c) for c in col) for col in _VP_BGR], 3)
    if depth_directions is not None:
        needles(depth_directions, [(255, 255, 255)] * 3, 1)
    return out


def save_png(path: Path | str, image: np.ndarray) -> Path:
    """Write a BGR (H, W, 3) or gray (H, W) uint8 image as PNG (parent folders created);
    returns the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), image):
        raise OSError(f"{path}: cannot write PNG")
    return path
