from dataclasses import replace

import cv2
import numpy as np
import pytest

from rectified_colmap import camera as cam_utils
from rectified_colmap import sift as sift_module
from rectified_colmap.budget import OPENCV_VIEW_PIXELS_RATIO, view_pixel_budget
from rectified_colmap.camera import make_camera, rays_to_image
from rectified_colmap.config import VIEW_RESOLUTIONS, RectifyConf
from rectified_colmap.planes import BLIND_AXIS, HYPOTHESIS_AXIS, Patch
from rectified_colmap.rectify import (
    Rectification,
    image_to_rectified_homography,
    plan_rectification,
    rectified_to_image,
    fitting_roll,
    patch_view,
    rectifying_rotation,
    upsampled_rectification,
    warp_to_rectified,
)

W, H = 240, 160
GW, GH = 120, 80  # work grid
CAMERAS = {
    "PINHOLE": ("PINHOLE", [200.0, 190.0, 121.0, 79.0]),
    "SIMPLE_RADIAL": ("SIMPLE_RADIAL", [200.0, 120.0, 80.0, -0.08]),
    "OPENCV": ("OPENCV", [200.0, 195.0, 118.0, 82.0, 0.05, -0.02, 0.002, -0.001]),
}


def camera(name):
    model, params = CAMERAS[name]
    return make_camera(model, params, W, H)


def unit(v):
    v = np.asarray(v, dtype=np.float64)
    return v / np.linalg.norm(v)


def plane_basis(n):
    e1 = unit(np.cross(n, [0.0, 0.0, 1.0]) if abs(n[2]) < 0.99 else np.cross(n, [1.0, 0, 0]))
    return e1, np.cross(n, e1)


def full_patch(n, mask=None):
    mask = np.ones((GH, GW), bool) if mask is None else mask
    return Patch(mask, 0, unit(n), float(mask.mean()))


NORMALS = [[0.5, -0.2, -0.8], [0.0, -0.9, -0.45], [-0.7, 0.1, -0.6]]


def test_rectifying_rotation_properties():
    rng = np.random.default_rng(0)
    ns = [rng.normal(size=3) for _ in range(50)]
    ns += [[0, 0, -1.0], [0, 0, 1.0], [1e-13, 0, 1.0], [1e-9, -1e-9, 1.0], [1.0, 0, 0]]
    for n in ns:
        n = unit(n)
        R = rectifying_rotation(n)
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(R) == pytest.approx(1.0, abs=1e-12)
        np.testing.assert_allclose(R @ -n, [0, 0, 1.0], atol=1e-9)
        # Smallest rotation: its angle is the angle between -n and z.
        angle = np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))
        assert angle == pytest.approx(np.arccos(np.clip(-n[2], -1, 1)), abs=1e-6)
    np.testing.assert_allclose(rectifying_rotation([0, 0, -1.0]), np.eye(3), atol=1e-15)


@pytest.mark.parametrize("n", NORMALS)
def test_homography_makes_plane_fronto_parallel(n):
    cam = camera("PINHOLE")
    n = unit(n)
    rect = plan_rectification(cam, full_patch(n), 0)
    assert rect is not None
    e1, e2 = plane_basis(n)
    g = np.stack(np.meshgrid(np.linspace(-1, 1, 7), np.linspace(-1, 1, 7)), -1).reshape(-1, 2)
    X = -4.0 * n + g[:, :1] * e1 + g[:, 1:] * e2
    xy = rays_to_image(cam, X)
    Hm = image_to_rectified_homography(cam, rect)
    q = np.c_[xy, np.ones(len(xy))] @ Hm.T
    q = q[:, :2] / q[:, 2:]
    # q is a similarity of the plane coordinates g: q = s Rot g + t.
    A = np.c_[g, np.ones(len(g))]
    M = np.linalg.lstsq(A, q, rcond=None)[0]
    assert np.abs(A @ M - q).max() < 1e-6
    L = M[:2]
    G = L.T @ L  # a similarity: orthogonal columns of equal length
    np.testing.assert_allclose(G, np.eye(2) * G[0, 0], atol=1e-6 * np.abs(L).max() ** 2)


@pytest.mark.parametrize("name", list(CAMERAS))
def test_round_trips_and_direct_projection(name):
    cam = camera(name)
    n = unit(NORMALS[0])
    rect = plan_rectification(cam, full_patch(n), 0)
    e1, e2 = plane_basis(n)
    rng = np.random.default_rng(1)
    g = rng.uniform(-1, 1, (200, 2))
    X = -5.0 * n + g[:, :1] * e1 + g[:, 1:] * e2
    xy = rays_to_image(cam, X)
    ok = (xy > 0).all(1) & (xy[:, 0] < W) & (xy[:, 1] < H)
    X, xy = X[ok], xy[ok]
    # Direct projection of the 3D points into the virtual camera.
    Xv = X @ rect.R.T @ rect.K.T
    q = Xv[:, :2] / Xv[:, 2:]
    back, _ = rectified_to_image(cam, rect, q)
    assert np.abs(back - xy).max() < 0.1
    assert np.abs(back - xy).max() < 1e-6  # in fact exact
    # image -> rectified -> image through the pinhole part when the camera is pinhole.
    if cam_utils.is_pinhole(cam):
        Hm = image_to_rectified_homography(cam, rect)
        p = np.c_[xy, np.ones(len(xy))] @ Hm.T
        np.testing.assert_allclose(p[:, :2] / p[:, 2:], q, atol=1e-6)


@pytest.mark.parametrize("name", list(CAMERAS))
def test_jacobian_matches_central_differences(name):
    cam = camera(name)
    rect = plan_rectification(cam, full_patch(NORMALS[1]), 0)
    w, h = rect.size
    rng = np.random.default_rng(2)
    q = np.stack(np.nonzero(rect.mask)[::-1], 1)[rng.choice(rect.mask.sum(), 100)] + 0.5
    xy, J = rectified_to_image(cam, rect, q)
    assert np.isfinite(J).all()
    eps = 1e-3
    Jn = np.empty_like(J)
    for j in range(2):
        d = np.zeros(2)
        d[j] = eps
        Jn[:, :, j] = (
            rectified_to_image(cam, rect, q + d)[0] - rectified_to_image(cam, rect, q - d)[0]
        ) / (2 * eps)
    rel = np.abs(Jn - J).max((1, 2)) / np.abs(J).max((1, 2))
    assert rel.max() < 1e-5


@pytest.mark.parametrize("name", list(CAMERAS))
def test_view_jacobian_is_the_product_with_the_cameras(name):
    """d(u)/d(image xy) of a pinhole camera (K^-1 scales Ju's columns) has exactly the
    numbers of the product with K^-1 at every cell; a distorted camera's is the product
    with its undistortion's central differences."""
    from rectified_colmap.rectify import _image_to_ray_jacobian, image_to_view_jacobian

    cam = camera(name)
    rng = np.random.default_rng(3)
    Ju = rng.normal(size=(500, 2, 2)) * 10.0 ** rng.uniform(-3, 1, (500, 1, 1))
    xy = rng.uniform([0, 0], [W, H], (500, 2))
    J = image_to_view_jacobian(cam, Ju, xy)
    if cam_utils.is_pinhole(cam):
        Ki = np.linalg.inv(cam_utils.calibration_matrix(cam))[:2, :2]
        assert np.array_equal(J, Ju @ np.broadcast_to(Ki, (500, 2, 2)))
    else:
        assert np.allclose(J, Ju @ _image_to_ray_jacobian(cam, xy), rtol=0, atol=1e-15)
        assert not np.allclose(
            J, Ju * np.diag(np.linalg.inv(cam_utils.calibration_matrix(cam))[:2, :2])
        )


def test_viewing_angles_are_each_patchs_own_median():
    """A patch's median viewing angle over its cells does not depend on the other patches
    asked with it; a patch without cells gets 0."""
    from rectified_colmap.views import viewing_angles

    cam = camera("PINHOLE")
    rng = np.random.default_rng(4)
    masks = [rng.random((GH, GW)) < q for q in (0.1, 0.5, 1.0, 0.0)]
    patches = [full_patch(NORMALS[i % 3], m) for i, m in enumerate(masks)]
    rays = cam_utils.unit_grid_rays(cam, GW, GH)
    want = [
        np.degrees(np.arccos(np.median(-(rays[p.mask] @ p.normal)))) if p.mask.any() else 0.0
        for p in patches
    ]
    assert np.allclose(viewing_angles(cam, patches), want, rtol=0, atol=1e-9)
    alone = [viewing_angles(cam, [p])[0] for p in patches]
    assert np.array_equal(viewing_angles(cam, patches), alone)
    assert viewing_angles(cam, patches)[3] == 0.0 and want[0] > 10


@pytest.mark.parametrize("rule", VIEW_RESOLUTIONS)
def test_plan_view_resolution_and_caps(rule):
    """finest: the median smaller singular value of d(rectified)/d(image) over the patch is
    1 (nothing shrinks); area: the median product (the patch keeps its pixels); coarsest:
    the median larger one (nothing grows, as ASIFT's tilt simulation)."""
    cam = camera("PINHOLE")
    n = unit(NORMALS[1])  # ground-like, strongly foreshortened
    big = RectifyConf(max_patch_side=10000, border=4, view_resolution=rule)
    rect = plan_rectification(cam, full_patch(n), 3, big)
    assert rect.patch_index == 3 and rect.mask.shape == rect.size[::-1]
    # Median smaller singular value of d(rectified)/d(image) over the patch is 1.
    rows, cols = np.nonzero(np.ones((GH, GW), bool))
    xy = np.stack([(cols + 0.5) * W / GW, (rows + 0.5) * H / GH], 1)
    rays = cam_utils.image_to_rays(cam, xy)
    cos_max = np.cos(np.deg2rad(big.max_viewing_angle_deg))
    xy = xy[-(rays @ n) / np.linalg.norm(rays, axis=1) >= cos_max]
    Hm = image_to_rectified_homography(cam, rect)
    q = np.c_[xy, np.ones(len(xy))] @ Hm.T
    q = q[:, :2] / q[:, 2:]
    _, J = rectified_to_image(cam, rect, q)
    sv = 1.0 / np.linalg.svd(J, compute_uv=False)[:, ::-1]  # (larger, smaller) of the inverse
    assert np.median(sv[:, 0] / sv[:, 1]) > 2  # strongly foreshortened: the rules differ
    median = {
        "finest": np.median(sv[:, 1]),
        "area": np.median(np.sqrt(sv[:, 0] * sv[:, 1])),
        "coarsest": np.median(sv[:, 0]),
    }[rule]
    assert median == pytest.approx(1.0, rel=1e-3)
    # Every patch cell is inside the rectified image, with the border margin.
    assert q.min() >= 4 - 1e-6 and (q.max(0) <= np.array(rect.size) - 4 + 1e-6).all()
    # The side cap, and a scale (the image's pixel budget) on top of it.
    capped = plan_rectification(cam, full_patch(n), 0, replace(big, max_patch_side=100))
    assert max(capped.size) <= 100 and capped.K[0, 0] < rect.K[0, 0]
    half = plan_rectification(cam, full_patch(n), 0, big, scale=0.5)
    assert half.K[0, 0] == pytest.approx(0.5 * rect.K[0, 0])


def test_mask_excludes_grazing_rays_and_none_when_nothing_left():
    cam = camera("PINHOLE")
    n = unit([0.0, -1.0, -0.15])  # ground seen at grazing angles
    conf = RectifyConf(max_viewing_angle_deg=60, max_patch_side=4000)
    rect = plan_rectification(cam, full_patch(n), 0, conf)
    q = np.stack(np.nonzero(rect.mask)[::-1], 1) + 0.5
    xy, _ = rectified_to_image(cam, rect, q)
    rays = cam_utils.image_to_rays(cam, xy)
    cosv = -(rays @ n) / np.linalg.norm(rays, axis=1)
    assert cosv.min() >= np.cos(np.deg2rad(60)) - 1e-9
    # ...while the image has plenty of pixels beyond 60 degrees.
    all_rays = cam_utils.grid_rays(cam, GW, GH).reshape(-1, 3)
    assert (
        -(all_rays @ n) / np.linalg.norm(all_rays, axis=1) < np.cos(np.deg2rad(60))
    ).mean() > 0.2
    # Everything beyond the limit: nothing usable.
    assert plan_rectification(cam, full_patch(n), 0, RectifyConf(max_viewing_angle_deg=20)) is None


def test_mask_excludes_rays_the_distortion_folds_back_into_the_image():
    """Radial distortion with k < 0 is monotonic only up to a radius: rays beyond it fold
    back into the image, so their pixels are not where the ray would be seen. Every masked
    pixel's ray must come back from its image point (the undistortion's principal branch)."""
    cam = camera("SIMPLE_RADIAL")  # r (1 + k r^2) turns back at r = (-3 k)^-1/2 = 2.04
    n = unit([0.0, -1.0, -0.15])  # ground: the rectified view reaches far off the axis
    conf = RectifyConf(max_viewing_angle_deg=89, max_patch_side=1000)
    rect = plan_rectification(cam, full_patch(n), 0, conf)
    from rectified_colmap.rectify import _rectified_pixel_rays

    X = _rectified_pixel_rays(rect)
    m = X[..., :2] / X[..., 2:]
    r = np.linalg.norm(m, axis=-1)
    folded = (X[..., 2] > 0) & (r > 1 / np.sqrt(0.24))
    xy = rays_to_image(cam, X[folded])
    inside = (xy >= 0).all(1) & (xy[:, 0] < W) & (xy[:, 1] < H)
    assert inside.sum() > 100  # the scene has such rays: their pixels lie in the image...
    assert not rect.mask[folded].any()  # ...and the mask excludes them
    q = np.stack(np.nonzero(rect.mask)[::-1], 1) + 0.5
    xy, _ = rectified_to_image(cam, rect, q)
    back = cam_utils.image_to_rays(cam, xy)[:, :2]
    assert np.abs(back - m[rect.mask]).max() * 200.0 < 0.01  # every masked ray, < 0.01 px
    # The rays within the monotonic range and the viewing angle that the image sees stay.
    cos_view = -(X @ n) / np.linalg.norm(X, axis=-1)
    seen = (X[..., 2] > 0) & (r < 2.0) & (cos_view > np.cos(np.deg2rad(89)))
    xy = rays_to_image(cam, X[seen])
    seen[seen] = (xy >= 0).all(1) & (xy[:, 0] < W) & (xy[:, 1] < H)
    assert rect.mask[seen].mean() > 0.98
    out = warp_to_rectified(np.full((H, W), 200, np.uint8), cam, rect)
    assert (out[folded] == 0).all() and (out[rect.mask] > 0).mean() > 0.95


def test_warp_masks_rays_behind_camera():
    cam = camera("PINHOLE")
    n = unit([-1.0, 0.0, -0.05])  # a wall almost parallel to the optical axis
    R = rectifying_rotation(n)
    f = 100.0
    K = np.array([[f, 0, 300.0], [0, f, 150.0], [0, 0, 1]])
    rect = Rectification(R, K, (600, 300), np.ones((300, 600), bool), n, 0)
    from rectified_colmap.rectify import _rectified_mask, _rectified_pixel_rays

    X = _rectified_pixel_rays(rect)
    behind = X[..., 2] <= 0
    assert behind.mean() > 0.1
    rect.mask = _rectified_mask(cam, rect, np.ones((GH, GW), bool), np.cos(np.deg2rad(89.9)))
    assert not (rect.mask & behind).any() and rect.mask.any()
    img = np.full((H, W), 200, np.uint8)
    # Plain warpPerspective mirrors content into the rays behind the camera...
    from rectified_colmap.conventions import to_opencv_homography

    Hcv = to_opencv_homography(image_to_rectified_homography(cam, rect))
    raw = cv2.warpPerspective(img, Hcv, rect.size)
    assert (raw[behind] > 0).any()
    # ...warp_to_rectified does not.
    out = warp_to_rectified(img, cam, rect)
    assert (out[behind] == 0).all() and (out[rect.mask] > 0).mean() > 0.95


@pytest.mark.parametrize("name", list(CAMERAS))
def test_warp_samples_the_right_pixels(name):
    """Bilinear warping of a linear ramp is exact: the rectified value must equal the ramp
    at rectified_to_image of the pixel centre (checks every pixel convention)."""
    cam = camera(name)
    mask = np.zeros((GH, GW), bool)
    mask[10:70, 20:100] = True
    rect = plan_rectification(cam, full_patch(NORMALS[2], mask), 0)
    a, b, c = 0.7, -0.4, 120.0
    ys, xs = np.mgrid[0:H, 0:W].astype(np.float64) + 0.5  # COLMAP centres
    img = (a * xs + b * ys + c).astype(np.float32)
    out = warp_to_rectified(img, cam, rect)
    assert out.shape == rect.mask.shape and (out[~rect.mask] == 0).all()
    # Interior pixels (bilinear support inside the image).
    q = np.stack(np.nonzero(rect.mask)[::-1], 1) + 0.5
    xy, _ = rectified_to_image(cam, rect, q)
    inner = (xy[:, 0] > 1) & (xy[:, 1] > 1) & (xy[:, 0] < W - 1) & (xy[:, 1] < H - 1)
    assert inner.mean() > 0.9
    expect = a * xy[inner, 0] + b * xy[inner, 1] + c
    got = out[rect.mask][inner]
    tol = 1e-3 if cam_utils.is_pinhole(cam) else 0.02  # remap maps are float32
    assert np.abs(got - expect).max() < tol
    # The rectified mask covers the patch: its cells map into the rectified image.
    assert rect.mask.sum() > 0.5 * mask.sum() * (W / GW) * (H / GH) * 0.3


@pytest.mark.parametrize("name", list(CAMERAS))
def test_upsampled_rectification_is_the_same_view_on_a_finer_grid(name):
    """The view at 2x: every pixel of the planned view is 2 x 2 pixels (COLMAP convention:
    planned q is 2 q there), the map back and its Jacobian agree exactly."""
    cam = camera(name)
    rect = plan_rectification(cam, full_patch(NORMALS[1]), 3)
    assert upsampled_rectification(rect, 1) is rect
    up = upsampled_rectification(rect, 2)
    w, h = rect.size
    assert up.size == (2 * w, 2 * h) and up.patch_index == 3
    for dy in (0, 1):
        for dx in (0, 1):
            np.testing.assert_array_equal(up.mask[dy::2, dx::2], rect.mask)
    rng = np.random.default_rng(4)
    q = rng.uniform(0, 1, (100, 2)) * [w, h]
    xy, J = rectified_to_image(cam, rect, q)
    xy2, J2 = rectified_to_image(cam, up, 2 * q)
    ok = np.isfinite(xy).all(1)
    assert ok.mean() > 0.5
    np.testing.assert_allclose(xy2[ok], xy[ok], atol=1e-9)
    np.testing.assert_allclose(2 * J2[ok], J[ok], rtol=1e-9, atol=1e-12)
    if cam_utils.is_pinhole(cam):
        np.testing.assert_allclose(
            image_to_rectified_homography(cam, up),
            np.diag([2.0, 2.0, 1.0]) @ image_to_rectified_homography(cam, rect),
        )


PLANE_K = np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])


def oblique_and_frontal_shots(oblique_deg: float):
    """A textured plane seen 640x480 (f = 500) from ``oblique_deg`` and from 20 degrees off
    its normal: (camera, image 0 (oblique), image 1, H01 image 0 -> 1 (through PLANE_K), the
    plane's normal facing camera 0)."""
    from rectified_colmap_research.synth.planar import look_at, plane_view, textured_image

    tex = textured_image(1200, 1200, 5)
    shots = []
    for deg in (oblique_deg, 20.0):
        a = np.deg2rad(deg)
        R, t = look_at([4.0 * np.sin(a), 0.0, 4.0 * np.cos(a)], [0, 0, 0], up=(0, 1.0, 0))
        shots.append((plane_view(tex, 0.008, PLANE_K, R, t, (640, 480))[0], R, t))
    (img0, R0, t0), (img1, R1, t1) = shots
    H01 = (
        PLANE_K
        @ np.stack([R1[:, 0], R1[:, 1], t1], 1)
        @ np.linalg.inv(np.stack([R0[:, 0], R0[:, 1], t0], 1))
        @ np.linalg.inv(PLANE_K)
    )
    n_true = -R0[:, 2] if R0[2, 2] > 0 else R0[:, 2]
    cam = make_camera("PINHOLE", [500.0, 500.0, 320.0, 240.0], 640, 480)
    return cam, img0, img1, H01, n_true


def gt_consistent_matches(a, b, H01: np.ndarray, px: float = 3.0) -> int:
    """Mutual ratio-test matches of Features a (image 0) and b (image 1) within ``px`` of
    the ground truth H01."""
    from rectified_colmap.eval.matching import match_ratio

    m = match_ratio(a.descriptors.astype(np.float32), b.descriptors.astype(np.float32), 0.8, True)
    X = np.c_[a.keypoints[m[:, 0]], np.ones(len(m))] @ H01.T
    return int((np.linalg.norm(X[:, :2] / X[:, 2:] - b.keypoints[m[:, 1]], axis=1) < px).sum())


def test_warp_upsampling_only_where_sift_would_upsample_the_view():
    from rectified_colmap.config import SiftConf
    from rectified_colmap.sift import warp_upsampling

    conf = SiftConf()
    assert warp_upsampling((400, 300), 2000, -1, conf) == 2  # 60 px / feature: upsampled
    assert warp_upsampling((400, 300), 2000, 0, conf) == 1  # no upsampled octave
    assert warp_upsampling((1000, 1000), 100, -1, conf) == 1  # coarse-first pays there
    assert warp_upsampling((1700, 200), 2000, -1, conf) == 1  # 3400 > max_image_size
    assert warp_upsampling((1600, 200), 2000, -1, conf) == 2


def test_warping_at_the_first_octave_keeps_detail_a_shrunk_view_lost(monkeypatch):
    """A plane 75 degrees from the view, rectified with its true normal, matched to a view
    20 degrees from it (plain SIFT). With the view shrunk by a small pixel budget, warping
    it at SIFT's upsampled octave (sift.warp_upsampling; COLMAP's SIFT) gives more GT-consistent
    matches than SIFT upsampling the shrunk view; with a budget that does not shrink it,
    the two are the same scale space (about the same count)."""
    from rectified_colmap.config import ExtractConf
    from rectified_colmap.geometry import scaled_size
    from rectified_colmap.pipeline import extract_image, features_on_top
    from rectified_colmap.sift import plain_sift, warp_upsampling
    from rectified_colmap.views import plan_views

    cam, img0, img1, H01, n_true = oblique_and_frontal_shots(75.0)
    b = extract_image(img1, cam, None).features  # plain SIFT
    counts = {}
    for factor in (0.25, 2.0):
        for on in (False, True):
            conf = ExtractConf.from_dict(
                {
                    "rectify": {"tilt_steps": 0, "max_view_pixels_factor": factor},
                    "sift": {"patch_backend": "colmap"},
                }
            )
            monkeypatch.setattr(
                sift_module, "warp_upsampling", warp_upsampling if on else lambda *a: 1
            )
            w, h = scaled_size(640, 480, conf.normals.work_max_size)
            patch = Patch(np.ones((h, w), bool), 0, n_true, 1.0)
            pixels = view_pixel_budget(img0.shape, conf)
            views = plan_views(img0, cam, [patch], (h, w), conf.rectify, pixels)
            a = features_on_top(img0, cam, views, plain_sift(img0, conf.sift), conf)
            counts[factor, on] = gt_consistent_matches(a, b, H01)
    assert counts[0.25, True] >= 1.08 * counts[0.25, False], counts  # measured 239 / 197
    assert abs(counts[2.0, True] - counts[2.0, False]) <= 0.1 * counts[2.0, False], counts


def _true_view_matches(conf, pixels: float) -> int:
    """GT-consistent matches of plain SIFT plus the view of a plane 75 degrees from the
    camera, rectified with its true normal within ``pixels`` (asserted to be the conf's
    budget), against plain SIFT of a view 20 degrees from it (``conf`` for both)."""
    from rectified_colmap.geometry import scaled_size
    from rectified_colmap.pipeline import extract_image, features_on_top
    from rectified_colmap.sift import plain_sift
    from rectified_colmap.views import plan_views

    cam, img0, img1, H01, n_true = oblique_and_frontal_shots(75.0)
    b = extract_image(img1, cam, None, conf).features  # plain SIFT
    w, h = scaled_size(640, 480, conf.normals.work_max_size)
    patch = Patch(np.ones((h, w), bool), 0, n_true, 1.0)
    assert view_pixel_budget(img0.shape, conf) == pytest.approx(pixels)
    views = plan_views(img0, cam, [patch], (h, w), conf.rectify, pixels)
    a = features_on_top(img0, cam, views, plain_sift(img0, conf.sift), conf)
    assert (a.patch >= 0).sum() > 300
    return gt_consistent_matches(a, b, H01)


def test_views_through_opencv_sift_match_as_through_colmap_sift(monkeypatch):
    """The views' backend: a plane 75 degrees from the view, rectified with its true normal,
    matched to plain SIFT of a view 20 degrees from it. OpenCV's SIFT in the view
    (sift.patch_backend "opencv") gives about the GT-consistent matches of COLMAP's from
    the same upsampled octave and the same view pixels (within 15 %)."""
    from rectified_colmap.config import ExtractConf

    monkeypatch.setattr(sift_module, "warp_upsampling", lambda *a: 1)  # SIFT upsamples
    counts = {}
    for backend, factor in (("colmap", 2.0), ("opencv", 2.0 / OPENCV_VIEW_PIXELS_RATIO)):
        conf = ExtractConf.from_dict(
            {
                "rectify": {"tilt_steps": 0, "max_view_pixels_factor": factor},
                "sift": {"patch_backend": backend},
            }
        )
        counts[backend] = _true_view_matches(conf, 2.0 * 640 * 480)
    assert counts["colmap"] > 200, counts
    # measured 1378 / 1542: OpenCV finds ~10 % fewer points (docs/architecture.md)
    assert 0.85 * counts["colmap"] <= counts["opencv"] <= 1.15 * counts["colmap"], counts


def test_views_from_octave_0_through_opencv_sift_match_as_through_colmap_sift():
    """Where the views' SIFT starts at octave 0 (here 2000 features on 640x480: 154 pixels
    per feature; 1.2-4 MP images at 8192), OpenCV's SIFT runs them from the halved view
    (sift.opencv_sift): about the GT-consistent matches of COLMAP's from octave 0 at the
    same view pixels (within 15 %), on the scene of the test above."""
    from rectified_colmap.config import ExtractConf
    from rectified_colmap.sift import opencv_views, patch_first_octave

    counts = {}
    for backend in ("colmap", "opencv"):
        sift = {"patch_backend": backend, "max_num_features": 2000}
        conf = ExtractConf.from_dict({"rectify": {"tilt_steps": 0}, "sift": sift})
        assert patch_first_octave((480, 640), 2000, conf.sift) == 0
        assert opencv_views((480, 640), conf.sift) == (backend == "opencv")
        counts[backend] = _true_view_matches(conf, 2.0 * 2000 * 150)  # no ratio from octave 0
    assert counts["colmap"] > 200, counts
    assert 0.85 * counts["colmap"] <= counts["opencv"] <= 1.15 * counts["colmap"], counts


def test_fitting_roll_turns_the_smallest_box_onto_the_axes():
    rng = np.random.default_rng(3)
    strip = rng.uniform([-2.0, -0.3], [2.0, 0.3], (400, 2))
    for deg in (0.0, 10.0, 44.0, 46.0, 89.0, 120.0, -20.0):
        a = np.deg2rad(deg)
        turned = strip @ np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]).T + 5.0
        Rz = fitting_roll(turned)
        np.testing.assert_allclose(Rz @ Rz.T, np.eye(3), atol=1e-12)
        assert Rz[2, 2] == 1.0 and abs(np.linalg.det(Rz) - 1.0) < 1e-12
        box = np.prod(np.ptp(turned @ Rz[:2, :2].T, 0))
        assert box <= np.prod(np.ptp(turned, 0)) + 1e-9
        assert box < 1.03 * np.prod(np.ptp(strip, 0))  # the strip's own box (4 x 0.6)
        assert abs(np.degrees(np.arctan2(Rz[1, 0], Rz[0, 0]))) <= 45.0 + 1e-9
    np.testing.assert_array_equal(fitting_roll(strip[:2]), np.eye(3))


@pytest.mark.parametrize("name", list(CAMERAS))
@pytest.mark.parametrize("turn", [False, True])
def test_view_box_holds_every_kept_cell_with_half_a_cell_each_side(name, turn):
    """The view's extent (lo, hi) is the box of every cell of the patch within the viewing
    angle, widened by the same margin on both sides, for a ragged patch with holes (from
    each row's end cells under a pinhole camera, from all cells under distortion)."""
    cam = camera(name)
    rng = np.random.default_rng(5)
    rows, cols = np.mgrid[0:GH, 0:GW]
    mask = np.zeros((GH, GW), bool)
    for cx, cy, r in rng.uniform([0, 0, 4], [GW, GH, 18], (12, 3)):
        mask |= (cols - cx) ** 2 + (rows - cy) ** 2 < r * r
    mask &= rng.uniform(size=mask.shape) > 0.3  # holes inside every row
    n = unit(NORMALS[0])
    conf = RectifyConf()
    view = patch_view(cam, full_patch(n, mask), conf, turn)
    rays = cam_utils.grid_rays(cam, GW, GH)[mask]
    cos = -(rays @ n) / np.linalg.norm(rays, axis=1)
    rays = rays[cos >= np.cos(np.deg2rad(conf.max_viewing_angle_deg))]
    X = rays @ view.R.T
    u = X[:, :2] / X[:, 2:]
    below, above = u.min(0) - view.lo, view.hi - u.max(0)
    assert (below > 0).all() and (above > 0).all()
    np.testing.assert_allclose(below, above, rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("name", list(CAMERAS))
def test_a_diagonal_patch_gets_a_smaller_view_turned_to_fit(name):
    """A diagonal band of the image: turned to fit, its view has fewer pixels for the same
    content; the virtual camera still looks along the normal and maps back exactly."""
    cam = camera(name)
    rows, cols = np.mgrid[0:GH, 0:GW]
    band = np.abs((rows - GH / 2) - 0.66 * (cols - GW / 2)) < 6
    n = unit(NORMALS[1])
    fit = plan_rectification(cam, full_patch(n, band), 0)
    plain = plan_rectification(cam, full_patch(n, band), 0, turn=False)
    assert fit.size[0] * fit.size[1] < 0.8 * plain.size[0] * plain.size[1]
    np.testing.assert_allclose(fit.R @ -n, [0.0, 0.0, 1.0], atol=1e-12)
    assert fit.mask.sum() > 0.5 * plain.mask.sum() * (np.prod(fit.size) / np.prod(plain.size))
    q = np.stack(np.nonzero(fit.mask)[::-1], 1)[::50] + 0.5
    xy, _ = rectified_to_image(cam, fit, q)
    X = cam_utils.image_to_rays(cam, xy) @ fit.R.T @ fit.K.T
    err = np.abs(X[:, :2] / X[:, 2:] - q).max(1)
    # distorted cameras: a few rays far outside the field fold back into the image through
    # the distortion polynomial (turned or not); every other pixel maps back exactly
    assert (err < 1e-6).mean() > (0.999 if cam_utils.is_pinhole(cam) else 0.97)


def test_upright_sift_keeps_the_views_unturned():
    from rectified_colmap.views import plan_views

    cam = camera("PINHOLE")
    rows, cols = np.mgrid[0:GH, 0:GW]
    band = np.abs((rows - GH / 2) - 0.66 * (cols - GW / 2)) < 6
    gray = (np.random.default_rng(0).uniform(0, 255, (H, W))).astype(np.uint8)
    patch = full_patch(NORMALS[1], band)
    conf = RectifyConf(min_texture=0.0)
    turned = plan_views(gray, cam, [patch], (GH, GW), conf, 1e9).rects[0]
    upright = plan_views(gray, cam, [patch], (GH, GW), conf, 1e9, upright=True).rects[0]
    np.testing.assert_allclose(upright.R, rectifying_rotation(patch.normal), atol=1e-12)
    assert not np.allclose(turned.R, upright.R)


def test_warp_color_and_bad_size():
    cam = camera("PINHOLE")
    rect = plan_rectification(cam, full_patch(NORMALS[0]), 0)
    img = np.random.default_rng(0).integers(0, 255, (H, W, 3), dtype=np.uint8)
    out = warp_to_rectified(img, cam, rect)
    assert out.shape == rect.mask.shape + (3,) and out.dtype == np.uint8
    with pytest.raises(ValueError, match="camera"):
        warp_to_rectified(img[:10], cam, rect)


@pytest.mark.parametrize("name", list(CAMERAS))
def test_tilt_neighbours_scale_the_tilt_exactly(name):
    """Each neighbour's tilt t = 1 / cos(angle between its normal and the patch's mean
    viewing ray) is the patch's times factor**k, k = +-1, +-2, +-3 (those from 1 to 89
    degrees); the
    normals stay in the plane of the normal and the ray (only the tilt changes)."""
    from rectified_colmap.views import tilt_neighbours

    cam = camera(name)
    mask = np.zeros((GH, GW), bool)
    mask[10:50, 30:100] = True
    n = unit([-0.8, 0.15, -0.55])
    rays = cam_utils.grid_rays(cam, GW, GH)[mask]
    v = unit(rays.sum(0))
    t0 = 1.0 / -(n @ v)
    out = tilt_neighbours(cam, full_patch(n, mask), 2.0, 3)
    tilts = sorted(1.0 / -(p.normal @ v) for p in out)
    expect = [t0 * 2.0**k for k in (-3, -2, -1, 1, 2, 3)]
    expect = [e for e in expect if 1 <= e <= 1 / np.cos(np.deg2rad(89))]
    assert len(expect) < 6  # the limits are exercised
    np.testing.assert_allclose(tilts, sorted(expect), rtol=1e-9)
    for p in out:
        assert p.mask is mask and abs(np.linalg.norm(p.normal) - 1) < 1e-12
        assert abs(np.linalg.det(np.stack([p.normal, n, v]))) < 1e-12  # coplanar


def test_only_oblique_plane_hypotheses_get_tilt_neighbours():
    """Only patches of HYPOTHESIS_AXIS (plane hypotheses from pairs of vanishing points,
    whose orientations err most) seen at tilt_bank_min_angle_deg or more get tilt
    neighbours; a depth patch and a frontal hypothesis do not, unless ``bank_depth``, when
    the oblique depth patch gets them too (with its axis), and a blind view never does.
    Neighbours are appended with their indices."""
    from rectified_colmap.views import with_tilt_neighbours

    cam = camera("PINHOLE")
    oblique = unit([-0.8, 0.15, -0.55])  # about 57 degrees from the rays
    depth_patch = full_patch(oblique)
    hyp_patch = Patch(depth_patch.mask, HYPOTHESIS_AXIS, oblique, 1.0)
    frontal = Patch(depth_patch.mask, HYPOTHESIS_AXIS, np.array([0.0, 0.0, -1.0]), 1.0)
    patches = [depth_patch, hyp_patch, frontal]
    out, todo = with_tilt_neighbours(cam, patches, [0, 1, 2], RectifyConf(tilt_steps=1))
    assert out[:3] == patches
    assert todo == list(range(len(out)))
    assert len(out) == 5  # one step each way around the oblique hypothesis (both valid)
    assert all(p.axis == HYPOTHESIS_AXIS and p.mask is hyp_patch.mask for p in out[3:])
    out, todo = with_tilt_neighbours(cam, patches, [0, 2], RectifyConf(tilt_steps=1))
    assert out == patches and todo == [0, 2]  # not in todo: no neighbours
    # bank_depth (where plain SIFT left budget unused): the depth patch gets them too
    out, todo = with_tilt_neighbours(cam, patches, [0, 1, 2], RectifyConf(tilt_steps=1), True)
    assert out[:3] == patches and todo == list(range(len(out))) and len(out) == 7
    assert [p.axis for p in out[3:]] == [0, 0, HYPOTHESIS_AXIS, HYPOTHESIS_AXIS]
    assert all(p.mask is depth_patch.mask for p in out[3:])
    blind = Patch(depth_patch.mask, BLIND_AXIS, oblique, 1.0)
    out, _ = with_tilt_neighbours(cam, [blind], [0], RectifyConf(tilt_steps=1), True)
    assert out == [blind]  # blind views sample orientations already


def test_tilt_bank_recovers_matches_lost_to_an_orientation_error():
    """Two views of a textured plane 80 and 20 degrees from its normal; the oblique view is
    rectified with a normal 12 degrees too frontal (an error the network and vanishing
    points make): few GT-consistent matches from its single view (it stays foreshortened),
    several times more with the tilt bank (its neighbour lands near the true tilt)."""
    from rectified_colmap.config import ExtractConf
    from rectified_colmap.geometry import scaled_size
    from rectified_colmap.pipeline import extract_image, features_on_top
    from rectified_colmap.sift import plain_sift
    from rectified_colmap.views import plan_views

    cam, img0, img1, H01, n_true = oblique_and_frontal_shots(80.0)
    axis = unit(np.cross(n_true, [0, 0, 1.0]))
    e = np.deg2rad(12.0)
    Kx = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    n_err = (np.eye(3) + np.sin(e) * Kx + (1 - np.cos(e)) * Kx @ Kx) @ n_true
    if np.degrees(np.arccos(-n_err[2])) > np.degrees(np.arccos(-n_true[2])):
        n_err = (np.eye(3) - np.sin(e) * Kx + (1 - np.cos(e)) * Kx @ Kx) @ n_true
    counts = []
    for steps in (0, 1):
        conf = ExtractConf.from_dict({"rectify": {"tilt_steps": steps}})
        w, h = scaled_size(640, 480, conf.normals.work_max_size)
        # the erring orientation as a plane hypothesis (a whole-image patch), as the lines give
        hypothesis = Patch(np.ones((h, w), bool), HYPOTHESIS_AXIS, n_err, 1.0)
        pixels = view_pixel_budget(img0.shape, conf)
        views = plan_views(img0, cam, [hypothesis], (h, w), conf.rectify, pixels)
        assert len(views.rects) == 1 + 2 * steps
        a = features_on_top(img0, cam, views, plain_sift(img0, conf.sift), conf)
        b = extract_image(img1, cam, None, conf).features  # plain SIFT
        counts.append(gt_consistent_matches(a, b, H01))
    assert counts[1] >= 3 * max(counts[0], 5), counts


@pytest.mark.parametrize("name", ["PINHOLE", "OPENCV"])
def test_blind_patches_sample_asift_tilts_exactly(name):
    """Blind patches: for each tilt t, normals at exactly arccos(1 / t) from the ray through
    the image centre, tilt directions 72 / t degrees apart over 180 (ASIFT's: an affine
    view of phi and of phi + 180 are the same up to a half turn; 5 for t = 2, 10 for 4),
    whole-grid masks, BLIND_AXIS; the view of one compresses by exactly t at the image
    centre: the image -> view Jacobian there has singular values in the ratio t."""
    from rectified_colmap.planes import BLIND_AXIS
    from rectified_colmap.rectify import finish_rectification
    from rectified_colmap.views import blind_patches, view_of_patch

    cam = camera(name)
    out = blind_patches(cam, (GH, GW), (2.0, 4.0), 72.0)
    assert len(out) == 5 + 10
    c = np.array([[cam.width / 2.0, cam.height / 2.0]])
    v = unit(np.append(cam.cam_from_img(c)[0], 1.0))
    tilts = np.array([1.0 / -(p.normal @ v) for p in out])
    np.testing.assert_allclose(tilts, [2.0] * 5 + [4.0] * 10, rtol=1e-12)
    for group in (out[:5], out[5:]):  # consecutive directions equally spaced about v
        d = [unit(p.normal - (p.normal @ v) * v) for p in group]
        step = np.degrees([np.arccos(np.clip(a @ b, -1, 1)) for a, b in zip(d, d[1:])])
        np.testing.assert_allclose(step, 180.0 / len(group), atol=1e-9)
    assert all(p.axis == BLIND_AXIS and p.mask.shape == (GH, GW) and p.mask.all() for p in out)
    # square pixels, principal point at the centre: the image plane is square to that ray
    pinhole = make_camera("PINHOLE", [200.0, 200.0, W / 2, H / 2], W, H)
    for p, t in zip(blind_patches(pinhole, (GH, GW), (2.0, 4.0), 72.0)[::5], (2.0, 4.0, 4.0)):
        conf = RectifyConf()
        rect = finish_rectification(pinhole, view_of_patch(pinhole, p, conf), 0, conf, 1.0)
        M = image_to_rectified_homography(pinhole, rect)
        s = np.linalg.svd(M[:2, :2] / M[2, 2], compute_uv=False)  # affine: the same everywhere
        assert s[0] / s[1] == pytest.approx(t, rel=1e-9)


@pytest.mark.parametrize("turn", [True, False])
def test_blind_views_simulate_asift_tilts(turn):
    """A blind patch's view is ASIFT's tilt simulation, whatever the conf's resolution
    rule: an affine map of the image (the homography's last row 0 0 1, the same linear part
    everywhere), nothing enlarged (its larger singular value 1 on a square-pixel pinhole)
    and the other 1 / t, compressing across the tilt direction d, not along it; with
    ``turn`` off (upright SIFT) the map is symmetric: the image's axes are kept. A plane
    hypothesis of the same normal is a perspective rectification that stretches (finest)."""
    from rectified_colmap.planes import BLIND_AXIS
    from rectified_colmap.rectify import finish_rectification, patch_view, view_camera
    from rectified_colmap.views import view_of_patch

    cam = make_camera("PINHOLE", [300.0, 300.0, W / 2, H / 2], W, H)
    t = 3.0
    d = unit([0.8, 0.6, 0.0])  # the tilt direction in the image
    n = -np.array([0.0, 0.0, 1.0]) / t + np.sqrt(1 - 1 / t**2) * d
    conf = RectifyConf(view_resolution="finest")
    view = view_of_patch(cam, Patch(np.ones((GH, GW), bool), BLIND_AXIS, n, 1.0), conf, turn)
    rect = finish_rectification(cam, view, 0, conf, 1.0)
    Hv = image_to_rectified_homography(cam, rect)
    np.testing.assert_allclose(Hv[2], [0.0, 0.0, 1.0], atol=1e-12)
    M = Hv[:2, :2]
    np.testing.assert_allclose(np.linalg.svd(M, compute_uv=False), [1.0, 1.0 / t], rtol=1e-9)
    np.testing.assert_allclose(np.linalg.norm(M @ d[:2]), 1.0, rtol=1e-9)  # d is kept
    np.testing.assert_allclose(np.linalg.norm(M @ [-d[1], d[0]]), 1.0 / t, rtol=1e-9)
    if not turn:
        np.testing.assert_allclose(M, M.T, atol=1e-12)
    # the mask is the whole image compressed: its pixels / t (to the border's pixels)
    assert rect.mask.sum() == pytest.approx(W * H / t, rel=0.02)
    hyp = patch_view(cam, Patch(np.ones((GH, GW), bool), HYPOTHESIS_AXIS, n, 1.0), conf)
    hyp_pixels = np.prod(view_camera(hyp, conf, 1.0)[1])
    assert hyp_pixels > t * rect.pixels  # the rectification stretches; the simulation does not


def test_blind_views_match_an_oblique_plane_the_depth_calls_frontal():
    """The oblique shot (75 degrees) with a depth that says the plane is frontal (as the
    network does on many oblique photos) and no lines: no view from the estimates, so the
    image gets blind views (BLIND_AXIS), second tier, where plain SIFT left budget unused;
    GT-consistent matches with the 20-degree shot at least twice plain SIFT's. Where plain
    SIFT fills its budget, or with lookalikes_in_unused_budget off, the output is plain
    SIFT's exactly."""
    from rectified_colmap.config import ExtractConf
    from rectified_colmap.depth import DepthMap
    from rectified_colmap.pipeline import extract_image
    from rectified_colmap.planes import BLIND_AXIS

    cam, img0, img1, H01, _ = oblique_and_frontal_shots(75.0)
    frontal = DepthMap(np.full((480, 640), 5.0, np.float32), "metric")
    no_lines = {"vp": {"enabled": False, "line_hypotheses": 0}}
    conf = ExtractConf.from_dict({**no_lines, "sift": {"max_num_features": 4000}})
    b = extract_image(img1, cam, None, conf).features
    plain = extract_image(img0, cam, None, conf).features
    assert len(plain) < 4000  # part of plain SIFT's budget unused
    res = extract_image(img0, cam, frontal, conf)
    rects = res.rectifications
    assert rects and all(res.planes.patches[r.patch_index].axis == BLIND_AXIS for r in rects)
    kept = res.features.subset(res.features.patch < 0)
    np.testing.assert_array_equal(kept.keypoints, plain.keypoints)
    assert len(res.features) <= conf.sift.max_num_features  # second tier: unused part only
    got, base = gt_consistent_matches(res.features, b, H01), gt_consistent_matches(plain, b, H01)
    assert got >= 2 * max(base, 10), (got, base)  # 30 vs 4 here
    base_conf = {**no_lines, "sift": {"max_num_features": 4000}}
    full = {"sift": {"max_num_features": len(plain)}}
    for off in (full, {"dedup": {"lookalikes_in_unused_budget": False}}):
        c = ExtractConf.from_dict({**base_conf, **off})
        out = extract_image(img0, cam, frontal, c)
        assert not out.rectifications
        np.testing.assert_array_equal(out.features.keypoints, plain.keypoints)


def test_views_that_add_almost_nothing_are_planned_again_with_blind_views(monkeypatch):
    """pipeline.views_and_features: the 75-degree shot's view from its true normal adds many
    rectified features, and the image gets no blind view; a view of a small part of the
    plane adds at most budget.BLIND_YIELD_FRAC x plain SIFT's count (the case of a view of
    a wrong estimate), and the image gets the blind views beside it, their features on top
    of all the others (those kept exactly; within plain SIFT's unused budget), and matches
    the 20-degree shot with more GT-consistent matches than without them. No second tier
    (lookalikes_in_unused_budget off): the views of the estimates alone."""
    from rectified_colmap import budget as budget_module
    from rectified_colmap.config import ExtractConf
    from rectified_colmap.geometry import scaled_size
    from rectified_colmap.pipeline import extract_image, views_and_features
    from rectified_colmap.planes import BLIND_AXIS
    from rectified_colmap.sift import plain_sift

    cam, img0, img1, H01, n_true = oblique_and_frontal_shots(75.0)
    conf = ExtractConf.from_dict({"sift": {"max_num_features": 4000}})
    b = extract_image(img1, cam, None, conf).features
    plain = plain_sift(img0, conf.sift)
    assert len(plain) < 4000  # part of plain SIFT's budget unused
    w, h = scaled_size(640, 480, conf.normals.work_max_size)
    small = np.zeros((h, w), bool)  # 1 / 64 of the image, right of the centre
    small[h * 5 // 12 : h * 13 // 24, w * 5 // 8 : w * 3 // 4] = True

    def run(mask, c):
        views, feats = views_and_features(
            img0, cam, [Patch(mask, 0, n_true, 1.0)], (h, w), plain, c
        )
        blind = {views.patches[r.patch_index].axis == BLIND_AXIS for r in views.rects}
        np.testing.assert_array_equal(feats.subset(feats.patch < 0).keypoints, plain.keypoints)
        return views, feats, blind

    _, whole, blind = run(np.ones((h, w), bool), conf)
    assert blind == {False} and len(whole) - len(plain) > budget_module.BLIND_YIELD_FRAC * len(
        plain
    )
    views, feats, blind = run(small, conf)
    assert blind == {False, True}  # the small view and the blind ones
    second = np.isin(feats.patch, [i for i, p in enumerate(views.patches) if p.axis == BLIND_AXIS])
    assert 0 < second.sum() <= budget_module.unused_room(len(plain), conf)  # second tier
    c = ExtractConf.from_dict({"sift": {"max_num_features": 4000}})
    c.dedup.lookalikes_in_unused_budget = False
    assert run(small, c)[2] == {False}
    # the blind features come on top: the small view's features without them kept as is
    frac = budget_module.BLIND_YIELD_FRAC
    monkeypatch.setattr(budget_module, "BLIND_YIELD_FRAC", -1.0)  # never blind views
    _, alone, blind_off = run(small, conf)
    assert blind_off == {False}
    assert 0 < len(alone) - len(plain) <= frac * len(plain), len(alone) - len(plain)
    np.testing.assert_array_equal(feats.keypoints[: len(alone)], alone.keypoints)
    np.testing.assert_array_equal(feats.descriptors[: len(alone)], alone.descriptors)
    got, base = gt_consistent_matches(feats, b, H01), gt_consistent_matches(alone, b, H01)
    assert got >= 1.5 * max(base, 10), (got, base)  # measured 49 vs 27
    # the switch itself: a yield counted as almost nothing re-plans the whole plane's view
    monkeypatch.setattr(budget_module, "BLIND_YIELD_FRAC", 1e9)
    assert run(np.ones((h, w), bool), conf)[2] == {False, True}


def test_tilt_simulations_are_antialiased():
    """A tilt simulation that compresses the image by 4 is rendered 4 x finer and averaged
    down (rectify.antialias_factor): a sinusoid of 0.3 cycles per pixel across the compressed
    direction, beyond the view's Nyquist limit, is damped to a faint ripple (as ASIFT's blur
    before subsampling damps it), where plain bilinear sampling every 4 pixels aliases it
    to a wave of nearly its full amplitude; a perspective rectification keeps plain
    sampling (factor 1)."""
    from rectified_colmap.conventions import to_opencv_homography
    from rectified_colmap.planes import BLIND_AXIS
    from rectified_colmap.rectify import antialias_factor, finish_rectification, warp_to_rectified
    from rectified_colmap.views import view_of_patch

    cam = make_camera("PINHOLE", [300.0, 300.0, W / 2, H / 2], W, H)
    t = 4.0
    n = -np.array([0.0, 0.0, 1.0]) / t + np.sqrt(1 - 1 / t**2) * np.array([0.0, 1.0, 0.0])
    conf = RectifyConf()
    patch = Patch(np.ones((GH, GW), bool), BLIND_AXIS, n, 1.0)
    rect = finish_rectification(cam, view_of_patch(cam, patch, conf, False), 0, conf, 1.0)
    assert antialias_factor(cam, rect) == 4  # compressed by t along the image's x
    x = np.arange(W) + 0.5
    wave = np.tile(127.5 + 100 * np.sin(2 * np.pi * 0.3 * x), (H, 1)).astype(np.float32)
    inner = cv2.erode(rect.mask.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
    view = warp_to_rectified(wave, cam, rect)[inner]
    Hv = to_opencv_homography(image_to_rectified_homography(cam, rect))
    plain = cv2.warpPerspective(wave, Hv, rect.size, flags=cv2.INTER_LINEAR)[inner]
    assert abs(view.mean() - 127.5) < 3 and view.std() < 15, (view.mean(), view.std())
    assert plain.std() > 30, plain.std()  # aliased
    hyp = plan_rectification(cam, Patch(np.ones((GH, GW), bool), HYPOTHESIS_AXIS, n, 1.0), 0)
    assert antialias_factor(cam, hyp) == 1
