"""Pictures of the vanishing-point stage (research only: scripts/bench_vp.py, the VP tests).

``draw_segments`` (segments coloured by frame row) and ``draw_directions`` (needles towards
each direction's VP), from a rectified_colmap.vp.fusion.VpResult; images in are grayscale
(H, W) or RGB (H, W, 3) uint8, images out BGR. Colours: red/green/blue = frame rows (or
directions) 0/1/2.
"""

from __future__ import annotations

import cv2
import numpy as np
import pycolmap

from rectified_colmap import camera as cam_utils
from rectified_colmap.conventions import pixel_centers, to_opencv_points
from rectified_colmap.viz import bgr_image
from rectified_colmap.vp.fusion import VpResult

_VP_BGR = np.array([[60, 60, 235], [60, 210, 60], [235, 130, 40]])  # red, green, blue


def _cv_pt(xy: np.ndarray) -> tuple[int, int]:
    p = np.round(to_opencv_points(xy) * 16).astype(int)  # 4 fractional bits
    return int(p[0]), int(p[1])


def draw_segments(image: np.ndarray, result: VpResult) -> np.ndarray:
    """BGR image (darkened) with segments coloured by VP (red/green/blue = frame rows 0/1/2,
    grey = none)."""
    out = (bgr_image(image) * 0.5).astype(np.uint8)
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
    out = (bgr_image(image) * 0.6).astype(np.uint8)
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
