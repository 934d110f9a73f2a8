"""Depth-free planes: plane patches from a line-derived Manhattan frame (research only).

Moved out of the package with the depth-free mode (issue 42): the training's normal labels
from lines (training/real.py), the VP-only rows of scripts/eval_vp.py and scripts/bench_vp.py
use it; the extractor never does.

Input: the grayscale image (H, W) uint8, its camera and the work-grid shape (h, w) (the grid
of rectified_colmap.planes). Output: a planes.PlaneResult on the work grid, like
planes.detect_planes gives from depth: directions (3, 3) (the confident frame, or None),
labels (h, w) int8 (2k + s, -1 = none) and ``Patch``es with work-grid masks and normals
facing the camera; and the VpResult behind it (rectified_colmap.vp.fusion).

The confident frame (``manhattan_from_image``) gives the directions, and the patches come
from ``line_support_patches`` (LinePlaneConf.regions = 'lines': a plane with normal F[k] is
where segments of both other VPs are dense, see its docstring, split by the sign of
ray . F[k]) or ``whole_image_patches`` ('whole', the paper's VP baseline: per trusted axis,
each side of its vanishing line entirely; the patches overlap).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import cv2
import numpy as np
import pycolmap

from rectified_colmap import camera as cam_utils
from rectified_colmap.config import ExtractConf, VpConf
from rectified_colmap.conventions import to_opencv_points
from rectified_colmap.geometry import scaled_size
from rectified_colmap.pipeline import (
    ImageResult,
    add_plane_hypotheses,
    timed,
    views_and_features,
)
from rectified_colmap.planes import Patch, PlaneResult
from rectified_colmap.sift import plain_sift
from rectified_colmap.vp.fusion import VpResult, refine_directions


@dataclass
class LinePlaneConf:
    """Depth-free planes (were vp.support_radius_frac, vp.support_min_lines,
    vp.depth_free_regions of the package's conf)."""

    support_radius_frac: float = 0.06  # window half-side (fraction of the grid's side)
    support_min_lines: float = 0.5  # segment lengths per window for each VP
    regions: str = "lines"  # "lines" (line_support_patches) or "whole" (whole-image warps)

    def __post_init__(self):
        if self.regions not in ("lines", "whole"):
            raise ValueError(f"regions must be 'lines' or 'whole', got {self.regions!r}")


def manhattan_from_image(
    image_gray: np.ndarray,
    camera: pycolmap.Camera,
    conf: VpConf = VpConf(),
    rng: np.random.Generator | None = None,
) -> VpResult:
    """The line-derived frame as the dominant directions.

    Args:
        image_gray, camera, conf, rng: as rectified_colmap.vp.refine_directions.
    Returns:
        VpResult whose ``directions`` (3, 3) is the frame (rows by support, like
        planes.fit_dominant_directions) when at least two of its axes are confident
        (sigma <= conf.max_sigma_deg), else None; ``snapped`` (3,) marks the confident
        axes; ``support`` and ``sigma_deg`` (3,) are the frame's.
    """
    res = refine_directions(image_gray, camera, None, conf, rng)
    mf = res.manhattan
    confident = mf.sigma_deg <= conf.max_sigma_deg
    res.snapped = confident
    res.support = mf.support.copy()
    res.sigma_deg = mf.sigma_deg.copy()
    res.directions = mf.frame.copy() if mf.frame is not None and confident.sum() >= 2 else None
    return res


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
    conf: LinePlaneConf = LinePlaneConf(),
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
    conf: LinePlaneConf = LinePlaneConf(),
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
    line_conf: LinePlaneConf = LinePlaneConf(),
    min_area_frac: float = 0.005,
    rng: np.random.Generator | None = None,
) -> tuple[PlaneResult, VpResult]:
    """Manhattan frame from lines (manhattan_from_image) + patches.

    The patches follow line_conf.regions: 'lines' = line_support_patches (disjoint),
    'whole' = whole_image_patches (the paper's VP baseline, overlapping).

    Args:
        image_gray: (H, W) uint8 matching the camera's size.
        camera: the image's camera.
        work_shape: (h, w) of the work grid.
        conf: VpConf (segments and frame); line_conf: the regions.
        min_area_frac: smallest patch, as a fraction of the grid.
        rng: as rectified_colmap.vp.refine_directions.
    Returns:
        (planes.PlaneResult on the work grid: directions (3, 3) or None, support (3,) =
        label area fraction per axis, labels (h, w) int8, patches; without a confident
        frame no patches and directions None; the VpResult of manhattan_from_image).
    """
    regions = {"lines": line_support_patches, "whole": whole_image_patches}
    res = manhattan_from_image(image_gray, camera, conf, rng)
    patches, labels = regions[line_conf.regions](res, camera, work_shape, line_conf, min_area_frac)
    areas = np.bincount(labels[labels >= 0] // 2, minlength=3)[:3]
    support = areas / max(1, labels.size)
    return PlaneResult(res.directions, support, labels, patches), res


def extract_depth_free(
    image: np.ndarray,
    camera: pycolmap.Camera,
    conf: ExtractConf | None = None,
    line_conf: LinePlaneConf = LinePlaneConf(),
    rng: np.random.Generator | None = None,
) -> ImageResult:
    """The package's pipeline for an image without depth, planes from lines alone
    (``depth_free_planes``), then plane hypotheses, views and features as in
    rectified_colmap.pipeline.extract_image. Without a confident frame and hypotheses:
    exactly plain SIFT where it fills its budget, else blind views in its unused part
    (pipeline.views_and_features)."""
    conf = conf or ExtractConf()
    gray = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
    H, W = gray.shape
    w, h = scaled_size(W, H, conf.normals.work_max_size)
    t: dict[str, float] = {}
    with timed(t, "vp"):
        planes, lines = depth_free_planes(
            gray, camera, (h, w), conf.vp, line_conf, conf.planes.min_area_frac, rng
        )
        if conf.vp.line_hypotheses > 0:
            planes = add_plane_hypotheses(camera, planes, lines.segments, conf)
    with timed(t, "sift_plain"):
        plain = plain_sift(gray, conf.sift)
    views, feats = views_and_features(gray, camera, planes.patches, (h, w), plain, conf, None, t)
    planes = replace(planes, patches=views.patches)
    return ImageResult(feats, planes, views.rects, views.cover, None, t)
