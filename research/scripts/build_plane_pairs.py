#!/usr/bin/env python
"""Extreme-viewpoint planar pairs with homographies from the real-pool's reconstructions.

For each set of ``--real_pool`` with a COLMAP model (``<set>/colmap_sparse``, SfM results,
not ground truth), writes pairs that scripts/eval_homography.py (and ``rectified-colmap
evaluate-homography``) evaluate as it does evd-dev's:

    OUT/images/<set>/<name>   undistorted photos (pycolmap.undistort_images: pinhole, JPEG q95)
    OUT/pairs.json            evd-dev's format (H image 0 -> image 1, OpenCV pixels) plus the
                              plane's region in image 0 (region0), set, band, angle, the
                              homography's validation error, intrinsics (K0, K1)
    OUT/README.md             provenance, selection rule, counts per set and band

The rule (rectified_colmap_research.evaluation.plane_pairs; nothing here looks at any
method's results):
planes are fitted to each model's 3D points as the training labels are (training.real
.fit_planes, inlier distance PLANE_THRESHOLD x the median depth); a plane and two images
make a candidate when >= --min_points of its points are seen in both, the viewpoint change
at their centroid is 30-85 degrees, the median transfer error of their observations under
the plane-induced homography is <= --max_median_err px, and the region (dilated hulls of
the plane's keypoints in image 0, each holding >= 80 % points that transfer within 3 px)
holds >= --min_points of them and covers >= --min_frac of both images. Per image pair the
plane with the most points in its region is kept (parallel facade layers cannot all be
solved by one estimated homography); per set and band (strong 30-50, extreme 50-85
degrees) pairs are then taken by that count while no image has --max_per_image pairs and no
plane --max_per_plane.

    python scripts/build_plane_pairs.py --real_pool ../shared/data/real-pool --output ../plane-pairs
    python scripts/eval_homography.py --data ../plane-pairs --output_dir OUT \
        --methods sift rectsift --group_by band
"""

from __future__ import annotations

import argparse
import json
import logging
import shutil
import sys
import tempfile
from pathlib import Path

import numpy as np
import pycolmap

from rectified_colmap.conventions import to_opencv_homography, to_opencv_points
from rectified_colmap_research.evaluation.plane_pairs import (
    BANDS,
    band_of,
    best_plane_per_pair,
    pair_candidates,
    select_pairs,
    views_of_model,
)
from rectified_colmap_research.training.real import PLANE_THRESHOLD, fit_planes

logger = logging.getLogger("build_plane_pairs")

SETS = (
    "opensfm-lund",
    "opensfm-berlin",
    "sceaux-castle",
    "sacre-coeur",
    "british-museum",
    "nle-tower",
)
# MANIFEST.md: what the embedded network was trained on, and the sets' terms
TRAINED_ON = {"opensfm-lund", "opensfm-berlin", "sceaux-castle"}
TERMS = {
    "opensfm-lund": "BSD-2-Clause (mapillary/OpenSfM)",
    "opensfm-berlin": "BSD-2-Clause (mapillary/OpenSfM)",
    "sceaux-castle": "unstated (openMVG sample data, (c) 2012 Pierre Moulon)",
    "sacre-coeur": "Apache-2.0 / MIT repositories; photos from YFCC100M (Flickr CC)",
    "british-museum": "CC BY-NC 4.0 (facebookresearch/vggsfm)",
    "nle-tower": "CC BY-NC-SA 4.0 (naver/mast3r)",
}


def set_pairs(set_dir: Path, work: Path, args) -> tuple[list, Path]:
    """Undistort one set's model into ``work`` and select its pairs -> ([(band, PlanePair)],
    folder of the undistorted images)."""
    pycolmap.undistort_images(
        str(work), str(set_dir / "colmap_sparse"), str(set_dir / "images"), jpeg_quality=95
    )
    rec = pycolmap.Reconstruction(str(work / "sparse"))
    views, xyz = views_of_model(rec)
    if len(xyz) == 0:
        return [], work / "images"
    depth = np.concatenate([(xyz[v.points] @ v.R.T + v.t)[:, 2] for v in views])
    planes, labels = fit_planes(xyz, PLANE_THRESHOLD * float(np.median(depth)))
    lo = min(b[0] for b in BANDS.values())
    hi = max(b[1] for b in BANDS.values())
    cands = [
        c
        for i in range(len(views))
        for j in range(i + 1, len(views))
        for c in pair_candidates(
            views[i],
            views[j],
            xyz,
            planes,
            labels,
            min_points=args.min_points,
            angle_range=(lo, hi),
            max_median_err=args.max_median_err,
            min_frac=args.min_frac,
        )
    ]
    best = best_plane_per_pair(cands)  # then its band: an image pair is in one band only
    out = []
    for band in BANDS:
        inband = [c for c in best if band_of(c.angle_deg) == band]
        kept = select_pairs(inband, args.max_per_image, args.max_per_plane)
        logger.info(
            "%s: %s: %d image pairs, %d kept (caps)", set_dir.name, band, len(inband), len(kept)
        )
        out += [(band, c) for c in kept]
    return out, work / "images"


def opencv_K(K: np.ndarray) -> list:
    """COLMAP-convention intrinsics -> the same camera in OpenCV pixels (0-based centres)."""
    K = np.array(K, np.float64)
    K[:2, 2] = to_opencv_points(K[:2, 2])
    return K.tolist()


def pair_record(set_name: str, band: str, c) -> dict:
    """One pairs.json entry (OpenCV pixel convention for H, region0, K0, K1)."""
    stem0, stem1 = Path(c.name0).stem, Path(c.name1).stem
    return {
        "pair": f"{set_name}/{stem0}--{stem1}",
        "im0": f"images/{set_name}/{c.name0}",
        "im1": f"images/{set_name}/{c.name1}",
        "H": to_opencv_homography(c.H).tolist(),
        "convention": "opencv",
        "size0": list(c.size0),
        "size1": list(c.size1),
        "region0": [np.round(to_opencv_points(q), 2).tolist() for q in c.region0],
        "set": set_name,
        "band": band,
        "angle_deg": round(c.angle_deg, 2),
        "tilt0_deg": round(c.tilt0_deg, 2),
        "tilt1_deg": round(c.tilt1_deg, 2),
        "transition_tilt": round(c.tilt_ratio, 3),
        "plane": c.plane,
        "num_points": c.num_points,
        "h_median_err_px": round(c.median_err, 3),
        "h_p90_err_px": round(c.p90_err, 3),
        "region_frac0": round(c.frac0, 4),
        "region_frac1": round(c.frac1, 4),
        "K0": opencv_K(c.K0),
        "K1": opencv_K(c.K1),
        "trained_on": set_name in TRAINED_ON,
        "source": f"real-pool/{set_name}: SfM poses (pycolmap 4.2.1) and a plane fit, "
        "not ground truth",
    }


def counts_table(records: list[dict], sets: list[str]) -> str:
    bands = list(BANDS)
    head = " | ".join(f"{b} ({BANDS[b][0]:g}-{BANDS[b][1]:g} deg)" for b in bands)
    lines = [f"| set | {head} | network trained on it |", "|---|" + "---|" * (len(bands) + 1)]
    for s in sets:
        n = [sum(r["set"] == s and r["band"] == b for r in records) for b in bands]
        lines.append(
            f"| {s} | " + " | ".join(map(str, n)) + f" | {'yes' if s in TRAINED_ON else 'no'} |"
        )
    tot = [sum(r["band"] == b for r in records) for b in bands]
    lines.append("| all | " + " | ".join(map(str, tot)) + " | |")
    return "\n".join(lines)


README = """# plane-pairs: real planar pairs under strong and extreme viewpoint change

Built by `scripts/build_plane_pairs.py` of rectified-colmap (command below) from the
multi-view sets of real-pool (see its MANIFEST.md for the photos' origins). NOT ground
truth: the homographies come from SfM poses and intrinsics (the COLMAP models in
`<set>/colmap_sparse`, SIFT + pycolmap 4.2.1) and planes fitted to the models' 3D points.

    {command}

- `images/<set>/<name>`: the photos undistorted to pinhole views (pycolmap.undistort_images,
  JPEG q95); sizes can differ from the originals.
- `pairs.json`: a list of evd-dev pair records: `pair`, `im0`, `im1`, `H` (3x3 row-major,
  image 0 -> image 1, the plane-induced homography H = K1 (R_rel - t_rel n0^T / d0) K0^-1),
  `convention` ("opencv": 0-based pixel centres, for `H`, `region0`, `K0`, `K1`),
  `size0`/`size1` ([W, H]); and `region0`: polygons in image 0 where H holds (dilated hulls
  of the plane's keypoints seen in both images), `set`, `band` (strong: {strong} degrees,
  extreme: {extreme} degrees), `angle_deg` (angle between the two viewing directions of the
  plane's observed centroid), `tilt0_deg`/`tilt1_deg` (each view's angle from the plane
  normal), `transition_tilt` (anisotropy of H's local affine map, median over the plane's
  points: what a local feature must absorb; evd-dev's pairs have 3.6-46), `plane`,
  `num_points` (plane points seen in both images inside the region),
  `h_median_err_px`/`h_p90_err_px` (transfer error under H of the observations of all the
  plane's points seen in both images, pixels of image 1), `region_frac0/1`, `trained_on`
  (the shipped network was trained on these photos), `source`.

Selection rule (fixed before any evaluation): >= {min_points} plane points seen in both
images, median transfer error <= {max_median_err} px, region covering >= {min_frac} of each
image, one plane per image pair (the one with the most points in its region), at most
{max_per_image} pairs per image and {max_per_plane} per plane in each set and band.

Counts:

{table}

Terms of the photos (MANIFEST.md): {terms}. british-museum and nle-tower are for
development and evaluation only; sceaux-castle, opensfm-lund and opensfm-berlin were
training data of the shipped network (results on them are not held out).
"""


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--real_pool", type=Path, required=True, help="real-pool folder")
    p.add_argument("--output", type=Path, required=True)
    p.add_argument("--sets", nargs="+", default=list(SETS))
    p.add_argument("--min_points", type=int, default=30)
    p.add_argument("--max_median_err", type=float, default=2.0)
    p.add_argument("--min_frac", type=float, default=0.03)
    p.add_argument("--max_per_image", type=int, default=4)
    p.add_argument("--max_per_plane", type=int, default=6)
    args = p.parse_args(argv)
    for s in args.sets:
        model = args.real_pool / s / "colmap_sparse"
        if not model.is_dir():
            print(f"error: no model folder {model}", file=sys.stderr)
            return 2
    out = args.output.resolve()
    if out == args.real_pool.resolve() or args.real_pool.resolve() in out.parents:
        print(f"error: --output {args.output} is inside --real_pool", file=sys.stderr)
        return 2
    logging.basicConfig(level=logging.INFO, format="[%(asctime)s %(name)s] %(message)s")
    records = []
    for s in args.sets:
        with tempfile.TemporaryDirectory() as tmp:
            pairs, image_dir = set_pairs(args.real_pool / s, Path(tmp) / s, args)
            for name in sorted({n for _, c in pairs for n in (c.name0, c.name1)}):
                dst = out / "images" / s / name
                dst.parent.mkdir(parents=True, exist_ok=True)
                shutil.copyfile(image_dir / name, dst)
        records += [pair_record(s, band, c) for band, c in pairs]
    records.sort(key=lambda r: (list(BANDS).index(r["band"]), r["set"], r["angle_deg"]))
    out.mkdir(parents=True, exist_ok=True)
    (out / "pairs.json").write_text(json.dumps(records, indent=1) + "\n")
    table = counts_table(records, args.sets)
    cmd = "python scripts/build_plane_pairs.py " + " ".join(
        f"--{k} {' '.join(map(str, v)) if isinstance(v, list) else v}"
        for k, v in vars(args).items()
        if k not in ("real_pool", "output")
    )
    (out / "README.md").write_text(
        README.format(
            command=cmd + " --real_pool REAL_POOL --output OUT",
            strong="{:g}-{:g}".format(*BANDS["strong"]),
            extreme="{:g}-{:g}".format(*BANDS["extreme"]),
            table=table,
            terms="; ".join(f"{s}: {TERMS.get(s, 'see MANIFEST.md')}" for s in args.sets),
            **{k: getattr(args, k) for k in vars(args)},
        )
    )
    print(table)
    return 0


if __name__ == "__main__":
    sys.exit(main())
