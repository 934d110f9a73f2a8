#!/usr/bin/env python
"""Structure from motion through hloc: plain SIFT beside rectified SIFT, over mapper seeds.

For a folder of images and each method, the same hloc calls as a user's pipeline:
``rectified_colmap.extraction`` into an hloc feature file (``sift``: exactly plain COLMAP SIFT
through the same code; ``rectsift``: the default configuration and embedded network;
``--variant NAME=JSON`` or ``--variant NAME=CONF``: more), ``pairs_from_exhaustive``,
``match_features`` with NN-ratio, then ``reconstruction.main`` once per ``--seeds`` value
(``pycolmap.set_random_seed``, one mapper thread). On hloc's 10 Sacre Coeur photos the
3D-point count varies by ~6 (standard deviation) from seed to seed for the same matches, so
one run cannot tell two feature sets apart that differ by less: compare the means and the
per-seed differences (docs/evaluation.md).

    python scripts/eval_hloc_sfm.py --output_dir OUT --variant fast=rectsift-fast
    python scripts/eval_hloc_sfm.py --images DIR --output_dir OUT --seeds 0 1 2

Writes ``OUT/<method>/`` (features, pairs, matches, one model per seed), ``OUT/hloc_sfm.json``
and prints a Markdown table. Feature and match files already there are reused.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path

import numpy as np

from rectified_colmap.errors import run_script
from rectified_colmap_research.evaluation.methods import (
    add_variant_argument,
    depth_model_of,
    method_conf,
    parse_variants,
)

ROOT = Path(__file__).resolve().parents[2]  # the repository
SACRE_COEUR = ROOT.parent / "shared" / "vendor" / "hloc" / "datasets" / "sacre_coeur" / "mapping"
logger = logging.getLogger("eval_hloc_sfm")


def run_method(images: Path, out: Path, method: str, conf: dict, args) -> list[dict]:
    """Features, exhaustive pairs, NN-ratio matches and one reconstruction per seed."""
    import pycolmap
    from hloc import match_features, pairs_from_exhaustive, reconstruction

    from rectified_colmap.extraction import extract

    out.mkdir(parents=True, exist_ok=True)
    feats, pairs, matches = out / "features.h5", out / "pairs.txt", out / "matches.h5"
    summary = extract(
        images,
        hloc_features=feats,
        conf=conf,
        depth={"model": depth_model_of(method)},
        run={"progress": False},
    )
    if not summary.ok:
        raise SystemExit(f"{method}: extraction failed\n{summary.report()}")
    pairs_from_exhaustive.main(pairs, features=feats)
    if not matches.exists():
        match_features.main(
            match_features.confs["NN-ratio"], pairs, features=feats, matches=matches
        )
    rows = []
    for seed in args.seeds:
        pycolmap.set_random_seed(seed)
        rec = reconstruction.main(
            out / f"sfm-{seed}", images, pairs, feats, matches, mapper_options={"num_threads": 1}
        )
        rows.append(
            {
                "method": method,
                "seed": seed,
                "registered": rec.num_reg_images() if rec else 0,
                "points": rec.num_points3D() if rec else 0,
                "track_length": float(rec.compute_mean_track_length()) if rec else 0.0,
            }
        )
        r = rows[-1]
        logger.info("%s seed %d: %d images, %d points", method, seed, r["registered"], r["points"])
    return rows


def markdown(rows: list[dict], baseline: str = "sift") -> str:
    """Per method: images, points per seed, mean and standard deviation; against
    ``baseline``: the mean per-seed difference and on how many seeds it is higher / lower."""
    methods = list(dict.fromkeys(r["method"] for r in rows))
    pts = {m: {r["seed"]: r["points"] for r in rows if r["method"] == m} for m in methods}
    reg = {m: [r["registered"] for r in rows if r["method"] == m] for m in methods}
    lines = [
        "| method | registered (min-max) | 3D points per seed | mean | std | vs "
        + baseline
        + ": mean difference | seeds higher / lower |",
        "|---|---|---|---|---|---|---|",
    ]
    for m in methods:
        v = np.array(list(pts[m].values()), float)
        cells = [
            m,
            f"{min(reg[m])}-{max(reg[m])}",
            " ".join(str(int(x)) for x in v),
            f"{v.mean():.1f}",
            f"{v.std(ddof=1):.1f}" if len(v) > 1 else "-",
        ]
        if m != baseline and baseline in pts:
            common = sorted(set(pts[m]) & set(pts[baseline]))
            d = np.array([pts[m][s] - pts[baseline][s] for s in common], float)
            base = np.mean([pts[baseline][s] for s in common])
            mean_d = f"{d.mean():+.1f} ({d.mean() / base:+.1%})"
            cells += [mean_d, f"{int((d > 0).sum())} / {int((d < 0).sum())}"]
        else:
            cells += ["-", "-"]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--images", type=Path, default=SACRE_COEUR, help="default: hloc's Sacre Coeur")
    p.add_argument("--output_dir", type=Path, required=True)
    p.add_argument(
        "--methods", nargs="+", default=["sift", "rectsift"], choices=["sift", "rectsift"]
    )
    add_variant_argument(p)
    p.add_argument("--seeds", type=int, nargs="+", default=list(range(8)))
    p.add_argument("--max_num_features", type=int, default=8192)
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="[%(asctime)s %(name)s] %(message)s")
    if not args.images.is_dir():
        p.error(f"--images {args.images}: not a directory")
    try:
        variants = parse_variants(args.variant, taken=args.methods)
    except ValueError as e:
        p.error(str(e))
    confs = {
        m: method_conf(m, variants, max_num_features=args.max_num_features)
        for m in [*args.methods, *variants]
    }
    rows = []
    for m, conf in confs.items():
        rows += run_method(args.images, args.output_dir / m, m, conf, args)
    (args.output_dir / "hloc_sfm.json").write_text(json.dumps(rows, indent=1))
    print(markdown(rows, args.methods[0]))
    return 0


if __name__ == "__main__":
    sys.exit(run_script(main, "eval_hloc_sfm"))
