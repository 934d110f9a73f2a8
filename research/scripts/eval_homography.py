#!/usr/bin/env python
"""Plain vs rectified SIFT on planar pairs with ground-truth homographies (EVD protocol).

Reproducible benchmark behind docs/evaluation.md ("Issue 9"). For a folder with
``pairs.json`` and ``images/`` (shared/data/evd-dev: see its README):

1. features per method into ``<output_dir>/features/<method>.h5`` (existing files are
   reused), every image with a guessed pinhole camera (no EXIF): f = ``--focal_factor`` x
   max(W, H), principal point at the centre;
   - ``sift``: plain COLMAP SIFT (the pipeline without depth);
   - ``rectsift``: the pipeline with the embedded depth network (``--depth_model``);
   - ``oracle``: the pipeline with the plane orientation taken from the ground-truth
     homography, decomposed with the guessed intrinsics (one plane over the whole image,
     normal n0 in image 0 and R n0 in image 1): the upper bound of rectification itself;
   - ``asift``: OpenCV's ASIFT (``cv2.AffineFeature`` over SIFT, the budget per synthesised
     view; rectified_colmap_research.evaluation.asift), the view-synthesis anchor;
   - extra variants with ``--variant NAME=JSON`` or ``NAME=CONF`` (conf overrides or a named
     configuration such as ``rectsift-fast``; ``"_base": "oracle"``
     in the JSON makes it a variant of ``oracle``, else of ``rectsift``);
2. homography evaluation in both directions of every pair (rectified_colmap.eval.homography;
   a pair's ``region0``, where the file gives one, restricts its errors and GT-consistent
   matches to that plane) -> records.csv, summary.md; ``--group_by KEY`` adds a summary per
   value of that key of the pair file (e.g. ``band`` of scripts/build_plane_pairs.py);
   ``--region_ransac`` estimates each homography from the matches in the region only.

Example::

    python scripts/eval_homography.py --data ../shared/data/evd-dev --output_dir outputs/evd \
        --methods sift rectsift oracle
"""

from __future__ import annotations

import argparse
import csv
import json
import logging
import sys
from pathlib import Path

import cv2
import numpy as np

from rectified_colmap import camera as cam_utils
from rectified_colmap.config import ExtractConf
from rectified_colmap.eval.homography import (
    HomographyConf,
    evaluate_homography_pairs,
    homography_group_markdown,
    homography_markdown,
    plane_normals_from_homography,
    read_homography_pairs,
    visible_grid,
)
from rectified_colmap.geometry import scaled_size
from rectified_colmap.pipeline import extract_image
from rectified_colmap.errors import run_script
from rectified_colmap_research.evaluation.asift import asift_features
from rectified_colmap_research.evaluation.oracle import plane_depth
from rectified_colmap_research.evaluation.methods import (
    add_variant_argument,
    method_conf,
    parse_variants,
)

logger = logging.getLogger("eval_homography")
METHODS = ("sift", "rectsift", "oracle", "asift")


def guessed_camera(width: int, height: int, focal_factor: float):
    f = focal_factor * max(width, height)
    return cam_utils.make_camera("PINHOLE", [f, f, width / 2, height / 2], width, height)


def oracle_normals(pairs, cameras) -> dict[str, np.ndarray]:
    """image name -> (3,) plane normal from the ground-truth homography of its pair."""
    out = {}
    for p in pairs:
        K0 = cam_utils.calibration_matrix(cameras[p.im0])
        K1 = cam_utils.calibration_matrix(cameras[p.im1])
        n0, n1 = plane_normals_from_homography(p.H, K0, K1, visible_grid(p, 20))
        out[p.im0], out[p.im1] = n0, n1
    return out


def extract_method(
    method: str, names: list[str], root: Path, cameras, normals, args, out: Path
) -> Path:
    from rectified_colmap.io.hloc_h5 import HlocFeatureWriter

    h5 = out / "features" / f"{method}.h5"
    if h5.exists():
        logger.info("%s: reusing %s", method, h5)
        return h5
    h5.parent.mkdir(parents=True, exist_ok=True)
    overrides = json.loads(args.rect_conf) if args.rect_conf else {}
    variant = dict(args.variants.get(method, {}))
    base = variant.pop("_base", "rectsift")  # a variant of rectsift (network) or of oracle
    # sift: exactly plain COLMAP SIFT; rectsift, oracle and the variants: --rect_conf, then
    # the variant's own overrides (methods.method_conf)
    # asift: plain SIFT's budget, per synthesised view
    own = None if method in ("sift", "asift") else {"rectsift": variant}
    name = "sift" if method in ("sift", "asift") else "rectsift"
    conf = ExtractConf.from_dict(
        method_conf(name, own, base=overrides, max_num_features=args.max_num_features)
    )
    source = None
    if method == "asift" or args.depth_model == "none":
        pass  # asift needs no depth; none: plain SIFT
    elif method == "rectsift" or (method in args.variants and base == "rectsift"):
        from rectified_colmap.depth.registry import load_depth_source
        from rectified_colmap.config import DEFAULT_DEPTH_MODEL

        source = load_depth_source(args.depth_model or DEFAULT_DEPTH_MODEL, num_threads=1)
    tmp = h5.with_suffix(".h5.tmp")
    tmp.unlink(missing_ok=True)
    with HlocFeatureWriter(tmp) as writer:
        for name in names:
            rgb = cv2.cvtColor(cv2.imread(str(root / name)), cv2.COLOR_BGR2RGB)
            cam = cameras[name]
            depth = None
            if method == "asift":
                gray = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
                feats = asift_features(gray, conf.sift.max_num_features)
                writer.write(name, feats, (cam.width, cam.height))
                logger.info("%s %s: %d keypoints", method, name, len(feats))
                continue
            if source is not None:
                depth = source(rgb, cam, name)
            elif method == "oracle" or base == "oracle":
                w, h = scaled_size(cam.width, cam.height, conf.normals.work_max_size)
                depth = plane_depth(cam, normals[name], (h, w))  # the plane's exact depth
            res = extract_image(rgb, cam, depth, conf, np.random.default_rng(0))
            writer.write(name, res.features, (cam.width, cam.height))
            logger.info(
                "%s %s: %d keypoints, %d rectified, %d patches",
                method,
                name,
                len(res.features),
                int((res.features.patch >= 0).sum()),
                len(res.rectifications),
            )
    tmp.rename(h5)
    return h5


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--data", type=Path, required=True, help="folder with pairs.json, images/")
    p.add_argument("--output_dir", type=Path, required=True)
    p.add_argument("--methods", nargs="+", default=list(METHODS), choices=METHODS)
    add_variant_argument(p, "--rect_conf")
    p.add_argument(
        "--depth_model",
        default=None,
        help="registry name, .onnx, or none (no depth: plain SIFT)",
    )
    p.add_argument("--rect_conf", default=None, help="JSON conf overrides (rectsift, oracle)")
    p.add_argument("--max_num_features", type=int, default=None)
    p.add_argument("--focal_factor", type=float, default=1.2)
    p.add_argument(
        "--group_by",
        default=None,
        metavar="KEY",
        help="also summarise per value of this key of the pair records (e.g. band)",
    )
    p.add_argument(
        "--region_ransac",
        action="store_true",
        help="RANSAC on the matches in a pair's region only (HomographyConf.region_ransac)",
    )
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="[%(asctime)s %(name)s] %(message)s")
    try:
        args.variants = parse_variants(args.variant, taken=METHODS)
    except ValueError as e:
        p.error(str(e))
    pairs = read_homography_pairs(args.data / "pairs.json", args.data)
    names = list(dict.fromkeys(n for q in pairs for n in (q.im0, q.im1)))
    sizes = {}
    for q in pairs:
        sizes[q.im0], sizes[q.im1] = q.size0, q.size1
    cameras = {n: guessed_camera(*sizes[n], args.focal_factor) for n in names}
    normals = oracle_normals(pairs, cameras)
    out = args.output_dir
    methods = list(args.methods) + list(args.variants)
    feats = {m: extract_method(m, names, args.data, cameras, normals, args, out) for m in methods}
    conf = HomographyConf(region_ransac=args.region_ransac)
    records = evaluate_homography_pairs(pairs, feats, conf)
    with open(out / "records.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(records[0]))
        w.writeheader()
        w.writerows(records)
    table = homography_markdown(records, conf)
    if args.group_by:
        groups = {q.name: str(q.info.get(args.group_by, "-")) for q in pairs}
        table = homography_group_markdown(records, groups, conf) + "\n" + table
    (out / "summary.md").write_text(table)
    print(table)
    return 0


if __name__ == "__main__":
    sys.exit(run_script(main, "eval_homography"))
