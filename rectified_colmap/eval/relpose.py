"""Relative-pose evaluation of features on image pairs with ground truth (as the paper).

Per pair and method: ratio-test matching (rectified_colmap.eval.matching), essential matrix
with the known intrinsics (pycolmap LO-RANSAC, pixel threshold), and errors against the
ground-truth ``T_0to1`` (X1 = R X0 + t):

- ``R_err``: angle of R_est^T R_gt (degrees); success when under ``success_deg`` (5);
- ``t_err``: angle between the estimated and true translation directions, folded to
  [0, 90] (the sign of t from E is ambiguous under degeneracies, as SuperGlue's protocol);
- ``pose_err`` = max(R_err, t_err), for the pose AUC;
- ``num_correct``: matches whose Sampson error under the ground-truth epipolar geometry is
  below ``epipolar_threshold`` pixels. This count does not depend on RANSAC picking the
  right one of two near-equivalent solutions when a pair shares a single plane.

A failed estimation gives errors of 180 degrees. Keypoints are COLMAP pixels and K is in
the same convention. Records are plain dicts (one per pair and method) for report.py.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Mapping
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

from .config import EvalConf
from ..geometry import angle_between_deg, rotation_angle_deg, skew
from ..parallel import context
from ..progress import progress_bar
from .matching import FeatureSource, match_ratio
from .pairs import Pair

logger = logging.getLogger(__name__)

FAILED_DEG = 180.0


def fundamental_from_pose(
    K0: np.ndarray, K1: np.ndarray, R: np.ndarray, t: np.ndarray
) -> np.ndarray:
    """F with x1^T F x0 = 0 for X1 = R X0 + t (pixel coordinates of K0, K1)."""
    E = skew(np.asarray(t, float)) @ R
    return np.linalg.inv(K1).T @ E @ np.linalg.inv(K0)


def sampson_error(F: np.ndarray, x0: np.ndarray, x1: np.ndarray) -> np.ndarray:
    """(N,) Sampson distance in pixels (square root of the first-order squared error)."""
    h0 = np.concatenate([x0, np.ones((len(x0), 1))], 1)
    h1 = np.concatenate([x1, np.ones((len(x1), 1))], 1)
    Fx0 = h0 @ F.T
    Ftx1 = h1 @ F
    num = np.sum(h1 * Fx0, 1) ** 2
    den = Fx0[:, 0] ** 2 + Fx0[:, 1] ** 2 + Ftx1[:, 0] ** 2 + Ftx1[:, 1] ** 2
    return np.sqrt(num / np.maximum(den, 1e-30))


def pose_errors(
    R_est: np.ndarray, t_est: np.ndarray, R_gt: np.ndarray, t_gt: np.ndarray
) -> tuple[float, float]:
    """(rotation error, translation-direction error folded to [0, 90]) in degrees.

    A pure rotation (|t_gt| ~ 0) has no translation direction: its t error is 0."""
    r = rotation_angle_deg(R_est.T @ R_gt)
    t = angle_between_deg(t_est, t_gt)
    t = 0.0 if np.isnan(t) else min(t, 180.0 - t)
    return r, t


def _camera(K: np.ndarray):
    import pycolmap

    return pycolmap.Camera(
        model="PINHOLE",
        width=max(int(round(2 * K[0, 2])), 1),
        height=max(int(round(2 * K[1, 2])), 1),
        params=[K[0, 0], K[1, 1], K[0, 2], K[1, 2]],
    )


def estimate_relative_pose(
    x0: np.ndarray,
    x1: np.ndarray,
    K0: np.ndarray,
    K1: np.ndarray,
    max_error: float = 2.0,
    seed: int = 0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """Essential matrix by LO-RANSAC (pycolmap) -> (R, t, inlier mask) or None.

    x0, x1 (N, 2) COLMAP pixels; ``max_error`` in pixels; X1 = R X0 + t, |t| = 1."""
    import pycolmap

    if len(x0) < 5:
        return None
    opts = pycolmap.RANSACOptions()
    opts.max_error = float(max_error)
    opts.random_seed = int(seed)
    opts.num_threads = 1
    out = pycolmap.estimate_essential_matrix(
        np.ascontiguousarray(x0, np.float64),
        np.ascontiguousarray(x1, np.float64),
        _camera(K0),
        _camera(K1),
        opts,
    )
    if out is None:
        return None
    T = out["cam2_from_cam1"]
    R = np.asarray(T.rotation.matrix())
    t = np.asarray(T.translation, float)
    return R, t / max(np.linalg.norm(t), 1e-12), np.asarray(out["inlier_mask"], bool)


def evaluate_matches(
    pair: Pair, kp0: np.ndarray, kp1: np.ndarray, matches: np.ndarray, conf: EvalConf
) -> dict:
    """Errors of one pair given its keypoints (COLMAP px) and matches (M, 2)."""
    x0, x1 = kp0[matches[:, 0]], kp1[matches[:, 1]]
    F = fundamental_from_pose(pair.K0, pair.K1, pair.R, pair.t)
    correct = (
        sampson_error(F, x0, x1) < conf.epipolar_threshold if len(matches) else np.zeros(0, bool)
    )
    runs = []  # (R err, t err, inliers, correct inliers) per RANSAC seed
    for k in range(conf.ransac_runs):
        est = estimate_relative_pose(
            x0, x1, pair.K0, pair.K1, conf.ransac_max_error, conf.ransac_seed + k
        )
        if est is None:
            runs.append((FAILED_DEG, FAILED_DEG, 0, 0))
            continue
        R, t, inl = est
        runs.append(
            (*pose_errors(R, t, pair.R, pair.t), int(inl.sum()), int((inl & correct).sum()))
        )
    runs = np.array(runs, float)
    r_err, t_err = np.median(runs[:, 0]), np.median(runs[:, 1])
    n_in, n_in_correct = np.median(runs[:, 2]), np.median(runs[:, 3])
    num_correct = int(correct.sum())
    return {
        "num_matches": int(len(matches)),
        "num_inliers": int(n_in),
        "num_correct": num_correct,
        "num_inliers_correct": int(n_in_correct),
        "R_err": float(r_err),
        "t_err": float(t_err),
        "pose_err": float(max(r_err, t_err)),
        "success": bool(r_err < conf.success_deg),
        "success_rate": float(np.mean(runs[:, 0] < conf.success_deg)),
        "epipolar_success": bool(num_correct >= conf.min_correct),
    }


def evaluate_pair(pair: Pair, features: Mapping[str, FeatureSource], conf: EvalConf) -> list[dict]:
    """All methods on one pair -> one record per method."""
    out = []
    for method, src in features.items():
        rec = {
            "name0": pair.name0,
            "name1": pair.name1,
            "method": method,
            "gt_rot": pair.rotation_deg,
            "category": pair.category,
        }
        f0, f1 = src[pair.name0], src[pair.name1]
        m = match_ratio(f0["descriptors"], f1["descriptors"], conf.ratio, conf.mutual)
        rec.update(num_kp0=len(f0["keypoints"]), num_kp1=len(f1["keypoints"]))
        rec.update(evaluate_matches(pair, f0["keypoints"], f1["keypoints"], m, conf))
        out.append(rec)
    return out


# -- many pairs, many processes ------------------------------------------------------------

_WORKER: dict = {}


def single_thread_env() -> None:
    """One thread per worker: BLAS/OpenMP and OpenCV (oversubscription inflates time 3-5x)."""
    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ[var] = "1"
    try:
        import cv2

        cv2.setNumThreads(1)
    except ImportError:  # pragma: no cover
        pass


def _init(features, conf, worker=True):
    if worker:
        single_thread_env()
    _WORKER["features"] = {k: FeatureSource(v) for k, v in features.items()}
    _WORKER["conf"] = conf


def _run(pair: Pair) -> list[dict]:
    return evaluate_pair(pair, _WORKER["features"], _WORKER["conf"])


def check_features(pairs: list[Pair], features: Mapping[str, Path | str | Mapping]) -> None:
    """Every image of every pair must be in every feature source (clear error otherwise)."""
    needed = {n for p in pairs for n in (p.name0, p.name1)}
    for method, src in features.items():
        missing = needed - FeatureSource(src).names()
        if missing:
            raise ValueError(
                f"method {method!r} ({src if not isinstance(src, Mapping) else 'mapping'}): "
                f"no features for {len(missing)} image(s), e.g. "
                f"{sorted(missing)[:3]}"
            )


def evaluate_pairs(
    pairs: list[Pair],
    features: Mapping[str, Path | str | Mapping],
    conf: EvalConf | None = None,
    num_workers: int = 1,
    progress: bool = True,
) -> list[dict]:
    """Evaluate every method on every pair -> records (pair order, then method order).

    ``features``: method name -> hloc feature file (or a features-by-name mapping)."""
    conf = conf or EvalConf()
    if not features:
        raise ValueError("no feature files given")
    check_features(pairs, features)
    records: list[dict] = []
    with progress_bar(total=len(pairs), desc="pairs", unit="pair", disable=not progress) as bar:
        if num_workers > 1 and len(pairs) > 1:
            with ProcessPoolExecutor(  # never forked: rectified_colmap.parallel
                num_workers,
                mp_context=context([__name__]),
                initializer=_init,
                initargs=(dict(features), conf),
            ) as ex:
                chunk = max(1, len(pairs) // (8 * num_workers))
                for recs in ex.map(_run, pairs, chunksize=chunk):
                    records.extend(recs)
                    bar.update()
        else:
            _init(dict(features), conf, worker=False)
            for p in pairs:
                records.extend(_run(p))
                bar.update()
    return records
