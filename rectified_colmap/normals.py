"""Depth -> camera-frame points -> per-pixel surface normals.

Shapes and conventions (all stages): images are indexed [row, col]; a grid of size (h, w)
covers the whole image; camera frame x right, y down, z forward; points (h, w, 3) float32;
normals (h, w, 3) float32, unit length, oriented TOWARD the camera (n . X < 0), NaN where a
pixel has no normal (invalid depth, depth discontinuity, non-planar window).
"""

from __future__ import annotations

import numpy as np

from .config import NormalConf


def backproject(depth: np.ndarray, rays: np.ndarray) -> np.ndarray:
    """z-depth (h, w) (NaN/0/neg/inf invalid) and rays (h, w, 3) with z = 1 -> points (h, w, 3)
    float32, NaN where depth is invalid."""
    raise NotImplementedError


def estimate_normals(points: np.ndarray, conf: NormalConf = NormalConf()) -> np.ndarray:
    """Plane fit over conf.window x conf.window neighbourhoods (box-filtered moments and a
    closed-form 3x3 eigen-solve, vectorised). Returns normals (h, w, 3) float32 as above."""
    raise NotImplementedError
