#!/usr/bin/env python
"""Plain vs rectified SIFT on the Strecha scenes: relative pose per pair and localization.

Reproducible benchmark behind docs/evaluation.md. Per scene of ``--data`` (folders with
images/, sparse/ and pairs_with_gt.txt, see the data README; the wide-baseline scenes of
scripts/build_wide_pairs.py have the same layout plus pairs.csv, whose viewpoint changes
add tables by viewpoint change):

1. features per method of the model's images into ``<output_dir>/features/<scene>/<method>.h5``
   with rectified_colmap.extraction.extract, one call per camera (resumable; existing files
   are reused):
   ``sift`` = the pipeline without planes (exactly plain COLMAP SIFT), ``rectsift`` = the
   pipeline with depth from ``--depth_path`` and/or ``--depth_model``;
2. relative pose on every pair of pairs_with_gt.txt (rectified_colmap.eval.relpose), all
   scenes pooled -> records.csv, summary.md, success.png;
3. with ``--localize``: every third image held out as a query, the rest triangulated into
   their known (metric) poses -> localization.md.

``--plain_budget N`` adds plain SIFT with another budget (method ``sift@N``) and a paired
table against it: the control for methods that output more keypoints than plain SIFT with
the same budget (e.g. ``rectsift-fast``).

Example (plain SIFT only)::

    python scripts/eval_strecha.py --data ../shared/data/strecha-dev \
        --output_dir outputs/strecha --methods sift --num_workers 2 --localize
"""

from __future__ import annotations

import argparse
import json
import logging
import shlex
import sys
import time
from pathlib import Path

import numpy as np
import pycolmap

from rectified_colmap.config import SiftConf
from rectified_colmap.eval.config import EvalConf, LocalizeConf
from rectified_colmap.eval.localize import accuracy_table, localize_with_model
from rectified_colmap.eval.pairs import read_pairs_with_gt
from rectified_colmap.eval.relpose import evaluate_pairs
from rectified_colmap.eval.report import paired_markdown, write_outputs
from rectified_colmap.eval.wide_pairs import read_viewpoints
from rectified_colmap.errors import run_script
from rectified_colmap_research.evaluation.methods import (
    add_variant_argument,
    depth_model_of,
    is_plain,
    method_conf,
    parse_variants,
)

logger = logging.getLogger("eval_strecha")

METHODS = ("sift", "rectsift")


def scene_cameras(scene: Path) -> dict[tuple[str, str], list[str]]:
    """(model, 'p1,p2,...') -> the names ("images/...") of the images of the scene's
    model that have this camera (Strecha: one camera; photo collections: one per image)."""
    rec = pycolmap.Reconstruction(str(scene / "sparse"))
    out: dict[tuple[str, str], list[str]] = {}
    for im in sorted(rec.images.values(), key=lambda im: im.name):
        c = rec.cameras[im.camera_id]
        key = (c.model.name, ",".join(f"{p:.10g}" for p in np.round(c.params, 6)))
        out.setdefault(key, []).append(f"images/{im.name}")
    return out


def scene_camera(scene: Path) -> tuple[str, str]:
    """(model, 'p1,p2,...') of the scene's single camera model (all images must share it)."""
    cams = scene_cameras(scene)
    if len(cams) != 1:
        raise SystemExit(f"{scene}/sparse: {len(cams)} different cameras; expected one")
    return next(iter(cams))


def extract_method(scene: Path, method: str, out: Path, args) -> Path:
    from rectified_colmap.extraction import extract

    h5 = out / "features" / scene.name / f"{method}.h5"
    # sift, sift@N (--plain_budget N): exactly plain COLMAP SIFT; the others: --rect_conf,
    # then a variant's overrides, then the budget (methods.method_conf)
    overrides = json.loads(args.rect_conf) if args.rect_conf else {}
    conf = method_conf(method, args.variants, overrides, args.max_num_features)
    depth = {"model": depth_model_of(method, args.depth_model) or "none"}
    if not is_plain(method):
        depth["path"] = args.depth_path
    t = time.perf_counter()
    groups = scene_cameras(scene)
    for k, ((model, params), names) in enumerate(groups.items(), 1):  # one call per camera
        summary = extract(
            scene,
            hloc_features=h5,
            conf=conf,
            reader={"image_list": names, "camera_model": model, "camera_params": params},
            depth=depth,
            run={"num_workers": args.num_workers, "progress": not args.no_progress},
        )
        if not summary.ok:
            raise SystemExit(f"{scene.name}/{method}: extraction failed\n{summary.report()}")
        where = f" (camera {k} of {len(groups)})" if len(groups) > 1 else ""
        logger.info("%s/%s%s: %s", scene.name, method, where, summary.report().splitlines()[1])
    logger.info("%s/%s: %.1f s", scene.name, method, time.perf_counter() - t)
    return h5


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--data", type=Path, required=True, help="strecha-dev folder")
    p.add_argument("--output_dir", type=Path, required=True)
    p.add_argument("--methods", nargs="+", default=list(METHODS), choices=METHODS)
    p.add_argument("--scenes", nargs="*", help="scene names (default: all)")
    p.add_argument("--depth_model", help="depth network for rectsift (registry name or .onnx)")
    p.add_argument("--depth_path", type=Path, help="folder of depth maps for rectsift")
    p.add_argument(
        "--max_num_features",
        type=int,
        default=None,
        help="SIFT budget per image for both methods (default: the configuration's, "
        f"{SiftConf().max_num_features})",
    )
    p.add_argument(
        "--rect_conf",
        default=None,
        help="JSON overrides of the extraction conf for rectsift, e.g. "
        '\'{"rectify": {"tilt_steps": 0}}\'',
    )
    add_variant_argument(p, "--rect_conf")
    p.add_argument(
        "--plain_budget",
        type=int,
        action="append",
        default=[],
        metavar="N",
        help="also plain SIFT with budget N (method sift@N), with a paired table against it; "
        "repeatable",
    )
    p.add_argument("--bin_deg", type=float, default=10.0)
    p.add_argument("--ransac_max_error", type=float, default=None)
    p.add_argument(
        "--ransac_runs",
        type=int,
        default=1,
        help="RANSAC runs per pair (seeds 0, 1, ...; odd): median pose errors, majority "
        "success, and the mean success over runs",
    )
    p.add_argument("--num_workers", type=int, default=2)
    p.add_argument("--localize", action="store_true", help="also run the localization")
    p.add_argument("--no_plot", action="store_true")
    p.add_argument("--no_progress", action="store_true")
    args = p.parse_args(argv)
    try:
        args.variants = parse_variants(args.variant, taken=METHODS)
    except ValueError as e:
        p.error(str(e))
    logging.basicConfig(level=logging.INFO, format="[%(asctime)s %(name)s] %(message)s")
    if not args.data.is_dir():
        raise SystemExit(f"--data {args.data}: not a directory")
    scenes = sorted(d for d in args.data.iterdir() if (d / "pairs_with_gt.txt").is_file())
    if args.scenes:
        scenes = [s for s in scenes if s.name in args.scenes]
    if not scenes:
        raise SystemExit(f"{args.data}: no scene with pairs_with_gt.txt")
    out = args.output_dir
    out.mkdir(parents=True, exist_ok=True)
    try:
        conf = EvalConf(bin_deg=args.bin_deg, ransac_runs=args.ransac_runs)
    except ValueError as e:
        raise SystemExit(f"--ransac_runs: {e}") from None
    if args.ransac_max_error is not None:
        conf.ransac_max_error = args.ransac_max_error

    records, loc_rows = [], {}
    for scene in scenes:
        names = list(args.methods) + [f"sift@{n}" for n in args.plain_budget] + list(args.variants)
        feats = {m: extract_method(scene, m, out, args) for m in names}
        pairs = read_pairs_with_gt(scene / "pairs_with_gt.txt")
        recs = evaluate_pairs(pairs, feats, conf, args.num_workers, progress=not args.no_progress)
        # wide-baseline scenes (scripts/build_wide_pairs.py) know each pair's viewpoint change
        views = read_viewpoints(scene / "pairs.csv") if (scene / "pairs.csv").is_file() else {}
        for r in recs:
            r["viewpoint"] = views.get((r["name0"], r["name1"]))
            r["name0"], r["name1"] = f"{scene.name}/{r['name0']}", f"{scene.name}/{r['name1']}"
        records += recs
        if args.localize:
            model = pycolmap.Reconstruction(str(scene / "sparse"))
            for m, h5 in feats.items():
                res, acc = localize_with_model(
                    model,
                    h5,
                    out / "localize" / scene.name / m,
                    holdout_every=3,
                    name_prefix="images/",
                    conf=LocalizeConf(),
                    image_dir=scene,
                )
                loc_rows[f"{scene.name} {m}"] = (acc, len(res))
    title = f"{args.data.name} ({', '.join(s.name for s in scenes)})"
    table = write_outputs(records, out, conf, not args.no_plot, title)
    for n in args.plain_budget:
        table += f"\nPaired with sift@{n} (same pairs; p: exact two-sided)\n\n"
        table += paired_markdown(records, f"sift@{n}", conf.bin_deg)
    text = [
        f"# Relative pose on {args.data.name}",
        "",
        "Command:",
        "",
        "    python " + " ".join(shlex.quote(a) for a in [sys.argv[0]] + (argv or sys.argv[1:])),
        "",
        "## Relative pose",
        "",
        table,
    ]
    if loc_rows:
        loc = accuracy_table(
            {k: v[0] for k, v in loc_rows.items()},
            LocalizeConf().thresholds,
            {k: v[1] for k, v in loc_rows.items()},
        )
        (out / "localization.md").write_text(loc)
        text += ["## Localization (every third image a query)", "", loc]
    (out / "results.md").write_text("\n".join(text))
    print("\n".join(text))
    return 0


if __name__ == "__main__":
    sys.exit(run_script(main, "eval_strecha"))
