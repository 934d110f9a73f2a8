"""Depth sources: the seam between "where depth comes from" and the geometry.

A depth source is any callable ``source(image, camera, name) -> DepthMap | None``:

- ``image``: (H, W, 3) uint8 RGB, the full image;
- ``camera``: its pycolmap.Camera;
- ``name``: the image name relative to the image root (``sub/0001.jpg``).

It returns ``None`` when it has no depth for that image (the image then gets plain SIFT).
The returned map may have any resolution: :func:`resample_depth` brings it to the grid where
normals are computed. Depth values are *z-depth* (distance along the optical axis, as in
COLMAP's dense depth maps), not ray length.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, Protocol

import cv2
import numpy as np
import pycolmap

DepthKind = Literal["metric", "depth", "disparity"]
DEPTH_KINDS = ("metric", "depth", "disparity")
MIN_VALID_FRACTION = 0.01
"""A depth map with fewer valid (finite, positive) values than this is unusable."""


@dataclass
class DepthMap:
    """A dense depth map of one image.

    ``values`` (h, w) float32; invalid where 0, negative, NaN or inf. ``kind``:

    - ``metric``: z-depth in metres;
    - ``depth``: z-depth up to an unknown scale;
    - ``disparity``: inverse z-depth up to an unknown scale AND shift (p = s / z + t).
    """

    values: np.ndarray
    kind: DepthKind = "depth"

    def __post_init__(self):
        if self.kind not in DEPTH_KINDS:
            raise ValueError(f"unknown depth kind {self.kind!r}, expected one of {DEPTH_KINDS}")
        self.values = np.asarray(self.values, dtype=np.float32)
        if self.values.ndim != 2:
            raise ValueError(f"depth map must be 2-D, got shape {self.values.shape}")

    def problem(self) -> str | None:
        """Why this map cannot give geometry (all NaN, no positive depth, constant
        disparity), or None when it is usable."""
        v = self.values
        finite = np.isfinite(v)
        if not finite.any():
            return "no finite values: all NaN or inf"
        if self.kind == "disparity":
            if np.ptp(v[finite]) == 0:
                return "constant disparity: no geometry"
            return None
        valid = float((finite & (v > 0)).mean())
        if valid < MIN_VALID_FRACTION:
            return (
                f"{valid:.1%} of the values are positive depths: the rest are zero, negative or NaN"
            )
        return None

    def to_depth(self, shift: float = 0.0) -> np.ndarray:
        """z-depth (up to scale), NaN where invalid. For disparity, z = 1 / (p - shift)
        (choosing the shift is a stage of its own: rectified_colmap.disparity)."""
        if self.kind == "disparity":
            return disparity_to_depth(self.values, shift)
        v = self.values
        return np.where(np.isfinite(v) & (v > 0), v, np.nan).astype(np.float32)


def disparity_to_depth(disparity: np.ndarray, shift: float = 0.0) -> np.ndarray:
    """z = 1 / (p - t) up to scale; NaN where p - t <= 0 or non-finite."""
    with np.errstate(divide="ignore", invalid="ignore"):
        z = 1.0 / (np.asarray(disparity, np.float32) - np.float32(shift))
    return np.where(np.isfinite(z) & (z > 0), z, np.nan).astype(np.float32)


class DepthSource(Protocol):
    def __call__(
        self, image: np.ndarray, camera: pycolmap.Camera, name: str
    ) -> DepthMap | None: ...


def resample_depth(depth: np.ndarray, width: int, height: int) -> np.ndarray:
    """Resample a z-depth map (NaN = invalid) to width x height without mixing invalid pixels
    into valid ones: area-average where downsampling, nearest where upsampling."""
    h, w = depth.shape
    if (w, h) == (width, height):
        return depth.astype(np.float32)
    valid = np.isfinite(depth)
    if width <= w and height <= h:
        filled = np.where(valid, depth, 0).astype(np.float32)
        s = cv2.resize(filled, (width, height), interpolation=cv2.INTER_AREA)
        c = cv2.resize(valid.astype(np.float32), (width, height), interpolation=cv2.INTER_AREA)
        with np.errstate(divide="ignore", invalid="ignore"):
            out = s / c
        out[c < 0.999] = np.nan  # any invalid pixel under the cell: unreliable
        return out.astype(np.float32)
    return cv2.resize(depth.astype(np.float32), (width, height), interpolation=cv2.INTER_NEAREST)
