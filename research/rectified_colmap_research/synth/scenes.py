"""Scene layouts and random training samples beyond the demo's street: a corner, a square and
a heap of rubble built with the demo wing's scene builder (rectified_colmap.demo.scene), and
random scenes, cameras and views for training (:func:`random_sample`).

World frame: metres, **z up**, the ground is z = 0 (see rectified_colmap.demo.scene). Like
the street, corner and square take ``trees`` (opt-in, so that seeded scenes without it stay
as they were).
"""

from __future__ import annotations

import numpy as np

from rectified_colmap.demo.render import RenderResult, render
from rectified_colmap.demo.scene import RUBBLE, Scene, SceneBuilder, texture_photos
from rectified_colmap.demo.street import add_clutter, add_facade_row, add_trees, street

from .views import random_camera, random_view


def corner(
    rng: np.random.Generator,
    texture_dir=None,
    photo_prob: float = 0.5,
    texel: float = 0.025,
    trees: bool = False,
) -> Scene:
    """Two orthogonal rows of facades (along +x at y = 0 facing +y, along +y at x = 0
    facing +x) and the ground in front of them; with ``trees``, 1-5 trees."""
    seed = int(rng.integers(1 << 31))
    b = SceneBuilder(rng, texel=texel, photos=texture_photos(texture_dir), photo_prob=photo_prob)
    L = rng.uniform(25.0, 45.0)
    b.ground(-5, L + 40, -5, L + 40, rng.choice(["cobbles", "paving", "asphalt"]), tile=15.0)
    add_facade_row(b, rng, [0, 0, 0], [1, 0, 0], [0, 1, 0], L, setback_prob=0.25)
    add_facade_row(b, rng, [0, L, 0], [0, -1, 0], [1, 0, 0], L, setback_prob=0.25)
    add_clutter(b, rng, [3, 3], [L * 0.8, L * 0.8], int(rng.integers(1, 6)))
    if trees:
        add_trees(b, rng, [4, 4], [L, L], int(rng.integers(1, 6)))
    return b.finish("corner", seed, [2.0, 2.0, 1.2], [L, L, 10.0], {"length": L})


def square(
    rng: np.random.Generator,
    texture_dir=None,
    photo_prob: float = 0.5,
    texel: float = 0.025,
    trees: bool = False,
) -> Scene:
    """A rectangular square closed by facades on all four sides (facing inward); with
    ``trees``, 1-6 trees."""
    seed = int(rng.integers(1 << 31))
    b = SceneBuilder(rng, texel=texel, photos=texture_photos(texture_dir), photo_prob=photo_prob)
    W, D = rng.uniform(20, 45), rng.uniform(20, 45)
    b.ground(-5, W + 5, -5, D + 5, rng.choice(["cobbles", "paving", "asphalt"]), tile=12.0)
    add_facade_row(b, rng, [0, 0, 0], [1, 0, 0], [0, 1, 0], W, setback_prob=0.2)
    add_facade_row(b, rng, [W, 0, 0], [0, 1, 0], [-1, 0, 0], D, setback_prob=0.2)
    add_facade_row(b, rng, [W, D, 0], [-1, 0, 0], [0, -1, 0], W, setback_prob=0.2)
    add_facade_row(b, rng, [0, D, 0], [0, -1, 0], [1, 0, 0], D, setback_prob=0.2)
    add_clutter(b, rng, [3, 3], [W - 3, D - 3], int(rng.integers(2, 8)))
    if trees:
        add_trees(b, rng, [4, 4], [W - 4, D - 4], int(rng.integers(1, 7)))
    return b.finish(
        "square", seed, [1.5, 1.5, 1.2], [W - 1.5, D - 1.5, 10.0], {"width": W, "depth": D}
    )


def rubble(
    rng: np.random.Generator, num: int = 900, radius: float = 6.0, size=(0.25, 0.9)
) -> Scene:
    """A heap of ``num`` small randomly oriented textured quads (no dominant planes, no
    ground) in a ball of ``radius`` metres around (0, 0, radius); cameras stand outside."""
    seed = int(rng.integers(1 << 31))
    b = SceneBuilder(rng)
    shared = [b.texture("rubble", 20.0, 20.0, texel=0.02, max_tex=512) for _ in range(8)]
    c = np.array([0.0, 0.0, radius])
    for _ in range(num):
        p = rng.normal(size=3)
        p = c + p / np.linalg.norm(p) * radius * rng.random() ** (1 / 3)
        R = np.linalg.qr(rng.normal(size=(3, 3)))[0]
        su, sv = rng.uniform(*size, 2)
        t = shared[int(rng.integers(len(shared)))]
        off = rng.uniform(0, 400, 2)
        b.quad(
            p - R[:, 0] * su / 2 - R[:, 1] * sv / 2,
            R[:, 0] * su,
            R[:, 1] * sv,
            R[:, 2],
            RUBBLE,
            t,
            tex_offset=off,
        )
    b.blockers.append(
        np.stack([c - radius, [2 * radius, 0, 0], [0, 2 * radius, 0], [0, 0, 2 * radius]])
    )
    r = 2.0 * radius
    return b.finish("rubble", seed, [-r, -r, 0.5], [r, r, 2 * radius + 4], {"radius": radius})


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
