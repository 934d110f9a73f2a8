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
budget stays the image's. Hypotheses are not tested for chance (a wrong one costs budget:
it is one more synthesised view, as in ASIFT). Where plain SIFT fills its budget they get
no view (pipeline.UNUSED_BUDGET_AXES): there their features, over the whole image at a
fraction of its resolution, cost pose accuracy on moderate pairs. A hypothesis of a plane the
image's patches already hold in part covers the rest of that plane (planes.REST_AXIS; its
features only in plain SIFT's unused budget, rectified_colmap.budget).

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
from ..planes import HYPOTHESIS_AXIS, REST_AXIS, Patch
from .segments import NUM_SAMPLE_SEGMENTS, Segments, _unit, sin_errors, within_angle


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
    NUM_SAMPLE_SEGMENTS longest unassigned segments (drawn with probability ~ length),
    scored by the length of the unassigned segments within conf.inlier_angle_deg
    (``within_angle``); the best is refined by weighted least squares (v = argmin sum_i
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
        k = idx[:NUM_SAMPLE_SEGMENTS]
        p = seg.lengths[k] / seg.lengths[k].sum()
        a, b = rng.choice(k, size=(2, conf.num_free_vp_hypotheses), p=p)
        cand = np.cross(seg.normals[a], seg.normals[b])
        cand = _unit(cand[np.linalg.norm(cand, axis=1) > 1e-3])
        if len(cand) == 0:
            break
        inliers = within_angle(seg.normals[idx], seg.mids[idx], cand, thr)
        v = cand[np.argmax(seg.lengths[idx].astype(np.float32) @ inliers.astype(np.float32))]
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
    cands = []
    for i, j in combinations(range(len(vps.directions)), 2):
        vi, vj = vps.directions[i], vps.directions[j]
        if line_angle_deg(vi, vj) < conf.hypothesis_min_vp_angle_deg:
            continue
        n = _unit(np.cross(vi, vj))
        cands.append((min(vps.support[i], vps.support[j]), -n if n[2] > 0 else n))
    cands.sort(key=lambda c: -c[0])
    normals, scores = [], []
    for s, n in cands:
        if any(line_angle_deg(n, m) < conf.hypothesis_merge_angle_deg for m in normals):
            continue
        normals.append(n)
        scores.append(s)
    return np.reshape(normals, (-1, 3)), np.array(scores, float)


def hypothesis_patches(
    normals: np.ndarray,
    camera: pycolmap.Camera,
    work_shape: tuple[int, int],
    existing: list[Patch],
    conf: VpConf = VpConf(),
) -> list[Patch]:
    """Whole-image patches for the first conf.line_hypotheses normals not already present
    and tilted at least conf.hypothesis_min_tilt_deg from the image plane, and patches over
    the rest of the planes the image's patches hold in part.

    A hypothesis within conf.hypothesis_merge_angle_deg of existing patches (the depth's,
    oriented by the lines) covers the front-facing cells they do not, as a REST_AXIS patch,
    not counted against conf.line_hypotheses (the normals are read best first until that
    many whole-image patches are found). Such a patch often holds part of its plane
    only (its near part, or what the network segmented as one surface; on generated extreme
    pairs the far part of a plane, seen at 78-85 degrees, where the other image's overlap
    lay, had no view). Its features come only in plain SIFT's unused budget
    (rectified_colmap.budget.cut_to_room): a plane the depth confirmed in part is covered
    whole where plain SIFT leaves room, and nothing changes where plain SIFT fills its
    budget.

    Args:
        normals: (P, 3) from plane_hypotheses, best first.
        camera: the image's camera; work_shape: (h, w) of the work grid.
        existing: the patches the image already has (depth or lines), on the work grid.
    Returns:
        Patches (axis HYPOTHESIS_AXIS or REST_AXIS) whose masks hold the work cells seeing
        the plane from the front (ray . n < 0; REST_AXIS: but no existing patch of its
        orientation); they overlap each other and the existing patches of other
        orientations. A hypothesis within the merge angle of an earlier one of its kind is
        skipped.
    """
    h, w = work_shape
    rays = cam_utils.unit_grid_rays(camera, w, h)
    have = [(np.asarray(p.normal, float), p.mask) for p in existing]  # mask None: all cells
    merge = conf.hypothesis_merge_angle_deg
    out, count = [], 0
    for n in normals:
        if count >= conf.line_hypotheses:
            break
        if line_angle_deg(n, _OPTICAL_AXIS) < conf.hypothesis_min_tilt_deg:
            continue
        near = [m for normal, m in have if line_angle_deg(n, normal) < merge]
        if any(m is None for m in near):
            continue
        mask = rays @ n < 0
        if not near:
            out.append(Patch(mask, HYPOTHESIS_AXIS, n, float(mask.mean())))
            have.append((n, None))
            count += 1
            continue
        for m in near:
            mask &= ~m
        rests = [p.normal for p in out if p.axis == REST_AXIS]
        if mask.any() and all(line_angle_deg(n, r) >= merge for r in rests):
            out.append(Patch(mask, REST_AXIS, n, float(mask.mean())))
    return out
