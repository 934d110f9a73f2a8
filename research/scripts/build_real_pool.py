#!/usr/bin/env python
"""Turn the real-pool photos that may train the shipped depth network into training samples.

    python scripts/build_real_pool.py --data ../shared/data/real-pool --output /tmp/real_pool

One compact .npz per photo (rectified_colmap_research.training.real: the photo at 320x240, sparse
SfM depth, normal labels from planes fitted to the SfM points and from line support where
the Manhattan frame passes its trust test, sky pseudo-labels); which sets and which split:
``real.real_pool_items``. See docs/training.md.
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

import cv2
import numpy as np

from rectified_colmap.parallel import context
from rectified_colmap_research.training.real import (
    make_real_sample,
    real_pool_items,
    save_real_sample,
)
from rectified_colmap_research.training.sky import sky_pseudo_label
from rectified_colmap.errors import run_script

logger = logging.getLogger("build_real_pool")


def _one(job) -> tuple[str, dict]:
    item, out, width, height = job
    cv2.setNumThreads(1)
    try:
        s = make_real_sample(item, width, height, sky_fn=sky_pseudo_label)
    except ValueError as e:
        return str(e), {}
    save_real_sample(out, s)
    has_n = np.abs(s["normals"]).sum(-1) > 0
    return "", {
        "points": int((s["depth"] > 0).sum()),
        "normals": float(has_n.mean()),
        "sky": float((s["sky"] == 1).mean()),
        "frame": bool(np.isfinite(s["frame"]).all()),
    }


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--data", type=Path, default=Path("../shared/data/real-pool"))
    p.add_argument("--output", type=Path, required=True)
    p.add_argument("--width", type=int, default=320)
    p.add_argument("--height", type=int, default=240)
    p.add_argument("--processes", type=int, default=2)
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    if not args.data.is_dir():
        logger.error("%s: no such folder (the real-pool data set)", args.data)
        return 2
    args.output.mkdir(parents=True, exist_ok=True)
    items = real_pool_items(args.data)
    jobs = [
        (
            it,
            args.output / f"{i:04d}_{it.path.parent.parent.name}_{it.path.stem}.npz",
            args.width,
            args.height,
        )
        for i, it in enumerate(items)
    ]
    failed = 0
    stats = []
    # never forked (rectified_colmap.parallel): workers import this script, under its guard
    with context(["rectified_colmap_research.training.real"]).Pool(args.processes) as pool:
        for err, st in pool.imap(_one, jobs):
            if err:
                logger.error("%s", err)
                failed += 1
            else:
                stats.append(st)
    logger.info(
        "%d samples in %s (%d failed): %d with SfM points, %d with a confident frame; "
        "mean labelled-normal fraction %.2f, mean sky-label fraction %.2f",
        len(stats),
        args.output,
        failed,
        sum(s["points"] > 0 for s in stats),
        sum(s["frame"] for s in stats),
        float(np.mean([s["normals"] for s in stats])) if stats else 0.0,
        float(np.mean([s["sky"] for s in stats])) if stats else 0.0,
    )
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(run_script(main, "build_real_pool"))
