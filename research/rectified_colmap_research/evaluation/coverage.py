"""Whether an image pair's views bring its plane within SIFT's reach: the residual
transition tilt (issue 41, item 3).

A view of an image is a map of its pixels (a homography ``H``, image -> view pixels, COLMAP
convention: the plain image is the identity, a rectified view ``K_v R K^-1``, an ASIFT
view an affine tilt). Two views, one of each image of a planar pair with ground truth ``G``
(image 0 -> image 1), see a point ``x`` of the plane with the local affine map

    A = J_b(G x) @ J_G(x) @ J_a(x)^-1

between them (J: the maps' Jacobians). SIFT absorbs an ``A`` whose anisotropy, the ratio
of its singular values (ASIFT's *transition tilt*), is small: about 2 (Morel and Yu 2009;
plain SIFT matches up to 60-65 degrees from a frontal view). The residual tilt of a point
is the smallest over all pairs of views that both contain it; where it is small, the
views *cover* the point, whatever SIFT then finds there. It separates an orientation that
no view reaches (a loss before SIFT) from a view set that reaches the plane and still
loses the pair (the views' resolution, the budget, the detector, the matching).

Everything here is geometry on arrays: no image is read.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rectified_colmap.planes import BLIND_AXIS, HYPOTHESIS_AXIS, Patch

from .extreme_pairs import singular_values
from .plane_pairs import homography_jacobian

SIFT_TILT_TOLERANCE = 2.0
"""The transition tilt SIFT absorbs (Morel and Yu 2009, ASIFT's analysis: about 2). A
reporting threshold, not a setting of the pipeline."""


@dataclass
class View:
    """One view of an image: ``H`` (3, 3) image -> view pixels (COLMAP convention); the
    points it contains: inside ``size`` (width, height) and, where given, on ``mask``
    (height, width) bool; None: every point of the image (the plain image, ASIFT's
    views). ``kind`` names it in reports."""

    H: np.ndarray
    size: tuple[int, int] | None = None
    mask: np.ndarray | None = None
    kind: str = "plain"


def view_kinds(patches: list[Patch]) -> list[str]:
    """The kind of each patch's view: ``depth`` (a plane of the depth network), ``hyp`` /
    ``rest`` (a plane hypothesis of the vanishing points, over the whole image / over the
    rest of a plane), ``blind`` (ASIFT-like views without an estimate), and ``-nbr`` for
    their tilt neighbours: a depth, hypothesis or
    rest patch with the axis and the very mask array of an earlier one is a tilt neighbour
    (views.tilt_neighbours gives each its parent's mask object; two hypotheses over the
    same cells have equal masks, not the same one)."""
    out = []
    for i, p in enumerate(patches):
        if p.axis == BLIND_AXIS:
            out.append("blind")
            continue
        kind = "depth" if p.axis >= 0 else "hyp" if p.axis == HYPOTHESIS_AXIS else "rest"
        nbr = any(q.axis == p.axis and q.mask is p.mask for q in patches[:i])
        out.append(kind + "-nbr" if nbr else kind)
    return out


def plain_view() -> View:
    """The image itself: plain SIFT's view."""
    return View(np.eye(3))


def asift_views(max_tilt: int = 5, tilt_step: float = 2**0.5, roll_base_deg: float = 72.0):
    """OpenCV's ``AffineFeature`` views with its defaults (tilts 1, sqrt 2, ..., 4 sqrt 2;
    at tilt t the longitudes 0, s, 2 s, ... below 180 degrees, s = 72 / t): each rotates the
    image by the longitude and compresses its x axis by t (``affineSkew``). A list of
    :class:`View` covering the whole image, kind ``asift``."""
    views = [View(np.eye(3), kind="asift")]
    for k in range(1, max_tilt + 1):
        t = tilt_step**k
        step = roll_base_deg / t
        n = int(np.floor(180.0 / step))
        n -= int(np.isclose(n * step, 180.0))
        for j in range(n + 1):
            c, s = np.cos(np.radians(step * j)), np.sin(np.radians(step * j))
            A = np.diag([1.0 / t, 1.0, 1.0]) @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
            views.append(View(A, kind="asift"))
    return views


def view_contains(view: View, xy: np.ndarray) -> np.ndarray:
    """(N,) bool: which of the (N, 2) image points (COLMAP pixels) the view contains: in
    front of it and inside its size and mask (the pixel whose square holds the mapped
    point)."""
    xy = np.asarray(xy, np.float64).reshape(-1, 2)
    if view.size is None:
        return np.ones(len(xy), bool)
    p = np.c_[xy, np.ones(len(xy))] @ view.H.T
    ok = p[:, 2] > 1e-12
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = p[:, :2] / p[:, 2:]
    w, h = view.size
    ok &= (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
    if view.mask is not None and ok.any():
        col = np.clip(np.floor(uv[ok, 0]).astype(int), 0, w - 1)
        row = np.clip(np.floor(uv[ok, 1]).astype(int), 0, h - 1)
        ok[ok] = view.mask[row, col]
    return ok


def anisotropy(A: np.ndarray) -> np.ndarray:
    """(...) ratio of the larger to the smaller singular value of (..., 2, 2) matrices (inf
    for a singular one, NaN for a NaN one)."""
    s = singular_values(A.reshape(-1, 2, 2))
    with np.errstate(divide="ignore", invalid="ignore"):
        return (s[:, 0] / s[:, 1]).reshape(A.shape[:-2])


def view_pair_maps(G: np.ndarray, xy0: np.ndarray, views0: list[View], views1: list[View]):
    """For each view b of ``views1``, the local affine maps ``A`` (V0, N, 2, 2) from every
    view of ``views0`` to b at the (N, 2) image-0 points ``xy0`` of the plane ``G`` (3, 3)
    image 0 -> image 1, and (V0, N) bool: both views contain the point. A generator of
    (b, A, contains)."""
    xy0 = np.asarray(xy0, np.float64).reshape(-1, 2)
    xy1 = np.c_[xy0, np.ones(len(xy0))] @ G.T
    xy1 = xy1[:, :2] / xy1[:, 2:]
    JG = homography_jacobian(G, xy0)
    # image 0's side of A for each view a: J_G @ J_a^-1, (V0, N, 2, 2)
    left = np.stack([JG @ np.linalg.inv(homography_jacobian(v.H, xy0)) for v in views0])
    in0 = np.stack([view_contains(v, xy0) for v in views0])
    for b, v in enumerate(views1):
        A = homography_jacobian(v.H, xy1)[None] @ left
        yield b, A, in0 & view_contains(v, xy1)[None]


def residual_tilts(
    G: np.ndarray, xy0: np.ndarray, views0: list[View], views1: list[View]
) -> tuple[np.ndarray, np.ndarray]:
    """The residual transition tilt of each point and the views that give it.

    ``G`` (3, 3) image 0 -> image 1 (the plane's ground truth), ``xy0`` (N, 2) image-0
    points of the plane that image 1 sees, ``views0`` / ``views1`` the views of each image.
    Returns ((N,) smallest anisotropy of ``A`` over the pairs of views that both contain
    the point, inf where none does; (N, 2) int, the indices of that pair, -1 where none)."""
    n = len(np.asarray(xy0).reshape(-1, 2))
    best, which = np.full(n, np.inf), np.full((n, 2), -1)
    for b, A, contains in view_pair_maps(G, xy0, views0, views1):
        tau = anisotropy(A)  # (V0, N)
        tau = np.where(contains & np.isfinite(tau), tau, np.inf)
        a = np.argmin(tau, axis=0)
        t = tau[a, np.arange(n)]
        better = t < best
        best[better], which[better, 0], which[better, 1] = t[better], a[better], b
    return best, which


def covered_scales(
    G: np.ndarray,
    xy0: np.ndarray,
    views0: list[View],
    views1: list[View],
    tolerance: float = SIFT_TILT_TOLERANCE,
) -> np.ndarray:
    """(N,) at each point of ``residual_tilts``, the scale change between the two views
    (max(s, 1 / s), s = sqrt |det A|) nearest 1 among the pairs of views that contain it
    with a residual tilt at most ``tolerance``; inf where none does. SIFT meets a scale
    change only where both views hold the texture at the matching octaves: views that
    reach the plane's tilt only at a 10-30x scale change reach it in name."""
    n = len(np.asarray(xy0).reshape(-1, 2))
    best = np.full(n, np.inf)
    for _, A, contains in view_pair_maps(G, xy0, views0, views1):
        tau = anisotropy(A)
        with np.errstate(divide="ignore", invalid="ignore"):  # NaN: behind a view
            s = np.sqrt(np.abs(np.linalg.det(A)))
            factor = np.maximum(s, 1.0 / s)
        ok = contains & np.isfinite(tau) & (tau <= tolerance)
        best = np.minimum(best, np.where(ok, factor, np.inf).min(axis=0))
    return best


def coverage(tilts: np.ndarray, tolerance: float = SIFT_TILT_TOLERANCE) -> float:
    """Share of the points whose residual tilt is at most ``tolerance`` (NaN for none)."""
    tilts = np.asarray(tilts, np.float64)
    return float(np.mean(tilts <= tolerance)) if len(tilts) else float("nan")
