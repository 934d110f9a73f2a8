"""Cameras and poses for the demo's scenes: pinhole cameras, look-at poses, the walk along a
street (:func:`view_orbit`, :func:`pitched`) and the coarse renders that check its views.

Poses are ``cam_from_world`` pycolmap.Rigid3d (camera x right, y down, z forward; world z
up). Cameras are pycolmap PINHOLE cameras in the COLMAP pixel convention. Random views,
view pairs and ground truth between views (training, tests): rectified_colmap_research.synth.
"""

from __future__ import annotations

import logging

import numpy as np
import pycolmap

from .render import RenderResult, cast, pinhole_K
from .scene import UP, Scene

logger = logging.getLogger(__name__)


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


def coverage(
    scene: Scene, camera: pycolmap.Camera, pose: pycolmap.Rigid3d, size: int = 40
) -> tuple[float, float]:
    """(fraction of pixels hitting a surface, min depth) on a coarse grid."""
    r = coarse_render(scene, camera, pose, size)
    hit = r.plane_id >= 0
    return float(hit.mean()), float(np.nanmin(r.depth)) if hit.any() else np.inf


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
        cov = [coverage(scene, camera, p) for p in poses]
        if all(c >= 0.8 and d >= min_depth for c, d in cov):
            return poses
    raise RuntimeError(f"view_orbit: no free walk found in scene {scene.name}")


def pitched(cam_from_world: pycolmap.Rigid3d, down_deg: float) -> pycolmap.Rigid3d:
    """The same camera tilted down by ``down_deg`` about its own x axis (y is down)."""
    a = np.deg2rad(down_deg)
    tilt = np.array([[1.0, 0.0, 0.0], [0.0, np.cos(a), -np.sin(a)], [0.0, np.sin(a), np.cos(a)]])
    return pycolmap.Rigid3d(pycolmap.Rotation3d(tilt), np.zeros(3)) * cam_from_world
