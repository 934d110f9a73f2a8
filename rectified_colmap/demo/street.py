"""The demo's street: a canyon of facade rows (setbacks, gaps, balconies, relief), clutter
boxes and, opt-in (so that seeded scenes without them stay as they were), trees of many
small leaf quads, the commonest non-planar thing in real street photos; built with
:class:`~rectified_colmap.demo.scene.SceneBuilder`.

World frame: metres, **z up**, the ground is z = 0, the street along +y (see
rectified_colmap.demo.scene). The helpers (:func:`add_facade_row`, :func:`add_clutter`,
:func:`add_trees`) also build the corner and square scenes of
rectified_colmap_research.synth.scenes. All deterministic from a numpy Generator.
"""

from __future__ import annotations

import numpy as np

from .scene import (
    CLUTTER,
    FACADE,
    RELIEF,
    ROOF,
    UP,
    VEGETATION,
    WALL,
    Scene,
    SceneBuilder,
    texture_photos,
)


def add_facade_row(
    b: SceneBuilder,
    rng,
    start,
    along,
    inward,
    length: float,
    setback_prob: float = 0.4,
    gap_prob: float = 0.1,
    relief_prob: float = 0.5,
    height=(6.0, 25.0),
) -> None:
    """Buildings along ``along`` from ``start`` over ``length`` metres, fronts facing
    ``inward`` (horizontal unit vectors), with setbacks, gaps, balconies and relief."""
    start, along, inward = (np.asarray(x, float) for x in (start, along, inward))
    s = 0.0
    while s < length - 1.0:
        w = min(rng.uniform(6.0, 22.0), length - s)
        if rng.random() < gap_prob and s > 0:
            s += rng.uniform(2.0, 6.0)
            continue
        setback = rng.uniform(0.5, 4.0) if rng.random() < setback_prob else 0.0
        depth = rng.uniform(8.0, 14.0)
        hgt = rng.uniform(*height)
        front0 = start + along * s - inward * setback
        ids = b.box(
            front0 - inward * depth,
            along * w,
            inward * depth,
            hgt,
            kinds=(WALL, FACADE, WALL, WALL, ROOF),
            textures=("plaster", "facade", "plaster", "plaster", "roof"),
        )
        # the front (edge along +along at the inward side) is wall index 1 or 2 depending
        # on the box orientation: relabel by normal
        for i in ids[:4]:
            front = np.dot(b.q["normal"][i], inward) > 0.99
            b.q["kind"][i] = FACADE if front else WALL
            if front and b.textures[b.q["tex"][i]].kind != "facade":
                su, sv = b.q["size"][i]
                t = b.texture("facade", su, sv)
                b.q["tex"][i], b.q["texel"][i] = t
        if rng.random() < relief_prob:  # balconies / relief boxes on the front
            _add_relief(b, rng, front0, along, inward, w, hgt)
        s += w


def _add_relief(b: SceneBuilder, rng, front0, along, inward, w: float, hgt: float) -> None:
    """1-6 balconies / relief boxes on the front of a building ``w`` wide and ``hgt`` high
    whose front starts at ``front0``, at floor heights, sticking out toward ``inward``."""
    floor_h = rng.uniform(2.8, 3.8)
    for _ in range(int(rng.integers(1, 7))):
        bw = rng.uniform(1.2, min(4.0, w - 0.5)) if w > 1.8 else w * 0.6
        a0 = rng.uniform(0.2, max(0.25, w - bw - 0.2))
        z0 = floor_h * int(rng.integers(1, max(2, int(hgt / floor_h))))
        if z0 + 1.2 > hgt:
            continue
        d = rng.uniform(0.3, 1.3)
        bh = rng.uniform(0.25, 1.1)
        corner = front0 + along * a0 + UP * z0
        b.box(
            corner,
            along * bw,
            inward * d,
            bh,
            kinds=(RELIEF,) * 5,
            textures=("plaster", "stone", "plaster", "stone", "plaster"),
        )


def add_clutter(b: SceneBuilder, rng, lo, hi, n: int) -> None:
    """``n`` boxes (kiosks, containers, vans) on the ground in the xy rectangle lo..hi."""
    for _ in range(n):
        yaw = rng.uniform(0, np.pi) if rng.random() < 0.5 else rng.choice([0, np.pi / 2])
        L, W, H = rng.uniform(1.0, 4.5), rng.uniform(0.8, 2.2), rng.uniform(0.8, 2.6)
        e1 = np.array([np.cos(yaw), np.sin(yaw), 0.0]) * L
        e2 = np.array([-np.sin(yaw), np.cos(yaw), 0.0]) * W
        c = np.array([rng.uniform(lo[0], hi[0]), rng.uniform(lo[1], hi[1]), 0.0])
        b.box(c - (e1 + e2) / 2, e1, e2, H, kinds=(CLUTTER,) * 5, textures=("clutter",) * 5)


def add_trees(b: SceneBuilder, rng, lo, hi, n: int, leaves=(150, 320)) -> None:
    """``n`` trees in the xy rectangle lo..hi: a trunk (a thin box) and a crown of many
    small randomly oriented leaf-cluster quads in an ellipsoid (no dominant plane, like
    rubble), sharing a few foliage textures. Each tree is a camera blocker."""
    foliage = [b.texture("foliage", 12.0, 12.0, texel=0.02, max_tex=512) for _ in range(3)]
    bark = b.texture("bark", 1.0, 8.0, texel=0.02, max_tex=512)
    for _ in range(n):
        c = np.array([rng.uniform(lo[0], hi[0]), rng.uniform(lo[1], hi[1]), 0.0])
        trunk_h = rng.uniform(1.8, 4.0)
        tw = rng.uniform(0.2, 0.5)
        b.box(
            c - [tw / 2, tw / 2, 0],
            [tw, 0, 0],
            [0, tw, 0],
            trunk_h + 0.5,
            kinds=(VEGETATION,) * 5,
            textures=(bark,) * 5,
            blocker=False,
        )
        rx, rz = rng.uniform(1.5, 3.5), rng.uniform(1.5, 4.0)
        centre = c + UP * (trunk_h + rz * 0.8)
        t = foliage[int(rng.integers(len(foliage)))]
        for _ in range(int(rng.integers(*leaves))):
            p = rng.normal(size=3)
            p = p / np.linalg.norm(p) * rng.random() ** (1 / 3) * np.array([rx, rx, rz])
            R = np.linalg.qr(rng.normal(size=(3, 3)))[0]
            su, sv = rng.uniform(0.3, 0.9, 2)
            b.quad(
                centre + p - R[:, 0] * su / 2 - R[:, 1] * sv / 2,
                R[:, 0] * su,
                R[:, 1] * sv,
                R[:, 2],
                VEGETATION,
                t,
                albedo=rng.uniform(0.6, 1.1),
                tex_offset=rng.uniform(0, 400, 2),
            )
        r = rx + 0.5
        b.blockers.append(
            np.stack([c - [r, r, 0], [2 * r, 0, 0], [0, 2 * r, 0], UP * (trunk_h + 2 * rz)])
        )


def street(
    rng: np.random.Generator,
    texture_dir=None,
    photo_prob: float = 0.5,
    length: float | None = None,
    two_sided: bool | None = None,
    texel: float = 0.025,
    trees: bool = False,
) -> Scene:
    """A street canyon along +y: ground (road + sidewalks, tiles), facades on one or both
    sides facing each other (setbacks, gaps, balconies), clutter boxes, sky behind; with
    ``trees``, 2-8 trees on the sidewalks."""
    seed = int(rng.integers(1 << 31))
    b = SceneBuilder(rng, texel=texel, photos=texture_photos(texture_dir), photo_prob=photo_prob)
    L = length or rng.uniform(50.0, 90.0)
    w = rng.uniform(9.0, 22.0)
    sw = rng.uniform(1.5, 3.5)
    two = (rng.random() < 0.8) if two_sided is None else two_sided
    far = 60.0 if not two else 8.0  # the open side: ground far toward the horizon
    b.ground(-w / 2 + sw, w / 2 - sw, -10, L + 10, "road", tile=rng.uniform(8, 14))
    b.ground(-w / 2 - 6, -w / 2 + sw, -10, L + 10, "paving", tile=10.0)
    b.ground(
        w / 2 - sw,
        w / 2 + far,
        -10,
        L + 10,
        "paving" if two else "cobbles",
        tile=10.0 if two else 15.0,
    )
    add_facade_row(b, rng, [-w / 2, L, 0], [0, -1, 0], [1, 0, 0], L)
    if two:
        add_facade_row(b, rng, [w / 2, 0, 0], [0, 1, 0], [-1, 0, 0], L)
    if rng.random() < 0.5:  # a building closing the street
        b.box(
            [-w / 2 - 6, L + 10, 0],
            [w + 12, 0, 0],
            [0, 10, 0],
            rng.uniform(8, 25),
            kinds=(FACADE, WALL, WALL, WALL, ROOF),
            textures=("facade", "plaster", "plaster", "plaster", "roof"),
        )
    add_clutter(b, rng, [-w / 2 + 0.5, 2], [w / 2 - 0.5, L - 2], int(rng.integers(2, 9)))
    if trees:
        side = [(-w / 2 + 0.3, -w / 2 + sw - 0.2), (w / 2 - sw + 0.2, w / 2 - 0.3)]
        for k in range(int(rng.integers(2, 9))):
            x0, x1 = side[k % 2 if two else 0]
            add_trees(b, rng, [x0, 2], [max(x0, x1), L - 2], 1)
    return b.finish(
        "street",
        seed,
        [-w / 2 + 0.8, 0.0, 1.2],
        [w / 2 - 0.8, L, 10.0],
        {"width": w, "length": L, "two_sided": two, "sidewalk": sw},
    )
