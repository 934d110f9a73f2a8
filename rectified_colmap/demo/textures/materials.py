"""Materials: walls (plaster, bricks, stone), ground (cobbles, asphalt, paving), roofs,
clutter panels, rubble, foliage and bark. Each is ``f(rng, h, w, ppm) -> (h, w, 3) float32
RGB in [0, 1]`` (see rectified_colmap.demo.textures).
"""

from __future__ import annotations

import cv2
import numpy as np

from .blocks import draw_text, grain, hash_uniform, posters, random_colour, stains, value_noise


def plaster(rng, h, w, ppm) -> np.ndarray:
    img = np.broadcast_to(random_colour(rng, 0.35, 0.9, 0.25), (h, w, 3)) * grain(
        rng, h, w, ppm, 0.2
    )
    return stains(img.astype(np.float32), rng, ppm, rng.uniform(0.1, 0.4))


def bricks(rng, h, w, ppm) -> np.ndarray:
    """Running-bond bricks with per-row phase jitter, per-brick colour and size noise."""
    seed = int(rng.integers(1 << 30))
    bw = rng.uniform(0.2, 0.32) * ppm
    bh = rng.uniform(0.06, 0.1) * ppm
    mortar = max(0.012 * ppm, 0.6)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    row = np.floor(yy / bh)
    phase = (0.5 * (row % 2) + 0.15 * (hash_uniform(row, 0, seed) - 0.5)) * bw
    col = np.floor((xx + phase) / bw)
    fx = (xx + phase) - col * bw
    fy = yy - row * bh
    r = hash_uniform(col, row, seed + 1)[..., None]
    base = random_colour(rng, 0.25, 0.7, 0.45)
    alt = random_colour(rng, 0.15, 0.6, 0.45)
    img = base * (1 - r) + alt * r
    img = img * (0.8 + 0.4 * hash_uniform(col, row, seed + 2))[..., None]
    odd = hash_uniform(col, row, seed + 3) > 0.93  # replaced / burnt bricks
    img[odd] = img[odd] * rng.uniform(0.3, 0.6) + random_colour(rng, 0.2, 0.9, 0.5) * 0.5
    joint = (fx < mortar) | (fy < mortar)
    img[joint] = random_colour(rng, 0.4, 0.85, 0.1)
    img = img * grain(rng, h, w, ppm, 0.25, 0.5)
    return stains(img.astype(np.float32), rng, ppm, rng.uniform(0.1, 0.35))


def stone(rng, h, w, ppm) -> np.ndarray:
    """Ashlar stone: rows of random height, blocks of random width, per-block shade."""
    seed = int(rng.integers(1 << 30))
    rows = np.cumsum(rng.uniform(0.25, 0.8, int(h / ppm / 0.25) + 4) * ppm)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    row = np.searchsorted(rows, yy[:, 0])[:, None] * np.ones((1, w), np.int64)
    bw = (0.5 + 1.2 * hash_uniform(row, 7, seed)) * ppm
    phase = hash_uniform(row, 3, seed) * bw
    col = np.floor((xx + phase) / bw)
    fx = (xx + phase) - col * bw
    top = np.concatenate([[0.0], rows])[row]
    fy = yy - top
    joint = (fx < 0.015 * ppm + 0.5) | (fy < 0.015 * ppm + 0.5)
    base = random_colour(rng, 0.4, 0.85, 0.15)
    img = base * (0.8 + 0.35 * hash_uniform(col, row, seed + 1))[..., None]
    img = img * grain(rng, h, w, ppm, 0.35, 0.4)
    img[joint] *= 0.55
    return stains(img.astype(np.float32), rng, ppm, rng.uniform(0.15, 0.4))


def cobbles(rng, h, w, ppm) -> np.ndarray:
    """Cobblestones / setts: jittered rows, rounded dark borders, per-stone colour."""
    seed = int(rng.integers(1 << 30))
    s = rng.uniform(0.1, 0.2) * ppm
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    row = np.floor(yy / s)
    phase = hash_uniform(row, 1, seed) * s
    sw = s * rng.uniform(0.9, 1.5)
    col = np.floor((xx + phase) / sw)
    fx = ((xx + phase) - col * sw) / sw
    fy = (yy - row * s) / s
    d = np.maximum(np.abs(fx - 0.5), np.abs(fy - 0.5)) * 2  # 0 centre, 1 border
    shade = 0.7 + 0.5 * hash_uniform(col, row, seed + 1)
    edge = np.clip((d - 0.7) / 0.3, 0, 1)
    img = random_colour(rng, 0.3, 0.7, 0.2) * (shade * (1 - 0.7 * edge))[..., None]
    img = img * grain(rng, h, w, ppm, 0.3, 0.3)
    return stains(img.astype(np.float32), rng, ppm, 0.3)


def asphalt(rng, h, w, ppm, markings: bool = False) -> np.ndarray:
    grey = rng.uniform(0.18, 0.4)
    img = np.full((h, w, 3), grey, np.float32) * (1 + rng.uniform(-0.05, 0.05, 3))
    img = img * grain(rng, h, w, ppm, 0.35, 0.15) * grain(rng, h, w, ppm, 0.25, 4.0)
    speck = rng.random((h, w)) < 0.02
    img[speck] *= rng.uniform(0.4, 1.8, (int(speck.sum()), 1)).astype(np.float32)
    for _ in range(int(rng.integers(3, 10))):  # patches
        x0, y0 = rng.uniform(0, w), rng.uniform(0, h)
        pw, ph = rng.uniform(0.3, 3) * ppm, rng.uniform(0.3, 3) * ppm
        cv2.rectangle(
            img,
            (int(x0), int(y0)),
            (int(x0 + pw), int(y0 + ph)),
            tuple(map(float, img[int(y0), int(x0)] * rng.uniform(0.7, 1.3))),
            -1,
        )
    for _ in range(int(rng.integers(2, 8))):  # cracks
        pts = np.cumsum(rng.normal(0, 0.3 * ppm, (int(rng.integers(4, 12)), 2)), 0)
        pts = (pts + [rng.uniform(0, w), rng.uniform(0, h)]).astype(np.int32)
        cv2.polylines(img, [pts], False, (0.08, 0.08, 0.08), 1, cv2.LINE_AA)
    if markings:
        for _ in range(int(rng.integers(1, 5))):  # worn paint marks, arrows, text
            x0, y0 = rng.uniform(0, w), rng.uniform(0, h)
            if rng.random() < 0.5:
                pw, ph = rng.uniform(0.1, 0.4) * ppm, rng.uniform(0.8, 3) * ppm
                cv2.rectangle(
                    img, (int(x0), int(y0)), (int(x0 + pw), int(y0 + ph)), (0.85, 0.85, 0.8), -1
                )
            else:
                draw_text(
                    img,
                    rng,
                    int(x0),
                    int(y0),
                    int(x0 + 2 * ppm),
                    int(y0 + 0.8 * ppm),
                    (0.85, 0.85, 0.8),
                )
        img = img * grain(rng, h, w, ppm, 0.2, 0.2)
    return np.clip(img, 0, 1)


def paving(rng, h, w, ppm) -> np.ndarray:
    """Sidewalk slabs with jittered joints and stains."""
    seed = int(rng.integers(1 << 30))
    s = rng.uniform(0.3, 0.8) * ppm
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    row = np.floor(yy / s)
    phase = hash_uniform(row, 5, seed) * s
    col = np.floor((xx + phase) / s)
    fx, fy = (xx + phase) - col * s, yy - row * s
    joint = (fx < 0.01 * ppm + 0.6) | (fy < 0.01 * ppm + 0.6)
    img = (
        random_colour(rng, 0.45, 0.8, 0.1) * (0.85 + 0.3 * hash_uniform(col, row, seed))[..., None]
    )
    img = img * grain(rng, h, w, ppm, 0.3, 0.3)
    img[joint] *= 0.6
    return stains(img.astype(np.float32), rng, ppm, rng.uniform(0.2, 0.45))


def roof(rng, h, w, ppm) -> np.ndarray:
    img = np.broadcast_to(random_colour(rng, 0.15, 0.5, 0.3), (h, w, 3)) * grain(
        rng, h, w, ppm, 0.4, 0.3
    )
    return stains(img.astype(np.float32), rng, ppm, 0.4)


def clutter(rng, h, w, ppm) -> np.ndarray:
    """Kiosks, containers, vans: coloured panels with text, stickers and dirt."""
    img = np.ascontiguousarray(
        np.broadcast_to(random_colour(rng, 0.2, 0.9, 0.8), (h, w, 3)), np.float32
    )
    img = img * grain(rng, h, w, ppm, 0.15, 0.5)
    img = np.ascontiguousarray(img, np.float32)
    posters(img, rng, ppm, 0, h, density=rng.uniform(0.3, 1.0))
    for _ in range(int(rng.integers(1, 4))):
        y0 = rng.uniform(0, h * 0.8)
        draw_text(img, rng, 0, int(y0), w, int(y0 + rng.uniform(0.1, 0.3) * h + 6))
    return np.clip(stains(img, rng, ppm, 0.3), 0, 1).astype(np.float32)


def rubble(rng, h, w, ppm) -> np.ndarray:
    """Broken concrete, bricks and debris: noise, blobs and strokes of many colours."""
    img = np.ascontiguousarray(
        value_noise(rng, h, w, 0.3 * ppm, 6)[..., None] * random_colour(rng, 0.5, 1, 0.3)
        + 0.1 * random_colour(rng),
        np.float32,
    )
    n = int(h * w / (0.05 * ppm * ppm + 1) * 0.02) + 5
    for _ in range(min(n, 400)):
        c = (int(rng.uniform(0, w)), int(rng.uniform(0, h)))
        if rng.random() < 0.6:
            ax = (int(rng.uniform(0.02, 0.15) * ppm) + 1, int(rng.uniform(0.02, 0.1) * ppm) + 1)
            cv2.ellipse(
                img,
                c,
                ax,
                rng.uniform(0, 180),
                0,
                360,
                tuple(map(float, random_colour(rng, 0, 1, 0.6))),
                -1,
                cv2.LINE_AA,
            )
        else:
            d = rng.normal(0, 0.1 * ppm, 2)
            cv2.line(
                img,
                c,
                (int(c[0] + d[0]), int(c[1] + d[1])),
                tuple(map(float, random_colour(rng, 0, 1, 0.6))),
                1,
                cv2.LINE_AA,
            )
    return np.clip(img, 0, 1)


def foliage(rng, h, w, ppm) -> np.ndarray:
    """Leaves: multi-scale green-to-olive noise with dark gaps and sunlit flecks."""
    base = random_colour(rng, 0.15, 0.45, 0.2) * np.array([0.7, 1.2, 0.6], np.float32)
    n = value_noise(rng, h, w, rng.uniform(0.05, 0.15) * ppm, 5)[..., None]
    img = base * (0.35 + 1.1 * n)
    gaps = value_noise(rng, h, w, 0.08 * ppm, 3) < rng.uniform(0.25, 0.4)
    img[gaps] *= 0.3
    flecks = value_noise(rng, h, w, 0.03 * ppm, 2) > 0.8
    img[flecks] = img[flecks] * 1.6 + 0.05
    return np.clip(img, 0, 1).astype(np.float32)


def bark(rng, h, w, ppm) -> np.ndarray:
    """Tree bark: dark brown-grey with vertical streaks."""
    img = np.broadcast_to(random_colour(rng, 0.15, 0.4, 0.25), (h, w, 3)).astype(np.float32)
    streak = value_noise(rng, h, w, 0.05 * ppm, 3)
    streak = cv2.blur(streak, (1, max(3, int(0.3 * ppm)) | 1))
    return np.clip(img * (0.5 + streak[..., None]), 0, 1).astype(np.float32)
