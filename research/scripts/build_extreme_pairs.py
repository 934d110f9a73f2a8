#!/usr/bin/env python
"""Generated extreme-viewpoint planar pairs with exact ground truth, from real photos.

Issue 41, item 1 (docs/evaluation.md, "Generated extreme pairs"). Each pair: one photo of
``--sources`` (a list of roughly frontal facade photos: research/data/extreme_sources.txt,
paths under ``--data_root``) taken as a texture on a plane and seen by two virtual pinhole
cameras, each drawn from a tilt (t = 1 / cos, 1-8), a tilt direction, an in-plane rotation
(exactly 0 / 90 / 180 / 270 degrees or any), a scale (0.25-4 view pixels per texture
pixel), a true focal length and a crop; at least half of the pairs both-oblique (both
views tilted >= 60 degrees, in different directions); pairs with too little overlap are
redrawn (rectified_colmap_research.evaluation.extreme_pairs: the distributions, the
rejection rule, the anti-aliased rendering). Writes:

    OUT/images/<pair>_0.jpg, <pair>_1.jpg   the two views (sensor noise, JPEG)
    OUT/pairs.json   evd-dev's pair format (H image 0 -> image 1, OpenCV pixels, exact),
                     region0 / region1 (the texture in each view), and per pair the source,
                     its split (choose / check: a hash of the source's group), the views'
                     tilts, directions, rotations, scales, true focal lengths and plane
                     normals, and bin labels (tilt_bin, scale_bin, rotation, both_oblique,
                     portrait, viewpoint_bin)
    OUT/README.md    the command, the counts per bin and split, the sources

Deterministic: pair i depends on --seed and i only (a longer set starts with the shorter).

    python research/scripts/build_extreme_pairs.py --output ../outputs/extreme-pairs \
        --num_pairs 120 --seed 0
    python research/scripts/eval_homography.py --data ../outputs/extreme-pairs --output_dir OUT \
        --methods sift rectsift asift oracle \
        --group_by tilt_bin scale_bin rotation both_oblique portrait
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np

from rectified_colmap.conventions import to_opencv_homography, to_opencv_points
from rectified_colmap.errors import run_script
from rectified_colmap_research.evaluation.extreme_pairs import (
    DrawnPair,
    ExtremeConf,
    Source,
    direction_difference_deg,
    draw_pair,
    labels,
    load_texture,
    pair_transition_tilt,
    photo_finish,
    read_sources,
    render_view,
    source_order,
    split_of,
    texture_region,
)

logger = logging.getLogger("build_extreme_pairs")

RESEARCH = Path(__file__).resolve().parents[1]
DATA_ROOT = RESEARCH.parents[1] / "shared" / "data"
"""The project's shared data (../shared/data beside the repository)."""
SOURCES = RESEARCH / "data" / "extreme_sources.txt"
LABEL_KEYS = ("tilt_bin", "scale_bin", "rotation", "both_oblique", "portrait", "viewpoint_bin")


def _r(x, nd=4):
    return (
        [_r(v, nd) for v in x] if isinstance(x, (list, tuple, np.ndarray)) else round(float(x), nd)
    )


def opencv_K(K: np.ndarray) -> list:
    """COLMAP-convention intrinsics -> the same camera in OpenCV pixels."""
    K = np.array(K, np.float64)
    K[:2, 2] = to_opencv_points(K[:2, 2])
    return K.tolist()


def pair_record(name: str, src: Source, d: DrawnPair, tex_size, conf: ExtremeConf, extra) -> dict:
    """One pairs.json entry: OpenCV pixel convention for H, regions, K0/K1 and anchors."""
    p0, p1 = d.v0.params, d.v1.params
    rec = {
        "pair": name,
        "im0": f"images/{name}_0.jpg",
        "im1": f"images/{name}_1.jpg",
        # its sign kept (w > 0 where both cameras see the plane): H[2, 2] may be negative
        "H": to_opencv_homography(d.H / abs(d.H[2, 2])).tolist(),
        "convention": "opencv",
        "size0": list(p0.size),
        "size1": list(p1.size),
        "region0": [_r(to_opencv_points(texture_region(d.v0, tex_size)), 3)],
        "region1": [_r(to_opencv_points(texture_region(d.v1, tex_size)), 3)],
        "source": src.path,
        "group": src.group,
        "split": split_of(src.group),
        "trained_on": src.trained_on,
        "texture_size": list(tex_size),
        "anchor_texture": _r(to_opencv_points(d.anchor), 2),
    }
    for k, (v, p) in enumerate(((d.v0, p0), (d.v1, p1))):
        rec |= {
            f"tilt{k}": _r(p.tilt),
            f"tilt{k}_deg": _r(np.degrees(np.arccos(1 / p.tilt)), 2),
            f"tilt_dir{k}_deg": _r(p.direction_deg, 2),
            f"rotation{k}_deg": _r(p.rotation_deg, 2),
            f"scale{k}": _r(p.scale),
            f"focal{k}": _r(p.focal, 3),
            f"focal_factor{k}": _r(p.focal / (1.2 * max(p.size))),
            f"K{k}": opencv_K(v.K),
            f"normal{k}": _r(v.normal, 6),
            f"anchor{k}": _r(to_opencv_points(np.array(p.anchor_px)), 2),
        }
    rec |= {
        "tilt_dir_diff_deg": _r(direction_difference_deg(p0.direction_deg, p1.direction_deg), 2),
        "rotation_rel_deg": _r((p1.rotation_deg - p0.rotation_deg) % 360, 2),
        "scale_change": _r(max(p0.scale, p1.scale) / min(p0.scale, p1.scale)),
        "viewpoint_deg": _r(d.stats["viewpoint_deg"], 2),
        "transition_tilt": _r(pair_transition_tilt(d), 3),
        **{k: _r(d.stats[k]) for k in ("coverage0", "coverage1", "overlap01", "overlap10")},
        **labels(d, conf),
        **extra,
    }
    return rec


def build(args) -> list[dict]:
    conf = ExtremeConf()
    if args.max_tries:
        conf = replace(conf, max_tries=args.max_tries)
    sources = read_sources(args.sources)
    textures: dict[int, np.ndarray] = {}
    images = args.output / "images"
    images.mkdir(parents=True, exist_ok=True)
    records = []
    for i in range(args.num_pairs):
        rng = np.random.default_rng([args.seed, i])
        both = bool(rng.random() < conf.both_oblique_frac)
        for s in source_order(i, args.seed, len(sources)):
            if s not in textures:
                textures[s] = load_texture(args.data_root, sources[s])
            tex = textures[s]
            tex_size = (tex.shape[1], tex.shape[0])
            d = draw_pair(rng, tex_size, conf, both)
            if d is not None:
                break
            logger.warning("pair %d: no draw kept from %s, next source", i, sources[s].path)
        else:
            raise RuntimeError(f"pair {i}: no source gave a pair in {conf.max_tries} draws")
        name = f"{i:04d}"
        extra = {}
        for k, v in enumerate((d.v0, d.v1)):
            sigma = 0.0 if args.no_noise else float(rng.uniform(*conf.noise_sigma))
            quality = int(rng.integers(conf.jpeg_quality[0], conf.jpeg_quality[1] + 1))
            img = photo_finish(render_view(tex, v.G, v.params.size, conf.fill), rng, sigma)
            path = images / f"{name}_{k}.jpg"
            if not cv2.imwrite(str(path), img, [cv2.IMWRITE_JPEG_QUALITY, quality]):
                raise OSError(f"{path}: cannot write")
            extra |= {f"noise_sigma{k}": round(sigma, 3), f"jpeg_quality{k}": quality}
        rec = pair_record(name, sources[s], d, tex_size, conf, extra)
        rec["draws"] = d.tries
        rec["rejected_draws"] = dict(sorted(d.rejected.items()))
        records.append(rec)
        logger.info(
            "%s %s (%s): tilts %.1f / %.1f, scales %.2f / %.2f, rot %s, %s, %d draws",
            name,
            sources[s].path,
            rec["split"],
            rec["tilt0"],
            rec["tilt1"],
            rec["scale0"],
            rec["scale1"],
            rec["rotation"],
            "both-oblique" if rec["both_oblique"] == "yes" else "one-sided",
            d.tries,
        )
    return records


def counts_table(records: list[dict]) -> str:
    """Pairs per label value and split."""
    lines = ["| key | value | choose | check | all |", "|---|---|---|---|---|"]
    for key in ("split", "trained_on", *LABEL_KEYS):
        for v in sorted({r[key] for r in records}):
            n = [sum(r[key] == v and r["split"] == s for r in records) for s in ("choose", "check")]
            lines.append(f"| {key} | {v} | {n[0]} | {n[1]} | {sum(n)} |")
    return "\n".join(lines)


README = """# extreme-pairs: generated extreme-viewpoint planar pairs with exact ground truth

Built by `research/scripts/build_extreme_pairs.py` of rectified-colmap:

    {command}

Each pair is one real photo (a texture on a plane) seen by two virtual pinhole cameras; `H`
in `pairs.json` is exact by construction (OpenCV pixel convention, image 0 -> image 1),
`region0` / `region1` the texture in each image. The pair keys, the distributions and the
rejection rule: docs/evaluation.md of rectified-colmap, "Generated extreme pairs".
Evaluate with

    python research/scripts/eval_homography.py --data THIS_FOLDER --output_dir OUT \\
        --methods sift rectsift asift oracle \\
        --group_by tilt_bin scale_bin rotation both_oblique portrait

Counts ({n} pairs; split = a hash of the source's group):

{table}

Sources ({nsrc}; under the shared data folder, not copied here; their terms are those of
textures/facades (Pexels), real-pool (its MANIFEST.md) and strecha-dev (research use)):

{sources}
"""


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--output", type=Path, required=True)
    p.add_argument("--num_pairs", type=int, default=120)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--data_root", type=Path, default=DATA_ROOT, help="folder the sources are in")
    p.add_argument("--sources", type=Path, default=SOURCES, help="sources file")
    p.add_argument("--max_tries", type=int, default=None, help="draws per pair and source")
    p.add_argument("--no_noise", action="store_true", help="no sensor noise (JPEG still)")
    args = p.parse_args(argv)
    if args.num_pairs < 1:
        p.error("--num_pairs must be positive")
    if not args.sources.is_file():
        raise OSError(f"{args.sources}: no such sources file")
    if not args.data_root.is_dir():
        raise OSError(f"{args.data_root}: no such data folder")
    logging.basicConfig(level=logging.INFO, format="[%(asctime)s %(name)s] %(message)s")
    records = build(args)
    (args.output / "pairs.json").write_text(json.dumps(records, indent=1) + "\n")
    table = counts_table(records)
    used = sorted({(r["source"], r["group"], r["split"], r["trained_on"]) for r in records})
    src_lines = ["| photo | group | split | network trained on it |", "|---|---|---|---|"]
    src_lines += [f"| {a} | {b} | {c} | {d} |" for a, b, c, d in used]
    cmd = (
        f"python research/scripts/build_extreme_pairs.py --output OUT --num_pairs "
        f"{args.num_pairs} --seed {args.seed}"
        + (f" --max_tries {args.max_tries}" if args.max_tries else "")
        + (" --no_noise" if args.no_noise else "")
        + (f" --sources {args.sources}" if args.sources != SOURCES else "")
    )
    (args.output / "README.md").write_text(
        README.format(
            command=cmd,
            n=len(records),
            table=table,
            nsrc=len(used),
            sources="\n".join(src_lines),
        )
    )
    print(table)
    return 0


if __name__ == "__main__":
    sys.exit(run_script(main, "build_extreme_pairs"))
