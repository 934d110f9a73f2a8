#!/usr/bin/env python
"""Aachen Day-Night (v1.0 or v1.1), or a mini Aachen built from a posed scene, with rectified
SIFT through hloc.

Steps (hloc's public functions, unpatched; docs/hloc.md):
1. features for every database and query image into one hloc feature file: rectified SIFT
   (``--method rectsift``), this tool's plain SIFT (``sift``) or hloc's own ``sift``
   extractor (``hloc-sift``). Database images get the reference model's intrinsics, queries
   those of ``queries/*_time_queries_with_intrinsics.txt`` (through a COLMAP database of
   cameras that rectified_colmap.extraction reads), never a guessed focal length;
2. database pairs by covisibility in the reference model (hloc.pairs_from_covisibility),
   all database pairs when the model has no 3D points (``--db_pairs`` to give a list), and
   query pairs from a given retrieval list (e.g. hloc's NetVLAD top-50 files);
3. matching with hloc's NN-ratio (mutual nearest neighbour, Lowe ratio 0.8);
4. the reference model triangulated into the dataset's poses with hloc.triangulation's steps
   (either hloc API generation, told apart by signature), PLUS the pycolmap 4.2 fix: the
   two-view geometries hloc writes have config UNDEFINED, which pycolmap 4.2.1 ignores
   (stock ``triangulation.main`` triangulates 0 points); they are rewritten as CALIBRATED
   (rectified_colmap.eval.aachen.set_two_view_config) before triangulate_points;
5. queries localized with hloc.localize_sfm; the queries it could not localize (it silently
   writes the first retrieved image's pose for them) are reported; the result file
   (``basename qw qx qy qz tx ty tz``) is what the benchmark server (visuallocalization.net)
   takes. With ``ground_truth.txt`` in the dataset (a mini Aachen), errors and recall at
   (0.25 m, 2 deg), (0.5 m, 5 deg), (5 m, 10 deg) are written to ``summary.json``.

hloc needs torch (hloc imports it everywhere). hloc is not on PyPI: clone it from its GitHub
repository (cvg/Hierarchical-Localization) and ``pip install -e .``, or use the vendored copy
(docs/hloc.md). The script says so when it is missing or incompatible.

Examples::

    # mini Aachen from Strecha fountain-P11 (4 held-out queries with ground truth)
    python scripts/aachen_hloc.py --make_mini_from path/to/strecha/fountain-P11 \\
        --max_size 1024 --dataset outputs/mini_aachen --outputs outputs/mini_aachen/rectsift

    # Aachen v1.1
    python scripts/aachen_hloc.py --dataset datasets/aachen_v1.1 \\
        --reference_sfm datasets/aachen_v1.1/3D-models/aachen_v_1_1 \\
        --loc_pairs pairs/aachen_v1.1/pairs-query-netvlad50.txt --outputs outputs/aachen
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path

from rectified_colmap.errors import run_script
from rectified_colmap_research.evaluation.methods import depth_model_of, is_plain

logger = logging.getLogger("aachen_hloc")

METHODS = ("rectsift", "sift", "hloc-sift")


def require_hloc():
    """hloc, or SystemExit with what to do (missing, a dependency missing, unknown API)."""
    from rectified_colmap.eval.aachen import HlocError, import_hloc

    try:
        hloc = import_hloc()
    except HlocError as e:
        raise SystemExit(f"aachen_hloc: {e}") from None
    from hloc import triangulation

    from rectified_colmap.eval.aachen import hloc_generation

    logger.info(
        "hloc %s from %s (API generation: %s)",
        getattr(hloc, "__version__", "?"),
        Path(hloc.__file__).parent,
        hloc_generation(triangulation),
    )
    return hloc


def _extract_conf(method: str, conf: str | None, max_num_features: int | None):
    from rectified_colmap.config import ExtractConf, confs

    spec = conf or ("sift" if method == "sift" else "rectsift")
    if spec in confs:
        out = ExtractConf.from_dict(confs[spec])
    else:
        out = ExtractConf.from_dict(json.loads(Path(spec).read_text()))
    if max_num_features:
        out.sift.max_num_features = max_num_features
    return out


def extract_features(
    method: str,
    images: Path,
    features: Path,
    cameras: dict,
    work: Path,
    depth_model: str | None,
    depth_path: Path | None,
    conf: str | None,
    max_num_features: int | None,
    num_workers: int,
) -> None:
    """Features for every image of ``cameras`` (name -> pycolmap.Camera) into ``features``."""
    names = sorted(cameras)
    if method == "hloc-sift":
        from hloc import extract_features as hloc_extract

        hconf = dict(hloc_extract.confs["sift"])
        if max_num_features:  # COLMAP's own budget (DoG's max_keypoints ranks by zero scores)
            model = dict(hconf["model"])
            model["options"] = {**model.get("options", {}), "max_num_features": max_num_features}
            hconf["model"] = model
        hloc_extract.main(hconf, images, image_list=names, feature_path=features)
        return
    from rectified_colmap.eval.aachen import write_camera_database
    from rectified_colmap.extraction import extract

    # A database holding every image's camera: extract() uses these intrinsics (the
    # reference model's for database images, the query list's for queries).
    cam_db = work / f"cameras-{method}.db"
    if not cam_db.exists():
        n = write_camera_database(cam_db, cameras)
        logger.info("%d images, %d distinct cameras", len(names), n)
    depth = {
        "depth_model": depth_model_of(method, depth_model),
        "depth_path": None if is_plain(method) else depth_path,
    }
    s = extract(
        images,
        database=cam_db,
        hloc_features=features,
        image_list=names,
        conf=_extract_conf(method, conf, max_num_features),
        num_workers=num_workers,
        **depth,
    )
    logger.info("features (%s)\n%s", method, s.report())
    if s.failed:
        raise SystemExit(
            f"feature extraction failed for {len(s.failed)} images: "
            f"{dict(list(s.failed.items())[:3])}"
        )


def run(args) -> dict:
    require_hloc()
    import pycolmap
    from hloc import localize_sfm, match_features, pairs_from_covisibility

    from rectified_colmap.eval import aachen as A
    from rectified_colmap.eval.pairs import read_pair_list, write_pair_list

    if args.make_mini_from is not None:
        A.make_mini_aachen(
            args.make_mini_from, args.dataset, max_size=args.max_size, num_queries=args.num_queries
        )
    dataset = args.dataset
    reference_sfm = args.reference_sfm or dataset / "3D-models" / "reference"
    loc_pairs = args.loc_pairs or dataset / "pairs-query-exhaustive.txt"
    images = dataset / "images" / "images_upright"
    query_lists = sorted((dataset / "queries").glob("*_time_queries_with_intrinsics.txt"))
    for what, path in (
        ("images", images),
        ("reference model", reference_sfm),
        ("localization pairs", loc_pairs),
    ):
        if not path.exists():
            raise SystemExit(f"{path}: {what} not found (see --help)")
    if not query_lists:
        raise SystemExit(f"{dataset}/queries: no *_time_queries_with_intrinsics.txt")
    out = args.outputs
    out.mkdir(parents=True, exist_ok=True)
    reference = pycolmap.Reconstruction(str(reference_sfm))
    q_cams = {}
    for q in query_lists:
        q_cams.update(A.read_query_list(q))
    db_cams = A.model_cameras(reference)
    logger.info("%d database images (reference model), %d queries", len(db_cams), len(q_cams))

    # 1. features
    features = out / f"feats-{args.method}.h5"
    extract_features(
        args.method,
        images,
        features,
        {**db_cams, **q_cams},
        out,
        args.depth_model,
        args.depth_path,
        args.conf,
        args.max_num_features,
        args.num_workers,
    )
    # 2. pairs
    if args.db_pairs is not None:
        sfm_pairs = args.db_pairs
    elif reference.num_points3D() > 0:
        sfm_pairs = out / f"pairs-db-covis{args.num_covis}.txt"
        pairs_from_covisibility.main(reference_sfm, sfm_pairs, num_matched=args.num_covis)
    else:
        names = sorted(db_cams)
        sfm_pairs = out / "pairs-db-exhaustive.txt"
        write_pair_list(sfm_pairs, [(a, b) for i, a in enumerate(names) for b in names[i + 1 :]])
        logger.info(
            "reference model without 3D points: all %d database pairs",
            len(names) * (len(names) - 1) // 2,
        )
    # 3. matches
    conf = match_features.confs["NN-ratio"]
    sfm_matches = out / "matches-db.h5"
    loc_matches = out / "matches-loc.h5"
    match_features.main(conf, sfm_pairs, features=features, matches=sfm_matches)
    logger.info("%d localization pairs", len(read_pair_list(loc_pairs)))
    match_features.main(conf, loc_pairs, features=features, matches=loc_matches)
    # 4. reference model with the pycolmap 4.2 fix
    ref = out / "sfm"
    try:
        rec = A.triangulate_with_hloc(reference, ref, images, sfm_pairs, features, sfm_matches)
    except RuntimeError as e:
        raise SystemExit(str(e)) from None
    # 5. localization (all query lists together)
    results = out / f"results-{args.method}.txt"
    localize_sfm.main(
        rec,
        dataset / "queries" / "*_time_queries_with_intrinsics.txt",
        loc_pairs,
        features,
        loc_matches,
        results,
        ransac_thresh=args.ransac_thresh,
        covisibility_clustering=False,
    )
    n, missing = A.check_results(results, list(q_cams))
    fallbacks = A.localize_sfm_fallbacks(results)
    if fallbacks:
        logger.warning(
            "%d of %d queries NOT localized: localize_sfm wrote the pose of their "
            "first retrieved image (%s%s)",
            len(fallbacks),
            len(q_cams),
            ", ".join(fallbacks[:5]),
            "..." if len(fallbacks) > 5 else "",
        )
    summary = {
        "method": args.method,
        "features": str(features),
        "results": str(results),
        "database_images": len(db_cams),
        "queries": len(q_cams),
        "registered_images": rec.num_reg_images(),
        "points3D": rec.num_points3D(),
        "result_lines": n,
        "missing": missing,
        "not_localized": fallbacks,
    }
    gt = dataset / "ground_truth.txt"
    if gt.is_file():
        errors = A.localization_errors(results, gt)
        thresholds = ((0.25, 2.0), (0.5, 5.0), (5.0, 10.0))
        summary["errors_m_deg"] = errors
        summary["recall"] = dict(
            zip(
                [f"{d:g}m,{a:g}deg" for d, a in thresholds], A.recall(errors, thresholds, fallbacks)
            )
        )
        for name, (dt, dr) in sorted(errors.items()):
            logger.info(
                "%s: %.3f m, %.3f deg%s",
                name,
                dt,
                dr,
                " (NOT localized: fallback pose)"
                if name in {f.split("/")[-1] for f in fallbacks}
                else "",
            )
        logger.info("recall %s", summary["recall"])
    (out / "summary.json").write_text(json.dumps(summary, indent=1))
    logger.info(
        "%s: %d queries in the result file, %d missing, %d not localized",
        results,
        n,
        len(missing),
        len(fallbacks),
    )
    return summary


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument(
        "--dataset",
        type=Path,
        required=True,
        help="Aachen-layout folder: images/images_upright, queries/ "
        "(written first with --make_mini_from)",
    )
    p.add_argument("--outputs", type=Path, required=True)
    p.add_argument(
        "--reference_sfm",
        type=Path,
        help="COLMAP model with the database poses (v1.1: 3D-models/aachen_v_1_1; "
        "v1.0: convert the NVM with hloc.colmap_from_nvm first). Default: "
        "DATASET/3D-models/reference (mini Aachen)",
    )
    p.add_argument(
        "--loc_pairs",
        type=Path,
        help="query-database retrieval pairs (e.g. pairs-query-netvlad50.txt). "
        "Default: DATASET/pairs-query-exhaustive.txt (mini Aachen)",
    )
    p.add_argument(
        "--db_pairs",
        type=Path,
        help="database pairs (default: covisibility in the reference model)",
    )
    p.add_argument("--num_covis", type=int, default=20)
    p.add_argument(
        "--method",
        choices=METHODS,
        default="rectsift",
        help="rectsift (this tool), sift (this tool's plain SIFT, no depth), "
        "hloc-sift (hloc's own DoG extractor, conf 'sift')",
    )
    p.add_argument("--depth_model", default=None, help="depth network (registry name/.onnx)")
    p.add_argument("--depth_path", type=Path, help="folder of depth maps instead")
    p.add_argument(
        "--conf",
        default=None,
        help="extraction configuration: a name of rectified_colmap.config.confs or "
        "a JSON file of overrides",
    )
    p.add_argument("--max_num_features", type=int, default=None)
    p.add_argument("--num_workers", type=int, default=4)
    p.add_argument("--ransac_thresh", type=float, default=12.0)
    p.add_argument(
        "--make_mini_from",
        type=Path,
        help="first build a mini Aachen in --dataset from a posed scene "
        "(images/ + sparse/, e.g. a Strecha scene; every third image, from "
        "the second, is a held-out query with ground truth)",
    )
    p.add_argument(
        "--max_size",
        type=int,
        default=None,
        help="with --make_mini_from: downscale images (and cameras) to this size",
    )
    p.add_argument(
        "--num_queries",
        type=int,
        default=None,
        help="with --make_mini_from: keep only the first N held-out queries",
    )
    return p


def main(argv=None) -> int:
    args = parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="[%(asctime)s %(name)s] %(message)s")
    run(args)
    return 0


if __name__ == "__main__":
    sys.exit(run_script(main, "aachen_hloc"))
