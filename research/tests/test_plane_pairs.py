"""Planar pairs from a reconstruction (rectified_colmap_research.evaluation.plane_pairs) and
the builder script."""

import json

import numpy as np
import pycolmap
import pytest

from scripts_util import load_script

from rectified_colmap.eval.homography import (
    apply_homography,
    points_in_region,
    read_homography_pairs,
    visible_grid,
)
from rectified_colmap_research.evaluation.plane_pairs import (
    ViewData,
    band_of,
    best_plane_per_pair,
    dilated_hull,
    link_components,
    pair_candidates,
    plane_homography,
    plane_in_camera,
    plane_region,
    region_fraction,
    select_pairs,
    homography_jacobian,
    tilt_deg,
    transition_tilt,
    viewpoint_change_deg,
    views_of_model,
)


def look_at(center, target, up=(0.0, -1.0, 0.0)):
    """cam_from_world (R, t) of a camera at ``center`` looking at ``target`` (y down)."""
    z = np.asarray(target, float) - center
    z /= np.linalg.norm(z)
    x = np.cross(np.asarray(up, float), z)
    x /= np.linalg.norm(x)
    R = np.stack([x, np.cross(z, x), z])
    return R, -R @ center


def project(K, R, t, X):
    Xc = X @ R.T + t
    uv = Xc @ K.T
    return uv[:, :2] / uv[:, 2:]


def ring_center(azimuth_deg, radius=10.0):
    """A camera centre in front of the wall z = 0 (cameras at z < 0), ``azimuth`` from its
    normal, at 1.5 m height above the wall's centre row (y down: y = -1.5)."""
    a = np.radians(azimuth_deg)
    return np.array([radius * np.sin(a), -1.5, -radius * np.cos(a)])


K0 = np.array([[800.0, 0, 320.5], [0, 810, 240.5], [0, 0, 1]])
K1 = np.array([[650.0, 0, 300.0], [0, 640, 250.0], [0, 0, 1]])


def test_plane_homography_maps_projections_exactly():
    rng = np.random.default_rng(0)
    n = np.array([0.3, -0.2, 1.0])
    n /= np.linalg.norm(n)
    plane = np.append(n, -2.0)  # n . X = 2
    # points of the plane around its foot point 2 n
    basis = np.linalg.svd(n[None])[2][1:]  # two directions in the plane
    X = 2 * n + rng.uniform(-3, 3, (50, 2)) @ basis
    assert np.allclose(X @ plane[:3] + plane[3], 0)
    R0, t0 = look_at(2 * n - 8 * n + np.array([1.0, 0.5, 0]), 2 * n)
    R1, t1 = look_at(2 * n - 6 * np.array([0.9, 0.1, 0.4]), 2 * n + 0.3)
    x0, x1 = project(K0, R0, t0, X), project(K1, R1, t1, X)
    H = plane_homography(K0, K1, R0, t0, R1, t1, plane)
    np.testing.assert_allclose(apply_homography(H, x0), x1, atol=1e-8)
    # the plane in camera 0: its points satisfy n0 . X0 + d0 = 0
    n0, d0 = plane_in_camera(plane, R0, t0)
    np.testing.assert_allclose((X @ R0.T + t0) @ n0 + d0, 0, atol=1e-9)
    # another plane's homography does not map them
    other = plane_homography(K0, K1, R0, t0, R1, t1, np.append(n, -2.5))
    assert np.abs(apply_homography(other, x0) - x1).max() > 5


def test_viewpoint_change_and_tilt_exact():
    c0, c1 = np.array([-1.0, 0, 0]), np.array([1.0, 0, 0])
    assert viewpoint_change_deg(c0, c1, np.array([0, 0, 1.0])) == pytest.approx(90.0)
    assert viewpoint_change_deg(c0, c1, np.array([0, 0, np.sqrt(3)])) == pytest.approx(60.0)
    # a wall z = 0 with normal z: seen from its normal direction 0, at 45 deg 45, from the
    # other side too (unsigned)
    p = np.array([1.0, 2.0, 0.0])
    normal = np.array([0, 0, 1.0])
    assert tilt_deg(p + [0, 0, 5.0], p, normal) == pytest.approx(0.0, abs=1e-6)
    assert tilt_deg(p + [5.0, 0, 5.0], p, normal) == pytest.approx(45.0)
    assert tilt_deg(p + [0, -5.0, -5.0 * np.sqrt(3)], p, -normal) == pytest.approx(30.0)
    # the ring: cameras 35 degrees either side of the normal see the centre 70 degrees apart
    assert viewpoint_change_deg(
        ring_center(-35, 7.0), ring_center(35, 7.0), np.array([0, -1.5, 0])
    ) == pytest.approx(70.0)


def test_transition_tilt_exact():
    xy = np.array([[10.0, 20.0], [300.0, -50.0]])
    np.testing.assert_allclose(transition_tilt(np.diag([2.0, 0.5, 1.0]), xy), [4.0, 4.0])
    c, s_ = np.cos(0.3), np.sin(0.3)
    similarity = np.array([[2 * c, -2 * s_, 5], [2 * s_, 2 * c, -3], [0, 0, 1]])
    np.testing.assert_allclose(transition_tilt(similarity, xy), [1.0, 1.0])
    # the Jacobian of a projective map against central differences
    H = np.array([[0.9, 0.1, 12], [-0.05, 1.2, 4], [3e-4, -2e-4, 1]])
    e = 1e-4
    num = np.stack(
        [
            (apply_homography(H, xy + [e, 0]) - apply_homography(H, xy - [e, 0])) / (2 * e),
            (apply_homography(H, xy + [0, e]) - apply_homography(H, xy - [0, e])) / (2 * e),
        ],
        -1,
    )
    np.testing.assert_allclose(homography_jacobian(H, xy), num, rtol=1e-6)
    # a wall seen frontally by camera 0 and at 60 degrees by camera 1, both looking at the
    # same wall point through their principal points: 1 / cos(60) = 2 there
    target = np.array([0.0, 0.0, 0.0])
    R0, t0 = look_at(np.array([0.0, 0, -5]), target)
    R1, t1 = look_at(8 * np.array([np.sin(np.pi / 3), 0, -np.cos(np.pi / 3)]), target)
    Ka = np.array([[700.0, 0, 320], [0, 700, 240], [0, 0, 1]])  # square pixels
    Kb = np.array([[500.0, 0, 300], [0, 500, 200], [0, 0, 1]])
    H = plane_homography(Ka, Kb, R0, t0, R1, t1, np.array([0, 0, 1.0, 0]))
    np.testing.assert_allclose(apply_homography(H, Ka[:2, 2][None]), Kb[:2, 2][None])
    assert transition_tilt(H, Ka[:2, 2][None])[0] == pytest.approx(2.0)
    # non-square pixels add their aspect ratios: (fy1 / fy0) / (fx1 cos 60 / fx0)
    H = plane_homography(K0, K1, R0, t0, R1, t1, np.array([0, 0, 1.0, 0]))
    assert transition_tilt(H, K0[:2, 2][None])[0] == pytest.approx((640 / 810) / (650 * 0.5 / 800))


def test_link_components_and_hull():
    xy = np.array([[0.0, 0], [5, 0], [9, 0], [30, 0], [33, 4], [100, 100]])
    np.testing.assert_array_equal(link_components(xy, 6.0), [0, 0, 0, 1, 1, 2])
    np.testing.assert_array_equal(link_components(xy, 3.0), [0, 1, 2, 3, 4, 5])
    assert link_components(np.zeros((0, 2)), 1.0).shape == (0,)
    square = np.array([[10.0, 10], [20, 10], [20, 20], [10, 20], [15, 15]])
    hull = dilated_hull(square, 2.0)
    inside = points_in_region(
        np.array([[15.0, 15], [8.5, 15], [15, 21.5], [7, 15], [23, 23]]), [hull]
    )
    np.testing.assert_array_equal(inside, [True, True, True, False, False])


def test_plane_region_rejects_hulls_with_other_surfaces():
    rng = np.random.default_rng(0)
    a = rng.uniform([0, 0], [50, 50], (40, 2))  # plane points, cluster A
    b = rng.uniform([200, 0], [250, 50], (40, 2))  # plane points, cluster B
    clutter = rng.uniform([200, 0], [250, 50], (40, 2))  # off-plane points among B
    x_all = np.vstack([a, b, clutter])
    err = np.r_[np.zeros(80), np.full(40, 20.0)]
    region = plane_region(np.vstack([a, b]), x_all, err, link=60, radius=5)
    assert len(region) == 1 and points_in_region(a, region).all()
    assert not points_in_region(b, region).any()
    # without clutter both clusters are kept; tiny clusters never are
    assert len(plane_region(np.vstack([a, b]), np.vstack([a, b]), np.zeros(80), 60, 5)) == 2
    assert plane_region(a[:5], a[:5], np.zeros(5), 60, 5) == []
    assert region_fraction(region, (500, 100), step=1.0) == pytest.approx(
        region_fraction([dilated_hull(a, 5)], (500, 100), step=1.0)
    )


def wall_views(azimuths, n_points=200, seed=0):
    """ViewData of cameras around a textured wall z = 0 (x, y in [-3, 3] x [-3, 0], y down)
    that see all its points, and the ground y = 0 in front of it, whose points only the
    first two see; exact observations."""
    rng = np.random.default_rng(seed)
    wall = np.c_[rng.uniform(-3, 3, n_points), rng.uniform(-3, 0, n_points), np.zeros(n_points)]
    ground = np.c_[rng.uniform(-2, 2, 60), np.zeros(60), rng.uniform(-3, -0.5, 60)]
    xyz = np.vstack([wall, ground])
    labels = np.r_[np.zeros(n_points, int), np.ones(60, int)]
    planes = np.array([[0, 0, 1.0, 0], [0, 1.0, 0, 0]])
    views = []
    for k, az in enumerate(azimuths):
        R, t = look_at(ring_center(az), np.array([0, -1.5, 0]))
        seen = np.arange(len(xyz)) if k < 2 else np.arange(n_points)
        views.append(
            ViewData(f"im{k}.jpg", K0, R, t, (640, 480), seen, project(K0, R, t, xyz[seen]))
        )
    return views, xyz, planes, labels


def test_pair_candidates_on_an_exact_wall():
    views, xyz, planes, labels = wall_views([-30.0, 30.0, 50.0])
    (c,) = pair_candidates(views[0], views[2], xyz, planes, labels)
    assert (c.name0, c.name1, c.plane) == ("im0.jpg", "im2.jpg", 0)
    assert c.angle_deg == pytest.approx(80.0, abs=1.0)  # 30 + 50 at the wall's centroid
    assert c.median_err < 1e-6 and c.num_points == 200
    # tilted 30 and 50 degrees about the same axis: cos 30 / cos 50 = 1.35 near the centre
    assert c.tilt_ratio == pytest.approx(np.cos(np.radians(30)) / np.cos(np.radians(50)), rel=0.05)
    assert len(c.region0) == 1
    np.testing.assert_allclose(
        apply_homography(c.H, views[0].xy[:200]), views[2].xy[:200], atol=1e-6
    )
    # the ground is seen by im0 and im1 only; too few points with min_points 61
    both = pair_candidates(views[0], views[1], xyz, planes, labels, angle_range=(30, 85))
    assert sorted(c.plane for c in both) == [0, 1]
    assert [c.plane for c in best_plane_per_pair(both)] == [0]  # 200 points beat 60
    assert pair_candidates(views[0], views[1], xyz, planes, labels, min_points=61)[0].plane == 0
    # a narrow angle range or a wrong plane drop the pair
    assert pair_candidates(views[0], views[2], xyz, planes, labels, angle_range=(30, 70)) == []
    bad = planes.copy()
    bad[0, 3] = 0.3  # the wall 0.3 m off: its homography does not transfer the observations
    assert pair_candidates(views[0], views[2], xyz, bad, labels) == []


def test_select_pairs_caps_and_bands():
    views, xyz, planes, labels = wall_views([-40.0, -20.0, 0.0, 20.0, 40.0])
    cands = [
        c
        for i in range(5)
        for j in range(i + 1, 5)
        for c in pair_candidates(views[i], views[j], xyz, planes, labels, angle_range=(10, 85))
    ]
    best = best_plane_per_pair(cands)
    assert len(best) == 10 and all(c.plane == 0 for c in best)
    kept = select_pairs(best, max_per_image=2, max_per_plane=100)
    counts = {}
    for c in kept:
        for n in (c.name0, c.name1):
            counts[n] = counts.get(n, 0) + 1
    assert max(counts.values()) <= 2
    # greedy, all with 200 points, ties by names: (0, 3), (0, 4), (1, 3)... are over the cap
    assert [(c.name0[2], c.name1[2]) for c in kept] == [
        ("0", "1"),
        ("0", "2"),
        ("1", "2"),
        ("3", "4"),
    ]
    assert len(select_pairs(best, max_per_image=10, max_per_plane=3)) == 3
    assert [band_of(a) for a in (29.9, 30.0, 49.9, 50.0, 84.9, 85.0)] == [
        None,
        "strong",
        "strong",
        "extreme",
        "extreme",
        None,
    ]


def wall_reconstruction(azimuths, root, seed=0):
    """A real-pool-like set at ``root``: images/ (noise) and colmap_sparse/ of the wall scene
    (SIMPLE_RADIAL without distortion, one camera)."""
    import cv2

    views, xyz, planes, labels = wall_views(azimuths, seed=seed)
    rec = pycolmap.Reconstruction()
    cam = pycolmap.Camera(
        model="SIMPLE_RADIAL", width=640, height=480, params=[800.0, 320.5, 240.5, 0.0]
    )
    cam.camera_id = 1
    rec.add_camera_with_trivial_rig(cam)
    K = cam.calibration_matrix()
    obs = {}
    for k, v in enumerate(views):
        xy = project(K, v.R, v.t, xyz[v.points])
        obs[k] = {int(p): i for i, p in enumerate(v.points)}
        im = pycolmap.Image(
            name=v.name, camera_id=1, image_id=k + 1, points2D=[pycolmap.Point2D(q) for q in xy]
        )
        rec.add_image_with_trivial_frame(im, pycolmap.Rigid3d(pycolmap.Rotation3d(v.R), v.t))
    for p in range(len(xyz)):
        track = pycolmap.Track()
        for k in obs:
            if p in obs[k]:
                track.add_element(k + 1, obs[k][p])
        rec.add_point3D(xyz[p], track)
    (root / "colmap_sparse").mkdir(parents=True)
    rec.write(str(root / "colmap_sparse"))
    (root / "images").mkdir()
    rng = np.random.default_rng(seed)
    for v in views:
        cv2.imwrite(str(root / "images" / v.name), rng.integers(0, 255, (480, 640, 3), np.uint8))
    return rec


def test_views_of_model_needs_pinhole(tmp_path):
    rec = wall_reconstruction([-30.0, 30.0], tmp_path / "s")
    views, xyz = views_of_model(rec)  # SIMPLE_RADIAL without distortion is pinhole
    assert [v.name for v in views] == ["im0.jpg", "im1.jpg"] and len(xyz) == 260
    np.testing.assert_allclose(views[1].center, ring_center(30.0), atol=1e-9)
    v = views[0]
    np.testing.assert_allclose(project(v.K, v.R, v.t, xyz[v.points]), v.xy, atol=1e-9)
    rec.cameras[1].params = [800.0, 320.5, 240.5, 0.05]
    with pytest.raises(ValueError, match="pinhole"):
        views_of_model(rec)


def test_build_plane_pairs_script(tmp_path, capsys):
    mod = load_script("build_plane_pairs")
    pool = tmp_path / "pool"
    wall_reconstruction([-40.0, -20.0, 15.0, 35.0], pool / "wall")
    out = tmp_path / "out"
    assert mod.main(["--real_pool", str(pool), "--output", str(out), "--sets", "wall"]) == 0
    records = json.loads((out / "pairs.json").read_text())
    # angles at the wall's centroid: 20, 55, 75, 35, 55, 20 -> 2 strong, 3 extreme, caps 4
    bands = sorted((r["band"], round(r["angle_deg"])) for r in records)
    assert [b for b, _ in bands] == ["extreme"] * 3 + ["strong"]
    assert all(r["h_median_err_px"] < 0.01 and r["region0"] for r in records)
    assert all(1 < r["transition_tilt"] < 3 for r in records)
    assert "| wall | 1 | 3 |" in (out / "README.md").read_text()
    pairs = read_homography_pairs(out / "pairs.json", out)
    for p, r in zip(pairs, records):
        assert (out / r["im0"]).is_file() and (out / r["im1"]).is_file()
        assert p.info["set"] == "wall" and len(visible_grid(p, 10)) > 100
    # a missing set: one line naming it, exit 2, nothing written
    assert (
        mod.main(["--real_pool", str(pool), "--output", str(tmp_path / "o2"), "--sets", "x"]) == 2
    )
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and str(pool / "x") in err
    assert not (tmp_path / "o2").exists()
