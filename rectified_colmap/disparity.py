"""Disparity -> depth: the unknown shift of affine-invariant disparity.

Depth sources return raw maps (rectified_colmap.depth); this stage turns a ``disparity`` map
into z-depth (up to scale), with the shift fitted to orthogonal planes. It comes after
planes because choosing the shift fits them.

Relative-depth networks (MiDaS, Depth Anything) predict disparity p = s / z + t with unknown
scale s and shift t. Scale leaves normals exact; a wrong shift bends planes into curved
surfaces whose normals tilt toward or away from the optical axis, the more so the farther
the plane. The shift t is chosen so that the two strongest dominant plane directions (e.g.
ground and facade) are orthogonal, as man-made scenes are: a 1-D search over t (log-spaced
coarse grid, then a finer one around the best), each step computing normals at low
resolution and the orthogonal dominant frame, and measuring the angle between the *free*
mean normals of the two best-supported clusters. It falls back to t = 0 (z = 1 / p) when no
candidate shows two planes. (Assuming t = 0 throughout, the other remedy, bent the planes
of far facades: docs/depth-models.md.)

Shapes: disparity (h, w) float32, NaN / non-finite invalid; the camera is a pycolmap.Camera
of the full image (the map may have any resolution with the image's aspect ratio).
"""

from __future__ import annotations

import logging

import numpy as np
import pycolmap

from . import camera as cam_utils
from .config import ExtractConf, PlaneConf
from .depth import DepthMap, disparity_to_depth, resample_depth
from .geometry import scaled_size
from .normals import backproject, estimate_normals
from .planes import fit_dominant_directions

logger = logging.getLogger(__name__)


def resolve_disparity(depth: DepthMap, camera: pycolmap.Camera, conf: ExtractConf) -> DepthMap:
    """A ``disparity`` map -> a ``depth`` map (z up to scale, NaN invalid) with the shift of
    ``estimate_shift``; maps of other kinds are returned as they are."""
    if depth.kind != "disparity":
        return depth
    return DepthMap(depth.to_depth(estimate_shift(depth.values, camera, conf)), "depth")


def orthogonality_cost(
    normals: np.ndarray,
    plane_conf: PlaneConf,
    rng: np.random.Generator,
    min_support: float = 0.05,
    min_count: int = 50,
    num_samples: int = 4000,
    num_restarts: int = 3,
) -> float:
    """|cos| of the angle between the mean normals of the two best-supported dominant
    clusters (0 = orthogonal); inf when fewer than two clusters have enough support. A
    cheaper fit than the planes stage's (at most ``num_samples`` normals, ``num_restarts``
    starts): it runs once per candidate shift.

    normals: (..., 3) with NaN rows for pixels without a normal."""
    n = normals.reshape(-1, 3)
    n = n[np.isfinite(n).all(1)]
    if len(n) < 2 * min_count:
        return np.inf
    if len(n) > num_samples:
        n = n[rng.choice(len(n), num_samples, replace=False)]
    dirs, _ = fit_dominant_directions(n, plane_conf, rng, num_samples, num_restarts)
    if dirs is None:
        return np.inf
    dots = n @ np.asarray(dirs, np.float64).T  # (N, 3)
    best = np.abs(dots).argmax(1)
    inlier = np.abs(dots).max(1) >= np.cos(np.deg2rad(plane_conf.inlier_angle_deg))
    counts = np.array([(inlier & (best == k)).sum() for k in range(3)])
    a, b = np.argsort(-counts)[:2]
    if counts[b] < max(min_count, min_support * len(n)):
        return np.inf
    means = []
    for k in (a, b):
        sel = inlier & (best == k)
        m = (n[sel] * np.sign(dots[sel, k])[:, None]).sum(0)
        means.append(m / np.linalg.norm(m))
    return float(abs(means[0] @ means[1]))


def candidate_shifts(
    disparity: np.ndarray, num: int = 15, lo: float = -2.0, hi: float = 1.5
) -> np.ndarray:
    """Shifts t = p_low - spread * 10^k for k in [lo, hi] (p_low: 1st percentile of the
    valid disparity, spread: median - p_low), so that p - t > 0 almost everywhere."""
    p = disparity[np.isfinite(disparity)]
    if p.size == 0:
        return np.zeros(0)
    p_low, med = np.percentile(p, [1, 50])
    spread = med - p_low if med > p_low else max(abs(med), 1e-6)
    return p_low - spread * 10.0 ** np.linspace(lo, hi, num)


def estimate_shift(
    disparity: np.ndarray,
    camera: pycolmap.Camera,
    conf: ExtractConf | None = None,
    rng: np.random.Generator | None = None,
    max_size: int = 160,
    levels: int = 3,
) -> float:
    """Shift t of p = s / z + t making the two strongest dominant planes orthogonal
    (see module docstring). Returns 0.0 when no shift shows two planes."""
    conf = conf or ExtractConf()
    rng = rng or np.random.default_rng(0)
    disparity = np.where(np.isfinite(disparity), disparity, np.nan).astype(np.float32)
    h0, w0 = disparity.shape
    w, h = scaled_size(w0, h0, min(max_size, conf.normals.work_max_size))
    p = resample_depth(disparity, w, h)
    rays = cam_utils.grid_rays(camera, w, h)

    def cost(t: float) -> float:
        z = disparity_to_depth(p, t)
        normals = estimate_normals(backproject(z, rays), conf.normals)
        return orthogonality_cost(normals, conf.planes, rng)

    coarse = candidate_shifts(p)
    if coarse.size == 0:
        return 0.0
    ks = np.linspace(-2.0, 1.5, len(coarse))
    costs = np.array([cost(t) for t in coarse])
    cost0 = cost(0.0) if np.nanpercentile(p, 1) > 0 else np.inf
    if not np.isfinite(costs).any() and not np.isfinite(cost0):
        logger.debug("orthogonal shift: no two planes at any shift, using t = 0")
        return 0.0
    ts, cs = [*coarse, 0.0], [*costs, cost0]
    k, step = ks[int(np.argmin(costs))], ks[1] - ks[0]
    for _ in range(levels):  # finer grids around the best k so far
        fine = candidate_shifts(p, 7, k - step, k + step)
        ts += list(fine)
        cs += [cost(t) for t in fine]
        step /= 3.0
        k = np.linspace(k - 3 * step, k + 3 * step, 7)[int(np.argmin(cs[-7:]))]
    ts, cs = np.array(ts), np.array(cs)
    best = int(np.argmin(cs))
    logger.debug("orthogonal shift: t = %.4g (|cos| %.4f; t = 0: %.4f)", ts[best], cs[best], cost0)
    return float(ts[best])
