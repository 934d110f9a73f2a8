"""One image: depth -> normals -> planes -> rectified patches -> SIFT -> features.

``extract_image(image, camera, depth, conf)`` is the whole method for a single image: the
chain of the stages, each in its own module (disparity, normals, planes, vp, rectify,
features, dedup). It is pure (no I/O) and single-threaded, so callers may run it in worker
processes.

Guarantee: with no depth, or no usable plane, the output is exactly plain COLMAP SIFT with
the same options (same call, same budget).
"""

from __future__ import annotations

import logging
import time
from contextlib import contextmanager
from dataclasses import dataclass, field, replace

import cv2
import numpy as np
import pycolmap

from .config import ExtractConf
from .dedup import fill_from_plain, keypoint_cap
from .depth import DepthMap
from .disparity import resolve_disparity
from .features import (
    Features,
    detect_sift,
    plain_features,
    pool_coarse_first,
    rectification_budgets,
    rectified_features,
    split_budget,
)
from .geometry import scaled_size
from .normals import depth_to_normals
from .planes import PlaneResult, detect_planes
from .rectify import (
    Rectification,
    patches_worth_rectifying,
    rectifications_within_area,
    viewing_coverage,
    viewing_masks,
    with_tilt_neighbours,
)
from .vp import (
    depth_free_planes,
    free_vanishing_points,
    hypothesis_patches,
    image_segments,
    plane_hypotheses,
    refine_directions,
)
from .vp.segments import Segments

logger = logging.getLogger(__name__)


@dataclass
class ImageResult:
    features: Features
    planes: PlaneResult | None = None
    rectifications: list[Rectification] = field(default_factory=list)
    coverage: np.ndarray | None = None
    """(h, w) int16 at work resolution: index of the rectification covering the cell, -1."""
    normals: np.ndarray | None = None
    """(h, w, 3) normals at work resolution (for visualisation)."""
    timings: dict[str, float] = field(default_factory=dict)


@contextmanager
def timed(timings: dict[str, float], key: str):
    """Adds the seconds spent in the block to ``timings[key]`` (0 if absent); the clock is
    this module's ``time.perf_counter`` (scripts/benchmark.py swaps it for a CPU clock)."""
    t0 = time.perf_counter()
    try:
        yield
    finally:
        timings[key] = timings.get(key, 0.0) + time.perf_counter() - t0


def plain_sift(gray: np.ndarray, conf: ExtractConf) -> Features:
    """Plain SIFT on the whole image with the whole budget (images without planes)."""
    n = conf.sift.max_num_features
    return detect_sift(gray, conf.sift, n, coarse_first=pool_coarse_first(gray.shape, n, conf.sift))


def orient_with_vanishing_points(
    gray: np.ndarray,
    camera: pycolmap.Camera,
    planes: PlaneResult,
    conf: ExtractConf,
    rng: np.random.Generator,
    segments: Segments | None = None,
) -> PlaneResult:
    """Depth says WHICH pixels form planes, lines say HOW they are oriented: when a direction
    snapped to a trusted vanishing direction, each patch takes its fused direction (with the
    patch's sign; unsnapped directions are rotated with the snapped ones); patches of a
    direction the lines contradict keep their depth normal. ``segments``: the image's, if
    already detected."""
    vp = refine_directions(gray, camera, planes.directions, conf.vp, rng=rng, segments=segments)
    if vp.directions is None:
        return planes
    patches = []
    for patch in planes.patches:
        k = patch.axis
        if not vp.contradicted[k] and vp.snapped.any():
            d = vp.directions[k]
            patch = replace(patch, normal=d * np.sign(d @ patch.normal))
        patches.append(patch)
    return replace(planes, directions=vp.directions, patches=patches)


def add_plane_hypotheses(
    camera: pycolmap.Camera, planes: PlaneResult, segments: Segments, conf: ExtractConf
) -> PlaneResult:
    """The planes plus whole-image patches for the strongest plane hypotheses from pairs of
    vanishing points (vp.hypotheses; conf.vp.line_hypotheses of them, none within
    conf.vp.hypothesis_merge_angle_deg of a patch the planes already have)."""
    normals, _ = plane_hypotheses(free_vanishing_points(segments, conf.vp), conf.vp)
    existing = [p.normal for p in planes.patches]
    extra = hypothesis_patches(normals, camera, planes.labels.shape, existing, conf.vp)
    return replace(planes, patches=list(planes.patches) + extra) if extra else planes


def extract_image(
    image: np.ndarray,
    camera: pycolmap.Camera,
    depth: DepthMap | None,
    conf: ExtractConf | None = None,
    rng: np.random.Generator | None = None,
    normals: np.ndarray | None = None,
) -> ImageResult:
    """Rectified SIFT of one image.

    image: (H, W) uint8 grayscale or (H, W, 3) uint8 RGB; camera: its pycolmap.Camera
    (width/height must match the image); depth: any resolution and kind (disparity is
    resolved with ``conf.depth``), or None for plain SIFT. ``normals`` (h, w, 3) on the work
    grid may be given instead of depth (e.g. ground truth).
    """
    conf = conf or ExtractConf()
    gray = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
    H, W = gray.shape
    if (W, H) != (camera.width, camera.height):
        raise ValueError(f"image is {W}x{H} but its camera is {camera.width}x{camera.height}")
    rng = rng if rng is not None else np.random.default_rng(0)
    total = conf.sift.max_num_features
    t = {}

    depth_free = depth is None and normals is None
    if depth_free and not conf.vp.depth_free:
        return ImageResult(plain_sift(gray, conf), timings=t)

    if depth_free:  # planes from vanishing points alone (conf.vp.depth_free)
        with timed(t, "vp"):
            w, h = scaled_size(W, H, conf.normals.work_max_size)
            planes, lines = depth_free_planes(
                gray, camera, (h, w), conf.vp, conf.planes.min_area_frac, rng=rng
            )
    else:
        with timed(t, "normals"):
            if normals is None:
                depth = resolve_disparity(depth, camera, conf)
                normals = depth_to_normals(depth, camera, conf.normals)
        with timed(t, "planes"):
            planes = detect_planes(normals, conf.planes, rng)
    orient = not depth_free and conf.vp.enabled and planes.directions is not None
    if orient or conf.vp.line_hypotheses > 0:
        with timed(t, "vp"):
            # depth-free: the segments its frame was fitted to
            segments = lines.segments if depth_free else image_segments(gray, camera, conf.vp)
            if orient:
                planes = orient_with_vanishing_points(gray, camera, planes, conf, rng, segments)
            if conf.vp.line_hypotheses > 0:
                planes = add_plane_hypotheses(camera, planes, segments, conf)

    with timed(t, "homographies"):
        todo = patches_worth_rectifying(gray, camera, planes.patches, conf.rectify)
        patches, todo = with_tilt_neighbours(camera, planes.patches, todo, conf.rectify)
        planes = replace(planes, patches=patches)
        rects = rectifications_within_area(camera, planes.patches, todo, conf.rectify)
        masks = viewing_masks(
            camera, rects, planes.patches, planes.labels.shape, conf.rectify.max_viewing_angle_deg
        )
        cover = viewing_coverage(masks)
    result = ImageResult(Features.empty(), planes, rects, cover, normals, t)
    if not rects or not (cover >= 0).any():
        result.features = plain_sift(gray, conf)
        return result

    if conf.dedup.keep_all_plain:
        result.features = features_on_top(gray, camera, rects, masks, conf, t)
        return result
    budgets = rectification_budgets(masks, total, conf.rectify.keep_plain)
    plain_region = np.ones_like(cover, bool) if conf.rectify.keep_plain else cover < 0

    with timed(t, "sift_plain"):
        # With dedup, plain SIFT is detected with the whole budget: the pool that fills what
        # the patches leave (COLMAP keeps the largest scales, so a smaller budget is a subset).
        plain_budget = total if conf.dedup.enabled else int(budgets[0])
        plain = Features.empty()
        if plain_budget > 0 and plain_region.any():
            plain = plain_features(gray, plain_region, plain_budget, conf.sift)
    parts = _rectified_parts(gray, camera, rects, budgets[1:], conf, t)
    if not conf.dedup.enabled:
        result.features = Features.concatenate([plain] + parts)
        return result
    with timed(t, "dedup"):
        # Target: as many keypoints as plain SIFT keeps with the whole budget on the image.
        region_frac = plain_region.mean()
        target = round(len(plain) / region_frac) if region_frac > 0 else total
        cap = keypoint_cap(target, conf.dedup)
        result.features = fill_from_plain(Features.concatenate(parts), plain, cap, conf.dedup)
    return result


def _rectified_parts(gray, camera, rects, budgets, conf: ExtractConf, t) -> list[Features]:
    """SIFT in each rectified view with its budget, mapped back (timed)."""
    parts = []
    for rect, budget in zip(rects, budgets):
        with timed(t, "warps+sift_patches"):
            parts.append(
                rectified_features(
                    gray,
                    camera,
                    rect,
                    rect.patch_index,
                    int(budget),
                    conf.sift,
                    conf.rectify.border,
                )
            )
    return parts


def features_on_top(
    gray: np.ndarray,
    camera: pycolmap.Camera,
    rects: list[Rectification],
    masks: np.ndarray,
    conf: ExtractConf,
    t: dict[str, float],
) -> Features:
    """Exactly plain SIFT's features (the whole budget on the whole image) plus rectified
    ones on top (``conf.dedup.keep_all_plain``): at most ``dedup.extra_frac`` x plain SIFT's
    count, none a twin of a plain feature or crowding one out of the ratio test. The views'
    SIFT budgets share ``sift.patch_budget_factor`` x that room by covered area (``masks``,
    (n, h, w) bool), so they cost what they may add."""
    with timed(t, "sift_plain"):
        plain = plain_sift(gray, conf)
    cap = keypoint_cap(len(plain), conf.dedup)
    room = round(conf.sift.patch_budget_factor * (cap - len(plain)))
    areas = masks.reshape(len(masks), -1).sum(1)
    parts = _rectified_parts(gray, camera, rects, split_budget(room, areas), conf, t)
    with timed(t, "dedup"):
        return fill_from_plain(Features.concatenate(parts), plain, cap, conf.dedup)
