#!/usr/bin/env python
"""How good a method's relative-pose matches are, by the features they join: plain SIFT's or
the ones added on top (``match_sources.py`` counts where matches come from and which of
plain SIFT's are lost; this script measures their quality against ground-truth poses).

A method's feature is plain when the baseline's file holds it exactly (same keypoint and
descriptor: match_sources.plain_index), added otherwise. For every pair of
``eval_strecha.py``'s scenes (``--data``: folders with ``pairs_with_gt.txt``; its features
under ``--features SCENE/METHOD.h5``) the matches are made as that evaluation makes them
(rectified_colmap.eval: ratio test, EvalConf) and sorted by the features they join:
plain-plain, plain-added (either image), added-added. Per kind: matches, the GT-correct
share (Sampson error under the ground truth below ``epipolar_threshold``), the GT-correct
matches' median and 90th-percentile Sampson error (how well they are located) and their
image scales; then the pose success (rotation error under ``success_deg``, mean over
``--ransac_runs`` LO-RANSAC runs) from all of the method's matches, from its plain-plain
matches alone, and from the baseline's.

    python research/scripts/match_quality.py --data /work/outputs/r7/WIDE \\
        --features OUT/features [--method rectsift] [--baseline sift] [--ransac_runs 5]
"""

from __future__ import annotations

import argparse
import logging
from functools import lru_cache
from pathlib import Path

import numpy as np

from rectified_colmap.errors import run_script
from rectified_colmap.eval.config import EvalConf
from rectified_colmap.eval.matching import FeatureSource, match_ratio
from rectified_colmap.eval.pairs import Pair, read_pairs_with_gt
from rectified_colmap.eval.relpose import (
    FAILED_DEG,
    estimate_relative_pose,
    fundamental_from_pose,
    pose_errors,
    sampson_error,
)
from rectified_colmap.io.hloc_h5 import read
from rectified_colmap_research.evaluation.match_sources import plain_index

logger = logging.getLogger("match_quality")

KINDS = ("plain-plain", "plain-added", "added-added")


def match_kinds(matches: np.ndarray, added0: np.ndarray, added1: np.ndarray) -> np.ndarray:
    """(M,) index into KINDS of each match (M, 2) [i0, i1]: how many of its two features
    are added (``added0`` / ``added1``: (N,) bool per feature of each image)."""
    m = np.asarray(matches, np.int64).reshape(-1, 2)
    return added0[m[:, 0]].astype(np.int64) + added1[m[:, 1]]


def pose_success(x0: np.ndarray, x1: np.ndarray, pair: Pair, conf: EvalConf) -> float:
    """Share of ``conf.ransac_runs`` LO-RANSAC runs (seeds as the evaluation's) whose
    rotation error is under ``conf.success_deg``; 0 for fewer than 5 matches."""
    ok = []
    for k in range(conf.ransac_runs):
        est = estimate_relative_pose(
            x0, x1, pair.K0, pair.K1, conf.ransac_max_error, conf.ransac_seed + k
        )
        err = FAILED_DEG if est is None else pose_errors(est[0], est[1], pair.R, pair.t)[0]
        ok.append(err < conf.success_deg)
    return float(np.mean(ok))


@lru_cache(maxsize=64)
def added(method: Path, base: Path, name: str) -> np.ndarray:
    """(N,) bool per feature of ``method`` for the image: not in ``base`` (exactly)."""
    return plain_index(read_features(method, name), read_features(base, name)) < 0


def pair_matches(pair: Pair, method: Path, base: Path, conf: EvalConf) -> dict:
    """One pair, features from the hloc files ``method`` and ``base``: the method's matches'
    Sampson errors under the GT (M,), kinds (M,), image scales (M,: the geometric mean of
    the two features' ``scales``, NaN where the file has none), and the pose success from
    all of them, from the plain-plain ones alone and from the baseline's matches."""
    f0, f1 = read_features(method, pair.name0), read_features(method, pair.name1)
    b0, b1 = read_features(base, pair.name0), read_features(base, pair.name1)
    F = fundamental_from_pose(pair.K0, pair.K1, pair.R, pair.t)
    out = {}
    for key, a0, a1 in (("method", f0, f1), ("base", b0, b1)):
        m = match_ratio(a0["descriptors"], a1["descriptors"], conf.ratio, conf.mutual)
        x0, x1 = a0["keypoints"][m[:, 0]], a1["keypoints"][m[:, 1]]
        out[key] = (m, x0, x1)
    m, x0, x1 = out["method"]
    kinds = match_kinds(m, added(method, base, pair.name0), added(method, base, pair.name1))
    plain = kinds == 0
    return {
        "error": sampson_error(F, x0, x1) if len(m) else np.zeros(0),
        "kind": kinds,
        "scale": np.sqrt(f0["scales"][m[:, 0]] * f1["scales"][m[:, 1]]),
        "success": pose_success(x0, x1, pair, conf),
        "success_plain": pose_success(x0[plain], x1[plain], pair, conf),
        "success_base": pose_success(*out["base"][1:], pair, conf),
    }


def kind_table(records: list[dict], threshold: float) -> list[str]:
    """Markdown rows per kind: matches, GT-correct share, the GT-correct matches' median
    and 90th-percentile Sampson error (px), median image scale."""
    err = np.concatenate([r["error"] for r in records])
    kind = np.concatenate([r["kind"] for r in records])
    scale = np.concatenate([r["scale"] for r in records])
    rows = [
        "| matches joining | matches | GT-correct | Sampson error of the GT-correct, median / "
        "90 % (px) | image scale, median |",
        "|---|---|---|---|---|",
    ]
    for k, name in enumerate(KINDS):
        sel = kind == k
        good = err[sel & (err < threshold)]
        if not sel.any():
            rows.append(f"| {name} | 0 | - | - | - |")
            continue
        q = f"{np.median(good):.2f} / {np.quantile(good, 0.9):.2f}" if len(good) else "-"
        rows.append(
            f"| {name} | {sel.sum()} | {len(good) / sel.sum():.0%} | {q} | "
            f"{np.nanmedian(scale[sel]):.1f} |"
        )
    return rows


@lru_cache(maxsize=8)
def read_features(path: Path, name: str) -> dict[str, np.ndarray]:
    """One image's ``keypoints`` and ``descriptors`` as eval.matching.FeatureSource gives
    them, and its image ``scales`` (N,) (NaN where the file has none), read once."""
    d = FeatureSource(path)[name]
    s = read(path, name).get("scales")
    d["scales"] = np.full(len(d["keypoints"]), np.nan) if s is None else np.asarray(s, float)
    return d


def main(argv=None) -> int:
    p = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("--data", type=Path, required=True, help="scenes with pairs_with_gt.txt")
    p.add_argument("--features", type=Path, required=True, help="eval_strecha's features/")
    p.add_argument("--method", default="rectsift")
    p.add_argument("--baseline", default="sift")
    p.add_argument("--ransac_runs", type=int, default=5)
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="[%(asctime)s %(name)s] %(message)s")
    conf = EvalConf(ransac_runs=args.ransac_runs)
    scenes = sorted(d for d in args.data.iterdir() if (d / "pairs_with_gt.txt").is_file())
    if not scenes:
        raise SystemExit(f"{args.data}: no scene with pairs_with_gt.txt")
    records = []
    for scene in scenes:
        method = args.features / scene.name / f"{args.method}.h5"
        base = args.features / scene.name / f"{args.baseline}.h5"
        for path in (method, base):
            if not path.is_file():
                raise SystemExit(f"{path}: feature file not found")
        pairs = read_pairs_with_gt(scene / "pairs_with_gt.txt")
        records += [pair_matches(q, method, base, conf) for q in pairs]
        logger.info("%s: %d pairs", scene.name, len(pairs))
    print(f"{len(records)} pairs of {args.data}; {args.method} beside {args.baseline}\n")
    print("\n".join(kind_table(records, conf.epipolar_threshold)))
    mean = {k: 100 * np.mean([r[k] for r in records]) for k in records[0] if "success" in k}
    print(
        f"\npose success (R error < {conf.success_deg:g} deg, mean of {conf.ransac_runs} "
        f"RANSAC runs): {args.method} {mean['success']:.1f} %, its plain-plain matches "
        f"alone {mean['success_plain']:.1f} %, {args.baseline} {mean['success_base']:.1f} %"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(run_script(main, "match_quality.py"))
