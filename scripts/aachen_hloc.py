#!/usr/bin/env python
"""Aachen Day-Night (v1.0 or v1.1) with rectified SIFT through hloc.

Steps (hloc's public functions, unchanged; see docs/evaluation.md):
1. rectified SIFT for every database and query image into one hloc feature file
   (rectified_colmap.extract.extract; names relative to images_upright/);
2. database pairs by covisibility in the reference model (hloc.pairs_from_covisibility),
   query pairs from a given retrieval list (e.g. hloc's precomputed NetVLAD top-50);
3. matching with hloc's NN-ratio (mutual nearest neighbour, Lowe ratio 0.8);
4. reference model triangulated into the dataset's poses with hloc.triangulation's steps,
   PLUS the pycolmap 4.2 fix: the two-view geometries hloc writes have config UNDEFINED,
   which pycolmap 4.2.1 ignores (0 points); they are rewritten as CALIBRATED
   (rectified_colmap.eval.aachen.set_two_view_config) before triangulate_points;
5. night and day queries localized with hloc.localize_sfm; the result file
   (``basename qw qx qy qz tx ty tz``) is what the benchmark server (visuallocalization.net)
   takes.

hloc is not on PyPI: clone it from its GitHub repository (cvg/Hierarchical-Localization) and
``pip install -e .`` it (its torch-free modules are enough here).

Example::

    python scripts/aachen_hloc.py --dataset datasets/aachen_v1.1 \
        --reference_sfm datasets/aachen_v1.1/3D-models/aachen_v_1_1 \
        --loc_pairs pairs/aachen_v1.1/pairs-query-netvlad50.txt --outputs outputs/aachen
"""

from __future__ import annotations

import argparse
import inspect
import logging
import sys
from pathlib import Path

logger = logging.getLogger("aachen_hloc")

MIN_HLOC = (1, 4)


def require_hloc():
    try:
        import hloc
    except ImportError:
        raise SystemExit(
            "this script needs hloc, which is not on PyPI: git clone the GitHub repository "
            "cvg/Hierarchical-Localization and run `pip install -e .` in it") from None
    version = getattr(hloc, "__version__", "0")
    try:
        parts = tuple(int(v) for v in version.split(".")[:2])
    except ValueError:
        parts = (0, 0)
    if parts < MIN_HLOC:
        logger.warning("hloc %s is older than %s: the function signatures may differ",
                       version, ".".join(map(str, MIN_HLOC)))
    logger.info("hloc %s from %s", version, Path(hloc.__file__).parent)
    return hloc


def call_with(fn, **available):
    """Call an hloc function with the arguments its signature names (hloc versions differ
    in which of them they take)."""
    params = inspect.signature(fn).parameters
    kwargs = {k: v for k, v in available.items() if k in params}
    missing = [k for k, p in params.items() if p.default is p.empty and k not in kwargs
               and p.kind not in (p.VAR_POSITIONAL, p.VAR_KEYWORD)]
    if missing:
        raise SystemExit(f"hloc {fn.__module__}.{fn.__name__} needs {missing}: unsupported "
                         "hloc version")
    return fn(**kwargs)


def triangulate(ref_sfm_in: Path, sfm_dir: Path, image_dir: Path, pairs: Path, features: Path,
                matches: Path):
    """hloc.triangulation.main's steps with the UNDEFINED-config fix before triangulating."""
    import pycolmap
    from hloc import triangulation

    from rectified_colmap.eval.aachen import set_two_view_config

    sfm_dir.mkdir(parents=True, exist_ok=True)
    database = sfm_dir / "database.db"
    reference = pycolmap.Reconstruction(str(ref_sfm_in))
    image_ids = triangulation.create_db_from_model(reference, database)
    triangulation.import_features(image_ids, database, features)
    call_with(triangulation.import_matches, image_ids=image_ids, database_path=database,
              pairs_path=pairs, matches_path=matches, min_match_score=None,
              skip_geometric_verification=False)
    call_with(triangulation.geometric_verification, image_ids=image_ids, reference=reference,
              database_path=database, features_path=features, pairs_path=pairs,
              matches_path=matches)
    n = set_two_view_config(database, "CALIBRATED")
    logger.info("pycolmap 4.2 fix: %d verified geometries given config CALIBRATED", n)
    rec = call_with(triangulation.run_triangulation, model_path=sfm_dir,
                    database_path=database, image_dir=image_dir, reference_model=reference)
    logger.info("reference model:\n%s", rec.summary())
    if rec.num_points3D() == 0:
        raise SystemExit("0 points triangulated: check the pairs, matches and geometries")
    return rec


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--dataset", type=Path, required=True,
                   help="Aachen folder with images/images_upright and queries/")
    p.add_argument("--reference_sfm", type=Path, required=True,
                   help="COLMAP model with the database poses (v1.1: 3D-models/aachen_v_1_1; "
                        "v1.0: convert the NVM with hloc.colmap_from_nvm first)")
    p.add_argument("--loc_pairs", type=Path, required=True,
                   help="query-database retrieval pairs (e.g. pairs-query-netvlad50.txt)")
    p.add_argument("--outputs", type=Path, required=True)
    p.add_argument("--num_covis", type=int, default=20)
    p.add_argument("--depth_model", default=None, help="depth network (registry name/.onnx)")
    p.add_argument("--depth_path", type=Path, help="folder of depth maps instead")
    p.add_argument("--num_workers", type=int, default=4)
    p.add_argument("--ransac_thresh", type=float, default=12.0)
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="[%(asctime)s %(name)s] %(message)s")
    require_hloc()
    from hloc import localize_sfm, match_features, pairs_from_covisibility

    from rectified_colmap.eval.aachen import check_results, group_by_camera, read_query_list
    from rectified_colmap.eval.pairs import read_pair_list
    from rectified_colmap.extract import DEFAULT_DEPTH_MODEL, extract, list_images

    images = args.dataset / "images" / "images_upright"
    queries = sorted((args.dataset / "queries").glob("*_time_queries_with_intrinsics.txt"))
    if not images.is_dir() or not queries:
        raise SystemExit(f"{args.dataset}: expected images/images_upright and "
                         "queries/*_time_queries_with_intrinsics.txt")
    out = args.outputs
    out.mkdir(parents=True, exist_ok=True)
    features = out / "feats-rectsift.h5"
    db_names = [n for n in list_images(images) if n.startswith("db/")]
    q_cams = {}
    for q in queries:
        q_cams.update(read_query_list(q))
    # 1. features: database images (SIMPLE_RADIAL from EXIF as COLMAP), queries with the
    #    given intrinsics (one extract call per query camera).
    depth = dict(depth_model=args.depth_model or DEFAULT_DEPTH_MODEL, depth_path=args.depth_path)
    s = extract(images, hloc_features=features, image_list=db_names,
                num_workers=args.num_workers, **depth)
    logger.info("database features\n%s", s.report())
    for model, params, names in group_by_camera(q_cams):
        s = extract(images, hloc_features=features, image_list=names, camera_model=model,
                    camera_params=list(params), num_workers=args.num_workers, **depth)
        logger.info("queries %s %s\n%s", model, params, s.report())
    # 2-3. pairs and matches
    sfm_pairs = out / f"pairs-db-covis{args.num_covis}.txt"
    pairs_from_covisibility.main(args.reference_sfm, sfm_pairs, num_matched=args.num_covis)
    conf = match_features.confs["NN-ratio"]
    sfm_matches = out / "matches-db.h5"
    loc_matches = out / "matches-loc.h5"
    match_features.main(conf, sfm_pairs, features=features, matches=sfm_matches)
    n_loc = len(read_pair_list(args.loc_pairs))
    logger.info("%d localization pairs", n_loc)
    match_features.main(conf, args.loc_pairs, features=features, matches=loc_matches)
    # 4. reference model with the pycolmap 4.2 fix
    ref = out / "sfm_rectsift"
    triangulate(args.reference_sfm, ref, images, sfm_pairs, features, sfm_matches)
    # 5. localization (day and night query lists together)
    results = out / "Aachen_hloc_rectsift_NN-ratio.txt"
    localize_sfm.main(ref, args.dataset / "queries" / "*_time_queries_with_intrinsics.txt",
                      args.loc_pairs, features, loc_matches, results,
                      ransac_thresh=args.ransac_thresh, covisibility_clustering=False)
    n, missing = check_results(results, list(q_cams))
    logger.info("%s: %d queries localized, %d missing; submit this file to the benchmark",
                results, n, len(missing))
    return 0


if __name__ == "__main__":
    sys.exit(main())
