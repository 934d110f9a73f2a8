"""The demo wing's renderer (rectified_colmap.demo): exact geometry of the renders, the walk
along a street, textures (procedural and photos), trees and clouds."""

import numpy as np
import pycolmap
import pytest

from rectified_colmap.demo.scene import FACADE
from rectified_colmap_research import synth
from tests.scenes import dominant_fraction

W, H = 160, 120


@pytest.fixture(scope="module")
def street_scene():
    return synth.street(np.random.default_rng(3))


@pytest.fixture(scope="module")
def camera():
    return synth.pinhole_camera(W, H, 0.9 * W)


def _world_points(r):
    """Valid pixels of a render -> world points (P, 3), plane ids (P,), depths (P,)."""
    X = synth.backproject(r.depth.astype(np.float64), r.camera)
    m = np.asarray(r.cam_from_world.matrix())
    valid = r.plane_id >= 0
    Xw = (X[valid] - m[:, 3]) @ m[:, :3]
    return Xw, r.plane_id[valid], r.depth[valid].astype(np.float64)


def test_render_is_deterministic(camera):
    out = []
    for _ in range(2):
        rng = np.random.default_rng(7)
        scene = synth.street(rng)
        pose = synth.random_view(scene, rng, camera)
        out.append(synth.render(scene, camera, pose))
    np.testing.assert_array_equal(out[0].image, out[1].image)
    np.testing.assert_array_equal(out[0].depth, out[1].depth)
    np.testing.assert_array_equal(out[0].plane_id, out[1].plane_id)
    rng = np.random.default_rng(8)
    scene = synth.street(rng)
    other = synth.render(scene, camera, synth.random_view(scene, rng, camera))
    assert np.abs(other.image.astype(int) - out[0].image).mean() > 5


def test_depth_is_exact_on_the_quads(street_scene, camera):
    rng = np.random.default_rng(0)
    n = 0
    for _ in range(3):
        r = synth.render(street_scene, camera, synth.random_view(street_scene, rng, camera))
        assert r.image.shape == (H, W, 3) and r.image.dtype == np.uint8
        assert r.depth.dtype == np.float32 and r.plane_id.dtype == np.int32
        Xw, q, z = _world_points(r)
        rel = Xw - street_scene.origin[q]
        nrm = np.cross(street_scene.eu, street_scene.ev)[q]
        dist = np.abs(np.einsum("ij,ij->i", rel, nrm))
        assert np.all(dist <= 1e-4 * z)
        u = np.einsum("ij,ij->i", rel, street_scene.eu[q])
        v = np.einsum("ij,ij->i", rel, street_scene.ev[q])
        tol = 1e-4 * z
        assert np.all((u >= -tol) & (u <= street_scene.size[q, 0] + tol))
        assert np.all((v >= -tol) & (v <= street_scene.size[q, 1] + tol))
        n += len(q)
    assert n > 0.5 * 3 * W * H


def test_zbuffer_agrees_with_independent_raycast(street_scene, camera):
    """The first hit along sampled pixel rays (brute force over all quads) is the
    rendered surface, and sky pixels hit nothing."""
    rng = np.random.default_rng(1)
    pose = synth.look_at([0.0, 10.0, 1.6], [3.0, 30.0, 6.0])  # along the street, up a bit
    r = synth.render(street_scene, camera, pose)
    assert (r.plane_id < 0).any() and (r.plane_id >= 0).any()
    ii, jj = rng.integers(0, H, 400), rng.integers(0, W, 400)
    K = r.K
    rays = np.stack(
        [(jj + 0.5 - K[0, 2]) / K[0, 0], (ii + 0.5 - K[1, 2]) / K[1, 1], np.ones(400)], 1
    )
    m = np.asarray(pose.matrix())
    dirs = rays @ m[:, :3]  # world directions with camera z = 1
    c = synth.camera_center(pose)
    t, q = synth.raycast(street_scene, np.repeat(c[None], 400, 0), dirs)
    np.testing.assert_array_equal(q, r.plane_id[ii, jj])
    hit = q >= 0
    np.testing.assert_allclose(t[hit], r.depth[ii, jj][hit], rtol=1e-5)


def test_normals_are_the_quad_normals_toward_the_camera(street_scene, camera):
    rng = np.random.default_rng(2)
    r = synth.render(street_scene, camera, synth.random_view(street_scene, rng, camera))
    valid = r.plane_id >= 0
    n = r.normals[valid].astype(np.float64)
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1, atol=1e-5)
    R = np.asarray(r.cam_from_world.matrix())[:, :3]
    nq = np.cross(street_scene.eu, street_scene.ev)[r.plane_id[valid]] @ R.T
    np.testing.assert_allclose(np.abs(np.einsum("ij,ij->i", n, nq)), 1, atol=1e-5)
    X = synth.backproject(r.depth.astype(np.float64), camera)[valid]
    assert np.all(np.einsum("ij,ij->i", n, X) < 0)


def test_sky_is_nan(street_scene, camera):
    pose = synth.look_at([0.0, 10.0, 1.6], [0.0, 30.0, 12.0])  # looking up the street
    r = synth.render(street_scene, camera, pose)
    sky = r.plane_id < 0
    assert 0.05 < sky.mean() < 0.95
    assert np.isnan(r.depth[sky]).all() and np.isnan(r.normals[sky]).all()
    assert np.isfinite(r.depth[~sky]).all() and np.isfinite(r.normals[~sky]).all()
    assert (r.depth[~sky] > 0).all()
    # the sky is the top of the image (brighter/bluer than black)
    assert r.image[sky].mean() > 40


def test_look_at_geometry():
    eye, target = np.array([1.0, -2.0, 1.7]), np.array([6.0, 4.0, 3.0])
    pose = synth.look_at(eye, target)
    np.testing.assert_allclose(synth.camera_center(pose), eye, atol=1e-9)
    Xc = pose * target[None]
    np.testing.assert_allclose(Xc[0, :2], 0, atol=1e-9)
    assert Xc[0, 2] > 0
    up = pose.rotation.matrix() @ np.array([0, 0, 1.0])
    assert up[1] < 0 and abs(up[0]) < 1e-9  # world up is image up, no roll
    rolled = synth.look_at(eye, target, roll_deg=10)
    up_r = rolled.rotation.matrix() @ np.array([0, 0, 1.0])
    assert abs(np.degrees(np.arctan2(-up_r[0], -up_r[1]))) == pytest.approx(10, abs=1e-6)


def test_orbit_overlaps(camera):
    scene = synth.street(np.random.default_rng(9))
    poses = synth.view_orbit(scene, 6)
    rs = [synth.render(scene, camera, p, supersample=1) for p in poses]
    assert all(np.isfinite(r.depth).mean() > 0.8 for r in rs)
    for a, b in zip(rs[:-1], rs[1:]):
        assert synth.covisible_fraction(a, b, 0.02) > 0.5
    centres = np.array([synth.camera_center(p) for p in poses])
    assert np.all(np.linalg.norm(np.diff(centres, axis=0), axis=1) > 0.5)


def test_textures_are_deterministic_with_detail_at_several_scales():
    import cv2

    for kind in ("facade", "bricks", "road", "cobbles", "clutter", "foliage", "bark"):
        a = synth.make_texture(kind, 11, 256, 384, 40.0)
        b = synth.make_texture(kind, 11, 256, 384, 40.0)
        c = synth.make_texture(kind, 12, 256, 384, 40.0)
        assert a.shape == (256, 384, 3) and a.dtype == np.float32
        assert 0 <= a.min() and a.max() <= 1
        np.testing.assert_array_equal(a, b)
        assert np.abs(a - c).mean() > 0.01
        g = a.mean(-1)
        for _ in range(3):  # detail at 1, 1/4 and 1/16 resolution
            assert np.abs(cv2.Laplacian(g, cv2.CV_32F)).mean() > 0.005, kind
            g = cv2.pyrDown(cv2.pyrDown(g))


def test_bad_camera_model(street_scene):
    cam = pycolmap.Camera(model="SIMPLE_RADIAL", width=W, height=H, params=[100, 80, 60, 0.1])
    with pytest.raises(ValueError, match="SIMPLE_RADIAL"):
        synth.render(street_scene, cam, synth.look_at([0, 5, 1.6], [0, 20, 2]))


def test_photo_textures_from_a_folder(tmp_path, camera):
    import cv2

    (tmp_path / "sub").mkdir()
    photo = np.zeros((60, 90, 3), np.uint8)
    photo[..., 2] = 230  # pure red (BGR on disk)
    photo[::7] = 40  # some structure
    cv2.imwrite(str(tmp_path / "sub" / "red.png"), photo)
    (tmp_path / "notes.txt").write_text("not an image")
    scene = synth.street(np.random.default_rng(13), texture_dir=tmp_path, photo_prob=1.0)
    facades = np.flatnonzero(scene.kind == FACADE)
    assert all(scene.textures[scene.tex[q]].photo >= 0 for q in facades)
    p0, _, _ = synth.view_pair(scene, np.random.default_rng(0), 0, 30, "facade", camera=camera)
    r = synth.render(scene, camera, p0)
    on_facade = np.isin(r.plane_id, facades)
    assert on_facade.mean() > 0.2
    rgb = r.image[on_facade].astype(float).mean(0)
    assert rgb[0] > 3 * max(rgb[1], rgb[2])


def test_bad_texture_folder(tmp_path):
    with pytest.raises(FileNotFoundError, match="missing"):
        synth.street(np.random.default_rng(0), texture_dir=tmp_path / "missing")
    (tmp_path / "empty").mkdir()
    with pytest.raises(ValueError, match="empty"):
        synth.street(np.random.default_rng(0), texture_dir=tmp_path / "empty")


def test_sift_matches_between_views_are_geometrically_consistent():
    """Textures are rich and mapped consistently: plain SIFT matches between two views
    20-40 degrees apart agree with the GT (depth + relative pose) to a few pixels."""
    import cv2

    from rectified_colmap.sift import detect_sift

    cam = synth.pinhole_camera(320, 240, 280)
    rng = np.random.default_rng(14)
    good, total = 0, 0
    for _ in range(3):
        scene = synth.street(rng)
        p0, p1, _ = synth.view_pair(scene, rng, 20, 40, "facade", camera=cam, max_incidence_deg=50)
        r0, r1 = synth.render(scene, cam, p0), synth.render(scene, cam, p1)
        f0, f1 = (
            detect_sift(cv2.cvtColor(r.image, cv2.COLOR_RGB2GRAY), max_num_features=2000)
            for r in (r0, r1)
        )
        d0, d1 = f0.descriptors.astype(np.float32), f1.descriptors.astype(np.float32)
        knn = cv2.BFMatcher(cv2.NORM_L2).knnMatch(d0, d1, k=2)
        m = np.array([(a.queryIdx, a.trainIdx) for a, b in knn if a.distance < 0.8 * b.distance])
        xy0 = f0.keypoints[m[:, 0]]
        j, i = np.floor(xy0).astype(int).T
        gt, _ = synth.reproject(r0, cam, p1)
        err = np.linalg.norm(gt[i, j] - f1.keypoints[m[:, 1]], axis=1)
        good += int(np.sum(err < 3.0))
        total += len(m)
    assert total > 200 and good / total > 0.85


def test_trees_add_non_planar_vegetation_and_leave_the_rest(camera):
    """Trees are appended after everything else (the scene without them is a prefix, so
    seeded scenes without trees are unchanged), block cameras, and a view of a crown has
    no dominant plane (like rubble)."""
    plain = synth.street(np.random.default_rng(4))
    treed = synth.street(np.random.default_rng(4), trees=True)
    n = len(plain)
    assert len(treed) > n + 300
    np.testing.assert_array_equal(treed.origin[:n], plain.origin[:n])
    np.testing.assert_array_equal(treed.kind[:n], plain.kind[:n])
    veg = synth.KIND_NAMES.index("vegetation")
    assert np.all(treed.kind[n:] == veg) and not np.any(plain.kind == veg)
    assert len(treed.blockers) > len(plain.blockers)
    # look at the first crown from 7 m away, level with it
    leaves = n + 5 + np.arange(150)  # after the first trunk's 5 quads: its leaves
    c = np.median(treed.origin[leaves], 0)
    eye = c + np.array([7.0, 0.0, 0.0]) if c[0] < 0 else c - np.array([7.0, 0.0, 0.0])
    r = synth.render(treed, camera, synth.look_at(eye, c), supersample=1)
    valid = r.plane_id >= 0
    on_veg = valid & (treed.kind[np.maximum(r.plane_id, 0)] == veg)
    assert on_veg.mean() > 0.2
    R = r.cam_from_world.rotation.matrix()
    assert dominant_fraction(r.normals[on_veg].astype(np.float64) @ R) < 0.3
    assert len(np.unique(r.plane_id[on_veg])) > 40


def test_clouds_change_only_the_sky(street_scene, camera):
    """Clouds (opt-in) texture the sky and nothing else: the same view with and without
    them has the same depth, the same colours on surfaces, and a sky with more detail;
    the cloud map is periodic in azimuth (no seam behind the camera)."""
    import dataclasses

    from rectified_colmap.demo.render import _cloud_map

    pose = synth.look_at([0.0, 5.0, 1.6], [0.0, 40.0, 12.0])
    clear = synth.render(street_scene, camera, pose, supersample=1)
    cloudy_scene = dataclasses.replace(street_scene, clouds=0.6, _pyramids={})
    cloudy = synth.render(cloudy_scene, camera, pose, supersample=1)
    np.testing.assert_array_equal(clear.depth, cloudy.depth)
    surf = clear.plane_id >= 0
    sky = ~surf
    assert sky.mean() > 0.1
    np.testing.assert_array_equal(clear.image[surf], cloudy.image[surf])
    assert np.abs(cloudy.image[sky].astype(int) - clear.image[sky]).mean() > 3
    cmap = _cloud_map(cloudy_scene)
    assert 0.3 < (cmap > 0).mean() < 0.9
    seam = np.abs(cmap[:, 0] - cmap[:, -1]).mean()
    inner = np.abs(np.diff(cmap, axis=1)).mean()
    assert seam < 3 * inner + 1e-3
