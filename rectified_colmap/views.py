"""The views of one image: which plane patches get rectified views, and within what budget.

Input: the grayscale image (H, W) uint8, its camera and the planes' ``Patch``es (work-grid
masks, normals facing the camera; rectified_colmap.planes, plane hypotheses from
rectified_colmap.vp.hypotheses). Output: a :class:`ViewSet`: the patches (tilt neighbours
appended), their ``Rectification``s (rectified_colmap.rectify) within the image's pixel
budget, the work-grid cells each view covers and the first view covering each cell.

- ``textured_patches``: each patch cut to its textured cells, so that no view spends pixels
  on sky, blank walls or what lies around a plane, nor on specks of noise there
  (``without_specks``);
- ``patches_worth_rectifying``: near-frontal patches and small ones are left to plain SIFT;
- ``with_tilt_neighbours``: views at tilts x or / ``tilt_factor`` around oblique plane
  hypotheses' views (orientations from lines err most) and, where the pipeline asks
  (plain SIFT left budget unused), around the depth planes' oblique views;
- ``blind_patches``: for an image where no estimate gave a working view, orientations
  sampled as ASIFT samples tilts (rectified_colmap.pipeline.views_and_features: the second
  tier), planned apart and ``joined_views`` beside the estimates' views; their views are
  ASIFT's affine tilt simulations (``tilt_simulation_view``), not rectifications
  (``view_of_patch`` picks);
- ``rectifications_within_budget``: every view planned, then scaled down to the image's
  pixel budget, a multiple of its own pixels: each work cell of the image buys the same
  view pixels, shared among the views over it, so no view takes another's (``shared_cells``);
- ``viewing_masks`` / ``viewing_coverage``: the cells each view covers.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace

import cv2
import numpy as np
import pycolmap

from . import camera as cam_utils
from .config import RectifyConf
from .conventions import OFFSET
from .geometry import axis_angle_rotation, singular_values_2x2
from .planes import BLIND_AXIS, HYPOTHESIS_AXIS, REST_AXIS, Patch
from .rectify import (
    MAX_FOCAL_SAMPLES,
    PatchView,
    Rectification,
    finish_rectification,
    fitting_roll,
    image_to_view_jacobian,
    patch_view,
    rays_to_rectified_jacobian,
    row_ends,
    view_camera,
    view_focal,
    virtual_coords,
)

logger = logging.getLogger(__name__)

BLIND_TILTS = (2.0, 4.0)
"""Tilts t = 1 / cos(viewing angle) of the blind views (``blind_patches``): 60 and 75.5
degrees at the image centre. A factor of 2 apart, so every tilt from sqrt(2) to 4 sqrt(2)
(45-80 degrees) is within sqrt(2) of one, the residual SIFT absorbs (ASIFT samples both
images at sqrt(2) steps: sqrt(2) between the two; here one image may be plain)."""
BLIND_LONGITUDE_STEP_DEG = 72.0
"""Tilt directions of the blind views: ``BLIND_LONGITUDE_STEP_DEG`` / t apart, ASIFT's step
(Morel and Yu, 2009), over 180 degrees: their views are affine (``tilt_simulation_view``),
and the affine views of phi and phi + 180 differ by a half turn, which SIFT does not see."""

MIN_VIEW_AREA_FRAC = 0.005
"""Patches whose textured cells cover less of the image than this get no view (as
planes.min_area_frac drops smaller components), and textured regions smaller than this
widen no view (``without_specks``)."""
TEXTURE_MARGIN = 2
"""Work cells around a textured cell that a view keeps (``textured_patches``)."""


@dataclass
class ViewSet:
    """The rectified views of one image (``plan_views``)."""

    patches: list[Patch]
    """The image's patches, tilt neighbours appended (``Rectification.patch_index``
    indexes this list)."""
    rects: list[Rectification]
    masks: np.ndarray
    """(n, h, w) bool: the work-grid cells each view covers (``viewing_masks``)."""
    cover: np.ndarray
    """(h, w) int16: the first view covering each cell, -1 for none."""

    def __bool__(self) -> bool:
        """Whether any view covers any cell (else the image gets plain SIFT alone)."""
        return bool(self.rects) and bool((self.cover >= 0).any())


def plan_views(
    gray: np.ndarray,
    camera: pycolmap.Camera,
    patches: list[Patch],
    shape: tuple[int, int],
    conf: RectifyConf,
    pixel_budget: float,
    upright: bool = False,
    bank_depth: bool = False,
) -> ViewSet:
    """The views of an image with these plane patches on its (h, w) work grid ``shape``
    (the module docstring's steps), all of them within ``pixel_budget`` pixels
    (rectified_colmap.budget.view_pixel_budget). ``upright`` (upright SIFT, whose features
    take the view's up): no view is turned to fit (rectify.patch_view's ``turn``).
    ``bank_depth``: the depth planes' views get tilt neighbours too."""
    patches = textured_patches(gray, patches, conf.min_texture)
    todo = patches_worth_rectifying(camera, patches, conf)
    patches, todo = with_tilt_neighbours(camera, patches, todo, conf, bank_depth)
    rects = rectifications_within_budget(camera, patches, todo, conf, pixel_budget, not upright)
    masks = viewing_masks(camera, rects, patches, shape, conf.max_viewing_angle_deg)
    return ViewSet(patches, rects, masks, viewing_coverage(masks))


def joined_views(a: ViewSet, b: ViewSet) -> ViewSet:
    """The views of ``a`` and of ``b`` (planned apart, on the same work grid) as one
    ViewSet: ``b``'s patches after ``a``'s, its ``Rectification.patch_index`` shifted."""
    k = len(a.patches)
    rects = list(a.rects) + [replace(r, patch_index=r.patch_index + k) for r in b.rects]
    masks = np.concatenate([a.masks, b.masks])
    return ViewSet(list(a.patches) + list(b.patches), rects, masks, viewing_coverage(masks))


def viewing_angles(camera: pycolmap.Camera, patches: list[Patch]) -> np.ndarray:
    """(n,) median viewing angle of each patch in degrees: the angle between a cell's ray
    and the patch normal (0: seen frontally there)."""
    if not patches:
        return np.zeros(0)
    h, w = patches[0].mask.shape
    rays = cam_utils.unit_grid_rays(camera, w, h).reshape(-1, 3)
    angle = np.zeros(len(patches))
    for i, p in enumerate(patches):
        cos = -(rays @ np.asarray(p.normal, float))[p.mask.ravel()]  # the grid's, then cut
        if cos.size:
            angle[i] = np.degrees(np.arccos(np.median(np.clip(cos, -1.0, 1.0))))
    return angle


def texture_map(gray: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """(h, w) float32 Sobel gradient magnitude of the image resampled (INTER_AREA) to the
    work grid ``shape``: 8 x grey levels per cell (sky and blank walls are under ~5,
    Strecha facades ~40, cobblestones ~15)."""
    h, w = shape
    g = cv2.resize(gray, (w, h), interpolation=cv2.INTER_AREA).astype(np.float32)
    return np.hypot(cv2.Sobel(g, cv2.CV_32F, 1, 0), cv2.Sobel(g, cv2.CV_32F, 0, 1))


def textured_patches(gray: np.ndarray, patches: list[Patch], min_texture: float) -> list[Patch]:
    """Each patch cut to its textured cells: ``texture_map`` >= ``min_texture``, dilated by
    TEXTURE_MARGIN cells (a feature's support reaches past a textured cell). A view then
    spends no pixels on sky, blank walls or what lies around a plane, and a plane seen in a
    small part of a mostly blank image still gets its view. Textured regions too small for
    a view of their own (``without_specks``: specks of noise in a sky or a grey background)
    are left out: a speck near a plane's horizon, where the view stretches the image most,
    widened the view's box many times over (one of 40x on a generated pair), and the pixel
    budget then took the resolution of the whole view. Indices are kept (a patch may end up
    empty)."""
    if not patches:
        return patches
    textured = texture_map(gray, patches[0].mask.shape) >= min_texture
    k = 2 * TEXTURE_MARGIN + 1
    textured = cv2.dilate(textured.astype(np.uint8), np.ones((k, k), np.uint8)) > 0
    textured = without_specks(textured, MIN_VIEW_AREA_FRAC)
    masks = [p.mask & textured for p in patches]
    return [Patch(m, p.axis, p.normal, float(m.mean())) for p, m in zip(patches, masks)]


def without_specks(mask: np.ndarray, min_frac: float) -> np.ndarray:
    """(h, w) bool ``mask`` without its 8-connected components of fewer than ``min_frac``
    x its cells (in ``textured_patches``: MIN_VIEW_AREA_FRAC, the size a patch needs for a
    view: a region this small could not have one alone; a plane whose texture lies only in
    such islands, farther apart than TEXTURE_MARGIN, loses them too)."""
    _, labels, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
    keep = stats[:, cv2.CC_STAT_AREA] >= min_frac * mask.size
    keep[0] = False
    return keep[labels]


def tilt_neighbours(
    camera: pycolmap.Camera, patch: Patch, factor: float, steps: int
) -> list[Patch]:
    """Patches with ``patch``'s mask whose normals are tilted so that the patch's tilt
    t = 1 / cos(viewing angle) becomes t * factor**k, k = +-1..+-steps (rotations about
    n x v, v the patch's mean viewing ray; tilts under 1 or beyond 89 degrees are skipped).

    At strong obliquity the rectification is steep in the orientation: at 70 degrees a
    5-degree error leaves a residual tilt of 1.3, at 80 degrees one of 1.7, beyond what
    SIFT absorbs, and the network and vanishing points err by more than that. ASIFT samples
    tilts factor-spaced (sqrt 2) for the same reason. Both directions count on real photos
    (evd-dev, docs/evaluation.md "One default"): a plane rectified too little stays
    foreshortened; one rectified too much is stretched, which hurts less on a single view
    (synthetic: 40 vs 177 GT-consistent matches for 6 degrees either way at 75) but
    guessed focal lengths and vanishing points overstate tilts too."""
    h, w = patch.mask.shape
    rays = cam_utils.grid_rays(camera, w, h)[patch.mask]
    v = rays.sum(0)
    v /= np.linalg.norm(v)
    n = np.asarray(patch.normal, float) / np.linalg.norm(patch.normal)
    cos0 = float(np.clip(-(n @ v), 1e-6, 1.0))
    axis = np.cross(n, v)
    if np.linalg.norm(axis) < 1e-9:
        return []
    axis /= np.linalg.norm(axis)
    out = []
    for k in [k for k in range(-steps, steps + 1) if k != 0]:
        cos_k = cos0 / factor**k
        if not np.cos(np.deg2rad(89.0)) <= cos_k <= 1.0:
            continue
        delta = np.arccos(cos_k) - np.arccos(cos0)  # > 0: more tilt
        # rotating n about n x v by +delta moves it away from -v (more tilt)
        normal = axis_angle_rotation(axis, delta) @ n
        out.append(Patch(patch.mask, patch.axis, normal, patch.area_frac))
    return out


def with_tilt_neighbours(
    camera: pycolmap.Camera,
    patches: list[Patch],
    todo: list[int],
    conf: RectifyConf,
    bank_depth: bool = False,
) -> tuple[list[Patch], list[int]]:
    """``patches`` followed by the ``tilt_neighbours`` (conf.tilt_factor, conf.tilt_steps)
    of the plane hypotheses in ``todo`` (HYPOTHESIS_AXIS and REST_AXIS: planes from pairs of
    vanishing points, rectified_colmap.vp.hypotheses, whose orientations err most) and, with
    ``bank_depth``, of the depth planes' patches (axis >= 0) seen at
    conf.tilt_bank_min_angle_deg or more (appended after all of ``patches``, each a patch of
    its own, with its parent's axis), and ``todo`` with their indices added. Blind views
    (BLIND_AXIS) never get neighbours: they sample orientations already."""
    if conf.tilt_steps <= 0 or not todo:
        return patches, todo
    banked = [
        i
        for i in todo
        if patches[i].axis in (HYPOTHESIS_AXIS, REST_AXIS) or (bank_depth and patches[i].axis >= 0)
    ]
    angle = viewing_angles(camera, [patches[i] for i in banked])
    patches, todo = list(patches), list(todo)
    for i, a in zip(banked, angle):
        if a < conf.tilt_bank_min_angle_deg:
            continue
        for p in tilt_neighbours(camera, patches[i], conf.tilt_factor, conf.tilt_steps):
            todo.append(len(patches))
            patches.append(p)
    return patches, todo


def patches_worth_rectifying(
    camera: pycolmap.Camera, patches: list[Patch], conf: RectifyConf
) -> list[int]:
    """Indices of the patches to rectify. Left to plain SIFT (at full budget: the pipeline
    fills from plain SIFT) are patches seen nearly frontally (median viewing angle under
    conf.min_rectify_angle_deg: the warp would change little) and patches of less than
    MIN_VIEW_AREA_FRAC of the image (after ``textured_patches``: too little texture)."""
    angle = viewing_angles(camera, patches)
    area = np.array([p.mask.mean() for p in patches])
    keep = (angle >= conf.min_rectify_angle_deg) & (area >= MIN_VIEW_AREA_FRAC)
    if len(patches):
        logger.debug(
            "patches: viewing angle %s, textured area %s -> rectify %s",
            np.round(angle),
            np.round(area, 3),
            keep.astype(int),
        )
    return [int(i) for i in np.flatnonzero(keep)]


def rectifications_within_budget(
    camera: pycolmap.Camera,
    patches: list[Patch],
    indices: list[int],
    conf: RectifyConf,
    pixel_budget: float,
    turn: bool = True,
) -> list[Rectification]:
    """Views (``view_of_patch``: rectifications, a blind patch's tilt simulation) of the
    given patches within ``pixel_budget``
    (their summed sizes w x h, to within a view's border when views are tiny). When the
    views' own sizes exceed it, each view is scaled down to at most a common claim per work
    cell of its patch, a cell held by several views' patches shared among them
    (``shared_cells``, ``water_fill``): a view that needs less keeps its size, and no view,
    however large (a plane hypothesis seen near grazing), takes another's pixels. Each
    patch's view is computed once, and its mask only at the final scale. ``turn``:
    views turned to their smallest box (rectify.patch_view)."""
    views = [(i, view_of_patch(camera, patches[i], conf, turn)) for i in indices]
    views = [(i, v) for i, v in views if v is not None]
    claims = shared_cells(np.stack([v.mask for _, v in views])) if views else None
    scales = np.ones(len(views))
    for _ in range(4):  # the borders do not scale: a few steps to fit
        sizes = np.array(
            [np.prod(view_camera(v, conf, s)[1]) for (_, v), s in zip(views, scales)], float
        )
        total = sizes.sum()
        if total <= pixel_budget:
            break
        caps = water_fill(sizes, claims, 0.999 * pixel_budget)
        scales *= np.sqrt(np.minimum(1.0, caps / sizes))
    rects = (finish_rectification(camera, v, i, conf, s) for (i, v), s in zip(views, scales))
    return [r for r in rects if r is not None]


def view_of_patch(
    camera: pycolmap.Camera, patch: Patch, conf: RectifyConf, turn: bool = True
) -> PatchView | None:
    """A patch's view before the budget: ASIFT's tilt simulation for a blind patch
    (``tilt_simulation_view``: an orientation sampled, not estimated), else the
    rectification of its plane (rectify.patch_view)."""
    if patch.axis == BLIND_AXIS:
        return tilt_simulation_view(camera, patch, conf, turn)
    return patch_view(camera, patch, conf, turn)


def shared_cells(masks: np.ndarray) -> np.ndarray:
    """(n, h, w) bool work-grid masks of n views' patches -> (n,) each view's share of its
    cells: a cell held by k of the masks counts 1 / k for each of them (the shares sum to
    the cells held by any)."""
    share = 1.0 / np.maximum(masks.sum(0), 1)
    return np.array([share[m].sum() for m in masks], np.float64)


def water_fill(needs: np.ndarray, weights: np.ndarray, total: float) -> np.ndarray:
    """(n,) shares of ``total`` for n claims: min(need_i, c * weight_i) with the largest
    common c whose shares sum to at most ``total`` (all of ``needs`` when they fit).
    A claim that needs less than its weight's part keeps its need, and no claim can take
    another's part, however large its need (a claim of weight 0 gets nothing)."""
    needs = np.asarray(needs, float)
    weights = np.asarray(weights, float)
    if needs.sum() <= total:
        return needs.copy()
    ratio = np.where(weights > 0, needs / np.maximum(weights, 1e-300), np.inf)
    order = np.argsort(ratio)
    r, n, w = ratio[order], needs[order], weights[order]
    # at c = r[k], claims 0..k are met: sum(n[:k+1]) + r[k] * sum(w[k+1:])
    after = w.sum() - np.cumsum(w)
    tail = np.zeros_like(after)
    tail[after > 0] = r[after > 0] * after[after > 0]  # no inf x 0 (a claim of weight 0)
    filled = np.cumsum(n) + tail
    k = int(np.searchsorted(filled, total, side="right"))  # claims 0..k-1 met
    met = n[:k].sum()
    rest = w[k:].sum()
    c = (total - met) / rest if rest > 0 else 0.0
    return np.minimum(needs, c * weights)


def viewing_masks(
    camera: pycolmap.Camera,
    rects: list[Rectification],
    patches: list[Patch],
    shape: tuple[int, int],
    max_viewing_angle_deg: float,
) -> np.ndarray:
    """(n, h, w) bool: the work-grid cells each rectification covers: cells of its patch
    whose viewing angle is within the limit (cells beyond it are left to plain SIFT).
    Patches may overlap (depth-free whole-image warps): a cell can be in several masks."""
    h, w = shape
    rays = cam_utils.unit_grid_rays(camera, w, h)
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


def centre_ray(camera: pycolmap.Camera) -> np.ndarray:
    """(3,) unit ray through the image centre (COLMAP pixels): the axis about which
    ``blind_patches`` samples tilts and ``tilt_simulation_view`` measures them."""
    v = cam_utils.image_to_rays(camera, [camera.width / 2.0, camera.height / 2.0])[0]
    return v / np.linalg.norm(v)


def blind_patches(
    camera: pycolmap.Camera,
    shape: tuple[int, int],
    tilts: tuple[float, ...] = BLIND_TILTS,
    longitude_step_deg: float = BLIND_LONGITUDE_STEP_DEG,
) -> list[Patch]:
    """Whole-grid patches (BLIND_AXIS, masks of the (h, w) work grid ``shape``) of planes
    sampled as ASIFT samples affine tilts, for an image where no estimate (depth, lines) gave
    a view: for each tilt t, planes seen at arccos(1 / t) from the ray through the image
    centre, tilted towards image directions phi = 0, s / t, 2 s / t, ... < 180 degrees
    (s = ``longitude_step_deg``): 5 + 10 views with the defaults, ASIFT's. Normals face the
    camera. Their views: ``tilt_simulation_view``."""
    h, w = shape
    v = centre_ray(camera)
    e1 = np.array([1.0, 0.0, 0.0]) - v[0] * v  # the image's x, perpendicular to v
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(v, e1)
    mask = np.ones((h, w), bool)
    out = []
    for t in tilts:
        theta = np.arccos(1.0 / t)
        for phi in np.deg2rad(np.arange(0.0, 180.0, longitude_step_deg / t)):
            d = np.cos(phi) * e1 + np.sin(phi) * e2
            normal = -np.cos(theta) * v + np.sin(theta) * d
            out.append(Patch(mask, BLIND_AXIS, normal, 1.0))
    return out


def tilt_simulation_view(
    camera: pycolmap.Camera, patch: Patch, conf: RectifyConf, turn: bool = True
) -> PatchView | None:
    """The view of a blind patch (views.blind_patches: an orientation sampled, not
    estimated): ASIFT's tilt simulation instead of a perspective rectification. With t =
    1 / cos of the patch's viewing angle at the image centre and d its tilt direction, the
    image (in normalised coordinates: distortion undone) is compressed by t across d, an
    affine map: a plane of that orientation is undone to first order at the centre, no
    part of the image is enlarged (the larger singular value is 1 at the median: ASIFT's
    rule), and neither the focal length nor a whole-image plane's perspective (stretched up
    to the viewing-angle limit by a rectification) sets the view's size. ``turn``: d is
    turned onto the view's x axis, as ASIFT turns; without it (upright SIFT) the view keeps
    the image's axes."""
    mask = np.asarray(patch.mask, bool)
    gh, gw = mask.shape
    cells = np.flatnonzero(mask)
    if len(cells) == 0:
        return None
    v = centre_ray(camera)
    n = np.asarray(patch.normal, np.float64) / np.linalg.norm(patch.normal)
    cos0 = float(-(n @ v))
    d = n + cos0 * v  # the tilt direction, perpendicular to v
    if not 0.0 < cos0 < 1.0 or np.hypot(d[0], d[1]) < 1e-12:
        return None
    a = -np.arctan2(d[1], d[0])  # the rotation that takes d onto +x
    Rz = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    A = np.diag([1.0, cos0])  # compress y (across d) by t
    R = np.eye(3)
    if turn:
        R[:2, :2] = Rz
    else:
        A = Rz.T @ A @ Rz
    sx, sy = camera.width / gw, camera.height / gh
    grid = cam_utils.grid_rays(camera, gw, gh).reshape(-1, 3)
    # the box of the hull: each grid row's end cells where the map is affine (pinhole)
    box = cells[row_ends(cells // gw)] if cam_utils.is_pinhole(camera) else cells
    u = np.stack(virtual_coords(R, grid[box]), 1) @ A.T
    if turn:  # the compressed image (a parallelogram) turned to its smallest box
        Rfit = fitting_roll(u)[:2, :2]
        A, u = Rfit @ A, u @ Rfit.T
    sel = np.linspace(0, len(cells) - 1, min(len(cells), MAX_FOCAL_SAMPLES)).astype(np.int64)
    rows, cols = np.divmod(cells[sel], gw)
    xy = np.stack([(cols + OFFSET) * sx, (rows + OFFSET) * sy], 1)
    _, Ju = rays_to_rectified_jacobian(R, grid[cells[sel]])
    J = A @ image_to_view_jacobian(camera, Ju, xy)
    f = view_focal(singular_values_2x2(J), "coarsest")
    if f is None:
        return None
    half = np.nanmax((0.5 * np.abs(J).reshape(-1, 2) @ np.array([sx, sy])).reshape(-1, 2), axis=0)
    return PatchView(
        normal=np.array([0.0, 0.0, -1.0]),  # the image plane's: the view is an affine image
        R=R,
        mask=mask,
        cos_max=np.cos(np.deg2rad(conf.max_viewing_angle_deg)),
        f=f,
        lo=u.min(0) - half,
        hi=u.max(0) + half,
        A=A,
    )
