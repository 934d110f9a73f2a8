"""Oracle inputs of the evaluations: the exact depth of a known plane.

The pipeline takes depth, not normals: a plane's orientation known from ground truth (e.g.
decomposed from a pair's homography, scripts/eval_homography.py's ``oracle``) goes in as the
plane's own z-depth, which the normals stage turns back into that normal everywhere but near
the horizon (where the depth changes too fast for a window: as with real depth).
"""

from __future__ import annotations

import numpy as np
import pycolmap

from rectified_colmap import camera as cam_utils
from rectified_colmap.conventions import pixel_centers
from rectified_colmap.depth import DepthMap
from rectified_colmap.eval.homography import points_in_region


def plane_depth(
    camera: pycolmap.Camera,
    normal: np.ndarray,
    shape: tuple[int, int],
    region: list[np.ndarray] | None = None,
) -> DepthMap:
    """z-depth (h, w) float32 of the plane n . X = -1 (``normal`` (3,) facing the camera,
    camera frame) on the grid of ``shape`` (h, w) covering the image (cell centres); NaN
    where a cell's ray does not meet the plane in front of the camera, and outside
    ``region`` (polygons of COLMAP pixels, rectified_colmap.eval.homography's regions: where
    the plane is seen; None: everywhere), as a depth sensor would see only the plane."""
    h, w = shape
    n = np.asarray(normal, np.float64).reshape(3)
    along = cam_utils.grid_rays(camera, w, h) @ n  # rays with z = 1: z = -1 / (r . n)
    with np.errstate(divide="ignore"):
        z = np.where(along < -1e-9, -1.0 / along, np.nan)
    if region is not None:
        xy = pixel_centers(w, h, camera.width, camera.height).reshape(-1, 2)
        z[~points_in_region(xy, region).reshape(h, w)] = np.nan
    return DepthMap(z.astype(np.float32), "depth")
