"""One image: depth -> normals -> planes -> rectified views -> SIFT -> features.

``extract_image(image, camera, depth, conf)`` is the whole method for a single image: the
chain of the stages, each in its own module (disparity, normals, planes, vp, views and
rectify, sift, dedup, budget). It is pure (no I/O) and single-threaded, so callers may run
it in worker processes. Its steps are public functions too (``image_planes``,
``with_vanishing_points``, ``views_and_features``, ``features_on_top``), so that a tool can
run a variant of one step and the others as they are.

Guarantee: the output holds exactly plain COLMAP SIFT's features with the same options (the
same call, the same budget), and rectified features on top; with no depth, or no usable
plane where plain SIFT fills its budget, it is exactly plain SIFT (where it leaves part
unused, an image with no view, views that add almost nothing, or planes its lines do not
confirm, gets blind ones: ``views_and_features``).
"""

from __future__ import annotations

import logging
import time
from contextlib import contextmanager
from dataclasses import dataclass, field, replace

import cv2
import numpy as np
import pycolmap

from .budget import (
    blind_room,
    blind_share,
    cut_to_room,
    fits_either_tier,
    largest_scales,
    unused_room,
    view_budgets,
    view_pixel_budget,
    wants_blind_views,
    without_share,
)
from .config import ExtractConf
from .dedup import distinct_from_plain, lookalikes
from .depth import DepthMap
from .disparity import resolve_disparity
from .features import Features
from .normals import depth_to_normals
from .planes import BLIND_AXIS, HYPOTHESIS_AXIS, REST_AXIS, Patch, PlaneResult, detect_planes
from .rectify import Rectification
from .sift import Sift, plain_sift, rectified_features
from .views import ViewSet, blind_patches, joined_views, plan_views
from .vp import (
    free_vanishing_points,
    hypothesis_patches,
    image_segments,
    plane_hypotheses,
    refine_directions,
)
from .vp.segments import Segments

logger = logging.getLogger(__name__)

SECOND_TIER_AXES = (REST_AXIS, BLIND_AXIS)
"""Patches whose views' features come only in the part of plain SIFT's budget its own
keypoints left unused (budget.view_budgets, budget.cut_to_room): over the rest of a plane
and blind views."""

UNUSED_BUDGET_AXES = (*SECOND_TIER_AXES, HYPOTHESIS_AXIS)
"""Patches that get views only where plain SIFT left part of its budget unused
(``patches_with_room``): the second tier's and the whole-image plane hypotheses of the
vanishing points (their tilt neighbours share the axis). Where plain SIFT fills its budget
only the depth's planes get views: there, on the photo-collection pairs, the hypotheses'
views (guesses over the whole image, each at under half its resolution) added matches
half of them wrong and 3-4x worse located than plain SIFT's, and the poses lost to them
(research log, stop 60). Where the budget has room (small images, as the generated and
evd-dev pairs) their features stay first tier."""


@dataclass
class ImageResult:
    features: Features
    planes: PlaneResult | None = None
    """The planes, with the tilt neighbours' patches appended (Rectification.patch_index)."""
    rectifications: list[Rectification] = field(default_factory=list)
    coverage: np.ndarray | None = None
    """(h, w) int16 at work resolution: index of the rectification covering the cell, -1."""
    normals: np.ndarray | None = None
    """(h, w, 3) normals at work resolution (for visualisation)."""
    timings: dict[str, float] = field(default_factory=dict)
    """Seconds (wall clock) per stage."""


@contextmanager
def timed(timings: dict[str, float], key: str):
    """Adds the seconds spent in the block to ``timings[key]`` (0 if absent)."""
    t0 = time.perf_counter()
    try:
        yield
    finally:
        timings[key] = timings.get(key, 0.0) + time.perf_counter() - t0


def extract_image(
    image: np.ndarray,
    camera: pycolmap.Camera,
    depth: DepthMap | None,
    conf: ExtractConf | None = None,
    rng: np.random.Generator | None = None,
    sift: Sift | None = None,
) -> ImageResult:
    """Rectified SIFT of one image.

    image: (H, W) uint8 grayscale or (H, W, 3) uint8 RGB; camera: its pycolmap.Camera
    (width/height must match the image); depth: any resolution and kind (disparity is
    resolved, rectified_colmap.disparity), or None for plain SIFT; rng: RANSAC and k-means
    (default: seeded 0); sift: SIFT extractors kept warm across images (rectified_colmap.sift;
    default: new ones for this image).
    """
    conf = conf or ExtractConf()
    gray = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
    H, W = gray.shape
    if (W, H) != (camera.width, camera.height):
        raise ValueError(f"image is {W}x{H} but its camera is {camera.width}x{camera.height}")
    rng = rng if rng is not None else np.random.default_rng(0)
    sift = sift if sift is not None else Sift()
    t: dict[str, float] = {}
    if depth is None:
        return ImageResult(plain_sift(gray, conf.sift, sift), timings=t)
    planes, normals = image_planes(camera, depth, conf, rng, t)
    with timed(t, "sift_plain"):
        plain = plain_sift(gray, conf.sift, sift)
    lined = with_vanishing_points(gray, camera, planes, conf, rng, t, len(plain))
    supported = lines_support(planes, lined, conf)
    planes, shape = lined, lined.labels.shape
    views, features = views_and_features(
        gray, camera, planes.patches, shape, plain, conf, sift, t, supported
    )
    planes = replace(planes, patches=views.patches)
    return ImageResult(features, planes, views.rects, views.cover, normals, t)


def image_planes(
    camera: pycolmap.Camera,
    depth: DepthMap,
    conf: ExtractConf,
    rng: np.random.Generator,
    t: dict[str, float],
) -> tuple[PlaneResult, np.ndarray]:
    """Depth (disparity resolved) -> (planes on the work grid, normals (h, w, 3))."""
    with timed(t, "normals"):
        normals = depth_to_normals(resolve_disparity(depth, camera, conf), camera, conf.normals)
    with timed(t, "planes"):
        planes = detect_planes(normals, conf.planes, rng)
    return planes, normals


def with_vanishing_points(
    gray: np.ndarray,
    camera: pycolmap.Camera,
    planes: PlaneResult,
    conf: ExtractConf,
    rng: np.random.Generator,
    t: dict[str, float],
    plain_count: int | None = None,
) -> PlaneResult:
    """The planes oriented by the image's lines (``conf.vp.enabled``), with plane hypotheses
    from pairs of vanishing points appended (``conf.vp.line_hypotheses``); segments are
    detected once for both. Where plain SIFT keeps ``plain_count`` keypoints and
    ``patches_with_room`` would drop their patches (``unused_budget_axes_kept`` false), no
    hypotheses: the result's views are the same without them (None: always the
    hypotheses)."""
    orient = conf.vp.enabled and planes.directions is not None
    room = plain_count is None or unused_budget_axes_kept(plain_count, conf)
    hypotheses = conf.vp.line_hypotheses > 0 and room
    if not (orient or hypotheses):
        return planes
    with timed(t, "vp"):
        segments = image_segments(gray, camera, conf.vp)
        if orient:
            planes = orient_with_vanishing_points(gray, camera, planes, conf, rng, segments)
        if hypotheses:
            planes = add_plane_hypotheses(camera, planes, segments, conf)
    return planes


def lines_support(planes: PlaneResult, lined: PlaneResult, conf: ExtractConf) -> bool:
    """Whether an image's lines gave its plane estimates an orientation of their own:
    ``lined`` (``with_vanishing_points`` of ``planes``) holds a plane hypothesis
    (HYPOTHESIS_AXIS), or a depth patch whose normal the vanishing points changed. Where
    they did not (no lines, or lines that confirm no plane), every orientation is the
    network's alone (budget.blind_share). True with the lines off (``conf.vp.enabled``
    false: the depth's planes are used as they are, nothing is tested)."""
    if not conf.vp.enabled or any(p.axis == HYPOTHESIS_AXIS for p in lined.patches):
        return True
    pairs = zip(planes.patches, lined.patches)
    return any(not np.array_equal(a.normal, b.normal) for a, b in pairs)


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
    conf.vp.hypothesis_merge_angle_deg of a patch the planes already have), and patches
    over the rest of the planes the patches hold in part (REST_AXIS)."""
    normals, _ = plane_hypotheses(free_vanishing_points(segments, conf.vp), conf.vp)
    extra = hypothesis_patches(normals, camera, planes.labels.shape, planes.patches, conf.vp)
    return replace(planes, patches=list(planes.patches) + extra) if extra else planes


def unused_budget_axes_kept(plain_count: int, conf: ExtractConf) -> bool:
    """Whether the patches of ``UNUSED_BUDGET_AXES`` get views where plain SIFT keeps
    ``plain_count`` keypoints: where it left part of its budget unused (budget.unused_room).
    The one rule for ``patches_with_room`` and ``with_vanishing_points``."""
    return unused_room(plain_count, conf) > 0


def patches_with_room(patches: list[Patch], plain_count: int, conf: ExtractConf) -> list[Patch]:
    """The patches whose views may add features above plain SIFT's ``plain_count``
    keypoints: the second tier's (over the rest of a plane, blind) and the plane hypotheses
    (``UNUSED_BUDGET_AXES``) only where plain SIFT left part of its budget unused
    (budget.unused_room), the depth's planes always."""
    if unused_budget_axes_kept(plain_count, conf):
        return patches
    return [p for p in patches if p.axis not in UNUSED_BUDGET_AXES]


def image_views(
    gray: np.ndarray,
    camera: pycolmap.Camera,
    patches: list[Patch],
    shape: tuple[int, int],
    plain_count: int,
    conf: ExtractConf,
    pixel_budget: float | None = None,
) -> ViewSet:
    """The views (views.plan_views) of an image's plane ``patches`` on its (h, w) work grid
    ``shape``, where plain SIFT keeps ``plain_count`` keypoints (``patches_with_room``),
    within ``pixel_budget`` pixels (default: budget.view_pixel_budget). The depth planes'
    oblique views get tilt neighbours (views.with_tilt_neighbours) only where plain SIFT
    left part of its budget unused, as the views of ``UNUSED_BUDGET_AXES``: where it fills
    its budget they cost moderate pairs more than they gave (research log, session 37);
    where it does not they hedge the network's orientation error (stop 67)."""
    patches = patches_with_room(patches, plain_count, conf)
    pixels = view_pixel_budget(gray.shape, conf) if pixel_budget is None else pixel_budget
    bank = unused_budget_axes_kept(plain_count, conf)
    return plan_views(
        gray, camera, patches, shape, conf.rectify, pixels, conf.sift.upright, bank_depth=bank
    )


def views_and_features(
    gray: np.ndarray,
    camera: pycolmap.Camera,
    patches: list[Patch],
    shape: tuple[int, int],
    plain: Features,
    conf: ExtractConf,
    sift: Sift | None = None,
    t: dict[str, float] | None = None,
    supported: bool = True,
) -> tuple[ViewSet, Features]:
    """(views, features) of an image with plane ``patches`` on its (h, w) work grid
    ``shape`` and plain SIFT's features ``plain``: the views of the patches
    (``image_views``) and their features on top of ``plain`` (``features_on_top``).

    Blind views (views.blind_patches: ASIFT's tilts) come beside them, their features on
    top of all the others (``blind_on_top``: none of those changes), where plain SIFT left
    part of its budget unused and either the patches are not ``supported`` by the image's
    lines (``lines_support``; budget.blind_share: a share of the pixels and of the room is
    held for the blind views) or their views add almost nothing (budget.wants_blind_views:
    no view, or views of a wrong estimate over blank or blurred pixels). The blind views get
    the pixels the others leave: the network calls many oblique planes frontal, and an image
    with no working view cannot meet an oblique one. ``dedup.lookalikes_in_unused_budget``
    false: no blind views."""
    t = {} if t is None else t
    share = blind_share(len(plain), supported, conf)
    own = without_share(conf, share)
    pixels = view_pixel_budget(gray.shape, conf)
    with timed(t, "homographies"):
        views = image_views(gray, camera, patches, shape, len(plain), own, (1 - share) * pixels)
    rectified = views_features(gray, camera, views, len(plain), own, sift, t)
    features = with_rectified(plain, rectified, views, own, t)
    if not share and not wants_blind_views(len(features) - len(plain), len(plain), conf):
        return views, features
    with timed(t, "homographies"):
        used = sum(r.pixels for r in views.rects)
        blind_pixels = max(share * pixels, pixels - used) if share else pixels
        blind_views = blind_patches(camera, shape)
        blind = image_views(gray, camera, blind_views, shape, len(plain), conf, blind_pixels)
    more = views_features(gray, camera, blind, len(plain), conf, sift, t)
    more.patch[more.patch >= 0] += len(views.patches)
    with timed(t, "dedup"):
        features = blind_on_top(features, more, len(plain), conf)
    return joined_views(views, blind), features


def blind_on_top(
    features: Features, blind: Features, plain_count: int, conf: ExtractConf
) -> Features:
    """``features`` (plain SIFT's ``plain_count`` and the rectified features kept on top,
    all kept as they are) and the features of the blind views ``blind`` that twin none of
    them (dedup.distinct_from_plain, every kept feature counted as plain: it always wins),
    largest major scales first, look-alikes of kept features last (dedup.lookalikes, tested
    only where not all fit), at most budget.blind_room."""
    kept = replace(features, patch=np.full(len(features), -1, features.patch.dtype))
    index = distinct_from_plain(blind, kept, conf.dedup)
    room = blind_room(len(features), plain_count, conf)
    if len(index) > room:
        lookalike = lookalikes(blind, index, kept, conf.dedup)
        first = largest_scales(blind, index[~lookalike], room)
        later = largest_scales(blind, index[lookalike], room - len(first))
        index = np.sort(np.r_[first, later])
    return Features.concatenate([features, blind.subset(index)])


def second_tier_patches(views: ViewSet) -> np.ndarray:
    """(len(views.patches),) bool: which of the views' patches are second tier (over the
    rest of a plane or blind: SECOND_TIER_AXES); index it by ``Rectification.patch_index``
    or ``Features.patch``."""
    return np.array([p.axis in SECOND_TIER_AXES for p in views.patches], bool)


def view_sift_budgets(views: ViewSet, plain_count: int, conf: ExtractConf) -> np.ndarray:
    """(len(views.rects),) SIFT budgets of the views where plain SIFT keeps ``plain_count``
    keypoints (budget.view_budgets: the room shared by covered area, the second tier's views
    in plain SIFT's unused part)."""
    areas = views.masks.sum((1, 2))
    rest = second_tier_patches(views)[[r.patch_index for r in views.rects]]
    return view_budgets(plain_count, areas, rest, conf)


def rectified_to_keep(
    rectified: Features, plain: Features, views: ViewSet, conf: ExtractConf
) -> tuple[np.ndarray, np.ndarray]:
    """(candidates, kept): indices into ``rectified`` (the features of ``views``) that twin
    no plain feature (dedup.distinct_from_plain), and those of them kept on top of
    ``plain`` (budget.cut_to_room; look-alikes, dedup.lookalikes, and the features of the
    second tier's views, ``second_tier_patches``, come last). Where all candidates fit
    either tier (budget.fits_either_tier) they are all kept, with no look-alike test."""
    index = distinct_from_plain(rectified, plain, conf.dedup)
    if fits_either_tier(len(index), len(plain), conf):
        return index, index
    second = lookalikes(rectified, index, plain, conf.dedup)
    second |= second_tier_patches(views)[rectified.patch[index]]
    return index, cut_to_room(rectified, index, second, len(plain), conf)


def features_on_top(
    gray: np.ndarray,
    camera: pycolmap.Camera,
    views: ViewSet,
    plain: Features,
    conf: ExtractConf,
    sift: Sift | None = None,
    t: dict[str, float] | None = None,
) -> Features:
    """``plain`` (plain SIFT of the whole image, all kept) plus the rectified features of the
    views (``views_features``) that twin no plain one (rectified_colmap.dedup), at most the
    budget's room above plain SIFT; look-alikes of plain features and the features of the
    second tier's views (SECOND_TIER_AXES: over the rest of a plane, blind) only in plain
    SIFT's unused budget (``with_rectified``, rectified_colmap.budget.cut_to_room)."""
    rectified = views_features(gray, camera, views, len(plain), conf, sift, t)
    return with_rectified(plain, rectified, views, conf, t)


def views_features(
    gray: np.ndarray,
    camera: pycolmap.Camera,
    views: ViewSet,
    plain_count: int,
    conf: ExtractConf,
    sift: Sift | None = None,
    t: dict[str, float] | None = None,
) -> Features:
    """The rectified features of every view of ``views`` in image pixels
    (sift.rectified_features, each within its SIFT budget: ``view_sift_budgets``),
    ``Features.patch`` indexing ``views.patches``. (sift.view_features is one view's, in
    its own pixels.)"""
    t = {} if t is None else t
    parts = [Features.empty()]
    for rect, budget in zip(views.rects, view_sift_budgets(views, plain_count, conf)):
        with timed(t, "warps+sift_patches"):
            args = (int(budget), conf.sift, conf.rectify.border, sift)
            parts.append(rectified_features(gray, camera, rect, *args))
    return Features.concatenate(parts)


def with_rectified(
    plain: Features,
    rectified: Features,
    views: ViewSet,
    conf: ExtractConf,
    t: dict[str, float] | None = None,
) -> Features:
    """``plain`` and the features of ``rectified`` (those of ``views``) kept on top of it
    (``rectified_to_keep``)."""
    with timed({} if t is None else t, "dedup"):
        if not len(rectified):
            return plain
        _, keep = rectified_to_keep(rectified, plain, views, conf)
        return Features.concatenate([plain, rectified.subset(keep)])
