import numpy as np
import pytest

from rectified_colmap.camera import grid_rays, make_camera
from rectified_colmap.config import NormalConf
from rectified_colmap.depth import DepthMap
from rectified_colmap.normals import (
    backproject,
    depth_to_normals,
    estimate_normals,
    smallest_eigenvectors,
)

W, H = 160, 120


@pytest.fixture
def rays():
    cam = make_camera("PINHOLE", [150.0, 140.0, 80.0, 61.0], W, H)
    return grid_rays(cam, W, H)


def plane_depth(rays, n, d):
    """z-depth of the plane n . X + d = 0 along rays with z = 1 (NaN behind)."""
    with np.errstate(divide="ignore"):
        z = -d / (rays @ n)
    z[~(z > 0)] = np.nan
    return z


def random_facing_normals(rng, num, min_cos=0.25):
    out = []
    while len(out) < num:
        n = rng.normal(size=3)
        n /= np.linalg.norm(n)
        if n[2] > 0:
            n = -n
        if -n[2] >= min_cos:
            out.append(n)
    return out


def angle_err(N, n):
    return np.linalg.norm(np.cross(N.astype(np.float64), n), axis=-1)


def test_backproject_invalid(rays):
    z = np.full((H, W), 4.0)
    z[0, 0], z[1, 1], z[2, 2], z[3, 3] = 0.0, np.nan, np.inf, -2.0
    P = backproject(z, rays)
    assert P.dtype == np.float32 and P.shape == (H, W, 3)
    for i in range(4):
        assert np.isnan(P[i, i]).all()
    np.testing.assert_allclose(P[5, 7], rays[5, 7] * 4.0, rtol=1e-6)
    with pytest.raises(ValueError, match="depth"):
        backproject(z[:10], rays)


def test_plane_normals_exact(rays):
    rng = np.random.default_rng(0)
    for n in random_facing_normals(rng, 12) + [np.array([0.0, 0.0, -1.0])]:
        d = rng.uniform(1.0, 20.0)
        P = backproject(plane_depth(rays, n, d), rays)
        N = estimate_normals(P)
        ok = np.isfinite(N).all(-1)
        assert ok.mean() > 0.2
        assert angle_err(N[ok], n).max() < 1e-4, n
        assert (N[ok] @ n > 0).all()  # oriented like n, which faces the camera
        assert (np.einsum("ij,ij->i", N[ok], P[ok]) < 0).all()
        np.testing.assert_allclose(np.linalg.norm(N[ok], axis=-1), 1.0, atol=1e-5)


def test_normals_face_camera_and_reach_borders(rays):
    n = np.array([0.3, -0.2, -0.9])
    n /= np.linalg.norm(n)
    P = backproject(plane_depth(rays, n, 5.0), rays)
    N = estimate_normals(P)
    assert np.isfinite(N).all()  # border windows are fitted on their in-grid part
    assert (np.einsum("ijk,ijk->ij", N, P) < 0).all()


def test_far_points_do_not_spoil_near_windows(rays):
    # A ground plane up to the horizon: huge depths in the same columns as near windows.
    n = np.array([0.0, -1.0, -0.02])
    n /= np.linalg.norm(n)
    z = plane_depth(rays, n, 1.5)
    N = estimate_normals(backproject(z, rays))
    ok = np.isfinite(N).all(-1)
    assert ok[-20:].all()
    assert angle_err(N[ok], n).max() < 1e-4


def test_invalid_depth_and_discontinuity(rays):
    z = np.full((H, W), 5.0)
    z[:, 80:] = 10.0  # depth step between two fronto-parallel planes
    z[30, 20] = np.nan
    z[60, 40] = 0.0
    N = estimate_normals(backproject(z, rays), NormalConf(window=5))
    assert np.isnan(N[30, 20]).all() and np.isnan(N[60, 40]).all()
    # Windows touching the step have no normal; the rest are exact.
    assert np.isnan(N[:, 78:82]).all()
    ok = np.isfinite(N).all(-1)
    assert ok[:, :78].mean() > 0.95 and ok[:, 82:].mean() > 0.95
    np.testing.assert_allclose(N[ok], np.tile([0, 0, -1.0], (ok.sum(), 1)), atol=1e-5)


def test_too_many_invalid_in_window(rays):
    z = np.full((H, W), 5.0)
    z[50:55:2, 50:55:2] = np.nan  # 9 holes in one 5x5 window
    N = estimate_normals(backproject(z, rays), NormalConf(min_valid_frac=0.9))
    assert np.isnan(N[52, 51]).all()  # valid itself, but 6 holes in its window
    N = estimate_normals(backproject(z, rays), NormalConf(min_valid_frac=0.5))
    assert np.isfinite(N[52, 51]).all()


def test_non_planar_windows_rejected(rays):
    rng = np.random.default_rng(1)
    z = 5.0 + rng.uniform(-0.2, 0.2, (H, W))  # high-frequency noise: no plane
    N = estimate_normals(backproject(z, rays), NormalConf(max_depth_jump=1.0))
    assert np.isnan(N[..., 0]).mean() > 0.9


def test_closed_form_eigen_matches_eigh():
    rng = np.random.default_rng(2)
    A = rng.normal(size=(500, 3, 3))
    C = A @ A.transpose(0, 2, 1)
    C[:100] = (
        C[:100] * np.array([1, 1, 1e-6])[None, :, None] * np.array([1, 1, 1e-6])[None, None, :]
    )  # near-degenerate (plane-like) matrices
    c6 = np.stack([C[:, 0, 0], C[:, 0, 1], C[:, 0, 2], C[:, 1, 1], C[:, 1, 2], C[:, 2, 2]], -1)
    lam, v = smallest_eigenvectors(c6)
    w, V = np.linalg.eigh(C)
    np.testing.assert_allclose(lam, w, rtol=1e-6, atol=1e-9 * np.abs(w).max())
    gap = (w[:, 1] - w[:, 0]) / w[:, 2]
    good = gap > 1e-3
    assert np.abs(np.abs(np.einsum("ij,ij->i", v, V[:, :, 0]))[good] - 1).max() < 1e-8


def test_bad_shapes():
    with pytest.raises(ValueError, match="points"):
        estimate_normals(np.zeros((10, 10)))
    with pytest.raises(ValueError, match="window"):
        estimate_normals(np.zeros((10, 10, 3), np.float32), NormalConf(window=4))


def test_depth_to_normals_on_the_work_grid_never_finer_than_the_depth(rays):
    cam = make_camera("PINHOLE", [150.0, 140.0, 80.0, 61.0], W, H)
    z = plane_depth(rays, np.array([0.3, -0.2, -1.0]) / np.linalg.norm([0.3, -0.2, 1.0]), 4.0)
    conf = NormalConf()
    depth = DepthMap(z, "metric")
    n = depth_to_normals(depth, cam, conf)
    np.testing.assert_array_equal(n, estimate_normals(backproject(depth.to_depth(), rays), conf))
    assert depth_to_normals(DepthMap(z[::2, ::2], "depth"), cam, conf).shape == (H // 2, W // 2, 3)
    with pytest.raises(ValueError, match="resolve disparity first"):
        depth_to_normals(DepthMap(1.0 / z, "disparity"), cam, conf)
