"""Plane hypotheses from pairs of vanishing points, without a Manhattan frame.

A plane holding two families of parallel lines has their two vanishing points on its
vanishing line, so its normal is n = v_i x v_j (camera frame). Unlike the Manhattan frame
(vp.manhattan), this needs neither orthogonal directions nor correct intrinsics: the warp
built from n with the same intrinsics sends that vanishing line to infinity whatever the
focal length (only a mild affine distortion remains where the intrinsics are wrong). It is
what rectifies photos without EXIF, posters, shop fronts and walls seen at 60-85 degrees,
where the depth network's normals are tens of degrees off (docs/vp.md, "Plane hypotheses").

Each hypothesis becomes one whole-image patch (every work cell that sees the plane from the
front, as vp.line_planes.whole_image_patches): the rectification's viewing-angle crop keeps
the cells near its vanishing line out, dedup keeps one feature per location, and the
budget stays the image's. Hypotheses are not tested for chance (a wrong one costs budget,
not correctness: it is one more synthesised view, as in ASIFT).

Conventions: those of vp.segments (camera frame x right, y down, z forward; directions
sign-free unit 3-vectors); normals face the camera (n_z < 0).
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import combinations

import numpy as np
import pycolmap

from .. import camera as cam_utils
from ..config import VpConf
from ..geometry import line_angle_deg
from ..planes import Patch
from .segments import Segments, _unit, sin_errors


_OPTICAL_AXIS = np.array([0.0, 0.0, 1.0])


@dataclass
class VanishingPoints:
    directions: np.ndarray
    """(M, 3) unit VP directions (sign-free), in the order found (most supported first)."""
    support: np.ndarray
    """(M,) fraction of the total segment length supporting each VP."""
    counts: np.ndarray
    """(M,) int: number of supporting segments."""


def free_vanishing_points(
    seg: Segments, conf: VpConf = VpConf(), rng: np.random.Generator | None = None
) -> VanishingPoints:
    """Sequential RANSAC for up to conf.num_free_vps VPs, no orthogonality between them.

    Per VP: conf.num_free_vp_hypotheses candidates v = l_a x l_b from pairs of the
    conf.num_sample_segments longest unassigned segments (drawn with probability ~ length),
    scored by the length of the unassigned segments within conf.inlier_angle_deg
    (``sin_errors``); the best is refined by weighted least squares (v = argmin sum_i
    L_i (l_i . v)^2 over its inliers, 3 rounds); its inliers are then removed. Stops when
    fewer than conf.min_vp_segments segments would support the next one.

    Args:
        seg: segments (vp.segments.segments_on_sphere), sorted longest first.
        conf: VpConf.
        rng: candidate sampling (default: seeded by conf.seed).
    Returns:
        VanishingPoints with M <= conf.num_free_vps.
    """
    rng = rng if rng is not None else np.random.default_rng(conf.seed)
    thr = np.sin(np.deg2rad(conf.inlier_angle_deg))
    free = np.ones(len(seg), bool)
    total = max(float(seg.lengths.sum()), 1e-9)
    V, S, C = [], [], []
    for _ in range(conf.num_free_vps):
        idx = np.flatnonzero(free)
        if len(idx) < conf.min_vp_segments:
            break
        k = idx[: conf.num_sample_segments]
        p = seg.lengths[k] / seg.lengths[k].sum()
        a, b = rng.choice(k, size=(2, conf.num_free_vp_hypotheses), p=p)
        cand = np.cross(seg.normals[a], seg.normals[b])
        cand = _unit(cand[np.linalg.norm(cand, axis=1) > 1e-3])
        if len(cand) == 0:
            break
        E = sin_errors(seg.normals[idx], seg.mids[idx], cand)
        v = cand[np.argmax(seg.lengths[idx] @ (E < thr))]
        for _ in range(3):
            inl = idx[sin_errors(seg.normals[idx], seg.mids[idx], v[None])[:, 0] < thr]
            if len(inl) < 2:
                break
            lw = seg.normals[inl] * np.sqrt(seg.lengths[inl])[:, None]
            v = np.linalg.eigh(lw.T @ lw)[1][:, 0]
        inl = idx[sin_errors(seg.normals[idx], seg.mids[idx], v[None])[:, 0] < thr]
        if len(inl) < conf.min_vp_segments:
            break
        V.append(v)
        S.append(seg.lengths[inl].sum() / total)
        C.append(len(inl))
        free[inl] = False
    return VanishingPoints(np.reshape(V, (-1, 3)), np.array(S, float), np.array(C, int))


def plane_hypotheses(
    vps: VanishingPoints, conf: VpConf = VpConf()
) -> tuple[np.ndarray, np.ndarray]:
    """Pairs of VPs -> plane normals, strongest first.

    A pair counts when its VPs are at least conf.hypothesis_min_vp_angle_deg apart (closer
    ones are one family split in two); its score is the weaker VP's support. A normal within
    conf.hypothesis_merge_angle_deg of a better-scored one is dropped.

    Returns:
        normals (P, 3) unit, facing the camera (n_z <= 0); scores (P,).
    """
    normals, scores, _ = plane_hypothesis_pairs(vps, conf)
    return normals, scores


def plane_hypothesis_pairs(
    vps: VanishingPoints, conf: VpConf = VpConf()
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``plane_hypotheses`` and, per normal, (P, 2, 3) the pair of VP directions it
    comes from."""
    cands = []
    for i, j in combinations(range(len(vps.directions)), 2):
        vi, vj = vps.directions[i], vps.directions[j]
        if line_angle_deg(vi, vj) < conf.hypothesis_min_vp_angle_deg:
            continue
        n = _unit(np.cross(vi, vj))
        cands.append((min(vps.support[i], vps.support[j]), -n if n[2] > 0 else n, (vi, vj)))
    cands.sort(key=lambda c: -c[0])
    normals, scores, pairs = [], [], []
    for s, n, pair in cands:
        if any(line_angle_deg(n, m) < conf.hypothesis_merge_angle_deg for m in normals):
            continue
        normals.append(n)
        scores.append(s)
        pairs.append(pair)
    return np.reshape(normals, (-1, 3)), np.array(scores, float), np.reshape(pairs, (-1, 2, 3))


_SELF_CAL_SIGMA_DEG = 0.5
"""Angular error of a vanishing point assumed by ``orthogonal_focal_scale``."""
_SELF_CAL_MAX_REL = 0.1
"""The focal scale is used only when that error moves it by less than this fraction."""
_SELF_CAL_RANGE = (0.5, 2.0)
"""...and when it is within this range of the guess."""


def _focal_scale_sq(di: np.ndarray, dj: np.ndarray) -> float:
    den = di[2] * dj[2]
    if abs(den) < 1e-12:
        return np.nan
    return -(di[0] * dj[0] + di[1] * dj[1]) / den


def orthogonal_focal_scale(di: np.ndarray, dj: np.ndarray) -> float | None:
    """The factor s of the camera's focal length that makes the 3-D directions of two
    vanishing points orthogonal (camera frame, z forward, principal point known): under
    focal s f the direction (x, y, z) becomes (x, y, s z), so s^2 = -(x_i x_j + y_i y_j) /
    (z_i z_j), the classic calibration from two orthogonal vanishing points.

    None when the pair does not determine it: s^2 <= 0 (not orthogonal for any focal
    length), a vanishing point at infinity (z = 0: every s fits), s outside
    ``_SELF_CAL_RANGE``, or s moved by more than ``_SELF_CAL_MAX_REL`` when either
    direction moves by ``_SELF_CAL_SIGMA_DEG`` (ill-conditioned)."""
    di = _unit(np.asarray(di, float))
    dj = _unit(np.asarray(dj, float))
    s2 = _focal_scale_sq(di, dj)
    if not np.isfinite(s2) or s2 <= 0:
        return None
    s = float(np.sqrt(s2))
    if not _SELF_CAL_RANGE[0] <= s <= _SELF_CAL_RANGE[1]:
        return None
    eps = np.deg2rad(_SELF_CAL_SIGMA_DEG)
    for k, d in enumerate((di, dj)):
        a = np.cross(d, _OPTICAL_AXIS if abs(d[2]) < 0.9 else np.array([1.0, 0.0, 0.0]))
        a = _unit(a)
        b = np.cross(d, a)
        for t in (a, -a, b, -b):
            moved = _unit(d + eps * t)
            q = _focal_scale_sq(moved, dj) if k == 0 else _focal_scale_sq(di, moved)
            if not np.isfinite(q) or q <= 0 or abs(np.sqrt(q) / s - 1.0) > _SELF_CAL_MAX_REL:
                return None
    return s


def metric_correction(di: np.ndarray, dj: np.ndarray, normal: np.ndarray) -> np.ndarray | None:
    """(3, 3) affine map of the virtual normalised coordinates of the rectification of
    ``normal`` (the plane of VP directions ``di``, ``dj`` under the guessed focal length
    f; rectify.rectifying_rotation) onto those of the plane's metric rectification under
    focal s f, s = ``orthogonal_focal_scale`` (the two directions orthogonal there), or
    None where s is undetermined or within 1 % of 1.

    Both rectifications send the plane's vanishing line to infinity, so the map between
    them is affine: M = R' D R^T with D = diag(1/s, 1/s, 1) (normalised coordinates under
    s f from those under f) and R, R' the rectifying rotations of ``normal`` and of the
    plane's normal under s f, D^-1 n. In the plane's view this undoes the affine
    distortion a wrong focal length leaves (a residual tilt of up to s at grazing angles)."""
    from ..rectify import rectifying_rotation

    s = orthogonal_focal_scale(di, dj)
    if s is None or abs(s - 1.0) < 0.01:
        return None
    n = _unit(np.asarray(normal, float))
    D = np.diag([1.0 / s, 1.0 / s, 1.0])
    n_metric = _unit(np.linalg.solve(D, n))  # D^-1 n, facing the camera as n does
    M = rectifying_rotation(n_metric) @ D @ rectifying_rotation(n).T
    A = M / M[2, 2]
    A[2] = (0.0, 0.0, 1.0)  # exactly affine (M[2, :2] is rounding)
    return A


def hypothesis_patches(
    normals: np.ndarray,
    camera: pycolmap.Camera,
    work_shape: tuple[int, int],
    existing: list[np.ndarray],
    conf: VpConf = VpConf(),
    affines: list[np.ndarray | None] | None = None,
) -> list[Patch]:
    """Whole-image patches for the first conf.line_hypotheses normals not already present
    and tilted at least conf.hypothesis_min_tilt_deg from the image plane.

    Args:
        normals: (P, 3) from plane_hypotheses, best first.
        camera: the image's camera; work_shape: (h, w) of the work grid.
        existing: normals (3,) of the patches the image already has (depth or lines): a
            hypothesis within conf.hypothesis_merge_angle_deg of one of them is skipped.
        affines: per normal, its Patch.view_affine (metric_correction) or None.
    Returns:
        Patches (axis -1) whose masks hold every work cell seeing the plane from the front
        (ray . n < 0); they overlap each other and the existing patches.
    """
    h, w = work_shape
    rays = cam_utils.unit_grid_rays(camera, w, h)
    have = [np.asarray(m, float) for m in existing]
    out = []
    affines = affines if affines is not None else [None] * len(normals)
    for n, affine in zip(normals, affines):
        if len(out) >= conf.line_hypotheses:
            break
        if any(line_angle_deg(n, m) < conf.hypothesis_merge_angle_deg for m in have):
            continue
        if line_angle_deg(n, _OPTICAL_AXIS) < conf.hypothesis_min_tilt_deg:
            continue
        mask = rays @ n < 0
        out.append(Patch(mask, -1, n, float(mask.mean()), affine))
        have.append(n)
    return out
