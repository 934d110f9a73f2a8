"""COLMAP's SIFT through pycolmap: on the whole image (plain SIFT) and in rectified views;
in the views of small images OpenCV's SIFT made to give COLMAP's features (``opencv_sift``,
``SiftConf.patch_backend``).

Input: a grayscale image (h, w) uint8, a ``SiftConf`` and a budget. Output: ``Features``
(rectified_colmap.features): keypoints in COLMAP pixels of the ORIGINAL image, affine
frames, descriptors (RootSIFT in COLMAP's byte scale).

Extractors are pycolmap objects that keep VLFeat's scale space for the last image they saw
(about 18 float32 images of the first octave: 288 bytes per pixel at first_octave = -1,
~450 MB for 1536x1024, ~2 GB for 3200x2133) and reuse it for the next image of that size; a
new scale space costs its page faults (~0.25-0.5 CPU s at 1536x1024). A :class:`Sift`
object keeps them warm: per slot at most ``MAX_LIVE_EXTRACTORS[slot]``, least recently used
evicted (destroyed BEFORE the next is created). Slot "image" (whole images: one budget, and
the coarse and fine calls of coarse-first) stays warm from one same-size photo to the next,
as in COLMAP's extractor; slot "patch" (rectified views, a new size and budget each) holds
one. Whoever extracts many images holds one ``Sift`` (an extraction worker does); without
one, each call makes its own extractors (the same features, slower).
"""

from __future__ import annotations

from collections import OrderedDict

import cv2
import numpy as np
import pycolmap

from .config import SiftConf
from .conventions import from_opencv_points
from .features import Features, keypoints_in_mask, similarity_frames
from .geometry import scaled_size
from .rectify import (
    Rectification,
    rectified_to_image,
    upsampled_rectification,
    warp_to_rectified,
)

MIN_SIFT_SIDE = 16
"""Images (and rectified views) with a shorter side get no SIFT features."""
MAX_LIVE_EXTRACTORS = {"image": 2, "patch": 1}
"""Extractors a :class:`Sift` keeps per slot."""
_DEFAULT_NUM_OCTAVES = pycolmap.SiftExtractionOptions().num_octaves


class Sift:
    """pycolmap SIFT extractors kept warm across calls (see the module docstring)."""

    def __init__(self):
        self._cache: dict[str, OrderedDict[tuple, object]] = {
            slot: OrderedDict() for slot in MAX_LIVE_EXTRACTORS
        }

    def live(self) -> int:
        """Extractors alive (at most the sum of MAX_LIVE_EXTRACTORS)."""
        return sum(len(cache) for cache in self._cache.values())

    def extractors(self, slot: str) -> list:
        """The live extractors of a slot, least recently used first."""
        return list(self._cache[slot].values())

    def release(self) -> None:
        """Destroy every extractor (and the scale-space memory it holds)."""
        for cache in self._cache.values():
            cache.clear()

    def extractor(self, conf: SiftConf, n: int, first_octave: int, num_octaves: int, slot: str):
        """The pycolmap extractor for these options (CPU, one thread), made on first use."""
        cache = self._cache[slot]
        key = (
            conf.peak_threshold,
            conf.edge_threshold,
            conf.max_num_orientations,
            conf.upright,
            int(n),
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
            sift.max_num_features = int(n)
            sift.first_octave = int(first_octave)
            sift.num_octaves = int(num_octaves)
            sift.peak_threshold = conf.peak_threshold
            sift.edge_threshold = conf.edge_threshold
            sift.max_num_orientations = conf.max_num_orientations
            sift.upright = conf.upright
            ex = pycolmap.FeatureExtractor.create(opts, pycolmap.Device.cpu)
        cache[key] = ex  # most recently used last
        return ex

    def run(
        self,
        image: np.ndarray,
        conf: SiftConf,
        n: int,
        first_octave: int,
        num_octaves: int = _DEFAULT_NUM_OCTAVES,
        slot: str = "image",
    ) -> tuple[np.ndarray, np.ndarray]:
        """One pycolmap SIFT call on a contiguous (h, w) uint8 image -> ((N, 4) float64
        [x, y, scale, orientation] in COLMAP convention, (N, 128) uint8 descriptors), in
        COLMAP's order: DoG level by DoG level, finest first."""
        ex = self.extractor(conf, n, first_octave, num_octaves, slot)
        kps, desc = ex.extract_from_uint8_array(image)
        if len(kps) == 0:
            return np.zeros((0, 4)), np.zeros((0, 128), np.uint8)
        m = np.asarray(pycolmap.keypoints_to_matrix(kps), dtype=np.float64)
        return m, np.ascontiguousarray(desc.data, dtype=np.uint8)


def opencv_sift(
    image: np.ndarray, conf: SiftConf, n: int, first_octave: int = -1
) -> tuple[np.ndarray, np.ndarray]:
    """OpenCV's SIFT on a contiguous (h, w) uint8 image, as COLMAP's with ``first_octave``
    -1 or 0 would give it: ((N, 4) float64 [x, y, scale, orientation] in COLMAP convention,
    (N, 128) uint8 descriptors in COLMAP's RootSIFT byte scale).

    With precise upscaling (pixel x at 2x, as VLFeat's) the keypoints are COLMAP's (on
    photos the median distance to the nearest COLMAP keypoint is 2e-4 px, scale = OpenCV's
    size / 2, orientation = its angle in radians; docs/architecture.md), and the descriptors
    differ only in normalization: OpenCV's are L2-normalized, COLMAP's L1-normalized, square
    rooted and x 512 (cosine 0.997 to COLMAP's at the same keypoint). The thresholds are
    COLMAP's: OpenCV's contrast threshold is divided by its 3 levels per octave, VLFeat's
    peak threshold is not. Budget as COLMAP's ``max_num_features``: the ``n`` detected points
    of largest scale (a point is its rows with equal x, y, scale), at most
    ``conf.max_num_orientations`` rows each. OpenCV's threads are the caller's (the CLI's
    workers run one: extraction.run.Worker).

    OpenCV always starts at the upsampled octave. First octave 0 (views of 1.2-4 MP images
    at 8192 features): the image halved (``halved``), OpenCV's upsampled octave is then the
    image's own resolution, and the keypoints are doubled back: COLMAP's octaves, but the
    halving and OpenCV's upsampling blur the finest detail a little differently from
    VLFeat's octave 0 (on 1536x1024 photos 69-70 % of COLMAP's keypoints within 0.5 px,
    against 85-89 % from octave -1; scale ratio 1.000, descriptor cosine 0.998 where the
    orientations agree), at a quarter of OpenCV's pixels."""
    if first_octave not in (-1, 0):
        raise ValueError(f"opencv_sift: first octave {first_octave}, not -1 or 0")
    if first_octave == 0:
        image = halved(image)
    detector = cv2.SIFT_create(
        0, 3, 3.0 * conf.peak_threshold, conf.edge_threshold, 1.6, cv2.CV_32F, True
    )
    kps, desc = detector.detectAndCompute(image, None)
    if len(kps) == 0 or desc is None:
        return np.zeros((0, 4)), np.zeros((0, 128), np.uint8)
    m = np.array([(*k.pt, k.size, k.angle) for k in kps], dtype=np.float64)
    m[:, :2] = from_opencv_points(m[:, :2])
    m[:, 2] /= 2.0
    if first_octave == 0:  # back to the full image (COLMAP convention: a multiplication)
        m[:, :3] *= 2.0
    m[:, 3] = np.deg2rad(m[:, 3])
    num_points, point, rank = _points_and_ranks(m[:, :3])
    point_scale = np.zeros(num_points)
    point_scale[point] = m[:, 2]
    chosen = np.argsort(-point_scale, kind="stable")[: max(0, n)]  # largest scales
    keep = (rank < conf.max_num_orientations) & np.isin(point, chosen)
    root = np.sqrt(desc[keep] / np.maximum(desc[keep].sum(1, keepdims=True), 1e-12))
    return m[keep], np.minimum(np.round(512.0 * root), 255).astype(np.uint8)


def halved(image: np.ndarray) -> np.ndarray:
    """(h, w) uint8 -> (ceil(h / 2), ceil(w / 2)): each output pixel the mean of a 2 x 2
    block (an odd last row or column padded with zeros, as outside a view's mask), so COLMAP
    pixel x of the output is 2 x in the input exactly."""
    h, w = image.shape
    if h % 2 or w % 2:
        image = cv2.copyMakeBorder(image, 0, h % 2, 0, w % 2, cv2.BORDER_CONSTANT, value=0)
    return cv2.resize(image, ((w + 1) // 2, (h + 1) // 2), interpolation=cv2.INTER_AREA)


def _points_and_ranks(xys: np.ndarray) -> tuple[int, np.ndarray, np.ndarray]:
    """Rows of (N, 3) [x, y, scale] grouped into points (equal rows): (number of points,
    (N,) point index, (N,) rank of the row within its point in input order)."""
    _, point = np.unique(xys, axis=0, return_inverse=True)
    point = point.ravel()
    order = np.argsort(point, kind="stable")
    sorted_point = point[order]
    starts = np.r_[0, np.flatnonzero(sorted_point[1:] != sorted_point[:-1]) + 1]
    run_start = np.repeat(starts, np.diff(np.r_[starts, len(point)]))
    rank = np.empty(len(point), np.int64)
    rank[order] = np.arange(len(point)) - run_start
    return len(starts), point, rank


def count_detections(m: np.ndarray) -> int:
    """Number of detected points in COLMAP SIFT output (N, >=3) [x, y, scale, ...]: a point
    with several orientations is output as consecutive rows with equal x, y and scale.
    COLMAP's max_num_features counts these points, not the rows."""
    if len(m) == 0:
        return 0
    return 1 + int(np.any(m[1:, :3] != m[:-1, :3], axis=1).sum())


def _sift_coarse_first(
    sift: Sift, image: np.ndarray, conf: SiftConf, n: int, first_octave: int, slot: str
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
        return sift.run(image, conf, n, first_octave, num_octaves, slot)
    coarse = sift.run(image, conf, n, first_octave + 1, num_octaves - 1, slot)
    found = count_detections(coarse[0])
    if found > n:
        return coarse
    fine = sift.run(image, conf, max(1, n - found), first_octave, 1, slot)
    return np.concatenate([fine[0], coarse[0]]), np.concatenate([fine[1], coarse[1]])


def detect_sift(
    image: np.ndarray,
    conf: SiftConf = SiftConf(),
    max_num_features: int | None = None,
    first_octave: int | None = None,
    coarse_first: bool = False,
    slot: str = "image",
    sift: Sift | None = None,
) -> Features:
    """COLMAP SIFT on a grayscale uint8 image (h, w); keypoints in that image's frame.

    Images larger than ``conf.max_image_size`` are downscaled first, as COLMAP does, and the
    keypoints scaled back. Returns Features with ``patch = -1``.

    coarse_first: with a negative first octave, compute the upsampled first octave only
    when the budget reaches it (see ``_sift_coarse_first``): the same points as one pycolmap
    call up to small differences, at ~1/4 of the cost when the budget is filled by the
    coarser octaves. False (default): exactly one pycolmap call with these options.
    slot: the extractor slot (``MAX_LIVE_EXTRACTORS``): "image" for whole images, "patch"
    for rectified views, so that views do not evict the whole image's extractor.
    sift: the extractors to use (kept warm across calls); None: new ones for this call.
    """
    if image.ndim != 2 or image.dtype != np.uint8:
        raise ValueError(f"SIFT needs a (h, w) uint8 image, got {image.shape} {image.dtype}")
    n = conf.max_num_features if max_num_features is None else max_num_features
    if n <= 0 or min(image.shape) < MIN_SIFT_SIDE:
        return Features.empty()
    sift = sift if sift is not None else Sift()
    sx = sy = 1.0
    h, w = image.shape
    nw, nh = sift_input_size(w, h, conf)
    if (nw, nh) != (w, h):
        image = cv2.resize(image, (nw, nh), interpolation=cv2.INTER_AREA)
        sx, sy = w / nw, h / nh
    image = np.ascontiguousarray(image)
    fo = conf.first_octave if first_octave is None else first_octave
    if coarse_first and fo < 0:
        m, desc = _sift_coarse_first(sift, image, conf, n, fo, slot)
    else:
        m, desc = sift.run(image, conf, n, fo, slot=slot)
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
    """``coarse_first_pays`` for plain SIFT on the whole image of ``shape``, on images of at
    least ``conf.pool_coarse_first_min_pixels`` (after SIFT's downscaling); else exact
    COLMAP calls: exactly plain SIFT's features."""
    w, h = sift_input_size(shape[1], shape[0], conf)
    return w * h >= conf.pool_coarse_first_min_pixels and coarse_first_pays(
        shape, max_num_features, conf
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


def plain_sift(gray: np.ndarray, conf: SiftConf, sift: Sift | None = None) -> Features:
    """Plain SIFT on the whole image with the whole budget: COLMAP's features (coarse-first
    on large images: ``pool_coarse_first``)."""
    n = conf.max_num_features
    return detect_sift(
        gray, conf, n, coarse_first=pool_coarse_first(gray.shape, n, conf), sift=sift
    )


def warp_upsampling(size: tuple[int, int], budget: int, first_octave: int, conf: SiftConf) -> int:
    """How much finer than planned a view of ``size`` (w, h) with this SIFT ``budget`` is
    warped (``rectified_features``): 2**-first_octave for a negative first octave with
    COLMAP's SIFT, unless coarse-first pays in the view or the finer view
    would pass ``conf.max_image_size``; else 1."""
    w, h = size
    up = 2 ** max(0, -first_octave)
    if up == 1 or coarse_first_pays((h, w), budget, conf) or max(w, h) * up > conf.max_image_size:
        return 1
    return up


def opencv_views(shape: tuple[int, int], conf: SiftConf) -> bool:
    """Whether OpenCV's SIFT runs the views of an image of ``shape`` (h, w):
    ``sift.patch_backend`` "opencv" where the views' SIFT starts at octave -1 or 0 in one
    call, i.e. where coarse-first does not pay (at 8192 features: up to ~4 MP; octave 0 from
    ``sift.patch_octave0_pixels_per_feature`` pixels per feature, ~1.2 MP; ``opencv_view``
    decides per view). Where they start at -1 the views get more pixels
    (budget.view_pixel_budget)."""
    n = conf.max_num_features
    return (
        conf.patch_backend == "opencv"
        and not conf.upright
        and patch_first_octave(shape, n, conf) in (-1, 0)
        and not coarse_first_pays(shape, n, conf)
    )


def opencv_view(image_shape: tuple[int, int], size: tuple[int, int], conf: SiftConf) -> bool:
    """Whether a view of ``size`` (w, h) of an image of ``image_shape`` (h, w) takes OpenCV's
    SIFT (``opencv_sift``): every view of an image where ``opencv_views`` (also those whose
    coarser octaves would fill their budget: there OpenCV's whole scale space costs about
    what COLMAP's coarse-first does, so the image's views cost what their pixels say), unless
    it is larger than ``conf.max_image_size``."""
    w, h = size
    return (
        opencv_views(image_shape, conf)
        and max(w, h) <= conf.max_image_size
        and min(w, h) >= MIN_SIFT_SIDE
    )


def view_features(
    gray: np.ndarray,
    camera: pycolmap.Camera,
    rect: Rectification,
    budget: int,
    conf: SiftConf,
    sift: Sift | None = None,
) -> Features:
    """SIFT of one rectified view (``budget`` features), keypoints in the planned view's
    pixels. COLMAP's from the octave ``patch_first_octave`` gives the whole image ``gray``;
    a negative one (small images) is taken in the warp (``warp_upsampling``): the view
    warped from the image that much finer, SIFT from octave 0 there. The same scale space
    and cost as SIFT upsampling the planned view, but where the pixel budget shrank the view
    below the image's resolution the finer octave holds the image's detail. Where
    ``opencv_view``: the view at its planned size, OpenCV's SIFT from the same octave
    (``opencv_sift``)."""
    if budget <= 0:
        return Features.empty()
    first_octave = patch_first_octave(gray.shape, conf.max_num_features, conf)
    if opencv_view(gray.shape, rect.size, conf):
        view = warp_to_rectified(gray, camera, rect)
        m, desc = opencv_sift(view, conf, budget, first_octave)
        frames = similarity_frames(m[:, 2], m[:, 3])
        return Features(m[:, :2], frames, desc, np.full(len(m), -1, np.int32))
    up = warp_upsampling(rect.size, budget, first_octave, conf)
    patch_img = warp_to_rectified(gray, camera, upsampled_rectification(rect, up))
    feats = detect_sift(
        patch_img,
        conf,
        budget,
        first_octave if up == 1 else 0,
        coarse_first=coarse_first_pays(patch_img.shape, budget, conf),
        slot="patch",
        sift=sift,
    )
    if up > 1 and len(feats):  # back to the planned view's pixels (a plain multiplication)
        feats = Features(feats.keypoints / up, feats.shapes / up, feats.descriptors, feats.patch)
    return feats


def rectified_features(
    gray: np.ndarray,
    camera: pycolmap.Camera,
    rect: Rectification,
    budget: int,
    conf: SiftConf,
    border: int,
    sift: Sift | None = None,
) -> Features:
    """SIFT inside one rectified view (``view_features``), mapped back to the original
    image; features closer than ``border`` rectified pixels to the border of the warped
    region are dropped. Their source (``patch``) is ``rect.patch_index``."""
    feats = view_features(gray, camera, rect, budget, conf, sift)
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
        np.full(int(inside.sum()), rect.patch_index, np.int32),
    )
