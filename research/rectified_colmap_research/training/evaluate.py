"""Evaluate an ONNX depth model on held-out renders: normals and dominant directions.

    python -m rectified_colmap_research.training.evaluate MODEL.onnx [--num 24] [--seed 900000000]

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
Ground-truth frames (``--york REAL_POOL``): the same per image against York Urban's
hand-labelled Manhattan frames, ECCV08 test split (never used in training).
Timing: seconds per 1536x1024 image through OnnxDepthSource (1 and 2 threads).

Trees and clouds (``--outdoor N``): N held-out renders whose scenes all have trees and a
cloudy sky (seeds from ``--seed`` + 10^6, ``synth`` ``tree_prob`` and ``cloud_prob`` 1;
views with < 5 % tree pixels skipped); the pipeline's plane labels of the predicted depth
(``evaluate_sky.plane_labels``) are counted on the tree pixels (``veg_planar``: should be
low, crowns have no plane), on the sky (``sky_planar``) and on the other surfaces
(``surface_planar``: so that labelling nothing is visible), pooled over the views, beside
the same from the exact depth (``*_gtdepth``; its sky has no depth).

Plane-fit normals (``--planes REAL_POOL``): on the held-out multi-view sets of the real
pool (:data:`PLANE_EVAL_SETS`, never trained on), planes fitted to each set's SfM points give
exact normals where one plane's points are dense
(:func:`rectified_colmap_research.training.real.plane_normal_map_camera`); per image, the pipeline's
normals of the predicted depth (as extraction computes them) are scored there:
``plane_err`` median angle (deg, sign-free), ``plane_within15`` fraction within 15 deg,
``plane_coverage`` fraction of the labelled pixels that got a normal. Unlike the line-frame
measures below, these labels also cover oblique walls without straight lines.

Real photos (``--real SCENE_DIR ...``, COLMAP scenes with ``images/`` and ``sparse/``, e.g.
Strecha): no true depth, but the Manhattan frame from line segments
(:func:`rectified_colmap_research.line_planes.manhattan_from_image`, consistent across
Strecha images to ~0.3 deg) is an accurate reference for the dominant directions. Per image,
over the line frame's confident axes: ``dir_err`` = angle (deg) from each axis to the nearest fitted
direction (mean), ``agree`` = fraction of the pixels with a normal whose normal is within
15 deg of a confident axis. Cheap enough to run on every checkpoint.
"""

from __future__ import annotations

import argparse
import json
import logging
import time
from pathlib import Path

import numpy as np

from rectified_colmap.config import NormalConf, PlaneConf
from rectified_colmap.geometry import angle_deg, rays_from_K
from rectified_colmap.normals import backproject, estimate_normals
from rectified_colmap.planes import fit_dominant_directions
from .data import synth_sample

logger = logging.getLogger(__name__)


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


def direction_error(dirs: np.ndarray | None, true_axes: np.ndarray) -> float:
    """Mean over fitted directions of the angle (deg) to the nearest true axis (sign-free)."""
    if dirs is None:
        return 90.0
    cos = np.abs(dirs @ true_axes.T).max(1).clip(0, 1)
    return float(np.degrees(np.arccos(cos)).mean())


def evaluate(
    model: str | Path,
    num: int = 24,
    seed: int = 900_000_000,
    width: int = 384,
    height: int = 288,
    texture_dir: str | Path | None = None,
    threads: int = 2,
) -> dict:
    from rectified_colmap.depth.onnx import OnnxDepthSource

    src = OnnxDepthSource(model, providers=["CPUExecutionProvider"], num_threads=threads)
    conf = NormalConf()
    rows = []
    for i in range(num):
        s = synth_sample(seed + i, width, height, texture_dir)
        rays = rays_from_K(s["K"], width, height).astype(np.float32)
        gt_n = s["normals"].astype(np.float64)
        mask = planar_mask(s["normals"], s["depth"])
        pred = src(s["image"]).to_depth()
        if pred.shape != (height, width):
            raise ValueError(f"{model}: depth {pred.shape} for a {width}x{height} image")
        row = {}
        for tag, depth in (
            ("pred", pred),
            ("gtdepth", np.where(s["depth"] > 0, s["depth"], np.nan)),
        ):
            n = estimate_normals(backproject(depth, rays), conf)
            has = mask & np.isfinite(n).all(-1)
            err = angle_deg(n[has].astype(np.float64), gt_n[has])
            row[f"normal_err_{tag}"] = float(np.median(err)) if err.size else 90.0
            row[f"coverage_{tag}"] = float(has.sum() / max(mask.sum(), 1))
            dirs, _ = fit_dominant_directions(
                n.reshape(-1, 3), PlaneConf(), np.random.default_rng(0)
            )
            # true scene axes (the scene is axis-aligned): world axes in the camera frame
            row[f"dir_err_{tag}"] = direction_error(dirs, s["R"].T)
        rows.append(row)
        logger.info("view %d: %s", i, {k: round(v, 2) for k, v in row.items()})
    out = {k: float(np.median([r[k] for r in rows])) for k in rows[0]}
    out["num_views"] = num
    return out


def evaluate_outdoor(
    depth_for,
    num: int = 12,
    seed: int = 901_000_000,
    width: int = 384,
    height: int = 288,
    texture_dir: str | Path | None = None,
    min_veg: float = 0.05,
) -> dict:
    """Tree, sky and other pixels labelled planar (module docstring) -> pooled fractions.
    ``depth_for(rgb)`` -> DepthMap of one render."""
    from rectified_colmap_research import synth
    from rectified_colmap.depth import DepthMap
    from .evaluate_sky import plane_labels, upsample_nearest

    veg_kind = synth.KIND_NAMES.index("vegetation")
    tex = None if texture_dir is None else str(texture_dir)
    counts = {}
    used = 0
    for i in range(num * 3):
        if used == num:
            break
        rng = np.random.default_rng(seed + i)
        r = synth.random_sample(rng, width, height, tex, tree_prob=1.0, cloud_prob=1.0)
        veg, surf = r.kind == veg_kind, (r.kind >= 0) & (r.kind != veg_kind)
        sky = r.kind < 0
        if veg.mean() < min_veg:
            continue
        used += 1
        exact = DepthMap(np.where(np.isfinite(r.depth), r.depth, 0.0), "metric")
        for tag, dm in (("pred", depth_for(r.image)), ("gtdepth", exact)):
            planar = upsample_nearest(plane_labels(dm, r.camera)[0] >= 0, width, height)
            for name, m in (("veg", veg), ("surface", surf), ("sky", sky)):
                c = counts.setdefault(f"{name}_{tag}", [0, 0])
                c[0] += int((m & planar).sum())
                c[1] += int(m.sum())
    if not used:
        raise ValueError("no tree view with enough tree pixels")
    out = {}
    for key, (a, b) in counts.items():
        name, tag = key.split("_")
        out[f"{name}_planar_{tag}"] = a / max(b, 1)
    out["veg_views"] = used
    return out


def image_directions(depth_map, camera, conf) -> tuple[np.ndarray | None, np.ndarray]:
    """The pipeline's view of one depth map -> (fitted dominant directions (3, 3) or None,
    valid normals (N, 3)): disparity resolved, normals at the work size, directions fitted
    as extraction does."""
    from rectified_colmap.disparity import resolve_disparity
    from rectified_colmap.normals import depth_to_normals

    depth = resolve_disparity(depth_map, camera, conf)
    n = depth_to_normals(depth, camera, conf.normals).reshape(-1, 3)
    n = n[np.isfinite(n).all(1)]
    dirs, _ = fit_dominant_directions(n, conf.planes, np.random.default_rng(0))
    return dirs, n


def _row(name: str, axes: np.ndarray, dirs, n: np.ndarray, agree_deg: float) -> dict:
    cos = np.abs(n @ axes.T).max(1) if len(n) else np.zeros(0)
    return {
        "image": name,
        "dir_err": direction_error(axes, dirs) if dirs is not None else 90.0,
        "agree": float(np.mean(cos > np.cos(np.deg2rad(agree_deg)))) if len(n) else 0.0,
    }


def _summary(rows: list[dict], prefix: str) -> dict:
    return {
        f"{prefix}_images": len(rows),
        f"{prefix}_dir_err_median": float(np.median([r["dir_err"] for r in rows])),
        f"{prefix}_dir_err_mean": float(np.mean([r["dir_err"] for r in rows])),
        f"{prefix}_dir_err_le5": float(np.mean([r["dir_err"] <= 5.0 for r in rows])),
        f"{prefix}_agree_median": float(np.median([r["agree"] for r in rows])),
        "rows": rows,
    }


def evaluate_real(depth_for, scene_dirs, agree_deg: float = 15.0) -> dict:
    """Dominant directions and normals of a depth source vs the line-derived Manhattan frame,
    on the images of COLMAP scene folders (``images/``, ``sparse/``).

    ``depth_for(path, rgb)`` -> DepthMap of one image (rgb: (H, W, 3) uint8). Images without
    a confident line frame are skipped. Per image: ``dir_err`` = mean over the confident
    line axes of the angle to the nearest fitted direction; ``agree`` = fraction of the
    normals within ``agree_deg`` of a confident axis. Returns medians/means and ``rows``."""
    import cv2
    import pycolmap

    from rectified_colmap.config import ExtractConf
    from rectified_colmap_research.line_planes import manhattan_from_image

    conf = ExtractConf()
    rows = []
    for scene in map(Path, scene_dirs):
        rec = pycolmap.Reconstruction(str(scene / "sparse"))
        for image in sorted(rec.images.values(), key=lambda im: im.name):
            path = scene / "images" / image.name
            bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
            if bgr is None:
                raise ValueError(f"{path}: cannot read image")
            camera = rec.cameras[image.camera_id]
            vp = manhattan_from_image(cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY), camera, conf.vp)
            if vp.directions is None:
                continue  # no reference frame for this image
            rgb = np.ascontiguousarray(bgr[..., ::-1])
            dirs, n = image_directions(depth_for(path, rgb), camera, conf)
            rows.append(
                _row(f"{scene.name}/{image.name}", vp.directions[vp.snapped], dirs, n, agree_deg)
            )
            logger.info(
                "%s: dir_err %.2f agree %.3f",
                rows[-1]["image"],
                rows[-1]["dir_err"],
                rows[-1]["agree"],
            )
    if not rows:
        raise ValueError(f"no image with a confident line frame in {list(map(str, scene_dirs))}")
    return _summary(rows, "real")


PLANE_EVAL_SETS = ("sacre-coeur", "british-museum", "nle-tower")
"""Real-pool sets with COLMAP models that never train a shipped network (sacre-coeur: the
hloc evaluation photos; british-museum, nle-tower: non-commercial terms)."""


def evaluate_planes(depth_for, root: str | Path, sets=PLANE_EVAL_SETS, min_labelled=0.005):
    """Normals of a depth source vs plane-fit normals of held-out multi-view sets (module
    docstring); images with less than ``min_labelled`` of the grid labelled are skipped."""
    import cv2

    from rectified_colmap.config import ExtractConf
    from rectified_colmap.disparity import resolve_disparity
    from rectified_colmap.geometry import scaled_size
    from rectified_colmap.normals import depth_to_normals
    from .real import items_from_model, plane_normal_map_camera

    conf = ExtractConf()
    rows, pooled = [], []
    for name in sets:
        for it in items_from_model(Path(root) / name):
            bgr = cv2.imread(str(it.path), cv2.IMREAD_COLOR)
            if bgr is None:
                raise ValueError(f"{it.path}: cannot read image")
            cam = it.camera
            dm = depth_for(it.path, np.ascontiguousarray(bgr[..., ::-1]))
            n = depth_to_normals(resolve_disparity(dm, cam, conf), cam, conf.normals)
            h, w = n.shape[:2]
            if (w, h) != scaled_size(cam.width, cam.height, max(w, h)):
                raise ValueError(f"{it.path}: normals grid {w}x{h} does not cover the image")
            gt = plane_normal_map_camera(
                it.points, it.point_planes, it.planes, it.cam_from_world, cam, w, h
            )
            lab = np.abs(gt).sum(-1) > 0
            if lab.mean() < min_labelled:
                continue
            has = lab & np.isfinite(n).all(-1)
            cos = np.abs((n[has] * gt[has]).sum(-1)).clip(0, 1)
            err = np.degrees(np.arccos(cos))
            pooled.append(err)
            rows.append(
                {
                    "image": f"{name}/{it.path.name}",
                    "labelled": float(lab.mean()),
                    "plane_coverage": float(has.sum() / lab.sum()),
                    "plane_err": float(np.median(err)) if err.size else 90.0,
                    "plane_within15": float(np.mean(err <= 15)) if err.size else 0.0,
                }
            )
            logger.info(
                "%s: %s",
                rows[-1]["image"],
                {k: round(v, 3) for k, v in rows[-1].items() if k != "image"},
            )
    if not rows:
        raise ValueError(f"{root}: no held-out image with plane labels in {list(sets)}")
    allerr = np.concatenate(pooled)
    return {
        "plane_images": len(rows),
        "plane_err_median": float(np.median([r["plane_err"] for r in rows])),
        "plane_err_pooled": float(np.median(allerr)) if allerr.size else 90.0,
        "plane_within15_pooled": float(np.mean(allerr <= 15)) if allerr.size else 0.0,
        "plane_coverage_median": float(np.median([r["plane_coverage"] for r in rows])),
        "rows": rows,
    }


def york_test_items(root: str | Path, sets=("yorkurban",)) -> list[tuple[Path, object, np.ndarray]]:
    """York Urban images of the ECCV08 TEST split (never trained on) -> (path, camera,
    ground-truth Manhattan frame (3, 3), rows = axes in the camera frame, y down)."""
    from .real import camera_from_record

    root = Path(root)
    items = []
    for name in sets:
        recs = json.loads((root / name / "cameras.json").read_text())
        gt = json.loads((root / name / "gt" / "gt_vps.json").read_text())["images"]
        for fname, rec in sorted(recs.items()):
            g = gt.get(Path(fname).stem)
            if g is None or g.get("eccv_split") != "test":
                continue
            F = np.array(g["vp_orthogonal"], np.float64).T  # rows = VP directions, y up
            F[:, 1] *= -1
            items.append((root / name / "images" / fname, camera_from_record(rec), F))
    return items


def evaluate_gt_frames(depth_for, items, agree_deg: float = 15.0) -> dict:
    """Dominant directions of a depth source vs GROUND-TRUTH Manhattan frames (York Urban:
    hand-labelled segments, orthogonalised VPs): ``items`` from :func:`york_test_items`.
    Per image ``dir_err`` = mean over the three true axes of the angle to the nearest
    fitted direction; ``agree`` as in :func:`evaluate_real`."""
    import cv2

    from rectified_colmap.config import ExtractConf

    conf = ExtractConf()
    rows = []
    for path, camera, F in items:
        bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
        if bgr is None:
            raise ValueError(f"{path}: cannot read image")
        rgb = np.ascontiguousarray(bgr[..., ::-1])
        dirs, n = image_directions(depth_for(path, rgb), camera, conf)
        rows.append(
            _row(f"{Path(path).parent.parent.name}/{Path(path).name}", F, dirs, n, agree_deg)
        )
    if not rows:
        raise ValueError("no ground-truth frames to evaluate against")
    return _summary(rows, "york")


def time_inference(
    model: str | Path, threads: int, width: int = 1536, height: int = 1024, repeats: int = 5
) -> float:
    from rectified_colmap.depth.onnx import OnnxDepthSource

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
    p.add_argument(
        "--real",
        type=Path,
        nargs="*",
        default=[],
        help="COLMAP scene folders (images/, sparse/) of real photos",
    )
    p.add_argument(
        "--york",
        type=Path,
        default=None,
        help="real-pool folder: score against York Urban's ground-truth frames (test split)",
    )
    p.add_argument(
        "--outdoor",
        type=int,
        default=0,
        help="N held-out renders with trees and clouds: tree and sky pixels labelled planar",
    )
    p.add_argument(
        "--planes",
        type=Path,
        default=None,
        help="real-pool folder: score against plane-fit normals of its held-out SfM sets",
    )
    p.add_argument("--output", type=Path, default=None, help="JSON of the results")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    res = {}
    if args.num > 0:
        res = evaluate(
            args.model, args.num, args.seed, texture_dir=args.texture_dir, threads=args.threads
        )
    if args.real or args.york or args.outdoor > 0 or args.planes:
        from rectified_colmap.depth.onnx import OnnxDepthSource

        src = OnnxDepthSource(
            args.model, providers=["CPUExecutionProvider"], num_threads=args.threads
        )

        def depth_for(path, rgb):
            return src(rgb)

        parts = []
        if args.real:
            parts.append(evaluate_real(depth_for, args.real))
        if args.york:
            parts.append(evaluate_gt_frames(depth_for, york_test_items(args.york)))
        if args.outdoor > 0:
            seed = args.seed + 1_000_000
            parts.append(evaluate_outdoor(src, args.outdoor, seed, texture_dir=args.texture_dir))
        if args.planes:
            parts.append(evaluate_planes(depth_for, args.planes))
        for part in parts:
            part.pop("rows", None)
            res.update(part)
    if args.timing:
        for t in (1, 2):
            res[f"time_1536x1024_{t}thread_s"] = time_inference(args.model, t)
    print(json.dumps(res, indent=1))
    if args.output:
        args.output.write_text(json.dumps(res, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
