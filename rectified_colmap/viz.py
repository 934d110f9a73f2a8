"""PNG visualisations of one image's planes, patches and keypoints (OpenCV only).

Three pictures per image (``save_visualizations``; docs/usage.md, ``--visualize``), each
with a caption and a legend drawn into a band below it:

``<out>/<name>.overview.png``: the image with its keypoints, plain SIFT in blue and the
features found in rectified patches in orange (counts in the caption), the rectified regions
outlined (dashed: plane hypotheses from vanishing points). Written for every image.
``<out>/<name>.planes.png``: the plane labels blended into the image, coloured by the way
the plane faces (below), non-planar pixels darkened, each rectified region outlined and
tagged ``#i``.
``<out>/<name>.patches.png``: the rectified patches (fronto-parallel virtual views, black
outside the patch), each framed in its plane colour (dashed: a hypothesis from vanishing
points) with a header ``#i``, its kind, its tilt (the angle between the plane and the image
plane, 0-90 degrees) and the number of features it contributed (orange dots).

Plane colours are a fixed function of the normal in the camera frame (x right, y down,
z forward; normals face the camera), never of a cluster index, so one orientation has one
colour in every image (``orientation_colours``). "Up" is the image's up direction (-y): the
pipeline has no gravity. Normals within ``HORIZONTAL_DEG`` of up are ground (green), of down
ceiling (cyan); the other (vertical) planes take a hue from their azimuth, the direction
the normal points seen from above, on a continuous wheel: blue = the wall faces left
(normal towards -x), violet, pink = faces the camera, red, orange = faces right (+x)
(``wall_hue_deg``).

Pictures wider or taller than ``DISPLAY_MAX_SIDE`` are scaled down. Images in are grayscale
(H, W) or RGB (H, W, 3) uint8, images out BGR (H, W, 3).

Vanishing points (a vp.fusion.VpResult, e.g. for scripts/bench_vp.py): ``draw_segments``
(segments coloured by frame row) and ``draw_directions`` (needles towards each direction's
VP); ``save_png`` writes a BGR image. Colours there: red/green/blue = frame rows (or
directions) 0/1/2.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pycolmap

from . import camera as cam_utils
from .conventions import pixel_centers, to_opencv_points
from .geometry import line_angle_deg
from .rectify import warp_to_rectified
from .vp.fusion import VpResult

# -- colours of plane orientations --------------------------------------------------------

IMAGE_UP = np.array([0.0, -1.0, 0.0])
""""Up" in the camera frame without gravity: the image's -y."""
HORIZONTAL_DEG = 45.0
"""Normals within this angle of up (down) are ground (ceiling); the others are walls."""
GROUND_BGR = (70, 200, 70)  # green
CEILING_BGR = (220, 210, 40)  # cyan
NONE_BGR = (128, 128, 128)  # undefined normal
PLAIN_BGR = (255, 150, 30)  # blue: plain SIFT keypoints
RECTIFIED_BGR = (0, 150, 255)  # orange: keypoints found in a rectified patch
OUTLINE_BGR = (255, 255, 255)
DISPLAY_MAX_SIDE = 1600
"""Pictures are scaled down to at most this side (None in the functions: full size)."""

_WALL_HUE_FACING_CAMERA = 320.0  # pink; -90 deg (faces left) -> 230 blue, +90 -> 50 orange


def wall_hue_deg(azimuth_deg: np.ndarray) -> np.ndarray:
    """Hue in degrees [0, 360) of a vertical plane whose normal points ``azimuth_deg`` away
    from the camera's backward direction, positive towards +x (clipped to [-90, 90]): a
    continuous wheel from blue (faces left) through pink (faces the camera) and red to orange
    (faces right) that stays clear of the ground's green and the ceiling's cyan."""
    az = np.clip(np.asarray(azimuth_deg, np.float64), -90.0, 90.0)
    return (_WALL_HUE_FACING_CAMERA + az) % 360.0


def _hue_bgr(hue_deg: np.ndarray) -> np.ndarray:
    """(...) hues in degrees -> (..., 3) uint8 BGR (saturation 210, value 255)."""
    hue_deg = np.asarray(hue_deg, np.float64)
    hsv = np.empty(hue_deg.shape + (3,), np.uint8)
    hsv[..., 0] = np.round(hue_deg / 2.0).astype(np.int64) % 180  # OpenCV hue is degrees / 2
    hsv[..., 1], hsv[..., 2] = 210, 255
    flat = hsv.reshape(-1, 1, 3)
    return cv2.cvtColor(flat, cv2.COLOR_HSV2BGR).reshape(hsv.shape)


def orientation_kind(normals: np.ndarray, up: np.ndarray = IMAGE_UP):
    """(..., 3) unit normals (camera frame, facing the camera) -> (kind, azimuth_deg):
    kind (...) int8 0 = ground, 1 = ceiling, 2 = wall, -1 = undefined (NaN); azimuth (...)
    degrees of a wall's normal about ``up``, 0 = facing the camera, positive = facing right
    (towards +x when up is the image's -y), in (-180, 180]."""
    n = np.asarray(normals, np.float64)
    up = np.asarray(up, np.float64) / np.linalg.norm(up)
    # Horizontal frame about up: forward = the optical axis made horizontal, right = f x up.
    forward = np.array([0.0, 0.0, 1.0]) - up[2] * up
    if np.linalg.norm(forward) < 1e-6:  # looking straight up or down: image x is right
        forward = np.cross(np.array([1.0, 0.0, 0.0]), up)
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, up)
    elev = np.degrees(np.arcsin(np.clip(n @ up, -1.0, 1.0)))
    azimuth = np.degrees(np.arctan2(n @ right, -(n @ forward)))
    kind = np.full(n.shape[:-1], 2, np.int8)
    kind[elev >= 90.0 - HORIZONTAL_DEG] = 0
    kind[elev <= HORIZONTAL_DEG - 90.0] = 1
    kind[~np.isfinite(n).all(-1)] = -1
    return kind, azimuth


def orientation_colours(normals: np.ndarray, up: np.ndarray = IMAGE_UP) -> np.ndarray:
    """(..., 3) unit normals (camera frame, facing the camera) -> (..., 3) uint8 BGR: ground
    ``GROUND_BGR``, ceiling ``CEILING_BGR``, walls by ``wall_hue_deg`` of their azimuth,
    undefined (NaN) ``NONE_BGR``. A function of the orientation only: the same in every
    image."""
    kind, azimuth = orientation_kind(normals, up)
    out = _hue_bgr(wall_hue_deg(np.nan_to_num(azimuth)))
    out[kind == 0] = GROUND_BGR
    out[kind == 1] = CEILING_BGR
    out[kind == -1] = NONE_BGR
    return out


def orientation_text(normal: np.ndarray, up: np.ndarray = IMAGE_UP) -> str:
    """Short name of a normal's orientation: ground, ceiling, wall facing left / camera /
    right (with its azimuth)."""
    kind, az = orientation_kind(np.asarray(normal, np.float64).reshape(1, 3), up)
    kind, az = int(kind[0]), float(az[0])
    if kind < 0:
        return "undefined"
    if kind < 2:
        return ("ground", "ceiling")[kind]
    side = "left" if az < -20 else "right" if az > 20 else "camera"
    return f"wall facing {side} ({az:+.0f} deg)"


def tilt_deg(normal: np.ndarray) -> float:
    """Angle between a plane and the image plane (between the lines of its normal and the
    optical axis), in degrees in [0, 90]: 0 = fronto-parallel, 90 = seen edge-on. A plane
    facing the camera can still have a normal more than 90 degrees from -z (ground seen by
    a camera pitched up): the dihedral angle is the one a tilt label means."""
    n = np.asarray(normal, np.float64).reshape(3)
    return float(line_angle_deg(n / np.linalg.norm(n), np.array([0.0, 0.0, 1.0])))


def label_colours(directions: np.ndarray | None, up: np.ndarray = IMAGE_UP) -> np.ndarray:
    """(6, 3) uint8 BGR of the labels 2 k + s of a PlaneResult: the colour of the normal
    d_k (s = 0) or -d_k (s = 1); NONE_BGR without directions."""
    if directions is None:
        return np.tile(np.array(NONE_BGR, np.uint8), (6, 1))
    d = np.asarray(directions, np.float64)
    return orientation_colours(np.stack([d, -d], 1).reshape(6, 3), up)


# -- legend and caption bands -------------------------------------------------------------

_FONT = cv2.FONT_HERSHEY_SIMPLEX
_BAND_BGR = (35, 35, 35)
_TEXT_BGR = (240, 240, 240)
_MIN_WIDTH = 480


def _unit(width: int) -> float:
    """Size unit of text and glyphs: 1 up to 1200 px wide, growing beyond."""
    return max(1.0, width / 1200.0)


def _font(u: float) -> tuple[float, int]:
    return 0.5 * u, max(1, round(u))


def _wrap(text: str, width: int, scale: float, thick: int) -> list[str]:
    """Text split into lines of at most ``width`` pixels, at spaces and newlines."""
    lines = []
    for para in text.split("\n"):
        cur = ""
        for word in para.split(" "):
            cand = f"{cur} {word}" if cur else word
            if cur and cv2.getTextSize(cand, _FONT, scale, thick)[0][0] > width:
                lines.append(cur)
                cur = word
            else:
                cur = cand
        lines.append(cur)
    return lines


def _swatch(colour, u: float, w: float = 22) -> np.ndarray:
    g = np.empty((round(14 * u), round(w * u), 3), np.uint8)
    g[:] = colour
    g[[0, -1]] = g[:, [0, -1]] = 200
    return g


def _wall_bar(u: float, w: float = 150) -> np.ndarray:
    """Colour bar of walls from facing left (-90 deg) to facing right (+90 deg)."""
    width = round(w * u)
    az = np.radians(np.linspace(-90.0, 90.0, width))
    n = np.stack([np.sin(az), np.zeros_like(az), -np.cos(az)], 1)
    row = orientation_colours(n)
    return np.repeat(row[None], round(14 * u), axis=0)


def _dot(colour, u: float) -> np.ndarray:
    g = np.empty((round(14 * u), round(14 * u), 3), np.uint8)
    g[:] = _BAND_BGR
    c = (g.shape[1] // 2, g.shape[0] // 2)
    cv2.circle(g, c, round(5 * u), (0, 0, 0), -1, cv2.LINE_AA)
    cv2.circle(g, c, round(4 * u), colour, -1, cv2.LINE_AA)
    return g


def _outline(u: float, dashed: bool) -> np.ndarray:
    g = np.empty((round(14 * u), round(26 * u), 3), np.uint8)
    g[:] = (90, 90, 90)
    edge = np.zeros(g.shape[:2], bool)
    t = max(1, round(2 * u))
    edge[:t], edge[-t:], edge[:, :t], edge[:, -t:] = True, True, True, True
    if dashed:
        edge &= _dash_mask(g.shape[:2], u)
    g[edge] = OUTLINE_BGR
    return g


def _dash_mask(shape: tuple[int, int], u: float) -> np.ndarray:
    """(h, w) bool checkerboard of dashes (on half of an outline's pixels)."""
    yy, xx = np.indices(shape)
    return ((xx + yy) // max(2, round(5 * u))) % 2 == 0


def legend_band(width: int, caption: str, items: list[tuple[np.ndarray, str]]) -> np.ndarray:
    """(h, width, 3) BGR band: the caption (wrapped) then the legend items (glyph, text)
    flowing left to right in rows."""
    u = _unit(width)
    scale, thick = _font(u)
    pad = round(8 * u)
    (_, asc), desc = cv2.getTextSize("Ag", _FONT, scale, thick)
    line_h = asc + desc + round(4 * u)
    cap = _wrap(caption, width - 2 * pad, scale, thick) if caption else []
    rows, x, cur = [], pad, []  # the legend's rows of items (x, glyph, text)
    for glyph, text in items:
        tw = cv2.getTextSize(text, _FONT, scale, thick)[0][0]
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
    band[:] = _BAND_BGR
    y = pad
    for line in cap:
        cv2.putText(band, line, (pad, y + asc), _FONT, scale, _TEXT_BGR, thick, cv2.LINE_AA)
        y += line_h
    y += pad // 2 if rows else 0
    for row in rows:
        for x, glyph, text in row:
            gh, gw = glyph.shape[:2]
            gy, fit = y + (row_h - gh) // 2, max(0, min(gw, width - x))
            band[gy : gy + gh, x : x + fit] = glyph[:, :fit]
            ty = y + (row_h + asc - desc) // 2
            cv2.putText(
                band, text, (x + gw + round(6 * u), ty), _FONT, scale, _TEXT_BGR, thick, cv2.LINE_AA
            )
        y += row_h
    return band


def with_band(image: np.ndarray, caption: str, items: list[tuple[np.ndarray, str]]) -> np.ndarray:
    """The BGR image above its caption and legend band (the image padded on the right
    when the band needs more width)."""
    H, W = image.shape[:2]
    width = max(W, _MIN_WIDTH)
    band = legend_band(width, caption, items)
    top = np.empty((H, width, 3), np.uint8)
    top[:] = _BAND_BGR
    top[:, :W] = image
    return np.concatenate([top, band], 0)


# -- the pictures of one image -------------------------------------------------------------


def _display(rgb: np.ndarray, max_side: int | None) -> tuple[np.ndarray, float]:
    """BGR copy of the image scaled to at most max_side, and the scale."""
    bgr = _bgr(rgb)
    H, W = bgr.shape[:2]
    s = 1.0 if max_side is None or max(H, W) <= max_side else max_side / max(H, W)
    if s < 1.0:
        size = (max(1, round(W * s)), max(1, round(H * s)))
        bgr = cv2.resize(bgr, size, interpolation=cv2.INTER_AREA)
    return bgr, s


def _grid_to(grid: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """A work-grid array (nearest) on an image of shape (H, W)."""
    return cv2.resize(grid.astype(np.int16), shape[::-1], interpolation=cv2.INTER_NEAREST)


def _is_hypothesis(result, rect) -> bool:
    patches = result.planes.patches if result.planes is not None else []
    return 0 <= rect.patch_index < len(patches) and patches[rect.patch_index].axis < 0


def _draw_regions(out: np.ndarray, result, label: bool = True, thickness: float = 2) -> None:
    """Outline each rectified region of result.coverage on out (dashed: plane hypotheses
    from vanishing points) and tag it ``#i`` at its centroid."""
    if result.coverage is None or not result.rectifications:
        return
    H, W = out.shape[:2]
    u = _unit(W)
    cover = _grid_to(result.coverage, (H, W))
    c = np.pad(cover, 1, constant_values=-1)  # regions on the image's border are closed too
    edge = (c[1:-1, 1:-1] != c[1:-1, :-2]) | (c[1:-1, 1:-1] != c[1:-1, 2:])
    edge |= (c[1:-1, 1:-1] != c[:-2, 1:-1]) | (c[1:-1, 1:-1] != c[2:, 1:-1])
    edge &= cover >= 0
    t = max(1, round(thickness * u))
    edge = cv2.dilate(edge.astype(np.uint8), np.ones((t, t), np.uint8)) > 0
    hyp = np.array([_is_hypothesis(result, r) for r in result.rectifications])
    dashed = ((cover >= 0) & hyp[np.clip(cover, 0, None)]).astype(np.uint8)  # hypotheses
    dashed = cv2.dilate(dashed, np.ones((t, t), np.uint8)) > 0  # as far as their edges go
    edge &= ~dashed | _dash_mask((H, W), u)
    out[edge] = OUTLINE_BGR
    if not label:
        return
    scale, thick = _font(u)
    gh, gw = result.coverage.shape
    for i in range(len(result.rectifications)):
        ii, jj = np.nonzero(result.coverage == i)
        if not len(ii):
            continue
        x = round((jj.mean() + 0.5) * W / gw)
        y = round((ii.mean() + 0.5) * H / gh)
        text = f"#{i}"
        (tw, th), _ = cv2.getTextSize(text, _FONT, 1.4 * scale, thick + 1)
        org = (int(np.clip(x - tw // 2, 0, W - tw)), int(np.clip(y + th // 2, th, H - 1)))
        cv2.putText(out, text, org, _FONT, 1.4 * scale, (0, 0, 0), thick + 3, cv2.LINE_AA)
        cv2.putText(out, text, org, _FONT, 1.4 * scale, OUTLINE_BGR, thick + 1, cv2.LINE_AA)


def label_overlay(
    rgb: np.ndarray,
    labels: np.ndarray,
    directions: np.ndarray | None,
    alpha: float = 0.5,
    up: np.ndarray = IMAGE_UP,
) -> np.ndarray:
    """BGR image with labels (h, w) int8 (any grid covering the image) blended in, each in
    the colour of its plane's orientation (``label_colours``); non-planar pixels darkened."""
    return _overlay(_bgr(rgb), labels, directions, alpha, up)


def _overlay(bgr, labels, directions, alpha=0.5, up=IMAGE_UP) -> np.ndarray:
    H, W = bgr.shape[:2]
    lab = _grid_to(labels, (H, W))
    planar = lab >= 0
    colour = label_colours(directions, up)[np.where(planar, lab, 0)]
    blend = bgr * (1 - alpha) + colour * alpha
    return np.where(planar[..., None], blend, bgr * 0.45).astype(np.uint8)


_HORIZONTAL_TEXT = f"{HORIZONTAL_DEG:.0f}"


def _hypothesis_legend(result, u: float) -> list[tuple[np.ndarray, str]]:
    """The dashed outline's legend item, when the image has plane hypotheses."""
    if any(_is_hypothesis(result, r) for r in result.rectifications):
        return [(_outline(u, True), "dashed: plane hypothesis from vanishing points")]
    return []


def _plane_legend(u: float) -> list[tuple[np.ndarray, str]]:
    return [
        (_swatch(GROUND_BGR, u), f"ground (normal within {_HORIZONTAL_TEXT} deg of up)"),
        (_swatch(CEILING_BGR, u), "ceiling"),
        (_wall_bar(u), "wall facing left / camera / right"),
    ]


def draw_planes(rgb: np.ndarray, result, name: str = "", max_side: int | None = None):
    """The planes picture: labels coloured by orientation, rectified regions outlined and
    tagged, with its caption and legend; BGR."""
    bgr, _ = _display(rgb, max_side)
    planes = result.planes
    out = _overlay(bgr, planes.labels, planes.directions)
    _draw_regions(out, result)
    u = _unit(max(out.shape[1], _MIN_WIDTH))
    planar = float((planes.labels >= 0).mean()) * 100
    n = len(result.rectifications)
    caption = (
        f"{name + ': ' if name else ''}planes coloured by the way they face "
        f"(camera frame; no gravity: up = the image's up). {planar:.0f}% of the image on "
        + (
            f"planes; {n} rectified region{'s' if n != 1 else ''} outlined, #i as in the "
            "patches picture."
            if n
            else "planes; no patch worth rectifying (near-frontal or textureless): plain SIFT."
        )
    )
    items = _plane_legend(u) + [
        (_swatch((int(128 * 0.45),) * 3, u), "no plane"),
        (_outline(u, False), "rectified region #i"),
    ]
    return with_band(out, caption, items + _hypothesis_legend(result, u))


def _stamp(out: np.ndarray, xy: np.ndarray, radius: float, colour) -> None:
    """Filled discs at (N, 2) OpenCV points (vectorised over points)."""
    if not len(xy):
        return
    H, W = out.shape[:2]
    r = int(np.ceil(radius))
    dy, dx = np.mgrid[-r : r + 1, -r : r + 1]
    disc = dx**2 + dy**2 <= radius**2 + 0.25
    offs = np.stack([dx[disc], dy[disc]], 1)
    p = (np.round(xy).astype(np.int64)[:, None, :] + offs[None]).reshape(-1, 2)
    ok = (p[:, 0] >= 0) & (p[:, 0] < W) & (p[:, 1] >= 0) & (p[:, 1] < H)
    out[p[ok, 1], p[ok, 0]] = colour


def _dots(out: np.ndarray, xy: np.ndarray, colour, radius: float) -> None:
    _stamp(out, xy, radius + 1, (0, 0, 0))
    _stamp(out, xy, radius, colour)


def draw_overview(rgb: np.ndarray, result, name: str = "", max_side: int | None = None):
    """The overview picture: plain SIFT keypoints in blue, rectified ones in orange,
    rectified regions outlined, counts in the caption; BGR."""
    bgr, s = _display(rgb, max_side)
    out = (bgr * 0.8).astype(np.uint8)
    _draw_regions(out, result, label=False, thickness=1)
    f = result.features
    rect = f.patch >= 0
    xy = to_opencv_points(f.keypoints * s)
    radius = 2.5 * _unit(out.shape[1])
    _dots(out, xy[~rect], PLAIN_BGR, radius)
    _dots(out, xy[rect], RECTIFIED_BGR, radius)
    n_rect = int(rect.sum())
    per = [
        f"#{i} {int((f.patch == r.patch_index).sum())}" for i, r in enumerate(result.rectifications)
    ]
    caption = f"{name + ': ' if name else ''}{len(f)} features: {len(f) - n_rect} plain SIFT"
    caption += f" (blue), {n_rect} found in rectified patches (orange)"
    if per:
        caption += f", per patch: {', '.join(per)}."
    elif result.planes is None:
        caption += "; no depth or no planes: plain SIFT only."
    else:
        caption += "; no patch worth rectifying: plain SIFT only."
    u = _unit(max(out.shape[1], _MIN_WIDTH))
    items = [
        (_dot(PLAIN_BGR, u), f"plain SIFT ({len(f) - n_rect})"),
        (_dot(RECTIFIED_BGR, u), f"rectified ({n_rect})"),
        (_outline(u, False), "rectified region"),
    ]
    return with_band(out, caption, items + _hypothesis_legend(result, u))


def _to_rectified(camera: pycolmap.Camera, rect, xy: np.ndarray) -> np.ndarray:
    """(N, 2) COLMAP pixels of the image -> (N, 2) COLMAP pixels of the rectified patch."""
    X = cam_utils.image_to_rays(camera, xy) @ (rect.K @ rect.R).T
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(X[:, 2:] > 0, X[:, :2] / X[:, 2:], np.nan)


def _tile(rgb, camera, rect, index, result, height, max_width, u) -> np.ndarray:
    """One rectified patch, scaled to ``height`` (or ``max_width``), framed in its plane
    colour, its features as dots, under a two-line header."""
    img = _bgr(warp_to_rectified(rgb, camera, rect))
    s = min(height / img.shape[0], max_width / img.shape[1])
    size = (max(1, round(img.shape[1] * s)), max(1, round(img.shape[0] * s)))
    img = cv2.resize(img, size, interpolation=cv2.INTER_AREA)
    f = result.features
    mine = f.patch == rect.patch_index
    xy = to_opencv_points(_to_rectified(camera, rect, f.keypoints[mine]) * s)
    _dots(img, xy[np.isfinite(xy).all(1)], RECTIFIED_BGR, 1.5 * u)
    hyp = _is_hypothesis(result, rect)
    colour = tuple(int(c) for c in orientation_colours(np.asarray(rect.normal)))
    lines = [
        f"#{index}{' VP hypothesis' if hyp else ''}: {orientation_text(rect.normal)}",
        f"tilt {tilt_deg(rect.normal):.0f} deg, {int(mine.sum())} features",
    ]
    scale, thick = _font(u)
    pad = round(6 * u)
    (_, asc), desc = cv2.getTextSize("Ag", _FONT, scale, thick)
    line_h = asc + desc + round(4 * u)
    text_w = max(cv2.getTextSize(t, _FONT, scale, thick)[0][0] for t in lines)
    b = max(2, round(4 * u))  # frame
    w = max(img.shape[1] + 2 * b, text_w + 2 * pad)
    h = pad + 2 * line_h + img.shape[0] + 2 * b
    tile = np.empty((h, w, 3), np.uint8)
    tile[:] = _BAND_BGR
    for i, t in enumerate(lines):
        y = pad + i * line_h + asc
        cv2.putText(tile, t, (pad, y), _FONT, scale, _TEXT_BGR, thick, cv2.LINE_AA)
    y0 = pad + 2 * line_h
    frame = np.zeros((img.shape[0] + 2 * b, img.shape[1] + 2 * b), bool)
    frame[:b], frame[-b:], frame[:, :b], frame[:, -b:] = True, True, True, True
    if hyp:
        frame &= _dash_mask(frame.shape, u)
    box = tile[y0 : y0 + frame.shape[0], : frame.shape[1]]
    box[frame] = colour
    box[b:-b, b:-b] = img
    return tile


def draw_patches(
    rgb: np.ndarray,
    camera: pycolmap.Camera,
    result,
    name: str = "",
    height: int = 300,
    max_width: int = 1600,
) -> np.ndarray | None:
    """The patches picture: every rectified patch of result (``_tile``), in rows of at most
    ``max_width`` pixels, with its caption and legend; BGR, None without patches."""
    rects = result.rectifications
    if not rects:
        return None
    u = _unit(max_width)
    gap = round(8 * u)
    tiles = [_tile(rgb, camera, r, i, result, height, max_width, u) for i, r in enumerate(rects)]
    rows, cur, x = [], [], 0
    for t in tiles:
        if cur and x + t.shape[1] > max_width:
            rows.append(cur)
            cur, x = [], 0
        cur.append(t)
        x += t.shape[1] + gap
    rows.append(cur)
    width = max(sum(t.shape[1] for t in r) + gap * (len(r) - 1) for r in rows)
    parts = []
    for r in rows:
        row = np.empty((max(t.shape[0] for t in r), width, 3), np.uint8)
        row[:] = _BAND_BGR
        x = 0
        for t in r:
            row[: t.shape[0], x : x + t.shape[1]] = t
            x += t.shape[1] + gap
        parts.append(row)
    mosaic = np.concatenate(parts, 0)
    u = _unit(max(width, _MIN_WIDTH))
    caption = (
        f"{name + ': ' if name else ''}the {len(rects)} rectified patch"
        f"{'es' if len(rects) != 1 else ''}: fronto-parallel views of each plane "
        "(black = outside the patch). Header: #i (region #i in the planes picture), the plane's "
        "orientation (up = the image's up), tilt = angle between the plane and the image "
        "plane (0-90 deg), the features it contributed (orange dots)."
    )
    items = _plane_legend(u) + [
        (_dot(RECTIFIED_BGR, u), "feature from this patch"),
    ]
    return with_band(mosaic, caption, items + _hypothesis_legend(result, u))


def save_visualizations(
    out_dir: Path,
    name: str,
    rgb: np.ndarray,
    camera: pycolmap.Camera,
    result,
    max_side: int | None = DISPLAY_MAX_SIDE,
) -> list[Path]:
    """Write the PNGs of one image (an ImageResult): overview always, planes and patches
    when it has them; returns their paths."""
    out_dir = Path(out_dir)
    stem = name.replace("/", "_")
    written = [
        save_png(out_dir / f"{stem}.overview.png", draw_overview(rgb, result, name, max_side))
    ]
    if result.planes is not None:
        picture = draw_planes(rgb, result, name, max_side)
        written.append(save_png(out_dir / f"{stem}.planes.png", picture))
    mosaic = draw_patches(rgb, camera, result, name, max_width=max_side or 1600)
    if mosaic is not None:
        written.append(save_png(out_dir / f"{stem}.patches.png", mosaic))
    return written


# -- vanishing points ---------------------------------------------------------------------

_VP_BGR = np.array([[60, 60, 235], [60, 210, 60], [235, 130, 40]])  # red, green, blue


def _bgr(image: np.ndarray) -> np.ndarray:
    return (
        cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
        if image.ndim == 2
        else cv2.cvtColor(image, cv2.COLOR_RGB2BGR)
    )


def _cv_pt(xy: np.ndarray) -> tuple[int, int]:
    p = np.round(to_opencv_points(xy) * 16).astype(int)  # 4 fractional bits
    return int(p[0]), int(p[1])


def draw_segments(image: np.ndarray, result: VpResult) -> np.ndarray:
    """BGR image (darkened) with segments coloured by VP (red/green/blue = frame rows 0/1/2,
    grey = none)."""
    out = (_bgr(image) * 0.5).astype(np.uint8)
    seg = result.segments
    for xy, lab in zip(seg.xy, seg.labels):
        colour = (150, 150, 150) if lab < 0 else tuple(int(c) for c in _VP_BGR[lab])
        cv2.line(out, _cv_pt(xy[0]), _cv_pt(xy[1]), colour, 2, cv2.LINE_AA, shift=4)
    return out


def draw_directions(
    image: np.ndarray,
    camera: pycolmap.Camera,
    result: VpResult,
    depth_directions: np.ndarray | None = None,
    grid: int = 6,
) -> np.ndarray:
    """BGR image with, at a grid of anchors, needles pointing to each direction's VP:
    thick = fused directions (or the frame), thin white = the depth directions."""
    out = (_bgr(image) * 0.6).astype(np.uint8)
    W, H = camera.width, camera.height
    length = 0.04 * max(W, H)
    anchors = pixel_centers(grid, max(2, grid * H // W), W, H).reshape(-1, 2)
    rays = cam_utils.image_to_rays(camera, anchors)

    def needles(D, colours, thickness):
        for d, colour in zip(D, colours):
            tip = cam_utils.rays_to_image(camera, rays + 1e-3 * d)
            u = tip - anchors
            u /= np.maximum(np.linalg.norm(u, axis=1, keepdims=True), 1e-12)
            for p, q in zip(anchors - length * u, anchors + length * u):
                if np.isfinite(p).all() and np.isfinite(q).all():
                    cv2.line(out, _cv_pt(p), _cv_pt(q), colour, thickness, cv2.LINE_AA, shift=4)

    D = result.directions if result.directions is not None else result.frame
    if D is not None:
        needles(D, [tuple(int(c) for c in col) for col in _VP_BGR], 3)
    if depth_directions is not None:
        needles(depth_directions, [(255, 255, 255)] * 3, 1)
    return out


def save_png(path: Path | str, image: np.ndarray) -> Path:
    """Write a BGR (H, W, 3) or gray (H, W) uint8 image as PNG (parent folders created);
    returns the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), image):
        raise OSError(f"{path}: cannot write PNG")
    return path
