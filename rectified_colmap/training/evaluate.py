"""Evaluate an ONNX depth model on held-out renders: normals and dominant directions.

    python -m rectified_colmap.training.evaluate MODEL.onnx [--num 24] [--seed 900000000]

For each held-out view (seeds never used by training) the model runs through the runtime
path (:class:`rectified_colmap.depth.onnx.OnnxDepthSource`); per-pixel normals come from
:func:`rectified_colmap.normals.estimate_normals` on the predicted depth and, as a
reference, on the exact rendered depth. Reported (medians over views):

- ``normal_err_pred`` / ``normal_err_gtdepth``: median angle (deg) between estimated and
  rendered normals on planar pixels (interior of a plane in the render) that got a normal;
  ``coverage_*``: fraction of those pixels that got a normal;
- ``dir_err_pred``: mean over the three dominant directions fitted
  (:func:`rectified_colmap.planes.fit_dominant_directions`) to the predicted normals of the
  angle to the nearest (sign-free) true scene axis; ``dir_err_gtdepth`` the same from the
  exact depth.
Timing: seconds per 1536x1024 image through OnnxDepthSource (1 and 2 threads).
"""

from __future__ import annotations

import argparse
import json
import logging
import time
from pathlib import Path

import numpy as np

from ..config import NormalConf, PlaneConf
from ..normals import backproject, estimate_normals
from ..planes import fit_dominant_directions
from .render import Textures, random_sample

logger = logging.getLogger(__name__)


def rays_from_K(K: np.ndarray, width: int, height: int) -> np.ndarray:
    jj, ii = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    return np.stack([(jj - K[0, 2]) / K[0, 0], (ii - K[1, 2]) / K[1, 1],
                     np.ones_like(jj)], -1).astype(np.float32)


def planar_mask(normals: np.ndarray, depth: np.ndarray, r: int = 3) -> np.ndarray:
    """Pixels whose (2r+1)^2 neighbourhood is valid and has one rendered normal."""
    import cv2

    valid = (depth > 0).astype(np.uint8)
    k = np.ones((2 * r + 1, 2 * r + 1), np.uint8)
    ok = cv2.erode(valid, k, borderType=cv2.BORDER_CONSTANT, borderValue=0) > 0
    for c in range(3):
        ch = normals[..., c].astype(np.float32)
        ok &= (cv2.dilate(ch, k) - cv2.erode(ch, k)) < 1e-3
    return ok


def angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    cos = np.clip((a * b).sum(-1), -1.0, 1.0)
    return np.degrees(np.arccos(cos))


def direction_error(dirs: np.ndarray | None, true_axes: np.ndarray) -> float:
    """Mean over fitted directions of the angle (deg) to the nearest true axis (sign-free)."""
    if dirs is None:
        return 90.0
    cos = np.abs(dirs @ true_axes.T).max(1).clip(0, 1)
    return float(np.degrees(np.arccos(cos)).mean())


def evaluate(model: str | Path, num: int = 24, seed: int = 900_000_000, width: int = 384,
             height: int = 288, texture_dir: str | Path | None = None,
             threads: int = 2) -> dict:
    from ..depth.onnx import OnnxDepthSource

    src = OnnxDepthSource(model, providers=["CPUExecutionProvider"], num_threads=threads)
    textures = Textures(texture_dir) if texture_dir else None
    conf = NormalConf()
    rows = []
    for i in range(num):
        s = random_sample(seed + i, width, height, textures)
        rays = rays_from_K(s["K"], width, height)
        gt_n = s["normals"].astype(np.float64)
        mask = planar_mask(s["normals"], s["depth"])
        pred = src(s["image"]).to_depth()
        if pred.shape != (height, width):
            raise ValueError(f"{model}: depth {pred.shape} for a {width}x{height} image")
        row = {}
        for tag, depth in (("pred", pred), ("gtdepth", np.where(s["depth"] > 0, s["depth"],
                                                                 np.nan))):
            n = estimate_normals(backproject(depth, rays), conf)
            has = mask & np.isfinite(n).all(-1)
            err = angle_deg(n[has].astype(np.float64), gt_n[has])
            row[f"normal_err_{tag}"] = float(np.median(err)) if err.size else 90.0
            row[f"coverage_{tag}"] = float(has.sum() / max(mask.sum(), 1))
            dirs, _ = fit_dominant_directions(n.reshape(-1, 3), PlaneConf(),
                                              np.random.default_rng(0))
            # true scene axes (the scene is axis-aligned): world axes in the camera frame
            row[f"dir_err_{tag}"] = direction_error(dirs, s["R"])
        rows.append(row)
        logger.info("view %d: %s", i, {k: round(v, 2) for k, v in row.items()})
    out = {k: float(np.median([r[k] for r in rows])) for k in rows[0]}
    out["num_views"] = num
    return out


def time_inference(model: str | Path, threads: int, width: int = 1536, height: int = 1024,
                   repeats: int = 5) -> float:
    from ..depth.onnx import OnnxDepthSource

    src = OnnxDepthSource(model, providers=["CPUExecutionProvider"], num_threads=threads)
    img = np.random.default_rng(0).integers(0, 256, (height, width, 3), dtype=np.uint8)
    src(img)  # warm-up
    t = time.perf_counter()
    for _ in range(repeats):
        src(img)
    return (time.perf_counter() - t) / repeats


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description="evaluate an ONNX depth model on held-out renders")
    p.add_argument("model", type=Path)
    p.add_argument("--num", type=int, default=24)
    p.add_argument("--seed", type=int, default=900_000_000)
    p.add_argument("--texture_dir", type=Path, default=None)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--timing", action="store_true")
    p.add_argument("--output", type=Path, default=None, help="JSON of the results")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    res = evaluate(args.model, args.num, args.seed, texture_dir=args.texture_dir,
                   threads=args.threads)
    if args.timing:
        for t in (1, 2):
            res[f"time_1536x1024_{t}thread_s"] = time_inference(args.model, t)
    print(json.dumps(res, indent=1))
    if args.output:
        args.output.write_text(json.dumps(res, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
