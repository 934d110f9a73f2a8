"""SIFT features: COLMAP's SIFT through pycolmap, budgets, masks, and the Features container.

Keypoints are in COLMAP pixel convention in the ORIGINAL image. Each keypoint carries its
affine frame A (2x2; COLMAP's a11 a12 a21 a22): for a plain SIFT keypoint of scale s and
orientation t, A = s [[cos t, -sin t], [sin t, cos t]]; for a keypoint found in a rectified
patch, A = J A_rect, where J is the Jacobian of the rectified->image map at the keypoint.
Descriptors are uint8 (N, 128), RootSIFT in COLMAP's byte scale (L2 norm ~512).
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass

import cv2
import numpy as np
import pycolmap

from .config import SiftConf
from .geometry import scaled_size
from .rectify import Rectification, rectified_to_image, warp_to_rectified


@dataclass
class Features:
    keypoints: np.ndarray
    """(N, 2) float64, COLMAP convention, original image pixels."""
    shapes: np.ndarray
    """(N, 2, 2) float64 affine frames [[a11, a12], [a21, a22]]."""
    descriptors: np.ndarray
    """(N, 128) uint8, COLMAP scale."""
    patch: np.ndarray
    """(N,) int32: -1 = plain SIFT on non-planar pixels, k >= 0 = rectified patch k."""

    def __len__(self) -> int:
        return len(self.keypoints)

    @property
    def scales(self) -> np.ndarray:
        """(N,) COLMAP scale: mean norm of the frame's columns."""
        return 0.5 * (
            np.linalg.norm(self.shapes[:, :, 0], axis=1)
            + np.linalg.norm(self.shapes[:, :, 1], axis=1)
        )

    @property
    def orientations(self) -> np.ndarray:
        """(N,) orientation in radians, atan2(a21, a11) as COLMAP."""
        return np.arctan2(self.shapes[:, 1, 0], self.shapes[:, 0, 0])

    def colmap_keypoints(self) -> np.ndarray:
        """(N, 6) float32 [x, y, a11, a12, a21, a22] for a COLMAP database."""
        return np.concatenate([self.keypoints, self.shapes.reshape(-1, 4)], 1).astype(np.float32)

    @classmethod
    def empty(cls) -> "Features":
        return cls(
            np.zeros((0, 2)),
            np.zeros((0, 2, 2)),
            np.zeros((0, 128), np.uint8),
            np.zeros(0, np.int32),
        )

    @classmethod
    def concatenate(cls, parts: list["Features"]) -> "Features":
        if not parts:
            return cls.empty()
        return cls(
            *(
                np.concatenate([getattr(p, f) for p in parts])
                for f in ("keypoints", "shapes", "descriptors", "patch")
            )
        )

    def subset(self, index: np.ndarray) -> "Features":
        return Features(
            self.keypoints[index], self.shapes[index], self.descriptors[index], self.patch[index]
        )


MIN_SIFT_SIDE = 16
"""Images (and rectified views) with a shorter side get no SIFT features."""


def similarity_frames(scales: np.ndarray, orientations: np.ndarray) -> np.ndarray:
    """(N,) scales and orientations (rad) -> (N, 2, 2) frames s [[cos, -sin], [sin, cos]]."""
    c, s = np.cos(orientations), np.sin(orientations)
    return scales[:, None, None] * np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)


# Live pycolmap SIFT extractors per slot, least recently used first. Each one keeps VLFeat's
# scale space for the last image it saw (about 18 float32 images of the first octave: 288
# bytes per pixel at first_octave = -1, ~450 MB for 1536x1024, ~2 GB for 3200x2133) and
# reuses it for the next image of that size; a new scale space costs its page faults
# (~0.25-0.5 CPU s at 1536x1024). The budget (max_num_features) is fixed in an extractor's
# options, so a cache per budget held one scale space per distinct budget. Now each slot
# keeps at most MAX_LIVE_EXTRACTORS[slot], and an evicted one is destroyed BEFORE the next is
# created. Slot "image" (whole images: one budget, and the coarse and fine calls of
# coarse-first) stays warm from one same-size photo to the next, as in COLMAP's extractor;
# slot "patch" (rectified patches, a new size and budget each) holds one.
MAX_LIVE_EXTRACTORS = {"image": 2, "patch": 1}
_EXTRACTORS: dict[str, OrderedDict[tuple, object]] = {
    slot: OrderedDict() for slot in MAX_LIVE_EXTRACTORS
}
_DEFAULT_NUM_OCTAVES = pycolmap.SiftExtractionOptions().num_octaves


def live_extractors() -> int:
    """Number of pycolmap SIFT extractors alive in this process (at most the sum of
    MAX_LIVE_EXTRACTORS)."""
    return sum(len(cache) for cache in _EXTRACTORS.values())


def release_extractors() -> None:
    """Destroy every cached SIFT extractor (and the scale-space memory it holds)."""
    for cache in _EXTRACTORS.values():
        cache.clear()


def retain_freed_memory() -> bool:
    """Make this process keep the memory it frees for reuse instead of returning it to the
    system (glibc: no mmap for large blocks, no heap trimming). Returns False where this is
    not glibc (nothing changed).

    Every new pycolmap extractor, and every image of a new size, allocates a fresh scale
    space (~450 MB at 1536x1024); glibc maps such blocks anew and unmaps them when freed, so
    the kernel faults in and zeroes every page again: ~0.1-0.5 s of system time per image
    and patch. With this, the pages are reused: resident memory stays at the process's peak
    instead of falling back between images (the peak itself does not change). Process-wide
    and irreversible: meant for extraction workers, not for library imports."""
    import ctypes
    import ctypes.util

    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    M_TRIM_THRESHOLD, M_MMAP_MAX = -1, -4
    return bool(mallopt(M_MMAP_MAX, 0)) and bool(mallopt(M_TRIM_THRESHOLD, 2**31 - 1))


def _extractor(
    conf: SiftConf,
    max_num_features: int,
    first_octave: int,
    num_octaves: int = _DEFAULT_NUM_OCTAVES,
    slot: str = "image",
):
    cache = _EXTRACTORS[slot]
    key = (
        conf.peak_threshold,
        conf.edge_threshold,
        conf.max_num_orientations,
        conf.upright,
        int(max_num_features),
        int(first_octave),
        int(num_octaves),
    )
    ex = cache.pop(key, None)
    if ex is None:
        while len(cache) >= max(1, MAX_LIVE_EXTRACTORS[slot]):
            cache.popitem(last=False)  # destroyed here, before the new one allocates
        opts = pycolmap.FeatureExtractionOptions()
        opts.num_threads = 1
        sift = opts.sift
        sift.max_num_features = int(max_num_features)
        sift.first_octave = int(first_octave)
        sift.num_octaves = int(num_octaves)
        sift.peak_threshold = conf.peak_threshold
        sift.edge_threshold = conf.edge_threshold
        sift.max_num_orientations = conf.max_num_orientations
        sift.upright = conf.upright
        ex = pycolmap.FeatureExtractor.create(opts, pycolmap.Device.cpu)
    cache[key] = ex  # most recently used last
    return ex


def _run_sift(
    image: np.ndarray,
    conf: SiftConf,
    n: int,
    first_octave: int,
    num_octaves: int = _DEFAULT_NUM_OCTAVES,
    slot: str = "image",
) -> tuple[np.ndarray, np.ndarray]:
    """One pycolmap SIFT call on a contiguous (h, w) uint8 image -> ((N, 4) float64
    [x, y, scale, orientation] in COLMAP convention, (N, 128) uint8 descriptors), in COLMAP's
    order: DoG level by DoG level, finest first."""
    ex = _extractor(conf, n, first_octave, num_octaves, slot)
    kps, desc = ex.extract_from_uint8_array(image)
    if len(kps) == 0:
        return np.zeros((0, 4)), np.zeros((0, 128), np.uint8)
    m = np.asarray(pycolmap.keypoints_to_matrix(kps), dtype=np.float64)
    return m, np.ascontiguousarray(desc.data, dtype=np.uint8)


def count_detections(m: np.ndarray) -> int:
    """Number of detected points in COLMAP SIFT output (N, >=3) [x, y, scale, ...]: a point
    with several orientations is output as consecutive rows with equal x, y and scale.
    COLMAP's max_num_features counts these points, not the rows."""
    if len(m) == 0:
        return 0
    return 1 + int(np.any(m[1:, :3] != m[:-1, :3], axis=1).sum())


def _sift_coarse_first(
    image: np.ndarray, conf: SiftConf, n: int, first_octave: int, slot: str = "image"
) -> tuple[np.ndarray, np.ndarray]:
    """About the output of COLMAP SIFT with budget n and ``first_octave``, skipping the first
    octave (4x the pixels of the next: ~3/4 of the cost) when the budget does not reach it.

    COLMAP keeps whole DoG levels from the coarsest down until more than n points are kept
    (src/colmap/feature/sift.cc, SiftCPUFeatureExtractor::Extract), so its output contains
    first-octave points only when the coarser octaves hold at most n points. Step 1 runs the
    coarser octaves alone (first_octave + 1, one octave fewer: the same octaves); when they
    hold more than n points they are the answer. Otherwise step 2 runs the first octave
    alone with the budget left (n - points of step 1), which keeps its levels by the same
    rule, and the two are joined finest first. Every call so costs at most about one
    ordinary call. Not bit-identical to one call: the coarser octaves are computed from the
    image instead of from the upsampled first octave (on Strecha photos ~95% of the points
    coincide within 0.5 px and 5% in scale)."""
    num_octaves = _DEFAULT_NUM_OCTAVES
    if num_octaves < 2:
        return _run_sift(image, conf, n, first_octave, num_octaves, slot)
    coarse = _run_sift(image, conf, n, first_octave + 1, num_octaves - 1, slot)
    found = count_detections(coarse[0])
    if found > n:
        return coarse
    fine = _run_sift(image, conf, max(1, n - found), first_octave, 1, slot)
    return np.concatenate([fine[0], coarse[0]]), np.concatenate([fine[1], coarse[1]])


def detect_sift(
    image: np.ndarray,
    conf: SiftConf = SiftConf(),
    max_num_features: int | None = None,
    first_octave: int | None = None,
    coarse_first: bool = False,
    slot: str = "image",
) -> Features:
    """COLMAP SIFT on a grayscale uint8 image (h, w); keypoints in that image's frame.

    Images larger than ``conf.max_image_size`` are downscaled first, as COLMAP does, and the
    keypoints scaled back. Returns Features with ``patch = -1``.

    coarse_first: with a negative first octave, compute the upsampled first octave only
    when the budget reaches it (see ``_sift_coarse_first``): the same points as one pycolmap
    call up to small differences, at ~1/4 of the cost when the budget is filled by the
    coarser octaves. False (default): exactly one pycolmap call with these options.
    slot: the extractor cache to use (``MAX_LIVE_EXTRACTORS``): "image" for whole images,
    "patch" for rectified patches, so that patches do not evict the whole image's extractor.
    """
    if image.ndim != 2 or image.dtype != np.uint8:
        raise ValueError(f"SIFT needs a (h, w) uint8 image, got {image.shape} {image.dtype}")
    n = conf.max_num_features if max_num_features is None else max_num_features
    if n <= 0 or min(image.shape) < MIN_SIFT_SIDE:
        return Features.empty()
    sx = sy = 1.0
    h, w = image.shape
    nw, nh = sift_input_size(w, h, conf)
    if (nw, nh) != (w, h):
        image = cv2.resize(image, (nw, nh), interpolation=cv2.INTER_AREA)
        sx, sy = w / nw, h / nh
    image = np.ascontiguousarray(image)
    fo = conf.first_octave if first_octave is None else first_octave
    if coarse_first and fo < 0:
        m, desc = _sift_coarse_first(image, conf, n, fo, slot)
    else:
        m, desc = _run_sift(image, conf, n, fo, slot=slot)
    if len(m) == 0:
        return Features.empty()
    xy = m[:, :2] * [sx, sy]  # COLMAP convention: rescaling is a plain multiplication
    shapes = similarity_frames(m[:, 2], m[:, 3]) * np.array([[sx], [sy]])
    return Features(xy, shapes, desc, np.full(len(m), -1, np.int32))


def coarse_first_pays(
    shape: tuple[int, int], max_num_features: int, conf: SiftConf = SiftConf()
) -> bool:
    """Whether ``detect_sift`` should run ``coarse_first`` on an image of ``shape`` (h, w)
    with this budget: ``conf.coarse_first`` and at least
    ``conf.coarse_first_pixels_per_feature`` pixels per feature after SIFT's downscaling to
    ``conf.max_image_size`` (there the coarser octaves fill the budget)."""
    w, h = sift_input_size(shape[1], shape[0], conf)
    return bool(conf.coarse_first) and w * h >= conf.coarse_first_pixels_per_feature * max(
        1, max_num_features
    )


def pool_coarse_first(
    shape: tuple[int, int], max_num_features: int, conf: SiftConf = SiftConf()
) -> bool:
    """``coarse_first_pays`` for plain SIFT on the whole image of ``shape`` (the pool), on
    images of at least ``conf.pool_coarse_first_min_pixels`` (after SIFT's downscaling),
    unless ``conf.pool_coarse_first`` is off; else exact COLMAP calls: exactly plain SIFT's
    features."""
    w, h = sift_input_size(shape[1], shape[0], conf)
    return (
        bool(conf.pool_coarse_first)
        and w * h >= conf.pool_coarse_first_min_pixels
        and coarse_first_pays(shape, max_num_features, conf)
    )


def patch_first_octave(
    shape: tuple[int, int], max_num_features: int, conf: SiftConf = SiftConf()
) -> int:
    """first_octave of SIFT in the rectified patches of an image of ``shape`` (h, w) with
    this budget: 0 from ``conf.patch_octave0_pixels_per_feature`` pixels per feature (after
    SIFT's downscaling to ``conf.max_image_size``) up to where ``coarse_first`` pays (there
    it already skips the upsampled octave wherever a patch's coarser octaves fill its
    budget), else ``conf.patch_first_octave``."""
    w, h = sift_input_size(shape[1], shape[0], conf)
    n = max(1, max_num_features)
    if w * h >= conf.patch_octave0_pixels_per_feature * n and not coarse_first_pays(shape, n, conf):
        return max(0, conf.patch_first_octave)
    return conf.patch_first_octave


def sift_input_size(width: int, height: int, conf: SiftConf = SiftConf()) -> tuple[int, int]:
    """(w, h) of the image SIFT sees: downscaled to ``conf.max_image_size`` when larger,
    as COLMAP does (``geometry.scaled_size``, at least 1 px a side)."""
    if conf.max_image_size > 0 and max(width, height) > conf.max_image_size:
        return scaled_size(width, height, conf.max_image_size, min_side=1)
    return width, height


def split_budget(total: int, areas: np.ndarray, minimum: int = 64) -> np.ndarray:
    """Share a feature budget between regions in proportion to their areas (int array).

    Regions with any area get at least ``minimum`` (when the budget allows)."""
    areas = np.asarray(areas, dtype=np.float64)
    if areas.sum() <= 0:
        return np.zeros(len(areas), dtype=int)
    share = total * areas / areas.sum()
    share = np.where(areas > 0, np.maximum(share, min(minimum, total / max(len(areas), 1))), 0)
    share *= total / share.sum()
    return np.floor(share).astype(int)


def keypoints_in_mask(xy: np.ndarray, mask: np.ndarray, image_size: tuple[int, int]) -> np.ndarray:
    """(N,) bool: COLMAP-convention points of an image of size (W, H) that fall on True
    cells of ``mask`` (h, w), a grid covering that image (nearest cell)."""
    W, H = image_size
    h, w = mask.shape
    col = np.floor(xy[:, 0] * (w / W)).astype(int)
    row = np.floor(xy[:, 1] * (h / H)).astype(int)
    inside = (col >= 0) & (col < w) & (row >= 0) & (row < h)
    out = np.zeros(len(xy), dtype=bool)
    out[inside] = mask[row[inside], col[inside]]
    return out


def rectification_budgets(masks: np.ndarray, total: int, keep_plain: bool) -> np.ndarray:
    """(n + 1,) feature budgets [plain, rect 0, ...] summing to at most ``total``, for the
    (n, h, w) bool viewing masks of n rectifications (rectify.viewing_masks).

    Shares follow areas: plain SIFT gets the uncovered cells (with keep_plain: all cells,
    the covered ones at half weight), the rectifications the covered cells (half weight
    with keep_plain). When rectifications overlap, the share of the covered cells (their
    union) is split between them in proportion to each one's own covered area; without
    overlap this is each one's own area. So plain SIFT's share, and the total, never
    depend on the overlap."""
    own = masks.reshape(len(masks), -1).sum(1).astype(float)
    union = float(masks.any(0).sum())
    cells = masks.shape[1] * masks.shape[2]
    areas = np.concatenate([[cells - union], own * union / max(own.sum(), 1.0)])
    if keep_plain:  # rectified pixels share their budget with plain SIFT
        areas[0] += areas[1:].sum() / 2
        areas[1:] /= 2
    return split_budget(total, areas)


def plain_features(
    gray: np.ndarray, region: np.ndarray, budget: int, conf: SiftConf, margin: int = 16
) -> Features:
    """About ``budget`` plain SIFT features on the pixels of ``region`` (a grid covering the
    image), detected on the region's bounding box only."""
    H, W = gray.shape
    h, w = region.shape
    rows, cols = np.flatnonzero(region.any(1)), np.flatnonzero(region.any(0))
    x0 = max(0, int(np.floor(cols[0] * W / w)) - margin)
    x1 = min(W, int(np.ceil((cols[-1] + 1) * W / w)) + margin)
    y0 = max(0, int(np.floor(rows[0] * H / h)) - margin)
    y1 = min(H, int(np.ceil((rows[-1] + 1) * H / h)) + margin)
    box = region[
        int(y0 * h / H) : int(np.ceil(y1 * h / H)), int(x0 * w / W) : int(np.ceil(x1 * w / W))
    ]
    n = round(budget * box.size / max(region.sum(), 1))  # SIFT's budget covers the whole box
    box_img = np.ascontiguousarray(gray[y0:y1, x0:x1])
    feats = detect_sift(box_img, conf, n, coarse_first=pool_coarse_first(box_img.shape, n, conf))
    feats.keypoints += [x0, y0]  # integer offset: the same in every pixel convention
    return feats.subset(keypoints_in_mask(feats.keypoints, region, (W, H)))


def rectified_features(
    gray: np.ndarray,
    camera: pycolmap.Camera,
    rect: Rectification,
    index: int,
    budget: int,
    conf: SiftConf,
    border: int,
) -> Features:
    """SIFT inside one rectified patch (``budget`` features, from the octave
    ``patch_first_octave`` gives the whole image ``gray`` with ``conf``'s budget), mapped
    back to the original image; features closer than ``border`` rectified pixels to the
    border of the warped region are dropped. ``index`` is their source."""
    first_octave = patch_first_octave(gray.shape, conf.max_num_features, conf)
    patch_img = warp_to_rectified(gray, camera, rect)
    feats = detect_sift(
        patch_img,
        conf,
        budget,
        first_octave,
        coarse_first=coarse_first_pays(patch_img.shape, budget, conf),
        slot="patch",
    )
    if len(feats) == 0:
        return feats
    valid = rect.mask.astype(np.uint8)
    if border > 0:
        valid = cv2.erode(
            valid,
            np.ones((2 * border + 1, 2 * border + 1), np.uint8),
            borderType=cv2.BORDER_CONSTANT,
            borderValue=0,
        )
    keep = keypoints_in_mask(feats.keypoints, valid.astype(bool), rect.size)
    feats = feats.subset(keep)
    xy, J = rectified_to_image(camera, rect, feats.keypoints)
    inside = (
        np.isfinite(xy).all(1)
        & (xy[:, 0] >= 0)
        & (xy[:, 1] >= 0)
        & (xy[:, 0] <= camera.width)
        & (xy[:, 1] <= camera.height)
    )
    return Features(
        xy[inside],
        (J @ feats.shapes)[inside],
        feats.descriptors[inside],
        np.full(int(inside.sum()), index, np.int32),
    )
