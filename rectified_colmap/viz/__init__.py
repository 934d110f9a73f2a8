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

Modules: ``colours`` (orientation -> colour), ``legend`` (caption and legend bands); the
pictures and ``save_png`` here.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pycolmap

from .. import camera as cam_utils
from ..conventions import to_opencv_points
from ..rectify import warp_to_rectified
from .colours import (
    CEILING_BGR,
    DISPLAY_MAX_SIDE,
    GROUND_BGR,
    HORIZONTAL_DEG,
    IMAGE_UP,
    NONE_BGR,
    OUTLINE_BGR,
    PLAIN_BGR,
    RECTIFIED_BGR,
    label_colours,
    orientation_colours,
    orientation_kind,
    orientation_text,
    tilt_deg,
    wall_hue_deg,
)
from .legend import (
    BAND_BGR,
    FONT,
    MIN_WIDTH,
    TEXT_BGR,
    dash_mask,
    dot,
    font,
    legend_band,
    outline,
    size_unit,
    swatch,
    wall_bar,
    with_band,
)

__all__ = [
    "BAND_BGR",
    "CEILING_BGR",
    "DISPLAY_MAX_SIDE",
    "GROUND_BGR",
    "HORIZONTAL_DEG",
    "IMAGE_UP",
    "NONE_BGR",
    "OUTLINE_BGR",
    "PLAIN_BGR",
    "RECTIFIED_BGR",
    "bgr_image",
    "draw_overview",
    "draw_patches",
    "draw_planes",
    "label_colours",
    "label_overlay",
    "legend_band",
    "orientation_colours",
    "orientation_kind",
    "orientation_text",
    "save_png",
    "save_visualizations",
    "tilt_deg",
    "wall_hue_deg",
    "with_band",
]


def bgr_image(image: np.ndarray) -> np.ndarray:
    """A grayscale (H, W) or RGB (H, W, 3) uint8 image as BGR (H, W, 3)."""
    return (
        cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
        if image.ndim == 2
        else cv2.cvtColor(image, cv2.COLOR_RGB2BGR)
    )


def _display(rgb: np.ndarray, max_side: int | None) -> tuple[np.ndarray, float]:
    """BGR copy of the image scaled to at most max_side, and the scale."""
    bgr = bgr_image(rgb)
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
    u = size_unit(W)
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
    edge &= ~dashed | dash_mask((H, W), u)
    out[edge] = OUTLINE_BGR
    if not label:
        return
    scale, thick = font(u)
    gh, gw = result.coverage.shape
    for i in range(len(result.rectifications)):
        ii, jj = np.nonzero(result.coverage == i)
        if not len(ii):
            continue
        x = round((jj.mean() + 0.5) * W / gw)
        y = round((ii.mean() + 0.5) * H / gh)
        text = f"#{i}"
        (tw, th), _ = cv2.getTextSize(text, FONT, 1.4 * scale, thick + 1)
        org = (int(np.clip(x - tw // 2, 0, W - tw)), int(np.clip(y + th // 2, th, H - 1)))
        cv2.putText(out, text, org, FONT, 1.4 * scale, (0, 0, 0), thick + 3, cv2.LINE_AA)
        cv2.putText(out, text, org, FONT, 1.4 * scale, OUTLINE_BGR, thick + 1, cv2.LINE_AA)


def label_overlay(
    rgb: np.ndarray,
    labels: np.ndarray,
    directions: np.ndarray | None,
    alpha: float = 0.5,
    up: np.ndarray = IMAGE_UP,
) -> np.ndarray:
    """BGR image with labels (h, w) int8 (any grid covering the image) blended in, each in
    the colour of its plane's orientation (``label_colours``); non-planar pixels darkened."""
    return _overlay(bgr_image(rgb), labels, directions, alpha, up)


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
        return [(outline(u, True), "dashed: plane hypothesis from vanishing points")]
    return []


def _plane_legend(u: float) -> list[tuple[np.ndarray, str]]:
    return [
        (swatch(GROUND_BGR, u), f"ground (normal within {_HORIZONTAL_TEXT} deg of up)"),
        (swatch(CEILING_BGR, u), "ceiling"),
        (wall_bar(u), "wall facing left / camera / right"),
    ]


def draw_planes(rgb: np.ndarray, result, name: str = "", max_side: int | None = None):
    """The planes picture: labels coloured by orientation, rectified regions outlined and
    tagged, with its caption and legend; BGR."""
    bgr, _ = _display(rgb, max_side)
    planes = result.planes
    out = _overlay(bgr, planes.labels, planes.directions)
    _draw_regions(out, result)
    u = size_unit(max(out.shape[1], MIN_WIDTH))
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
        (swatch((int(128 * 0.45),) * 3, u), "no plane"),
        (outline(u, False), "rectified region #i"),
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
    radius = 2.5 * size_unit(out.shape[1])
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
    u = size_unit(max(out.shape[1], MIN_WIDTH))
    items = [
        (dot(PLAIN_BGR, u), f"plain SIFT ({len(f) - n_rect})"),
        (dot(RECTIFIED_BGR, u), f"rectified ({n_rect})"),
        (outline(u, False), "rectified region"),
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
    img = bgr_image(warp_to_rectified(rgb, camera, rect))
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
    scale, thick = font(u)
    pad = round(6 * u)
    (_, asc), desc = cv2.getTextSize("Ag", FONT, scale, thick)
    line_h = asc + desc + round(4 * u)
    text_w = max(cv2.getTextSize(t, FONT, scale, thick)[0][0] for t in lines)
    b = max(2, round(4 * u))  # frame
    w = max(img.shape[1] + 2 * b, text_w + 2 * pad)
    h = pad + 2 * line_h + img.shape[0] + 2 * b
    tile = np.empty((h, w, 3), np.uint8)
    tile[:] = BAND_BGR
    for i, t in enumerate(lines):
        y = pad + i * line_h + asc
        cv2.putText(tile, t, (pad, y), FONT, scale, TEXT_BGR, thick, cv2.LINE_AA)
    y0 = pad + 2 * line_h
    frame = np.zeros((img.shape[0] + 2 * b, img.shape[1] + 2 * b), bool)
    frame[:b], frame[-b:], frame[:, :b], frame[:, -b:] = True, True, True, True
    if hyp:
        frame &= dash_mask(frame.shape, u)
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
    u = size_unit(max_width)
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
        row[:] = BAND_BGR
        x = 0
        for t in r:
            row[: t.shape[0], x : x + t.shape[1]] = t
            x += t.shape[1] + gap
        parts.append(row)
    mosaic = np.concatenate(parts, 0)
    u = size_unit(max(width, MIN_WIDTH))
    caption = (
        f"{name + ': ' if name else ''}the {len(rects)} rectified patch"
        f"{'es' if len(rects) != 1 else ''}: fronto-parallel views of each plane "
        "(black = outside the patch). Header: #i (region #i in the planes picture), the plane's "
        "orientation (up = the image's up), tilt = angle between the plane and the image "
        "plane (0-90 deg), the features it contributed (orange dots)."
    )
    items = _plane_legend(u) + [
        (dot(RECTIFIED_BGR, u), "feature from this patch"),
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


def save_png(path: Path | str, image: np.ndarray) -> Path:
    """Write a BGR (H, W, 3) or gray (H, W) uint8 image as PNG (parent folders created);
    returns the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), image):
        raise OSError(f"{path}: cannot write PNG")
    return path
