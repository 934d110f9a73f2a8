#!/usr/bin/env python
"""Where a feature set's matches come from, beside plain SIFT's (eval/match_sources.py).

For feature files of the same images (hloc layout, e.g. from ``rectified-colmap extract
--hloc_features``): plain SIFT's (``--conf sift``) and one or more others. Per method, over
all pairs (hloc's NN-ratio matching): plain SIFT's matches kept, lost because an endpoint
was removed, lost to crowding (both endpoints still there), and the new matches; with
``--reference`` (a COLMAP model with the images' poses, e.g. plain SIFT's own
reconstruction) also how many are correct (Sampson distance under the model's relative
pose, on undistorted rays, scaled to pixels by the focal length).

Example (docs/evaluation.md, "Crowding")::

    python scripts/match_sources.py --plain sift.h5 --features plus=plus.h5 \
        --reference sfm_sift/ --output sources.md
"""

from __future__ import annotations

import argparse
import itertools
import logging
import sys
from pathlib import Path

import numpy as np
import pycolmap

from rectified_colmap.camera import image_to_rays
from rectified_colmap_research.evaluation.match_sources import (
    MatchSources,
    correct_matches,
    nn_ratio_mutual,
    pair_sources,
    plain_index,
)
from rectified_colmap.eval.matching import FeatureSource, parse_methods
from rectified_colmap.eval.pairs import read_pair_list
from rectified_colmap.eval.relpose import fundamental_from_pose
from rectified_colmap.errors import run_script

logger = logging.getLogger("match_sources")


class Reference:
    """Relative geometry of image pairs from a COLMAP model: keypoints are mapped to
    undistorted rays (z = 1) scaled by the mean focal length f of the two cameras, so
    Sampson distances under ``fundamental(a, b, f)`` are about pixels."""

    def __init__(self, path: Path):
        self.rec = pycolmap.Reconstruction(str(path))
        self.images = {im.name: im for im in self.rec.images.values()}

    def __contains__(self, name: str) -> bool:
        return name in self.images

    def focal(self, name: str) -> float:
        cam = self.rec.cameras[self.images[name].camera_id]
        return 0.5 * (cam.focal_length_x + cam.focal_length_y)

    def points(self, name: str, xy: np.ndarray, f: float) -> np.ndarray:
        cam = self.rec.cameras[self.images[name].camera_id]
        return image_to_rays(cam, xy)[:, :2] * f

    def fundamental(self, a: str, b: str, f: float) -> np.ndarray:
        """x_b^T F x_a = 0 for the scaled rays of ``points``."""
        T = self.images[b].cam_from_world() * self.images[a].cam_from_world().inverse()
        K = np.diag([f, f, 1.0])
        return fundamental_from_pose(K, K, T.rotation.matrix(), np.asarray(T.translation))


def run(plain: Path, methods: dict[str, Path], pairs, reference, ratio: float) -> dict:
    P = FeatureSource(plain)
    sources = {m: FeatureSource(p) for m, p in methods.items()}
    totals = {m: MatchSources() for m in methods}
    index: dict[tuple[str, str], np.ndarray] = {}
    keypoints: dict[tuple[str, str], int] = {}
    for a, b in pairs:
        pa, pb = P[a], P[b]
        mp = nn_ratio_mutual(pa["descriptors"], pb["descriptors"], ratio)
        F = f = ok_p = None
        if reference is not None and a in reference and b in reference:
            f = 0.5 * (reference.focal(a) + reference.focal(b))
            F = reference.fundamental(a, b, f)
            ok_p = correct_matches(
                F,
                reference.points(a, pa["keypoints"], f),
                reference.points(b, pb["keypoints"], f),
                mp,
            )
        for m, src in sources.items():
            fa, fb = src[a], src[b]
            for n, feats in ((a, fa), (b, fb)):
                if (m, n) not in index:
                    index[m, n] = plain_index(feats, P[n])
                    keypoints[m, n] = len(feats["keypoints"])
            mf = nn_ratio_mutual(fa["descriptors"], fb["descriptors"], ratio)
            ok_f = None
            if F is not None:
                xa = reference.points(a, fa["keypoints"], f)
                ok_f = correct_matches(F, xa, reference.points(b, fb["keypoints"], f), mf)
            counts = pair_sources(
                mp,
                mf,
                index[m, a],
                index[m, b],
                (len(pa["keypoints"]), len(pb["keypoints"])),
                ok_p,
                ok_f,
            )
            totals[m] = totals[m] + counts
        logger.info("%s - %s done", a, b)
    names = {n for ab in pairs for n in ab}
    plain_kp = sum(len(P[n]["keypoints"]) for n in names)
    kp = {m: sum(keypoints[m, n] for n in names) / plain_kp for m in methods}
    return {"totals": totals, "keypoints": kp}


def markdown(result: dict, num_pairs: int) -> str:
    rows = [
        f"{num_pairs} pairs, hloc NN-ratio matching",
        "",
        "| method | keypoints vs plain | plain SIFT's matches | kept | lost: endpoint removed "
        "| lost: crowded out | new plain-plain | with an added feature (correct) "
        "| correct: all vs plain SIFT alone |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for m, t in result["totals"].items():
        added = f"{t.with_added}" + (
            f" ({t.with_added_correct})" if t.with_added_correct is not None else ""
        )
        correct = f"{t.correct} vs {t.plain_correct}" if t.correct is not None else "-"
        kept = f"{t.kept} ({100 * t.kept / max(t.plain_matches, 1):.1f} %)"
        rows.append(
            f"| {m} | {result['keypoints'][m]:.3f}x | {t.plain_matches} | {kept} | "
            f"{t.lost_removed} | {t.lost_crowded} | {t.new_plain_plain} | {added} | {correct} |"
        )
    return "\n".join(rows) + "\n"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--plain", type=Path, required=True, help="plain SIFT's feature file")
    p.add_argument(
        "--features", nargs="+", required=True, metavar="NAME=H5", help="feature files to compare"
    )
    p.add_argument("--pairs", type=Path, help="hloc pair list (default: all pairs of images)")
    p.add_argument("--reference", type=Path, help="COLMAP model with the images' poses")
    p.add_argument("--ratio", type=float, default=0.8)
    p.add_argument("--output", type=Path, help="also write the table here")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="[%(asctime)s %(name)s] %(message)s")
    try:
        methods = parse_methods(args.features)
        if not args.plain.is_file():
            raise ValueError(f"--plain {args.plain}: not a file")
        names = sorted(FeatureSource(args.plain).names())
        pairs = read_pair_list(args.pairs) if args.pairs else list(itertools.combinations(names, 2))
        reference = Reference(args.reference) if args.reference else None
    except (ValueError, OSError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    try:
        result = run(args.plain, methods, pairs, reference, args.ratio)
    except (KeyError, ValueError) as e:  # an image missing from a file, a malformed file
        print(f"error: {e.args[0] if e.args else e}", file=sys.stderr)
        return 1
    table = markdown(result, len(pairs))
    print(table)
    if args.output:
        args.output.write_text(table)
    return 0


if __name__ == "__main__":
    sys.exit(run_script(main, "match_sources"))
