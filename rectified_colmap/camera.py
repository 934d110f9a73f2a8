"""Cameras: pycolmap.Camera objects, COLMAP pixel convention, any COLMAP camera model.

Rays are in the camera frame (x right, y down, z forward), scaled to z = 1. Distortion is
handled by pycolmap's own ``cam_from_img``/``img_from_cam``, so every model COLMAP knows is
supported consistently for depth back-projection, warps and keypoints.
"""

from __future__ import annotations

import logging
import threading
from collections import OrderedDict
from pathlib import Path

import numpy as np
import pycolmap

from .config import DEFAULT_CAMERA_MODEL
from .conventions import pixel_centers

logger = logging.getLogger(__name__)

# Models whose params are exactly the focal length(s) and principal point.
PINHOLE_MODELS = {"SIMPLE_PINHOLE", "PINHOLE"}


def model_name(camera: pycolmap.Camera) -> str:
    return camera.model.name if hasattr(camera.model, "name") else str(camera.model)


def is_pinhole(camera: pycolmap.Camera) -> bool:
    """True when the camera has no distortion terms (or all of them are zero)."""
    if model_name(camera) in PINHOLE_MODELS:
        return True
    extra = np.asarray(camera.params)[len(_focal_and_pp(camera)) :]
    return bool(np.all(extra == 0))


def _focal_and_pp(camera: pycolmap.Camera) -> list[int]:
    idx = list(camera.focal_length_idxs()) + list(camera.principal_point_idxs())
    return idx


def calibration_matrix(camera: pycolmap.Camera) -> np.ndarray:
    """K (3, 3) of the camera's pinhole part, COLMAP pixel convention."""
    return np.asarray(camera.calibration_matrix(), dtype=np.float64)


def image_to_rays(camera: pycolmap.Camera, xy: np.ndarray) -> np.ndarray:
    """(N, 2) COLMAP pixel coordinates -> (N, 3) undistorted rays with z = 1."""
    xy = np.ascontiguousarray(np.asarray(xy, dtype=np.float64).reshape(-1, 2))
    n = np.asarray(camera.cam_from_img(xy), dtype=np.float64)
    return np.concatenate([n, np.ones((len(n), 1))], axis=1)


def rays_to_image(camera: pycolmap.Camera, rays: np.ndarray) -> np.ndarray:
    """(N, 3) rays in the camera frame (z > 0) -> (N, 2) COLMAP pixel coordinates.

    Rays with z <= 0 map to NaN.
    """
    rays = np.asarray(rays, dtype=np.float64).reshape(-1, 3)
    out = np.full((len(rays), 2), np.nan)
    front = rays[:, 2] > 1e-12
    if front.any():
        n = np.ascontiguousarray(rays[front] / rays[front, 2:3])
        out[front] = np.asarray(camera.img_from_cam(n), dtype=np.float64)
    return out


_GRID_RAYS_CACHE_SIZE = 8  # grids and unit grids
_grid_rays_cache: OrderedDict[tuple, np.ndarray] = OrderedDict()
_grid_rays_lock = threading.Lock()


def grid_rays(camera: pycolmap.Camera, width: int, height: int) -> np.ndarray:
    """Rays (height, width, 3) float64 through the centres of a width x height grid that
    covers the whole image (the grid may be a downsampling of the image). Read-only: the
    last few grids are kept (one image's stages ask for its work grid a dozen times; through
    a distorted camera each costs a pycolmap call per cell)."""
    return _cached_grid(camera, width, height, unit=False)


def unit_grid_rays(camera: pycolmap.Camera, width: int, height: int) -> np.ndarray:
    """``grid_rays`` scaled to unit length; read-only and kept as ``grid_rays`` is."""
    return _cached_grid(camera, width, height, unit=True)


def _cached_grid(camera: pycolmap.Camera, width: int, height: int, unit: bool) -> np.ndarray:
    """The grid's rays (``unit``: scaled to unit length) from the cache of the last
    _GRID_RAYS_CACHE_SIZE grids, computed (and made read-only) when absent."""
    key = (model_name(camera), camera.width, camera.height, tuple(camera.params), width, height)
    key += (unit,)
    with _grid_rays_lock:
        rays = _grid_rays_cache.pop(key, None)
    if rays is None:
        if unit:
            rays = grid_rays(camera, width, height)
            rays = rays / np.linalg.norm(rays, axis=-1, keepdims=True)
        else:
            xy = pixel_centers(width, height, camera.width, camera.height)
            rays = image_to_rays(camera, xy.reshape(-1, 2)).reshape(height, width, 3)
        rays.setflags(write=False)
    with _grid_rays_lock:
        while len(_grid_rays_cache) >= _GRID_RAYS_CACHE_SIZE:
            _grid_rays_cache.popitem(last=False)
        _grid_rays_cache[key] = rays  # most recently used last
    return rays


def num_params(model: str) -> int:
    """Number of parameters of a COLMAP camera model; ValueError for an unknown name."""
    try:
        return len(pycolmap.Camera.create_from_model_name(1, model, 1.0, 1, 1).params)
    except Exception:
        known = ", ".join(
            m.name for m in pycolmap.CameraModelId.__members__.values() if m.name != "INVALID"
        )
        raise ValueError(f"unknown camera model {model!r}; COLMAP's are {known}") from None


def make_camera(
    model: str, params: list[float] | np.ndarray, width: int, height: int
) -> pycolmap.Camera:
    """A camera from COLMAP's model name and parameter list (COLMAP order and convention)."""
    expected = num_params(model)
    if len(params) != expected:
        raise ValueError(
            f"camera model {model} takes {expected} params, got {len(params)}: {list(params)}"
        )
    cam = pycolmap.Camera(
        model=model, width=int(width), height=int(height), params=[float(p) for p in params]
    )
    if not cam.verify_params() or not np.isfinite(cam.params).all():
        raise ValueError(f"camera model {model}: invalid params {list(params)}")
    return cam


def parse_camera_params(text: str) -> list[float]:
    """'fx,fy,cx,cy' -> [fx, fy, cx, cy] (COLMAP's --ImageReader.camera_params syntax)."""
    try:
        return [float(v) for v in text.replace(" ", "").split(",") if v]
    except ValueError as e:
        raise ValueError(f"cannot parse camera params {text!r}: {e}") from None


def infer_camera(
    image_path: Path, model: str = DEFAULT_CAMERA_MODEL, focal_factor: float = 1.2
) -> tuple[pycolmap.Camera, bool]:
    """A camera of COLMAP's ``model`` for the image, as ``colmap feature_extractor`` makes it
    (pycolmap.infer_camera_from_image): the focal length from EXIF, else ``focal_factor`` x
    the larger side (COLMAP's --ImageReader.default_focal_length_factor); the principal
    point at the image centre; the model's default extra params.

    Returns (camera, focal_is_prior): ``focal_is_prior`` is False when the focal length is
    the guess."""
    options = pycolmap.ImageReaderOptions(
        camera_model=model, default_focal_length_factor=float(focal_factor)
    )
    try:
        cam = pycolmap.infer_camera_from_image(str(image_path), options)
    except Exception:
        cam = None
    if cam is None:
        raise ValueError(f"{image_path}: cannot read image to infer its camera")
    return cam, bool(cam.has_prior_focal_length)
