"""Procedural textures for the synthetic scenes, by name (:data:`GENERATORS`,
:func:`make_texture`).

Every generator is ``f(rng, height, width, ppm) -> (height, width, 3) float32 RGB in [0, 1]``
where ``ppm`` is texels per metre (so sizes of bricks, windows, ... are physical). Row 0 is
the *top* of a wall texture. Textures are rich in non-repetitive detail at several scales:
jittered bricks/stones/cobbles, window grids with per-window variation, stains, posters and
text; nothing is purely periodic. All randomness comes from ``rng``.

Optional photos (e.g. facades) are loaded with :func:`load_photos` and cropped/resized with
:func:`photo_texture` (``photos``). The generators are in ``materials`` (walls, ground,
roofs, clutter, rubble, foliage, bark) and ``facade`` (building fronts); what they are made
of (noise, colours, grain, stains, text, posters, wall marks) is in ``blocks``.
"""

from __future__ import annotations

import functools

import numpy as np

from .facade import facade
from .materials import (
    asphalt,
    bark,
    bricks,
    clutter,
    cobbles,
    foliage,
    paving,
    plaster,
    roof,
    rubble,
    stone,
)
from .photos import load_photos, photo_texture

GENERATORS = {
    "foliage": foliage,
    "bark": bark,
    "facade": facade,
    "plaster": plaster,
    "bricks": bricks,
    "stone": stone,
    "cobbles": cobbles,
    "asphalt": asphalt,
    "paving": paving,
    "roof": roof,
    "clutter": clutter,
    "rubble": rubble,
    "road": functools.partial(asphalt, markings=True),
}


def make_texture(
    kind: str, seed: int, height: int, width: int, ppm: float, photo: np.ndarray | None = None
) -> np.ndarray:
    """A texture (height, width, 3) float32 in [0, 1], deterministic from ``seed``."""
    if kind not in GENERATORS:
        raise ValueError(f"unknown texture kind {kind!r} (known: {sorted(GENERATORS)})")
    rng = np.random.default_rng(seed)
    if photo is not None:
        return photo_texture(photo, rng, height, width)
    return np.ascontiguousarray(GENERATORS[kind](rng, height, width, ppm), np.float32)


__all__ = ["GENERATORS", "load_photos", "make_texture", "photo_texture"]
