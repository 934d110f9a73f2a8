"""Do two images' views meet? The geometry of a view set, before any SIFT (issue 41, item 2).

Two views of one plane can be matched by SIFT where the map between them is close to a
similarity: its **transition tilt** (ratio of the singular values of its local affine map,
ASIFT's measure) must be small, about 2 at most for SIFT. An image's **view set** is the image
itself (the identity) plus its rectified views (homographies image -> view, each with the
mask of view pixels it holds). For a planar pair with a ground-truth homography H, a point of
the overlap is **met** when some view a of image 0 and some view b of image 1 both hold it
and the map a -> b = H_b H H_a^-1 has a transition tilt there of at most ``tau_max``.

This tells, with no SIFT, whether a view set can match a pair at all: what the orientation
hypotheses, their neighbours and the masks give. What the resolution, the budget and the
detector then lose is research/scripts/diagnose_views.py's SIFT stages.

Conventions: COLMAP pixels everywhere (H, the view homographies and the masks' pixel
centres at +0.5); a view is ``(H (3, 3) image -> view, mask (h, w) bool or None)``, None for
the whole plane of the image (no mask).
"""

from __future__ import annotations

import numpy as np
import pycolmap

from rectified_colmap.features import keypoints_in_mask
from rectified_colmap.eval.homography import HomographyPair, apply_homography, points_in_region
from rectified_colmap.planes import BLIND_AXIS, HYPOTHESIS_AXIS, Patch
from rectified_colmap.rectify import Rectification, image_to_rectified_homography
from rectified_colmap_research.evaluation.plane_pairs import homography_jacobian

View = tuple[np.ndarray, np.ndarray | None]


def view_set(camera: pycolmap.Camera, rects: list[Rectification]) -> list[View]:
    """The image itself (identity, no mask) and each rectification's (H image -> view,
    mask)."""
    return [(np.eye(3), None)] + [(image_to_rectified_homography(camera, r), r.mask) for r in rects]


def view_kinds(patches: list[Patch]) -> list[str]:
    """The kind of each patch's view: ``depth`` (a plane of the depth network), ``hyp`` /
    ``rest`` (a plane hypothesis of the vanishing points, over the whole image / over the
    rest of a plane), ``blind`` (ASIFT-like views without an estimate), and ``-nbr`` for
    their tilt neighbours: a depth, hypothesis or rest patch with the axis and the very
    mask array of an earlier one (views.tilt_neighbours gives each its parent's mask
    object; two hypotheses over the same cells have equal masks, not the same one)."""
    out = []
    for i, p in enumerate(patches):
        if p.axis == BLIND_AXIS:
            out.append("blind")
            continue
        kind = "depth" if p.axis >= 0 else "hyp" if p.axis == HYPOTHESIS_AXIS else "rest"
        nbr = any(q.axis == p.axis and q.mask is p.mask for q in patches[:i])
        out.append(kind + "-nbr" if nbr else kind)
    return out


def asift_view_set(num_tilts: int = 5, longitude_step_deg: float = 72.0) -> list[View]:
    """ASIFT's simulated views (Morel and Yu, 2009; OpenCV's defaults): the identity, and for
    tilts t = sqrt(2)^k, k = 1..num_tilts, the image rotated by each longitude phi in
    [0, 180) degrees in steps of longitude_step_deg / t and compressed by t along x."""
    out: list[View] = [(np.eye(3), None)]
    for k in range(1, num_tilts + 1):
        t = 2 ** (k / 2)
        for phi in np.arange(0.0, 180.0, longitude_step_deg / t):
            c, s = np.cos(np.radians(phi)), np.sin(np.radians(phi))
            rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
            out.append((np.diag([1.0 / t, 1.0, 1.0]) @ rot, None))
    return out


def overlap_points(pair: HomographyPair, step: float = 8.0) -> np.ndarray:
    """(N, 2) points of image 0 on a ``step``-pixel grid (cell centres) inside the pair's
    region whose image under H is in front of camera 1, inside image 1 and its region."""
    W, H = pair.size0
    xs, ys = np.meshgrid(np.arange(step / 2, W, step), np.arange(step / 2, H, step))
    xy = np.stack([xs.ravel(), ys.ravel()], 1)
    xy = xy[points_in_region(xy, pair.region0)]
    xy1 = apply_homography(pair.H, xy)
    W1, H1 = pair.size1
    with np.errstate(invalid="ignore"):
        ok = np.isfinite(xy1).all(1)
        ok &= (xy1[:, 0] >= 0) & (xy1[:, 1] >= 0) & (xy1[:, 0] < W1) & (xy1[:, 1] < H1)
    ok[ok] = points_in_region(xy1[ok], pair.region1)
    return xy[ok]


def in_mask(mask: np.ndarray | None, xy: np.ndarray) -> np.ndarray:
    """(N,) bool: which COLMAP pixel positions (N, 2) fall on a True pixel of ``mask``
    (None: all; non-finite positions: none)."""
    if mask is None:
        return np.ones(len(xy), bool)
    h, w = mask.shape
    finite = np.isfinite(xy).all(1)
    return finite & keypoints_in_mask(np.where(finite[:, None], xy, -1.0), mask, (w, h))


def best_transition_tilt(
    pair: HomographyPair, views0: list[View], views1: list[View], xy0: np.ndarray
) -> np.ndarray:
    """(N,) the smallest transition tilt over all (view of image 0, view of image 1) that
    both hold the image-0 point (N, 2) (and its image under H); inf where no pair does."""
    return best_view_pairs(pair, views0, views1, xy0)[0]


def best_view_pairs(
    pair: HomographyPair,
    views0: list[View],
    views1: list[View],
    xy0: np.ndarray,
    tau_max: float = 2.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per image-0 point (N, 2): ((N,) the smallest transition tilt over the pairs of views
    that both hold it, inf where none does; (N, 2) int, the indices of that pair of views,
    -1 where none; (N,) the scale change max(s, 1 / s), s = sqrt |det|, of the map between
    the two views nearest 1 among the pairs that meet there (tilt at most ``tau_max``), inf
    where none does). SIFT meets a scale change only where both views hold the texture at
    the matching octaves: views that meet only 10-30x apart in scale meet in name."""
    n = len(xy0)
    best, which, scale = np.full(n, np.inf), np.full((n, 2), -1), np.full(n, np.inf)
    if n == 0:
        return best, which, scale
    xy1 = apply_homography(pair.H, xy0)
    JH = homography_jacobian(pair.H, xy0)
    side1 = []
    for Hb, mb in views1:
        held = in_mask(mb, apply_homography(Hb, xy1))
        side1.append((held, homography_jacobian(Hb, xy1)))
    for a, (Ha, ma) in enumerate(views0):
        held0 = in_mask(ma, apply_homography(Ha, xy0))
        if not held0.any():
            continue
        inv_a = np.linalg.inv(homography_jacobian(Ha, xy0)[held0])
        for b, (held1, Jb) in enumerate(side1):
            both = held1[held0]
            if not both.any():
                continue
            M = Jb[held0][both] @ JH[held0][both] @ inv_a[both]
            s = np.linalg.svd(M, compute_uv=False)
            with np.errstate(invalid="ignore", divide="ignore"):
                tau = np.nan_to_num(np.where(s[:, 1] > 0, s[:, 0] / s[:, 1], np.inf), nan=np.inf)
                change = np.sqrt(s[:, 0] * s[:, 1])
                change = np.nan_to_num(np.maximum(change, 1.0 / change), nan=np.inf)
            idx = np.flatnonzero(held0)[both]
            better = tau < best[idx]
            best[idx[better]], which[idx[better]] = tau[better], (a, b)
            meet = tau <= tau_max
            scale[idx[meet]] = np.minimum(scale[idx[meet]], change[meet])
    return best, which, scale


def met_fraction(
    pair: HomographyPair,
    views0: list[View],
    views1: list[View],
    tau_max: float = 2.0,
    step: float = 8.0,
) -> float:
    """Fraction of the pair's overlap (``overlap_points``) met by the two view sets (a
    transition tilt of at most ``tau_max`` between some two views that hold the point); 0
    for no overlap."""
    xy0 = overlap_points(pair, step)
    if len(xy0) == 0:
        return 0.0
    return float((best_transition_tilt(pair, views0, views1, xy0) <= tau_max).mean())
