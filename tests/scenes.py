"""Rendered street views with exact depth and poses for the pipeline tests (synth)."""

from __future__ import annotations

import numpy as np
import pycolmap

from rectified_colmap_research import synth
from rectified_colmap.eval.pairs import Pair


SINGLE_VIEW = {"vp": {"enabled": False, "line_hypotheses": 0}, "rectify": {"tilt_steps": 0}}
"""Conf overrides for one rectified view per depth patch: no lines (no orientation from
vanishing points, no plane hypotheses, so no blind views for planes the lines do not
confirm: budget.blind_share), no tilt neighbours (tests of one view's geometry and
budget)."""


def _view(scene, camera, pose):
    r = synth.render(scene, camera, pose)
    return {"image": r.image, "depth": r.depth, "camera": camera, "pose": pose}


def street_pair(
    seed: int,
    min_deg: float = 50,
    max_deg: float = 90,
    width: int = 480,
    height: int = 360,
    target: str = "facade",
):
    """Two views of one street point (on a facade or the ground) whose viewing directions
    are min_deg-max_deg apart."""
    rng = np.random.default_rng(seed)
    scene = synth.street(rng)
    camera = synth.pinhole_camera(width, height, 0.9 * width)
    p0, p1, _ = synth.view_pair(scene, rng, min_deg, max_deg, target=target, camera=camera)
    return _view(scene, camera, p0), _view(scene, camera, p1)


def street_orbit(
    seed: int, num: int = 6, width: int = 480, height: int = 360, pitch_down_deg: float = 12.0
):
    """A walk along a street (an SfM sequence), pitched down so that the ground is in view
    beside the facades (a single plane is a degenerate scene for SfM initialisation)."""
    rng = np.random.default_rng(seed)
    scene = synth.street(rng)
    camera = synth.pinhole_camera(width, height, 0.7 * width)
    poses = synth.view_orbit(scene, num, rng, camera=camera)
    return [_view(scene, camera, synth.pitched(p, pitch_down_deg)) for p in poses]


def dominant_fraction(normals_world: np.ndarray, max_angle_deg: float = 15.0) -> float:
    """Largest fraction of normals within max_angle of one direction (or its antipode)."""
    n = normals_world / np.linalg.norm(normals_world, axis=1, keepdims=True)
    cands = n[np.random.default_rng(0).choice(len(n), 200)]
    c = np.abs(n @ cands.T) > np.cos(np.deg2rad(max_angle_deg))
    return float(c.mean(0).max())


def to_pair(view0, view1, name0: str = "0", name1: str = "1") -> Pair:
    K0 = view0["camera"].calibration_matrix()
    K1 = view1["camera"].calibration_matrix()
    return Pair(name0, name1, K0, K1, synth.relative_T(view0["pose"], view1["pose"]))


def plane_depth(n: np.ndarray, K: np.ndarray, h: int, w: int) -> np.ndarray:
    """(h, w) z-depth of the plane n . X = -1 (n unit, toward the camera) seen with K, pixel
    centres in the COLMAP convention."""
    jj, ii = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    rays = np.stack([(jj - K[0, 2]) / K[0, 0], (ii - K[1, 2]) / K[1, 1], np.ones_like(jj)], -1)
    return -1.0 / (rays @ n)


def street_views_folder(folder, seed: int, width: int, height: int, focal: float, n: int = 2):
    """``n`` random views of one street written as ``folder/images/<i>.png`` with a
    pycolmap Reconstruction holding their camera and poses (not written: the caller adds
    what it needs and writes it) -> (reconstruction, {name: render}, rng)."""
    import cv2
    import pycolmap

    rng = np.random.default_rng(seed)
    scene = synth.street(rng)
    camera = synth.pinhole_camera(width, height, focal)
    camera.camera_id = 1
    rec = pycolmap.Reconstruction()
    rec.add_camera_with_trivial_rig(camera)
    (folder / "images").mkdir(parents=True)
    renders = {}
    for i in range(n):
        pose = synth.random_view(scene, rng, camera)
        r = synth.render(scene, camera, pose)
        name = f"{i}.png"
        cv2.imwrite(str(folder / "images" / name), r.image[..., ::-1])
        renders[name] = r
    return rec, renders, rng


# -- a synthetic SfM model: cameras on a ring around the origin -------------------------


def ring_camera(azimuth_deg: float, radius: float = 10.0) -> pycolmap.Rigid3d:
    """cam_from_world of a camera on a circle in the x-z plane looking at the origin."""
    a = np.radians(azimuth_deg)
    c = radius * np.array([np.sin(a), 0.0, -np.cos(a)])
    z = -c / np.linalg.norm(c)
    y = np.array([0.0, 1.0, 0.0])
    R = np.stack([np.cross(y, z), y, z])
    return pycolmap.Rigid3d(pycolmap.Rotation3d(R), -R @ c)


def ring_reconstruction(azimuths, tracks, points) -> pycolmap.Reconstruction:
    """A model of PINHOLE cameras on a ring (``ring_camera``) at ``azimuths`` (degrees) and
    3D ``points`` seen by the cameras of their ``tracks`` (lists of camera indices)."""
    rec = pycolmap.Reconstruction()
    cam = pycolmap.Camera(model="PINHOLE", width=640, height=480, params=[500, 500, 320, 240])
    cam.camera_id = 1
    rec.add_camera_with_trivial_rig(cam)
    n_obs = [sum(k in t for t in tracks) for k in range(len(azimuths))]
    for k, az in enumerate(azimuths):
        im = pycolmap.Image(
            name=f"im{k}.jpg",
            camera_id=1,
            image_id=k + 1,
            points2D=[pycolmap.Point2D(np.array([320.0, 240.0])) for _ in range(n_obs[k])],
        )
        rec.add_image_with_trivial_frame(im, ring_camera(az))
    used = [0] * len(azimuths)
    for xyz, t in zip(points, tracks):
        track = pycolmap.Track()
        for k in t:
            track.add_element(k + 1, used[k])
            used[k] += 1
        rec.add_point3D(xyz, track)
    return rec
