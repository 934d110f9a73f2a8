"""Building fronts: a wall material with floors of windows (each different), a ground floor
of shop windows and signs, posters and graffiti near the ground (see
rectified_colmap.demo.textures for the conventions).
"""

from __future__ import annotations

import cv2
import numpy as np

from .blocks import decorate, draw_text, grain, posters, random_colour, value_noise
from .materials import bricks, plaster, stone
from .photos import photo_texture


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
    n_cols = int(w / spacing)
    margin = (w - n_cols * spacing) / 2
    y_ground = h - ground_h
    n_floors = int((y_ground - 0.3 * floor_h) / floor_h)
    glass_base = random_colour(rng, 0.1, 0.5, 0.3) * np.array([0.8, 0.9, 1.1], np.float32)
    glass = np.zeros((h, w), np.uint8)  # where reflections and interiors are added
    for f in range(n_floors):
        y1 = y_ground - f * floor_h - 0.25 * floor_h
        y0 = y1 - win_h * rng.uniform(0.97, 1.03)
        if rng.random() < 0.4:  # cornice / floor band
            yb = int(y_ground - f * floor_h)
            cv2.rectangle(
                img,
                (0, yb - max(1, int(0.1 * ppm))),
                (w, yb),
                tuple(map(float, np.clip(frame_col * rng.uniform(0.7, 1.2), 0, 1))),
                -1,
            )
        for c in range(n_cols):
            if rng.random() < 0.04:
                continue  # a missing window
            cx = margin + (c + 0.5) * spacing + rng.normal(0, 0.01 * ppm)
            x0, x1 = int(cx - win_w / 2), int(cx + win_w / 2)
            g = np.clip(glass_base * rng.uniform(0.5, 1.8) + rng.normal(0, 0.04, 3), 0, 1)
            cv2.rectangle(
                img,
                (x0 - frame, int(y0) - frame),
                (x1 + frame, int(y1) + frame),
                tuple(map(float, frame_col)),
                -1,
            )
            cv2.rectangle(img, (x0, int(y0)), (x1, int(y1)), tuple(map(float, g)), -1)
            cv2.rectangle(glass, (x0, int(y0)), (x1, int(y1)), 1, -1)
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
    # ground floor: shop windows, doors, signs with text
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
    # reflections (sky, opposite buildings) and interiors: multi-scale detail on the glass
    refl = value_noise(rng, h, w, rng.uniform(0.5, 2.0) * ppm, 5)
    refl = (np.float32(0.5) + np.float32(1.2) * refl)[..., None]
    img = np.where(glass[..., None] > 0, img * refl, img).astype(np.float32)
    posters(img, rng, ppm, h - 2.5 * ppm, h, density=rng.uniform(0.05, 0.3))
    img = img * grain(rng, h, w, ppm, 0.12, 2.0)
    return np.clip(img, 0, 1).astype(np.float32)
