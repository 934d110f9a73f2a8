#!/usr/bin/env python
"""Aachen Day-Night (v1.0 or v1.1), or a mini Aachen built from a posed scene, with rectified
SIFT through hloc.

Runs with the installed package and hloc only: ``pip install .`` (or ``pip install
rectified-colmap``), then hloc as docs/hloc.md says (hloc is not on PyPI; it needs torch).
The script says so when hloc is missing or of an API it does not know.

Steps (hloc's public functions, unpatched; docs/hloc.md):
1. features for every database and query image into one hloc feature file: rectified SIFT
   (``--method rectsift``), this tool's plain SIFT (``sift``) or hloc's own ``sift``
   extractor (``hloc-sift``). Database images get the reference model's intrinsics, queries
   those of ``queries/*_time_queries_with_intrinsics.txt`` (through a COLMAP database of
   cameras that rectified_colmap.extract reads), never a guessed focal length;
2. database pairs by covisibility in the reference model (hloc.pairs_from_covisibility),
   all database pairs when the model has no 3D points (``--db_pairs`` to give a list), and
   query pairs from a given retrieval list (e.g. hloc's NetVLAD top-50 files);
3. matching with hloc's NN-ratio (mutual nearest neighbour, Lowe ratio 0.8);
4. the reference model triangulated into the dataset's poses with hloc.triangulation's steps
   (either hloc API generation, told apart by signature), PLUS the pycolmap 4.2 fix: the
   two-view geometries hloc writes have config UNDEFINED, which pycolmap 4.2.1 ignores
   (stock ``triangulation.main`` triangulates 0 points); they are rewritten as CALIBRATED
   (rectified_colmap.eval.hloc_compat.triangulate_with_hloc) before triangulate_points;
5. queries localized with hloc.localize_sfm; the queries it could not localize (it silently
   writes the first retrieved image's pose for them) are reported; the result file
   (``basename qw qx qy qz tx ty tz``) is what the benchmark server (visuallocalization.net)
   takes. With ``ground_truth.txt`` in the dataset (a mini Aachen), errors and recall at
   (0.25 m, 2 deg), (0.5 m, 5 deg), (5 m, 10 deg) are written to ``summary.json``.

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
from types import SimpleNamespace

from rectified_colmap.errors import run_script  # first: loads zlib before pycolmap

logger = logging.getLogger("aachen_hloc")

METHODS = ("rectsift", "sift", "hloc-sift")


def require_hloc():
    """hloc, or SystemExit with what to do (missing, a dependency missing, unknown API)."""
    from rectified_colmap.eval.hloc_compat import HlocError, hloc_generation, import_hloc

    try:
        hloc = import_hloc()
    except HlocError as e:
        raise SystemExit(f"aachen_hloc: {e}") from None
    from hloc import triangulation

    logger.info(
        "hloc %s from %s (API generation: %s)",
        getattr(hloc, "__version__", "?"),
        Path(hloc.__file__).parent,
        hloc_generation(triangulation),
    )
    return hloc


def method_conf(method: str, conf: str | None, max_num_features: int | None) -> dict:
    """The configuration a method runs with: ``--conf`` (a named conf or a JSON file of
    overrides) or the method's named conf, with the budget on top."""
    from rectified_colmap import confs, merge_conf

    spec = conf or method
    base = confs[spec] if spec in confs else json.loads(Path(spec).read_text())
    budget = {"sift": {"max_num_features": max_num_features}} if max_num_features else {}
    return merge_conf(base, budget)


def depth_args(method: str, depth_model: str | None, depth_path: Path | None) -> dict:
    """The depth inputs (rectified_colmap.DepthInputConf keys): plain SIFT runs without
    depth; rectified SIFT with ``depth_path`` and the given network (the embedded default
    when none)."""
    from rectified_colmap.config import DEFAULT_DEPTH_MODEL

    if method == "sift":
        return {"model": None, "path": None}
    return {"model": depth_model or DEFAULT_DEPTH_MODEL, "path": depth_path}


def extract_hloc_sift(images: Path, features: Path, names: list[str], max_num_features):
    """hloc's own DoG extractor (conf ``sift``), with COLMAP's own budget when given
    (DoG's ``max_keypoints`` ranks by zero scores)."""
    from hloc import extract_features as hloc_extract

    hconf = dict(hloc_extract.confs["sift"])
    if max_num_features:
        model = dict(hconf["model"])
        model["options"] = {**model.get("options", {}), "max_num_features": max_num_features}
        hconf["model"] = model
    hloc_extract.main(hconf, images, image_list=names, feature_path=features)


def extract_features(method: str, images: Path, features: Path, cameras: dict, work: Path, args):
    """Features for every image of ``cameras`` (name -> pycolmap.Camera) into ``features``."""
    names = sorted(cameras)
    if method == "hloc-sift":
        return extract_hloc_sift(images, features, names, args.max_num_features)
    from rectified_colmap import extract
    from rectified_colmap.eval.aachen import write_camera_database

    # A database holding every image's camera: extract() uses these intrinsics (the
    # reference model's for database images, the query list's for queries).
    cam_db = work / f"cameras-{method}.db"
    if not cam_db.exists():
        n = write_camera_database(cam_db, cameras)
        logger.info("%d images, %d distinct cameras", len(names), n)
    s = extract(
        images,
        database=cam_db,
        hloc_features=features,
        conf=method_conf(method, args.conf, args.max_num_features),
        reader={"image_list": names},
        depth=depth_args(method, args.depth_model, args.depth_path),
        run={"num_workers": args.num_workers},
    )
    logger.info("features (%s)\n%s", method, s.report())
    if s.failed:
        raise SystemExit(
            f"feature extraction failed for {len(s.failed)} images: "
            f"{dict(list(s.failed.items())[:3])}"
        )


def load_dataset(args) -> SimpleNamespace:
    """The dataset's paths (checked), its reference model and every image's camera."""
    import pycolmap

    from rectified_colmap.eval import aachen as A

    d = SimpleNamespace(dataset=args.dataset)
    d.reference_sfm = args.reference_sfm or args.dataset / "3D-models" / "reference"
    d.loc_pairs = args.loc_pairs or args.dataset / "pairs-query-exhaustive.txt"
    d.images = args.dataset / "images" / "images_upright"
    d.query_glob = args.dataset / "queries" / "*_time_queries_with_intrinsics.txt"
    query_lists = sorted(d.query_glob.parent.glob(d.query_glob.name))
    for what, path in (
        ("images", d.images),
        ("reference model", d.reference_sfm),
        ("localization pairs", d.loc_pairs),
    ):
        if not path.exists():
            raise SystemExit(f"{path}: {what} not found (see --help)")
    if not query_lists:
        raise SystemExit(f"{args.dataset}/queries: no *_time_queries_with_intrinsics.txt")
    d.reference = pycolmap.Reconstruction(str(d.reference_sfm))
    d.q_cams = {}
    for q in query_lists:
        d.q_cams.update(A.read_query_list(q))
    d.db_cams = A.model_cameras(d.reference)
    logger.info("%d database images (reference model), %d queries", len(d.db_cams), len(d.q_cams))
    return d


def database_pairs(d: SimpleNamespace, out: Path, args) -> Path:
    """``--db_pairs``, else covisibility in the reference model, else all pairs."""
    from hloc import pairs_from_covisibility

    from rectified_colmap.eval.pairs import write_pair_list

    if args.db_pairs is not None:
        return args.db_pairs
    if d.reference.num_points3D() > 0:
        pairs = out / f"pairs-db-covis{args.num_covis}.txt"
        pairs_from_covisibility.main(d.reference_sfm, pairs, num_matched=args.num_covis)
        return pairs
    names = sorted(d.db_cams)
    pairs = out / "pairs-db-exhaustive.txt"
    write_pair_list(pairs, [(a, b) for i, a in enumerate(names) for b in names[i + 1 :]])
    logger.info(
        "reference model without 3D points: all %d database pairs",
        len(names) * (len(names) - 1) // 2,
    )
    return pairs


def localization_summary(d: SimpleNamespace, results: Path) -> dict:
    """Result lines, missing and not-localized queries; with ``ground_truth.txt``, the
    errors and the recall (fallback poses count as failures)."""
    from rectified_colmap.eval import aachen as A
    from rectified_colmap.eval.hloc_compat import localize_sfm_fallbacks

    n, missing = A.check_results(results, list(d.q_cams))
    fallbacks = localize_sfm_fallbacks(results)
    if fallbacks:
        logger.warning(
            "%d of %d queries NOT localized: localize_sfm wrote the pose of their "
            "first retrieved image (%s%s)",
            len(fallbacks),
            len(d.q_cams),
            ", ".join(fallbacks[:5]),
            "..." if len(fallbacks) > 5 else "",
        )
    out = {"result_lines": n, "missing": missing, "not_localized": fallbacks}
    gt = d.dataset / "ground_truth.txt"
    if not gt.is_file():
        return out
    errors = A.localization_errors(results, gt)
    keys = [f"{m:g}m,{a:g}deg" for m, a in A.RECALL_THRESHOLDS]
    out["errors_m_deg"] = errors
    out["recall"] = dict(zip(keys, A.recall(errors, A.RECALL_THRESHOLDS, fallbacks)))
    failed = {f.split("/")[-1] for f in fallbacks}
    for name, (dt, dr) in sorted(errors.items()):
        note = " (NOT localized: fallback pose)" if name in failed else ""
        logger.info("%s: %.3f m, %.3f deg%s", name, dt, dr, note)
    logger.info("recall %s", out["recall"])
    return out


def run(args) -> dict:
    """The whole pipeline; returns (and writes to OUTPUTS/summary.json) the summary."""
    require_hloc()
    from hloc import localize_sfm, match_features

    from rectified_colmap.eval.aachen import make_mini_aachen
    from rectified_colmap.eval.hloc_compat import triangulate_with_hloc
    from rectified_colmap.eval.pairs import read_pair_list

    if args.make_mini_from is not None:
        make_mini_aachen(
            args.make_mini_from, args.dataset, max_size=args.max_size, num_queries=args.num_queries
        )
    d = load_dataset(args)
    out = args.outputs
    out.mkdir(parents=True, exist_ok=True)
    features = out / f"feats-{args.method}.h5"  # 1. features
    extract_features(args.method, d.images, features, {**d.db_cams, **d.q_cams}, out, args)
    sfm_pairs = database_pairs(d, out, args)  # 2. pairs
    conf = match_features.confs["NN-ratio"]  # 3. matches
    sfm_matches, loc_matches = out / "matches-db.h5", out / "matches-loc.h5"
    match_features.main(conf, sfm_pairs, features=features, matches=sfm_matches)
    logger.info("%d localization pairs", len(read_pair_list(d.loc_pairs)))
    match_features.main(conf, d.loc_pairs, features=features, matches=loc_matches)
    try:  # 4. reference model with the pycolmap 4.2 fix
        rec = triangulate_with_hloc(
            d.reference, out / "sfm", d.images, sfm_pairs, features, sfm_matches
        )
    except RuntimeError as e:
        raise SystemExit(str(e)) from None
    results = out / f"results-{args.method}.txt"  # 5. localization (all query lists)
    localize_sfm.main(
        rec,
        d.query_glob,
        d.loc_pairs,
        features,
        loc_matches,
        results,
        ransac_thresh=args.ransac_thresh,
        covisibility_clustering=False,
    )
    summary = {
        "method": args.method,
        "features": str(features),
        "results": str(results),
        "database_images": len(d.db_cams),
        "queries": len(d.q_cams),
        "registered_images": rec.num_reg_images(),
        "points3D": rec.num_points3D(),
        **localization_summary(d, results),
    }
    (out / "summary.json").write_text(json.dumps(summary, indent=1))
    return summary


def summary_lines(s: dict) -> list[str]:
    """The summary for the terminal."""
    lines = [
        f"reference model: {s['registered_images']} of {s['database_images']} database "
        f"images, {s['points3D']} 3D points",
        f"queries: {s['queries']}, {s['result_lines']} in {s['results']}, "
        f"{len(s['missing'])} missing, {len(s['not_localized'])} not localized",
    ]
    if "recall" in s:
        worst = max(s["errors_m_deg"].values())
        lines.append(
            "recall "
            + ", ".join(f"({k}) {v:.0%}" for k, v in s["recall"].items())
            + f"; largest error {worst[0]:.3f} m, {worst[1]:.2f} deg"
        )
    return lines


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
    add_mini_arguments(p)
    return p


def add_mini_arguments(p: argparse.ArgumentParser) -> None:
    """--make_mini_from and its options."""
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


def main(argv=None) -> int:
    args = parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="[%(asctime)s %(name)s] %(message)s")
    summary = run(args)
    print("\n".join(summary_lines(summary)))
    return 0


if __name__ == "__main__":
    sys.exit(run_script(main, "aachen_hloc"))
