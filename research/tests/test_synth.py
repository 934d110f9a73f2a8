"""rectified_colmap_research.synth: random views and view pairs of the demo wing's scenes and
their ground truth (reprojection, relative pose), more scene layouts (rubble), random
training samples."""

import numpy as np
import pytest

from rectified_colmap_research import synth
from rectified_colmap_research.synth.views import TARGET_KINDS
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


def test_reprojection_lands_on_the_same_surface_point(street_scene, camera):
    """Pixels of view 0 back-projected with their depth and moved with the relative pose:
    where view 1 sees them unoccluded (independent ray cast), view 1 renders the same quad
    there, and the quad's plane gives both depths exactly."""
    rng = np.random.default_rng(4)
    p0, p1, X = synth.view_pair(street_scene, rng, 50, 90, "facade", camera=camera)
    r0, r1 = synth.render(street_scene, camera, p0), synth.render(street_scene, camera, p1)
    xy, z = synth.reproject(r0, camera, p1)
    Xw, q, _ = _world_points(r0)
    c1 = synth.camera_center(p1)
    t, q1 = synth.raycast(street_scene, np.repeat(c1[None], len(Xw), 0), Xw - c1)
    seen = (t > 1 - 1e-6) & (q1 == q)  # first hit of camera 1's ray is the point's quad
    xy, z = xy[r0.plane_id >= 0], z[r0.plane_id >= 0]
    inside = (xy[:, 0] > 1) & (xy[:, 0] < W - 1) & (xy[:, 1] > 1) & (xy[:, 1] < H - 1)
    ok = seen & inside
    assert ok.sum() > 0.2 * W * H
    j, i = np.floor(xy[ok]).astype(int).T
    assert np.mean(r1.plane_id[i, j] == q[ok]) > 0.97  # same surface (edges aside)
    # exact: the quad's plane in camera 1 predicts both view 1's depth at its pixel centre
    # and the reprojected depth at the (sub-pixel) reprojected position
    m1 = np.asarray(p1.matrix())
    nw = np.cross(street_scene.eu, street_scene.ev)[q[ok]]
    n1 = nw @ m1[:, :3].T
    d1 = np.einsum("ij,ij->i", n1, street_scene.origin[q[ok]] @ m1[:, :3].T + m1[:, 3])
    Kinv = np.linalg.inv(camera.calibration_matrix())

    def plane_depth(x, y):
        rays = np.stack([x, y, np.ones_like(x)], 1) @ Kinv.T
        return d1 / np.einsum("ij,ij->i", n1, rays)

    np.testing.assert_allclose(plane_depth(xy[ok, 0], xy[ok, 1]), z[ok], rtol=1e-6)
    same = r1.plane_id[i, j] == q[ok]
    np.testing.assert_allclose(plane_depth(j + 0.5, i + 0.5)[same], r1.depth[i, j][same], rtol=1e-5)
    # the covisibility helper agrees with the ray cast
    frac = synth.covisible_fraction(r0, r1, rel_tol=0.02)
    assert abs(frac - ok.sum() / (r0.plane_id >= 0).sum()) < 0.1


def test_relative_pose_convention():
    p0 = synth.look_at([0, 0, 1.5], [5, 5, 2])
    p1 = synth.look_at([2, -1, 3], [5, 5, 2])
    T = synth.relative_T(p0, p1)
    Xw = np.array([[4.0, 6.0, 1.0], [1.0, 8.0, 3.0]])
    X0 = p0 * Xw
    X1 = p1 * Xw
    np.testing.assert_allclose(X0 @ T[:3, :3].T + T[:3, 3], X1, atol=1e-9)


def test_random_view_is_in_free_space_and_sees_the_scene(street_scene, camera):
    rng = np.random.default_rng(5)
    for _ in range(5):
        pose = synth.random_view(street_scene, rng, camera)
        c = synth.camera_center(pose)
        assert street_scene.in_free_space(c[None])[0]
        assert 1.2 <= c[2] <= 10.0
        r = synth.render(street_scene, camera, pose, supersample=1)
        assert np.isfinite(r.depth).mean() > 0.5 and np.nanmin(r.depth) > 0.5
        R = pose.rotation.matrix()
        up = R @ np.array([0, 0, 1.0])
        roll = np.degrees(np.arctan2(-up[0], -up[1]))
        assert abs(roll) < 10.5


@pytest.mark.parametrize("target", ["facade", "ground"])
def test_view_pair_constraints(target, camera):
    rng = np.random.default_rng(6)
    for gen in (synth.street, synth.corner):
        scene = gen(rng)
        p0, p1, X = synth.view_pair(scene, rng, 50, 90, target, camera=camera)
        assert 50 - 1e-6 <= synth.angle_between_views(p0, p1, X) <= 90 + 1e-6
        kinds = TARGET_KINDS[target]
        q = synth.raycast(scene, synth.camera_center(p0)[None], X - synth.camera_center(p0))[1]
        assert scene.kind[q[0]] in kinds
        sides = []
        for p in (p0, p1):
            xc = p * X[None]
            K = camera.calibration_matrix()
            uv = K[:2, :2] @ (xc[0, :2] / xc[0, 2]) + K[:2, 2]
            assert xc[0, 2] > 0 and 0 <= uv[0] < W and 0 <= uv[1] < H
            r = synth.render(scene, camera, p, supersample=1)
            assert r.depth[int(uv[1]), int(uv[0])] == pytest.approx(xc[0, 2], rel=0.02)
            sides.append(np.sign(scene.normal[q[0]] @ (synth.camera_center(p) - X)))
        assert sides[0] == sides[1] == 1


def test_rubble_has_no_dominant_planes(camera):
    rng = np.random.default_rng(10)
    scene = synth.rubble(rng)
    street_like = synth.street(rng)
    fr_rubble, fr_street, cover = [], [], []
    for sc, out in ((scene, fr_rubble), (street_like, fr_street)):
        for _ in range(2):
            pose = synth.random_view(sc, rng, camera)
            r = synth.render(sc, camera, pose, supersample=1)
            valid = r.plane_id >= 0
            R = pose.rotation.matrix()
            out.append(dominant_fraction(r.normals[valid].astype(np.float64) @ R))
            if sc is scene:
                cover.append(valid.mean())
                ids, counts = np.unique(r.plane_id[valid], return_counts=True)
                assert len(ids) > 50 and counts.max() < 0.1 * valid.sum()
    assert min(cover) > 0.4
    assert max(fr_rubble) < 0.2 and min(fr_street) > 0.3


def test_random_sample_for_training():
    r = synth.random_sample(np.random.default_rng(12), 128, 96)
    assert r.image.shape == (96, 128, 3)
    f = r.K[0, 0]
    assert 0.6 * 128 <= f <= 1.4 * 128
    assert np.isfinite(r.depth).mean() > 0.5
