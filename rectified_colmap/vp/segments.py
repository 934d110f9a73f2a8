"""Line segments of one image, and their geometry on the Gaussian sphere.

Input: a grayscale image (H, W) uint8 and its pycolmap camera (any COLMAP model). Output:
``Segments`` (endpoints, lengths, interpretation-plane normals, midpoint rays) and the
consistency of segments with vanishing directions (``sin_errors``, ``within_angle``).

Conventions (as everywhere in the package):
- Segment endpoints ``xy`` (N, 2, 2) are COLMAP pixel coordinates of the full image
  (centre of the top-left pixel at (0.5, 0.5)); OpenCV's LSD output is converted through
  rectified_colmap.conventions.
- Everything geometric lives on the Gaussian sphere of the camera frame (x right, y down,
  z forward), after undistortion by rectified_colmap.camera.image_to_rays. A segment is its
  interpretation plane's unit normal ``l`` (N, 3) and its midpoint's unit ray ``m`` (N, 3).
  Undistortion: the endpoints are undistorted and ``l`` is the cross product of their
  rays, exact for endpoints on the image of a 3D line under any COLMAP model. The image of
  a straight line bends under distortion, so LSD splits strongly curved edges into shorter
  chords; their endpoints stay on the curve, so each chord still gives the exact plane.
  The midpoint ray (for the consistency angle only) is the undistorted chord midpoint.
- Directions and VPs are unit 3-vectors, sign-free (v and -v are the same VP).
- Consistency of segment i with VP v: the angle theta at the midpoint between the segment
  and the great circle through m and v; sin(theta) = |l . v| / |m x v|.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import pycolmap

from .. import camera as cam_utils
from ..config import VpConf
from ..conventions import from_opencv_points
from ..geometry import scaled_size

_MIN_SIN = 0.05  # floor of |m x v| (VP on the segment's midpoint: angle undefined)
NUM_SAMPLE_SEGMENTS = 200
"""Minimal sets of RANSAC (vp.manhattan, vp.hypotheses) are drawn from this many of the
longest segments."""


@dataclass
class Segments:
    xy: np.ndarray
    """(N, 2, 2) endpoints, COLMAP pixels of the full image."""
    lengths: np.ndarray
    """(N,) pixels of the full image."""
    normals: np.ndarray
    """(N, 3) unit normals of the interpretation planes (camera frame)."""
    mids: np.ndarray
    """(N, 3) unit rays through the midpoints."""
    labels: np.ndarray = None
    """(N,) int: index of the frame row the segment supports, -1 for none."""

    def __len__(self) -> int:
        return len(self.lengths)

    @classmethod
    def empty(cls) -> "Segments":
        return cls(
            np.zeros((0, 2, 2)), np.zeros(0), np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0, int)
        )


def detect_segments(image_gray: np.ndarray, conf: VpConf = VpConf()) -> np.ndarray:
    """LSD (OpenCV) on the image downscaled to conf.max_image_size; falls back to
    HoughLinesP on Canny in OpenCV builds without LSD.

    Args:
        image_gray: (H, W) uint8.
        conf: ``max_image_size``, ``min_length_frac``, ``max_segments``.
    Returns:
        (N, 2, 2) float64 endpoints in COLMAP pixels of the full image, longest first, at
        most conf.max_segments, each at least conf.min_length_frac x max(H, W) long.
    """
    img = np.asarray(image_gray)
    if img.ndim != 2 or img.dtype != np.uint8:
        raise ValueError(f"detect_segments needs a (H, W) uint8 image, got {img.dtype} {img.shape}")
    H, W = img.shape
    s = min(1.0, conf.max_image_size / max(H, W))
    small = (
        img
        if s == 1.0
        else cv2.resize(img, scaled_size(W, H, conf.max_image_size), interpolation=cv2.INTER_AREA)
    )
    h, w = small.shape
    try:
        lsd = cv2.createLineSegmentDetector(cv2.LSD_REFINE_STD)
        raw = lsd.detect(small)[0]
    except (AttributeError, cv2.error):  # builds without LSD
        edges = cv2.Canny(small, 50, 150)
        raw = cv2.HoughLinesP(
            edges, 1, np.pi / 360, 30, minLineLength=conf.min_length_frac * max(h, w), maxLineGap=2
        )
    if raw is None or len(raw) == 0:
        return np.zeros((0, 2, 2))
    seg = from_opencv_points(np.asarray(raw, np.float64).reshape(-1, 2, 2))
    seg = seg * np.array([W / w, H / h])
    length = np.linalg.norm(seg[:, 1] - seg[:, 0], axis=-1)
    keep = np.flatnonzero(length >= conf.min_length_frac * max(H, W))
    keep = keep[np.argsort(-length[keep], kind="stable")][: conf.max_segments]
    return seg[keep]


def _unit(v: np.ndarray) -> np.ndarray:
    """(..., 3) vectors -> unit vectors along the last axis (zero stays zero)."""
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-300)


def segments_on_sphere(camera: pycolmap.Camera, xy: np.ndarray) -> Segments:
    """Endpoints -> interpretation-plane normals and midpoint rays, undistorted through the
    camera (module docstring).

    Args:
        camera: the image's camera.
        xy: (N, 2, 2) endpoints, COLMAP pixels of the full image.
    Returns:
        Segments with labels (N,) all -1.
    """
    xy = np.asarray(xy, np.float64).reshape(-1, 2, 2)
    n = len(xy)
    if n == 0:
        return Segments.empty()
    mid = xy.mean(1)
    pts = np.concatenate([xy[:, 0], xy[:, 1], mid])
    rays = _unit(cam_utils.image_to_rays(camera, pts)).reshape(3, n, 3)
    normals = _unit(np.cross(rays[0], rays[1]))
    lengths = np.linalg.norm(xy[:, 1] - xy[:, 0], axis=-1)
    return Segments(xy, lengths, normals, rays[2], np.full(n, -1))


def image_segments(
    image_gray: np.ndarray, camera: pycolmap.Camera, conf: VpConf = VpConf()
) -> Segments:
    """The image's segments on the sphere: segments_on_sphere(camera, detect_segments(...)).

    Args:
        image_gray: (H, W) uint8, the camera's size.
        camera: the image's camera.
        conf: VpConf (detection options).
    Returns:
        Segments, longest first, labels all -1.
    """
    return segments_on_sphere(camera, detect_segments(image_gray, conf))


def sin_errors(normals: np.ndarray, mids: np.ndarray, V: np.ndarray) -> np.ndarray:
    """Consistency of segments with VP directions (module docstring).

    Args:
        normals: (N, 3) interpretation-plane normals ``l``.
        mids: (N, 3) midpoint rays ``m``.
        V: (M, 3) unit VP directions.
    Returns:
        (N, M) sin(theta), with |m x v| floored at 0.05.
    """
    a = np.abs(normals @ V.T)
    b = mids @ V.T
    return a / np.sqrt(np.maximum(1.0 - b * b, _MIN_SIN**2))


def within_angle(
    normals: np.ndarray, mids: np.ndarray, V: np.ndarray, sin_thr: float
) -> np.ndarray:
    """``sin_errors(normals, mids, V) < sin_thr`` for scoring many candidates at once: in
    float32 and without square roots, sin(theta) < t <=> (l.v)^2 + t^2 min((m.v)^2,
    1 - 0.05^2) < t^2 (the same |m x v| floor).

    Args:
        normals: (N, 3) interpretation-plane normals; mids: (N, 3) midpoint rays.
        V: (M, 3) unit VP directions.
        sin_thr: the threshold on sin(theta).
    Returns:
        (N, M) bool.
    """
    t2 = np.float32(sin_thr**2)
    Vt = np.ascontiguousarray(np.asarray(V).T, dtype=np.float32)
    a = np.asarray(normals, np.float32) @ Vt
    b = np.asarray(mids, np.float32) @ Vt
    a *= a
    b *= b
    np.minimum(b, np.float32(1.0 - _MIN_SIN**2), out=b)
    b *= t2
    a += b
    return a < t2
