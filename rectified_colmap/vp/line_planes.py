"""Depth-free planes: plane patches from a line-derived Manhattan frame, beside planes.py.

Input: the grayscale image (H, W) uint8, its camera and the work-grid shape (h, w) (the grid
of rectified_colmap.planes). Output: a planes.PlaneResult on the work grid, like
planes.detect_planes gives from depth: directions (3, 3) (the confident frame, or None),
labels (h, w) int8 (2k + s, -1 = none) and ``Patch``es with work-grid masks and normals
facing the camera; and the VpResult behind it (vp.fusion).

Used for images without depth (conf.depth_free): the confident frame gives the directions,
and the patches come from ``line_support_patches`` (conf.depth_free_regions = 'lines': a
plane with normal F[k] is where segments of both other VPs are dense, see its docstring,
split by the sign of ray . F[k]) or ``whole_image_patches`` ('whole', the paper's VP
baseline: per trusted axis, each side of its vanishing line entirely; the patches overlap).
"""

from __future__ import annotations

import cv2
import numpy as np
import pycolmap

from .. import camera as cam_utils
from ..config import VpConf
from ..conventions import to_opencv_points
from ..planes import Patch, PlaneResult
from .fusion import VpResult, manhattan_from_image


def _fill_holes(mask: np.ndarray) -> np.ndarray:
    """Background components not touching the border become foreground."""
    n, lab = cv2.connectedComponents((~mask).astype(np.uint8), connectivity=4)
    border = np.unique(np.concatenate([lab[0], lab[-1], lab[:, 0], lab[:, -1]]))
    outside = np.zeros(n, bool)
    outside[border] = True
    return mask | ~outside[lab]


def line_support_patches(
    result: VpResult,
    camera: pycolmap.Camera,
    work_shape: tuple[int, int],
    conf: VpConf = VpConf(),
    min_area_frac: float = 0.005,
) -> tuple[list[Patch], np.ndarray]:
    """Depth-free plane patches from labelled segments -> (patches, labels (h, w) int8).

    A plane with normal F[k] contains the lines of the two other VPs, so its image is where
    segments of BOTH other families are dense. Per family j, the density D_j is the
    fraction of cells of a (2r+1)^2 window (r = conf.support_radius_frac x max(h, w))
    crossed by its segments (rasterised on the work grid); axis k scores
    min(D_a, D_b) and needs, for both, conf.support_min_lines window-crossing lines
    (D >= support_min_lines / (2r + 1)). Each cell takes the best axis; the two sides of
    the axis' vanishing line (sign of ray . F[k]) are separate planes (normal facing the
    camera). Holes are filled; components under ``min_area_frac`` of the grid are dropped.
    Labels follow rectified_colmap.planes (2k + s, s = 1 when the normal is -F[k]).
    ``result`` must carry a confident frame (``result.directions``, e.g. from
    manhattan_from_image); only axes whose two in-plane VPs are observed get patches."""
    h, w = work_shape
    labels = np.full((h, w), -1, np.int8)
    F, seg = result.directions, result.segments
    if F is None or len(seg) == 0 or result.manhattan is None:
        return [], labels
    observed = result.manhattan.observed
    r = max(1, int(round(conf.support_radius_frac * max(h, w))))
    k2 = 2 * r + 1
    scale = np.array([w / camera.width, h / camera.height])
    dens = np.zeros((3, h, w), np.float32)
    for j in np.flatnonzero(observed):
        xy = to_opencv_points(seg.xy[seg.labels == j] * scale)
        lines = [p for p in np.round(xy * 16).astype(np.int32)]  # 4 fractional bits
        m = np.zeros((h, w), np.uint8)
        cv2.polylines(m, lines, False, 1, 1, cv2.LINE_8, shift=4)
        dens[j] = cv2.boxFilter(m.astype(np.float32), -1, (k2, k2), borderType=cv2.BORDER_CONSTANT)
    score = np.zeros((3, h, w), np.float32)
    for k in range(3):
        a, b = (k + 1) % 3, (k + 2) % 3
        if observed[a] and observed[b]:
            score[k] = np.minimum(dens[a], dens[b])
    best = np.argmax(score, 0)
    valid = score.max(0) >= conf.support_min_lines / k2
    side = (cam_utils.grid_rays(camera, w, h) @ F.T) > 0  # (h, w, 3): normal is -F[k]
    patches = []
    for k in range(3):
        for s in (0, 1):
            mask = _fill_holes(valid & (best == k) & (side[..., k] == bool(s)))
            n, comp, stats, _ = cv2.connectedComponentsWithStats(
                mask.astype(np.uint8), connectivity=8
            )
            for c in np.flatnonzero(stats[1:, cv2.CC_STAT_AREA] >= min_area_frac * h * w) + 1:
                pm = comp == c
                labels[pm] = 2 * k + s
                patches.append(Patch(pm, k, F[k] * (-1.0 if s else 1.0), float(pm.mean())))
    patches.sort(key=lambda p: -p.area_frac)
    return patches, labels


def whole_image_patches(
    result: VpResult,
    camera: pycolmap.Camera,
    work_shape: tuple[int, int],
    conf: VpConf = VpConf(),
    min_area_frac: float = 0.005,
) -> tuple[list[Patch], np.ndarray]:
    """The paper's VP baseline: whole-image warps -> (patches, labels (h, w) int8).

    For each trusted frame axis k (``result.snapped``) and each side of its vanishing line,
    one patch holds ALL cells whose ray r sees the plane of normal n = +-F[k] from the
    front (r . n < 0); n faces the camera. No segmentation: the patches overlap (a cell
    lies in one patch per trusted axis, so in up to 3); rectify's viewing-angle crop then
    removes the grazing cells near each vanishing line. Sides under ``min_area_frac`` of
    the grid are dropped. ``labels`` (for visualisation and support only) gives each cell
    the label (2k + s, as line_support_patches) of the patch seeing it most frontally.
    ``result`` must carry a confident frame (``result.directions``)."""
    h, w = work_shape
    labels = np.full((h, w), -1, np.int8)
    F = result.directions
    if F is None:
        return [], labels
    rays = cam_utils.unit_grid_rays(camera, w, h)
    cos = rays @ F.T  # (h, w, 3): r . F[k]; side s = 1 (normal -F[k]) where > 0
    patches, best = [], np.zeros((h, w))
    for k in np.flatnonzero(result.snapped):
        for s in (0, 1):
            frontal = -cos[..., k] * (-1.0 if s else 1.0)  # -r . n
            mask = frontal > 0
            if mask.mean() < min_area_frac:
                continue
            patches.append(Patch(mask, int(k), F[k] * (-1.0 if s else 1.0), float(mask.mean())))
            better = mask & (frontal > best)
            labels[better], best[better] = 2 * k + s, frontal[better]
    patches.sort(key=lambda p: -p.area_frac)
    return patches, labels


def depth_free_planes(
    image_gray: np.ndarray,
    camera: pycolmap.Camera,
    work_shape: tuple[int, int],
    conf: VpConf = VpConf(),
    min_area_frac: float = 0.005,
    gravity: np.ndarray | None = None,
    rng: np.random.Generator | None = None,
) -> tuple[PlaneResult, VpResult]:
    """Depth-free mode: Manhattan frame from lines (manhattan_from_image) + patches.

    The patches follow conf.depth_free_regions: 'lines' = line_support_patches (disjoint),
    'whole' = whole_image_patches (the paper's VP baseline, overlapping).

    Args:
        image_gray: (H, W) uint8 matching the camera's size.
        camera: the image's camera.
        work_shape: (h, w) of the work grid.
        conf: VpConf.
        min_area_frac: smallest patch, as a fraction of the grid.
        gravity, rng: as vp.fusion.refine_directions.
    Returns:
        (planes.PlaneResult on the work grid: directions (3, 3) or None, support (3,) =
        label area fraction per axis, labels (h, w) int8, patches; without a confident
        frame no patches and directions None, so the pipeline falls back to plain SIFT;
        the VpResult of manhattan_from_image).
    """
    regions = {"lines": line_support_patches, "whole": whole_image_patches}
    if conf.depth_free_regions not in regions:
        raise ValueError(
            f"vp.depth_free_regions must be one of {sorted(regions)}, "
            f"got {conf.depth_free_regions!r}"
        )
    res = manhattan_from_image(image_gray, camera, conf, gravity, rng)
    patches, labels = regions[conf.depth_free_regions](res, camera, work_shape, conf, min_area_frac)
    areas = np.bincount(labels[labels >= 0] // 2, minlength=3)[:3]
    support = areas / max(1, labels.size)
    return PlaneResult(res.directions, support, labels, patches), res
