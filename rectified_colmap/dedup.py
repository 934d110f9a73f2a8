"""Near-duplicate keypoints: one feature per location and scale; look-alikes of plain SIFT's.

Plain SIFT over the whole image plus SIFT in a rectified patch over the same pixels finds
many features twice: a keypoint of the patch, mapped back, lands within a pixel of a plain
keypoint with an almost identical descriptor. Lowe's ratio test then rejects both (the
twin is the second-nearest neighbour), so every twin costs a match. This module finds such
pairs and says which rectified features stay: every plain feature does (the extractor's
output holds plain SIFT's exactly), a rectified twin of a plain feature or of a more
strongly rectified one does not. Of the rest it flags the **look-alikes**: rectified
features whose descriptor is within ``max_plain_cosine`` of a plain one anywhere in the
image, which can crowd that plain feature's match out of the ratio test. How many of each
kind are kept is the budget's (rectified_colmap.budget.cut_to_room: look-alikes only in the
part of plain SIFT's budget that plain SIFT left unused).

Conventions: keypoints (N, 2) in COLMAP pixels of the ORIGINAL image (distances do not
depend on the convention: both sides are in the same one); affine frames (N, 2, 2) as
``Features.shapes`` (the frame's singular values are the keypoint's scale along its two
axes; for a rectified keypoint ``A = J A_rect``); descriptors (N, D) uint8 or float, any
norm (cosine similarity is used). Everything is vectorised: neighbours come from a grid
hash (cells of side ``radius``, sorted keys, 3x3 cell neighbourhoods), no KD-tree needed.
"""

from __future__ import annotations

import numpy as np

from .config import DedupConf
from .features import Features
from .geometry import singular_values_2x2


def neighbour_pairs(xy: np.ndarray, radius: float) -> np.ndarray:
    """(P, 2) int64 index pairs (i, j), i < j, of points closer than ``radius`` (strictly).

    xy: (N, 2) float coordinates (any units, the same as ``radius``). Grid hash: every
    point goes to the cell floor(xy / radius); a pair closer than ``radius`` lies in the
    same or in adjacent cells, so each point is compared with the points of its 3x3 cells.
    Cost O(N + P'), P' = candidate pairs (about 9 x N x density x radius^2)."""
    xy = np.asarray(xy, np.float64).reshape(-1, 2)
    n = len(xy)
    if n < 2 or not radius > 0:
        return np.zeros((0, 2), np.int64)
    finite = np.isfinite(xy).all(1)
    idx = np.flatnonzero(finite)
    cell = np.floor(xy[idx] / radius).astype(np.int64)
    cell -= cell.min(0) - 1  # >= 1: neighbours at -1 stay non-negative
    ncol = int(cell[:, 0].max()) + 2
    key = cell[:, 1] * ncol + cell[:, 0]
    order = np.argsort(key, kind="stable")
    skey, sidx = key[order], idx[order]
    out = []
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            if (dy, dx) < (0, 0):  # half of the neighbourhood: each cell pair once
                continue
            target = skey + dy * ncol + dx
            lo = np.searchsorted(skey, target, "left")
            hi = np.searchsorted(skey, target, "right")
            cnt = hi - lo
            if not cnt.any():
                continue
            i = np.repeat(np.arange(len(skey)), cnt)  # sorted position of each candidate
            first = np.cumsum(cnt) - cnt  # where each point's run of candidates starts
            j = np.repeat(lo - first, cnt) + np.arange(len(i))  # lo + offset in the run
            if (dy, dx) == (0, 0):
                keep = j > i  # same cell: each unordered pair once, no self pairs
                i, j = i[keep], j[keep]
            a, b = sidx[i], sidx[j]
            d2 = ((xy[a] - xy[b]) ** 2).sum(1)
            close = d2 < radius * radius
            out.append(np.stack([a[close], b[close]], 1))
    if not out:
        return np.zeros((0, 2), np.int64)
    pairs = np.concatenate(out)
    pairs.sort(1)
    return pairs


def frame_anisotropy(shapes: np.ndarray) -> np.ndarray:
    """(N,) ratio of the larger to the smaller singular value of each frame (>= 1): 1 for
    plain SIFT, about 1 / cos(tilt) for a keypoint of a patch seen at that tilt."""
    sv = singular_values_2x2(shapes)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(sv[:, 1] > 0, sv[:, 0] / sv[:, 1], np.inf)


def unit_rows(desc: np.ndarray) -> np.ndarray:
    """(N, D) float32 descriptors scaled to unit rows (zero rows stay zero)."""
    d = np.asarray(desc, np.float32)
    norm = np.linalg.norm(d, axis=1, keepdims=True)
    return d / np.where(norm > 0, norm, 1.0)


def max_cosine(desc: np.ndarray, others: np.ndarray, chunk: int = 1024) -> np.ndarray:
    """(N,) largest cosine similarity of each descriptor of ``desc`` (N, D) with any of
    ``others`` (M, D); -1 where M = 0. Chunked: at most ``chunk`` x M similarities at once."""
    out = np.full(len(desc), -1.0, np.float32)
    if len(desc) == 0 or len(others) == 0:
        return out
    o = unit_rows(others).T
    for s in range(0, len(desc), chunk):
        out[s : s + chunk] = (unit_rows(desc[s : s + chunk]) @ o).max(1)
    return out


def cosine_pairs(desc: np.ndarray, pairs: np.ndarray) -> np.ndarray:
    """(P,) descriptor cosine similarity of the index pairs (P, 2)."""
    if len(pairs) == 0:
        return np.zeros(0)
    d = unit_rows(desc)
    return np.einsum("ij,ij->i", d[pairs[:, 0]], d[pairs[:, 1]])


def duplicate_pairs(feats: Features, conf: DedupConf = DedupConf()) -> np.ndarray:
    """(P, 2) index pairs of near-duplicates from different sources (plain SIFT, view 0,
    view 1, ...: SIFT's own twins inside one detection are left alone): closer than
    ``conf.radius_px``, descriptor cosine above ``conf.min_cosine`` and scales (square root
    of |det A|) within a factor ``conf.max_scale_ratio``."""
    pairs = neighbour_pairs(feats.keypoints, conf.radius_px)
    pairs = pairs[feats.patch[pairs[:, 0]] != feats.patch[pairs[:, 1]]]
    if len(pairs) == 0:
        return pairs
    sv = singular_values_2x2(feats.shapes)
    scale = np.sqrt(sv[:, 0] * sv[:, 1])
    s0, s1 = scale[pairs[:, 0]], scale[pairs[:, 1]]
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.maximum(s0, s1) / np.minimum(s0, s1)
    pairs = pairs[ratio <= conf.max_scale_ratio]
    return pairs[cosine_pairs(feats.descriptors, pairs) > conf.min_cosine]


def near_duplicate_mask(feats: Features, conf: DedupConf = DedupConf()) -> np.ndarray:
    """(N,) bool: True for the features to keep. Of each near-duplicate pair the one with
    the lower preference is dropped (ties: the later index): a plain keypoint always wins;
    between two rectified twins the more strongly rectified one (its frame anisotropy,
    ~ 1 / cos of the tilt at which its view sees the patch). A feature dropped for one pair
    is dropped even if it would have won another (chains resolve conservatively)."""
    keep = np.ones(len(feats), bool)
    pairs = duplicate_pairs(feats, conf)
    if len(pairs) == 0:
        return keep
    pref = np.full(len(feats), np.inf)
    rect = feats.patch >= 0
    pref[rect] = frame_anisotropy(feats.shapes[rect])  # finite: a twin has a scale (> 0)
    a, b = pairs[:, 0], pairs[:, 1]  # a < b
    loser = np.where(pref[b] > pref[a], a, b)
    keep[loser] = False
    return keep


def duplicate_fraction(feats: Features, radius: float = 1.0, min_cosine: float = 0.9) -> float:
    """Fraction of keypoints with a twin closer than ``radius`` px whose descriptor cosine
    exceeds ``min_cosine`` (any source, any scale): the measure of
    shared/tools/near_duplicates.py."""
    if len(feats) == 0:
        return 0.0
    pairs = neighbour_pairs(feats.keypoints, radius)
    pairs = pairs[cosine_pairs(feats.descriptors, pairs) > min_cosine]
    twin = np.zeros(len(feats), bool)
    twin[pairs.ravel()] = True
    return float(twin.mean())


def distinct_from_plain(
    rectified: Features, plain: Features, conf: DedupConf = DedupConf()
) -> np.ndarray:
    """(K,) sorted indices of the ``rectified`` features (all views, mapped back) that may
    come on top of ``plain`` (plain SIFT of the whole image, all kept): no near-duplicate
    (``near_duplicate_mask``)."""
    both = Features.concatenate([rectified, plain])
    return np.flatnonzero(near_duplicate_mask(both, conf)[: len(rectified)])


def lookalikes(
    rectified: Features, index: np.ndarray, plain: Features, conf: DedupConf = DedupConf()
) -> np.ndarray:
    """(K,) bool for the features ``rectified[index]``: True where the descriptor is within
    ``conf.max_plain_cosine`` of a plain feature's anywhere in the image (it can crowd that
    feature's match out of the ratio test; all False at ``max_plain_cosine`` 1)."""
    if conf.max_plain_cosine >= 1.0:
        return np.zeros(len(index), bool)
    return max_cosine(rectified.descriptors[index], plain.descriptors) > conf.max_plain_cosine
