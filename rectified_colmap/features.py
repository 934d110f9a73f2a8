"""The features of one image: the ``Features`` container.

Keypoints are in COLMAP pixel convention in the ORIGINAL image. Each keypoint carries its
affine frame A (2x2; COLMAP's a11 a12 a21 a22): for a plain SIFT keypoint of scale s and
orientation t, A = s [[cos t, -sin t], [sin t, cos t]]; for a keypoint found in a rectified
patch, A = J A_rect, where J is the Jacobian of the rectified->image map at the keypoint.
Descriptors are uint8 (N, 128), RootSIFT in COLMAP's byte scale (L2 norm ~512). SIFT itself
is in rectified_colmap.sift.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class Features:
    keypoints: np.ndarray
    """(N, 2) float64, COLMAP convention, original image pixels."""
    shapes: np.ndarray
    """(N, 2, 2) float64 affine frames [[a11, a12], [a21, a22]]."""
    descriptors: np.ndarray
    """(N, 128) uint8, COLMAP scale."""
    patch: np.ndarray
    """(N,) int32: -1 = plain SIFT, k >= 0 = rectified view k (``Rectification.patch_index``)."""

    def __len__(self) -> int:
        return len(self.keypoints)

    @property
    def scales(self) -> np.ndarray:
        """(N,) COLMAP scale: mean norm of the frame's columns."""
        return 0.5 * (
            np.linalg.norm(self.shapes[:, :, 0], axis=1)
            + np.linalg.norm(self.shapes[:, :, 1], axis=1)
        )

    @property
    def orientations(self) -> np.ndarray:
        """(N,) orientation in radians, atan2(a21, a11) as COLMAP."""
        return np.arctan2(self.shapes[:, 1, 0], self.shapes[:, 0, 0])

    def colmap_keypoints(self) -> np.ndarray:
        """(N, 6) float32 [x, y, a11, a12, a21, a22] for a COLMAP database."""
        return np.concatenate([self.keypoints, self.shapes.reshape(-1, 4)], 1).astype(np.float32)

    @classmethod
    def empty(cls) -> "Features":
        return cls(
            np.zeros((0, 2)),
            np.zeros((0, 2, 2)),
            np.zeros((0, 128), np.uint8),
            np.zeros(0, np.int32),
        )

    @classmethod
    def concatenate(cls, parts: list["Features"]) -> "Features":
        if not parts:
            return cls.empty()
        return cls(
            *(
                np.concatenate([getattr(p, f) for p in parts])
                for f in ("keypoints", "shapes", "descriptors", "patch")
            )
        )

    def subset(self, index: np.ndarray) -> "Features":
        return Features(
            self.keypoints[index], self.shapes[index], self.descriptors[index], self.patch[index]
        )


def similarity_frames(scales: np.ndarray, orientations: np.ndarray) -> np.ndarray:
    """(N,) scales and orientations (rad) -> (N, 2, 2) frames s [[cos, -sin], [sin, cos]]."""
    c, s = np.cos(orientations), np.sin(orientations)
    return scales[:, None, None] * np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)


def keypoints_in_mask(xy: np.ndarray, mask: np.ndarray, image_size: tuple[int, int]) -> np.ndarray:
    """(N,) bool: COLMAP-convention points of an image of size (W, H) that fall on True
    cells of ``mask`` (h, w), a grid covering that image (nearest cell)."""
    W, H = image_size
    h, w = mask.shape
    col = np.floor(xy[:, 0] * (w / W)).astype(int)
    row = np.floor(xy[:, 1] * (h / H)).astype(int)
    inside = (col >= 0) & (col < w) & (row >= 0) & (row < h)
    out = np.zeros(len(xy), dtype=bool)
    out[inside] = mask[row[inside], col[inside]]
    return out
