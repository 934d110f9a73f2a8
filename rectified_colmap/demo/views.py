"""Cameras and poses for synthetic scenes, and ground-truth helpers.

Poses are ``cam_from_world`` pycolmap.Rigid3d (camera x right, y down, z forward; world z
up). Cameras are pycolmap PINHOLE cameras in the COLMAP pixel convention.
"""

from __future__ import annotations

import logging

import numpy as np
import pycolmap

from .render import RenderResult, cast, pinhole_K, raycast
from .scene import FACADE, GROUND, UP, WALL, Scene

logger = logging.getLogger(__name__)

TARGET_KINDS = {"facade": (FACADE, WALL), "ground": (GROUND,), "any": None}


def pinhole_camera(
    width: int,
    height: int,
    focal: float | None = None,
    cx: float | None = None,
    cy: float | None = None,
) -> pycolmap.Camera:
    """PINHOLE camera; default focal 1.0 x width, principal point at the image centre."""
    f = float(focal if focal is not None else width)
    return pycolmap.Camera(
        model="PINHOLE",
        width=int(width),
        height=int(height),
        params=[f, f, width / 2.0 if cx is None else cx, height / 2.0 if cy is None else cy],
    )


def random_camera(
    rng: np.random.Generator,
    width: int,
    height: int,
    focal_range=(0.6, 1.4),
    pp_jitter: float = 0.02,
) -> pycolmap.Camera:
    """PINHOLE camera, focal uniform in ``focal_range`` x width, jittered principal point."""
    f = rng.uniform(*focal_range) * width
    return pinhole_camera(
        width,
        height,
        f,
        width / 2 + rng.normal(0, pp_jitter * width),
        height / 2 + rng.normal(0, pp_jitter * height),
    )


def rigid(R_cam_from_world: np.ndarray, t: np.ndarray) -> pycolmap.Rigid3d:
    return pycolmap.Rigid3d(
        pycolmap.Rotation3d(np.asarray(R_cam_from_world, float)), np.asarray(t, float).reshape(3)
    )


def look_at(eye, target, up=UP, roll_deg: float = 0.0) -> pycolmap.Rigid3d:
    """cam_from_world of a camera at ``eye`` looking at ``target`` (image y down = -up),
    rotated by ``roll_deg`` about its optical axis."""
    eye, target, up = (np.asarray(x, float) for x in (eye, target, up))
    z = target - eye
    if np.linalg.norm(z) < 1e-9:
        raise ValueError("look_at: eye and target coincide")
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-6:  # looking straight up/down: any right vector
        x = np.cross(z, [1.0, 0, 0]) if abs(z[0]) < 0.9 else np.cross(z, [0, 1.0, 0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])  # rows: camera axes in world = cam_from_world rotation
    if roll_deg:
        a = np.deg2rad(roll_deg)
        Rz = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
        R = Rz @ R
    return rigid(R, -R @ eye)


def camera_center(cam_from_world: pycolmap.Rigid3d) -> np.ndarray:
    m = np.asarray(cam_from_world.matrix())
    return -m[:, :3].T @ m[:, 3]


def viewing_direction(cam_from_world: pycolmap.Rigid3d) -> np.ndarray:
    """World direction of the optical axis."""
    return np.asarray(cam_from_world.matrix())[2, :3].copy()


def visible(scene: Scene, eyes: np.ndarray, point: np.ndarray, tol: float = 0.02) -> np.ndarray:
    """(P,) bool: the segment eye -> point is not blocked (the first hit is the point)."""
    eyes = np.asarray(eyes, float).reshape(-1, 3)
    out = np.zeros(len(eyes), bool)
    for s in range(0, len(eyes), 256):
        e = eyes[s : s + 256]
        t, _ = raycast(scene, e, point - e)
        out[s : s + 256] = t > 1 - tol
    return out


def coarse_render(
    scene: Scene, camera: pycolmap.Camera, pose: pycolmap.Rigid3d, size: int = 48
) -> RenderResult:
    """Geometry only (no image) on a grid of max side ``size`` covering the same view."""
    K = pinhole_K(camera)
    s = size / max(camera.width, camera.height)
    W, H = max(4, int(round(camera.width * s))), max(3, int(round(camera.height * s)))
    Ks = K.copy()
    Ks[0] *= W / camera.width
    Ks[1] *= H / camera.height
    m = np.asarray(pose.matrix())
    d, q = cast(scene, Ks, m[:, :3], m[:, 3], W, H)
    small = pinhole_camera(W, H, Ks[0, 0], Ks[0, 2], Ks[1, 2])
    small.params = [Ks[0, 0], Ks[1, 1], Ks[0, 2], Ks[1, 2]]
    depth = np.where(q >= 0, d, np.nan).astype(np.float32)
    return RenderResult(None, depth, None, q, small, pose)


def _coverage(
    scene: Scene, camera: pycolmap.Camera, pose: pycolmap.Rigid3d, size: int = 40
) -> tuple[float, float]:
    """(fraction of pixels hitting a surface, min depth) on a coarse grid."""
    r = coarse_render(scene, camera, pose, size)
    hit = r.plane_id >= 0
    return float(hit.mean()), float(np.nanmin(r.depth)) if hit.any() else np.inf


def random_view(
    scene: Scene,
    rng: np.random.Generator,
    camera: pycolmap.Camera | None = None,
    height_range=(1.2, 10.0),
    max_roll_deg: float = 10.0,
    max_pitch_jitter_deg: float = 10.0,
    min_coverage: float = 0.6,
    min_depth: float = 1.0,
    tries: int = 60,
) -> pycolmap.Rigid3d:
    """A random pose in the scene's free space looking at a random visible surface point
    (or along a street), pitch jittered, roll up to ``max_roll_deg``; retried until at
    least ``min_coverage`` of the view hits a surface and nothing is nearer than
    ``min_depth`` (coverage checked with ``camera``, default f = width 640x480)."""
    camera = camera or pinhole_camera(640, 480)
    best, best_cov = None, -1.0
    lo, hi = scene.free_lo.copy(), scene.free_hi.copy()
    lo[2], hi[2] = max(lo[2], height_range[0]), min(hi[2], height_range[1])
    for _ in range(tries):
        eye = lo + rng.random(3) * (hi - lo)
        if rng.random() < 0.6:  # low cameras are more common
            eye[2] = lo[2] + (hi[2] - lo[2]) * rng.random() ** 3
        if not scene.in_free_space(eye[None])[0]:
            continue
        if scene.name == "street" and rng.random() < 0.3:  # along the street
            ahead = rng.choice([-1.0, 1.0]) * rng.uniform(15, 40)
            target = eye + np.array([rng.uniform(-3, 3), ahead, rng.uniform(-2, 4)])
        else:
            pts, _ = scene.sample_points(rng, 16, min_area=min(1.0, scene.area.max()))
            dist = np.linalg.norm(pts - eye, axis=1)
            cand = [
                p for p, dd in zip(pts, dist) if 2.0 < dd < 60.0 and visible(scene, eye[None], p)[0]
            ]
            if not cand:
                continue
            target = cand[0]
        # pitch jitter: move the target vertically by the jitter angle
        dist = np.linalg.norm(target - eye)
        target = target + UP * dist * np.tan(np.deg2rad(rng.uniform(-1, 1) * max_pitch_jitter_deg))
        pose = look_at(eye, target, roll_deg=rng.uniform(-1, 1) * max_roll_deg)
        cov, dmin = _coverage(scene, camera, pose)
        if cov >= min_coverage and dmin >= min_depth:
            return pose
        if dmin >= min_depth and cov > best_cov:
            best, best_cov = pose, cov
    if best is None:
        raise RuntimeError(f"random_view: no valid view found in scene {scene.name}")
    logger.debug("random_view: best coverage %.2f < %.2f", best_cov, min_coverage)
    return best


def view_pair(
    scene: Scene,
    rng: np.random.Generator,
    min_angle_deg: float = 50.0,
    max_angle_deg: float = 90.0,
    target: str = "facade",
    dist_range=(4.0, 16.0),
    height_range=(1.2, 10.0),
    max_incidence_deg: float = 80.0,
    jitter_px: float = 0.15,
    max_scale_ratio: float = 1.5,
    max_point_height: float = 8.0,
    min_covisible: float = 0.2,
    camera: pycolmap.Camera | None = None,
    tries: int = 60,
) -> tuple[pycolmap.Rigid3d, pycolmap.Rigid3d, np.ndarray]:
    """Two poses looking at one 3D point on a quad of kind ``target`` from the same side
    of its plane, with the angle between the two viewing directions to the point in
    [min_angle_deg, max_angle_deg], both with the point unoccluded and in view (it is
    placed within ``jitter_px`` x image size of the centre) and their distances to it
    within a factor ``max_scale_ratio``; the point at most ``max_point_height`` above the
    ground; each view seeing at least ``min_covisible`` of the other's surface pixels
    (checked on coarse renders). Returns (pose0, pose1, point).
    """
    if target not in TARGET_KINDS:
        raise ValueError(f"view_pair: target must be one of {sorted(TARGET_KINDS)}")
    camera = camera or pinhole_camera(640, 480)
    kinds = TARGET_KINDS[target]
    cos_lo, cos_hi = np.cos(np.deg2rad(max_angle_deg)), np.cos(np.deg2rad(min_angle_deg))
    for _ in range(tries):
        pts, q = scene.sample_points(rng, 1, kinds=kinds, min_area=4.0, border=1.0)
        X, n = pts[0], scene.normal[q[0]]
        if X[2] > max_point_height:
            continue
        # candidate eyes on the outward side of the plane
        m = 3000
        d = rng.normal(size=(m, 3))
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        d *= np.sign(d @ n)[:, None]
        d = d[d @ n > np.cos(np.deg2rad(max_incidence_deg))]
        eyes = X + d * rng.uniform(*dist_range, (len(d), 1))
        ok = (eyes[:, 2] >= height_range[0]) & (eyes[:, 2] <= height_range[1])
        eyes, d = eyes[ok], d[ok]
        ok = scene.in_free_space(eyes)
        eyes, d = eyes[ok], d[ok]
        if len(eyes) < 2:
            continue
        ok = visible(scene, eyes, X)
        eyes, d = eyes[ok], d[ok]
        if len(eyes) < 2:
            continue
        i = int(rng.integers(len(eyes)))
        c = d @ d[i]
        dist = np.linalg.norm(eyes - X, axis=1)
        ratio = dist / dist[i]
        js = np.flatnonzero(
            (c >= cos_lo)
            & (c <= cos_hi)
            & (ratio < max_scale_ratio)
            & (ratio > 1 / max_scale_ratio)
        )
        if len(js) == 0:
            continue
        j = int(rng.choice(js))
        poses = [_aim(e, X, camera, rng, jitter_px) for e in (eyes[i], eyes[j])]
        if min_covisible > 0:
            r0, r1 = (coarse_render(scene, camera, p) for p in poses)
            if (
                min(covisible_fraction(r0, r1, 0.05), covisible_fraction(r1, r0, 0.05))
                < min_covisible
            ):
                continue
        return poses[0], poses[1], X
    raise RuntimeError(f"view_pair: no pair found in scene {scene.name} for target {target}")


def _aim(eye, X, camera, rng, jitter_px, max_roll_deg: float = 5.0) -> pycolmap.Rigid3d:
    """Look at X, then shift the aim so that X lands within jitter_px * size of the centre."""
    K = pinhole_K(camera)
    off = rng.uniform(-1, 1, 2) * jitter_px * np.array([camera.width, camera.height])
    base = look_at(eye, X, roll_deg=rng.uniform(-1, 1) * max_roll_deg)
    R = np.asarray(base.matrix())[:, :3]
    # a ray at pixel offset -off in the base camera becomes the new optical axis
    ray = np.array([-off[0] / K[0, 0], -off[1] / K[1, 1], 1.0])
    new_target = eye + R.T @ ray
    return look_at(eye, new_target, up=R.T @ np.array([0, -1.0, 0]))


def view_orbit(
    scene: Scene,
    n: int = 8,
    rng: np.random.Generator | None = None,
    step: float = 1.2,
    height: float = 1.7,
    yaw_deg=(25.0, 55.0),
    camera: pycolmap.Camera | None = None,
    min_depth: float = 2.0,
    tries: int = 50,
) -> list[pycolmap.Rigid3d]:
    """A walk along a street (or along one side of a corner/square scene): ``n`` poses
    ``step`` metres apart in free space, looking obliquely (``yaw_deg`` off the walking
    direction) at the facades of one side, nothing nearer than ``min_depth``."""
    rng = rng or np.random.default_rng(0)
    camera = camera or pinhole_camera(640, 480)
    lo, hi = scene.free_lo, scene.free_hi
    for _ in range(tries):
        if scene.name == "street":
            w, L = scene.meta["width"], scene.meta["length"]
            side = rng.choice([-1.0, 1.0]) if scene.meta.get("two_sided", True) else -1.0
            x = -side * w * rng.uniform(0.1, 0.3)
            y0 = rng.uniform(0.1, 0.9) * L - 0.5 * step * (n - 1)
            start, along, toward = (
                np.array([x, y0, height]),
                np.array([0, 1.0, 0]),
                np.array([side, 0, 0.0]),
            )
        else:  # walk parallel to the x = lo side, looking at it
            start = np.array(
                [lo[0] + rng.uniform(0.4, 0.7) * (hi[0] - lo[0]), rng.uniform(lo[1], hi[1]), height]
            )
            along, toward = np.array([0, 1.0, 0]) * rng.choice([-1.0, 1.0]), np.array([-1.0, 0, 0])
        eyes = start + along * step * np.arange(n)[:, None]
        if not scene.in_free_space(eyes, margin=0.5).all():
            continue
        yaw0 = np.deg2rad(rng.uniform(*yaw_deg))
        poses = []
        for i, eye in enumerate(eyes):
            yaw = yaw0 + np.deg2rad(10.0) * (i / max(n - 1, 1) - 0.5)
            fwd = np.cos(yaw) * toward + np.sin(yaw) * along
            poses.append(look_at(eye, eye + fwd + UP * 0.1))
        cov = [_coverage(scene, camera, p) for p in poses]
        if all(c >= 0.8 and d >= min_depth for c, d in cov):
            return poses
    raise RuntimeError(f"view_orbit: no free walk found in scene {scene.name}")


# -- ground truth ----------------------------------------------------------------------------


def relative_pose(pose0: pycolmap.Rigid3d, pose1: pycolmap.Rigid3d) -> pycolmap.Rigid3d:
    """cam1_from_cam0."""
    return pose1 * pose0.inverse()


def relative_T(pose0: pycolmap.Rigid3d, pose1: pycolmap.Rigid3d) -> np.ndarray:
    """4x4 T_0to1 (maps camera-0 points to camera 1), the SuperGlue pair convention."""
    T = np.eye(4)
    T[:3] = np.asarray(relative_pose(pose0, pose1).matrix())
    return T


def angle_between_views(pose0, pose1, point) -> float:
    """Angle (degrees) between the directions from the two camera centres to ``point``."""
    a = np.asarray(point) - camera_center(pose0)
    b = np.asarray(point) - camera_center(pose1)
    c = a @ b / np.linalg.norm(a) / np.linalg.norm(b)
    return float(np.degrees(np.arccos(np.clip(c, -1, 1))))


def backproject(depth: np.ndarray, camera: pycolmap.Camera) -> np.ndarray:
    """(H, W) z-depth -> (H, W, 3) camera-frame points at the pixel centres (NaN stays)."""
    K = pinhole_K(camera)
    H, W = depth.shape
    x = (np.arange(W) + 0.5 - K[0, 2]) / K[0, 0]
    y = (np.arange(H) + 0.5 - K[1, 2]) / K[1, 1]
    xx, yy = np.meshgrid(x, y)
    return np.stack([xx, yy, np.ones_like(xx)], -1) * depth[..., None]


def reproject(
    r0: RenderResult, camera1: pycolmap.Camera, pose1: pycolmap.Rigid3d
) -> tuple[np.ndarray, np.ndarray]:
    """Pixels of view 0 (with their depths) seen by camera 1: COLMAP pixel coordinates
    (H, W, 2) and z-depth in camera 1 (H, W); NaN where view 0 has no depth."""
    X0 = backproject(r0.depth.astype(np.float64), r0.camera)
    T = np.asarray(relative_pose(r0.cam_from_world, pose1).matrix())
    X1 = X0 @ T[:, :3].T + T[:, 3]
    K1 = pinhole_K(camera1)
    with np.errstate(divide="ignore", invalid="ignore"):
        xy = X1[..., :2] / X1[..., 2:]
    xy = xy * np.diag(K1)[:2] + K1[:2, 2]
    z = X1[..., 2]
    xy[~(z > 0)] = np.nan
    return xy, z


def covisible(r0: RenderResult, r1: RenderResult, rel_tol: float = 0.01) -> np.ndarray:
    """(H0, W0) bool: pixels of view 0 that view 1 sees (in its image and not occluded:
    the depth view 1 renders there agrees with the reprojected depth to ``rel_tol``)."""
    xy, z = reproject(r0, r1.camera, r1.cam_from_world)
    H1, W1 = r1.depth.shape
    with np.errstate(invalid="ignore"):
        j = np.floor(xy[..., 0])
        i = np.floor(xy[..., 1])
        inside = (j >= 0) & (j < W1) & (i >= 0) & (i < H1) & (z > 0)
    ji = np.where(inside, j, 0).astype(np.int64)
    ii = np.where(inside, i, 0).astype(np.int64)
    d1 = r1.depth[ii, ji].astype(np.float64)
    with np.errstate(invalid="ignore"):
        # nearest-pixel depth: allow the depth change across half a pixel on oblique planes
        ok = inside & np.isfinite(d1) & (np.abs(d1 - z) <= rel_tol * z + 0.0)
    return ok


def covisible_fraction(r0: RenderResult, r1: RenderResult, rel_tol: float = 0.01) -> float:
    """Fraction of the valid pixels of view 0 that view 1 sees (see :func:`covisible`)."""
    valid = np.isfinite(r0.depth)
    if not valid.any():
        return 0.0
    return float(covisible(r0, r1, rel_tol)[valid].mean())


def pitched(cam_from_world: pycolmap.Rigid3d, down_deg: float) -> pycolmap.Rigid3d:
    """The same camera tilted down by ``down_deg`` about its own x axis (y is down)."""
    a = np.deg2rad(down_deg)
    tilt = np.array([[1.0, 0.0, 0.0], [0.0, np.cos(a), -np.sin(a)], [0.0, np.sin(a), np.cos(a)]])
    return pycolmap.Rigid3d(pycolmap.Rotation3d(tilt), np.zeros(3)) * cam_from_world
