"""SIFT features: COLMAP's SIFT through pycolmap, budgets, masks, and the Features container.

Keypoints are in COLMAP pixel convention in the ORIGINAL image. Each keypoint carries its
affine frame A (2x2; COLMAP's a11 a12 a21 a22): for a plain SIFT keypoint of scale s and
orientation t, A = s [[cos t, -sin t], [sin t, cos t]]; for a keypoint found in a rectified
patch, A = J A_rect, where J is the Jacobian of the rectified->image map at the keypoint.
Descriptors are uint8 (N, 128), RootSIFT in COLMAP's byte scale (L2 norm ~512).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pycolmap

from .config import SiftConf


@dataclass
class Features:
    keypoints: np.ndarray
    """(N, 2) float64, COLMAP convention, original image pixels."""
    shapes: np.ndarray
    """(N, 2, 2) float64 affine frames [[a11, a12], [a21, a22]]."""
    descriptors: np.ndarray
    """(N, 128) uint8, COLMAP scale."""
    patch: np.ndarray
    """(N,) int32: -1 = plain SIFT on non-planar pixels, k >= 0 = rectified patch k."""

    def __len__(self) -> int:
        return len(self.keypoints)

    @property
    def scales(self) -> np.ndarray:
        """(N,) COLMAP scale: mean norm of the frame's columns."""
        return 0.5 * (np.linalg.norm(self.shapes[:, :, 0], axis=1)
                      + np.linalg.norm(self.shapes[:, :, 1], axis=1))

    @property
    def orientations(self) -> np.ndarray:
        """(N,) orientation in radians, atan2(a21, a11) as COLMAP."""
        return np.arctan2(self.shapes[:, 1, 0], self.shapes[:, 0, 0])

    def colmap_keypoints(self) -> np.ndarray:
        """(N, 6) float32 [x, y, a11, a12, a21, a22] for a COLMAP database."""
        return np.concatenate([self.keypoints, self.shapes.reshape(-1, 4)], 1).astype(np.float32)

    @classmethod
    def empty(cls) -> "Features":
        return cls(np.zeros((0, 2)), np.zeros((0, 2, 2)), np.zeros((0, 128), np.uint8),
                   np.zeros(0, np.int32))

    @classmethod
    def concatenate(cls, parts: list["Features"]) -> "Features":
        if not parts:
            return cls.empty()
        return cls(*(np.concatenate([getattr(p, f) for p in parts])
                     for f in ("keypoints", "shapes", "descriptors", "patch")))

    def subset(self, index: np.ndarray) -> "Features":
        return Features(self.keypoints[index], self.shapes[index], self.descriptors[index],
                        self.patch[index])
