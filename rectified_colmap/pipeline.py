"""One image: depth -> normals -> planes -> rectified patches -> SIFT -> features.

``extract_image(image, camera, depth, conf)`` is the whole method for a single image. It is
pure (no I/O) and single-threaded, so callers may run it in worker processes.

Guarantee: with no depth, or no usable plane, the output is exactly plain COLMAP SIFT with
the same options (same call, same budget).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field, replace

import cv2
import numpy as np
import pycolmap

from . import camera as cam_utils
from .config import ExtractConf
from .dedup import fill_from_plain
from .depth import DepthMap, resample_depth
from .features import Features, coarse_first_pays, detect_sift, keypoints_in_mask, split_budget
from .geometry import scaled_size
from .normals import backproject, estimate_normals
from .planes import PlaneResult, detect_planes
from .rectify import Rectification, plan_rectification, rectified_to_image, warp_to_rectified

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


def depth_to_normals(
    depth: DepthMap, camera: pycolmap.Camera, conf: ExtractConf, shift: float | None = None
) -> np.ndarray:
    """Depth of any resolution and kind -> normals (h, w, 3) on the work grid.

    The grid is never finer than the depth map: upsampled depth is piecewise constant or
    interpolated, and neither adds information to a plane fit."""
    max_size = min(conf.normals.work_max_size, max(depth.values.shape))
    w, h = scaled_size(camera.width, camera.height, max_size)
    if depth.kind == "disparity" and shift is None:
        shift = _disparity_shift(depth, camera, conf)
    z = resample_depth(depth.to_depth(shift or 0.0), w, h)
    points = backproject(z, cam_utils.grid_rays(camera, w, h))
    return estimate_normals(points, conf.normals)


def _disparity_shift(depth: DepthMap, camera: pycolmap.Camera, conf: ExtractConf) -> float:
    if conf.depth.disparity_shift == "zero":
        return 0.0
    from .depth.shift import estimate_shift  # needs normals and planes: import late

    return float(estimate_shift(depth.values, camera, conf))


def viewing_masks(
    camera: pycolmap.Camera,
    rects: list[Rectification],
    patches,
    shape: tuple[int, int],
    max_viewing_angle_deg: float,
) -> np.ndarray:
    """(n, h, w) bool: the work-grid cells each rectification covers: cells of its patch
    whose viewing angle is within the limit (cells beyond it are left to plain SIFT).
    Patches may overlap (depth-free whole-image warps): a cell can be in several masks."""
    h, w = shape
    rays = cam_utils.grid_rays(camera, w, h)
    rays /= np.linalg.norm(rays, axis=-1, keepdims=True)
    cos_max = np.cos(np.deg2rad(max_viewing_angle_deg))
    out = np.zeros((len(rects), h, w), bool)
    for i, rect in enumerate(rects):
        out[i] = patches[rect.patch_index].mask & (-(rays @ rect.normal) >= cos_max)
    return out


def viewing_coverage(masks: np.ndarray) -> np.ndarray:
    """(n, h, w) bool viewing_masks -> (h, w) int16: the first rectification covering
    each cell (-1: none)."""
    cover = np.full(masks.shape[1:], -1, np.int16)
    for i in range(len(masks) - 1, -1, -1):
        cover[masks[i]] = i
    return cover


def rectification_budgets(masks: np.ndarray, total: int, keep_plain: bool) -> np.ndarray:
    """(n + 1,) feature budgets [plain, rect 0, ...] summing to at most ``total``.

    Shares follow areas: plain SIFT gets the uncovered cells (with keep_plain: all cells,
    the covered ones at half weight), the rectifications the covered cells (half weight
    with keep_plain). When rectifications overlap, the share of the covered cells (their
    union) is split between them in proportion to each one's own covered area; without
    overlap this is each one's own area. So plain SIFT's share, and the total, never
    depend on the overlap."""
    own = masks.reshape(len(masks), -1).sum(1).astype(float)
    union = float(masks.any(0).sum())
    cells = masks.shape[1] * masks.shape[2]
    areas = np.concatenate([[cells - union], own * union / max(own.sum(), 1.0)])
    if keep_plain:  # rectified pixels share their budget with plain SIFT
        areas[0] += areas[1:].sum() / 2
        areas[1:] /= 2
    return split_budget(total, areas)


def plain_sift(gray: np.ndarray, conf: ExtractConf) -> Features:
    """Plain SIFT on the whole image with the whole budget (images without planes)."""
    n = conf.sift.max_num_features
    return detect_sift(gray, conf.sift, n, coarse_first=coarse_first_pays(gray.shape, n, conf.sift))


def plain_features(
    gray: np.ndarray, region: np.ndarray, budget: int, conf: ExtractConf, margin: int = 16
) -> Features:
    """About ``budget`` plain SIFT features on the pixels of ``region`` (a grid covering the
    image), detected on the region's bounding box only."""
    H, W = gray.shape
    h, w = region.shape
    rows, cols = np.flatnonzero(region.any(1)), np.flatnonzero(region.any(0))
    x0 = max(0, int(np.floor(cols[0] * W / w)) - margin)
    x1 = min(W, int(np.ceil((cols[-1] + 1) * W / w)) + margin)
    y0 = max(0, int(np.floor(rows[0] * H / h)) - margin)
    y1 = min(H, int(np.ceil((rows[-1] + 1) * H / h)) + margin)
    box = region[
        int(y0 * h / H) : int(np.ceil(y1 * h / H)), int(x0 * w / W) : int(np.ceil(x1 * w / W))
    ]
    n = round(budget * box.size / max(region.sum(), 1))  # SIFT's budget covers the whole box
    box_img = np.ascontiguousarray(gray[y0:y1, x0:x1])
    feats = detect_sift(
        box_img, conf.sift, n, coarse_first=coarse_first_pays(box_img.shape, n, conf.sift)
    )
    feats.keypoints += [x0, y0]  # integer offset: the same in every pixel convention
    return feats.subset(keypoints_in_mask(feats.keypoints, region, (W, H)))


def orient_with_vanishing_points(
    gray: np.ndarray,
    camera: pycolmap.Camera,
    planes: PlaneResult,
    conf: ExtractConf,
    rng: np.random.Generator,
) -> PlaneResult:
    """Depth says WHICH pixels form planes, lines say HOW they are oriented: when a direction
    snapped to a trusted vanishing direction, each patch takes its fused direction (with the
    patch's sign; unsnapped directions are rotated with the snapped ones); patches of a
    direction the lines contradict keep their depth normal, or are dropped with
    conf.vp.drop_contradicted."""
    from .vp import refine_directions

    vp = refine_directions(gray, camera, planes.directions, conf.vp, rng=rng)
    if vp.directions is None:
        return planes
    patches = []
    for patch in planes.patches:
        k = patch.axis
        if vp.contradicted[k]:
            if conf.vp.drop_contradicted:
                continue
        elif vp.snapped.any():
            d = vp.directions[k]
            patch = replace(patch, normal=d * np.sign(d @ patch.normal))
        patches.append(patch)
    return replace(planes, directions=vp.directions, patches=patches)


def patch_evidence(
    gray: np.ndarray, camera: pycolmap.Camera, patches
) -> tuple[np.ndarray, np.ndarray]:
    """Per patch: (median viewing angle in degrees, median texture), each (n,).

    The viewing angle of a cell is the angle between its ray and the patch normal (0: the
    patch is seen frontally there); texture is the Sobel gradient magnitude of the image
    resampled to the work grid (INTER_AREA; 8 x grey levels per work cell; sky and blank
    walls are under ~5, Strecha facades ~40, cobblestones ~15)."""
    if not patches:
        return np.zeros(0), np.zeros(0)
    h, w = patches[0].mask.shape
    rays = cam_utils.grid_rays(camera, w, h)
    rays /= np.linalg.norm(rays, axis=-1, keepdims=True)
    g = cv2.resize(gray, (w, h), interpolation=cv2.INTER_AREA).astype(np.float32)
    mag = np.hypot(cv2.Sobel(g, cv2.CV_32F, 1, 0), cv2.Sobel(g, cv2.CV_32F, 0, 1))
    angle, texture = np.zeros(len(patches)), np.zeros(len(patches))
    for i, p in enumerate(patches):
        cos = np.clip(-(rays[p.mask] @ p.normal), -1.0, 1.0)
        angle[i] = np.degrees(np.arccos(np.median(cos))) if cos.size else 0.0
        texture[i] = np.median(mag[p.mask]) if cos.size else 0.0
    return angle, texture


def patches_worth_rectifying(gray: np.ndarray, camera: pycolmap.Camera, patches, conf) -> list[int]:
    """Indices of the patches to rectify (conf: RectifyConf). Left to plain SIFT (at full
    budget: the pipeline fills from plain SIFT) are patches seen nearly frontally (median
    viewing angle under conf.min_rectify_angle_deg: the warp would change little) and
    patches without texture (median gradient under conf.min_texture: sky, blank walls)."""
    angle, texture = patch_evidence(gray, camera, patches)
    keep = (angle >= conf.min_rectify_angle_deg) & (texture >= conf.min_texture)
    if len(patches):
        logger.debug(
            "patches: viewing angle %s, texture %s -> rectify %s",
            np.round(angle),
            np.round(texture),
            keep.astype(int),
        )
    return [int(i) for i in np.flatnonzero(keep)]


def plan_rectifications(
    camera: pycolmap.Camera, patches, indices: list[int], conf: ExtractConf
) -> list[Rectification]:
    """Rectifications of the given patches, scaled down together when their summed size
    exceeds ``conf.rectify.max_total_area_factor`` x the image area x the patches'
    overlap (summed patch areas / area of their union: 1 for disjoint patches; up to 3
    for depth-free whole-image warps, which so keep the resolution that disjoint patches
    of their size would get)."""

    def plan(scale):
        rects = (plan_rectification(camera, patches[i], i, conf.rectify, scale) for i in indices)
        return [r for r in rects if r is not None]

    rects = plan(1.0)
    total = sum(r.size[0] * r.size[1] for r in rects)
    masks = [patches[i].mask for i in indices]
    overlap = 1.0
    if masks:
        overlap = sum(int(m.sum()) for m in masks) / max(1, int(np.logical_or.reduce(masks).sum()))
    budget = conf.rectify.max_total_area_factor * camera.width * camera.height * overlap
    if total > budget:
        rects = plan(float(np.sqrt(budget / total)))
    return rects


def rectified_features(
    gray: np.ndarray,
    camera: pycolmap.Camera,
    rect: Rectification,
    index: int,
    budget: int,
    conf: ExtractConf,
) -> Features:
    """SIFT inside one rectified patch, mapped back to the original image."""
    patch_img = warp_to_rectified(gray, camera, rect)
    feats = detect_sift(
        patch_img,
        conf.sift,
        budget,
        conf.sift.patch_first_octave,
        coarse_first=coarse_first_pays(patch_img.shape, budget, conf.sift),
    )
    if len(feats) == 0:
        return feats
    b = conf.rectify.border
    valid = rect.mask.astype(np.uint8)
    if b > 0:
        valid = cv2.erode(
            valid,
            np.ones((2 * b + 1, 2 * b + 1), np.uint8),
            borderType=cv2.BORDER_CONSTANT,
            borderValue=0,
        )
    keep = keypoints_in_mask(feats.keypoints, valid.astype(bool), rect.size)
    feats = feats.subset(keep)
    xy, J = rectified_to_image(camera, rect, feats.keypoints)
    inside = (
        np.isfinite(xy).all(1)
        & (xy[:, 0] >= 0)
        & (xy[:, 1] >= 0)
        & (xy[:, 0] <= camera.width)
        & (xy[:, 1] <= camera.height)
    )
    return Features(
        xy[inside],
        (J @ feats.shapes)[inside],
        feats.descriptors[inside],
        np.full(int(inside.sum()), index, np.int32),
    )


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
    (width/height must match the image); depth: any resolution, or None for plain SIFT.
    ``normals`` (h, w, 3) on the work grid may be given instead of depth (e.g. ground truth).
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
        from .vp import depth_free_planes

        t0 = time.perf_counter()
        w, h = scaled_size(W, H, conf.normals.work_max_size)
        planes, _ = depth_free_planes(
            gray, camera, (h, w), conf.vp, conf.planes.min_area_frac, rng=rng
        )
        t["vp"] = time.perf_counter() - t0
    else:
        t0 = time.perf_counter()
        if normals is None:
            normals = depth_to_normals(depth, camera, conf)
        t["normals"] = time.perf_counter() - t0

        t0 = time.perf_counter()
        planes = detect_planes(normals, conf.planes, rng)
        t["planes"] = time.perf_counter() - t0

        if conf.vp.enabled and planes.directions is not None:
            t0 = time.perf_counter()
            planes = orient_with_vanishing_points(gray, camera, planes, conf, rng)
            t["vp"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    todo = patches_worth_rectifying(gray, camera, planes.patches, conf.rectify)
    rects = plan_rectifications(camera, planes.patches, todo, conf)
    masks = viewing_masks(
        camera, rects, planes.patches, planes.labels.shape, conf.rectify.max_viewing_angle_deg
    )
    cover = viewing_coverage(masks)
    t["homographies"] = time.perf_counter() - t0
    result = ImageResult(Features.empty(), planes, rects, cover, normals, t)
    if not rects or not (cover >= 0).any():
        result.features = plain_sift(gray, conf)
        return result

    budgets = rectification_budgets(masks, total, conf.rectify.keep_plain)
    plain_region = np.ones_like(cover, bool) if conf.rectify.keep_plain else cover < 0

    parts = []
    t0 = time.perf_counter()
    # With dedup, plain SIFT is detected with the whole budget: the pool that fills what
    # the patches leave (COLMAP keeps the largest scales, so a smaller budget is a subset).
    plain_budget = total if conf.dedup.enabled else int(budgets[0])
    plain = Features.empty()
    if plain_budget > 0 and plain_region.any():
        plain = plain_features(gray, plain_region, plain_budget, conf)
    t["sift_plain"] = time.perf_counter() - t0
    t["warps+sift_patches"] = 0.0
    for i, rect in enumerate(rects):
        t0 = time.perf_counter()
        parts.append(
            rectified_features(gray, camera, rect, rect.patch_index, int(budgets[i + 1]), conf)
        )
        t["warps+sift_patches"] += time.perf_counter() - t0
    if not conf.dedup.enabled:
        result.features = Features.concatenate([plain] + parts)
        return result
    t0 = time.perf_counter()
    # Target: as many keypoints as plain SIFT keeps with the whole budget on the image.
    region_frac = plain_region.mean()
    target = round(len(plain) / region_frac) if region_frac > 0 else total
    result.features = fill_from_plain(Features.concatenate(parts), plain, target, conf.dedup)
    t["dedup"] = time.perf_counter() - t0
    return result
