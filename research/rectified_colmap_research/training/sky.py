"""Sky pseudo-labels for real photos: high precision, UNKNOWN where unsure.

The depth network's sky head learns from these labels (and the evaluation masks in
``research/data/sky_masks`` are made by hand, seeded by them). A wrong label hurts more than a
missing one, so every rule only labels what it is sure of:

- SKY: smooth (low local gradient energy), sky-coloured (bluish, or a bright neutral grey /
  white; never warm or dark) pixels in a region that reaches the top border (thin gaps such
  as wires bridged), above the horizon line when one is given, away from the bottom of the
  image; the region is eroded by a margin (the boundary is uncertain) and small pieces are
  dropped;
- NOT_SKY: pixels below the horizon, the bottom part of the image, and clearly textured
  pixels (high gradient energy) that are neither near the sky candidates nor enclosed by the
  sky (clouds, branches and wires in the sky stay UNKNOWN);
- UNKNOWN (255): the rest.

Shapes: images (H, W, 3) uint8 RGB; labels (H, W) uint8. Work is done on a copy scaled so
that its longer side is at most ``work_size``; labels are upsampled nearest. numpy + OpenCV
only (no torch): it runs in data loaders and offline tools.
"""

from __future__ import annotations

import cv2
import numpy as np

SKY = 1
NOT_SKY = 0
UNKNOWN = 255


def _scaled(rgb: np.ndarray, work_size: int) -> tuple[np.ndarray, float]:
    """(H, W, 3) -> ((h, w, 3) with max(h, w) <= work_size, scale s = h / H)."""
    H, W = rgb.shape[:2]
    s = min(1.0, work_size / max(H, W))
    if s >= 1.0:
        return rgb, 1.0
    w, h = max(1, round(W * s)), max(1, round(H * s))
    return cv2.resize(rgb, (w, h), interpolation=cv2.INTER_AREA), h / H


def above_line(
    horizon: np.ndarray | tuple[float, float, float], shape: tuple[int, int], scale: float = 1.0
) -> np.ndarray:
    """Signed distance (h, w) float32 in pixels of the (scaled) grid ABOVE the horizon line
    (negative below). ``horizon`` (a, b, c): a*x + b*y + c = 0 in the full image's pixel
    coordinates (x right, y down); ``scale``: grid size / image size. "Up" is decreasing y
    (the camera is assumed not rolled by more than 90 degrees)."""
    a, b, c = (float(v) for v in np.asarray(horizon, np.float64).ravel()[:3])
    if b > 0:  # orient so that the value grows upward (toward y -> -inf)
        a, b, c = -a, -b, -c
    norm = np.hypot(a, b)
    if norm == 0:
        raise ValueError(f"degenerate horizon line {horizon}")
    h, w = shape
    xs = (np.arange(w, dtype=np.float64) + 0.5) / scale
    ys = (np.arange(h, dtype=np.float64) + 0.5) / scale
    d = (a * xs[None, :] + b * ys[:, None] + c) / norm  # in full-image pixels
    return (d * scale).astype(np.float32)


def gradient_energy(gray: np.ndarray, window: int = 5) -> np.ndarray:
    """(h, w) uint8/float gray -> (h, w) float32 local mean of the gradient magnitude
    (grey levels per pixel) of the slightly blurred image over ``window x window``."""
    g = cv2.GaussianBlur(gray.astype(np.float32), (0, 0), 1.0)
    gx = cv2.Sobel(g, cv2.CV_32F, 1, 0, ksize=3) / 8.0
    gy = cv2.Sobel(g, cv2.CV_32F, 0, 1, ksize=3) / 8.0
    mag = np.sqrt(gx * gx + gy * gy)
    return cv2.blur(mag, (window, window), borderType=cv2.BORDER_REFLECT)


def sky_colour(lab: np.ndarray) -> np.ndarray:
    """(h, w, 3) float32 Lab (OpenCV 8-bit scale: L 0..255, a and b centred on 0) -> (h, w)
    bool: bluish, or bright neutral (grey-white) relative to the image's brightest pixels;
    never warm (yellow / orange / red) or dark."""
    L, a, b = lab[..., 0], lab[..., 1], lab[..., 2]
    L_top = float(np.percentile(L, 99.0))
    blue = (b < -8.0) & (b < -0.5 * np.abs(a) - 4.0) & (L > 90.0)
    neutral = (np.abs(a) < 6.0) & (b < 6.0) & (L > max(165.0, L_top - 40.0))
    return blue | neutral


def to_lab(rgb: np.ndarray) -> np.ndarray:
    """(h, w, 3) uint8 RGB -> (h, w, 3) float32 Lab, L in 0..255, a and b centred on 0."""
    lab = cv2.cvtColor(rgb, cv2.COLOR_RGB2LAB).astype(np.float32)
    lab[..., 1:] -= 128.0
    return lab


def _remove_small(mask: np.ndarray, min_area: int) -> np.ndarray:
    num, comp, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=4)
    keep = np.zeros(num, bool)
    keep[1:] = stats[1:, cv2.CC_STAT_AREA] >= min_area
    return keep[comp]


def _main_components(
    mask: np.ndarray, lab: np.ndarray, min_area: int, min_share: float, max_colour_dist: float
) -> np.ndarray:
    """Components (4-connectivity) of ``mask``: the largest, and others of at least
    ``min_area`` pixels and ``min_share`` of the largest whose median Lab colour (``lab``
    (h, w, 3) float32) is within ``max_colour_dist`` of the largest's. Small or differently
    coloured smooth pieces (glass reflecting the sky, white panels) are not trusted."""
    num, comp, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=4)
    if num <= 1:
        return np.zeros_like(mask, bool)
    area = stats[:, cv2.CC_STAT_AREA].copy()
    area[0] = 0
    main = int(area.argmax())
    keep = area >= max(min_area, min_share * area[main])
    keep[0] = False
    ref = np.median(lab[comp == main], axis=0)
    for c in np.flatnonzero(keep):
        if c != main and np.linalg.norm(np.median(lab[comp == c], axis=0) - ref) > max_colour_dist:
            keep[c] = False
    return keep[comp]


def _touching_top(mask: np.ndarray) -> np.ndarray:
    """Connected components (4-connectivity) of ``mask`` that touch the top row."""
    num, comp = cv2.connectedComponents(mask.astype(np.uint8), connectivity=4)
    top = np.zeros(num, bool)
    top[np.unique(comp[0][mask[0]])] = True
    top[0] = False
    return top[comp]


def _touching_row(mask: np.ndarray, row: int) -> np.ndarray:
    """Connected components (4-connectivity) of ``mask`` with a pixel at or below ``row``."""
    num, comp = cv2.connectedComponents(mask.astype(np.uint8), connectivity=4)
    low = np.zeros(num, bool)
    low[np.unique(comp[row:][mask[row:]])] = True
    low[0] = False
    return low[comp]


def _enclosed(mask: np.ndarray) -> np.ndarray:
    """Pixels not in ``mask`` that cannot reach the left, right or bottom border without
    crossing it (the top border counts as part of the mask): holes of the sky."""
    padded = np.zeros((mask.shape[0] + 1, mask.shape[1] + 2), np.uint8)
    padded[0, 1:-1] = 1  # the top border is sky: things hanging into it are holes
    padded[1:, 1:-1] = mask
    free = (padded == 0).astype(np.uint8)
    num, comp = cv2.connectedComponents(free, connectivity=4)
    outside = np.unique(np.concatenate([comp[:, 0], comp[:, -1], comp[-1]]))
    hole = np.ones(num, bool)
    hole[outside] = False
    hole[0] = False
    return hole[comp][1:, 1:-1] & ~mask


def sky_pseudo_label(
    rgb: np.ndarray,
    horizon: np.ndarray | None = None,
    work_size: int = 512,
    smooth_max: float = 2.5,
    texture_min: float = 10.0,
    bottom_frac: float = 0.3,
    margin: float = 0.008,
    min_area: float = 0.01,
    min_share: float = 0.2,
    max_colour_dist: float = 12.0,
) -> np.ndarray:
    """High-precision sky labels of one photo.

    rgb: (H, W, 3) uint8 RGB. horizon: optional (3,) line (a, b, c), a*x + b*y + c = 0 in
    the image's pixel coordinates (x right, y down), e.g. eurasian-cities'
    ``horizon_abc_out``. smooth_max / texture_min: gradient energy (grey levels per pixel at
    the work size, see :func:`gradient_energy`) below which a pixel may be sky / above which
    it is textured. bottom_frac: the bottom fraction of the image is NOT_SKY. margin: width of
    the uncertain band around the sky boundary and the horizon, as a fraction of the work
    image's longer side. min_area: sky pieces smaller than this fraction of the image and
    min_share: pieces smaller than this fraction of the largest
    are left UNKNOWN, and so are those whose median Lab colour is farther than
    max_colour_dist from the largest's. Returns (H, W) uint8: SKY (1), NOT_SKY (0), UNKNOWN (255).
    """
    rgb = np.asarray(rgb)
    if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
        raise ValueError(f"sky_pseudo_label: expected (H, W, 3) uint8 RGB, got {rgb.shape}")
    H, W = rgb.shape[:2]
    small, s = _scaled(rgb, work_size)
    h, w = small.shape[:2]
    m = max(1, round(margin * max(h, w)))
    gray = cv2.cvtColor(small, cv2.COLOR_RGB2GRAY)
    energy = gradient_energy(gray)

    rows = np.arange(h, dtype=np.float32)[:, None]
    bottom = np.broadcast_to(rows >= (1.0 - bottom_frac) * h, (h, w))
    if horizon is not None:
        up = above_line(horizon, (h, w), s)
        below, near_horizon = up < -m, up < m
    else:
        below = near_horizon = np.zeros((h, w), bool)

    lab = to_lab(small)
    colour = sky_colour(lab)
    cand = (energy < smooth_max) & colour & ~near_horizon & ~bottom
    # Bridge thin interruptions (wires, lamp posts' arms, faint cloud edges) for connectivity.
    bridged = (
        cv2.morphologyEx(
            cand.astype(np.uint8),
            cv2.MORPH_CLOSE,
            cv2.getStructuringElement(cv2.MORPH_RECT, (3, 7)),
        ).astype(bool)
        & ~near_horizon
        & ~bottom
    )
    region = _touching_top(bridged) & cand
    # Sky ends above the skyline: a smooth region reaching down to the bottom part is a wall.
    region &= ~_touching_row(region, max(0, int(np.ceil((1.0 - bottom_frac) * h)) - m - 1))
    region = _main_components(
        region, lab, max(16, int(min_area * h * w)), min_share, max_colour_dist
    )
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * m + 1, 2 * m + 1))
    sky = cv2.erode(region.astype(np.uint8), kernel, borderType=cv2.BORDER_REPLICATE) > 0
    sky = _remove_small(sky, max(16, int(min_area * h * w)))

    near_cand = cv2.dilate(cand.astype(np.uint8), kernel, iterations=2) > 0
    # Sky-coloured texture near the sky: branches or clouds with sky between them.
    dist = cv2.distanceTransform((~region).astype(np.uint8), cv2.DIST_L2, 3)
    tree_gaps = colour & (dist < 0.08 * max(h, w))
    textured = (energy > texture_min) & ~near_cand & ~_enclosed(region) & ~tree_gaps
    not_sky = below | bottom | textured

    out = np.full((h, w), UNKNOWN, np.uint8)
    out[not_sky] = NOT_SKY
    out[sky & ~not_sky] = SKY
    if (h, w) != (H, W):
        out = cv2.resize(out, (W, H), interpolation=cv2.INTER_NEAREST)
    return out
