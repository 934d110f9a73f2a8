#!/usr/bin/env python
"""Structure from motion with the COLMAP executable: plain COLMAP SIFT beside rectified SIFT.

For each scene of a Strecha-style folder (``<scene>/images``, ``<scene>/sparse`` with the
ground-truth COLMAP text model), and each method:

- ``sift``: ``colmap feature_extractor`` (CPU);
- ``rectsift``: ``rectified-colmap extract`` (default configuration and embedded network,
  another named configuration in ``--methods``; more with ``--variant NAME=JSON|CONF``);

both with the ground-truth intrinsics as one PINHOLE camera and the same budget, then
``colmap exhaustive_matcher`` and ``colmap mapper`` (CPU, one mapper thread: COLMAP 3.8's
multi-threaded bundle adjustment made the point count vary from run to run). Reported per
scene and method: registered images, 3D points, mean track length, mean reprojection
error, verified matches (inlier matches of the two-view geometries COLMAP accepted), image
pairs verified, and the median error of the relative rotations between registered images
against the ground truth (no alignment needed).

    python scripts/eval_colmap_sfm.py --data ../shared/data/strecha-dev --output_dir OUT
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
from pathlib import Path

import numpy as np
import pycolmap

from rectified_colmap.errors import run_script
from rectified_colmap_research.evaluation.methods import add_variant_argument
from rectified_colmap_research.evaluation.colmap_sfm import (
    best_model,
    conf_args,
    match_and_map,
    model_stats,
    parse_methods,
    pinhole_camera_args,
    rectified_command,
    rotation_errors,
    run,
    sift_command,
    verified_matches,
)


def evaluate_scene(scene: Path, method: str, spec: str | None, args, out: Path) -> dict:
    work = out / scene.name / method
    if work.exists():
        shutil.rmtree(work)
    (work / "sparse").mkdir(parents=True)
    db, log = work / "database.db", work / "log.txt"
    gt = pycolmap.Reconstruction()
    gt.read_text(scene / "sparse")
    camera = pinhole_camera_args(gt)
    images = scene / "images"
    if method == "sift":
        cmd = sift_command(db, images, args.max_num_features, camera)
    else:
        conf = conf_args(spec, work)
        cmd = rectified_command(db, images, args.max_num_features, args.num_workers, conf, camera)
    t_extract = run(cmd, log)
    t_match, t_map = match_and_map(db, images, work / "sparse", log)
    matches, pairs = verified_matches(db)
    rec = best_model(work / "sparse")
    row = {
        "scene": scene.name,
        "method": method,
        "images": gt.num_reg_images(),
        **model_stats(rec),
        "verified_matches": matches,
        "verified_pairs": pairs,
        "rot_err_med_deg": float("nan"),
        "extract_s": t_extract,
        "match_s": t_match,
        "map_s": t_map,
    }
    if rec is not None:
        errs = rotation_errors(rec, gt)
        row["rot_err_med_deg"] = float(np.median(errs)) if len(errs) else float("nan")
    return row


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--data", type=Path, required=True, help="folder of scenes")
    p.add_argument("--output_dir", type=Path, required=True)
    p.add_argument("--scenes", nargs="*")
    p.add_argument(
        "--methods",
        nargs="+",
        default=["sift", "rectsift"],
        help="sift (colmap feature_extractor), rectsift (the default configuration) or "
        "another named configuration of rectified-colmap",
    )
    add_variant_argument(p)
    p.add_argument("--max_num_features", type=int, default=8192)
    p.add_argument("--num_workers", type=int, default=1, help="rectified-colmap workers")
    args = p.parse_args(argv)
    if shutil.which("colmap") is None:
        sys.exit("the colmap executable is needed (e.g. apt-get install colmap)")
    try:
        methods = parse_methods(args.methods, args.variant)
    except ValueError as e:
        p.error(str(e))
    scenes = (
        [args.data / s for s in args.scenes]
        if args.scenes
        else sorted(
            d for d in args.data.iterdir() if (d / "images").is_dir() and (d / "sparse").is_dir()
        )
    )
    args.output_dir.mkdir(parents=True, exist_ok=True)
    rows = []
    for scene in scenes:
        for method, spec in methods.items():
            rows.append(evaluate_scene(scene, method, spec, args, args.output_dir))
            r = rows[-1]
            print(
                f"{scene.name} {method}: {r['registered']}/{r['images']} images, "
                f"{r['points']} points, {r['verified_matches']} verified matches",
                file=sys.stderr,
                flush=True,
            )
    (args.output_dir / "sfm.json").write_text(json.dumps(rows, indent=1))
    cols = [
        "scene",
        "method",
        "registered",
        "points",
        "track_length",
        "reproj_px",
        "verified_matches",
        "verified_pairs",
        "rot_err_med_deg",
        "extract_s",
    ]
    print("| " + " | ".join(cols) + " |")
    print("|" + "---|" * len(cols))
    for r in rows:
        cells = [
            f"{r[c]}/{r['images']}"
            if c == "registered"
            else f"{r[c]:.2f}"
            if isinstance(r[c], float)
            else str(r[c])
            for c in cols
        ]
        print("| " + " | ".join(cells) + " |")


if __name__ == "__main__":
    sys.exit(run_script(main, "eval_colmap_sfm"))
