"""Fusion of the line-derived Manhattan frame with the depth network's directions, and the
stage's entry points.

Input: the grayscale image (H, W) uint8, its camera, and the dominant directions (3, 3) of
rectified_colmap.planes (rows, or None). Output: a ``VpResult``: fused directions (rows in
the input order, still a rotation), per direction whether it snapped to or contradicts a
frame axis, and the frame and segments behind it. Conventions: vp.segments (pixels, the
sphere) and vp.manhattan (frames).

``refine_directions`` is the pipeline's entry point (segments -> frame -> fused
directions; without directions, the frame alone).

Fusion (``fuse_directions``): depth directions are matched to frame axes (best signed
permutation); a direction snaps when a confident frame axis (sigma <= max_sigma_deg) lies
within snap_angle_deg of it, and is contradicted when a confident axis lies further. The
output stays a rotation: with 2-3 snapped directions it is the matched frame; with one,
the depth frame rotated minimally onto it; with none, the depth frame unchanged.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from itertools import permutations

import numpy as np
import pycolmap

from ..config import VpConf
from ..geometry import angle_deg, smallest_rotation
from .manhattan import ManhattanFrame, fit_manhattan
from .segments import Segments, image_segments

logger = logging.getLogger(__name__)


@dataclass
class VpResult:
    directions: np.ndarray | None
    """(3, 3) fused directions (rows in the order of the input directions), or None."""
    snapped: np.ndarray
    """(3,) bool: the direction was replaced by a line-derived one."""
    support: np.ndarray
    """(3,) length fraction of the segments supporting the frame axis matched to each
    direction (0 where unmatched)."""
    frame: np.ndarray | None
    """(3, 3) the Manhattan frame from lines (rows ordered by support), or None."""
    segments: Segments
    sigma_deg: np.ndarray = field(default_factory=lambda: np.full(3, np.inf))
    """(3,) uncertainty of the frame axis matched to each direction."""
    contradicted: np.ndarray = field(default_factory=lambda: np.zeros(3, bool))
    """(3,) bool: a confident frame axis disagrees with the direction by > snap angle."""
    angle_change_deg: np.ndarray = field(default_factory=lambda: np.zeros(3))
    """(3,) angle between input and output directions."""
    manhattan: ManhattanFrame | None = None


def match_frame(directions: np.ndarray, frame: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Signed permutation of the frame rows best matching the directions (rows).

    Returns (perm (3,), signs (3,)): direction k matches signs[k] * frame[perm[k]]."""
    C = np.asarray(directions) @ np.asarray(frame).T
    best = max(permutations(range(3)), key=lambda p: np.abs(C[[0, 1, 2], list(p)]).sum())
    perm = np.array(best)
    signs = np.where(C[[0, 1, 2], perm] < 0, -1.0, 1.0)
    return perm, signs


def fuse_directions(
    directions: np.ndarray, mf: ManhattanFrame, conf: VpConf = VpConf()
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Depth directions + Manhattan frame -> fused directions (module docstring).

    Args:
        directions: (3, 3) rows, e.g. planes.PlaneResult.directions.
        mf: the frame from fit_manhattan.
        conf: ``max_sigma_deg``, ``snap_angle_deg``.
    Returns:
        (directions (3, 3), snapped (3,) bool, contradicted (3,) bool, support (3,),
        sigma_deg (3,)), all per input direction (support and sigma of the matched axis).
    """
    D = np.asarray(directions, np.float64)
    if mf.frame is None:
        return D.copy(), np.zeros(3, bool), np.zeros(3, bool), np.zeros(3), np.full(3, np.inf)
    perm, signs = match_frame(D, mf.frame)
    Fm = mf.frame[perm] * signs[:, None]
    sigma, support = mf.sigma_deg[perm], mf.support[perm]
    ang = angle_deg(D, Fm)
    confident = sigma <= conf.max_sigma_deg
    snapped = confident & (ang <= conf.snap_angle_deg)
    contradicted = confident & ~snapped
    out = D.copy()
    idx = np.flatnonzero(snapped)
    if len(idx) >= 2:
        out = Fm.copy()
        if len(idx) == 3 and np.linalg.det(out) > 0:
            pass
        else:  # complete the frame from the two best determined snapped rows
            a, b = idx[np.argsort(sigma[idx])[:2]]
            k = 3 - a - b
            out[k] = np.cross(out[(k + 1) % 3], out[(k + 2) % 3])
    elif len(idx) == 1:
        k = idx[0]
        out = D @ smallest_rotation(D[k], Fm[k]).T
    return out, snapped, contradicted, support, sigma


def refine_directions(
    image_gray: np.ndarray,
    camera: pycolmap.Camera,
    directions: np.ndarray | None,
    conf: VpConf = VpConf(),
    rng: np.random.Generator | None = None,
    segments: Segments | None = None,
) -> VpResult:
    """The pipeline's entry point: segments -> Manhattan frame -> fused directions.

    Never raises on scenes without lines: nothing snaps.

    Args:
        image_gray: (H, W) uint8 matching the camera's size.
        camera: the image's camera.
        directions: (3, 3) rows from rectified_colmap.planes, or None: then the result only
            carries the frame and its directions stay None.
        conf: VpConf.
        rng: RANSAC's generator (default: seeded by conf.seed).
        segments: the image's segments (vp.segments.image_segments) when the caller has
            them already; else they are detected here. Their labels are set.
    Returns:
        VpResult (per-direction arrays (3,) in the order of ``directions``).
    """
    img = np.asarray(image_gray)
    if img.shape[:2] != (camera.height, camera.width):
        raise ValueError(
            f"refine_directions: image is {img.shape[1]}x{img.shape[0]} but its "
            f"camera is {camera.width}x{camera.height}"
        )
    seg = segments if segments is not None else image_segments(img, camera, conf)
    mf = fit_manhattan(seg, conf, rng)
    seg.labels = mf.labels
    if directions is None:
        return VpResult(None, np.zeros(3, bool), np.zeros(3), mf.frame, seg, manhattan=mf)
    D = np.asarray(directions, np.float64)
    out, snapped, contra, support, sigma = fuse_directions(D, mf, conf)
    change = angle_deg(D, out)
    logger.debug(
        "vp: %d segments, frame support %s sigma %s, snapped %s, change %s deg",
        len(seg),
        np.round(mf.support, 2),
        np.round(mf.sigma_deg, 2),
        snapped,
        np.round(change, 1),
    )
    return VpResult(out, snapped, support, mf.frame, seg, sigma, contra, change, mf)
