"""The Manhattan frame of one image's segments: three orthogonal vanishing directions.

Input: ``Segments`` on the Gaussian sphere (vp.segments; conventions there). Output: a
``ManhattanFrame``: the frame (3, 3) (rows = VP directions, orthonormal, right-handed,
ordered by support, the first two facing the camera), per row its 1-sigma angular
uncertainty, support, segment count and chance-level score, and a label per segment.

RANSAC over minimal sets from the longest segments (2 lines -> VP1 = l_a x l_b, 1 line ->
VP2 = l_c x VP1, VP3 = VP1 x VP2), scored by the inlier length; then Gauss-Newton on the
rotation (residual sin(theta), weights = segment length) with re-assignment. Per direction:
support (length fraction), and sigma (1-sigma angular uncertainty from the covariance of
the rotation; inf when unobserved and not implied by the two others). Trust (finite sigma)
also needs strong support and a sharp VP: the
a-contrario test ``axis_log10_nfa`` rejects axes that locally random segment orientations
would explain.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from ..config import VpConf
from ..geometry import order_frame, skew
from .segments import _MIN_SIN, NUM_SAMPLE_SEGMENTS, Segments, _unit, sin_errors, within_angle

NUM_SCORE_SEGMENTS = 300
"""RANSAC frames are scored on this many of the longest segments."""
NUM_REFINE_ITERS = 6
"""Gauss-Newton iterations of the frame rotation (annealed threshold 3x -> 1x)."""
NUM_REFINE_STARTS = 3
"""The best RANSAC frames refined; the tightest soft inlier length wins."""
NFA_ANGLE_DEG = 1.0
"""Chance-level test (axis_log10_nfa): support within this angle of an axis..."""
NFA_WINDOW_DEG = 10.0
"""...against the segments within this angle (locally uniform orientations)."""

_WEXP = 1.0  # segment weights ~ length^_WEXP (2 lets long clutter edges dominate)
_CS = 0.25  # Cauchy scale of the refinement, x sin(inlier angle)
_MIN_SIGMA0 = np.sin(np.deg2rad(0.05))  # floor of the residual scale (noise-free data)
_SIGMA_INFLATION = 2.0  # measured err / sigma ~ 2 (median) on synthetic cluttered sets


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


def _hypotheses(seg: Segments, conf: VpConf, rng: np.random.Generator) -> np.ndarray:
    """(M, 3, 3) candidate frames from minimal line sets of the longest segments."""
    k = min(len(seg), NUM_SAMPLE_SEGMENTS)
    L = seg.normals[:k]  # segments are sorted longest first
    p = seg.lengths[:k] / seg.lengths[:k].sum()
    num = conf.num_hypotheses
    a, b, c = rng.choice(k, size=(3, num), p=p)
    v1 = np.cross(L[a], L[b])
    ok = np.linalg.norm(v1, axis=1) > 1e-3
    v1 = _unit(v1)
    v2 = np.cross(L[c], v1)
    ok &= np.linalg.norm(v2, axis=1) > 1e-3
    v2 = _unit(v2)
    return np.stack([v1, v2, np.cross(v1, v2)], 1)[ok]


def _ransac_scores(seg: Segments, frames: np.ndarray, sin_thr: float, num: int) -> np.ndarray:
    """(M,) inlier length of the ``num`` longest segments for each candidate frame
    (M, 3, 3) (``within_angle`` of any of its rows)."""
    n, m = seg.normals[:num], seg.mids[:num]  # segments are sorted longest first
    inl = np.zeros((len(n), len(frames)), bool)
    for j in range(3):
        inl |= within_angle(n, m, frames[:, j], sin_thr)
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
    num = NUM_REFINE_ITERS
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
        if it == NUM_REFINE_ITERS:
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


def axis_log10_nfa(
    errors_deg: np.ndarray, angle_deg: float = NFA_ANGLE_DEG, window_deg: float = NFA_WINDOW_DEG
) -> np.ndarray:
    """A-contrario test of each frame axis against locally random segment orientations.

    errors_deg (N, 3): consistency angle (vp.segments docstring) of each segment with each
    axis, degrees. Null hypothesis: near any VP, segment orientations are uniform within
    the window w = ``window_deg``, so of the n_w segments within w of axis k (those
    that are inliers of another axis excluded), each lies within t = ``angle_deg``
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
    t, w = float(angle_deg), float(window_deg)
    if not 0.0 < t < w:
        raise ValueError(f"vp: need 0 < angle_deg < window_deg, got {t}, {w}")
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
    seg: Segments, conf: VpConf = VpConf(), rng: np.random.Generator | None = None
) -> ManhattanFrame:
    """Three orthogonal VPs from segments on the sphere (RANSAC + Gauss-Newton)."""
    rng = rng if rng is not None else np.random.default_rng(conf.seed)
    n = len(seg)
    none = ManhattanFrame(
        None, np.full(3, np.inf), np.zeros(3), np.zeros(3, int), np.zeros(3, bool), np.full(n, -1)
    )
    if n < 3:
        return none
    frames = _hypotheses(seg, conf, rng)
    if len(frames) == 0:
        return none
    sin_thr = np.sin(np.deg2rad(conf.inlier_angle_deg))
    score = _ransac_scores(seg, frames, sin_thr, NUM_SCORE_SEGMENTS)
    # refine the best few distinct hypotheses; the tightest soft inlier length wins
    best = None
    for i in np.argsort(-score)[:NUM_REFINE_STARTS]:
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
    log10_nfa = axis_log10_nfa(errors)
    strong = observed & (support >= conf.min_strong_support) & (log10_nfa <= conf.max_log10_nfa)
    if strong.sum() == 0:
        sigma = np.full(3, np.inf)
    elif strong.sum() == 1:
        sigma = np.where(strong, sigma, np.inf)
    # order rows by support, first two facing the camera (z <= 0), right-handed
    F, order = order_frame(F, support)
    remap = np.full(4, -1)
    remap[order] = np.arange(3)
    labels = np.where(labels >= 0, remap[np.maximum(labels, 0)], -1)
    return ManhattanFrame(
        F, sigma[order], support[order], counts[order], observed[order], labels, log10_nfa[order]
    )
