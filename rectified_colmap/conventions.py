"""Pixel conventions, converted here and nowhere else.

Inside rectified_colmap every pixel coordinate is in COLMAP's convention: x to the right,
y down, and the *centre* of the top-left pixel at (0.5, 0.5). Camera intrinsics
(pycolmap.Camera), pycolmap SIFT keypoints and COLMAP databases use it as they are.

OpenCV (cv2.warpPerspective, cv2.remap, cv2.KeyPoint) and hloc HDF5 files put the centre of
the top-left pixel at (0, 0). Every crossing into or out of that convention goes through a
function of this module.
"""

from __future__ import annotations

import numpy as np

OFFSET = 0.5
"""COLMAP coordinate of the centre of pixel (0, 0)."""

_T = np.array([[1.0, 0.0, OFFSET], [0.0, 1.0, OFFSET], [0.0, 0.0, 1.0]])
_T_INV = np.array([[1.0, 0.0, -OFFSET], [0.0, 1.0, -OFFSET], [0.0, 0.0, 1.0]])


def pixel_centers(
    width: int, height: int, image_width: int | None = None, image_height: int | None = None
) -> np.ndarray:
    """COLMAP coordinates of the centres of a ``width x height`` grid of cells.

    When the grid is a resampling of an image of size ``image_width x image_height``, the
    coordinates are in that image's pixels (cell (0, 0) of a 2x downsampled grid has its
    centre at (1.0, 1.0)). Returns (height, width, 2) float64 [x, y].
    """
    sx = (image_width or width) / width
    sy = (image_height or height) / height
    xs = (np.arange(width) + OFFSET) * sx
    ys = (np.arange(height) + OFFSET) * sy
    return np.stack(np.meshgrid(xs, ys), axis=-1)


def to_opencv_points(xy: np.ndarray) -> np.ndarray:
    """COLMAP pixel coordinates -> OpenCV/hloc pixel coordinates."""
    return np.asarray(xy) - OFFSET


def from_opencv_points(xy: np.ndarray) -> np.ndarray:
    """OpenCV/hloc pixel coordinates -> COLMAP pixel coordinates."""
    return np.asarray(xy) + OFFSET


def to_opencv_homography(H: np.ndarray) -> np.ndarray:
    """A homography between COLMAP pixel frames -> the same map between OpenCV frames,
    ready for cv2.warpPerspective."""
    return _T_INV @ H @ _T


def to_hloc_keypoints(xy: np.ndarray) -> np.ndarray:
    """Keypoints for an hloc feature file: float32 (N, 2), top-left pixel centre at (0, 0)."""
    return to_opencv_points(xy).astype(np.float32)


def from_hloc_keypoints(xy: np.ndarray) -> np.ndarray:
    """Keypoints read from an hloc feature file -> COLMAP convention (float64)."""
    return from_opencv_points(np.asarray(xy, dtype=np.float64))
