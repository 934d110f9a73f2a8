#!/usr/bin/env python
"""Where do the matches die? The pipeline stage by stage on planar pairs (issue 41, item 2).

For every image of a homography pair file (e.g. the generated extreme pairs of
build_extreme_pairs.py; ``--split`` keeps one half), the views are planned as the pipeline
plans them, and the rectified features are taken after each stage, always together with
the image's plain SIFT. Each set is evaluated as a method of its own
(rectified_colmap.eval.homography: mutual ratio matching, RANSAC, visible error,
GT-consistent matches):

- ``met`` (geometry, no SIFT): pairs whose two view sets meet, i.e. some view of each image
  holds the point and the map between the two views has a transition tilt of at most 2 on
  at least 10 % of the overlap (rectified_colmap_research.evaluation.view_meeting);
- ``plain``: plain SIFT alone (the base every other set contains);
- ``views_uncapped``: SIFT in every view with no pixel budget (each view at "nothing
  shrinks", ``--unlimited`` features per view): what rectification could find at all;
- ``views``: the views as the pipeline sizes them (its pixel budget), ``--unlimited``
  features;
- ``budget``: the views' SIFT budgets (rectified_colmap.budget.view_budgets);
- ``dedup``: without twins of plain features (dedup.distinct_from_plain);
- ``final``: cut to the room above plain SIFT, look-alikes of plain features only in its
  unused budget (budget.cut_to_room), blind views' features on top
  (pipeline.blind_on_top): the pipeline's output (pipeline.views_and_features).

Orientation (``--orientation``): ``true`` gives each image the exact depth of its plane
where the plane is seen (the pair file's ``normal0``/``normal1`` and regions, as a depth
sensor would; vanishing points and plane hypotheses off), ``network`` runs the conf with the
embedded network. Cameras (``--cameras``): ``true`` (the pair file's focal lengths x
``--focal_factor``: 0.7 / 1.5 is the focal length 30 % short / 50 % long) or ``guessed``
(COLMAP's 1.2 x the longer side, what a photo without EXIF gets). Writes ``stages.md`` (per
stage and half: pairs solved, median GT-consistent matches, rectified features per image)
and records.csv.

    python research/scripts/diagnose_views.py --data ../outputs/extreme-pairs --split choose \\
        --orientation true --output_dir outputs/diagnose-true
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import sys
from pathlib import Path

import cv2
import numpy as np

from rectified_colmap.config import ExtractConf
from rectified_colmap.errors import run_script
from rectified_colmap.eval.homography import (
    HomographyConf,
    evaluate_homography_pairs,
)
from rectified_colmap.features import Features
from rectified_colmap.geometry import scaled_size
from rectified_colmap.io.hloc_h5 import rootsift_unit
from rectified_colmap.io.images import read_image
from rectified_colmap.pipeline import (
    image_planes,
    image_views,
    lines_support,
    rectified_to_keep,
    view_sift_budgets,
    views_and_features,
    with_vanishing_points,
)
from rectified_colmap.planes import BLIND_AXIS
from rectified_colmap.views import blind_patches, joined_views
from rectified_colmap.sift import Sift, plain_sift, rectified_features
from rectified_colmap_research.evaluation.homography_report import write_records_csv
from rectified_colmap_research.evaluation.extreme_pairs import pinhole_camera, read_half
from rectified_colmap_research.evaluation.oracle import plane_depth
from rectified_colmap_research.evaluation.view_meeting import met_fraction, view_set

logger = logging.getLogger("diagnose_views")
STAGES = ("plain", "views_uncapped", "views", "budget", "dedup", "final")
MET_FRACTION = 0.1
"""A pair's view sets meet when they meet on at least this fraction of its overlap."""
UNCAPPED = {"max_patch_side": 8192, "max_view_pixels_factor": 1e6}


def one_image_views(
    gray, rgb, camera, normal, region, plain, conf: ExtractConf, network, uncapped, rng, sift
):
    """(views, views without a pixel budget or None, the pipeline's features) of one image
    with plain SIFT's features ``plain`` (pipeline.views_and_features: blind views where
    the others add almost nothing or the lines confirm no plane; the uncapped views where
    the others add almost nothing): from the exact depth of its
    true plane within its region (``network`` None) or from the network's depth with the
    conf's vanishing points."""
    if network is None:
        w, h = scaled_size(camera.width, camera.height, conf.normals.work_max_size)
        depth = plane_depth(camera, normal, (h, w), region)
    else:
        depth = network(rgb, camera, "")
    planes, _ = image_planes(camera, depth, conf, rng, {})
    lined = with_vanishing_points(gray, camera, planes, conf, rng, {})
    supported = lines_support(planes, lined, conf)  # as extract_image
    planes, shape = lined, lined.labels.shape
    views, final = views_and_features(
        gray, camera, planes.patches, shape, plain, conf, sift, None, supported
    )
    if not uncapped:
        return views, None, final
    loose = dataclasses.replace(conf, rectify=dataclasses.replace(conf.rectify, **UNCAPPED))
    free = image_views(gray, camera, planes.patches, shape, len(plain), loose, 1e12)
    if any(p.axis == BLIND_AXIS for p in views.patches):
        blind = image_views(
            gray, camera, blind_patches(camera, shape), shape, len(plain), loose, 1e12
        )
        free = joined_views(free, blind)
    return views, free, final


def stage_features(
    gray, camera, conf: ExtractConf, plain, views, uncapped, final, unlimited: int, sift
):
    """{stage: Features} of one image (module docstring) with plain SIFT's ``plain``;
    ``final``: the pipeline's output (pipeline.views_and_features: the blind views'
    features come on top of the others, pipeline.blind_on_top, which the stages before
    count as any second-tier view's)."""
    border = conf.rectify.border

    def detect(vs, budgets):
        parts = [
            rectified_features(gray, camera, r, int(b), conf.sift, border, sift)
            for r, b in zip(vs.rects, budgets)
        ]
        return Features.concatenate(parts)

    out = {"plain": plain}
    if uncapped is not None:
        free = detect(uncapped, [unlimited] * len(uncapped.rects))
        out["views_uncapped"] = Features.concatenate([plain, free])
    out["views"] = Features.concatenate([plain, detect(views, [unlimited] * len(views.rects))])
    rect = detect(views, view_sift_budgets(views, len(plain), conf))
    out["budget"] = Features.concatenate([plain, rect])
    index, _ = rectified_to_keep(rect, plain, views, conf)
    out["dedup"] = Features.concatenate([plain, rect.subset(index)])
    out["final"] = final
    return out


def as_mapping(f: Features) -> dict[str, np.ndarray]:
    return {"keypoints": f.keypoints, "descriptors": rootsift_unit(f.descriptors).T}


def summary_markdown(records: list[dict], pairs, counts: dict, met: dict[str, bool]) -> str:
    """Per stage and half: pairs solved (either direction), median GT-consistent matches per
    case, rectified features per image; first the pairs whose view sets meet."""
    half = {p.name: str(p.info.get("split", "all")) for p in pairs}
    halves = sorted(set(half.values()))
    lines = [
        "| stage | " + " | ".join(f"{h}: solved / median GT / rect. kp" for h in halves) + " |"
    ]
    lines.append("|---|" + "---|" * len(halves))
    cells = []
    for h in halves:
        names = [p.name for p in pairs if half[p.name] == h]
        cells.append(f"{sum(met[n] for n in names)} / {len(names)} meet")
    lines.append("| met (geometry) | " + " | ".join(cells) + " |")
    for stage in [s for s in STAGES if s in counts and counts[s]]:
        cells = []
        for h in halves:
            rs = [r for r in records if r["method"] == stage and half[r["pair"]] == h]
            solved = {r["pair"] for r in rs if r["success"]}
            n = len({r["pair"] for r in rs})
            gt = np.median([r["num_gt"] for r in rs]) if rs else 0
            kp = np.mean(counts[stage][h]) if counts[stage].get(h) else 0
            cells.append(f"{len(solved)} / {n}, {gt:.0f}, {kp:.0f}")
        lines.append(f"| {stage} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def pair_camera(q, k: int, args):
    """Image k's camera: the pair file's true focal length x --focal_factor, or COLMAP's
    guess (1.2 x the longer side) with --cameras guessed; principal point at the centre."""
    size = q.size0 if k == 0 else q.size1
    if args.cameras == "guessed":
        return pinhole_camera(1.2 * max(size), size)
    return pinhole_camera(args.focal_factor * float(q.info[f"focal{k}"]), size)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--data", type=Path, required=True, help="folder with pairs.json, images/")
    p.add_argument("--output_dir", type=Path, required=True)
    p.add_argument("--split", default=None, help="only the pairs of this half (e.g. choose)")
    p.add_argument("--orientation", choices=("true", "network"), default="true")
    p.add_argument("--cameras", choices=("true", "guessed"), default="true")
    p.add_argument("--focal_factor", type=float, default=1.0, help="x the true focal length")
    p.add_argument("--uncapped", action="store_true", help="also the views_uncapped stage")
    p.add_argument("--unlimited", type=int, default=100000, help="SIFT budget of a free view")
    p.add_argument("--max_pairs", type=int, default=None)
    p.add_argument("--conf", default=None, help="JSON overrides of the extraction conf")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="[%(asctime)s %(name)s] %(message)s")
    cv2.setNumThreads(1)
    pairs = read_half(args.data, args.split, args.max_pairs)
    overrides = json.loads(args.conf) if args.conf else {}
    if args.orientation == "true":  # the true plane's own view only
        overrides = {"vp": {"enabled": False, "line_hypotheses": 0}, **overrides}
    conf = ExtractConf.from_dict(overrides)
    network = None
    if args.orientation == "network":
        from rectified_colmap.config import DEFAULT_DEPTH_MODEL
        from rectified_colmap.depth.registry import load_depth_source

        network = load_depth_source(DEFAULT_DEPTH_MODEL, num_threads=1)
    sift = Sift()
    feats = {s: {} for s in STAGES}
    counts = {s: {} for s in STAGES}
    met = {}
    for q in pairs:
        sets = []
        for k, name in enumerate((q.im0, q.im1)):
            camera = pair_camera(q, k, args)
            rgb = read_image(args.data / name)
            gray = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
            normal = np.asarray(q.info[f"normal{k}"], np.float64)
            region = q.region0 if k == 0 else q.region1
            rng = np.random.default_rng(0)
            plain = plain_sift(gray, conf.sift, sift)
            views, uncapped, final = one_image_views(
                gray, rgb, camera, normal, region, plain, conf, network, args.uncapped, rng, sift
            )
            sets.append(view_set(camera, views.rects))
            out = stage_features(
                gray, camera, conf, plain, views, uncapped, final, args.unlimited, sift
            )
            for s, f in out.items():
                feats[s][name] = as_mapping(f)
                half = str(q.info.get("split", "all"))
                counts[s].setdefault(half, []).append(int((f.patch >= 0).sum()))
        met[q.name] = met_fraction(q, sets[0], sets[1]) >= MET_FRACTION
        logger.info(
            "%s: met %s, %s",
            q.name,
            met[q.name],
            {s: len(feats[s].get(q.im0, {}).get("keypoints", [])) for s in STAGES},
        )
    feats = {s: f for s, f in feats.items() if f}
    records = evaluate_homography_pairs(pairs, feats, HomographyConf())
    args.output_dir.mkdir(parents=True, exist_ok=True)
    write_records_csv(args.output_dir / "records.csv", records)
    head = (
        f"orientation {args.orientation}, cameras {args.cameras}, focal x {args.focal_factor}, "
        f"{len(pairs)} pairs{f' ({args.split})' if args.split else ''}\n\n"
    )
    table = head + summary_markdown(records, pairs, counts, met)
    (args.output_dir / "stages.md").write_text(table)
    print(table)
    return 0


if __name__ == "__main__":
    sys.exit(run_script(main, "diagnose_views"))
