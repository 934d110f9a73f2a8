"""Depth -> camera-frame points -> per-pixel surface normals.

Shapes and conventions (all stages): images are indexed [row, col]; a grid of size (h, w)
covers the whole image; camera frame x right, y down, z forward; points (h, w, 3) float32;
normals (h, w, 3) float32, unit length, oriented TOWARD the camera (n . X < 0), NaN where a
pixel has no normal (invalid depth, depth discontinuity, non-planar window).

The normal of a pixel is the normal of the least-squares plane through the points of its
``window x window`` neighbourhood: the eigenvector of the smallest eigenvalue of the
window's scatter matrix. The nine moment sums (x, y, z, xx, xy, xz, yy, yz, zz) and the count
of valid points are box-filtered once over the whole grid, and the 3x3 symmetric eigen
problem is solved in closed form (trigonometric eigenvalues, eigenvector from cross
products of the rows of C - lambda I), all vectorised.
"""

from __future__ import annotations

import logging

import cv2
import numpy as np
import pycolmap

from . import camera as cam_utils
from .config import NormalConf
from .depth import DepthMap, resample_depth
from .geometry import scaled_size

logger = logging.getLogger(__name__)

_CHUNK = 8192


def backproject(depth: np.ndarray, rays: np.ndarray) -> np.ndarray:
    """z-depth (h, w) (NaN/0/neg/inf invalid) and rays (h, w, 3) with z = 1 -> points (h, w, 3)
    float32, NaN where depth is invalid."""
    depth = np.asarray(depth)
    rays = np.asarray(rays)
    if depth.ndim != 2 or rays.shape != depth.shape + (3,):
        raise ValueError(
            f"backproject: depth {depth.shape} and rays {rays.shape} do not "
            "match (expected (h, w) and (h, w, 3))"
        )
    z = depth.astype(np.float64)
    with np.errstate(invalid="ignore"):
        valid = np.isfinite(z) & (z > 0)
    z = np.where(valid, z, np.nan)
    return (rays * z[..., None]).astype(np.float32)


def _box(a: np.ndarray, k: int) -> np.ndarray:
    """Unnormalised k x k box sum, zero outside the grid.

    A separable direct convolution, not cv2.boxFilter: its running sums leak the rounding
    error of huge values (far points near the horizon) into every later window of a column.
    """
    ones = np.ones(k)
    return cv2.sepFilter2D(a, cv2.CV_64F, ones, ones, borderType=cv2.BORDER_CONSTANT)


def smallest_eigenvectors(c: tuple[np.ndarray, ...] | np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Closed-form eigen-solve of symmetric 3x3 matrices.

    c: upper triangles [c00, c01, c02, c11, c12, c22], as a (..., 6) array or a tuple of six
    arrays of one shape S. Returns (eigenvalues S + (3,) ascending, unit eigenvectors
    S + (3,) of the smallest eigenvalue); NaN where the input is NaN.
    """
    if isinstance(c, np.ndarray):
        c = tuple(np.moveaxis(c, -1, 0))
    a00, a01, a02, a11, a12, a22 = c
    q = (a00 + a11 + a22) / 3.0
    b00, b11, b22 = a00 - q, a11 - q, a22 - q
    s01, s02, s12 = a01 * a01, a02 * a02, a12 * a12
    p = np.sqrt((b00 * b00 + b11 * b11 + b22 * b22 + 2.0 * (s01 + s02 + s12)) / 6.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        det = (
            b00 * (b11 * b22 - s12) - a01 * (a01 * b22 - a12 * a02) + a02 * (a01 * a12 - b11 * a02)
        )  # det(C - qI)
        r = np.clip(det / (2.0 * p**3), -1.0, 1.0)
    r = np.where(p > 0, r, 1.0)
    phi = np.arccos(r) / 3.0
    l_max = q + 2.0 * p * np.cos(phi)
    l_min = q + 2.0 * p * np.cos(phi + 2.0 * np.pi / 3.0)
    l_mid = 3.0 * q - l_max - l_min
    # Rows of C - l_min I: r0 = (d0, a01, a02), r1 = (a01, d1, a12), r2 = (a02, a12, d2).
    # Their pairwise cross products are parallel to the eigenvector; take the longest.
    d0, d1, d2 = a00 - l_min, a11 - l_min, a22 - l_min
    v01 = (a01 * a12 - a02 * d1, a02 * a01 - d0 * a12, d0 * d1 - s01)
    v02 = (a01 * d2 - a02 * a12, a02 * a02 - d0 * d2, d0 * a12 - a01 * a02)
    v12 = (d1 * d2 - s12, a12 * a02 - a01 * d2, a01 * a12 - d1 * a02)
    n01 = v01[0] ** 2 + v01[1] ** 2 + v01[2] ** 2
    n02 = v02[0] ** 2 + v02[1] ** 2 + v02[2] ** 2
    n12 = v12[0] ** 2 + v12[1] ** 2 + v12[2] ** 2
    use02 = n02 > n01
    v = [np.where(use02, b, a) for a, b in zip(v01, v02)]
    nv = np.where(use02, n02, n01)
    use12 = n12 > nv
    v = [np.where(use12, b, a) for a, b in zip(v, v12)]
    nv = np.where(use12, n12, nv)
    with np.errstate(invalid="ignore", divide="ignore"):
        inv = 1.0 / np.sqrt(nv)
    return (np.stack([l_min, l_mid, l_max], -1), np.stack([v[0] * inv, v[1] * inv, v[2] * inv], -1))


def estimate_normals(points: np.ndarray, conf: NormalConf = NormalConf()) -> np.ndarray:
    """Plane fit over conf.window x conf.window neighbourhoods (box-filtered moments and a
    closed-form 3x3 eigen-solve, vectorised). Returns normals (h, w, 3) float32 as above."""
    points = np.asarray(points)
    if points.ndim != 3 or points.shape[2] != 3:
        raise ValueError(f"estimate_normals: points must be (h, w, 3), got {points.shape}")
    k = int(conf.window)
    if k < 3 or k % 2 == 0:
        raise ValueError(f"NormalConf.window must be odd and >= 3, got {k}")
    h, w = points.shape[:2]
    valid = np.isfinite(points).all(-1)
    count = _box(valid.astype(np.float64), k)
    ok = _windows_to_fit(points, valid, count, conf)
    out = np.full((h, w, 3), np.nan, np.float32)
    if not ok.any():
        return out
    cov = _window_covariances(points, valid, count, ok, k)
    # Chunks that stay in cache: ~1.5x faster than one pass over all pixels.
    parts = [
        smallest_eigenvectors(tuple(c[i : i + _CHUNK] for c in cov))
        for i in range(0, len(cov[0]), _CHUNK)
    ]
    lam = np.concatenate([p[0] for p in parts])
    n = np.concatenate([p[1] for p in parts])
    with np.errstate(invalid="ignore"):
        planar = (lam[:, 0] <= conf.max_planarity * lam[:, 1]) & (lam[:, 1] > 0)
    # Orient toward the camera: n . X < 0 with X the pixel's own point.
    X = points[ok]
    flip = (n[:, 0] * X[:, 0] + n[:, 1] * X[:, 1] + n[:, 2] * X[:, 2]) > 0
    n[flip] *= -1.0
    n[~planar] = np.nan
    out[ok] = n
    return out


def _windows_to_fit(
    points: np.ndarray, valid: np.ndarray, count: np.ndarray, conf: NormalConf
) -> np.ndarray:
    """(h, w) bool: pixels whose window has enough valid points (conf.min_valid_frac of the
    window's cells inside the grid, at least 3) and no depth discontinuity (relative depth
    range of the valid points within conf.max_depth_jump)."""
    h, w = valid.shape
    k = int(conf.window)
    inside = _box(np.ones((h, w)), k)  # window pixels inside the grid (borders)
    need = np.ceil(conf.min_valid_frac * inside - 1e-9)
    ok = valid & (count >= np.maximum(need, 3))
    kernel = np.ones((k, k), np.uint8)
    zv = points[..., 2].astype(np.float32)
    zmax = cv2.dilate(
        np.where(valid, zv, np.float32(0)), kernel, borderType=cv2.BORDER_CONSTANT, borderValue=0
    )
    zmin = cv2.erode(
        np.where(valid, zv, np.float32(np.inf)),
        kernel,
        borderType=cv2.BORDER_CONSTANT,
        borderValue=float(np.inf),
    )
    with np.errstate(invalid="ignore"):
        ok &= (zmax - zmin) <= conf.max_depth_jump * zmin
    return ok


def _window_covariances(
    points: np.ndarray, valid: np.ndarray, count: np.ndarray, ok: np.ndarray, k: int
) -> tuple[np.ndarray, ...]:
    """The six entries (xx, xy, xz, yy, yz, zz) of each ``ok`` pixel's window covariance,
    divided by its trace (a scale-free eigen-solve), each (M,) float64.

    Moments about the camera centre (not a global mean, which can lie far from every
    window): the relative error of a window's covariance is then ~eps * (f / window)^2,
    independent of depth. Box sums over the grid, then only the pixels that passed."""
    P = np.where(valid[..., None], points, 0).astype(np.float64)
    x, y, z = P[..., 0], P[..., 1], P[..., 2]
    inv = 1.0 / count[ok]
    mx, my, mz = (_box(a, k)[ok] * inv for a in (x, y, z))
    cov = (
        _box(x * x, k)[ok] * inv - mx * mx,
        _box(x * y, k)[ok] * inv - mx * my,
        _box(x * z, k)[ok] * inv - mx * mz,
        _box(y * y, k)[ok] * inv - my * my,
        _box(y * z, k)[ok] * inv - my * mz,
        _box(z * z, k)[ok] * inv - mz * mz,
    )
    tr = cov[0] + cov[3] + cov[5]
    with np.errstate(invalid="ignore", divide="ignore"):
        inv_tr = np.where(tr > 0, 1.0 / tr, np.nan)  # scale-free eigen-solve
    return tuple(c * inv_tr for c in cov)


def depth_to_normals(depth: DepthMap, camera: pycolmap.Camera, conf: NormalConf) -> np.ndarray:
    """Depth (kind ``depth`` or ``metric``) of any resolution -> normals (h, w, 3) on the work
    grid. Disparity must be resolved first (rectified_colmap.disparity.resolve_disparity).

    The grid is never finer than the depth map: upsampled depth is piecewise constant or
    interpolated, and neither adds information to a plane fit."""
    if depth.kind == "disparity":
        raise ValueError("depth_to_normals needs depth: resolve disparity first (disparity.py)")
    max_size = min(conf.work_max_size, max(depth.values.shape))
    w, h = scaled_size(camera.width, camera.height, max_size)
    z = resample_depth(depth.to_depth(), w, h)
    points = backproject(z, cam_utils.grid_rays(camera, w, h))
    return estimate_normals(points, conf)
