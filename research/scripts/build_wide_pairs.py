#!/usr/bin/env python
"""Wide-baseline real pairs with poses from a reconstruction (as MegaDepth / IMC build theirs).

For each set of ``--data`` with a COLMAP model in ``colmap_sparse/`` (the multi-view sets of
../shared/data/real-pool), writes a scene that ``scripts/eval_strecha.py`` evaluates as it
does Strecha's:

    OUT/<set>/images/            undistorted images (pycolmap.undistort_images: pinhole)
    OUT/<set>/sparse/            the undistorted model (PINHOLE cameras, same poses)
    OUT/<set>/pairs_with_gt.txt  pairs with >= --min_covisible common 3D points and a
                                 viewpoint change >= --min_viewpoint_deg (SuperGlue format)
    OUT/<set>/pairs.csv          per pair: common points, viewpoint change, rotation

The viewpoint change of a pair is the median angle between the two viewing rays of its
common points (rectified_colmap.eval.wide_pairs). The poses come from an SfM model built
with SIFT, not from an independent ground truth: pairs that no image links to the rest are
missing, and the poses are as good as the model (sub-pixel reprojection error).

    python scripts/build_wide_pairs.py --data ../shared/data/real-pool --output OUT \
        --sets sacre-coeur british-museum nle-tower sceaux-castle
    # or your own reconstruction:
    python scripts/build_wide_pairs.py --model sparse/0 --image_path images --output OUT --name mine
    python scripts/eval_strecha.py --data OUT --output_dir EVAL --methods sift rectsift
"""

from __future__ import annotations

import argparse
import logging
import shutil
import sys
from pathlib import Path

import numpy as np
import pycolmap

from rectified_colmap.eval.pairs import pairs_from_model, write_pairs_with_gt
from rectified_colmap.eval.wide_pairs import wide_pairs, write_pairs_csv
from rectified_colmap.errors import run_script

logger = logging.getLogger("build_wide_pairs")

# held out from the embedded network's training (rectified_colmap_research.training.real)
DEFAULT_SETS = ("sacre-coeur", "british-museum", "nle-tower")


def build_scene(model: Path, image_dir: Path, dst: Path, args) -> list:
    """Undistort the reconstruction ``model`` of the photos in ``image_dir`` into ``dst``
    (images/, sparse/) and write its pairs (pairs_with_gt.txt, pairs.csv)."""
    if not (dst / "sparse").is_dir():  # built into a temporary folder, renamed when complete
        tmp = dst.with_name(dst.name + ".partial")
        shutil.rmtree(tmp, ignore_errors=True)
        tmp.parent.mkdir(parents=True, exist_ok=True)
        pycolmap.undistort_images(str(tmp), str(model), str(image_dir), jpeg_quality=95)
        shutil.rmtree(tmp / "stereo", ignore_errors=True)  # for dense MVS, not needed here
        for script in tmp.glob("run-colmap-*.sh"):
            script.unlink()
        tmp.rename(dst)
    rec = pycolmap.Reconstruction(str(dst / "sparse"))
    pairs = wide_pairs(
        rec,
        min_covisible=args.min_covisible,
        min_viewpoint_deg=args.min_viewpoint_deg,
        max_viewpoint_deg=args.max_viewpoint_deg,
    )
    gt = {(q.name0, q.name1): q for q in pairs_from_model(rec, prefix="images/")}
    write_pairs_with_gt(  # in the order of pairs.csv: by viewpoint change
        dst / "pairs_with_gt.txt", [gt[f"images/{p.name0}", f"images/{p.name1}"] for p in pairs]
    )
    write_pairs_csv(dst / "pairs.csv", pairs, prefix="images/")
    return pairs


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--data", type=Path, help="folder of sets: <set>/images, <set>/colmap_sparse")
    src.add_argument("--model", type=Path, help="or one COLMAP model (e.g. sparse/0) ...")
    p.add_argument("--image_path", type=Path, help="... of the photos in this folder")
    p.add_argument("--name", default="scene", help="... written to OUTPUT/NAME")
    p.add_argument("--output", type=Path, required=True)
    p.add_argument("--sets", nargs="+", default=list(DEFAULT_SETS), help="with --data")
    p.add_argument("--min_covisible", type=int, default=30)
    p.add_argument("--min_viewpoint_deg", type=float, default=0.0)
    p.add_argument("--max_viewpoint_deg", type=float, default=180.0)
    args = p.parse_args(argv)
    if args.model is not None and args.image_path is None:
        p.error("--model needs --image_path")
    logging.basicConfig(level=logging.INFO, format="[%(asctime)s %(name)s] %(message)s")
    if args.model is not None:
        scenes = {args.name: (args.model, args.image_path)}
    else:
        scenes = {s: (args.data / s / "colmap_sparse", args.data / s / "images") for s in args.sets}
    edges = [0, 10, 20, 30, 40, 60, 90, 180]
    rows = []
    failed = False
    for name, (model, image_dir) in scenes.items():
        try:
            if not model.is_dir():
                raise FileNotFoundError("no such model folder")
            pairs = build_scene(model, image_dir, args.output / name, args)
        except Exception as e:  # one line per scene, the others go on
            logger.error("%s: %s", model, e)
            failed = True
            continue
        hist = np.histogram([q.viewpoint_deg for q in pairs], edges)[0]
        rows.append(f"| {name} | {len(pairs)} | " + " | ".join(map(str, hist)) + " |")
    head = " | ".join(f"{a}-{b}" for a, b in zip(edges[:-1], edges[1:]))
    print(f"| scene | pairs | {head} |\n|---|---|" + "---|" * (len(edges) - 1))
    print("\n".join(rows))
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(run_script(main, "build_wide_pairs"))
