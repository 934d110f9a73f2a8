"""Keypoint orientations for LightGlue's SIFT weights (docs/hloc.md, pitfall 6).

Our (and hloc DoG's) ``oris`` are COLMAP orientations (atan2(a21, a11), image axes) in
DEGREES; LightGlue's SIFT extractor hands its matcher the same angle in RADIANS (its pycolmap
backend passes COLMAP's keypoint angle through, its OpenCV backend
``deg2rad(KeyPoint.angle)``), and hloc's ``lightglue`` matcher passes every dataset of the
feature file through. Tested against pycolmap's SIFT angles; LightGlue itself was not run
(its package cannot be fetched offline).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np


def oris_for_lightglue(oris_deg: np.ndarray) -> np.ndarray:
    """COLMAP orientations in degrees -> float32 radians, LightGlue's unit."""
    return np.deg2rad(np.asarray(oris_deg, np.float64)).astype(np.float32)


def convert_oris_for_lightglue(src: Path | str, dst: Path | str) -> int:
    """Copy an hloc feature file with every ``oris`` dataset in radians (attribute
    ``oris_unit = 'rad'``), for LightGlue's SIFT weights; returns the number of images."""
    import h5py

    src, dst = Path(src), Path(dst)
    if src.resolve() == dst.resolve():
        raise ValueError("convert into a new file: hloc's own readers expect degrees")
    n = 0
    with h5py.File(src, "r") as fi, h5py.File(dst, "w") as fo:

        def visit(name, obj):
            nonlocal n
            if isinstance(obj, h5py.Group) and "keypoints" in obj:
                g = fo.require_group(name)
                for k, d in obj.items():
                    if k == "oris":
                        if d.attrs.get("oris_unit") == "rad":
                            raise ValueError(f"{src}: {name}/oris already in radians")
                        g.create_dataset(k, data=oris_for_lightglue(d[()]))
                        g[k].attrs["oris_unit"] = "rad"
                    else:
                        fi.copy(d, g, name=k)
                n += 1

        fi.visititems(visit)
    return n
