"""Small pure geometry functions on numpy arrays, each written once.

Conventions as everywhere in the package (docs/architecture.md): camera frame x right,
y down, z forward; pixel coordinates in COLMAP's convention (centre of the top-left pixel at
(0.5, 0.5), see conventions.py); rotations act on column vectors (``y = R @ x``); angles are
returned in degrees. No function here touches pycolmap, OpenCV or configuration.
"""

from __future__ import annotations

import numpy as np

from .conventions import pixel_centers


def skew(v: np.ndarray) -> np.ndarray:
    """Cross-product matrices: ``skew(v) @ w == np.cross(v, w)``.

    Args:
        v: (..., 3) vectors.
    Returns:
        (..., 3, 3) float64 ``[[0, -z, y], [z, 0, -x], [-y, x, 0]]``.
    """
    v = np.asarray(v, dtype=np.float64)
    if v.shape[-1:] != (3,):
        raise ValueError(f"skew needs (..., 3) vectors, got shape {v.shape}")
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    S = np.zeros(v.shape + (3,))
    S[..., 0, 1], S[..., 0, 2] = -z, y
    S[..., 1, 0], S[..., 1, 2] = z, -x
    S[..., 2, 0], S[..., 2, 1] = -y, x
    return S


def axis_angle_rotation(axis: np.ndarray, angle: float) -> np.ndarray:
    """The rotation by ``angle`` (radians) about the unit vector ``axis`` (Rodrigues).

    Args:
        axis: (3,) unit vector (not normalised here).
        angle: radians, counter-clockwise looking down ``axis``.
    Returns:
        (3, 3) float64 R.
    """
    K = skew(np.asarray(axis, dtype=np.float64).reshape(3))
    return np.eye(3) + np.sin(angle) * K + (1.0 - np.cos(angle)) * (K @ K)


def smallest_rotation(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The rotation of smallest angle taking unit vector a onto unit vector b.

    Rodrigues' formula about ``a x b``. When a and b are (anti)parallel (|a x b| < 1e-12):
    the identity for a = b, and for a = -b the half turn about the unit vector perpendicular
    to b built from the basis axis least aligned with b (the x axis for b = (0, 0, 1)).

    Args:
        a: (3,) unit vector (not normalised here).
        b: (3,) unit vector (not normalised here).
    Returns:
        (3, 3) float64 R with ``R @ a == b`` (up to rounding).
    """
    a = np.asarray(a, dtype=np.float64).reshape(3)
    b = np.asarray(b, dtype=np.float64).reshape(3)
    axis = np.cross(a, b)
    s = np.linalg.norm(axis)
    c = float(a @ b)
    if s < 1e-12:
        if c > 0:
            return np.eye(3)
        e = np.zeros(3)
        e[int(np.argmin(np.abs(b)))] = 1.0
        u = e - (e @ b) * b
        u = u / np.linalg.norm(u)
        return 2.0 * np.outer(u, u) - np.eye(3)
    return axis_angle_rotation(axis / s, np.arctan2(s, c))


def angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angles between unit vectors, in degrees in [0, 180].

    Args:
        a: (..., 3) unit vectors (not normalised here).
        b: (..., 3) unit vectors, broadcastable against a.
    Returns:
        (...) degrees; the cosine is clipped to [-1, 1] first.
    """
    cos = np.clip((a * b).sum(-1), -1.0, 1.0)
    return np.degrees(np.arccos(cos))


def line_angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angles between the lines of unit vectors (sign-free: v and -v are the same line, as
    vanishing directions and plane normals up to sign), in degrees in [0, 90].

    Args:
        a: (..., 3) unit vectors (not normalised here).
        b: (..., 3) unit vectors, broadcastable against a.
    Returns:
        (...) degrees; |cos| is clipped to [0, 1] first.
    """
    cos = np.clip(np.abs((a * b).sum(-1)), 0.0, 1.0)
    return np.degrees(np.arccos(cos))


def angle_between_deg(a: np.ndarray, b: np.ndarray) -> float:
    """Angle between two vectors of any length, in degrees in [0, 180].

    Args:
        a: (3,) vector.
        b: (3,) vector.
    Returns:
        float degrees; NaN when either vector is shorter than 1e-12 (no direction).
    """
    na, nb = np.linalg.norm(a), np.linalg.norm(b)
    if na < 1e-12 or nb < 1e-12:
        return float("nan")
    return float(np.degrees(np.arccos(np.clip(np.dot(a, b) / (na * nb), -1.0, 1.0))))


def rotation_angle_deg(R: np.ndarray) -> float:
    """Angle of a rotation matrix, in degrees in [0, 180].

    Args:
        R: (3, 3) rotation matrix.
    Returns:
        float ``arccos((trace(R) - 1) / 2)`` in degrees, the cosine clipped to [-1, 1].
    """
    c = (np.trace(R) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def order_frame(D: np.ndarray, support: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Canonical order of an orthogonal frame: rows by support (descending, stable), the
    first two facing the camera (z <= 0, flipped otherwise), the third their cross product
    (right-handed).

    Args:
        D: (3, 3) frame, one direction per row.
        support: (3,) support of each row.
    Returns:
        (D', order): D' (3, 3) a new array, order (3,) int with ``D'[i] = +-D[order[i]]``
        (``D'[2]`` recomputed as ``D'[0] x D'[1]``).
    """
    order = np.argsort(-np.asarray(support), kind="stable")
    D = np.asarray(D)[order].copy()
    for i in (0, 1):
        if D[i, 2] > 0:
            D[i] *= -1.0
    D[2] = np.cross(D[0], D[1])
    return D, order


def singular_values_2x2(m: np.ndarray) -> np.ndarray:
    """(N, 2) singular values (larger, smaller) of (N, 2, 2) matrices, in closed form (the
    eigenvalues of m^T m); e.g. the scales of affine keypoint frames along their two axes."""
    a, b, c, d = m[:, 0, 0], m[:, 0, 1], m[:, 1, 0], m[:, 1, 1]
    p, r, q = a * a + c * c, b * b + d * d, a * b + c * d
    mean = 0.5 * (p + r)
    half = np.sqrt(0.25 * (p - r) ** 2 + q * q)
    return np.sqrt(np.maximum(np.stack([mean + half, mean - half], 1), 0.0))


def scaled_size(width: int, height: int, max_size: float, min_side: int = 8) -> tuple[int, int]:
    """Size of an image scaled down (never up) so that its longer side is at most max_size.

    Args:
        width, height: image size in pixels.
        max_size: bound on the longer side.
        min_side: lower bound on each returned side.
    Returns:
        (w, h): ``max(min_side, round(side * s))`` with ``s = min(1, max_size / longer side)``.
    """
    s = min(1.0, max_size / max(width, height))
    return max(min_side, round(width * s)), max(min_side, round(height * s))


def rays_from_K(K: np.ndarray, width: int, height: int) -> np.ndarray:
    """Rays with z = 1 through the pixel centres of a pinhole camera given by K.

    Args:
        K: (3, 3) intrinsics, COLMAP pixel convention (skew ignored).
        width, height: image size in pixels.
    Returns:
        (height, width, 3) float64 ``((x - cx) / fx, (y - cy) / fy, 1)``. For cameras with
        distortion use camera.grid_rays (through pycolmap).
    """
    xy = pixel_centers(width, height)
    return np.stack(
        [
            (xy[..., 0] - K[0, 2]) / K[0, 0],
            (xy[..., 1] - K[1, 2]) / K[1, 1],
            np.ones((height, width)),
        ],
        -1,
    )
