"""Caption and legend bands under the pictures (BGR uint8 images)."""

from __future__ import annotations

import cv2
import numpy as np

from .colours import OUTLINE_BGR, orientation_colours

FONT = cv2.FONT_HERSHEY_SIMPLEX
BAND_BGR = (35, 35, 35)
TEXT_BGR = (240, 240, 240)
MIN_WIDTH = 480


def size_unit(width: int) -> float:
    """Size unit of text and glyphs: 1 up to 1200 px wide, growing beyond."""
    return max(1.0, width / 1200.0)


def font(u: float) -> tuple[float, int]:
    return 0.5 * u, max(1, round(u))


def wrap(text: str, width: int, scale: float, thick: int) -> list[str]:
    """Text split into lines of at most ``width`` pixels, at spaces and newlines."""
    lines = []
    for para in text.split("\n"):
        cur = ""
        for word in para.split(" "):
            cand = f"{cur} {word}" if cur else word
            if cur and cv2.getTextSize(cand, FONT, scale, thick)[0][0] > width:
                lines.append(cur)
                cur = word
            else:
                cur = cand
        lines.append(cur)
    return lines


def swatch(colour, u: float, w: float = 22) -> np.ndarray:
    g = np.empty((round(14 * u), round(w * u), 3), np.uint8)
    g[:] = colour
    g[[0, -1]] = g[:, [0, -1]] = 200
    return g


def wall_bar(u: float, w: float = 150) -> np.ndarray:
    """Colour bar of walls from facing left (-90 deg) to facing right (+90 deg)."""
    width = round(w * u)
    az = np.radians(np.linspace(-90.0, 90.0, width))
    n = np.stack([np.sin(az), np.zeros_like(az), -np.cos(az)], 1)
    row = orientation_colours(n)
    return np.repeat(row[None], round(14 * u), axis=0)


def dot(colour, u: float) -> np.ndarray:
    g = np.empty((round(14 * u), round(14 * u), 3), np.uint8)
    g[:] = BAND_BGR
    c = (g.shape[1] // 2, g.shape[0] // 2)
    cv2.circle(g, c, round(5 * u), (0, 0, 0), -1, cv2.LINE_AA)
    cv2.circle(g, c, round(4 * u), colour, -1, cv2.LINE_AA)
    return g


def outline(u: float, dashed: bool) -> np.ndarray:
    g = np.empty((round(14 * u), round(26 * u), 3), np.uint8)
    g[:] = (90, 90, 90)
    edge = np.zeros(g.shape[:2], bool)
    t = max(1, round(2 * u))
    edge[:t], edge[-t:], edge[:, :t], edge[:, -t:] = True, True, True, True
    if dashed:
        edge &= dash_mask(g.shape[:2], u)
    g[edge] = OUTLINE_BGR
    return g


def dash_mask(shape: tuple[int, int], u: float) -> np.ndarray:
    """(h, w) bool checkerboard of dashes (on half of an outline's pixels)."""
    yy, xx = np.indices(shape)
    return ((xx + yy) // max(2, round(5 * u))) % 2 == 0


def legend_band(width: int, caption: str, items: list[tuple[np.ndarray, str]]) -> np.ndarray:
    """(h, width, 3) BGR band: the caption (wrapped) then the legend items (glyph, text)
    flowing left to right in rows."""
    u = size_unit(width)
    scale, thick = font(u)
    pad = round(8 * u)
    (_, asc), desc = cv2.getTextSize("Ag", FONT, scale, thick)
    line_h = asc + desc + round(4 * u)
    cap = wrap(caption, width - 2 * pad, scale, thick) if caption else []
    rows, x, cur = [], pad, []  # the legend's rows of items (x, glyph, text)
    for glyph, text in items:
        tw = cv2.getTextSize(text, FONT, scale, thick)[0][0]
        w = glyph.shape[1] + round(6 * u) + tw
        if cur and x + w > width - pad:
            rows.append(cur)
            x, cur = pad, []
        cur.append((x, glyph, text))
        x += w + round(18 * u)
    if cur:
        rows.append(cur)
    glyph_h = max([g.shape[0] for g, _ in items], default=0)
    row_h = max(line_h, glyph_h + round(4 * u))
    height = pad + len(cap) * line_h + (pad // 2 if rows else 0) + len(rows) * row_h + pad
    band = np.empty((height, width, 3), np.uint8)
    band[:] = BAND_BGR
    y = pad
    for line in cap:
        cv2.putText(band, line, (pad, y + asc), FONT, scale, TEXT_BGR, thick, cv2.LINE_AA)
        y += line_h
    y += pad // 2 if rows else 0
    for row in rows:
        for x, glyph, text in row:
            gh, gw = glyph.shape[:2]
            gy, fit = y + (row_h - gh) // 2, max(0, min(gw, width - x))
            band[gy : gy + gh, x : x + fit] = glyph[:, :fit]
            ty = y + (row_h + asc - desc) // 2
            cv2.putText(
                band, text, (x + gw + round(6 * u), ty), FONT, scale, TEXT_BGR, thick, cv2.LINE_AA
            )
        y += row_h
    return band


def with_band(image: np.ndarray, caption: str, items: list[tuple[np.ndarray, str]]) -> np.ndarray:
    """The BGR image above its caption and legend band (the image padded on the right
    when the band needs more width)."""
    H, W = image.shape[:2]
    width = max(W, MIN_WIDTH)
    band = legend_band(width, caption, items)
    top = np.empty((H, width, 3), np.uint8)
    top[:] = BAND_BGR
    top[:, :W] = image
    return np.concatenate([top, band], 0)
