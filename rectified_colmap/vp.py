"""Vanishing points: line segments -> Manhattan frame -> fused dominant directions.

Depth-derived normals say WHICH pixels form planes; line segments say HOW those planes are
oriented, accurately even for far facades where depth is poor. This optional stage sits
between plane clustering and rectification (Toft et al. 2020 name such a hybrid as future
work).

Conventions (as everywhere in the package):
- Segment endpoints ``xy`` (N, 2, 2) are COLMAP pixel coordinates of the full image
  (centre of the top-left pixel at (0.5, 0.5)); OpenCV's LSD output is converted through
  rectified_colmap.conventions.
- Everything geometric lives on the Gaussian sphere of the camera frame (x right, y down,
  z forward), after undistortion by rectified_colmap.camera.image_to_rays. A segment is its
  interpretation plane's unit normal ``l`` (N, 3) and its midpoint's unit ray ``m`` (N, 3).
  Undistortion: the endpoints are undistorted and ``l`` is the cross product of their
  rays, exact for endpoints on the image of a 3D line under any COLMAP model. The image of
  a straight line bends under distortion, so LSD splits strongly curved edges into shorter
  chords; their endpoints stay on the curve, so each chord still gives the exact plane.
  The midpoint ray (for the consistency angle only) is the undistorted chord midpoint.
- Directions and VPs are unit 3-vectors, sign-free (v and -v are the same VP). Frames
  (3, 3) have the directions as rows, orthonormal, right-handed.
- Consistency of segment i with VP v: the angle theta at the midpoint between the segment
  and the great circle through m and v; sin(theta) = |l . v| / |m x v|.

Manhattan frame: RANSAC over minimal sets from the longest segments (2 lines -> VP1 =
l_a x l_b, 1 line -> VP2 = l_c x VP1, VP3 = VP1 x VP2), scored by the inlier length; then
Gauss-Newton on the rotation (residual sin(theta), weights = segment length) with
re-assignment. Per direction: support (length fraction), and sigma (1-sigma angular
uncertainty from the covariance of the rotation; inf when unobserved and not implied by
the two others). An optional gravity prior (camera-frame unit vector) adds hypotheses
containing it and rejects frames without an axis near it.

Fusion (``fuse_directions``): depth directions are matched to frame axes (best signed
permutation); a direction snaps when a confident frame axis (sigma <= max_sigma_deg) lies
within snap_angle_deg of it, and is contradicted when a confident axis lies further. The
output stays a rotation: with 2-3 snapped directions it is the matched frame; with one,
the depth frame rotated minimally onto it; with none, the depth frame unchanged.

Depth-free planes (``depth_free_planes``, conf.depth_free): the confident frame gives the
directions, and the patches come from ``line_support_patches`` (conf.depth_free_regions =
'lines': a plane with normal F[k] is where segments of both other VPs are dense, see its
docstring, split by the sign of ray . F[k]) or ``whole_image_patches`` ('whole', the
paper's VP baseline: per trusted axis, each side of its vanishing line entirely; the
patches overlap).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from itertools import permutations
from pathlib import Path

import cv2
import numpy as np
import pycolmap

from . import camera as cam_utils
from .config import VpConf
from .conventions import from_opencv_points, pixel_centers, to_opencv_points
from .geometry import skew
from .planes import Patch, PlaneResult

logger = logging.getLogger(__name__)

_MIN_SIN = 0.05  # floor of |m x v| (VP on the segment's midpoint: angle undefined)
_WEXP = 1.0  # segment weights ~ length^_WEXP (2 lets long clutter edges dominate)
_CS = 0.25  # Cauchy scale of the refinement, x sin(inlier angle)
_MIN_SIGMA0 = np.sin(np.deg2rad(0.05))  # floor of the residual scale (noise-free data)
_SIGMA_INFLATION = 2.0  # measured err / sigma ~ 2 (median) on synthetic cluttered sets


@dataclass
class Segments:
    xy: np.ndarray
    """(N, 2, 2) endpoints, COLMAP pixels of the full image."""
    lengths: np.ndarray
    """(N,) pixels of the full image."""
    normals: np.ndarray
    """(N, 3) unit normals of the interpretation planes (camera frame)."""
    mids: np.ndarray
    """(N, 3) unit rays through the midpoints."""
    labels: np.ndarray = None
    """(N,) int: index of the frame row the segment supports, -1 for none."""

    def __len__(self) -> int:
        return len(self.lengths)

    @classmethod
    def empty(cls) -> "Segments":
        return cls(
            np.zeros((0, 2, 2)), np.zeros(0), np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0, int)
        )


@dataclass
class ManhattanFrame:
    frame: np.ndarray | None
    """(3, 3) rows = VP directions, ordered by support; None when no VP is observed."""
    sigma_deg: np.ndarray
    """(3,) 1-sigma angular uncertainty of each row (inf: undetermined)."""
    support: np.ndarray
    """(3,) fraction of the total segment length supporting each row."""
    counts: np.ndarray
    """(3,) number of supporting segments."""
    observed: np.ndarray
    """(3,) bool: enough segments support the row (conf.min_vp_segments/min_vp_support)."""
    labels: np.ndarray
    """(N,) int per segment: supported row, -1 for none."""
    log10_nfa: np.ndarray = field(default_factory=lambda: np.full(3, -np.inf))
    """(3,) log10 of each row's number of false alarms (axis_log10_nfa): how often
    segments whose orientations are locally random would support a VP this sharply by
    chance. Rows above conf.max_log10_nfa are never trusted."""


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


# -- segments -----------------------------------------------------------------------------


def detect_segments(image_gray: np.ndarray, conf: VpConf = VpConf()) -> np.ndarray:
    """LSD (OpenCV) on the image downscaled to conf.max_image_size -> (N, 2, 2) endpoints in
    COLMAP pixels of the full image, longest first, at most conf.max_segments, each at
    least conf.min_length_frac x max side long. Falls back to HoughLinesP on Canny."""
    img = np.asarray(image_gray)
    if img.ndim != 2 or img.dtype != np.uint8:
        raise ValueError(f"detect_segments needs a (H, W) uint8 image, got {img.dtype} {img.shape}")
    H, W = img.shape
    s = min(1.0, conf.max_image_size / max(H, W))
    small = (
        img
        if s == 1.0
        else cv2.resize(
            img, (max(8, round(W * s)), max(8, round(H * s))), interpolation=cv2.INTER_AREA
        )
    )
    h, w = small.shape
    try:
        lsd = cv2.createLineSegmentDetector(cv2.LSD_REFINE_STD)
        raw = lsd.detect(small)[0]
    except (AttributeError, cv2.error):  # builds without LSD
        edges = cv2.Canny(small, 50, 150)
        raw = cv2.HoughLinesP(
            edges, 1, np.pi / 360, 30, minLineLength=conf.min_length_frac * max(h, w), maxLineGap=2
        )
    if raw is None or len(raw) == 0:
        return np.zeros((0, 2, 2))
    seg = from_opencv_points(np.asarray(raw, np.float64).reshape(-1, 2, 2))
    seg = seg * np.array([W / w, H / h])
    length = np.linalg.norm(seg[:, 1] - seg[:, 0], axis=-1)
    keep = np.flatnonzero(length >= conf.min_length_frac * max(H, W))
    keep = keep[np.argsort(-length[keep], kind="stable")][: conf.max_segments]
    return seg[keep]


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-300)


def segments_on_sphere(camera: pycolmap.Camera, xy: np.ndarray) -> Segments:
    """(N, 2, 2) COLMAP endpoints -> Segments (interpretation-plane normals, midpoint rays),
    undistorted through the camera (see module docstring)."""
    xy = np.asarray(xy, np.float64).reshape(-1, 2, 2)
    n = len(xy)
    if n == 0:
        return Segments.empty()
    mid = xy.mean(1)
    pts = np.concatenate([xy[:, 0], xy[:, 1], mid])
    rays = _unit(cam_utils.image_to_rays(camera, pts)).reshape(3, n, 3)
    normals = _unit(np.cross(rays[0], rays[1]))
    lengths = np.linalg.norm(xy[:, 1] - xy[:, 0], axis=-1)
    return Segments(xy, lengths, normals, rays[2], np.full(n, -1))


def sin_errors(normals: np.ndarray, mids: np.ndarray, V: np.ndarray) -> np.ndarray:
    """sin(theta) (N, M) between N segments and M VP directions (module docstring)."""
    a = np.abs(normals @ V.T)
    b = mids @ V.T
    return a / np.sqrt(np.maximum(1.0 - b * b, _MIN_SIN**2))


# -- Manhattan frame ----------------------------------------------------------------------


def _hypotheses(
    seg: Segments, conf: VpConf, rng: np.random.Generator, gravity: np.ndarray | None
) -> np.ndarray:
    """(M, 3, 3) candidate frames from minimal line sets of the longest segments."""
    k = min(len(seg), conf.num_sample_segments)
    L = seg.normals[:k]  # segments are sorted longest first
    p = seg.lengths[:k] / seg.lengths[:k].sum()
    num = conf.num_hypotheses
    a, b, c = rng.choice(k, size=(3, num), p=p)
    v1 = np.cross(L[a], L[b])
    ok = np.linalg.norm(v1, axis=1) > 1e-3
    v1 = _unit(v1)
    if gravity is not None:
        g = _unit(np.asarray(gravity, np.float64).reshape(3))
        v1 = np.concatenate([v1, np.tile(g, (k, 1))])
        c = np.concatenate([c, np.arange(k)])
        ok = np.concatenate([ok, np.ones(k, bool)])
    v2 = np.cross(L[c], v1)
    ok &= np.linalg.norm(v2, axis=1) > 1e-3
    v2 = _unit(v2)
    frames = np.stack([v1, v2, np.cross(v1, v2)], 1)[ok]
    if gravity is not None and len(frames):
        cos_g = np.abs(frames @ g).max(1)
        frames = frames[cos_g >= np.cos(np.deg2rad(conf.gravity_angle_deg))]
    return frames


def _ransac_scores(seg: Segments, frames: np.ndarray, sin_thr: float, num: int) -> np.ndarray:
    """(M,) inlier length of the ``num`` longest segments for each candidate frame
    (M, 3, 3). float32 and without square
    roots: sin(theta) < t  <=>  (l.v)^2 + t^2 (m.v)^2 < t^2 (up to the |m x v| floor)."""
    n = seg.normals[:num].astype(np.float32)  # segments are sorted longest first
    m = seg.mids[:num].astype(np.float32)
    t2 = np.float32(sin_thr**2)
    inl = np.zeros((len(n), len(frames)), bool)
    for j in range(3):
        V = np.ascontiguousarray(frames[:, j].T, dtype=np.float32)
        a, b = n @ V, m @ V
        a *= a
        b *= b
        np.minimum(b, np.float32(1.0 - _MIN_SIN**2), out=b)
        b *= t2
        a += b
        inl |= a < t2
    return seg.lengths[:num].astype(np.float32) @ inl.astype(np.float32)


def _assign(seg: Segments, F: np.ndarray, sin_thr: float) -> tuple[np.ndarray, np.ndarray]:
    """Per segment: (label in {-1, 0, 1, 2}, sin error to that row)."""
    E = sin_errors(seg.normals, seg.mids, F)
    k = np.argmin(E, axis=1)
    e = E[np.arange(len(k)), k]
    return np.where(e < sin_thr, k, -1), e


def _rotvec_matrix(w: np.ndarray) -> np.ndarray:
    return cv2.Rodrigues(np.asarray(w, np.float64).reshape(3, 1))[0]


def _refine(
    seg: Segments, F: np.ndarray, conf: VpConf
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Gauss-Newton on the frame's rotation with re-assignment.

    Returns (F, labels, observed (3,), sigma_deg (3,))."""
    total = seg.lengths.sum()
    w_all = seg.lengths**_WEXP / (seg.lengths**_WEXP).mean()
    A = np.zeros((3, 3))
    r = J = w = None
    num = max(1, conf.num_refine_iters)
    # annealed threshold: 3x down to 1x (escapes the minima of a hard threshold near the
    # RANSAC frame)
    scales = np.concatenate([np.linspace(3.0, 1.0, max(num - 1, 1)), [1.0, 1.0]])
    for it in range(num + 1):
        sin_thr = np.sin(np.deg2rad(conf.inlier_angle_deg * scales[min(it, len(scales) - 1)]))
        labels, _ = _assign(seg, F, sin_thr)
        counts = np.bincount(labels[labels >= 0], minlength=3)
        support = (
            np.bincount(labels[labels >= 0], weights=seg.lengths[labels >= 0], minlength=3) / total
        )
        observed = (counts >= conf.min_vp_segments) & (support >= conf.min_vp_support)
        use = (labels >= 0) & observed[np.maximum(labels, 0)]
        if not use.any():
            return F, labels, observed, np.full(3, np.inf)
        v = F[labels[use]]
        ln = seg.normals[use]
        m = seg.mids[use]
        s = np.sqrt(np.maximum(1.0 - np.einsum("ij,ij->i", m, v) ** 2, _MIN_SIN**2))
        r = np.einsum("ij,ij->i", ln, v) / s
        J = np.cross(v, ln) / s[:, None]
        # Cauchy weights: clutter passing the threshold pulls less than the true lines
        w = w_all[use] / (1.0 + (r / (_CS * sin_thr)) ** 2)
        A = (J * w[:, None]).T @ J
        if it == conf.num_refine_iters:
            break
        g = (J * w[:, None]).T @ r
        step = -np.linalg.pinv(A, rcond=1e-8) @ g
        F = F @ _rotvec_matrix(step).T
    # covariance of the rotation (radians^2): sigma0^2 A^-1, inf along unobserved axes
    dof = max(len(r) - 3, 1)
    sigma0_sq = max(float((w_all[use] * r * r).sum() / dof), _MIN_SIGMA0**2)
    lam, U = np.linalg.eigh(A)
    null = lam <= 1e-6 * max(lam.max(), 1e-300)  # rotations the observed VPs do not fix
    cov = sigma0_sq * (U[:, ~null] / lam[~null]) @ U[:, ~null].T
    sigma = np.empty(3)
    for k in range(3):
        S = skew(F[k])
        free = np.linalg.norm(np.cross(U[:, null].T, F[k]), axis=-1) > 1e-3
        sigma[k] = (
            np.inf if free.any() else np.sqrt(max(np.linalg.eigvalsh(S @ cov @ S.T).max(), 0.0))
        )
    sigma = sigma * _SIGMA_INFLATION
    sigma_deg = np.where(sigma < 1.0, np.degrees(sigma), np.inf)
    return F, labels, observed, sigma_deg


# -- chance-level test -----------------------------------------------------------------


def log10_binomial_tail(n: np.ndarray, k: np.ndarray, p: float) -> np.ndarray:
    """log10 P[X >= k] for X ~ Binomial(n, p), exact, elementwise over integer arrays n, k
    of one shape (any); 0 where k <= 0, -inf where k > n."""
    n = np.asarray(n, np.int64)
    k = np.asarray(k, np.int64)
    nmax = int(max(n.max(initial=0), 1))
    lf = np.concatenate([[0.0], np.cumsum(np.log(np.arange(1, nmax + 1)))])  # log j!
    j = np.arange(nmax + 1)
    nn, kk = n[..., None], k[..., None]
    ok = (j >= kk) & (j <= nn)
    logc = lf[np.minimum(nn, nmax)] - lf[j] - lf[np.clip(nn - j, 0, nmax)]
    terms = np.where(ok, logc + j * np.log(p) + (nn - j) * np.log1p(-p), -np.inf)
    top = terms.max(-1, keepdims=True)
    with np.errstate(divide="ignore", invalid="ignore"):
        out = (
            top[..., 0] + np.log(np.exp(terms - np.where(np.isfinite(top), top, 0.0)).sum(-1))
        ) / np.log(10)
    out = np.where(k <= 0, 0.0, out)
    return np.where(k > n, -np.inf, out)


def axis_log10_nfa(errors_deg: np.ndarray, conf: VpConf = VpConf()) -> np.ndarray:
    """A-contrario test of each frame axis against locally random segment orientations.

    errors_deg (N, 3): consistency angle (module docstring) of each segment with each
    axis, degrees. Null hypothesis: near any VP, segment orientations are uniform within
    the window w = conf.nfa_window_deg, so of the n_w segments within w of axis k (those
    that are inliers of another axis excluded), each lies within t = conf.nfa_angle_deg
    with probability t / w: P_k = P[Binomial(n_w, t / w) >= n_t], n_t the segments within
    t. This keeps the broad orientation bias of foreshortened texture (which a test
    against uniform orientations would take for structure) and rejects only what is
    sharper than it: real lines meet their VP within LSD's precision.

    Number of tests, nested (axes ranked by P_k): the first axis is any of 3 on the half
    sphere (3 x 2 pi / t^2 cells, t in radians); given it, the second is any of 2 on its
    orthogonal great circle (2 x pi / t); the third is then fixed (1). Returns (3,) log10
    NFA per axis, of the frame up to that axis: log10(tests) + log10 P_k, raised to the
    NFA of the better ranked axes (an axis is only as meaningful as the frame it needs)."""
    E = np.asarray(errors_deg, np.float64).reshape(-1, 3)
    t, w = float(conf.nfa_angle_deg), float(conf.nfa_window_deg)
    if not 0.0 < t < w:
        raise ValueError(f"vp: need 0 < nfa_angle_deg < nfa_window_deg, got {t}, {w}")
    inl = E < t
    other = np.stack([np.delete(inl, k, axis=1).any(1) for k in range(3)], 1) & ~inl
    n_w = ((E < w) & ~other).sum(0)
    n_t = inl.sum(0)
    log_p = log10_binomial_tail(n_w, n_t, t / w)
    rad = np.deg2rad(t)
    tests = np.log10([3 * 2 * np.pi / rad**2, 2 * np.pi / rad, 1.0])
    order = np.argsort(log_p, kind="stable")
    out = np.empty(3)
    out[order] = np.maximum.accumulate(log_p[order] + tests)
    return out


def fit_manhattan(
    seg: Segments,
    conf: VpConf = VpConf(),
    gravity: np.ndarray | None = None,
    rng: np.random.Generator | None = None,
) -> ManhattanFrame:
    """Three orthogonal VPs from segments on the sphere (RANSAC + Gauss-Newton).

    ``gravity``: optional camera-frame unit vector (e.g. [0, 1, 0] for an upright camera);
    it only adds hypotheses and rejects frames without an axis near it."""
    rng = rng if rng is not None else np.random.default_rng(conf.seed)
    n = len(seg)
    none = ManhattanFrame(
        None, np.full(3, np.inf), np.zeros(3), np.zeros(3, int), np.zeros(3, bool), np.full(n, -1)
    )
    if n < 3:
        return none
    frames = _hypotheses(seg, conf, rng, gravity)
    if len(frames) == 0:
        return none
    sin_thr = np.sin(np.deg2rad(conf.inlier_angle_deg))
    score = _ransac_scores(seg, frames, sin_thr, conf.num_score_segments)
    # refine the best few distinct hypotheses; the tightest soft inlier length wins
    best = None
    for i in np.argsort(-score)[: max(1, conf.num_refine_starts)]:
        cand = _refine(seg, frames[i], conf)
        e = sin_errors(seg.normals, seg.mids, cand[0]).min(1)
        soft = float(seg.lengths @ np.maximum(0.0, 1.0 - (e / sin_thr) ** 2))
        if best is None or soft > best[0]:
            best = (soft, cand)
    F, labels, observed, sigma = best[1]
    if not observed.any():
        return none
    counts = np.bincount(labels[labels >= 0], minlength=3)
    support = (
        np.bincount(labels[labels >= 0], weights=seg.lengths[labels >= 0], minlength=3)
        / seg.lengths.sum()
    )
    # Trust needs strong VPs: random clutter alone reaches ~0.06 support per VP; and
    # sharp ones: foreshortened line-free texture gives 0.10-0.15 (axis_log10_nfa)
    errors = np.degrees(np.arcsin(np.minimum(sin_errors(seg.normals, seg.mids, F), 1.0)))
    log10_nfa = axis_log10_nfa(errors, conf)
    strong = observed & (support >= conf.min_strong_support) & (log10_nfa <= conf.max_log10_nfa)
    if strong.sum() == 0:
        sigma = np.full(3, np.inf)
    elif strong.sum() == 1:
        sigma = np.where(strong, sigma, np.inf)
    # order rows by support, first two facing the camera (z <= 0), right-handed
    order = np.argsort(-support, kind="stable")
    F = F[order].copy()
    for i in (0, 1):
        if F[i, 2] > 0:
            F[i] *= -1.0
    F[2] = np.cross(F[0], F[1])
    remap = np.full(4, -1)
    remap[order] = np.arange(3)
    labels = np.where(labels >= 0, remap[np.maximum(labels, 0)], -1)
    return ManhattanFrame(
        F, sigma[order], support[order], counts[order], observed[order], labels, log10_nfa[order]
    )


# -- fusion -------------------------------------------------------------------------------


def match_frame(directions: np.ndarray, frame: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Signed permutation of the frame rows best matching the directions (rows).

    Returns (perm (3,), signs (3,)): direction k matches signs[k] * frame[perm[k]]."""
    C = np.asarray(directions) @ np.asarray(frame).T
    best = max(permutations(range(3)), key=lambda p: np.abs(C[[0, 1, 2], list(p)]).sum())
    perm = np.array(best)
    signs = np.where(C[[0, 1, 2], perm] < 0, -1.0, 1.0)
    return perm, signs


def _angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.degrees(np.arccos(np.clip(np.einsum("...i,...i->...", a, b), -1.0, 1.0)))


def _min_rotation(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Smallest rotation taking unit a onto unit b."""
    axis = np.cross(a, b)
    s = np.linalg.norm(axis)
    if s < 1e-12:
        return np.eye(3)
    return _rotvec_matrix(axis / s * np.arctan2(s, float(a @ b)))


def fuse_directions(
    directions: np.ndarray, mf: ManhattanFrame, conf: VpConf = VpConf()
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Depth directions (3, 3) + Manhattan frame -> (directions, snapped, contradicted,
    support, sigma_deg), the last two per input direction (module docstring)."""
    D = np.asarray(directions, np.float64)
    if mf.frame is None:
        return D.copy(), np.zeros(3, bool), np.zeros(3, bool), np.zeros(3), np.full(3, np.inf)
    perm, signs = match_frame(D, mf.frame)
    Fm = mf.frame[perm] * signs[:, None]
    sigma, support = mf.sigma_deg[perm], mf.support[perm]
    ang = _angle_deg(D, Fm)
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
        out = D @ _min_rotation(D[k], Fm[k]).T
    return out, snapped, contradicted, support, sigma


def refine_directions(
    image_gray: np.ndarray,
    camera: pycolmap.Camera,
    directions: np.ndarray | None,
    conf: VpConf = VpConf(),
    gravity: np.ndarray | None = None,
    rng: np.random.Generator | None = None,
) -> VpResult:
    """The pipeline's entry point: segments -> Manhattan frame -> fused directions.

    image_gray (H, W) uint8 matching the camera's size; directions (3, 3) rows from
    rectified_colmap.planes (or None: then the result only carries the frame and
    directions stay None). Never raises on scenes without lines: nothing snaps."""
    img = np.asarray(image_gray)
    if img.shape[:2] != (camera.height, camera.width):
        raise ValueError(
            f"refine_directions: image is {img.shape[1]}x{img.shape[0]} but its "
            f"camera is {camera.width}x{camera.height}"
        )
    seg = segments_on_sphere(camera, detect_segments(img, conf))
    mf = fit_manhattan(seg, conf, gravity, rng)
    seg.labels = mf.labels
    if directions is None:
        return VpResult(None, np.zeros(3, bool), np.zeros(3), mf.frame, seg, manhattan=mf)
    D = np.asarray(directions, np.float64)
    out, snapped, contra, support, sigma = fuse_directions(D, mf, conf)
    change = _angle_deg(D, out)
    logger.debug(
        "vp: %d segments, frame support %s sigma %s, snapped %s, change %s deg",
        len(seg),
        np.round(mf.support, 2),
        np.round(mf.sigma_deg, 2),
        snapped,
        np.round(change, 1),
    )
    return VpResult(out, snapped, support, mf.frame, seg, sigma, contra, change, mf)


def manhattan_from_image(
    image_gray: np.ndarray,
    camera: pycolmap.Camera,
    conf: VpConf = VpConf(),
    gravity: np.ndarray | None = None,
    rng: np.random.Generator | None = None,
) -> VpResult:
    """Depth-free mode: the line-derived frame as the dominant directions.

    ``directions`` is the frame (rows by support, like planes.fit_dominant_directions) when
    at least two of its axes are confident (sigma <= conf.max_sigma_deg), else None;
    ``snapped`` marks the confident axes."""
    res = refine_directions(image_gray, camera, None, conf, gravity, rng)
    mf = res.manhattan
    confident = mf.sigma_deg <= conf.max_sigma_deg
    res.snapped = confident
    res.support = mf.support.copy()
    res.sigma_deg = mf.sigma_deg.copy()
    res.directions = mf.frame.copy() if mf.frame is not None and confident.sum() >= 2 else None
    return res


# -- per patch ----------------------------------------------------------------------------


@dataclass
class PatchCheck:
    num_segments: int
    """Segments with a VP label whose midpoint lies in the patch."""
    inplane_frac: float
    """Length fraction of them whose VP is (within snap_angle_deg) in the patch's plane."""
    line_normal: np.ndarray | None
    """Normal implied by the two VPs with the most segment length in the patch (each with at
    least max(2, conf.patch_min_segments // 2) segments), signed like ``normal``; None
    without two such line families."""
    angle_deg: float
    """Angle between line_normal and the patch normal (nan without line_normal)."""
    consistent: bool | None
    """With line_normal: angle_deg <= conf.snap_angle_deg. Else, with at least
    conf.patch_min_segments segments: inplane_frac >= conf.patch_min_inplane_frac. Else
    None (no verdict)."""


def check_patch(
    result: VpResult,
    mask: np.ndarray,
    normal: np.ndarray,
    camera: pycolmap.Camera,
    conf: VpConf = VpConf(),
) -> PatchCheck:
    """Do the patch's own lines agree with its normal?

    mask (h, w) bool on any grid covering the image (e.g. the work grid of planes.Patch);
    normal (3,) the patch normal. Lines lying on a plane vanish on its vanishing line, so
    the VPs of the patch's segments must be orthogonal to its normal."""
    seg, F = result.segments, result.frame
    n = _unit(np.asarray(normal, np.float64))
    if F is None or len(seg) == 0:
        return PatchCheck(0, float("nan"), None, float("nan"), None)
    h, w = mask.shape
    mid = seg.xy.mean(1)
    col = np.clip((mid[:, 0] * w / camera.width).astype(int), 0, w - 1)
    row = np.clip((mid[:, 1] * h / camera.height).astype(int), 0, h - 1)
    inside = mask[row, col] & (seg.labels >= 0)
    num = int(inside.sum())
    if num == 0:
        return PatchCheck(0, float("nan"), None, float("nan"), None)
    lab, L = seg.labels[inside], seg.lengths[inside]
    inplane_axis = np.abs(F @ n) < np.sin(np.deg2rad(conf.snap_angle_deg))
    frac = float(L[inplane_axis[lab]].sum() / L.sum())
    counts = np.bincount(lab, minlength=3)
    families = np.flatnonzero(counts >= max(2, conf.patch_min_segments // 2))
    line_normal, angle, verdict = None, float("nan"), None
    if len(families) >= 2:
        length = np.bincount(lab, weights=L, minlength=3)
        a, b = families[np.argsort(-length[families])[:2]]
        line_normal = _unit(np.cross(F[a], F[b]))
        if line_normal @ n < 0:
            line_normal = -line_normal
        angle = float(_angle_deg(line_normal, n))
        verdict = angle <= conf.snap_angle_deg
    elif num >= conf.patch_min_segments:
        verdict = frac >= conf.patch_min_inplane_frac
    return PatchCheck(num, frac, line_normal, angle, verdict)


# -- depth-free planes --------------------------------------------------------------------


def _fill_holes(mask: np.ndarray) -> np.ndarray:
    """Background components not touching the border become foreground."""
    n, lab = cv2.connectedComponents((~mask).astype(np.uint8), connectivity=4)
    border = np.unique(np.concatenate([lab[0], lab[-1], lab[:, 0], lab[:, -1]]))
    outside = np.zeros(n, bool)
    outside[border] = True
    return mask | ~outside[lab]


def line_support_patches(
    result: VpResult,
    camera: pycolmap.Camera,
    work_shape: tuple[int, int],
    conf: VpConf = VpConf(),
    min_area_frac: float = 0.005,
) -> tuple[list[Patch], np.ndarray]:
    """Depth-free plane patches from labelled segments -> (patches, labels (h, w) int8).

    A plane with normal F[k] contains the lines of the two other VPs, so its image is where
    segments of BOTH other families are dense. Per family j, the density D_j is the
    fraction of cells of a (2r+1)^2 window (r = conf.support_radius_frac x max(h, w))
    crossed by its segments (rasterised on the work grid); axis k scores
    min(D_a, D_b) and needs, for both, conf.support_min_lines window-crossing lines
    (D >= support_min_lines / (2r + 1)). Each cell takes the best axis; the two sides of
    the axis' vanishing line (sign of ray . F[k]) are separate planes (normal facing the
    camera). Holes are filled; components under ``min_area_frac`` of the grid are dropped.
    Labels follow rectified_colmap.planes (2k + s, s = 1 when the normal is -F[k]).
    ``result`` must carry a confident frame (``result.directions``, e.g. from
    manhattan_from_image); only axes whose two in-plane VPs are observed get patches."""
    h, w = work_shape
    labels = np.full((h, w), -1, np.int8)
    F, seg = result.directions, result.segments
    if F is None or len(seg) == 0 or result.manhattan is None:
        return [], labels
    observed = result.manhattan.observed
    r = max(1, int(round(conf.support_radius_frac * max(h, w))))
    k2 = 2 * r + 1
    scale = np.array([w / camera.width, h / camera.height])
    dens = np.zeros((3, h, w), np.float32)
    for j in np.flatnonzero(observed):
        xy = to_opencv_points(seg.xy[seg.labels == j] * scale)
        lines = [p for p in np.round(xy * 16).astype(np.int32)]  # 4 fractional bits
        m = np.zeros((h, w), np.uint8)
        cv2.polylines(m, lines, False, 1, 1, cv2.LINE_8, shift=4)
        dens[j] = cv2.boxFilter(m.astype(np.float32), -1, (k2, k2), borderType=cv2.BORDER_CONSTANT)
    score = np.zeros((3, h, w), np.float32)
    for k in range(3):
        a, b = (k + 1) % 3, (k + 2) % 3
        if observed[a] and observed[b]:
            score[k] = np.minimum(dens[a], dens[b])
    best = np.argmax(score, 0)
    valid = score.max(0) >= conf.support_min_lines / k2
    side = (cam_utils.grid_rays(camera, w, h) @ F.T) > 0  # (h, w, 3): normal is -F[k]
    patches = []
    for k in range(3):
        for s in (0, 1):
            mask = _fill_holes(valid & (best == k) & (side[..., k] == bool(s)))
            n, comp, stats, _ = cv2.connectedComponentsWithStats(
                mask.astype(np.uint8), connectivity=8
            )
            for c in np.flatnonzero(stats[1:, cv2.CC_STAT_AREA] >= min_area_frac * h * w) + 1:
                pm = comp == c
                labels[pm] = 2 * k + s
                patches.append(Patch(pm, k, F[k] * (-1.0 if s else 1.0), float(pm.mean())))
    patches.sort(key=lambda p: -p.area_frac)
    return patches, labels


def whole_image_patches(
    result: VpResult,
    camera: pycolmap.Camera,
    work_shape: tuple[int, int],
    conf: VpConf = VpConf(),
    min_area_frac: float = 0.005,
) -> tuple[list[Patch], np.ndarray]:
    """The paper's VP baseline: whole-image warps -> (patches, labels (h, w) int8).

    For each trusted frame axis k (``result.snapped``) and each side of its vanishing line,
    one patch holds ALL cells whose ray r sees the plane of normal n = +-F[k] from the
    front (r . n < 0); n faces the camera. No segmentation: the patches overlap (a cell
    lies in one patch per trusted axis, so in up to 3); rectify's viewing-angle crop then
    removes the grazing cells near each vanishing line. Sides under ``min_area_frac`` of
    the grid are dropped. ``labels`` (for visualisation and support only) gives each cell
    the label (2k + s, as line_support_patches) of the patch seeing it most frontally.
    ``result`` must carry a confident frame (``result.directions``)."""
    h, w = work_shape
    labels = np.full((h, w), -1, np.int8)
    F = result.directions
    if F is None:
        return [], labels
    rays = cam_utils.grid_rays(camera, w, h)
    rays /= np.linalg.norm(rays, axis=-1, keepdims=True)
    cos = rays @ F.T  # (h, w, 3): r . F[k]; side s = 1 (normal -F[k]) where > 0
    patches, best = [], np.zeros((h, w))
    for k in np.flatnonzero(result.snapped):
        for s in (0, 1):
            frontal = -cos[..., k] * (-1.0 if s else 1.0)  # -r . n
            mask = frontal > 0
            if mask.mean() < min_area_frac:
                continue
            patches.append(Patch(mask, int(k), F[k] * (-1.0 if s else 1.0), float(mask.mean())))
            better = mask & (frontal > best)
            labels[better], best[better] = 2 * k + s, frontal[better]
    patches.sort(key=lambda p: -p.area_frac)
    return patches, labels


def depth_free_planes(
    image_gray: np.ndarray,
    camera: pycolmap.Camera,
    work_shape: tuple[int, int],
    conf: VpConf = VpConf(),
    min_area_frac: float = 0.005,
    gravity: np.ndarray | None = None,
    rng: np.random.Generator | None = None,
) -> tuple[PlaneResult, VpResult]:
    """Depth-free mode: Manhattan frame from lines (manhattan_from_image) + patches ->
    a planes.PlaneResult on the work grid (no patches, directions None, without a
    confident frame: the pipeline then falls back to plain SIFT). The patches follow
    conf.depth_free_regions: 'lines' = line_support_patches (disjoint), 'whole' =
    whole_image_patches (the paper's VP baseline, overlapping)."""
    regions = {"lines": line_support_patches, "whole": whole_image_patches}
    if conf.depth_free_regions not in regions:
        raise ValueError(
            f"vp.depth_free_regions must be one of {sorted(regions)}, "
            f"got {conf.depth_free_regions!r}"
        )
    res = manhattan_from_image(image_gray, camera, conf, gravity, rng)
    patches, labels = regions[conf.depth_free_regions](res, camera, work_shape, conf, min_area_frac)
    areas = np.bincount(labels[labels >= 0] // 2, minlength=3)[:3]
    support = areas / max(1, labels.size)
    return PlaneResult(res.directions, support, labels, patches), res


# -- visualisation ------------------------------------------------------------------------

_VP_BGR = np.array([[60, 60, 235], [60, 210, 60], [235, 130, 40]])  # red, green, blue


def _bgr(image: np.ndarray) -> np.ndarray:
    return (
        cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
        if image.ndim == 2
        else cv2.cvtColor(image, cv2.COLOR_RGB2BGR)
    )


def _cv_pt(xy: np.ndarray) -> tuple[int, int]:
    p = np.round(to_opencv_points(xy) * 16).astype(int)  # 4 fractional bits
    return int(p[0]), int(p[1])


def draw_segments(image: np.ndarray, result: VpResult) -> np.ndarray:
    """BGR image (darkened) with segments coloured by VP (red/green/blue = frame rows 0/1/2,
    grey = none)."""
    out = (_bgr(image) * 0.5).astype(np.uint8)
    seg = result.segments
    for xy, lab in zip(seg.xy, seg.labels):
        colour = (150, 150, 150) if lab < 0 else tuple(int(c) for c in _VP_BGR[lab])
        cv2.line(out, _cv_pt(xy[0]), _cv_pt(xy[1]), colour, 2, cv2.LINE_AA, shift=4)
    return out


def draw_directions(
    image: np.ndarray,
    camera: pycolmap.Camera,
    result: VpResult,
    depth_directions: np.ndarray | None = None,
    grid: int = 6,
) -> np.ndarray:
    """BGR image with, at a grid of anchors, needles pointing to each direction's VP:
    thick = fused directions (or the frame), thin white = the depth directions."""
    out = (_bgr(image) * 0.6).astype(np.uint8)
    W, H = camera.width, camera.height
    length = 0.04 * max(W, H)
    anchors = pixel_centers(grid, max(2, grid * H // W), W, H).reshape(-1, 2)
    rays = cam_utils.image_to_rays(camera, anchors)

    def needles(D, colours, thickness):
        for d, colour in zip(D, colours):
            tip = cam_utils.rays_to_image(camera, rays + 1e-3 * d)
            u = tip - anchors
            u /= np.maximum(np.linalg.norm(u, axis=1, keepdims=True), 1e-12)
            for p, q in zip(anchors - length * u, anchors + length * u):
                if np.isfinite(p).all() and np.isfinite(q).all():
                    cv2.line(out, _cv_pt(p), _cv_pt(q), colour, thickness, cv2.LINE_AA, shift=4)

    D = result.directions if result.directions is not None else result.frame
    if D is not None:
        needles(D, [tuple(int(c) for c in col) for col in _VP_BGR], 3)
    if depth_directions is not None:
        needles(depth_directions, [(255, 255, 255)] * 3, 1)
    return out


def save_png(path: Path | str, image: np.ndarray) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), image):
        raise OSError(f"{path}: cannot write PNG")
    return path
