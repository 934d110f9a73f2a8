"""Normals -> three orthogonal dominant directions -> per-pixel labels -> plane patches.

Labels (h, w) int8: -1 = non-planar; otherwise ``2 * k + s`` where k in {0, 1, 2} is the
dominant direction and s = 0 when the pixel normal n has n . d_k > 0, s = 1 when n . d_k < 0
(the antipode). Directions (3, 3) float64: rows d_k, orthonormal, right-handed.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .config import PlaneConf


@dataclass
class Patch:
    mask: np.ndarray
    """(h, w) bool at the normals' grid (work resolution)."""
    axis: int
    """Index k of the dominant direction."""
    normal: np.ndarray
    """(3,) unit normal of the patch: +-d_k, the sign of its label, facing the camera."""
    area_frac: float
    """Fraction of the image the patch covers."""


@dataclass
class PlaneResult:
    directions: np.ndarray | None
    """(3, 3) rows d_k, or None when no directions could be fitted."""
    support: np.ndarray
    """(3,) fraction of valid normals assigned to each direction."""
    labels: np.ndarray
    """(h, w) int8, see module docstring."""
    patches: list[Patch]


def fit_dominant_directions(normals: np.ndarray, conf: PlaneConf = PlaneConf(),
                            rng: np.random.Generator | None = None
                            ) -> tuple[np.ndarray | None, np.ndarray]:
    """Orthogonal k-means (with antipodes) on (N, 3) unit normals -> (directions (3, 3) or
    None, support (3,))."""
    raise NotImplementedError


def assign_directions(normals: np.ndarray, directions: np.ndarray,
                      conf: PlaneConf = PlaneConf()) -> np.ndarray:
    """(h, w, 3) normals (NaN = none) -> labels (h, w) int8."""
    raise NotImplementedError


def find_patches(labels: np.ndarray, directions: np.ndarray,
                 conf: PlaneConf = PlaneConf()) -> list[Patch]:
    """Connected components per label (direction AND sign), small ones dropped."""
    raise NotImplementedError


def detect_planes(normals: np.ndarray, conf: PlaneConf = PlaneConf(),
                  rng: np.random.Generator | None = None) -> PlaneResult:
    """fit_dominant_directions + assign_directions + find_patches."""
    raise NotImplementedError
