#!/usr/bin/env python
"""Structure from motion with rectified SIFT through hloc, on a folder of images.

Runs with the installed package and hloc only: ``pip install .`` (or ``pip install
rectified-colmap``), then hloc as docs/hloc.md says (hloc is not on PyPI; it needs torch).

Steps (hloc's public functions, unpatched; docs/hloc.md):
1. features: ``rectified_colmap.extract`` into an hloc feature file (``--method rectsift``:
   the default configuration and the embedded depth network; ``sift``: plain COLMAP SIFT
   through the same code, no depth). Images without EXIF get COLMAP's guessed focal length
   here and in hloc's image import alike;
2. pairs: every pair of images (hloc.pairs_from_exhaustive);
3. matches: hloc.match_features with NN-ratio (mutual nearest neighbour, Lowe ratio 0.8);
4. hloc.reconstruction.main: image import, hloc's geometric verification
   (pycolmap.verify_matches: two-view geometries WITH a configuration, so the pycolmap 4.2
   trap of hloc's triangulation, UNDEFINED geometries that the mapper skips, does not
   apply; the summary counts them all the same) and COLMAP's incremental mapper.

Writes OUTPUTS/feats-METHOD.h5, pairs.txt, matches-METHOD.h5, the model (sfm-METHOD/, the
largest one hloc found) and summary.json, and prints the summary: registered images, 3D
points, mean track length and reprojection error, verified pairs and inliers. A second run
reuses the features and matches already there.

Example (hloc's 10 Sacre Coeur photos, in hloc's repository)::

    python scripts/hloc_sfm.py --images Hierarchical-Localization/datasets/sacre_coeur/mapping \\
        --outputs outputs/sacre_coeur
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path

from rectified_colmap.errors import run_script  # first: loads zlib before pycolmap

logger = logging.getLogger("hloc_sfm")

METHODS = ("rectsift", "sift")
CAMERA_MODES = ("auto", "single", "per_folder", "per_image")


def require_hloc():
    """hloc, or SystemExit with what to do (missing, a dependency missing, unknown API)."""
    from rectified_colmap.eval.hloc_compat import HlocError, import_hloc

    try:
        return import_hloc(("pairs_from_exhaustive", "match_features", "reconstruction"))
    except HlocError as e:
        raise SystemExit(f"hloc_sfm: {e}") from None


def method_conf(method: str, conf: str | None, max_num_features: int | None) -> dict:
    """The configuration a method runs with: ``--conf`` (a named conf or a JSON file of
    overrides) or the method's named conf, with the budget on top."""
    from rectified_colmap import confs, merge_conf

    spec = conf or method
    base = confs[spec] if spec in confs else json.loads(Path(spec).read_text())
    budget = {"sift": {"max_num_features": max_num_features}} if max_num_features else {}
    return merge_conf(base, budget)


def extract_features(images: Path, features: Path, args) -> list[str]:
    """Features of every image of the folder into ``features``; returns their names."""
    from rectified_colmap import extract
    from rectified_colmap.config import DEFAULT_DEPTH_MODEL
    from rectified_colmap.io.hloc_h5 import list_names

    plain = args.method == "sift"
    summary = extract(
        images,
        hloc_features=features,
        conf=method_conf(args.method, args.conf, args.max_num_features),
        reader={
            "camera_model": args.camera_model,
            "camera_params": args.camera_params,
            "single_camera": args.camera_mode == "single",
            "single_camera_per_folder": args.camera_mode == "per_folder",
        },
        depth={
            "model": None if plain else (args.depth_model or DEFAULT_DEPTH_MODEL),
            "path": None if plain else args.depth_path,
        },
        run={"num_workers": args.num_workers},
    )
    logger.info("features (%s)\n%s", args.method, summary.report())
    if summary.failed:
        raise SystemExit(
            f"feature extraction failed for {len(summary.failed)} images: "
            f"{dict(list(summary.failed.items())[:3])}"
        )
    return sorted(list_names(features))


def image_options(args) -> dict:
    """The cameras of hloc's image import: those the features were extracted with."""
    out = {"camera_model": args.camera_model} if args.camera_model else {}
    if args.camera_params:
        out["camera_params"] = args.camera_params
    return out


def model_summary(rec, sfm_dir: Path, num_images: int) -> dict:
    """Registered images, points, track length and reprojection error of the model (none:
    zeros), and the two-view geometries of hloc's database."""
    from rectified_colmap.eval.hloc_compat import two_view_counts

    counts = two_view_counts(sfm_dir / "database.db")
    if counts["undefined_pairs"]:
        logger.warning(
            "%d two-view geometries with config UNDEFINED: pycolmap 4.2's mapper skips "
            "them (docs/hloc.md, pitfall 1)",
            counts["undefined_pairs"],
        )
    return {
        "images": num_images,
        "registered_images": rec.num_reg_images() if rec else 0,
        "points3D": rec.num_points3D() if rec else 0,
        "mean_track_length": float(rec.compute_mean_track_length()) if rec else 0.0,
        "mean_reprojection_error_px": float(rec.compute_mean_reprojection_error()) if rec else 0.0,
        **counts,
    }


def run(args) -> dict:
    """The whole pipeline; returns (and writes to OUTPUTS/summary.json) the summary."""
    require_hloc()
    import pycolmap
    from hloc import match_features, pairs_from_exhaustive, reconstruction

    if not args.images.is_dir():
        raise SystemExit(f"{args.images}: image folder not found (see --help)")
    out = args.outputs
    out.mkdir(parents=True, exist_ok=True)
    features = out / f"feats-{args.method}.h5"
    names = extract_features(args.images, features, args)  # 1. features
    pairs = out / "pairs.txt"  # 2. all pairs
    pairs_from_exhaustive.main(pairs, image_list=names)
    matches = out / f"matches-{args.method}.h5"  # 3. matches
    match_features.main(match_features.confs["NN-ratio"], pairs, features=features, matches=matches)
    mapper = {}
    if args.seed is not None:  # repeatable: seeded, one mapper thread
        pycolmap.set_random_seed(args.seed)
        mapper["num_threads"] = 1
    sfm_dir = out / f"sfm-{args.method}"  # 4. verification and mapping
    rec = reconstruction.main(
        sfm_dir,
        args.images,
        pairs,
        features,
        matches,
        camera_mode=getattr(pycolmap.CameraMode, args.camera_mode.upper()),
        image_list=names,
        image_options=image_options(args),
        mapper_options=mapper,
    )
    summary = {
        "method": args.method,
        "features": str(features),
        "model": str(sfm_dir) if rec else None,
        **model_summary(rec, sfm_dir, len(names)),
    }
    (out / "summary.json").write_text(json.dumps(summary, indent=1))
    return summary


def summary_lines(s: dict) -> list[str]:
    """The summary for the terminal."""
    if s["model"] is None:
        return [f"no model: COLMAP's mapper found no initial pair among {s['images']} images"]
    return [
        f"{s['model']}: {s['registered_images']} of {s['images']} images registered, "
        f"{s['points3D']} 3D points",
        f"mean track length {s['mean_track_length']:.2f}, mean reprojection error "
        f"{s['mean_reprojection_error_px']:.2f} px",
        f"{s['verified_pairs']} verified pairs, {s['verified_inliers']} inlier matches",
    ]


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("--images", type=Path, required=True, help="folder of images")
    p.add_argument("--outputs", type=Path, required=True, help="output folder")
    p.add_argument(
        "--method",
        choices=METHODS,
        default="rectsift",
        help="rectsift (default) or sift (this tool's plain COLMAP SIFT, no depth)",
    )
    p.add_argument(
        "--conf",
        default=None,
        help="extraction configuration instead of the method's: a name of "
        "rectified_colmap.confs or a JSON file of overrides",
    )
    p.add_argument("--max_num_features", type=int, default=None, help="plain SIFT's budget (8192)")
    p.add_argument("--depth_model", default=None, help="depth network (registry name/.onnx)")
    p.add_argument("--depth_path", type=Path, help="folder of depth maps instead")
    p.add_argument("--num_workers", type=int, default=1, help="extraction processes")
    p.add_argument("--camera_model", default=None, help="COLMAP camera model (default: COLMAP's)")
    p.add_argument(
        "--camera_params",
        default=None,
        help="intrinsics 'p1,p2,...' in COLMAP's order (default: EXIF, else COLMAP's guess)",
    )
    p.add_argument(
        "--camera_mode",
        choices=CAMERA_MODES,
        default="auto",
        help="cameras as COLMAP's image import (auto: one per image size and EXIF)",
    )
    p.add_argument(
        "--seed", type=int, default=None, help="seed the mapper (and run it on one thread)"
    )
    return p


def main(argv=None) -> int:
    args = parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="[%(asctime)s %(name)s] %(message)s")
    summary = run(args)
    print("\n".join(summary_lines(summary)))
    return 0 if summary["model"] else 1


if __name__ == "__main__":
    sys.exit(run_script(main, "hloc_sfm"))
