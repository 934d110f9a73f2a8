"""Disparity shift: exact conversion, and the orthogonal-planes estimate on a rendered
ground + facade scene with a known shift."""

import numpy as np
import pycolmap
import pytest

from rectified_colmap import camera as cam_utils
from rectified_colmap.config import ExtractConf
from rectified_colmap.depth import DepthMap, disparity_to_depth
from rectified_colmap.disparity import estimate_shift, resolve_disparity
from rectified_colmap.normals import backproject, estimate_normals

W, H, F = 192, 144, 150.0


def cam():
    return pycolmap.Camera(model="PINHOLE", width=W, height=H, params=[F, F, W / 2, H / 2])


def plane_scene(yaw_deg=35.0, height=1.5, dist=8.0, far=60.0, single=False):
    """z-depth (H, W) of a ground plane (y = height) and a vertical facade at ``dist``
    metres turned by ``yaw_deg``; NaN beyond ``far`` (sky). Returns depth, the two normals."""
    rays = cam_utils.grid_rays(cam(), W, H)  # z = 1
    a = np.deg2rad(yaw_deg)
    planes = [(np.array([0.0, -1.0, 0.0]), -height)]  # n . X = d, n toward the camera
    if not single:
        planes.append((np.array([np.sin(a), 0.0, -np.cos(a)]), -dist))
    z = np.full((H, W), np.inf)
    for n, d in planes:
        with np.errstate(divide="ignore", invalid="ignore"):
            t = d / (rays @ n)
        z = np.where((t > 0) & (t < z), t, z)
    z[~np.isfinite(z) | (z > far)] = np.nan
    return z.astype(np.float32), [p[0] for p in planes]


def normal_error_deg(z, true_normals):
    n = estimate_normals(
        backproject(z, cam_utils.grid_rays(cam(), W, H)), ExtractConf().normals
    ).reshape(-1, 3)
    n = n[np.isfinite(n).all(1)]
    cos = np.max(np.abs(n @ np.stack(true_normals).T), axis=1)
    return float(np.median(np.rad2deg(np.arccos(np.clip(cos, -1, 1)))))


def test_disparity_to_depth_exact():
    p = np.array([[2.0, 0.5], [0.25, np.nan]], np.float32)
    z = disparity_to_depth(p, shift=0.25)
    np.testing.assert_allclose(z[0], [1 / 1.75, 4.0], rtol=1e-6)
    assert np.isnan(z[1]).all()  # p - t = 0 and NaN are invalid


@pytest.mark.parametrize("rel_shift", [0.0, 0.5, -0.3])
def test_orthogonal_shift_recovers_planes(rel_shift):
    z, normals = plane_scene()
    inv = 1.0 / z
    t0 = rel_shift * np.nanmedian(inv)
    p = np.where(np.isfinite(inv), 3.0 * inv + 3.0 * t0, np.nan).astype(np.float32)
    t = estimate_shift(p, cam(), ExtractConf(), np.random.default_rng(0))
    err_ortho = normal_error_deg(disparity_to_depth(p, t), normals)
    err_zero = normal_error_deg(disparity_to_depth(p, 0.0), normals)
    assert err_ortho < 2.0
    assert abs(t / 3.0 - t0) < 0.1 * np.nanmedian(inv) + 1e-9
    if rel_shift != 0:
        assert err_zero > 2 * err_ortho


def test_single_plane_falls_back_to_zero():
    z, _ = plane_scene(single=True)
    p = np.where(np.isfinite(z), 1.0 / z + 0.1, np.nan).astype(np.float32)
    assert estimate_shift(p, cam()) == 0.0


def test_resolve_disparity_fits_the_shift_and_leaves_depth_alone():
    z, _ = plane_scene()
    inv = 1.0 / z
    p = np.where(np.isfinite(inv), 3.0 * inv + 0.5 * np.nanmedian(inv), np.nan).astype(np.float32)
    depth = DepthMap(z, "metric")
    assert resolve_disparity(depth, cam(), ExtractConf()) is depth
    conf = ExtractConf()
    t = estimate_shift(p, cam(), conf)
    assert t != 0.0
    ortho = resolve_disparity(DepthMap(p, "disparity"), cam(), conf)
    assert ortho.kind == "depth"
    np.testing.assert_array_equal(ortho.values, disparity_to_depth(p, t))
