from dataclasses import replace

import numpy as np
import pytest

from rectified_colmap.camera import grid_rays, make_camera
from rectified_colmap.config import PlaneConf
from rectified_colmap.normals import backproject, estimate_normals
from rectified_colmap.planes import (
    assign_directions,
    detect_planes,
    fit_dominant_directions,
    find_patches,
    patches_filling_gaps,
    patches_filling_hulls,
)
from rectified_colmap.planes import Patch


def random_rotation(rng):
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


def axis_errors_deg(D, R):
    """Angle from each true axis (rows of R) to the nearest fitted axis, either sign."""
    return np.degrees(np.arccos(np.clip(np.abs(R @ D.T).max(1), 0, 1)))


@pytest.mark.parametrize("seed", range(4))
def test_orthogonal_kmeans_recovers_rotation(seed):
    rng = np.random.default_rng(seed)
    R = random_rotation(rng)
    num = 6000
    k = rng.choice(3, num, p=[0.5, 0.3, 0.2])
    s = rng.choice([-1.0, 1.0], num)  # antipodes belong to the same axis
    n = R[k] * s[:, None] + rng.normal(scale=0.05, size=(num, 3))
    n = np.concatenate([n, rng.normal(size=(3000, 3))])  # 33% uniform outliers
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    n[:50] = np.nan
    D, support = fit_dominant_directions(n, PlaneConf(), np.random.default_rng(7))
    assert D is not None
    np.testing.assert_allclose(D @ D.T, np.eye(3), atol=1e-9)
    assert np.linalg.det(D) == pytest.approx(1.0)
    assert axis_errors_deg(D, R).max() < 1.0
    # Ordered by support: the 50% axis first.
    assert np.abs(D[0] @ R[0]) > np.cos(np.deg2rad(1))
    assert support[0] > support[1] > support[2] > 0
    # Deterministic given the generator.
    D2, _ = fit_dominant_directions(n, PlaneConf(), np.random.default_rng(7))
    np.testing.assert_array_equal(D, D2)


def test_too_few_normals():
    n = np.full((1000, 3), np.nan)
    n[:10] = [0, 0, -1.0]
    D, support = fit_dominant_directions(n, PlaneConf(min_normals=100))
    assert D is None and (support == 0).all()
    res = detect_planes(n.reshape(10, 100, 3))
    assert res.directions is None and res.patches == [] and (res.labels == -1).all()


def test_assign_directions_signs_and_thresholds():
    D = np.eye(3)
    a = np.deg2rad(10)
    normals = np.array(
        [
            [
                [np.cos(a), np.sin(a), 0],
                [-np.cos(a), np.sin(a), 0],
                [0, 0, -1],
                [np.nan, np.nan, np.nan],
                [np.cos(np.deg2rad(40)), np.sin(np.deg2rad(40)), 0],
            ]
        ]
    )
    labels = assign_directions(normals, D, PlaneConf(max_angle_deg=20))
    assert labels.dtype == np.int8
    assert labels.tolist() == [[0, 1, 5, -1, -1]]
    labels = assign_directions(normals, D, PlaneConf(max_angle_deg=45))
    assert labels[0, 4] == 0


def test_find_patches_split_by_sign_and_size():
    D = np.eye(3)
    labels = np.full((60, 90), -1, np.int8)
    labels[:, :30] = 0  # left wall: +d0
    labels[:, 60:] = 1  # right wall: -d0 (same direction, facing the other way)
    labels[40:, 30:60] = 3  # ground: -d1
    labels[5:7, 40:42] = 4  # tiny blob: dropped
    patches = find_patches(labels, D, PlaneConf(min_area_frac=0.01, opening_radius=1))
    assert len(patches) == 3
    by_label = {(p.axis, tuple(p.normal)): p for p in patches}
    assert set(by_label) == {(0, (1.0, 0.0, 0.0)), (0, (-1.0, 0.0, 0.0)), (1, (-0.0, -1.0, -0.0))}
    left = by_label[(0, (1.0, 0.0, 0.0))]
    assert left.mask[:, :30].all() and not left.mask[:, 30:].any()
    assert left.area_frac == pytest.approx(1 / 3)
    # Two separate blobs of one label are two patches.
    labels[:, 10:14] = -1
    assert len(find_patches(labels, D, PlaneConf(min_area_frac=0.01))) == 4


def canyon_depth(rays):
    """Street canyon: walls at x = -3 and x = +3, ground at y = 1.5, end wall at z = 40."""
    rx, ry = rays[..., 0], rays[..., 1]
    cands = [np.full(rx.shape, 40.0)]
    with np.errstate(divide="ignore", invalid="ignore"):
        cands.append(np.where(rx < 0, -3.0 / rx, np.inf))
        cands.append(np.where(rx > 0, 3.0 / rx, np.inf))
        cands.append(np.where(ry > 0, 1.5 / ry, np.inf))
    return np.min(cands, axis=0)


def test_detect_planes_street_canyon():
    W, H = 160, 120
    cam = make_camera("SIMPLE_PINHOLE", [90.0, 80.0, 60.0], W, H)
    # Look slightly to the right and down so no axis is aligned with the camera.
    c, s = np.cos(0.3), np.sin(0.3)
    Ry = np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    c, s = np.cos(0.15), np.sin(0.15)
    Rx = np.array([[1, 0, 0], [0, c, -s], [0, s, c]])
    R = Ry @ Rx  # camera -> world
    rays_cam = grid_rays(cam, W, H)
    rays_w = rays_cam @ R.T
    t = canyon_depth(rays_w / rays_w[..., 2:3]) / rays_w[..., 2]  # world z-depth -> t
    z = t  # rays_cam have z = 1, so the parameter along them is the camera z-depth
    normals = estimate_normals(backproject(z, rays_cam))
    conf = PlaneConf(min_area_frac=0.01, fill_gaps="none")  # the segmentation itself
    res = detect_planes(normals, conf, np.random.default_rng(0))
    assert res.directions is not None
    world_axes = R  # rows: world axes in the camera frame (R^T e_i)
    assert axis_errors_deg(res.directions, world_axes).max() < 0.1
    assert res.support.sum() > 0.8
    normals_found = np.array([p.normal for p in res.patches])
    expect = {
        "left": R.T @ [1.0, 0, 0],
        "right": R.T @ [-1.0, 0, 0],
        "ground": R.T @ [0, -1.0, 0],
        "end": R.T @ [0, 0, -1.0],
    }
    for name, e in expect.items():
        assert (normals_found @ e > np.cos(np.deg2rad(0.1))).sum() == 1, name
    # Both walls share an axis but are different patches with opposite normals.
    walls = [p for p in res.patches if abs(p.normal @ expect["left"]) > 0.99]
    assert len(walls) == 2 and walls[0].axis == walls[1].axis
    for p in res.patches:
        assert (normals[p.mask] @ p.normal > np.cos(np.deg2rad(20))).all()
    # with the gaps filled: the same patches, each grown by the cells around it
    for mode in ("hull", "nearest"):
        rng = np.random.default_rng(0)
        filled = detect_planes(normals, replace(conf, fill_gaps=mode), rng)
        assert len(filled.patches) == len(res.patches)
        for p, q in zip(res.patches, filled.patches):
            assert (q.mask >= p.mask).all() and np.array_equal(q.normal, p.normal)


def test_cells_in_no_patch_join_the_nearest_patch():
    h, w = 40, 60
    left, right = np.zeros((h, w), bool), np.zeros((h, w), bool)
    left[:, :10] = True
    right[5:35, 40:] = True
    patches = [
        Patch(left, 0, np.array([0.0, 0.0, -1.0]), float(left.mean())),
        Patch(right, 1, np.array([1.0, 0.0, 0.0]), float(right.mean())),
    ]
    out = patches_filling_gaps(patches)
    assert len(out) == 2 and [p.axis for p in out] == [0, 1]
    np.testing.assert_array_equal(out[0].normal, patches[0].normal)
    # a partition of the grid, each patch keeping its own cells ...
    assert ((out[0].mask.astype(int) + out[1].mask) == 1).all()
    assert out[0].mask[left].all() and out[1].mask[right].all()
    assert abs(out[0].area_frac + out[1].area_frac - 1.0) < 1e-12
    # ... and every other cell going to the nearer one (exact Euclidean distance)
    rows, cols = np.mgrid[0:h, 0:w]
    d_left = np.maximum(cols - 9, 0)
    dy = np.maximum(np.maximum(5 - rows, rows - 34), 0)
    d_right = np.hypot(np.maximum(40 - cols, 0), dy)
    clear = np.abs(d_left - d_right) > 1.0
    np.testing.assert_array_equal(out[0].mask[clear], (d_left < d_right)[clear])
    assert patches_filling_gaps([]) == []


def test_cells_in_no_patch_inside_a_patch_hull_join_it():
    """An L-shaped patch and a square one: the cells in no patch inside the L's convex hull
    (the triangle its corner cuts off) join the L, none of the square's cells move, and
    cells outside every hull stay out."""
    h, w = 40, 60
    ell, square = np.zeros((h, w), bool), np.zeros((h, w), bool)
    ell[:, :10] = True
    ell[30:, :30] = True
    square[5:15, 40:50] = True
    patches = [
        Patch(ell, 0, np.array([0.0, 0.0, -1.0]), float(ell.mean())),
        Patch(square, 1, np.array([1.0, 0.0, 0.0]), float(square.mean())),
    ]
    out = patches_filling_hulls(patches)
    assert [p.axis for p in out] == [0, 1]
    np.testing.assert_array_equal(out[1].mask, square)  # convex: nothing to fill
    rows, cols = np.mgrid[0:h, 0:w]
    # the L's hull: x <= 29 below the line from its top right (9, 0) to (29, 30)
    inside = (cols <= 29) & ((cols - 9) * 30 <= (rows - 0) * 20)
    grown = out[0].mask & ~ell
    assert grown.any() and not (grown & ~inside).any()
    margin = (cols - 9) * 30 <= rows * 20 - 60  # a cell's width inside the hull's edge
    assert out[0].mask[margin & (cols <= 29)].all()
    assert abs(out[0].area_frac - out[0].mask.mean()) < 1e-12
    assert patches_filling_hulls([]) == []
    # cells already in another patch are not taken
    other = np.zeros((h, w), bool)
    other[20:25, 12:16] = True
    out = patches_filling_hulls(patches + [Patch(other, 2, np.array([0, 1.0, 0]), 0.0)])
    assert not (out[0].mask & other).any() and (out[2].mask == other).all()


def test_detect_planes_fills_the_gaps_of_noisy_normals_when_asked():
    """A plane whose normals are noisy in places (some windows over depth jumps): the
    cells whose normals drop out of the plane's patch rejoin it with ``fill_gaps``."""
    rng = np.random.default_rng(0)
    h, w = 60, 80
    n = np.array([0.3, -0.2, -0.93])
    n /= np.linalg.norm(n)
    normals = np.broadcast_to(n, (h, w, 3)).copy()
    normals += rng.normal(0, 0.02, normals.shape)
    bad = rng.random((h, w)) < 0.2
    normals[bad] = np.nan  # no normal there
    normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
    plain = detect_planes(normals, PlaneConf(fill_gaps="none"), np.random.default_rng(0))
    filled = detect_planes(normals, PlaneConf(fill_gaps="nearest"), np.random.default_rng(0))
    cover = np.any([p.mask for p in plain.patches], axis=0)
    assert cover.mean() < 0.9
    assert np.any([p.mask for p in filled.patches], axis=0).all()
    np.testing.assert_array_equal(filled.labels, plain.labels)
    # the default fills the holes inside the patch, not the frame outside its hull
    hull = detect_planes(normals, PlaneConf(), np.random.default_rng(0))
    assert len(hull.patches) == len(plain.patches)
    masks = np.array([p.mask for p in hull.patches])
    assert (masks.sum(0) <= 1).all() and (masks.any(0) >= cover).all()
    inner = np.zeros((h, w), bool)
    inner[3:-3, 3:-3] = True
    assert masks.any(0)[inner].all() and cover[inner].mean() < 0.9
