"""Procedural textures for the synthetic scenes.

Every generator is ``f(rng, height, width, ppm) -> (height, width, 3) float32 RGB in [0, 1]``
where ``ppm`` is texels per metre (so sizes of bricks, windows, ... are physical). Row 0 is
the *top* of a wall texture. Textures are rich in non-repetitive detail at several scales:
jittered bricks/stones/cobbles, window grids with per-window variation, stains, posters and
text; nothing is purely periodic. All randomness comes from ``rng``.

Optional photos (e.g. facades) are loaded with :func:`load_photos` and cropped/resized with
:func:`photo_texture`.
"""

from __future__ import annotations

import functools
import logging
import string
from pathlib import Path

import cv2
import numpy as np

logger = logging.getLogger(__name__)

_FONTS = [
    cv2.FONT_HERSHEY_SIMPLEX,
    cv2.FONT_HERSHEY_DUPLEX,
    cv2.FONT_HERSHEY_COMPLEX,
    cv2.FONT_HERSHEY_TRIPLEX,
    cv2.FONT_HERSHEY_PLAIN,
]
_CHARS = string.ascii_uppercase + string.digits


# -- building blocks -----------------------------------------------------------------------


def hash_uniform(a: np.ndarray, b: np.ndarray, seed: int) -> np.ndarray:
    """Deterministic pseudo-random floats in [0, 1) from two integer arrays (broadcast)."""
    x = (
        np.asarray(a, np.int64).astype(np.uint64) * np.uint64(0x9E3779B1)
        ^ np.asarray(b, np.int64).astype(np.uint64) * np.uint64(0x85EBCA77)
        ^ np.uint64((seed * 0xC2B2AE3D) & 0xFFFFFFFF)
    )
    x = (x ^ (x >> np.uint64(15))) * np.uint64(0x2C1B3C6D)
    x = (x ^ (x >> np.uint64(12))) * np.uint64(0x297A2D39)
    x = x ^ (x >> np.uint64(15))
    return (x & np.uint64(0xFFFFFF)).astype(np.float32) / np.float32(0x1000000)


def value_noise(
    rng: np.random.Generator,
    h: int,
    w: int,
    cell: float,
    octaves: int = 4,
    persistence: float = 0.55,
) -> np.ndarray:
    """Multi-octave value noise (h, w) float32 in [0, 1]; ``cell``: largest feature (px).

    Built coarse to fine: a random grid of ``cell``-sized cells, upsampled 2x (bicubic)
    and perturbed with random values of amplitude ``persistence^k`` at each octave, then
    resized to (h, w): about one full-size resize in all."""
    cell = max(float(cell), 1.5)
    octaves = max(1, min(octaves, int(np.log2(cell)) + 1))
    gh, gw = int(np.ceil(h / cell)) + 2, int(np.ceil(w / cell)) + 2
    noise = rng.random((gh, gw), dtype=np.float32)
    amp = 1.0
    for _ in range(octaves - 1):
        gh, gw = 2 * gh, 2 * gw
        amp *= persistence
        noise = cv2.resize(noise, (gw, gh), interpolation=cv2.INTER_CUBIC)
        noise += np.float32(amp) * rng.random((gh, gw), dtype=np.float32)
    # the grid spans (gw - 2) cells of the finest octave over w pixels, +2 cells of margin
    fine = cell / 2 ** (octaves - 1)
    big = cv2.resize(
        noise,
        (int(np.ceil(gw * fine)), int(np.ceil(gh * fine))),
        interpolation=cv2.INTER_CUBIC if fine > 1 else cv2.INTER_AREA,
    )
    out = big[:h, :w]
    lo, hi = np.percentile(out[::4, ::4], [1, 99])
    return np.clip((out - lo) / max(hi - lo, 1e-6), 0, 1)


def _colour(rng, lo=0.15, hi=0.85, sat=0.35) -> np.ndarray:
    grey = rng.uniform(lo, hi)
    return np.clip(grey * (1 + rng.uniform(-sat, sat, 3)), 0.02, 1).astype(np.float32)


def _grain(rng, h, w, ppm, strength=0.25, scale_m=1.5) -> np.ndarray:
    """Multiplicative multi-scale grain (h, w, 1) around 1."""
    n = value_noise(rng, h, w, scale_m * ppm, octaves=6)
    return (1 + strength * (n - 0.5) * 2)[..., None]


def _stains(img: np.ndarray, rng, ppm, amount=0.3) -> np.ndarray:
    h, w = img.shape[:2]
    n = value_noise(rng, h, w, rng.uniform(1, 4) * ppm, octaves=5)
    m = np.clip((n - np.float32(1 - amount)) * np.float32(0.5 / amount), 0, 0.5)[..., None]
    tint = _colour(rng, 0.1, 0.5)
    out = np.asarray(img, np.float32) - tint
    out *= 1 - m
    out += tint
    return out


def _random_text(rng, n_min=2, n_max=9) -> str:
    return "".join(rng.choice(list(_CHARS), int(rng.integers(n_min, n_max + 1))))


def draw_text(img: np.ndarray, rng, x0, y0, x1, y1, colour=None) -> None:
    """Random text fitted in the box [x0, x1) x [y0, y1) (px), in place."""
    bw, bh = x1 - x0, y1 - y0
    if bw < 8 or bh < 6:
        return
    txt = _random_text(rng)
    font = _FONTS[int(rng.integers(len(_FONTS)))]
    th = max(1, int(bh / 10))
    (tw, tht), _ = cv2.getTextSize(txt, font, 1.0, th)
    scale = min(bw / max(tw, 1), bh / max(tht, 1)) * rng.uniform(0.6, 0.95)
    if scale * tht < 5:
        return
    th = max(1, int(scale * tht / 8))
    col = np.asarray(colour if colour is not None else _colour(rng, 0, 1, 0.9), np.float32)
    h, w = img.shape[:2]
    x0, y0, x1, y1 = max(int(x0), 0), max(int(y0), 0), min(int(x1), w), min(int(y1), h)
    if x1 - x0 < 4 or y1 - y0 < 4:
        return
    mask = np.zeros((y1 - y0, x1 - x0), np.uint8)  # cv2 5 draws text on 8-bit images only
    cv2.putText(
        mask,
        txt,
        (int(0.05 * bw), int(0.5 * bh + 0.5 * scale * tht)),
        font,
        scale,
        255,
        th,
        cv2.LINE_AA,
    )
    m = (mask.astype(np.float32) / 255.0)[..., None]
    img[y0:y1, x0:x1] = img[y0:y1, x0:x1] * (1 - m) + col * m


def posters(img: np.ndarray, rng, ppm, y_lo, y_hi, density=0.15) -> None:
    """Posters, graffiti blobs and strokes between rows y_lo and y_hi (px), in place."""
    h, w = img.shape[:2]
    y_lo, y_hi = int(max(0, y_lo)), int(min(h, y_hi))
    if y_hi - y_lo < 0.5 * ppm:
        return
    n = int(density * w / ppm * rng.uniform(0.5, 1.5)) + 1
    for _ in range(n):
        kind = rng.random()
        cx = rng.uniform(0, w)
        cy = rng.uniform(y_lo, y_hi)
        if kind < 0.45:  # poster: rectangle with text and shapes
            pw, ph = rng.uniform(0.4, 1.2) * ppm, rng.uniform(0.5, 1.5) * ppm
            x0, y0 = int(cx - pw / 2), int(cy - ph / 2)
            x1, y1 = int(cx + pw / 2), int(cy + ph / 2)
            cv2.rectangle(img, (x0, y0), (x1, y1), tuple(map(float, _colour(rng, 0.3, 1, 0.8))), -1)
            for _ in range(int(rng.integers(1, 4))):
                c = (int(rng.uniform(x0, x1)), int(rng.uniform(y0, y1)))
                r = int(rng.uniform(0.05, 0.3) * min(pw, ph)) + 1
                cv2.circle(img, c, r, tuple(map(float, _colour(rng, 0, 1, 1))), -1, cv2.LINE_AA)
            for k in range(int(rng.integers(1, 4))):
                yy = y0 + (k + 0.2) * (y1 - y0) / 4
                draw_text(img, rng, x0, int(yy), x1, int(yy + (y1 - y0) / 5))
        elif kind < 0.8:  # graffiti strokes
            pts = np.cumsum(rng.normal(0, 0.25 * ppm, (int(rng.integers(3, 9)), 2)), 0)
            pts = (pts + [cx, cy]).astype(np.int32)
            cv2.polylines(
                img,
                [pts],
                False,
                tuple(map(float, _colour(rng, 0, 1, 1))),
                max(1, int(rng.uniform(0.02, 0.08) * ppm)),
                cv2.LINE_AA,
            )
        else:  # blob
            ax = (int(rng.uniform(0.1, 0.6) * ppm) + 1, int(rng.uniform(0.1, 0.5) * ppm) + 1)
            cv2.ellipse(
                img,
                (int(cx), int(cy)),
                ax,
                rng.uniform(0, 180),
                0,
                360,
                tuple(map(float, _colour(rng, 0, 1, 1))),
                -1,
                cv2.LINE_AA,
            )


def decorate(img: np.ndarray, rng, ppm, per_m2: float = 0.25) -> None:
    """Distinctive irregular marks all over a wall, in place: repaired patches (random
    polygons), plaques with text, vents, pipes and graffiti; about ``per_m2`` per m^2."""
    h, w = img.shape[:2]
    n = int(per_m2 * h * w / ppm**2 * rng.uniform(0.6, 1.4)) + 1
    for _ in range(min(n, 400)):
        cx, cy = rng.uniform(0, w), rng.uniform(0, h)
        k = rng.random()
        if k < 0.45:  # patch: a random polygon, lighter or darker than the wall
            m = int(rng.integers(4, 9))
            ang = np.sort(rng.uniform(0, 2 * np.pi, m))
            rad = rng.uniform(0.15, 0.8) * ppm * rng.uniform(0.5, 1.0, m)
            pts = np.stack([cx + rad * np.cos(ang), cy + rad * np.sin(ang)], 1).astype(np.int32)
            base = img[int(min(cy, h - 1)), int(min(cx, w - 1))]
            col = np.clip(base * rng.uniform(0.55, 1.5) + rng.normal(0, 0.05, 3), 0, 1)
            cv2.fillPoly(img, [pts], tuple(map(float, col)), cv2.LINE_AA)
        elif k < 0.65:  # plaque / small sign with text
            pw, ph = rng.uniform(0.2, 0.8) * ppm, rng.uniform(0.1, 0.4) * ppm
            x0, y0 = int(cx), int(cy)
            cv2.rectangle(
                img,
                (x0, y0),
                (int(x0 + pw), int(y0 + ph)),
                tuple(map(float, _colour(rng, 0.1, 0.95, 0.6))),
                -1,
            )
            draw_text(img, rng, x0, y0, int(x0 + pw), int(y0 + ph))
        elif k < 0.75:  # vent / AC unit: box with a few slats
            pw, ph = rng.uniform(0.3, 0.9) * ppm, rng.uniform(0.2, 0.6) * ppm
            x0, y0 = int(cx), int(cy)
            c = _colour(rng, 0.5, 0.95, 0.1)
            cv2.rectangle(img, (x0, y0), (int(x0 + pw), int(y0 + ph)), tuple(map(float, c)), -1)
            for yy in np.linspace(y0 + ph * 0.2, y0 + ph * 0.8, int(rng.integers(2, 5))):
                cv2.line(
                    img,
                    (x0 + 2, int(yy)),
                    (int(x0 + pw) - 2, int(yy)),
                    tuple(map(float, c * 0.6)),
                    1,
                )
        elif k < 0.85:  # pipe / cable
            L = rng.uniform(0.5, 4.0) * ppm
            a = rng.choice([0.0, np.pi / 2]) + rng.normal(0, 0.05)
            p1 = (int(cx), int(cy))
            p2 = (int(cx + L * np.cos(a)), int(cy + L * np.sin(a)))
            cv2.line(
                img,
                p1,
                p2,
                tuple(map(float, _colour(rng, 0.1, 0.8, 0.3))),
                max(1, int(rng.uniform(0.02, 0.1) * ppm)),
                cv2.LINE_AA,
            )
        else:  # graffiti tag / stroke
            pts = np.cumsum(rng.normal(0, 0.15 * ppm, (int(rng.integers(3, 8)), 2)), 0)
            pts = (pts + [cx, cy]).astype(np.int32)
            cv2.polylines(
                img,
                [pts],
                False,
                tuple(map(float, _colour(rng, 0, 1, 1))),
                max(1, int(rng.uniform(0.02, 0.05) * ppm)),
                cv2.LINE_AA,
            )


# -- wall materials ------------------------------------------------------------------------


def plaster(rng, h, w, ppm) -> np.ndarray:
    img = np.broadcast_to(_colour(rng, 0.35, 0.9, 0.25), (h, w, 3)) * _grain(rng, h, w, ppm, 0.2)
    return _stains(img.astype(np.float32), rng, ppm, rng.uniform(0.1, 0.4))


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
    base = _colour(rng, 0.25, 0.7, 0.45)
    alt = _colour(rng, 0.15, 0.6, 0.45)
    img = base * (1 - r) + alt * r
    img = img * (0.8 + 0.4 * hash_uniform(col, row, seed + 2))[..., None]
    odd = hash_uniform(col, row, seed + 3) > 0.93  # replaced / burnt bricks
    img[odd] = img[odd] * rng.uniform(0.3, 0.6) + _colour(rng, 0.2, 0.9, 0.5) * 0.5
    joint = (fx < mortar) | (fy < mortar)
    img[joint] = _colour(rng, 0.4, 0.85, 0.1)
    img = img * _grain(rng, h, w, ppm, 0.25, 0.5)
    return _stains(img.astype(np.float32), rng, ppm, rng.uniform(0.1, 0.35))


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
    base = _colour(rng, 0.4, 0.85, 0.15)
    img = base * (0.8 + 0.35 * hash_uniform(col, row, seed + 1))[..., None]
    img = img * _grain(rng, h, w, ppm, 0.35, 0.4)
    img[joint] *= 0.55
    return _stains(img.astype(np.float32), rng, ppm, rng.uniform(0.15, 0.4))


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
    img = _colour(rng, 0.3, 0.7, 0.2) * (shade * (1 - 0.7 * edge))[..., None]
    img = img * _grain(rng, h, w, ppm, 0.3, 0.3)
    return _stains(img.astype(np.float32), rng, ppm, 0.3)


def asphalt(rng, h, w, ppm, markings: bool = False) -> np.ndarray:
    grey = rng.uniform(0.18, 0.4)
    img = np.full((h, w, 3), grey, np.float32) * (1 + rng.uniform(-0.05, 0.05, 3))
    img = img * _grain(rng, h, w, ppm, 0.35, 0.15) * _grain(rng, h, w, ppm, 0.25, 4.0)
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
        img = img * _grain(rng, h, w, ppm, 0.2, 0.2)
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
    img = _colour(rng, 0.45, 0.8, 0.1) * (0.85 + 0.3 * hash_uniform(col, row, seed))[..., None]
    img = img * _grain(rng, h, w, ppm, 0.3, 0.3)
    img[joint] *= 0.6
    return _stains(img.astype(np.float32), rng, ppm, rng.uniform(0.2, 0.45))


def roof(rng, h, w, ppm) -> np.ndarray:
    img = np.broadcast_to(_colour(rng, 0.15, 0.5, 0.3), (h, w, 3)) * _grain(
        rng, h, w, ppm, 0.4, 0.3
    )
    return _stains(img.astype(np.float32), rng, ppm, 0.4)


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
    frame_col = _colour(rng, 0.05, 0.95, 0.2)
    n_cols = int(w / spacing)
    margin = (w - n_cols * spacing) / 2
    y_ground = h - ground_h
    n_floors = int((y_ground - 0.3 * floor_h) / floor_h)
    glass_base = _colour(rng, 0.1, 0.5, 0.3) * np.array([0.8, 0.9, 1.1], np.float32)
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
                    tuple(map(float, _colour(rng, 0.4, 0.95, 0.4))),
                    -1,
                )
            elif r < 0.55:  # shutters half-closed: horizontal slats
                yc = int(y0 + rng.uniform(0.2, 0.9) * (y1 - y0))
                cv2.rectangle(
                    img, (x0, int(y0)), (x1, yc), tuple(map(float, _colour(rng, 0.2, 0.8, 0.5))), -1
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
                    tuple(map(float, _colour(rng, 0.5, 0.95, 0.1))),
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
                    tuple(map(float, _colour(rng, 0, 1, 1))),
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
                    tuple(map(float, _colour(rng, 0.1, 0.9, 0.9))),
                    -1,
                )
                draw_text(img, rng, int(x), int(sy0), int(x + sw), int(sy1))
        x += sw + rng.uniform(0.3, 2.5) * ppm
    # reflections (sky, opposite buildings) and interiors: multi-scale detail on the glass
    refl = value_noise(rng, h, w, rng.uniform(0.5, 2.0) * ppm, 5)
    refl = (np.float32(0.5) + np.float32(1.2) * refl)[..., None]
    img = np.where(glass[..., None] > 0, img * refl, img).astype(np.float32)
    posters(img, rng, ppm, h - 2.5 * ppm, h, density=rng.uniform(0.05, 0.3))
    img = img * _grain(rng, h, w, ppm, 0.12, 2.0)
    return np.clip(img, 0, 1).astype(np.float32)


def clutter(rng, h, w, ppm) -> np.ndarray:
    """Kiosks, containers, vans: coloured panels with text, stickers and dirt."""
    img = np.ascontiguousarray(np.broadcast_to(_colour(rng, 0.2, 0.9, 0.8), (h, w, 3)), np.float32)
    img = img * _grain(rng, h, w, ppm, 0.15, 0.5)
    img = np.ascontiguousarray(img, np.float32)
    posters(img, rng, ppm, 0, h, density=rng.uniform(0.3, 1.0))
    for _ in range(int(rng.integers(1, 4))):
        y0 = rng.uniform(0, h * 0.8)
        draw_text(img, rng, 0, int(y0), w, int(y0 + rng.uniform(0.1, 0.3) * h + 6))
    return np.clip(_stains(img, rng, ppm, 0.3), 0, 1).astype(np.float32)


def rubble(rng, h, w, ppm) -> np.ndarray:
    """Broken concrete, bricks and debris: noise, blobs and strokes of many colours."""
    img = np.ascontiguousarray(
        value_noise(rng, h, w, 0.3 * ppm, 6)[..., None] * _colour(rng, 0.5, 1, 0.3)
        + 0.1 * _colour(rng),
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
                tuple(map(float, _colour(rng, 0, 1, 0.6))),
                -1,
                cv2.LINE_AA,
            )
        else:
            d = rng.normal(0, 0.1 * ppm, 2)
            cv2.line(
                img,
                c,
                (int(c[0] + d[0]), int(c[1] + d[1])),
                tuple(map(float, _colour(rng, 0, 1, 0.6))),
                1,
                cv2.LINE_AA,
            )
    return np.clip(img, 0, 1)


def foliage(rng, h, w, ppm) -> np.ndarray:
    """Leaves: multi-scale green-to-olive noise with dark gaps and sunlit flecks."""
    base = _colour(rng, 0.15, 0.45, 0.2) * np.array([0.7, 1.2, 0.6], np.float32)
    n = value_noise(rng, h, w, rng.uniform(0.05, 0.15) * ppm, 5)[..., None]
    img = base * (0.35 + 1.1 * n)
    gaps = value_noise(rng, h, w, 0.08 * ppm, 3) < rng.uniform(0.25, 0.4)
    img[gaps] *= 0.3
    flecks = value_noise(rng, h, w, 0.03 * ppm, 2) > 0.8
    img[flecks] = img[flecks] * 1.6 + 0.05
    return np.clip(img, 0, 1).astype(np.float32)


def bark(rng, h, w, ppm) -> np.ndarray:
    """Tree bark: dark brown-grey with vertical streaks."""
    img = np.broadcast_to(_colour(rng, 0.15, 0.4, 0.25), (h, w, 3)).astype(np.float32)
    streak = value_noise(rng, h, w, 0.05 * ppm, 3)
    streak = cv2.blur(streak, (1, max(3, int(0.3 * ppm)) | 1))
    return np.clip(img * (0.5 + streak[..., None]), 0, 1).astype(np.float32)


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


# -- photos ----------------------------------------------------------------------------------


@functools.lru_cache(maxsize=4)
def load_photos(folder: str, max_side: int = 1024) -> tuple[np.ndarray, ...]:
    """All JPEG/PNG images under a folder (recursively) as float32 RGB, downscaled to
    ``max_side``."""
    path = Path(folder)
    if not path.is_dir():
        raise FileNotFoundError(f"{folder}: texture folder does not exist")
    out = []
    for p in sorted(path.rglob("*")):
        if p.suffix.lower() not in (".jpg", ".jpeg", ".png"):
            continue
        im = cv2.imread(str(p), cv2.IMREAD_COLOR)
        if im is None:
            logger.warning("%s: cannot read image, skipped", p)
            continue
        s = max_side / max(im.shape[:2])
        if s < 1:
            im = cv2.resize(im, None, fx=s, fy=s, interpolation=cv2.INTER_AREA)
        out.append(np.ascontiguousarray(im[..., ::-1], np.float32) / 255.0)
    if not out:
        raise ValueError(f"{folder}: no readable .jpg/.jpeg/.png textures")
    logger.info("loaded %d texture photos from %s", len(out), folder)
    return tuple(out)


def photo_texture(photo: np.ndarray, rng, h, w) -> np.ndarray:
    """A random crop of a photo with the aspect ratio h:w, resized to (h, w)."""
    ph, pw = photo.shape[:2]
    s = min(ph / h, pw / w) * rng.uniform(0.7, 1.0)
    ch, cw = max(2, int(h * s)), max(2, int(w * s))
    y0, x0 = int(rng.integers(0, ph - ch + 1)), int(rng.integers(0, pw - cw + 1))
    crop = photo[y0 : y0 + ch, x0 : x0 + cw]
    interp = cv2.INTER_AREA if s > 1 else cv2.INTER_CUBIC
    return np.clip(cv2.resize(crop, (w, h), interpolation=interp), 0, 1).astype(np.float32)
