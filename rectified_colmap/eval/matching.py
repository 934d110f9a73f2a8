"""Descriptor matching for evaluation, and feature access by image name.

Features come from hloc feature files (rectified_colmap.io.hloc_h5 layout), or from any
mapping ``name -> {"keypoints": (N, 2) COLMAP px, "descriptors": (D, N) unit-norm}``, so
plain and rectified SIFT go through identical code. Keypoints returned here are in COLMAP
convention (the h5 reader converts them).

Matching is brute-force nearest neighbour on L2 distance with Lowe's ratio test (0.8 as the
paper and hloc's NN-ratio), optionally mutual. Output: (M, 2) int64 index pairs (i0, i1).
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from pathlib import Path

import numpy as np

logger = logging.getLogger(__name__)

_CHUNK = 2048


def parse_methods(specs: list[str]) -> dict[str, Path]:
    """Command-line feature files per method: ``["sift=a.h5", "rect=b.h5"]`` ->
    {"sift": Path("a.h5"), ...} (a bare path is named after its stem).

    ValueError for an empty name or path, a method given twice, or a path that is not a
    file."""
    out: dict[str, Path] = {}
    for spec in specs:
        name, sep, path = spec.partition("=")
        if not sep:
            name, path = Path(spec).stem, spec
        if not name or not path:
            raise ValueError(f"--features {spec!r}: expected method=path")
        if name in out:
            raise ValueError(f"--features: method {name!r} given twice")
        if not Path(path).is_file():
            raise ValueError(f"--features {spec!r}: {path} is not a file")
        out[name] = Path(path)
    return out


class FeatureSource:
    """Features by image name from an hloc h5 file or an in-memory mapping.

    ``source[name]`` -> dict with ``keypoints`` (N, 2) float64 COLMAP px and ``descriptors``
    (N, D) float32 with unit rows (transposed from the file's (D, N)).
    """

    def __init__(self, source: Path | str | Mapping):
        self.source = source
        self._names: set[str] | None = None

    @property
    def path(self) -> Path | None:
        return None if isinstance(self.source, Mapping) else Path(self.source)

    def names(self) -> set[str]:
        if self._names is None:
            if isinstance(self.source, Mapping):
                self._names = set(self.source)
            else:
                from ..io.hloc_h5 import list_names

                if not Path(self.source).exists():
                    raise FileNotFoundError(f"{self.source}: feature file not found")
                self._names = set(list_names(self.source))
        return self._names

    def __contains__(self, name: str) -> bool:
        return name in self.names()

    def __getitem__(self, name: str) -> dict[str, np.ndarray]:
        if isinstance(self.source, Mapping):
            if name not in self.source:
                raise KeyError(f"no features for {name!r}")
            d = dict(self.source[name])
            kp = np.asarray(d["keypoints"], np.float64)
        else:
            from ..io.hloc_h5 import read

            d = read(self.source, name)
            kp = d["keypoints"]  # already COLMAP convention
        desc = np.asarray(d["descriptors"], np.float32)
        if desc.ndim != 2 or desc.shape[1] != len(kp):
            raise ValueError(
                f"{self.source}: {name!r}: descriptors {desc.shape} do not match "
                f"{len(kp)} keypoints (expected (D, N))"
            )
        return {"keypoints": kp, "descriptors": np.ascontiguousarray(desc.T)}


def match_ratio(
    desc0: np.ndarray, desc1: np.ndarray, ratio: float = 0.8, mutual: bool = False
) -> np.ndarray:
    """Nearest-neighbour matching with the ratio test.

    desc0 (N0, D), desc1 (N1, D) float; any norm (L2 distances are used). Returns (M, 2)
    int64 [i0, i1]: i1 is the nearest neighbour of i0, and d(nn1) < ratio * d(nn2); with
    ``mutual`` i0 must also be the nearest neighbour of i1.
    """
    d0 = np.asarray(desc0, np.float32)
    d1 = np.asarray(desc1, np.float32)
    if len(d0) == 0 or len(d1) < 2:
        return np.zeros((0, 2), np.int64)
    sq1 = (d1 * d1).sum(1)
    best = np.empty(len(d0), np.int64)
    keep = np.empty(len(d0), bool)
    col_best = np.full(len(d1), np.inf, np.float32)
    col_arg = np.zeros(len(d1), np.int64)
    for s in range(0, len(d0), _CHUNK):
        a = d0[s : s + _CHUNK]
        dist2 = (a * a).sum(1)[:, None] + sq1[None] - 2.0 * (a @ d1.T)
        np.maximum(dist2, 0, out=dist2)
        two = np.argpartition(dist2, 1, axis=1)[:, :2]
        v = np.take_along_axis(dist2, two, 1)
        order = np.argsort(v, axis=1)
        two = np.take_along_axis(two, order, 1)
        v = np.take_along_axis(v, order, 1)
        best[s : s + len(a)] = two[:, 0]
        keep[s : s + len(a)] = v[:, 0] < (ratio**2) * v[:, 1]
        if mutual:
            cb = dist2.argmin(0)
            cv = dist2[cb, np.arange(len(d1))]
            better = cv < col_best
            col_best[better] = cv[better]
            col_arg[better] = cb[better] + s
    idx0 = np.nonzero(keep)[0]
    idx1 = best[idx0]
    if mutual:
        ok = col_arg[idx1] == idx0
        idx0, idx1 = idx0[ok], idx1[ok]
    return np.stack([idx0, idx1], 1).astype(np.int64)
