"""Real-photo supervision (rectified_colmap_research.training.real) and the sky head / label losses.

Geometry is tested exactly on synthetic cameras; the line-derived labels statistically on a
rendered street with exact normals. The torch parts are skipped without torch."""

import numpy as np
import pycolmap
import pytest
from tests.scenes import plane_depth, street_views_folder

from rectified_colmap_research import synth
from rectified_colmap_research.training import real
from rectified_colmap_research.training.sky import NOT_SKY, SKY, UNKNOWN


def _radial_camera(w=200, h=150, f=180.0, k=0.15):
    return pycolmap.Camera(model="SIMPLE_RADIAL", width=w, height=h, params=[f, w / 2, h / 2, k])


def test_cover_crop_affine_covers_and_centres():
    for w, h, ow, oh in ((1024, 768, 320, 240), (768, 1024, 320, 240), (1024, 309, 320, 240)):
        a = real.cover_crop_affine(w, h, ow, oh)
        corners = np.array([[0, 0], [w, h]], float) @ a[:, :2].T + a[:, 2]
        assert corners[0, 0] <= 1e-9 and corners[0, 1] <= 1e-9  # covers the output
        assert corners[1, 0] >= ow - 1e-9 and corners[1, 1] >= oh - 1e-9
        centre = np.array([w / 2, h / 2]) @ a[:, :2].T + a[:, 2]
        assert np.allclose(centre, [ow / 2, oh / 2])


def test_source_coords_undistort_exactly():
    """The output is a pinhole view: a 3D point projected with the output K lands on the
    pixel whose source position is the camera's (distorted) projection of that point."""
    cam = _radial_camera()
    a = real.cover_crop_affine(cam.width, cam.height, 64, 48)
    xy, K = real.source_coords(cam, a, 64, 48)
    X = np.array([[0.2, -0.1, 1.0], [-0.3, 0.2, 2.0]])
    for p in X:
        uv = K @ p
        uv = uv[:2] / uv[2]
        r, c = int(uv[1]), int(uv[0])
        centre = np.array([c + 0.5, r + 0.5])  # COLMAP pixel centre
        ray = np.linalg.inv(K) @ np.array([*centre, 1.0])
        assert np.allclose(xy[r, c], cam.img_from_cam(ray[None])[0], atol=1e-9)
    xy0, K0 = real.source_coords(None, a, 64, 48)  # no camera: the affine crop
    assert np.isnan(K0).all()
    back = xy0 @ a[:, :2].T + a[:, 2]
    v, u = np.mgrid[:48, :64] + 0.5
    assert np.allclose(back, np.stack([u, v], -1))


def test_sparse_depth_nearest_point_wins():
    K = np.array([[50.0, 0, 16], [0, 50, 12], [0, 0, 1]])
    pose = pycolmap.Rigid3d()
    pts = np.array([[0.0, 0.0, 4.0], [0.0, 0.0, 2.0], [0.2, 0.1, 3.0], [0.0, 0.0, -1.0]])
    d = real.sparse_depth_map(pts, pose, K, 32, 24)
    assert d[12, 16] == 2.0  # two points on one pixel: the nearer one
    u, v = 50 * 0.2 / 3 + 16, 50 * 0.1 / 3 + 12
    assert d[int(v), int(u)] == 3.0
    assert (d > 0).sum() == 2  # the point behind the camera is dropped


def test_focal_from_horizon_and_zenith():
    f, pp = 700.0, np.array([320.0, 240.0])
    for tilt in (5.0, 20.0, 40.0):
        t = np.deg2rad(tilt)
        up = np.array([0.0, -np.cos(t), np.sin(t)])  # camera pitched up by `tilt`
        K = np.array([[f, 0, pp[0]], [0, f, pp[1]], [0, 0, 1]])
        z = K @ up
        zenith = z[:2] / z[2]
        horizon = np.linalg.inv(K).T @ up  # the vanishing line of planes normal to `up`
        assert real.focal_from_horizon_zenith(horizon, zenith, pp) == pytest.approx(f, 1e-9)


def test_save_load_roundtrip(tmp_path):
    rng = np.random.default_rng(0)
    h, w = 24, 32
    normals = np.zeros((h, w, 3), np.float32)
    normals[:10] = [0, 0, -1.0]
    normals[15:] = [0.6, 0, -0.8]
    depth = np.zeros((h, w), np.float32)
    depth[3, 4], depth[20, 30] = 2.5, 7.0
    s = {
        "image": rng.integers(0, 256, (h, w, 3), dtype=np.uint8),
        "K": np.array([[30.0, 0, 16], [0, 30, 12], [0, 0, 1]]),
        "depth": depth,
        "normals": normals,
        "sky": np.where(np.arange(h)[:, None] < 5, SKY, UNKNOWN).astype(np.uint8)
        * np.ones((1, w), np.uint8),
        "frame": np.eye(3),
        "name": "x.jpg",
    }
    real.save_real_sample(tmp_path / "a.npz", s)
    t = real.load_real_sample(tmp_path / "a.npz")
    assert np.array_equal(t["depth"], depth) and np.array_equal(t["normals"], normals)
    assert np.array_equal(t["sky"], s["sky"]) and np.array_equal(t["K"], s["K"])
    assert t["image"].shape == (h, w, 3) and t["name"] == "x.jpg"
    (tmp_path / "bad.npz").write_bytes(b"nope")
    with pytest.raises(ValueError, match="bad.npz"):
        real.load_real_sample(tmp_path / "bad.npz")


def test_line_labels_match_rendered_normals(tmp_path):
    """On a rendered street (exact normals), the line-support labels that make it into a
    real sample point where the surfaces do."""
    import cv2

    rng = np.random.default_rng(5)
    scene = synth.street(rng)
    cam = synth.pinhole_camera(640, 480, 500.0)
    good = 0
    for _ in range(3):
        pose = synth.random_view(scene, rng, cam)
        r = synth.render(scene, cam, pose)
        path = tmp_path / "v.png"
        cv2.imwrite(str(path), r.image[..., ::-1])
        s = real.make_real_sample(real.RealItem(path, cam), 160, 120)
        has = np.abs(s["normals"]).sum(-1) > 0
        if has.mean() < 0.05:
            continue
        a = real.cover_crop_affine(640, 480, 160, 120)
        xy, _ = real.source_coords(cam, a, 160, 120)
        gt = r.normals[
            np.clip(xy[..., 1].astype(int), 0, 479), np.clip(xy[..., 0].astype(int), 0, 639)
        ]
        ok = has & np.isfinite(gt).all(-1)
        cos = (s["normals"][ok] * gt[ok]).sum(-1)
        assert np.mean(cos > np.cos(np.deg2rad(5))) > 0.7, np.mean(cos > 0.99)
        assert (s["sky"][has] == NOT_SKY).all()
        good += 1
    assert good >= 1


# -- torch: losses, sky head ----------------------------------------------------------------
def _tilted_plane(torch):
    """A plane seen obliquely: its unit normal n, its exact log-depth (1, 1, h, w), K (1, 3, 3)
    and (h, w)."""
    n = np.array([0.3, -0.4, -0.8])
    n /= np.linalg.norm(n)
    K = np.array([[80.0, 0, 50], [0, 80, 30], [0, 0, 1]])
    h, w = 60, 100
    log_z = torch.from_numpy(np.log(plane_depth(n, K, h, w)))[None, None]
    return n, log_z, torch.from_numpy(K)[None], (h, w)


def test_label_normal_and_sky_losses():
    torch = pytest.importorskip("torch")
    from rectified_colmap_research.training import losses

    n, log_z, Kt, (h, w) = _tilted_plane(torch)
    labels = torch.zeros(1, 3, h, w, dtype=torch.float64)
    labels[:, :, 10:40, 20:70] = torch.from_numpy(n)[None, :, None, None]
    one = torch.ones(1, dtype=torch.float64)
    assert losses.label_normal_loss(log_z, labels, Kt, one) < 1e-12
    wrong = torch.zeros_like(labels)
    wrong[:, 2, 10:40, 20:70] = -1.0  # fronto-parallel label on a tilted plane
    got = float(losses.label_normal_loss(log_z, wrong, Kt, one))
    assert got == pytest.approx(1 - n[2] * -1.0, abs=1e-9)
    assert losses.label_normal_loss(log_z, wrong, Kt, 0 * one) == 0  # renders: not used
    sky = torch.full((1, 1, 4, 4), 255.0)
    sky[..., :2, :] = 1.0
    sky[..., 3, :] = 0.0
    logit = torch.zeros(1, 1, 4, 4)
    logit[..., :2, :] = 20.0
    logit[..., 3, :] = -20.0
    logit[..., 2, :] = 5.0  # unknown row: ignored whatever its value
    assert losses.sky_loss(logit, sky) < 1e-8
    assert losses.sky_loss(-logit, sky) > 10


def test_frame_axis_loss():
    """1 - cos of the angle to the nearest frame axis, on pixels within the gate, sky and
    frame-less images excluded."""
    torch = pytest.importorskip("torch")
    import cv2

    from rectified_colmap_research.training import losses

    n, log_z, Kt, (h, w) = _tilted_plane(torch)
    u = np.cross(n, [1.0, 0.0, 0.0])
    u /= np.linalg.norm(u)
    frame = np.stack([-n, u, np.cross(n, u)])  # the sign of an axis does not matter

    def loss(f, sky=None):
        return float(losses.frame_axis_loss(log_z, torch.from_numpy(f)[None], Kt, sky))

    assert loss(frame) < 1e-12
    tilt = cv2.Rodrigues(u[:, None] * np.deg2rad(10.0))[0]  # the plane's axis 10 degrees off
    assert loss(frame @ tilt.T) == pytest.approx(1 - np.cos(np.deg2rad(10.0)), abs=1e-9)
    far = cv2.Rodrigues(u[:, None] * np.deg2rad(40.0))[0]  # outside the 30-degree gate: clutter
    assert loss(frame @ far.T) == 0 and loss(np.full((3, 3), np.nan)) == 0
    sky = torch.ones(1, 1, h, w, dtype=torch.float64)
    assert loss(frame @ tilt.T, sky) == 0


def test_total_loss_shares_the_predicted_normals():
    """total_loss computes the predicted depth's normals once for the three normal losses:
    its parts equal each loss computed on its own, on a noisy prediction."""
    torch = pytest.importorskip("torch")
    from rectified_colmap_research.training import losses

    n, log_z, Kt, (h, w) = _tilted_plane(torch)
    depth = torch.exp(log_z)
    normals = torch.zeros(1, 3, h, w, dtype=torch.float64)
    normals[:, :, 5:50, 10:90] = torch.from_numpy(n)[None, :, None, None]
    u = np.cross(n, [1.0, 0.0, 0.0])
    u /= np.linalg.norm(u)
    frame = torch.from_numpy(np.stack([-n, u, np.cross(n, u)]))[None]
    one = torch.ones(1, dtype=torch.float64)
    batch = {"depth": depth, "normals": normals, "K": Kt, "real": one, "frame": frame}
    pred = log_z + 0.01 * torch.randn(log_z.shape, generator=torch.Generator().manual_seed(0))
    _, parts = losses.total_loss(pred, batch, w_axis=1.0)
    alone = {
        "normal": losses.normal_loss(pred, depth, normals, Kt),
        "lines": losses.label_normal_loss(pred, normals, Kt, one),
        "axis": losses.frame_axis_loss(pred, frame, Kt),
    }
    for k, v in alone.items():
        assert float(v) > 1e-6, k  # the noise is seen by every loss
        assert parts[k] == pytest.approx(float(v), rel=1e-12), k


def test_sky_head_zeroes_depth():
    torch = pytest.importorskip("torch")
    from rectified_colmap_research.training.model import DepthNet

    net = DepthNet(width=16, sky=True).eval()
    x = torch.zeros(1, 3, 64, 96)
    with torch.no_grad():
        net.sky_head[-1].bias.fill_(-50.0)
        assert (net(x) > 0).all()
        net.sky_head[-1].bias.fill_(50.0)
        assert (net(x) == 0).all()
        log, sky = net.forward_train(x)
        assert log.shape == sky.shape == (1, 1, 64, 96)
    assert DepthNet(width=16).forward_train(x)[1] is None


def test_pool_dataset_mixes_real_samples(tmp_path):
    pytest.importorskip("torch")
    from rectified_colmap_research.training.data import PoolDataset, synth_sample

    h, w = 60, 80
    sky = np.full((h, w), UNKNOWN, np.uint8)
    sky[:10, :40] = SKY
    s = {
        "image": np.full((h, w, 3), 128, np.uint8),
        "K": np.full((3, 3), np.nan),
        "depth": np.zeros((h, w), np.float32),
        "normals": np.zeros((h, w, 3), np.float32),
        "sky": sky,
        "frame": np.full((3, 3), np.nan),
        "name": "r",
    }
    real.save_real_sample(tmp_path / "r.npz", s)
    render = tmp_path / "pool"
    render.mkdir()
    r = synth_sample(3, w, h, None, supersample=1)
    np.savez(render / "00000003.npz", **{k: r[k] for k in ("image", "depth", "normals", "K")})
    ds = PoolDataset(
        [], 48, 64, real_paths=[tmp_path / "r.npz"], real_frac=0.5, pool_dir=render, length=40
    )
    kinds = [float(ds[i]["real"]) for i in range(40)]
    assert 5 < sum(kinds) < 35
    for i in range(40):
        item = ds[i]
        assert np.isfinite(item["K"].numpy()).all()  # camera-less photos get a valid K
        v = set(np.unique(item["sky"].numpy()).tolist())
        if float(item["real"]):
            assert v <= {0.0, 1.0, 255.0} and 1.0 in v
        else:  # renders: sky exactly where there is no depth
            assert v <= {0.0, 1.0}
            assert np.array_equal(item["sky"].numpy() == 1, item["depth"].numpy() <= 0)


def _two_plane_points(rng, n=1500, noise=0.005):
    """World points on a wall (z = 5, x in [-2, 0]) and a ground (y = 1.5, x in [0.3, 2],
    z in [3, 8]), camera-frame axes, with 10 % outliers in the box between."""
    wall = np.column_stack([rng.uniform(-2, 0, n), rng.uniform(-1, 1.4, n), np.full(n, 5.0)])
    ground = np.column_stack([rng.uniform(0.3, 2, n), np.full(n, 1.5), rng.uniform(3, 8, n)])
    out = rng.uniform([-2, -1, 3], [2, 1.5, 8], (n // 5, 3))
    pts = np.vstack([wall, ground]) + rng.normal(0, noise, (2 * n, 3)).clip(-3 * noise, 3 * noise)
    truth = np.r_[np.zeros(n, int), np.ones(n, int), np.full(len(out), -1)]
    return np.vstack([pts, out]), truth


def test_fit_planes_recovers_wall_and_ground():
    rng = np.random.default_rng(3)
    pts, truth = _two_plane_points(rng)
    planes, labels = real.fit_planes(pts, threshold=0.03, min_inliers=200)
    assert len(planes) == 2
    for k, normal, d in ((0, [0, 0, 1], -5.0), (1, [0, 1, 0], -1.5)):
        # which fitted plane holds the true plane's points, and is it the true plane
        p = np.bincount(labels[truth == k][labels[truth == k] >= 0]).argmax()
        # (the wall plane, fitted first, also takes the 1.2 % of ground points near z = 5)
        assert np.mean(labels[truth == k] == p) > 0.98
        s = np.sign(planes[p, :3] @ normal)
        assert np.allclose(s * planes[p, :3], normal, atol=2e-3)
        assert abs(s * planes[p, 3] - d) < 0.01
    assert np.mean(labels[truth == -1] == -1) > 0.9  # outliers stay unlabelled


def test_plane_normal_map_labels_only_where_points_are_dense():
    """A posed camera sees the wall and the ground: labelled pixels carry exactly the
    planes' normals in the camera frame, facing the camera, and only near their points."""
    rng = np.random.default_rng(4)
    pts, truth = _two_plane_points(rng, n=4000, noise=0.0)
    # move the world: world = A (camera frame) + b; the camera is then at b
    A = pycolmap.Rotation3d(np.array([0.1, -0.2, 0.3]) / np.linalg.norm([0.1, -0.2, 0.3]) * 0.5)
    A = A.matrix()
    b = np.array([3.0, -1.0, 2.0])
    world = pts @ A.T + b
    cam_from_world = pycolmap.Rigid3d(pycolmap.Rotation3d(A.T), -A.T @ b)
    planes = np.array([[*(A @ [0, 0, 1]), 0.0], [*(A @ [0, -1, 0]), 0.0]])
    planes[0, 3] = -planes[0, :3] @ (A @ [0, 0, 5] + b)
    planes[1, 3] = -planes[1, :3] @ (A @ [0, 1.5, 0] + b)
    K = np.array([[60.0, 0, 40], [0, 60, 30], [0, 0, 1]])
    n = real.plane_normal_map(world, truth, planes, cam_from_world, K, 80, 60, radius=3)
    has = np.abs(n).sum(-1) > 0
    assert 0.2 < has.mean() < 0.95
    facing = {(0.0, 0.0, -1.0), (0.0, -1.0, 0.0)}  # wall at z = 5, ground below (y down)
    got = {tuple(np.round(v, 6) + 0.0) for v in n[has]}
    assert got == facing
    # wall labels lie where the wall is: ray through the pixel meets z = 5 at x in [-2, 0]
    v, u = np.nonzero(np.all(np.isclose(n, [0, 0, -1]), -1))
    x = (u + 0.5 - 40) / 60 * 5
    assert x.max() < 0 + 4 / 60 * 5 and x.min() > -2 - 4 / 60 * 5
    # a grazing plane is left out
    n2 = real.plane_normal_map(
        world, truth, planes, cam_from_world, K, 80, 60, radius=3, max_incidence_deg=20
    )
    assert not np.all(np.isclose(n2, [0, -1, 0]), -1).any()  # the ground is seen > 20 deg
    assert np.all(np.isclose(n2, [0, 0, -1]), -1).any()  # the wall, frontal, stays


def test_plane_normal_map_camera_matches_the_pinhole_map():
    """On a PINHOLE camera the camera version (the evaluation's grid, half resolution here)
    gives exactly the labels of the K version with K scaled to the grid."""
    rng = np.random.default_rng(5)
    pts, truth = _two_plane_points(rng, n=4000, noise=0.0)
    planes = np.array([[0, 0, 1.0, -5.0], [0, 1.0, 0, -1.5]])
    cam = pycolmap.Camera(model="PINHOLE", width=160, height=120, params=[120, 120, 80, 60])
    pose = pycolmap.Rigid3d()
    a = real.plane_normal_map_camera(pts, truth, planes, pose, cam, 80, 60, radius=3)
    K = np.array([[60.0, 0, 40], [0, 60, 30], [0, 0, 1]])
    b = real.plane_normal_map(pts, truth, planes, pose, K, 80, 60, radius=3)
    assert (np.abs(a).sum(-1) > 0).mean() > 0.2
    np.testing.assert_allclose(a, b, atol=1e-6)


def test_merge_normal_labels_prefers_planes_and_drops_conflicts():
    planes = np.zeros((1, 4, 3), np.float32)
    lines = np.zeros((1, 4, 3), np.float32)
    planes[0, 0] = [0, 0, -1]  # plane only
    lines[0, 1] = [0, -1, 0]  # line only
    planes[0, 2], lines[0, 2] = [0, 0, -1], [0, np.sin(0.1), -np.cos(0.1)]  # agree (5.7 deg)
    planes[0, 3], lines[0, 3] = [0, 0, -1], [-1, 0, 0]  # disagree
    m = real.merge_normal_labels(planes, lines)
    np.testing.assert_array_equal(m[0, :3], [[0, 0, -1], [0, -1, 0], [0, 0, -1]])
    assert not m[0, 3].any()


def test_evaluate_planes_scores_normals_against_plane_fits(tmp_path):
    """The plane-fit measure on a rendered street written as a real-pool set: SfM-like
    points sampled from the exact depth; the exact depth scores < 1 deg on almost every
    labelled pixel, a depth tilting every plane scores far worse."""
    from rectified_colmap.depth import DepthMap
    from rectified_colmap_research.training.evaluate import evaluate_planes

    rec, renders, rng = street_views_folder(tmp_path / "s", 7, 320, 240, 260.0)
    camera = rec.cameras[1]
    depth = {name: r.depth for name, r in renders.items()}
    for i, (name, r) in enumerate(renders.items()):
        v, u = np.nonzero(r.depth > 0)
        pick = rng.choice(len(v), 3000, replace=False)
        uv = np.column_stack([u[pick], v[pick]]) + 0.5
        Xc = camera.cam_from_img(uv)
        Xc = np.column_stack([Xc, np.ones(len(Xc))]) * r.depth[v[pick], u[pick]][:, None]
        pose = r.cam_from_world
        R, t = pose.rotation.matrix(), np.asarray(pose.translation)
        Xw = (Xc - t) @ R
        im = pycolmap.Image(
            name=name,
            camera_id=1,
            image_id=i + 1,
            points2D=pycolmap.Point2DList([pycolmap.Point2D(p) for p in uv]),
        )
        rec.add_image_with_trivial_frame(im, pose)
        for k, x in enumerate(Xw):
            track = pycolmap.Track()
            track.add_element(i + 1, k)
            rec.add_point3D(x, track, np.zeros(3, np.uint8))
    (tmp_path / "s" / "colmap_sparse").mkdir()
    rec.write(str(tmp_path / "s" / "colmap_sparse"))

    exact = evaluate_planes(
        lambda path, rgb: DepthMap(depth[path.name], "metric"), tmp_path, sets=("s",)
    )
    assert exact["plane_images"] == 2
    assert exact["plane_err_pooled"] < 1.0 and exact["plane_within15_pooled"] > 0.95
    tilt = np.linspace(1.0, 2.5, 320)[None]  # depth x a horizontal ramp: planes bend
    bent = evaluate_planes(
        lambda path, rgb: DepthMap(depth[path.name] * tilt, "metric"), tmp_path, sets=("s",)
    )
    assert bent["plane_err_pooled"] > 10 * max(exact["plane_err_pooled"], 0.5)


def test_evaluate_outdoor_separates_trees_from_planes():
    """Through the pipeline's plane labels, the exact depth leaves tree crowns mostly
    non-planar and the buildings planar; a constant depth (one fronto-parallel plane
    everywhere) is caught labelling the trees planar."""
    from rectified_colmap.depth import DepthMap
    from rectified_colmap_research.training.evaluate import evaluate_outdoor

    res = evaluate_outdoor(
        lambda rgb: DepthMap(np.full(rgb.shape[:2], 5.0, np.float32), "metric"),
        num=3,
        width=192,
        height=144,
    )
    assert res["veg_views"] == 3
    assert res["veg_planar_gtdepth"] < 0.25 < 0.6 < res["surface_planar_gtdepth"]
    assert res["veg_planar_pred"] > 0.9
    assert res["sky_planar_gtdepth"] == 0 and res["sky_planar_pred"] > 0.9


def test_prepare_gpu_carry_shrinks_the_facade_photos(tmp_path):
    """scripts/prepare_gpu_carry.py: photos keep their folders, become JPEG with at most
    max_side px (aspect kept), small ones are not enlarged, unreadable files are skipped."""
    import cv2
    from scripts_util import load_script

    carry = load_script("prepare_gpu_carry")
    src = tmp_path / "facades"
    (src / "brick").mkdir(parents=True)
    cv2.imwrite(str(src / "brick" / "a.png"), np.zeros((300, 200, 3), np.uint8))
    cv2.imwrite(str(src / "b.jpg"), np.zeros((40, 50, 3), np.uint8))
    (src / "broken.jpg").write_bytes(b"not an image")
    assert carry.shrink_textures(src, tmp_path / "out", 96) == 2
    a = cv2.imread(str(tmp_path / "out" / "brick" / "a.jpg"))
    b = cv2.imread(str(tmp_path / "out" / "b.jpg"))
    assert a.shape[:2] == (96, 64) and b.shape[:2] == (40, 50)
