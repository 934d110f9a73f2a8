"""Oracle inputs of the evaluations: a known plane's orientation and exact depth.

``plane_normals_from_homography``: a planar pair's plane normal in each camera, from its
homography and (e.g. guessed) intrinsics (scripts/eval_homography.py's ``oracle``).
``plane_depth``: the pipeline takes depth, not normals, so a known orientation goes in as
the plane's own z-depth, which the normals stage turns back into that normal everywhere but
near the horizon (where the depth changes too fast for a window: as with real depth).
"""

from __future__ import annotations

import cv2
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


def plane_normals_from_homography(
    H: np.ndarray, K0: np.ndarray, K1: np.ndarray, x0: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Oracle orientation of a planar pair: the plane normal in camera 0 and in camera 1
    (unit, facing each camera: n . X < 0) from the ground-truth homography (COLMAP pixel
    frames) and intrinsics K0, K1 (COLMAP convention), e.g. guessed ones.

    K1^-1 H K0 = R + t n^T / d is decomposed (cv2.decomposeHomographyMat, up to 4
    solutions); kept is the one with the largest share of ``x0`` (image-0 pixels on the
    plane, (N, 2)) in front of both cameras (the first of a tie). Returns (n0, n1);
    ValueError when ``x0`` is empty."""
    Hn = np.linalg.inv(K1) @ H @ K0
    Hn /= np.cbrt(np.linalg.det(Hn))  # scale of H is arbitrary (det > 0 kept)
    _, Rs, ts, ns = cv2.decomposeHomographyMat(Hn, np.eye(3))
    m0 = np.c_[x0, np.ones(len(x0))] @ np.linalg.inv(K0).T  # rays of camera 0 (z = 1)
    best, best_score = None, -np.inf
    for R, t, n in zip(Rs, ts, ns):
        n, t = n.ravel(), t.ravel()
        # cv2: n^T X = d > 0 for plane points X of camera 0 (d = 1): in front when n.m > 0.
        front0 = m0 @ n > 0
        X0 = m0 / (m0 @ n)[:, None]  # plane points with d = 1
        X1 = X0 @ R.T + t
        front1 = X1[:, 2] > 0
        score = np.mean(front0 & front1)
        if score > best_score:
            best, best_score = (n, R), score
    if best is None:
        raise ValueError("no image-0 point on the plane to orient the homography's decomposition")
    n, R = best
    n0 = -n / np.linalg.norm(n)  # ours: facing the camera
    n1 = R @ n0
    return n0, n1 / np.linalg.norm(n1)
