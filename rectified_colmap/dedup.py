"""Near-duplicate keypoints: one feature per location and scale.

Plain SIFT over the whole image plus SIFT in a rectified patch over the same pixels finds
many features twice: a keypoint of the patch, mapped back, lands within a pixel of a plain
keypoint with an almost identical descriptor. Lowe's ratio test then rejects both (the
twin is the second-nearest neighbour), so every twin costs a match. This module finds such
pairs and keeps one feature of each.

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


def frame_scales(shapes: np.ndarray) -> np.ndarray:
    """(N, 2) singular values (large, small) of (N, 2, 2) affine frames."""
    a, b, c, d = shapes[:, 0, 0], shapes[:, 0, 1], shapes[:, 1, 0], shapes[:, 1, 1]
    p, r, q = a * a + c * c, b * b + d * d, a * b + c * d
    m = 0.5 * (p + r)
    s = np.sqrt(0.25 * (p - r) ** 2 + q * q)
    return np.sqrt(np.maximum(np.stack([m + s, m - s], 1), 0.0))


def frame_anisotropy(shapes: np.ndarray) -> np.ndarray:
    """(N,) ratio of the larger to the smaller singular value of each frame (>= 1): 1 for
    plain SIFT, about 1 / cos(tilt) for a keypoint of a patch seen at that tilt."""
    sv = frame_scales(shapes)
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


def duplicate_pairs(
    feats: Features, conf: DedupConf = DedupConf(), only_across: bool | None = None
) -> np.ndarray:
    """(P, 2) index pairs of near-duplicates: closer than ``conf.radius_px``, descriptor
    cosine above ``conf.min_cosine`` and scales (square root of |det A|) within a factor
    ``conf.max_scale_ratio``. With ``only_across`` (default conf.only_across) a pair must
    come from different sources (plain SIFT, patch 0, patch 1, ...): SIFT's own twins
    inside one detection are left alone (each rectified view, tilt neighbours included, is
    a patch of its own)."""
    only_across = conf.only_across if only_across is None else only_across
    pairs = neighbour_pairs(feats.keypoints, conf.radius_px)
    if only_across:
        pairs = pairs[feats.patch[pairs[:, 0]] != feats.patch[pairs[:, 1]]]
    if len(pairs) == 0:
        return pairs
    sv = frame_scales(feats.shapes)
    scale = np.sqrt(sv[:, 0] * sv[:, 1])
    s0, s1 = scale[pairs[:, 0]], scale[pairs[:, 1]]
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.maximum(s0, s1) / np.minimum(s0, s1)
    pairs = pairs[ratio <= conf.max_scale_ratio]
    return pairs[cosine_pairs(feats.descriptors, pairs) > conf.min_cosine]


def keep_preference(feats: Features, conf: DedupConf = DedupConf()) -> np.ndarray:
    """(N,) float: of two twins, the one with the higher value is kept.

    A rectified keypoint scores its frame anisotropy (~ 1 / cos of the tilt at which its
    patch is seen there); a plain keypoint scores 1 / cos(conf.keep_rectified_tilt_deg).
    So the rectified twin wins where the patch is seen obliquely, the plain one where it is
    near-frontal (the warp changed little there, and plain SIFT is the unwarped original).
    Between two rectified twins the more strongly rectified one wins. With
    ``conf.keep_all_plain`` a plain keypoint always wins (inf)."""
    plain_pref = (
        np.inf if conf.keep_all_plain else 1.0 / np.cos(np.deg2rad(conf.keep_rectified_tilt_deg))
    )
    pref = np.full(len(feats), plain_pref)
    rect = feats.patch >= 0
    pref[rect] = frame_anisotropy(feats.shapes[rect])
    return pref


def near_duplicate_mask(
    feats: Features, conf: DedupConf = DedupConf(), only_across: bool | None = None
) -> np.ndarray:
    """(N,) bool: True for the features to keep. Of each near-duplicate pair the one with
    the lower ``keep_preference`` is dropped (ties: the later index). A feature dropped for
    one pair is dropped even if it would have won another (chains resolve conservatively)."""
    keep = np.ones(len(feats), bool)
    pairs = duplicate_pairs(feats, conf, only_across)
    if len(pairs) == 0:
        return keep
    pref = keep_preference(feats, conf)
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


def keypoint_cap(plain_count: int, conf: DedupConf = DedupConf()) -> int:
    """How many keypoints rectified SIFT may output on an image where plain SIFT keeps
    ``plain_count``: ``plain_count`` x (1 + conf.extra_frac). With extra_frac 0 as many as
    plain SIFT, so every rectified feature replaces a plain one; above 0 the rectified
    features first come on top of plain SIFT's."""
    return round(plain_count * (1 + conf.extra_frac))


def largest_scales(feats: Features, index: np.ndarray, n: int, major: bool = False) -> np.ndarray:
    """The ``n`` of ``feats[index]`` with the largest scales, in index order (COLMAP's own
    budget keeps the largest scales); all of them when there are at most n. Scale: |det A|,
    or with ``major`` the larger singular value of A: a rectified feature's scale in its
    view along the direction the warp did not stretch, which does not penalise the most
    oblique views as |det A| (~ cos of the tilt) would."""
    if len(index) <= n:
        return index
    sv = frame_scales(feats.shapes[index])
    key = sv[:, 0] if major else sv[:, 0] * sv[:, 1]
    order = np.argsort(-key, kind="stable")[:n]
    return np.sort(index[order])


def fill_from_plain(
    rectified: Features, plain: Features, target: int, conf: DedupConf = DedupConf()
) -> Features:
    """Rectified features plus plain ones, without near-duplicates: ``target``
    (``keypoint_cap``) in all where there are enough, or the rectified ones alone where they
    already exceed it (each patch keeps whole DoG levels, as COLMAP does, so patches can
    overshoot their shares; they are never cut).

    rectified: the features of all patches (patch >= 0), mapped back; plain: plain SIFT
    detected with the whole budget (a superset of what a smaller budget would keep: COLMAP
    keeps the largest scales). Twins are resolved by ``near_duplicate_mask``; then plain
    features are dropped, smallest scale first (as COLMAP's own budget does), until the
    total is ``target``. So a patch that yields fewer features than its share (sky, blur)
    or whose features were twins leaves its budget to plain SIFT. Rectified features whose
    descriptor is within ``conf.max_plain_cosine`` of a kept plain feature's (anywhere in
    the image) are dropped before plain features make room: they leave their place too.

    With ``conf.keep_all_plain`` no plain feature ever makes room: the rectified ones are
    cut to ``target`` minus the plain count instead, smallest (major) scales first."""
    both = Features.concatenate([rectified, plain])
    keep = near_duplicate_mask(both, conf) if conf.enabled else np.ones(len(both), bool)
    n_rect = len(rectified)
    rect_keep = np.flatnonzero(keep[:n_rect])
    plain_keep = np.flatnonzero(keep[n_rect:])
    if conf.max_plain_cosine < 1.0:  # no rectified feature that crowds a plain one
        cos = max_cosine(rectified.descriptors[rect_keep], plain.descriptors[plain_keep])
        rect_keep = rect_keep[cos <= conf.max_plain_cosine]
    if conf.keep_all_plain:
        room = max(0, target - len(plain_keep))
        rect_keep = largest_scales(rectified, rect_keep, room, major=True)
    else:
        plain_keep = largest_scales(plain, plain_keep, max(0, target - len(rect_keep)))
    return Features.concatenate([plain.subset(plain_keep), rectified.subset(rect_keep)])
