"""Procedural street scenes of textured planar quads with exact depth, normals and poses:
the renderer of the demo wing (``rectified_colmap.demo``) with what training, tests and
benchmarks add (random training samples here; ``lines``: line drawings of a street for the
vanishing-point tests; ``planar``: one textured plane seen by a pinhole camera).

World frame: metres, z up, ground z = 0. Cameras: pycolmap PINHOLE / SIMPLE_PINHOLE (COLMAP
pixel convention); poses: ``cam_from_world`` pycolmap.Rigid3d (camera x right, y down,
z forward).

How to use::

    import numpy as np
    from rectified_colmap_research import synth

    rng = np.random.default_rng(0)
    scene = synth.street(rng)                      # also corner(), square(), rubble()
    camera = synth.pinhole_camera(640, 480, focal=500)
    pose = synth.random_view(scene, rng, camera)   # or synth.look_at(eye, target)
    r = synth.render(scene, camera, pose)          # supersample=2
    r.image    # (H, W, 3) uint8 RGB
    r.depth    # (H, W) float32 z-depth, NaN = sky
    r.normals  # (H, W, 3) float32 camera frame, unit, toward the camera, NaN = sky
    r.plane_id # (H, W) int32 quad index, -1 = sky

    # two views 50-90 deg apart looking at one facade point, and their GT
    p0, p1, X = synth.view_pair(scene, rng, 50, 90, target="facade", camera=camera)
    r0, r1 = synth.render(scene, camera, p0), synth.render(scene, camera, p1)
    T_0to1 = synth.relative_T(p0, p1)              # 4x4, camera 0 -> camera 1
    synth.covisible_fraction(r0, r1)               # pixels of view 0 seen by view 1

    poses = synth.view_orbit(scene, 8)             # an SfM walk along the street
    s = synth.random_sample(rng, 256, 192)         # training: random scene, camera, view

Photos can replace procedural facade textures: ``street(rng, texture_dir=folder)``.
"""

from __future__ import annotations

import numpy as np

from rectified_colmap.demo.render import RenderResult, cast, raycast, render
from rectified_colmap.demo.scene import KIND_NAMES, Scene, corner, rubble, square, street
from rectified_colmap.demo.textures import make_texture
from rectified_colmap.demo.views import (
    angle_between_views,
    backproject,
    camera_center,
    covisible,
    covisible_fraction,
    look_at,
    pinhole_camera,
    pitched,
    random_camera,
    random_view,
    relative_pose,
    relative_T,
    reproject,
    view_orbit,
    view_pair,
    viewing_direction,
)


def random_scene(
    rng: np.random.Generator,
    texture_dir=None,
    probs=(0.7, 0.15, 0.15),
    texel: float = 0.025,
    tree_prob: float = 0.0,
    cloud_prob: float = 0.0,
) -> Scene:
    """street / corner / square with probabilities ``probs``; with trees with probability
    ``tree_prob``, and clouds (cover 0.2-0.9) with probability ``cloud_prob`` (for 0 no
    random number is drawn, so seeded scenes are unchanged)."""
    k = int(rng.choice(3, p=np.asarray(probs) / np.sum(probs)))
    trees = bool(tree_prob > 0 and rng.random() < tree_prob)
    scene = (street, corner, square)[k](rng, texture_dir=texture_dir, texel=texel, trees=trees)
    if cloud_prob > 0 and rng.random() < cloud_prob:
        scene.clouds = float(rng.uniform(0.2, 0.9))
    return scene


def random_sample(
    rng: np.random.Generator,
    width: int = 256,
    height: int = 192,
    texture_dir=None,
    supersample: int = 2,
    focal_range=(0.6, 1.4),
    noise: float = 0.0,
    tree_prob: float = 0.0,
    cloud_prob: float = 0.0,
) -> RenderResult:
    """A training view: random scene (with trees and clouds with probabilities
    ``tree_prob`` and ``cloud_prob``), random
    camera (focal ``focal_range`` x width), random view (see :func:`random_view`). The
    camera and pose are in the result. Textures have about the resolution of a pixel 10 m
    away (10 / width metres per texel, 2.5-6 cm)."""
    texel = float(np.clip(10.0 / width, 0.025, 0.06))
    scene = random_scene(rng, texture_dir, texel=texel, tree_prob=tree_prob, cloud_prob=cloud_prob)
    camera = random_camera(rng, width, height, focal_range)
    pose = random_view(scene, rng, camera)
    return render(scene, camera, pose, supersample, noise, int(rng.integers(1 << 31)))


__all__ = [
    "RenderResult",
    "Scene",
    "KIND_NAMES",
    "angle_between_views",
    "backproject",
    "camera_center",
    "cast",
    "corner",
    "covisible",
    "covisible_fraction",
    "look_at",
    "make_texture",
    "pinhole_camera",
    "pitched",
    "random_camera",
    "random_sample",
    "random_scene",
    "random_view",
    "raycast",
    "relative_T",
    "relative_pose",
    "render",
    "reproject",
    "rubble",
    "square",
    "street",
    "view_orbit",
    "view_pair",
    "viewing_direction",
]
