"""Building fronts: a wall material with floors of windows (each different), a ground floor
of shop windows and signs, posters and graffiti near the ground (see
rectified_colmap.demo.textures for the conventions).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from .blocks import decorate, draw_text, grain, posters, random_colour, value_noise
from .materials import bricks, plaster, stone
from .photos import photo_texture


@dataclass(frozen=True)
class _Windows:
    """The window grid of a facade, in texels: floor height, column spacing, window width
    and height, frame width and colour, the base colour of the glass."""

    floor_h: float
    spacing: float
    width: float
    height: float
    frame: int
    frame_col: np.ndarray
    glass: np.ndarray


def facade(rng, h, w, ppm, photo: np.ndarray | None = None) -> np.ndarray:
    """A building front: wall material, floors of windows (each different), a ground floor
    with shop windows and signs, posters and graffiti near the ground. Row 0 = roof line."""
    if photo is not None:
        return photo_texture(photo, rng, h, w)
    wall = [plaster, bricks, stone][int(rng.choice(3, p=[0.4, 0.35, 0.25]))](rng, h, w, ppm)
    img = np.ascontiguousarray(wall, np.float32)
    decorate(img, rng, ppm, rng.uniform(0.1, 0.35))
    floor_h = rng.uniform(2.8, 3.8) * ppm
    ground_h = rng.uniform(3.2, 4.8) * ppm
    spacing = rng.uniform(2.0, 4.5) * ppm
    win_w = rng.uniform(0.35, 0.65) * spacing
    win_h = rng.uniform(0.4, 0.65) * floor_h
    frame = max(1, int(rng.uniform(0.04, 0.12) * ppm))
    frame_col = random_colour(rng, 0.05, 0.95, 0.2)
    glass_base = random_colour(rng, 0.1, 0.5, 0.3) * np.array([0.8, 0.9, 1.1], np.float32)
    windows = _Windows(floor_h, spacing, win_w, win_h, frame, frame_col, glass_base)
    y_ground = h - ground_h
    glass = np.zeros((h, w), np.uint8)  # where reflections and interiors are added
    _floors(img, glass, rng, ppm, y_ground, windows)
    _shop_fronts(img, glass, rng, ppm, y_ground, glass_base)
    # reflections (sky, opposite buildings) and interiors: multi-scale detail on the glass
    refl = value_noise(rng, h, w, rng.uniform(0.5, 2.0) * ppm, 5)
    refl = (np.float32(0.5) + np.float32(1.2) * refl)[..., None]
    img = np.where(glass[..., None] > 0, img * refl, img).astype(np.float32)
    posters(img, rng, ppm, h - 2.5 * ppm, h, density=rng.uniform(0.05, 0.3))
    img = img * grain(rng, h, w, ppm, 0.12, 2.0)
    return np.clip(img, 0, 1).astype(np.float32)


def _floors(img, glass, rng, ppm, y_ground: float, win: _Windows) -> None:
    """Floors of windows above the ground floor (whose top is row ``y_ground``), a cornice
    under some, a few windows missing, each window different; in place (``glass``: 1 where
    a window's glass is)."""
    w = img.shape[1]
    n_cols = int(w / win.spacing)
    margin = (w - n_cols * win.spacing) / 2
    n_floors = int((y_ground - 0.3 * win.floor_h) / win.floor_h)
    for f in range(n_floors):
        y1 = y_ground - f * win.floor_h - 0.25 * win.floor_h
        y0 = y1 - win.height * rng.uniform(0.97, 1.03)
        if rng.random() < 0.4:  # cornice / floor band
            yb = int(y_ground - f * win.floor_h)
            cv2.rectangle(
                img,
                (0, yb - max(1, int(0.1 * ppm))),
                (w, yb),
                tuple(map(float, np.clip(win.frame_col * rng.uniform(0.7, 1.2), 0, 1))),
                -1,
            )
        for c in range(n_cols):
            if rng.random() < 0.04:
                continue  # a missing window
            cx = margin + (c + 0.5) * win.spacing + rng.normal(0, 0.01 * ppm)
            _window(img, glass, rng, ppm, cx, y0, y1, win)


def _window(img, glass, rng, ppm, cx: float, y0: float, y1: float, win: _Windows) -> None:
    """One window centred on column ``cx`` from row ``y0`` to ``y1``: frame and glass, what
    is behind it (:func:`_behind_glass`), maybe a mullion and a sill; in place."""
    frame, frame_col = win.frame, win.frame_col
    x0, x1 = int(cx - win.width / 2), int(cx + win.width / 2)
    g = np.clip(win.glass * rng.uniform(0.5, 1.8) + rng.normal(0, 0.04, 3), 0, 1)
    cv2.rectangle(
        img,
        (x0 - frame, int(y0) - frame),
        (x1 + frame, int(y1) + frame),
        tuple(map(float, frame_col)),
        -1,
    )
    cv2.rectangle(img, (x0, int(y0)), (x1, int(y1)), tuple(map(float, g)), -1)
    cv2.rectangle(glass, (x0, int(y0)), (x1, int(y1)), 1, -1)
    _behind_glass(img, rng, ppm, x0, x1, y0, y1, g)
    if rng.random() < 0.6:  # mullion / cross
        cv2.line(
            img,
            (int(cx), int(y0)),
            (int(cx), int(y1)),
            tuple(map(float, frame_col)),
            max(1, frame // 2),
        )
    if rng.random() < 0.3:  # sill
        cv2.rectangle(
            img,
            (x0 - 2 * frame, int(y1) + frame),
            (x1 + 2 * frame, int(y1) + 3 * frame),
            tuple(map(float, random_colour(rng, 0.5, 0.95, 0.1))),
            -1,
        )


def _behind_glass(img, rng, ppm, x0: int, x1: int, y0: float, y1: float, g) -> None:
    """A curtain, half-closed shutters, a reflection or nothing on the glass (colour ``g``)
    of the window [x0, x1] x [y0, y1]; in place."""
    r = rng.random()
    if r < 0.35:  # curtain
        cw = int(rng.uniform(0.2, 0.6) * (x1 - x0))
        cv2.rectangle(
            img,
            (x0, int(y0)),
            (x0 + cw, int(y1)),
            tuple(map(float, random_colour(rng, 0.4, 0.95, 0.4))),
            -1,
        )
    elif r < 0.55:  # shutters half-closed: horizontal slats
        yc = int(y0 + rng.uniform(0.2, 0.9) * (y1 - y0))
        cv2.rectangle(
            img,
            (x0, int(y0)),
            (x1, yc),
            tuple(map(float, random_colour(rng, 0.2, 0.8, 0.5))),
            -1,
        )
    elif r < 0.7:  # reflection
        p1 = (int(rng.uniform(x0, x1)), int(y0))
        p2 = (int(rng.uniform(x0, x1)), int(y1))
        cv2.line(
            img,
            p1,
            p2,
            tuple(map(float, np.clip(g + 0.3, 0, 1))),
            max(1, int(0.05 * ppm)),
            cv2.LINE_AA,
        )


def _shop_fronts(img, glass, rng, ppm, y_ground: float, glass_base) -> None:
    """The ground floor below row ``y_ground``: shop windows (display items behind them),
    doors, signs with text; in place (``glass``: 1 where a shop window is)."""
    h, w = img.shape[:2]
    x = rng.uniform(0, 1) * ppm
    while x < w:
        sw = rng.uniform(1.2, 4.5) * ppm
        if rng.random() < 0.7:
            top = y_ground + rng.uniform(0.5, 1.0) * ppm
            g = np.clip(glass_base * rng.uniform(0.4, 1.6), 0, 1)
            cv2.rectangle(
                img, (int(x), int(top)), (int(x + sw), h - int(0.3 * ppm)), tuple(map(float, g)), -1
            )
            cv2.rectangle(glass, (int(x), int(top)), (int(x + sw), h - int(0.3 * ppm)), 1, -1)
            for _ in range(int(rng.integers(0, 4))):  # shop display items
                cx, cy = rng.uniform(x, x + sw), rng.uniform(top, h)
                cv2.circle(
                    img,
                    (int(cx), int(cy)),
                    int(rng.uniform(0.05, 0.3) * ppm) + 1,
                    tuple(map(float, random_colour(rng, 0, 1, 1))),
                    -1,
                    cv2.LINE_AA,
                )
            if rng.random() < 0.8:  # sign
                sy0 = y_ground + 0.05 * ppm
                sy1 = top - 0.05 * ppm
                cv2.rectangle(
                    img,
                    (int(x), int(sy0)),
                    (int(x + sw), int(sy1)),
                    tuple(map(float, random_colour(rng, 0.1, 0.9, 0.9))),
                    -1,
                )
                draw_text(img, rng, int(x), int(sy0), int(x + sw), int(sy1))
        x += sw + rng.uniform(0.3, 2.5) * ppm
