"""Building blocks of the procedural textures: hashed and value noise, random colours,
multiplicative grain, stains, random text, posters and graffiti, marks on walls.

Images are (h, w, 3) float32 RGB in [0, 1], row 0 at the top; ``ppm`` is texels per metre
(sizes are physical); all randomness comes from ``rng``. Drawing helpers work in place.
"""

from __future__ import annotations

import string

import cv2
import numpy as np

_FONTS = [
    cv2.FONT_HERSHEY_SIMPLEX,
    cv2.FONT_HERSHEY_DUPLEX,
    cv2.FONT_HERSHEY_COMPLEX,
    cv2.FONT_HERSHEY_TRIPLEX,
    cv2.FONT_HERSHEY_PLAIN,
]
_CHARS = string.ascii_uppercase + string.digits


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


def random_colour(rng, lo=0.15, hi=0.85, sat=0.35) -> np.ndarray:
    grey = rng.uniform(lo, hi)
    return np.clip(grey * (1 + rng.uniform(-sat, sat, 3)), 0.02, 1).astype(np.float32)


def grain(rng, h, w, ppm, strength=0.25, scale_m=1.5) -> np.ndarray:
    """Multiplicative multi-scale grain (h, w, 1) around 1."""
    n = value_noise(rng, h, w, scale_m * ppm, octaves=6)
    return (1 + strength * (n - 0.5) * 2)[..., None]


def stains(img: np.ndarray, rng, ppm, amount=0.3) -> np.ndarray:
    h, w = img.shape[:2]
    n = value_noise(rng, h, w, rng.uniform(1, 4) * ppm, octaves=5)
    m = np.clip((n - np.float32(1 - amount)) * np.float32(0.5 / amount), 0, 0.5)[..., None]
    tint = random_colour(rng, 0.1, 0.5)
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
    col = np.asarray(colour if colour is not None else random_colour(rng, 0, 1, 0.9), np.float32)
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
            cv2.rectangle(
                img, (x0, y0), (x1, y1), tuple(map(float, random_colour(rng, 0.3, 1, 0.8))), -1
            )
            for _ in range(int(rng.integers(1, 4))):
                c = (int(rng.uniform(x0, x1)), int(rng.uniform(y0, y1)))
                r = int(rng.uniform(0.05, 0.3) * min(pw, ph)) + 1
                cv2.circle(
                    img, c, r, tuple(map(float, random_colour(rng, 0, 1, 1))), -1, cv2.LINE_AA
                )
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
                tuple(map(float, random_colour(rng, 0, 1, 1))),
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
                tuple(map(float, random_colour(rng, 0, 1, 1))),
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
        if k < 0.45:
            _patch(img, rng, ppm, cx, cy)
        elif k < 0.65:
            _plaque(img, rng, ppm, cx, cy)
        elif k < 0.75:
            _vent(img, rng, ppm, cx, cy)
        elif k < 0.85:
            _pipe(img, rng, ppm, cx, cy)
        else:
            _tag(img, rng, ppm, cx, cy)


def _patch(img: np.ndarray, rng, ppm, cx: float, cy: float) -> None:
    """A repaired patch around (cx, cy): a random polygon, lighter or darker than the wall."""
    h, w = img.shape[:2]
    m = int(rng.integers(4, 9))
    ang = np.sort(rng.uniform(0, 2 * np.pi, m))
    rad = rng.uniform(0.15, 0.8) * ppm * rng.uniform(0.5, 1.0, m)
    pts = np.stack([cx + rad * np.cos(ang), cy + rad * np.sin(ang)], 1).astype(np.int32)
    base = img[int(min(cy, h - 1)), int(min(cx, w - 1))]
    col = np.clip(base * rng.uniform(0.55, 1.5) + rng.normal(0, 0.05, 3), 0, 1)
    cv2.fillPoly(img, [pts], tuple(map(float, col)), cv2.LINE_AA)


def _plaque(img: np.ndarray, rng, ppm, cx: float, cy: float) -> None:
    """A plaque / small sign with text, its top-left corner at (cx, cy)."""
    pw, ph = rng.uniform(0.2, 0.8) * ppm, rng.uniform(0.1, 0.4) * ppm
    x0, y0 = int(cx), int(cy)
    cv2.rectangle(
        img,
        (x0, y0),
        (int(x0 + pw), int(y0 + ph)),
        tuple(map(float, random_colour(rng, 0.1, 0.95, 0.6))),
        -1,
    )
    draw_text(img, rng, x0, y0, int(x0 + pw), int(y0 + ph))


def _vent(img: np.ndarray, rng, ppm, cx: float, cy: float) -> None:
    """A vent / AC unit, its top-left corner at (cx, cy): a box with a few slats."""
    pw, ph = rng.uniform(0.3, 0.9) * ppm, rng.uniform(0.2, 0.6) * ppm
    x0, y0 = int(cx), int(cy)
    c = random_colour(rng, 0.5, 0.95, 0.1)
    cv2.rectangle(img, (x0, y0), (int(x0 + pw), int(y0 + ph)), tuple(map(float, c)), -1)
    for yy in np.linspace(y0 + ph * 0.2, y0 + ph * 0.8, int(rng.integers(2, 5))):
        cv2.line(
            img,
            (x0 + 2, int(yy)),
            (int(x0 + pw) - 2, int(yy)),
            tuple(map(float, c * 0.6)),
            1,
        )


def _pipe(img: np.ndarray, rng, ppm, cx: float, cy: float) -> None:
    """A pipe / cable from (cx, cy), about horizontal or vertical."""
    L = rng.uniform(0.5, 4.0) * ppm
    a = rng.choice([0.0, np.pi / 2]) + rng.normal(0, 0.05)
    p1 = (int(cx), int(cy))
    p2 = (int(cx + L * np.cos(a)), int(cy + L * np.sin(a)))
    cv2.line(
        img,
        p1,
        p2,
        tuple(map(float, random_colour(rng, 0.1, 0.8, 0.3))),
        max(1, int(rng.uniform(0.02, 0.1) * ppm)),
        cv2.LINE_AA,
    )


def _tag(img: np.ndarray, rng, ppm, cx: float, cy: float) -> None:
    """A graffiti tag / stroke from (cx, cy)."""
    pts = np.cumsum(rng.normal(0, 0.15 * ppm, (int(rng.integers(3, 8)), 2)), 0)
    pts = (pts + [cx, cy]).astype(np.int32)
    cv2.polylines(
        img,
        [pts],
        False,
        tuple(map(float, random_colour(rng, 0, 1, 1))),
        max(1, int(rng.uniform(0.02, 0.05) * ppm)),
        cv2.LINE_AA,
    )
