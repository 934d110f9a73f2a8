"""The budget of one image, in one place: the views' pixels and the features.

The rectified views of an image together have at most ``rectify.max_view_pixels_factor``
x the image's pixels, :data:`OPENCV_VIEW_PIXELS_RATIO` x that where OpenCV's SIFT (~2.5x
faster per pixel on one core) runs them from the upsampled octave (:func:`view_pixel_budget`,
rectified_colmap.sift.opencv_views; pixels beyond those that SIFT's budget can use are not
counted): a budget relative to the image, so small photos and video frames pay the same
share as large ones. Views over it are cut to the largest common
claim per work cell that fits (rectified_colmap.views.rectifications_within_budget).

Plain SIFT keeps COLMAP's budget (``sift.max_num_features``: detected points, a point with
two orientations gives two keypoints) on the whole image, exactly as COLMAP. The rectified
features come on top: at most ``dedup.extra_frac`` x plain SIFT's budget, or x its keypoint
count where that is larger (:func:`rectified_room`: an image where plain SIFT finds few
features gets the room of a full one); the views' SIFT budgets share
``sift.patch_budget_factor`` x that room by covered area (:func:`view_budgets`,
:func:`split_budget`), so they cost what they may add; what survives the near-duplicate
test is cut to the room (:func:`cut_to_room`), largest major scales first
(:func:`largest_scales`, as COLMAP's own budget keeps the largest scales): first the
features unlike any plain one, then the look-alikes of plain features
(rectified_colmap.dedup), but these only in the part of plain SIFT's budget its keypoints
left unused (:func:`unused_room`), as the features of views over the rest of a plane
(planes.REST_AXIS: a plane hypothesis over the cells the depth's patches of its
orientation leave out); blind views' features (planes.BLIND_AXIS: an image whose estimates
gave no view that adds features) come after all of these, in what is left
(:func:`blind_room`); where the image's lines confirm none of its plane estimates, with a
share of the pixels and of the room held for them (:func:`blind_share`,
:func:`without_share`). A look-alike can crowd a plain feature's match out of
the ratio test; where plain SIFT fills its budget (a textured photo, whose moderate pairs
plain SIFT matches) none is kept, where it leaves budget unused (a small or sparse image, a
strongly foreshortened view) they may fill what plain SIFT did not use."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from .config import ExtractConf
from .features import Features
from .geometry import singular_values_2x2
from .sift import opencv_views, patch_first_octave, sift_input_size

OPENCV_VIEW_PIXELS_RATIO = 3.0
"""Where OpenCV's SIFT runs an image's views from the upsampled octave (sift.opencv_views,
small images: below ``sift.patch_octave0_pixels_per_feature`` pixels per feature), they get
this x
``rectify.max_view_pixels_factor`` x the image's pixels: its SIFT is 2.4-2.7x faster per
pixel on one core. Chosen on the choose half of the generated extreme pairs (2026-12-06,
research log): with the default's 2, 6 x solved the most pairs (then cases) at no more
extraction time than COLMAP's SIFT at 2 x. Views from octave 0 (1.2-4 MP at 8192 features)
keep their pixels: no pairs of that size chose a ratio, so OpenCV's speed is saved there."""


def view_pixel_budget(shape: tuple[int, int], conf: ExtractConf) -> float:
    """Pixels all rectified views of an image of ``shape`` (h, w) may have together:
    ``rectify.max_view_pixels_factor`` (x ``OPENCV_VIEW_PIXELS_RATIO`` where
    ``opencv_views`` from the upsampled octave) x the pixels of the image as SIFT sees it
    (downscaled to ``sift.max_image_size``, as COLMAP), counted up to what SIFT's budget
    can use: ``sift.max_num_features`` x ``sift.patch_octave0_pixels_per_feature`` (from
    that many pixels per feature on, the budget fills without the upsampled octave: finer
    detail adds no features the budget keeps, in the image or in its views)."""
    w, h = sift_input_size(shape[1], shape[0], conf.sift)
    usable = conf.sift.max_num_features * conf.sift.patch_octave0_pixels_per_feature
    factor = conf.rectify.max_view_pixels_factor
    n = conf.sift.max_num_features
    if opencv_views(shape, conf.sift) and patch_first_octave(shape, n, conf.sift) < 0:
        factor *= OPENCV_VIEW_PIXELS_RATIO
    return factor * min(w * h, usable)


def rectified_room(plain_count: int, conf: ExtractConf) -> int:
    """How many rectified keypoints may come on top of plain SIFT's ``plain_count``:
    ``dedup.extra_frac`` x the larger of plain SIFT's budget ``sift.max_num_features`` and
    its count (with two orientations a detected point gives two keypoints). The budget,
    not only the count: an image where plain SIFT finds few features (a small photo, an
    extreme view) gets the room of a full one, and no image more than a full one's."""
    return round(max(plain_count, conf.sift.max_num_features) * conf.dedup.extra_frac)


def unused_room(plain_count: int, conf: ExtractConf) -> int:
    """How many second-tier rectified keypoints (look-alikes of plain features, the features
    of views over the rest of a plane or blind: planes.REST_AXIS, BLIND_AXIS) may come on
    top of plain SIFT's ``plain_count`` keypoints: the part of plain SIFT's budget
    ``sift.max_num_features`` its keypoints left unused (0 where plain SIFT fills it, or
    with ``dedup.lookalikes_in_unused_budget`` False)."""
    if not conf.dedup.lookalikes_in_unused_budget:
        return 0
    return max(0, conf.sift.max_num_features - plain_count)


BLIND_YIELD_FRAC = 0.125
"""An image gets the blind views (views.blind_patches) beside its other views where those
add at most this x plain SIFT's keypoints on top of them (``wants_blind_views``): a view of
a wrong estimate (a plane called frontal seen at 74 degrees, a view over blank or blurred
pixels) adds almost nothing, and blocked the blind views, which came only where no view
was planned. Chosen on the choose halves of two sets of generated extreme pairs
(2026-12-06, stop 58, research log) among 0, 1/8, 1/4, 1/2 and 1: all but 0 solved the
most pairs and cases, 1/8 with the fewest images re-planned (none of the eight 640x480
fountain images; at 1/2 one, at 1 four)."""


def wants_blind_views(added: int, plain_count: int, conf: ExtractConf) -> bool:
    """Whether an image whose views added ``added`` rectified keypoints on top of plain
    SIFT's ``plain_count`` gets blind views: where they added at most
    ``BLIND_YIELD_FRAC`` x ``plain_count`` (0 where it has no view) and plain SIFT left part
    of its budget unused (``unused_room``: the blind views are second tier)."""
    return unused_room(plain_count, conf) > 0 and added <= BLIND_YIELD_FRAC * plain_count


UNSUPPORTED_BLIND_SHARE = 0.5
"""The share of an image's view pixels and rectified room held for its blind views where
its lines gave its planes no orientation of their own (``blind_share``). Not chosen on
data: an even split between an estimate nothing confirms and the blind bank, the only
value tried (2026-12-07, stop 65, research log)."""


def blind_share(plain_count: int, supported: bool, conf: ExtractConf) -> float:
    """The share of an image's view pixels (``view_pixel_budget``) and of its rectified
    room (``rectified_room``) held for blind views (views.blind_patches) beside the views of
    its plane estimates: ``UNSUPPORTED_BLIND_SHARE`` where the estimates are not
    ``supported`` by the image's lines (pipeline.lines_support: no plane hypothesis, no
    depth plane snapped to a vanishing direction) and plain SIFT's ``plain_count`` keypoints
    leave part of its budget unused (``unused_room``: blind views are second tier), else 0.
    Such an estimate is the network's alone, which on the generated pairs errs by 30 degrees
    at the median; its views still add features, so that ``wants_blind_views`` sees nothing
    wrong, and they fill the room, which left blind views, coming last (``blind_room``),
    nothing to add."""
    if supported or unused_room(plain_count, conf) == 0:
        return 0.0
    return UNSUPPORTED_BLIND_SHARE


def without_share(conf: ExtractConf, share: float) -> ExtractConf:
    """``conf`` for the estimates' views when blind views take ``share`` (``blind_share``):
    the rectified room (``dedup.extra_frac``) cut to 1 - ``share`` of it (``conf`` itself
    for 0)."""
    if share == 0:
        return conf
    dedup = replace(conf.dedup, extra_frac=conf.dedup.extra_frac * (1.0 - share))
    return replace(conf, dedup=dedup)


def blind_room(count: int, plain_count: int, conf: ExtractConf) -> int:
    """How many blind-view keypoints may come on top of an image's ``count`` features (plain
    SIFT's ``plain_count`` and the rectified ones of its other views, all kept): what is
    left both of the rectified room (``rectified_room``) and of plain SIFT's budget
    ``sift.max_num_features`` (the blind views only fill what nothing else used)."""
    room = rectified_room(plain_count, conf) - (count - plain_count)
    return max(0, min(room, conf.sift.max_num_features - count))


def fits_either_tier(count: int, plain_count: int, conf: ExtractConf) -> bool:
    """Whether ``cut_to_room`` keeps all of ``count`` candidates on top of plain SIFT's
    ``plain_count`` keypoints whichever tier each falls in: at most the room
    (``rectified_room``) and at most the unused budget (``unused_room``). Then which of them
    are look-alikes changes nothing, and the look-alike test (dedup.lookalikes, an N x M
    descriptor product) need not run."""
    return count <= min(rectified_room(plain_count, conf), unused_room(plain_count, conf))


def cut_to_room(
    feats: Features, index: np.ndarray, second: np.ndarray, plain_count: int, conf: ExtractConf
) -> np.ndarray:
    """The rectified features kept on top of plain SIFT's ``plain_count`` keypoints, sorted:
    of ``feats[index]`` (the candidates, dedup.distinct_from_plain), first those of the
    first tier (``second`` (K,) bool: False), largest major scales first, up to the room
    (``rectified_room``); then the second tier (look-alikes of plain features, features of
    views over the rest of a plane), largest major scales first, up to the room left and at
    most ``unused_room``."""
    room = max(0, rectified_room(plain_count, conf))
    index, second = np.asarray(index), np.asarray(second, bool)
    first = largest_scales(feats, index[~second], room)
    left = min(room - len(first), unused_room(plain_count, conf))
    later = largest_scales(feats, index[second], max(0, left))
    return np.sort(np.concatenate([first, later]))


def view_budgets(
    plain_count: int, areas: np.ndarray, rest: np.ndarray, conf: ExtractConf
) -> np.ndarray:
    """(n,) SIFT budgets of n rectified views covering ``areas`` (n,) work cells each, on an
    image where plain SIFT keeps ``plain_count`` keypoints: ``conf.sift.patch_budget_factor``
    x the room above plain SIFT (``rectified_room``), shared by area (``split_budget``);
    the second tier's views (over the rest of a plane, blind: ``rest`` (n,) bool) share
    that factor x the part of the room they may fill (``unused_room``) instead."""
    rest = np.asarray(rest, bool)
    room = rectified_room(plain_count, conf)
    factor = conf.sift.patch_budget_factor
    out = np.zeros(len(areas), dtype=int)
    out[~rest] = split_budget(round(factor * room), np.asarray(areas)[~rest])
    later = min(room, unused_room(plain_count, conf))
    out[rest] = split_budget(round(factor * later), np.asarray(areas)[rest])
    return out


def split_budget(total: int, areas: np.ndarray, minimum: int = 64) -> np.ndarray:
    """Share a feature budget between regions in proportion to their areas (int array).

    Regions with any area get at least ``minimum`` (when the budget allows)."""
    areas = np.asarray(areas, dtype=np.float64)
    if areas.sum() <= 0 or total <= 0:
        return np.zeros(len(areas), dtype=int)
    share = total * areas / areas.sum()
    share = np.where(areas > 0, np.maximum(share, min(minimum, total / max(len(areas), 1))), 0)
    share *= total / share.sum()
    return np.floor(share).astype(int)


def largest_scales(feats: Features, index: np.ndarray, n: int) -> np.ndarray:
    """The ``n`` of ``feats[index]`` with the largest major scales, in index order; all of
    them when there are at most n. Major scale: the larger singular value of A, a rectified
    feature's scale in its view along the direction the warp did not stretch (|det A|,
    ~ cos of the tilt, would penalise the most oblique views)."""
    if len(index) <= n:
        return index
    key = singular_values_2x2(feats.shapes[index])[:, 0]
    order = np.argsort(-key, kind="stable")[:n]
    return np.sort(index[order])
