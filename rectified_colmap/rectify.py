"""Plane patches -> virtual fronto-parallel cameras, rectified images, and the map back.

A patch with normal n (facing the camera) is seen by a virtual camera with the same centre,
rotated by the smallest rotation R that takes the viewing direction -n onto +z. A ray X of
the original camera is X_v = R X in the virtual one; the virtual camera is a pinhole with
intrinsics K_v (COLMAP convention) chosen so that the patch fits in (w, h) pixels, nothing
shrinks (median smaller singular value of the image->rectified Jacobian = 1) and the size
is capped. For an undistorted camera with intrinsics K the image->rectified map is the
homography H = K_v R K^-1; for other models warps go through the camera's own distortion.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pycolmap

from .config import RectifyConf
from .planes import Patch


@dataclass
class Rectification:
    R: np.ndarray
    """(3, 3) rotation original camera frame -> virtual camera frame."""
    K: np.ndarray
    """(3, 3) intrinsics of the virtual pinhole camera (COLMAP convention)."""
    size: tuple[int, int]
    """(width, height) of the rectified patch image."""
    mask: np.ndarray
    """(height, width) bool: rectified pixels that belong to the patch, are within the
    viewing-angle limit and whose rays are in front of the original camera."""
    normal: np.ndarray
    """(3,) patch normal in the original camera frame (facing the camera)."""
    patch_index: int


def rectifying_rotation(normal: np.ndarray) -> np.ndarray:
    """Smallest rotation R with R @ (-normal) = (0, 0, 1)."""
    raise NotImplementedError


def image_to_rectified_homography(camera: pycolmap.Camera, rect: Rectification) -> np.ndarray:
    """H = K_v R K^-1 between COLMAP pixel frames (pinhole part of the camera only)."""
    raise NotImplementedError


def plan_rectification(camera: pycolmap.Camera, patch: Patch, patch_index: int,
                       conf: RectifyConf = RectifyConf()) -> Rectification | None:
    """Virtual camera, size and valid mask for one patch; None if nothing usable remains
    (e.g. everything beyond the viewing-angle limit)."""
    raise NotImplementedError


def warp_to_rectified(image: np.ndarray, camera: pycolmap.Camera, rect: Rectification
                      ) -> np.ndarray:
    """Render the rectified patch (height, width[, C]) from the original image (bilinear);
    pixels outside rect.mask are 0."""
    raise NotImplementedError


def rectified_to_image(camera: pycolmap.Camera, rect: Rectification, xy: np.ndarray
                       ) -> tuple[np.ndarray, np.ndarray]:
    """(N, 2) rectified COLMAP pixel coords -> ((N, 2) original image COLMAP pixel coords,
    (N, 2, 2) Jacobians d(image xy)/d(rectified xy))."""
    raise NotImplementedError
