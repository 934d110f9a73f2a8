#!/usr/bin/env python
"""Where the default's GT-consistent matches come from on planar pairs, by the kind of view
of each endpoint, beside the view pixels each kind costs.

For the pairs of ``--data`` (pairs.json and images/, e.g. one half of
build_extreme_pairs.py's generated pairs with ``--split choose``), every image is extracted
as eval_homography.py's ``rectsift`` does (extreme_pairs.guessed_camera: f = 1.2 x the
longer side, the embedded network, ``--conf``). Each feature gets the kind of the view it came
from (``view_kinds``): ``plain`` (plain SIFT on the image), ``depth`` (a plane of the
depth network), ``hyp`` / ``rest`` (a plane hypothesis of the vanishing points, over the
whole image / over the rest of a plane), ``depth-nbr`` / ``hyp-nbr`` / ``rest-nbr``
(their tilt neighbours), ``blind`` (ASIFT-like views without an estimate). Both directions of every
pair are matched as eval_homography.py matches them (ratio test, mutual), and each case is
classed by whether plain SIFT's features alone (the output's plain part, exactly plain
SIFT) and all features solve it. The output (markdown): cases per class; the views'
pixels per kind (x the images' own); per class the GT-consistent matches by the kinds of
their two endpoints; and, on the cases only the default solves, the matches with an
endpoint of each kind per unit of view pixels (which kind of view earns its pixels).

    python research/scripts/view_yield.py --data OUT/seed0 --split choose --output yield.md
"""

from __future__ import annotations

import argparse
import logging
from collections import Counter, defaultdict
from pathlib import Path

import numpy as np

from rectified_colmap.config import DEFAULT_DEPTH_MODEL, ExtractConf, confs
from rectified_colmap.errors import run_script
from rectified_colmap.eval.config import HomographyConf
from rectified_colmap.eval.homography import evaluate_pair, match_gt_errors
from rectified_colmap.pipeline import ImageResult
from rectified_colmap_research.evaluation.view_meeting import view_kinds
from rectified_colmap_research.evaluation.extreme_pairs import extract_guessed, read_half

logger = logging.getLogger("view_yield")
KINDS = ("plain", "depth", "depth-nbr", "hyp", "hyp-nbr", "rest", "rest-nbr", "blind")


def feature_kinds(res: ImageResult) -> tuple[np.ndarray, Counter]:
    """(N,) kind of each of ``res.features`` and the view pixels per kind."""
    names = view_kinds(res.planes.patches if res.planes is not None else [])
    kind = np.full(len(res.features), "plain", object)
    rect = res.features.patch >= 0
    kind[rect] = [names[i] for i in res.features.patch[rect]]
    pixels = Counter()
    for r in res.rectifications:
        pixels[names[r.patch_index]] += r.pixels
    return kind, pixels


def per_pixel(matches: Counter, pixels: Counter, image_pixels: float) -> dict[str, float]:
    """kind -> GT-consistent matches with an endpoint of that kind per unit of view pixels
    (1 = the images' own pixels); ``matches`` counts kind pairs "a+b"."""
    ends = Counter()
    for pair, n in matches.items():
        for kind in set(pair.split("+")):
            ends[kind] += n
    return {k: ends[k] / (pixels[k] / image_pixels) for k in pixels if pixels[k] > 0}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--data", type=Path, required=True, help="folder with pairs.json, images/")
    p.add_argument("--split", help="the half (choose / check) of a generated pair file")
    p.add_argument("--conf", default="rectsift", choices=sorted(confs))
    p.add_argument("--output", type=Path, required=True, help="markdown file")
    args = p.parse_args(argv)
    from rectified_colmap.depth.registry import load_depth_source

    pairs = read_half(args.data, args.split)
    conf, hconf = ExtractConf.from_dict(confs[args.conf]), HomographyConf()
    source = load_depth_source(DEFAULT_DEPTH_MODEL, num_threads=1)
    images: dict[str, tuple] = {}

    def features(name: str):
        if name not in images:
            res, cam = extract_guessed(args.data, name, source, conf)
            f, plain = res.features, res.features.patch < 0
            every = {"keypoints": f.keypoints, "descriptors": f.descriptors}
            only = {"keypoints": f.keypoints[plain], "descriptors": f.descriptors[plain]}
            images[name] = (every, only, *feature_kinds(res), cam.width * cam.height)
            logger.info("%s: %d features", name, len(f))
        return images[name]

    classes, matches = Counter(), defaultdict(Counter)
    for pair in pairs:
        for case in (pair, pair.reverse()):
            a, b = features(case.im0), features(case.im1)
            plain = evaluate_pair(case, a[1], b[1], hconf)["success"]
            every = evaluate_pair(case, a[0], b[0], hconf)["success"]
            verdict = {True: "solves", False: "fails"}
            cls = f"plain {verdict[plain]}, default {verdict[every]}"
            classes[cls] += 1
            m, err = match_gt_errors(case, a[0], b[0], hconf)
            for i, j in m[err < hconf.gt_threshold]:
                matches[cls]["+".join(sorted((a[2][i], b[2][j])))] += 1
    pixels, image_pixels = Counter(), sum(v[4] for v in images.values())
    for v in images.values():
        pixels.update(v[3])
    args.output.write_text(report(args, classes, matches, pixels, image_pixels))
    logger.info("wrote %s", args.output)
    return 0


def report(args, classes: Counter, matches: dict, pixels: Counter, image_pixels: float) -> str:
    """The markdown of ``main``'s counts."""
    lines = [f"# View yield: {args.data} {args.split or ''} ({args.conf})", ""]
    lines += [f"- {cls}: {n} cases" for cls, n in classes.most_common()]
    share = ", ".join(f"{k} {pixels[k] / image_pixels:.2f}" for k in KINDS if pixels[k])
    lines += ["", f"View pixels per kind, x the images' own: {share}", ""]
    for cls, counts in matches.items():
        total = sum(counts.values())
        lines += [f"## {cls}: {total} GT-consistent matches", "", "| kinds | matches | % |"]
        lines += ["|---|---|---|"]
        lines += [f"| {k} | {n} | {100 * n / total:.1f} |" for k, n in counts.most_common()]
        yield_ = per_pixel(counts, pixels, image_pixels)
        per = ", ".join(f"{k} {yield_[k]:.0f}" for k in KINDS if k in yield_)
        lines += ["", f"Matches with an endpoint of each kind per unit of view pixels: {per}", ""]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    raise SystemExit(run_script(main, "view_yield"))
