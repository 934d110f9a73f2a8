"""Where a feature set's matches come from, beside plain SIFT's (superset bookkeeping).

A rectified feature set that keeps plain SIFT's features and adds others (the default)
can still lose plain SIFT's matches: an added feature whose descriptor is close to a plain
one becomes the second-nearest neighbour of that plain feature's true match, and Lowe's
ratio test rejects it ("crowding"). This module tells, per image pair, how many of plain
SIFT's matches a feature set keeps, how many it loses because an endpoint was removed
(a twin replaced, the budget) and how many because both endpoints are still there but the
ratio test or the mutual check now fails; and how many of its new matches (those with at
least one added feature) are correct under a known geometry.

Matching is hloc's ``NN-ratio``: nearest neighbour with the ratio test in both directions
and the mutual check (:func:`nn_ratio_mutual`). Features are mappings as
``eval.matching.FeatureSource`` returns them: ``keypoints`` (N, 2) COLMAP pixels,
``descriptors`` (N, D) float. Plain features are recognised in the other set by identical
keypoint and descriptor (:func:`plain_index`), so both files must come from the same SIFT
(``--conf sift`` and the rectified conf, same budget and camera).
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np

from rectified_colmap.eval.matching import match_ratio
from rectified_colmap.eval.relpose import sampson_error


def nn_ratio_mutual(desc0: np.ndarray, desc1: np.ndarray, ratio: float = 0.8) -> np.ndarray:
    """(M, 2) int64 [i0, i1] as hloc's NN-ratio: i1 is the nearest neighbour of i0 and i0
    of i1, and both pass the ratio test."""
    fwd = match_ratio(desc0, desc1, ratio)
    bwd = match_ratio(desc1, desc0, ratio)
    if len(fwd) == 0 or len(bwd) == 0:
        return np.zeros((0, 2), np.int64)
    back = np.full(len(desc1), -1, np.int64)
    back[bwd[:, 0]] = bwd[:, 1]
    return fwd[back[fwd[:, 1]] == fwd[:, 0]]


def plain_index(feats: dict, plain: dict) -> np.ndarray:
    """(N,) int64: for each feature of ``feats``, the index of the identical feature (same
    keypoint and descriptor, exactly) in ``plain``, or -1 for an added one."""
    kp0 = np.ascontiguousarray(np.asarray(plain["keypoints"], np.float64))
    d0 = np.ascontiguousarray(np.asarray(plain["descriptors"], np.float32))
    lookup = {(k.tobytes(), d.tobytes()): i for i, (k, d) in enumerate(zip(kp0, d0))}
    kp = np.ascontiguousarray(np.asarray(feats["keypoints"], np.float64))
    d = np.ascontiguousarray(np.asarray(feats["descriptors"], np.float32))
    return np.array([lookup.get((a.tobytes(), b.tobytes()), -1) for a, b in zip(kp, d)], np.int64)


@dataclass
class MatchSources:
    """Counts for one pair, or summed over pairs (``+``). ``*_correct`` are None without a
    geometry; a sum counts them over the pairs that have one (None + n = n)."""

    plain_matches: int = 0
    """Matches of plain SIFT alone."""
    kept: int = 0
    """Of those, found again between the same two plain features."""
    lost_removed: int = 0
    """Lost because an endpoint is not in the feature set."""
    lost_crowded: int = 0
    """Lost although both endpoints are there (ratio test or mutual check now fail)."""
    new_plain_plain: int = 0
    """Matches between two plain features that plain SIFT alone did not have."""
    with_added: int = 0
    """Matches with at least one added feature."""
    plain_correct: int | None = None
    """Correct matches of plain SIFT alone."""
    correct: int | None = None
    """Correct matches of the feature set (all of them)."""
    with_added_correct: int | None = None
    """Correct matches with at least one added feature."""

    def __add__(self, other: "MatchSources") -> "MatchSources":
        out = {}
        for f in fields(self):
            a, b = getattr(self, f.name), getattr(other, f.name)
            out[f.name] = b if a is None else a if b is None else a + b
        return MatchSources(**out)


def correct_matches(
    F: np.ndarray, kp0: np.ndarray, kp1: np.ndarray, matches: np.ndarray, max_px: float = 4.0
) -> np.ndarray:
    """(M,) bool: the matches (M, 2) whose Sampson distance under F (x1^T F x0 = 0, in the
    keypoints' units) is below ``max_px``."""
    return sampson_error(F, kp0[matches[:, 0]], kp1[matches[:, 1]]) < max_px


def pair_sources(
    plain_matches: np.ndarray,
    matches: np.ndarray,
    index0: np.ndarray,
    index1: np.ndarray,
    num_plain: tuple[int, int],
    plain_correct: np.ndarray | None = None,
    correct: np.ndarray | None = None,
) -> MatchSources:
    """Bookkeeping of one pair. plain_matches (P, 2): plain SIFT's matches (indices into
    its features); matches (M, 2): the feature set's; index0, index1: ``plain_index`` of
    the feature set's features in each image; num_plain: plain SIFT's feature counts of
    the two images; plain_correct (P,), correct (M,): optional correctness of each match
    (``correct_matches``)."""
    mp, mf = np.asarray(plain_matches), np.asarray(matches)
    i0, i1 = index0[mf[:, 0]], index1[mf[:, 1]]
    both_plain = (i0 >= 0) & (i1 >= 0)
    n1 = num_plain[1]
    found = np.isin(mp[:, 0] * n1 + mp[:, 1], i0[both_plain] * n1 + i1[both_plain])
    present0 = np.zeros(num_plain[0], bool)
    present0[index0[index0 >= 0]] = True
    present1 = np.zeros(n1, bool)
    present1[index1[index1 >= 0]] = True
    present = present0[mp[:, 0]] & present1[mp[:, 1]]
    out = MatchSources(
        plain_matches=len(mp),
        kept=int(found.sum()),
        lost_removed=int((~present).sum()),
        lost_crowded=int((present & ~found).sum()),
        new_plain_plain=int(both_plain.sum() - found.sum()),
        with_added=int((~both_plain).sum()),
    )
    if plain_correct is not None and correct is not None:
        out.plain_correct = int(np.sum(plain_correct))
        out.correct = int(np.sum(correct))
        out.with_added_correct = int(np.sum(correct & ~both_plain))
    return out
