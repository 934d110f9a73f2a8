"""Random views, view pairs and ground truth between views of the demo wing's scenes
(rectified_colmap.demo), for training, tests and benchmarks.

Poses are ``cam_from_world`` pycolmap.Rigid3d (camera x right, y down, z forward; world z
up). Cameras are pycolmap PINHOLE cameras in the COLMAP pixel convention. Pinhole cameras,
look-at poses and the walk along a street are rectified_colmap.demo.views.
"""

from __future__ import annotations

import logging

import numpy as np
import pycolmap

from rectified_colmap.demo.render import RenderResult, pinhole_K
from rectified_colmap.demo.scene import FACADE, GROUND, UP, WALL, Scene
from rectified_colmap.demo.views import coarse_render, coverage, look_at, pinhole_camera

logger = logging.getLogger(__name__)

TARGET_KINDS = {"facade": (FACADE, WALL), "ground": (GROUND,), "any": None}


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


def camera_center(cam_from_world: pycolmap.Rigid3d) -> np.ndarray:
    m = np.asarray(cam_from_world.matrix())
    return -m[:, :3].T @ m[:, 3]


def viewing_direction(cam_from_world: pycolmap.Rigid3d) -> np.ndarray:
    """World direction of the optical axis."""
    return np.asarray(cam_from_world.matrix())[2, :3].copy()


def raycast(scene: Scene, origins: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Nearest hits of world rays (P, 3) origins and directions: ray parameter t (P,)
    (inf: none; in units of |dir|) and quad id (P,) (-1)."""
    origins = np.asarray(origins, float).reshape(-1, 3)
    dirs = np.asarray(dirs, float).reshape(-1, 3)
    nrm = np.cross(scene.eu, scene.ev)
    best = np.full(len(dirs), np.inf)
    ids = np.full(len(dirs), -1, np.int32)
    with np.errstate(divide="ignore", invalid="ignore"):
        den = dirs @ nrm.T  # (P, N)
        rel = scene.origin[None] - origins[:, None]  # (P, N, 3)
        tt = np.einsum("pnk,nk->pn", rel, nrm) / den
        hit = origins[:, None] + tt[..., None] * dirs[:, None] - scene.origin[None]
        u = np.einsum("pnk,nk->pn", hit, scene.eu)
        v = np.einsum("pnk,nk->pn", hit, scene.ev)
        ok = (tt > 1e-6) & (u >= 0) & (u <= scene.size[:, 0]) & (v >= 0) & (v <= scene.size[:, 1])
    tt = np.where(ok, tt, np.inf)
    if tt.shape[1]:
        ids = np.argmin(tt, 1).astype(np.int32)
        best = tt[np.arange(len(dirs)), ids]
        ids[~np.isfinite(best)] = -1
    return best, ids


def visible(scene: Scene, eyes: np.ndarray, point: np.ndarray, tol: float = 0.02) -> np.ndarray:
    """(P,) bool: the segment eye -> point is not blocked (the first hit is the point)."""
    eyes = np.asarray(eyes, float).reshape(-1, 3)
    out = np.zeros(len(eyes), bool)
    for s in range(0, len(eyes), 256):
        e = eyes[s : s + 256]
        t, _ = raycast(scene, e, point - e)
        out[s : s + 256] = t > 1 - tol
    return out


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
        cov, dmin = coverage(scene, camera, pose)
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
        eyes, d = _candidate_eyes(scene, rng, X, n, dist_range, height_range, max_incidence_deg)
        if len(eyes) < 2:
            continue
        pick = _pick_pair(rng, eyes, d, X, (cos_lo, cos_hi), max_scale_ratio)
        if pick is None:
            continue
        poses = [_aim(eyes[k], X, camera, rng, jitter_px) for k in pick]
        if min_covisible > 0:
            r0, r1 = (coarse_render(scene, camera, p) for p in poses)
            if (
                min(covisible_fraction(r0, r1, 0.05), covisible_fraction(r1, r0, 0.05))
                < min_covisible
            ):
                continue
        return poses[0], poses[1], X
    raise RuntimeError(f"view_pair: no pair found in scene {scene.name} for target {target}")


def _candidate_eyes(
    scene: Scene, rng, X, n, dist_range, height_range, max_incidence_deg: float
) -> tuple[np.ndarray, np.ndarray]:
    """Candidate camera centres on the outward side of the plane through ``X`` with unit
    normal ``n``, within ``max_incidence_deg`` of it, ``dist_range`` away and in
    ``height_range``, in free space; when at least two are left, only those that see ``X``.
    Returns (eyes (P, 3), unit directions from X to them (P, 3))."""
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
        return eyes, d
    ok = visible(scene, eyes, X)
    return eyes[ok], d[ok]


def _pick_pair(rng, eyes, d, X, cos_range, max_scale_ratio: float) -> tuple[int, int] | None:
    """A random candidate ``i`` and a random partner ``j`` whose direction to ``X`` has a
    cosine with ``i``'s in ``cos_range`` (lo, hi) and whose distance to ``X`` is within a
    factor ``max_scale_ratio`` of ``i``'s; None when ``i`` has no partner."""
    cos_lo, cos_hi = cos_range
    i = int(rng.integers(len(eyes)))
    c = d @ d[i]
    dist = np.linalg.norm(eyes - X, axis=1)
    ratio = dist / dist[i]
    js = np.flatnonzero(
        (c >= cos_lo) & (c <= cos_hi) & (ratio < max_scale_ratio) & (ratio > 1 / max_scale_ratio)
    )
    if len(js) == 0:
        return None
    return i, int(rng.choice(js))


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
