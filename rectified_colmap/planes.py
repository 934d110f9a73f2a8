"""Normals -> three orthogonal dominant directions -> per-pixel labels -> plane patches.

Labels (h, w) int8: -1 = non-planar; otherwise ``2 * k + s`` where k in {0, 1, 2} is the
dominant direction and s = 0 when the pixel normal n has n . d_k > 0, s = 1 when n . d_k < 0
(the antipode). Directions (3, 3) float64: rows d_k, orthonormal, right-handed.

The three directions come from orthogonal k-means with antipodes (Toft et al. 2020): each
normal joins the axis k maximising |n . d_k| (an outlier when that angle exceeds
conf.inlier_angle_deg); the rotation whose rows are the axes is then refitted to the
sign-aligned members by orthogonal Procrustes (SVD), and the two steps alternate. Several
initialisations (the strongest normal directions, then random rotations); the most inliers
win.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import cv2
import numpy as np

from .config import PlaneConf
from .geometry import order_frame

logger = logging.getLogger(__name__)


NUM_SAMPLES = 8000
"""Normals subsampled to fit the three directions (more change the directions by less than
the network's error)."""
NUM_RESTARTS = 4
"""Starts of the orthogonal k-means (the strongest normal directions, then random
rotations); the most inliers win."""
NUM_ITERS = 15
"""Iterations of the orthogonal k-means (it stops earlier when the labels settle)."""

HYPOTHESIS_AXIS = -1
"""``Patch.axis`` of a plane hypothesis from a pair of vanishing points (no dominant
direction: rectified_colmap.vp.hypotheses)."""
REST_AXIS = -2
"""``Patch.axis`` of a plane hypothesis over the rest of its plane: the front-facing cells
that the image's patches of its orientation (the depth's, oriented by the lines) do not
cover (rectified_colmap.vp.hypotheses.hypothesis_patches). Its views' features come only
in the part of plain SIFT's budget its keypoints left unused (rectified_colmap.budget)."""
BLIND_AXIS = -3
"""``Patch.axis`` of a blind view: a plane orientation sampled with no estimate behind it
(rectified_colmap.views.blind_patches), for an image where no estimate gave a view.
Second tier, as REST_AXIS; its view compresses instead of stretching (coarsest)."""


@dataclass
class Patch:
    mask: np.ndarray
    """(h, w) bool at the normals' grid (work resolution)."""
    axis: int
    """Index k of the dominant direction, or HYPOTHESIS_AXIS / REST_AXIS / BLIND_AXIS."""
    normal: np.ndarray
    """(3,) unit normal of the patch: +-d_k, the sign of its label, facing the camera."""
    area_frac: float
    """Fraction of the image the patch covers."""


@dataclass
class PlaneResult:
    directions: np.ndarray | None
    """(3, 3) rows d_k, or None when no directions could be fitted."""
    support: np.ndarray
    """(3,) fraction of valid normals assigned to each direction."""
    labels: np.ndarray
    """(h, w) int8, see module docstring."""
    patches: list[Patch]


def _modes(cands: np.ndarray, pts: np.ndarray, cos_t: float) -> np.ndarray:
    """Axial support of each candidate direction: how many ``pts`` lie within the angle
    (either sign)."""
    return (np.abs(cands @ pts.T) >= cos_t).sum(1)


def _initial_rotations(
    n: np.ndarray, conf: PlaneConf, rng: np.random.Generator, num_restarts: int
) -> list[np.ndarray]:
    """First the strongest normal direction and the strongest direction orthogonal to it,
    then random rotations."""
    cos_t = np.cos(np.deg2rad(conf.inlier_angle_deg))
    sin_t = np.sin(np.deg2rad(conf.inlier_angle_deg))
    out = []
    ref = n[rng.choice(len(n), min(len(n), 1024), replace=False)]
    cand = ref[:128]
    d0 = cand[np.argmax(_modes(cand, ref, cos_t))]
    rest = ref[np.abs(ref @ d0) < sin_t]
    if len(rest) >= 2:
        proj = rest - np.outer(rest @ d0, d0)
        proj /= np.linalg.norm(proj, axis=1, keepdims=True)
        d1 = proj[np.argmax(_modes(proj[:128], proj, cos_t))]
    else:
        d1 = np.cross(d0, [1.0, 0.0, 0.0] if abs(d0[0]) < 0.9 else [0.0, 1.0, 0.0])
    out.append(_nearest_rotation(np.stack([d0, d1, np.cross(d0, d1)])))
    while len(out) < max(1, num_restarts):
        q, r = np.linalg.qr(rng.standard_normal((3, 3)))
        out.append(_nearest_rotation(q * np.sign(np.diag(r))))
    return out


def _nearest_rotation(m: np.ndarray) -> np.ndarray:
    """Rotation (det +1) maximising trace(R^T m): orthogonal Procrustes by SVD."""
    u, _, vt = np.linalg.svd(m)
    d = np.sign(np.linalg.det(u @ vt)) or 1.0
    return u @ np.diag([1.0, 1.0, d]) @ vt


def _orthogonal_kmeans(
    n: np.ndarray, D: np.ndarray, cos_t: float, num_iters: int
) -> tuple[np.ndarray, int, np.ndarray]:
    """Alternate assignment and Procrustes refit from D. Returns (D, inliers, counts)."""
    prev = None
    for _ in range(max(1, num_iters)):
        dots = n @ D.T
        k = np.argmax(np.abs(dots), axis=1)
        a = np.take_along_axis(dots, k[:, None], 1)[:, 0]
        inl = np.abs(a) >= cos_t
        lab = np.where(inl, k, -1)
        if prev is not None and np.array_equal(lab, prev):
            break
        prev = lab
        # Sign-aligned members summed per axis: B[k] = sum s_i n_i; the rotation maximising
        # sum_i d_k(i) . s_i n_i is the polar factor of B (weighted by member counts).
        if not inl.any():
            break
        s = np.sign(a[inl])[:, None] * n[inl]
        ki = k[inl]
        B = np.stack([np.bincount(ki, weights=s[:, j], minlength=3) for j in range(3)], 1)
        D = _nearest_rotation(B)
    dots = np.abs(n @ D.T)
    k = np.argmax(dots, axis=1)
    inl = np.take_along_axis(dots, k[:, None], 1)[:, 0] >= cos_t
    counts = np.bincount(k[inl], minlength=3)
    return D, int(inl.sum()), counts


def _canonical(D: np.ndarray, counts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Order axes by support (descending), face the first two toward the camera (d_z <= 0),
    and make the frame right-handed."""
    D, order = order_frame(D, counts)
    return D, counts[order]


def fit_dominant_directions(
    normals: np.ndarray,
    conf: PlaneConf = PlaneConf(),
    rng: np.random.Generator | None = None,
    num_samples: int = NUM_SAMPLES,
    num_restarts: int = NUM_RESTARTS,
) -> tuple[np.ndarray | None, np.ndarray]:
    """Orthogonal k-means (with antipodes) on (N, 3) unit normals -> (directions (3, 3) or
    None, support (3,)).

    NaN rows are ignored; at most ``num_samples`` normals (drawn with ``rng``) are fitted,
    from ``num_restarts`` starts (fewer for cheap repeated fits: rectified_colmap.disparity).
    Support is the fraction of the (subsampled) valid normals within conf.inlier_angle_deg
    of each direction. Directions are ordered by support. None when
    fewer than conf.min_normals valid normals remain. Deterministic given ``rng``.
    """
    rng = rng if rng is not None else np.random.default_rng(0)
    n = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
    n = n[np.isfinite(n).all(1)]
    if len(n) < max(conf.min_normals, 3):
        logger.debug("only %d valid normals: no dominant directions", len(n))
        return None, np.zeros(3)
    n = n / np.linalg.norm(n, axis=1, keepdims=True)
    if len(n) > num_samples:
        n = n[rng.choice(len(n), num_samples, replace=False)]
    cos_t = np.cos(np.deg2rad(conf.inlier_angle_deg))
    best = None
    for D0 in _initial_rotations(n, conf, rng, num_restarts):
        D, score, counts = _orthogonal_kmeans(n, D0, cos_t, NUM_ITERS)
        if best is None or score > best[1]:
            best = (D, score, counts)
    D, counts = _canonical(best[0], best[2])
    return D, counts / len(n)


def assign_directions(
    normals: np.ndarray, directions: np.ndarray, conf: PlaneConf = PlaneConf()
) -> np.ndarray:
    """(h, w, 3) normals (NaN = none) -> labels (h, w) int8."""
    D = np.asarray(directions, dtype=np.float64)
    dots = np.asarray(normals, dtype=np.float64) @ D.T
    k = np.argmax(np.abs(np.nan_to_num(dots)), axis=-1)
    a = np.take_along_axis(dots, k[..., None], -1)[..., 0]
    cos_t = np.cos(np.deg2rad(conf.max_angle_deg))
    with np.errstate(invalid="ignore"):
        ok = np.abs(a) >= cos_t  # False for NaN
    labels = np.where(ok, 2 * k + (a < 0), -1)
    return labels.astype(np.int8)


def find_patches(
    labels: np.ndarray, directions: np.ndarray, conf: PlaneConf = PlaneConf()
) -> list[Patch]:
    """Connected components per label (direction AND sign), small ones dropped.

    Each label mask is first opened (conf.opening_radius); components use 8-connectivity.
    Patches are returned largest first."""
    h, w = labels.shape
    min_area = conf.min_area_frac * h * w
    r = int(conf.opening_radius)
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1)) if r > 0 else None
    patches = []
    for lab in range(6):
        mask = (labels == lab).astype(np.uint8)
        if kernel is not None:
            mask = cv2.morphologyEx(mask, cv2.MORPH_OPEN, kernel)
        if mask.sum() < max(min_area, 1):
            continue
        num, comp, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
        k, s = divmod(lab, 2)
        normal = np.asarray(directions[k], dtype=np.float64) * (-1.0 if s else 1.0)
        for c in range(1, num):
            area = int(stats[c, cv2.CC_STAT_AREA])
            if area < max(min_area, 1):
                continue
            patches.append(Patch(comp == c, k, normal.copy(), area / (h * w)))
    patches.sort(key=lambda p: -p.area_frac)
    return patches


def detect_planes(
    normals: np.ndarray, conf: PlaneConf = PlaneConf(), rng: np.random.Generator | None = None
) -> PlaneResult:
    """fit_dominant_directions + assign_directions + find_patches.

    ``support`` here is the fraction of all valid normals of the grid carrying each axis's
    labels (either sign)."""
    h, w = normals.shape[:2]
    D, _ = fit_dominant_directions(normals.reshape(-1, 3), conf, rng)
    if D is None:
        return PlaneResult(None, np.zeros(3), np.full((h, w), -1, np.int8), [])
    labels = assign_directions(normals, D, conf)
    num_valid = max(int(np.isfinite(normals).all(-1).sum()), 1)
    support = np.bincount(labels[labels >= 0].ravel() // 2, minlength=3)[:3] / num_valid
    patches = find_patches(labels, D, conf)
    if conf.fill_gaps == "hull":
        patches = patches_filling_hulls(patches)
    elif conf.fill_gaps == "nearest":
        patches = patches_filling_gaps(patches)
    return PlaneResult(D, support, labels, patches)


def patches_filling_gaps(patches: list[Patch]) -> list[Patch]:
    """Every cell in no patch joins the patch nearest to it on the grid (Euclidean distance
    to the patch's closest cell; cv2.distanceTransformWithLabels). Cells drop out of patches
    where the depth's normals are noisy (outliers, windows over a depth jump, the opening,
    small components), most of all on the planes seen most obliquely: those cells then get
    the view of the plane around them instead of none."""
    if not patches:
        return patches
    h, w = patches[0].mask.shape
    owner = np.full(h * w, -1, np.int32)
    for i, p in enumerate(patches):
        owner[p.mask.ravel() & (owner < 0)] = i
    gaps = (owner < 0).reshape(h, w).astype(np.uint8)
    if not gaps.any():
        return patches
    _, lab = cv2.distanceTransformWithLabels(
        gaps, cv2.DIST_L2, cv2.DIST_MASK_PRECISE, labelType=cv2.DIST_LABEL_PIXEL
    )
    seeds = np.flatnonzero(gaps.ravel() == 0)  # label k: the k-th patch cell in scan order
    owner = owner[seeds[lab.ravel() - 1]].reshape(h, w)
    return [
        Patch(owner == i, p.axis, p.normal, float((owner == i).mean()))
        for i, p in enumerate(patches)
    ]


def patches_filling_hulls(patches: list[Patch]) -> list[Patch]:
    """Every cell in no patch whose centre lies in a patch's convex hull (of its cells'
    centres, edges included) joins that patch, the largest where hulls overlap: holes and
    bays where the normals were noisy. The filled cells lie in the hull, whose box is the
    box of the patch's own cells, so a view (rectify.patch_view: the box of its cells) keeps
    its box and pixels and only its mask grows; where the texture cut
    (views.textured_patches) shrank the box, at most back to that box."""
    if not patches:
        return patches
    free = ~np.any([p.mask for p in patches], axis=0)
    out = []
    for p in patches:
        take = free & convex_hull_cells(p.mask)
        free &= ~take
        mask = p.mask | take
        out.append(Patch(mask, p.axis, p.normal, float(mask.mean())))
    return out


def convex_hull_cells(mask: np.ndarray) -> np.ndarray:
    """(h, w) bool: the cells whose centres lie in the convex hull of ``mask``'s cell
    centres (on its edges included); exact half-plane tests, no rasterisation."""
    pts = cv2.findNonZero(mask.astype(np.uint8))
    out = np.zeros(mask.shape, bool)
    if pts is None:
        return out
    hull = cv2.convexHull(pts, clockwise=False).reshape(-1, 2).astype(np.int64)
    (x0, y0), (x1, y1) = hull.min(0), hull.max(0)
    ys, xs = np.mgrid[y0 : y1 + 1, x0 : x1 + 1]
    inside = np.ones(xs.shape, bool)
    for (ax, ay), (bx, by) in zip(hull, np.roll(hull, -1, 0)):
        cross = (bx - ax) * (ys - ay) - (by - ay) * (xs - ax)  # integers: exact
        inside &= cross >= 0
    out[y0 : y1 + 1, x0 : x1 + 1] = inside
    return out
