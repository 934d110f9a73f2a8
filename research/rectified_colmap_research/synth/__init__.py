"""Procedural street scenes of textured planar quads with exact depth, normals and poses:
the renderer of the demo wing (``rectified_colmap.demo``: street scenes, textures, render,
cameras and the walk along a street) with what training, tests and benchmarks add to it:
``scenes`` (corner, square and rubble scenes, random training samples), ``views`` (random
views, view pairs, ground truth between views), ``lines`` (line drawings of a street for the
vanishing-point tests) and ``planar`` (one textured plane seen by a pinhole camera). Every
name below is re-exported here, wherever it lives.

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

from rectified_colmap.demo.render import RenderResult, cast, render
from rectified_colmap.demo.scene import KIND_NAMES, Scene
from rectified_colmap.demo.street import street
from rectified_colmap.demo.textures import make_texture
from rectified_colmap.demo.views import look_at, pinhole_camera, pitched, view_orbit

from .scenes import corner, random_sample, random_scene, rubble, square
from .views import (
    angle_between_views,
    backproject,
    camera_center,
    covisible,
    covisible_fraction,
    random_camera,
    random_view,
    raycast,
    relative_pose,
    relative_T,
    reproject,
    view_pair,
    viewing_direction,
)

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
