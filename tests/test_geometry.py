"""geometry.py: properties, and bit-equality with the copies it replaced (issue 14)."""

import numpy as np
import pytest

from rectified_colmap import camera as cam_utils
from rectified_colmap.conventions import pixel_centers
from rectified_colmap.geometry import (
    angle_between_deg,
    angle_deg,
    line_angle_deg,
    order_frame,
    rays_from_K,
    rotation_angle_deg,
    scaled_size,
    skew,
    smallest_rotation,
)


def _unit(v):
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


# -- the former copies, verbatim (references for bit-equality) --------------------------------


def _old_skew(v):  # eval/relpose.py
    x, y, z = v
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def _old_rectifying_rotation(normal):  # rectify.py
    a = -np.asarray(normal, dtype=np.float64).reshape(3)
    a = a / np.linalg.norm(a)
    z = np.array([0.0, 0.0, 1.0])
    axis = np.cross(a, z)
    s = np.linalg.norm(axis)
    c = float(a @ z)
    if s < 1e-12:
        return np.eye(3) if c > 0 else np.diag([1.0, -1.0, -1.0])
    axis /= s
    angle = np.arctan2(s, c)
    Kx = np.array([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]])
    return np.eye(3) + np.sin(angle) * Kx + (1.0 - np.cos(angle)) * (Kx @ Kx)


def _old_angle_between_deg(a, b):  # eval/relpose.py
    na, nb = np.linalg.norm(a), np.linalg.norm(b)
    if na < 1e-12 or nb < 1e-12:
        return float("nan")
    return float(np.degrees(np.arccos(np.clip(np.dot(a, b) / (na * nb), -1.0, 1.0))))


def _old_angle_deg(a, b):  # training/evaluate.py
    cos = np.clip((a * b).sum(-1), -1.0, 1.0)
    return np.degrees(np.arccos(cos))


def _old_work_size(width, height, max_size):  # pipeline.py
    s = min(1.0, max_size / max(width, height))
    return max(8, round(width * s)), max(8, round(height * s))


def _old_shift_size(w0, h0, max_size, work_max_size):  # depth/shift.py
    s = min(1.0, max_size / max(w0, h0), work_max_size / max(w0, h0))
    return max(8, round(w0 * s)), max(8, round(h0 * s))


def _old_rays_from_K(K, width, height):  # training/evaluate.py
    from rectified_colmap.conventions import pixel_centers

    xy = pixel_centers(width, height)
    return np.stack(
        [
            (xy[..., 0] - K[0, 2]) / K[0, 0],
            (xy[..., 1] - K[1, 2]) / K[1, 1],
            np.ones((height, width)),
        ],
        -1,
    ).astype(np.float32)


def _old_canonical(D, counts):  # planes.py
    order = np.argsort(-counts, kind="stable")
    D, counts = D[order].copy(), counts[order]
    for i in (0, 1):
        if D[i, 2] > 0:
            D[i] *= -1.0
    D[2] = np.cross(D[0], D[1])
    return D, counts


def _old_rotation_angle_deg(R):  # eval/pairs.py
    c = (np.trace(R) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


# -- tests ---------------------------------------------------------------------------------------


def test_skew_cross_product_and_shapes():
    rng = np.random.default_rng(0)
    v, w = rng.normal(size=(5, 4, 3)), rng.normal(size=(5, 4, 3))
    S = skew(v)
    assert S.shape == (5, 4, 3, 3) and S.dtype == np.float64
    np.testing.assert_allclose(np.einsum("...ij,...j->...i", S, w), np.cross(v, w), atol=1e-12)
    np.testing.assert_array_equal(S, -np.swapaxes(S, -1, -2))
    for x in rng.normal(size=(50, 3)):
        assert np.array_equal(skew(x), _old_skew(x))
    assert np.array_equal(skew([0.0, -0.0, 2.0]), _old_skew(np.array([0.0, -0.0, 2.0])))
    with pytest.raises(ValueError):
        skew(np.zeros(4))


def test_smallest_rotation_properties():
    rng = np.random.default_rng(1)
    for _ in range(50):
        a, b = _unit(rng.normal(size=3)), _unit(rng.normal(size=3))
        R = smallest_rotation(a, b)
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(R) == pytest.approx(1.0)
        np.testing.assert_allclose(R @ a, b, atol=1e-12)
        axis = np.cross(a, b)
        np.testing.assert_allclose(R @ axis, axis, atol=1e-12)  # the axis stays
        assert rotation_angle_deg(R) == pytest.approx(angle_deg(a, b), abs=1e-6)
    assert np.array_equal(smallest_rotation([1.0, 0, 0], [1.0, 0, 0]), np.eye(3))
    for b in ([0, 0, 1.0], [0, 1.0, 0], _unit(np.array([1.0, 2.0, -3.0]))):
        b = np.asarray(b)
        R = smallest_rotation(-b, b)  # half turn about an axis perpendicular to b
        np.testing.assert_allclose(R @ -b, b, atol=1e-12)
        np.testing.assert_allclose(R @ R, np.eye(3), atol=1e-12)
        assert np.linalg.det(R) == pytest.approx(1.0)


def test_smallest_rotation_equals_former_rectifying_rotation():
    z = np.array([0.0, 0.0, 1.0])
    rng = np.random.default_rng(2)
    normals = [
        *rng.normal(size=(200, 3)),
        [0, 0, -1.0],
        [0, 0, 1.0],
        [1e-13, 0, 1.0],
        [0, 1e-13, -1.0],
        [3.0, 0, 0],
        [0, -2.0, 0],
    ]
    for n in normals:
        a = -np.asarray(n, dtype=np.float64)
        a = a / np.linalg.norm(a)
        assert np.array_equal(smallest_rotation(a, z), _old_rectifying_rotation(n)), n


def test_angles():
    rng = np.random.default_rng(3)
    a, b = _unit(rng.normal(size=(100, 3))), _unit(rng.normal(size=(100, 3)))
    d = angle_deg(a, b)
    assert d.shape == (100,) and np.array_equal(d, _old_angle_deg(a, b))
    assert angle_deg(a[0], a[0]) == 0.0 and angle_deg(a[0], -a[0]) == 180.0
    assert np.array_equal(angle_deg(a, b[0]), _old_angle_deg(a, b[0]))  # broadcasting
    for x, y in zip(rng.normal(size=(100, 3)) * 7, rng.normal(size=(100, 3)), strict=True):
        assert angle_between_deg(x, y) == _old_angle_between_deg(x, y)
    assert angle_between_deg([1.0, 0, 0], [0, 3.0, 0]) == pytest.approx(90.0)
    assert np.isnan(angle_between_deg(np.zeros(3), [1.0, 0, 0]))
    assert np.isnan(angle_between_deg([1.0, 0, 0], [1e-13, 0, 0]))


def test_rotation_angle_deg():
    import cv2

    rng = np.random.default_rng(4)
    for deg in (0.0, 1e-3, 30.0, 90.0, 179.0, 180.0):
        axis = _unit(rng.normal(size=3))
        R = cv2.Rodrigues(axis.reshape(3, 1) * np.deg2rad(deg))[0]
        assert rotation_angle_deg(R) == pytest.approx(deg, abs=1e-5)
        assert rotation_angle_deg(R) == _old_rotation_angle_deg(R)


def test_order_frame_equals_former_canonical():
    rng = np.random.default_rng(5)
    for _ in range(50):
        D = np.linalg.qr(rng.normal(size=(3, 3)))[0].T
        counts = rng.integers(0, 5, size=3)  # ties: stable order
        D1, order = order_frame(D, counts)
        D0, c0 = _old_canonical(D.copy(), counts)
        assert np.array_equal(D1, D0) and np.array_equal(counts[order], c0)
        assert (D1[:2, 2] <= 0).all() and np.linalg.det(D1) == pytest.approx(1.0)
        np.testing.assert_allclose(np.abs(D1), np.abs(D[order]), atol=1e-12)


def test_scaled_size():
    assert scaled_size(1536, 1024, 640) == (640, 427)
    assert scaled_size(100, 50, 640) == (100, 50)  # never upscaled
    assert scaled_size(4000, 10, 100) == (100, 8)  # min_side
    assert scaled_size(4000, 10, 100, min_side=1) == (100, 1)
    for w, h, m, m2 in [
        (1536, 1024, 160, 640),
        (333, 999, 160, 80),
        (7, 5, 160, 640),
        (4032, 3024, 160, 1024),
        (1000, 1, 160, 640),
    ]:
        assert scaled_size(w, h, m) == _old_work_size(w, h, m)
        assert scaled_size(w, h, min(m, m2)) == _old_shift_size(w, h, m, m2)


def test_rays_from_K():
    K = np.array([[200.0, 0, 121.0], [0, 190.0, 79.0], [0, 0, 1]])
    rays = rays_from_K(K, 240, 160)
    assert rays.shape == (160, 240, 3) and rays.dtype == np.float64
    assert np.array_equal(rays.astype(np.float32), _old_rays_from_K(K, 240, 160))
    cam = cam_utils.make_camera("PINHOLE", [200.0, 190.0, 121.0, 79.0], 240, 160)
    np.testing.assert_allclose(rays, cam_utils.grid_rays(cam, 240, 160), atol=1e-12)
    assert np.array_equal(rays[0, 0], [(0.5 - 121.0) / 200.0, (0.5 - 79.0) / 190.0, 1.0])


def test_line_angle_deg_is_sign_free():
    rng = np.random.default_rng(4)
    a, b = _unit(rng.normal(size=(50, 3))), _unit(rng.normal(size=(50, 3)))
    d = line_angle_deg(a, b)
    assert d.shape == (50,) and (d >= 0).all() and (d <= 90).all()
    assert np.array_equal(d, line_angle_deg(a, -b)) and np.array_equal(d, line_angle_deg(-a, b))
    full = angle_deg(a, b)
    assert np.allclose(d, np.minimum(full, 180.0 - full), atol=1e-9)
    assert line_angle_deg(a[0], -a[0]) < 1e-5  # arccos near 1: ~1e-6 deg from rounding
    assert line_angle_deg(np.array([1.0, 0, 0]), np.array([0, 1.0, 0])) == 90.0


def test_axis_angle_rotation_exact():
    from rectified_colmap.geometry import axis_angle_rotation

    R = axis_angle_rotation([0.0, 0.0, 1.0], np.pi / 2)
    np.testing.assert_allclose(R @ [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], atol=1e-15)
    rng = np.random.default_rng(3)
    for _ in range(5):
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        angle = rng.uniform(-np.pi, np.pi)
        R = axis_angle_rotation(axis, angle)
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
        np.testing.assert_allclose(R @ axis, axis, atol=1e-12)
        assert np.linalg.det(R) == pytest.approx(1.0)
        assert rotation_angle_deg(R) == pytest.approx(np.degrees(abs(angle)))


def test_grid_rays_cached_per_camera_and_grid():
    """grid_rays and unit_grid_rays keep recent grids: the same camera and grid give the
    same read-only array; any other parameter, size or grid gives that camera's own rays."""
    cam = cam_utils.make_camera("SIMPLE_RADIAL", [200.0, 120.0, 80.0, 0.05], 240, 160)
    rays = cam_utils.grid_rays(cam, 60, 40)
    assert cam_utils.grid_rays(cam, 60, 40) is rays
    assert not rays.flags.writeable
    with pytest.raises(ValueError):
        rays[0, 0, 0] = 1.0
    xy = pixel_centers(60, 40, 240, 160).reshape(-1, 2)
    assert np.array_equal(rays.reshape(-1, 3), cam_utils.image_to_rays(cam, xy))
    other = cam_utils.make_camera("SIMPLE_RADIAL", [200.0, 120.0, 80.0, -0.05], 240, 160)
    for c, (w, h) in [(other, (60, 40)), (cam, (30, 20))]:
        xy = pixel_centers(w, h, 240, 160).reshape(-1, 2)
        expected = cam_utils.image_to_rays(c, xy).reshape(h, w, 3)
        assert np.array_equal(cam_utils.grid_rays(c, w, h), expected)
    unit = cam_utils.unit_grid_rays(cam, 60, 40)
    assert cam_utils.unit_grid_rays(cam, 60, 40) is unit and not unit.flags.writeable
    assert cam_utils.grid_rays(cam, 60, 40) is not unit
    np.testing.assert_allclose(np.linalg.norm(unit, axis=-1), 1.0, atol=1e-12)
    length = np.linalg.norm(rays, axis=-1, keepdims=True)
    np.testing.assert_allclose(unit * length, rays, atol=1e-12)
