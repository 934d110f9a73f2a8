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
     normal n0 in image 0 and R n0 in image 1), the default conf otherwise: its vanishing
     points may turn that plane and add hypotheses (a variant with ``"vp": {"enabled":
     false, "line_hypotheses": 0}`` is the plane alone, as diagnose_views.py's ``true``);
   - ``oracle_true``: the same with the exact plane normals of the pair file (``normal0``,
     ``normal1`` in each camera's frame: scripts/build_extreme_pairs.py writes them); exact
     rectification only with the true cameras (``--cameras true``);
   - ``asift``: OpenCV's ASIFT (``cv2.AffineFeature`` over SIFT, the budget per synthesised
     view; rectified_colmap_research.evaluation.asift), the view-synthesis anchor;
   - extra variants with ``--variant NAME=JSON`` or ``NAME=CONF`` (conf overrides or a named
     configuration such as ``rectsift-fast``; ``"_base": "oracle"`` (or ``"oracle_true"``)
     in the JSON makes it a variant of that oracle, else of ``rectsift``);
   ``--cameras true`` gives the methods the pair file's true focal lengths (``focal0``,
   ``focal1``) times ``--true_focal_factor`` instead of the guess (focal errors of, e.g.,
   -30 to +50 %: factors 0.7 to 1.5); the CPU seconds of each image's extraction go to
   ``features/<method>.cpu.json``;
2. homography evaluation in both directions of every pair (rectified_colmap.eval.homography;
   a pair's ``region0``, where the file gives one, restricts its errors and GT-consistent
   matches to that plane) -> records.csv, summary.md: per method the pairs solved, the
   median GT-consistent matches and the CPU seconds (extraction per image, matching and
   RANSAC per case), per half of ``--split_key`` (``split``: choose / check of the generated
   extreme pairs) when the pair file has it, and in all; ``--group_by KEY [KEY ...]`` adds a
   table per key of the pair file (e.g. ``band`` of scripts/build_plane_pairs.py,
   ``tilt_bin scale_bin rotation both_oblique`` of scripts/build_extreme_pairs.py), each
   value per half (a joint key ``A+B``, e.g. ``both_oblique+scale_bin``: a row per pair of
   values); ``--region_ransac`` estimates each homography from the matches in the
   region only.

Example::

    python scripts/eval_homography.py --data ../shared/data/evd-dev --output_dir outputs/evd \
        --methods sift rectsift oracle
    python scripts/eval_homography.py --data ../outputs/extreme-pairs --output_dir outputs/ext \
        --methods sift rectsift asift oracle \
        --group_by tilt_bin scale_bin rotation both_oblique portrait
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from pathlib import Path

import cv2
import numpy as np

from rectified_colmap import camera as cam_utils
from rectified_colmap.config import ExtractConf
from rectified_colmap.eval.homography import (
    HomographyConf,
    evaluate_homography_pairs,
    homography_markdown,
    read_homography_pairs,
    visible_grid,
)
from rectified_colmap.geometry import scaled_size
from rectified_colmap.io.images import read_image
from rectified_colmap.pipeline import extract_image
from rectified_colmap.errors import run_script
from rectified_colmap_research.evaluation.asift import asift_features
from rectified_colmap_research.evaluation.homography_report import (
    JOINT,
    write_records_csv,
    split_group_markdown,
    split_summary_markdown,
)
from rectified_colmap_research.evaluation.extreme_pairs import (
    GUESSED_FOCAL_FACTOR,
    guessed_camera,
    pinhole_camera,
)
from rectified_colmap_research.evaluation.oracle import plane_depth, plane_normals_from_homography
from rectified_colmap_research.evaluation.methods import (
    add_variant_argument,
    method_conf,
    parse_variants,
)

logger = logging.getLogger("eval_homography")
METHODS = ("sift", "rectsift", "oracle", "oracle_true", "asift")
DEFAULT_METHODS = ("sift", "rectsift", "oracle", "asift")
ORACLES = ("oracle", "oracle_true")


def true_cameras(pairs, factor: float) -> dict:
    """image name -> PINHOLE camera with the pair file's true focal (``focal0``, ``focal1``)
    x ``factor``, principal point at the centre (as scripts/build_extreme_pairs.py renders)."""
    out = {}
    for p in pairs:
        for k, (name, size) in enumerate(((p.im0, p.size0), (p.im1, p.size1))):
            f = p.info.get(f"focal{k}")
            if f is None:
                raise ValueError(f"pair {p.name}: no focal{k} in the pair file (--cameras true)")
            out[name] = pinhole_camera(factor * float(f), size)
    return out


def true_normals(pairs) -> dict[str, np.ndarray]:
    """image name -> (3,) unit plane normal in its camera frame, from the pair file's
    ``normal0`` / ``normal1`` (facing the camera)."""
    out = {}
    for p in pairs:
        for k, name in enumerate((p.im0, p.im1)):
            n = p.info.get(f"normal{k}")
            if n is None:
                raise ValueError(f"pair {p.name}: no normal{k} in the pair file (oracle_true)")
            n = np.asarray(n, np.float64).reshape(3)
            out[name] = n / np.linalg.norm(n)
    return out


def image_regions(pairs) -> dict[str, list[np.ndarray] | None]:
    """image name -> the region of its pair where the plane is seen (``region0`` /
    ``region1``; None: the whole image): the oracles' depth covers only the plane."""
    out = {}
    for p in pairs:
        out[p.im0], out[p.im1] = p.region0, p.region1
    return out


def oracle_normals(pairs, cameras) -> dict[str, np.ndarray]:
    """image name -> (3,) plane normal from the ground-truth homography of its pair."""
    out = {}
    for p in pairs:
        K0 = cam_utils.calibration_matrix(cameras[p.im0])
        K1 = cam_utils.calibration_matrix(cameras[p.im1])
        try:
            n0, n1 = plane_normals_from_homography(p.H, K0, K1, visible_grid(p, 20))
        except ValueError as e:
            raise ValueError(f"pair {p.name}: {e}") from None
        out[p.im0], out[p.im1] = n0, n1
    return out


def extract_method(
    method: str, names: list[str], root: Path, cameras, normals, regions, args, out: Path
) -> Path:
    """Features of ``method`` for every image -> the hloc file (reused if it exists);
    ``normals``: oracle name -> {image: (3,) normal}; the CPU seconds of each image
    (process time, image reading excluded) -> ``<method>.cpu.json`` beside it."""
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
    elif method == "rectsift" or (method in args.variants and base not in ORACLES):
        from rectified_colmap.depth.registry import load_depth_source
        from rectified_colmap.config import DEFAULT_DEPTH_MODEL

        source = load_depth_source(args.depth_model or DEFAULT_DEPTH_MODEL, num_threads=1)
    oracle = method if method in ORACLES else base if base in ORACLES else None
    tmp = h5.with_suffix(".h5.tmp")
    tmp.unlink(missing_ok=True)
    cpu = {}
    with HlocFeatureWriter(tmp) as writer:
        for name in names:
            rgb = read_image(root / name)
            cam = cameras[name]
            depth = None
            t0 = time.process_time()
            if method == "asift":
                gray = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
                feats = asift_features(gray, conf.sift.max_num_features)
                cpu[name] = time.process_time() - t0
                writer.write(name, feats, (cam.width, cam.height))
                logger.info("%s %s: %d keypoints", method, name, len(feats))
                continue
            if source is not None:
                depth = source(rgb, cam, name)
            elif oracle is not None:
                w, h = scaled_size(cam.width, cam.height, conf.normals.work_max_size)
                depth = plane_depth(cam, normals[oracle][name], (h, w), regions[name])
            res = extract_image(rgb, cam, depth, conf, np.random.default_rng(0))
            cpu[name] = time.process_time() - t0
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
    h5.with_suffix(".cpu.json").write_text(json.dumps(cpu, indent=1) + "\n")
    return h5


def extraction_cpu(h5: Path) -> float | None:
    """Mean CPU seconds per image of a features file's extraction (None if not recorded)."""
    path = h5.with_suffix(".cpu.json")
    if not path.exists():
        return None
    cpu = json.loads(path.read_text())
    return float(np.mean(list(cpu.values()))) if cpu else None


def has_key(info: dict, key: str) -> bool:
    """Whether a pair record has ``key`` (each part of a joint ``A+B``)."""
    return all(k in info for k in key.split("+"))


def group_value(info: dict, key: str) -> str:
    """A pair record's value of ``key`` ("-" where it has none); a joint key ``A+B`` joins
    the values of A and B ("2-4 & 2-4x" for ``tilt_bin+scale_bin``), so a class that fails
    only where two properties meet shows as one row."""
    return JOINT.join(str(info.get(k, "-")) for k in key.split("+"))


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--data", type=Path, required=True, help="folder with pairs.json, images/")
    p.add_argument("--output_dir", type=Path, required=True)
    p.add_argument("--methods", nargs="+", default=list(DEFAULT_METHODS), choices=METHODS)
    add_variant_argument(p, "--rect_conf")
    p.add_argument(
        "--depth_model",
        default=None,
        help="registry name, .onnx, or none (no depth: plain SIFT)",
    )
    p.add_argument("--rect_conf", default=None, help="JSON conf overrides (rectsift, oracle)")
    p.add_argument("--max_num_features", type=int, default=None)
    p.add_argument(
        "--focal_factor",
        type=float,
        default=GUESSED_FOCAL_FACTOR,
        help="guessed f = this x max(W, H)",
    )
    p.add_argument(
        "--cameras",
        choices=("guessed", "true"),
        default="guessed",
        help="the cameras given to the methods: guessed (--focal_factor) or the pair "
        "file's true focal lengths x --true_focal_factor",
    )
    p.add_argument("--true_focal_factor", type=float, default=1.0)
    p.add_argument(
        "--group_by",
        nargs="+",
        default=[],
        metavar="KEY",
        help="also summarise per value of these keys of the pair records (e.g. band; "
        "tilt_bin scale_bin rotation both_oblique; A+B: per pair of values of A and B)",
    )
    p.add_argument(
        "--split_key",
        default="split",
        help="key of the pair records whose values (halves) every summary is given for, "
        "when the pair file has it",
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
    if args.cameras == "true":
        cameras = true_cameras(pairs, args.true_focal_factor)
    else:
        cameras = {n: guessed_camera(*sizes[n], args.focal_factor) for n in names}
    out = args.output_dir
    methods = list(args.methods) + list(args.variants)
    bases = set(methods) | {v.get("_base") for v in args.variants.values()}
    normals = {}
    if "oracle" in bases:
        normals["oracle"] = oracle_normals(pairs, cameras)
    if "oracle_true" in bases:
        normals["oracle_true"] = true_normals(pairs)
    regions = image_regions(pairs)
    feats = {
        m: extract_method(m, names, args.data, cameras, normals, regions, args, out)
        for m in methods
    }
    conf = HomographyConf(region_ransac=args.region_ransac)
    records, cpu = [], {}
    for m in methods:  # one method at a time: its matching and RANSAC CPU seconds
        t0 = time.process_time()
        rs = evaluate_homography_pairs(pairs, {m: feats[m]}, conf)
        cpu[m] = {
            "extract": extraction_cpu(feats[m]),
            "match": (time.process_time() - t0) / max(len(rs), 1),
        }
        records += rs
    cases = [(q.name, d, m) for q in pairs for d in ("0->1", "1->0") for m in methods]
    order = {c: k for k, c in enumerate(cases)}  # the records' order of one joint evaluation
    records.sort(key=lambda r: order[(r["pair"], r["direction"], r["method"])])
    info = {q.name: q.info for q in pairs}
    keys = [k for k in [args.split_key, *args.group_by] if any(has_key(q.info, k) for q in pairs)]
    for r in records:
        r.update({k: group_value(info[r["pair"]], k) for k in keys})
    write_records_csv(out / "records.csv", records)
    splits = None
    if any(args.split_key in q.info for q in pairs):
        splits = {q.name: str(q.info.get(args.split_key, "-")) for q in pairs}
    parts = [split_summary_markdown(records, splits, cpu, conf)]
    for key in args.group_by:
        groups = {q.name: group_value(q.info, key) for q in pairs}
        parts.append(split_group_markdown(records, key, groups, splits, conf))
    parts.append(homography_markdown(records, conf))
    table = "\n".join(parts)
    (out / "summary.md").write_text(table)
    print(table)
    return 0


if __name__ == "__main__":
    sys.exit(run_script(main, "eval_homography"))
