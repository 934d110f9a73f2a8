#!/usr/bin/env python
"""Vanishing points vs a mediocre depth network on rendered street pairs (docs/vp.md).

Pairs: rectified_colmap_research.synth street scenes, two views of one facade or ground
point whose viewing directions are ``--min_deg``-``--max_deg`` apart (synth.view_pair),
480x360, focal 0.9 x width, targets alternating facade / ground. Exact depth, normals and
poses.

Depth "network" = GT depth corrupted per image, independently in the two views:
- a smooth tilt of the inverse depth, 1/z' = 1/z + g . (x_n, y_n) with (x_n, y_n) the
  normalised image coordinates: planes stay planar but every normal rotates (a plane at
  distance d by ~atan(|g| d)); |g| is drawn so that a plane at the median distance rotates
  by ``--tilt_deg`` (uniform in the range), direction random;
- a low-frequency multiplicative field, z' *= 1 + a * f(x, y), f a bicubic upsampling of
  4x3 uniform noise in [-1, 1], a = ``--field`` (default 0.15: +-15%).

Methods (same SIFT budget): plain SIFT; rectified with GT depth (reference); rectified with
the corrupted depth; corrupted depth + VP (vp.enabled); VP only (no depth, planes from lines
alone: research line_planes, line-support regions); VP only with whole-image warps ('whole',
the paper's VP baseline).
Per method: dominant-direction error (each direction to the nearest GT axis = world axes
in the camera frame; depth-free: the Manhattan frame), patch-normal error (median angle
between a patch's normal and the GT normals of its pixels, area-weighted over patches),
pose success (rotation error < 5 deg), GT-correct matches (Sampson < 3 px).

    python scripts/eval_vp.py --num_pairs 12 --output docs/vp_synth.md

``--depth_model NAME|PATH ...`` adds one row "rect network (NAME)" per ONNX depth network
(registry name or .onnx path, resolved as `rectified-colmap extract --depth_model`; CPU,
one thread): each rendered image's depth is predicted by the network (OnnxDepthSource ->
DepthMap -> extract_image, as in extraction) and the conf is the default (with
``--rect_conf`` on top), vanishing points included: with the embedded network this row
is what `rectified-colmap extract` does. ``--depth_model_no_vp`` adds the same without the
vanishing points' orientation of the depth planes (vp.enabled off: "rect network (NAME),
no VP"; plane hypotheses from pairs of vanishing points stay). Their s / image include the
network. A paired line per network row compares it with plain SIFT (exact two-sided
binomial p-values)::

    python scripts/eval_vp.py --num_pairs 24 --depth_model rectsift-lite0 --methods plain

(Until 2026-12-03 the "rect network" row ran without vp.enabled and ``--depth_model_vp``
added the default as "+ VP"; the flag is still accepted and changes nothing.)

``--timing SCENE...`` times plain SIFT and the two depth-free modes per image instead
(first ``--num_images`` images of each scene; ``--max_num_features`` budget)::

    python scripts/eval_vp.py --timing /work/shared/data/strecha-dev/* --max_num_features 1024

``--combine`` merges relative-pose records of several scripts/eval_strecha.py runs (one
method each, renamed) into one table by rotation bin (the real-photo part of docs/vp.md)::

    python scripts/eval_vp.py --combine "plain SIFT=OUT_net/records.csv:sift" \
        "network=OUT_net/records.csv:rectsift" "network + VP=OUT_netvp/records.csv:rectsift"

With ``--baseline LABEL`` it adds each other row paired against that one (per rotation bin:
pairs solved only by either, McNemar p; more / fewer GT-correct, sign-test p). With
``--bin_by viewpoint`` the bins are of viewpoint change instead (records of wide scenes,
scripts/build_wide_pairs.py).
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from pathlib import Path

import cv2
import numpy as np

from rectified_colmap import camera as cam_utils
from rectified_colmap_research import synth
from rectified_colmap.config import ExtractConf
from rectified_colmap.eval.config import EvalConf
from rectified_colmap.depth import DepthMap
from rectified_colmap.eval.matching import FeatureSource
from rectified_colmap.eval.pairs import Pair
from rectified_colmap.eval.relpose import evaluate_pair
from rectified_colmap.sift import detect_sift
from rectified_colmap.io.hloc_h5 import rootsift_unit
from rectified_colmap.pipeline import ImageResult, extract_image
from rectified_colmap_research.line_planes import LinePlaneConf, extract_depth_free
from rectified_colmap.errors import run_script

logger = logging.getLogger("eval_vp")

WHOLE = "VP only, whole-image warps"
METHODS = ("plain", "rect GT depth", "rect corrupted", "rect corrupted + VP", "VP only", WHOLE)
CPU = ["CPUExecutionProvider"]


def network_rows(specs: list[str], without_vp: bool) -> dict[str, tuple[str, bool]]:
    """Row name -> (model name or path, VP as the conf has it) for --depth_model /
    --depth_model_no_vp: "rect network (NAME)" runs the conf as given (the default:
    vanishing points on), "rect network (NAME), no VP" with vp.enabled off. Rows are named
    by the registry name or the file name (the path as given if two models would share a
    name)."""
    from rectified_colmap.depth.registry import REGISTRY

    specs = list(dict.fromkeys(specs))
    labels = [s if s in REGISTRY else Path(s).name for s in specs]
    if len(set(labels)) < len(labels):
        labels = specs
    rows = {}
    for spec, label in zip(specs, labels):
        rows[f"rect network ({label})"] = (spec, True)
        if without_vp:
            rows[f"rect network ({label}), no VP"] = (spec, False)
    return rows


def load_networks(rows: dict[str, tuple[str, bool]]) -> dict:
    """Model name or path -> OnnxDepthSource (CPU, one thread), each model loaded once."""
    from rectified_colmap.depth.registry import load_depth_source

    specs = dict.fromkeys(spec for spec, _ in rows.values())
    return {spec: load_depth_source(spec, providers=CPU, num_threads=1) for spec in specs}


def predict(networks: dict, image: np.ndarray, camera) -> dict[str, tuple[DepthMap, float]]:
    """Model -> (predicted DepthMap, seconds) for one RGB image."""
    out = {}
    for spec, source in networks.items():
        t = time.perf_counter()
        out[spec] = (source(image, camera), time.perf_counter() - t)
    return out


def network_note(rows: dict[str, tuple[str, bool]], networks: dict) -> str:
    from rectified_colmap.depth.registry import sha256_file

    return (
        "Networks (CPU, one thread; s / image includes the network): "
        + "; ".join(
            f"{row} = {networks[spec].path} (sha256 {sha256_file(networks[spec].path)[:12]}, "
            f"resize {networks[spec].spec.resize})"
            for row, (spec, vp) in rows.items()
            if not vp
        )
        + "."
    )


def corrupt_depth(
    depth: np.ndarray, camera, rng: np.random.Generator, tilt_deg: tuple[float, float], field: float
) -> np.ndarray:
    """GT z-depth (H, W), NaN = sky -> a plausible mediocre prediction (module docstring)."""
    H, W = depth.shape
    rays = cam_utils.grid_rays(camera, W, H)
    xn, yn = rays[..., 0] / rays[..., 2], rays[..., 1] / rays[..., 2]
    finite = np.isfinite(depth)
    dist = np.median(depth[finite])  # ~ distance of the typical plane (fronto-parallel)
    theta = np.deg2rad(rng.uniform(*tilt_deg))
    phi = rng.uniform(0, 2 * np.pi)
    g = np.tan(theta) / dist * np.array([np.cos(phi), np.sin(phi)])
    inv = 1.0 / depth + g[0] * xn + g[1] * yn
    z = np.where(inv > 0.2 / depth, 1.0 / np.maximum(inv, 1e-12), np.nan)
    coarse = rng.uniform(-1, 1, (3, 4)).astype(np.float32)
    f = cv2.resize(coarse, (W, H), interpolation=cv2.INTER_CUBIC)
    return (z * (1.0 + field * np.clip(f, -1, 1))).astype(np.float32)


def direction_errors(directions: np.ndarray | None, gt_axes: np.ndarray) -> np.ndarray:
    """(3,) angle of each direction to its nearest GT axis (sign-free), NaN without."""
    if directions is None:
        return np.full(3, np.nan)
    c = np.abs(np.asarray(directions) @ gt_axes.T).max(1)
    return np.degrees(np.arccos(np.clip(c, -1, 1)))


def normals_on_grid(
    gt_normals: np.ndarray, shape: tuple[int, int]
) -> tuple[np.ndarray, np.ndarray]:
    """GT normals (H, W, 3), NaN where unknown, resampled (nearest) to a (h, w) grid: the
    normals (h, w, 3) with 0 where unknown, and (h, w) bool where known."""
    h, w = shape
    N = cv2.resize(np.nan_to_num(gt_normals), (w, h), interpolation=cv2.INTER_NEAREST)
    known = np.isfinite(gt_normals).all(-1).astype(np.uint8)
    valid = cv2.resize(known, (w, h), interpolation=cv2.INTER_NEAREST) > 0
    return N, valid


def patch_errors(planes, gt_normals: np.ndarray) -> list[tuple[float, int]]:
    """(median angle to the GT normals of its pixels, pixels) per patch (work grid)."""
    if planes is None:
        return []
    h, w = planes.labels.shape
    N, valid = normals_on_grid(gt_normals, (h, w))
    out = []
    for p in planes.patches:
        m = p.mask & valid
        if m.sum() < 20:
            continue
        ang = np.degrees(np.arccos(np.clip(N[m] @ p.normal, -1, 1)))
        out.append((float(np.median(ang)), int(m.sum())))
    return out


def patch_precision_recall(planes, gt_normals: np.ndarray, tol_deg: float = 10.0) -> np.ndarray:
    """(4,) cell counts on the work grid: [patch cells whose GT normal is within tol_deg
    of the patch normal, patch cells with a GT normal (summed over patches: overlapping
    patches count each time), GT-planar cells in some patch of their normal, GT-planar
    cells]. Precision = [0] / [1], recall = [2] / [3]."""
    if planes is None or planes.labels is None:
        return np.zeros(4)
    h, w = planes.labels.shape
    N, valid = normals_on_grid(gt_normals, (h, w))
    cos_t = np.cos(np.deg2rad(tol_deg))
    good, cells, hit = 0, 0, np.zeros((h, w), bool)
    for p in planes.patches:
        ok = p.mask & valid & (N @ p.normal >= cos_t)
        good += ok.sum()
        cells += (p.mask & valid).sum()
        hit |= ok
    return np.array([good, cells, hit.sum(), valid.sum()], float)


def make_pairs(num: int, min_deg: float, max_deg: float, width: int, height: int):
    pairs, seed = [], 0
    while len(pairs) < num and seed < 10 * num:
        target = ("facade", "ground")[len(pairs) % 2]
        rng = np.random.default_rng(1000 + seed)
        seed += 1
        scene = synth.street(rng)
        camera = synth.pinhole_camera(width, height, 0.9 * width)
        try:
            p0, p1, _ = synth.view_pair(scene, rng, min_deg, max_deg, target=target, camera=camera)
        except (RuntimeError, ValueError):
            continue
        if p0 is None:
            continue
        pairs.append(
            (target, camera, [synth.render(scene, camera, p) for p in (p0, p1)], (p0, p1), rng)
        )
    return pairs


def confs(
    max_num_features: int,
    rows: dict[str, tuple[str, bool]] | None = None,
    overrides: dict | None = None,
) -> dict[str, ExtractConf]:
    shipped = ExtractConf.from_dict(overrides)  # the default (+ overrides), VP as it has it
    shipped.sift.max_num_features = max_num_features
    base = ExtractConf.from_dict(shipped.to_dict())
    base.vp.enabled = False  # the depth rows without "+ VP" and ", no VP" run without it
    vp = ExtractConf.from_dict(base.to_dict())
    vp.vp.enabled = True
    out = {
        "rect GT depth": base,
        "rect corrupted": base,
        "rect corrupted + VP": vp,
        "VP only": base,  # planes from lines alone: LINE_ROWS
        WHOLE: base,
    }
    out.update({row: shipped if vp_on else base for row, (_, vp_on) in (rows or {}).items()})
    return out


LINE_ROWS = {"VP only": LinePlaneConf(), WHOLE: LinePlaneConf(regions="whole")}
"""Rows whose planes come from lines alone (research: line_planes), with their regions."""


def extract_row(m: str, image, camera, depth, conf: ExtractConf, rng) -> ImageResult:
    """Method m's features of one image: the pipeline, or for LINE_ROWS the pipeline on
    planes from lines alone."""
    if m in LINE_ROWS:
        return extract_depth_free(image, camera, conf, LINE_ROWS[m], rng)
    return extract_image(image, camera, depth, conf, rng)


def depth_for(
    m: str, gt: np.ndarray, bad: np.ndarray, rows: dict, predicted: dict
) -> tuple[DepthMap | None, float]:
    """(depth given to method m, seconds spent predicting it)."""
    if m in rows:
        return predicted[rows[m][0]]
    return {"rect GT depth": DepthMap(gt, "metric"), "VP only": None, WHOLE: None}.get(
        m, DepthMap(bad, "metric")
    ), 0.0


def run(args) -> str:
    t0 = time.perf_counter()
    pairs = make_pairs(args.num_pairs, args.min_deg, args.max_deg, args.width, args.height)
    rows = network_rows(args.depth_model, args.depth_model_no_vp)
    networks = load_networks(rows)
    methods = tuple(m for m in METHODS if m in args.methods) + tuple(rows)
    cfs = confs(args.max_num_features, rows, json.loads(args.rect_conf) if args.rect_conf else None)
    eval_conf = EvalConf()
    records, dir_err, patch_err, coverage, nrect, secs = [], {}, {}, {}, {}, {}
    for m in methods:
        dir_err[m], patch_err[m], coverage[m], nrect[m], secs[m] = [], [], [], [], []
    prec_rec = {m: np.zeros(4) for m in methods}
    for i, (target, camera, renders, poses, rng) in enumerate(pairs):
        feats = {m: {} for m in methods}
        for j, (r, pose) in enumerate(zip(renders, poses)):
            name = str(j)
            gray = cv2.cvtColor(r.image, cv2.COLOR_RGB2GRAY)
            gt_axes = np.asarray(pose.rotation.matrix()).T  # rows: world axes in camera
            bad = corrupt_depth(r.depth, camera, rng, args.tilt_deg, args.field)
            predicted = predict(networks, r.image, camera)
            for m in methods:
                ts = time.perf_counter()
                if m == "plain":
                    f = detect_sift(gray, cfs["rect GT depth"].sift, args.max_num_features)
                    res, t_depth = None, 0.0
                else:
                    depth, t_depth = depth_for(m, r.depth, bad, rows, predicted)
                    res = extract_row(m, r.image, camera, depth, cfs[m], np.random.default_rng(i))
                    f = res.features
                secs[m].append(time.perf_counter() - ts + t_depth)
                if res is not None:
                    dir_err[m].append(
                        direction_errors(res.planes.directions if res.planes else None, gt_axes)
                    )
                    patch_err[m] += patch_errors(res.planes, r.normals)
                    prec_rec[m] += patch_precision_recall(res.planes, r.normals)
                    cov = res.coverage
                    coverage[m].append(0.0 if cov is None else float((cov >= 0).mean()))
                    nrect[m].append(len(res.rectifications))
                feats[m][name] = {
                    "keypoints": f.keypoints,
                    "descriptors": rootsift_unit(f.descriptors).T,
                }
        K = camera.calibration_matrix()
        pair = Pair(f"{i}/0", f"{i}/1", K, K, synth.relative_T(*poses))
        srcs = {m: FeatureSource({f"{i}/{k}": v for k, v in fm.items()}) for m, fm in feats.items()}
        recs = evaluate_pair(pair, srcs, eval_conf)
        for rec in recs:
            rec["target"] = target
        records += recs
        logger.info(
            "pair %d (%s, %.0f deg): %s",
            i,
            target,
            pair.rotation_deg,
            ", ".join(f"{r['method']} {r['num_correct']}/{r['success']:d}" for r in recs),
        )
    text = report(
        records,
        dir_err,
        patch_err,
        coverage,
        nrect,
        secs,
        prec_rec,
        args,
        time.perf_counter() - t0,
        len(pairs),
        methods,
    )
    if rows:
        text += "\n" + network_note(rows, networks) + "\n\n" + paired_lines(records, rows)
    return text


def _fmt(x, nd=1):
    return "-" if x is None or not np.isfinite(x) else f"{x:.{nd}f}"


def report(
    records,
    dir_err,
    patch_err,
    coverage,
    nrect,
    secs,
    prec_rec,
    args,
    seconds,
    num_pairs,
    methods=METHODS,
) -> str:
    lines = [
        f"Rendered street pairs: {num_pairs} ({args.width}x{args.height}, "
        f"{args.min_deg:.0f}-{args.max_deg:.0f} deg apart, facade/ground alternating), "
        f"corrupted depth: normal tilt {args.tilt_deg[0]:.0f}-{args.tilt_deg[1]:.0f} deg at "
        f"the median distance + low-frequency field +-{100 * args.field:.0f}%; "
        f"SIFT budget {args.max_num_features}. {seconds:.0f} s.",
        "",
        "| method | directions found (images) | direction error median / p90 (deg) | "
        "patch-normal error median / p90 (deg, area-weighted) | "
        "patch precision / recall % (GT normal within 10 deg) | rectified area % | "
        "pose success (R err < 5 deg) | GT-correct matches (total / median) | "
        "keypoints / image (median) | s / image (median) |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for m in methods:
        rs = [r for r in records if r["method"] == m]
        succ = sum(r["success"] for r in rs)
        corr = [r["num_correct"] for r in rs]
        kps = np.median([r[k] for r in rs for k in ("num_kp0", "num_kp1")])
        if m == "plain":
            lines.append(
                f"| {m} | - | - | - | - | 0 | {succ}/{len(rs)} | {sum(corr)} / "
                f"{np.median(corr):.0f} | {kps:.0f} | {np.median(secs[m]):.2f} |"
            )
            continue
        d = np.array(dir_err[m])
        found = int(np.isfinite(d).all(1).sum())
        e = d[np.isfinite(d)]
        pe = np.array(patch_err[m]) if patch_err[m] else np.zeros((0, 2))
        pr = prec_rec[m]

        def wq(q, pe=pe):
            if len(pe) == 0:
                return None
            o = np.argsort(pe[:, 0])
            c = np.cumsum(pe[o, 1]) / pe[:, 1].sum()
            return float(pe[o, 0][np.searchsorted(c, q)])

        lines.append(
            f"| {m} | {found}/{len(d)} | {_fmt(np.median(e) if len(e) else None, 2)} / "
            f"{_fmt(np.percentile(e, 90) if len(e) else None, 2)} | {_fmt(wq(0.5), 2)} / "
            f"{_fmt(wq(0.9), 2)} | {_fmt(100 * pr[0] / max(pr[1], 1), 0)} / "
            f"{_fmt(100 * pr[2] / max(pr[3], 1), 0)} | "
            f"{100 * np.mean(coverage[m]):.0f} | {succ}/{len(rs)} | "
            f"{sum(corr)} / {np.median(corr):.0f} | {kps:.0f} | {np.median(secs[m]):.2f} |"
        )
    by_target = [
        "",
        "Per target (pose success; GT-correct total):",
        "",
        "| method | " + " | ".join(sorted({r["target"] for r in records})) + " |",
        "|---|" + "---|" * len({r["target"] for r in records}),
    ]
    for m in methods:
        cells = []
        for t in sorted({r["target"] for r in records}):
            rs = [r for r in records if r["method"] == m and r["target"] == t]
            cells.append(
                f"{sum(r['success'] for r in rs)}/{len(rs)}; {sum(r['num_correct'] for r in rs)}"
            )
        by_target.append(f"| {m} | " + " | ".join(cells) + " |")
    return "\n".join(lines + by_target) + "\n"


def paired_lines(records: list[dict], rows: dict) -> str:
    """One line per network row vs plain SIFT over all pairs: GT-correct more / fewer
    (sign test) and pose successes only by one or the other (McNemar), exact two-sided
    binomial p-values (rectified_colmap.eval.report.paired_comparison)."""
    from rectified_colmap.eval.report import paired_comparison

    lines = []
    for r in paired_comparison(records, "plain", bin_deg=180.0):
        if r["bin"] is not None or r["method"] not in rows:
            continue
        lines.append(
            f"- {r['method']} vs plain, {r['pairs']} pairs: more GT-correct on {r['more']}, "
            f"fewer on {r['fewer']} (sign test p = {r['p_correct']:.3f}); pose solved only "
            f"by the network row {r['wins']}, only by plain {r['losses']} "
            f"(McNemar p = {r['p_success']:.3f})."
        )
    return "Paired vs plain SIFT:\n\n" + "\n".join(lines) + "\n"


def combine(
    specs: list[str], bin_deg: float = 10.0, baseline: str | None = None, by: str = "gt_rot"
) -> str:
    """'LABEL=records.csv:method' ... -> Markdown tables (rectified_colmap.eval.report),
    with ``baseline`` (a LABEL) also the other rows paired against it; bins of ``by``
    ("gt_rot" or "viewpoint": then only the records that know their viewpoint change)."""
    from rectified_colmap.eval import report as rep

    records = []
    for spec in specs:
        label, _, rest = spec.partition("=")
        path, _, method = rest.rpartition(":")
        if not label or not path or not Path(path).is_file():
            raise SystemExit(
                f"--combine {spec!r}: expected LABEL=records.csv:method with an existing file"
            )
        recs = [dict(r, method=label) for r in rep.read_csv(path) if r["method"] == method]
        if not recs:
            raise SystemExit(f"--combine {spec!r}: no records of method {method!r} in {path}")
        records += recs
    records = rep.with_field(records, by)
    if not records:
        raise SystemExit(f"--combine: no records with a known {by!r}")
    c = EvalConf(bin_deg=bin_deg)
    text = rep.markdown_table(
        records, c.bin_deg, c.auc_thresholds, c.success_deg, c.min_correct, by=by
    )
    if baseline is not None:
        text += "\n" + rep.paired_markdown(records, baseline, c.bin_deg, by)
    return text


def timing(scenes: list[Path], num_images: int, max_num_features: int) -> str:
    """Seconds per image (one thread) of plain SIFT and the two depth-free modes on the
    first ``num_images`` images of each Strecha-layout scene (images/, sparse/)."""
    from eval_strecha import scene_camera  # scripts/ is on sys.path when run as a script

    from rectified_colmap.camera import make_camera
    from rectified_colmap.io.images import read_image

    cv2.setNumThreads(1)  # as extract's workers
    c = ExtractConf()
    c.sift.max_num_features = max_num_features
    modes = {"plain SIFT": None, "VP only (line regions)": "VP only", WHOLE: WHOLE}
    rows = {m: [] for m in modes}  # (seconds, warps, covered %, warped area / image)
    for scene in scenes:
        model, params = scene_camera(scene)
        for path in sorted((scene / "images").glob("*.jpg"))[:num_images]:
            image = read_image(path)
            camera = make_camera(
                model, [float(p) for p in params.split(",")], image.shape[1], image.shape[0]
            )
            for m, row in modes.items():
                t = time.perf_counter()
                if row is None:
                    gray = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
                    detect_sift(gray, ExtractConf().sift, max_num_features)
                    rows[m].append((time.perf_counter() - t, 0, 0.0, 0.0))
                    continue
                res = extract_depth_free(image, camera, c, LINE_ROWS[row])
                cov = 0.0 if res.coverage is None else 100 * float((res.coverage >= 0).mean())
                warped = sum(r.pixels for r in res.rectifications)
                rows[m].append(
                    (
                        time.perf_counter() - t,
                        len(res.rectifications),
                        cov,
                        warped / (camera.width * camera.height),
                    )
                )
            logger.info(
                "%s: %s", path.name, ", ".join(f"{m} {v[-1][0]:.2f} s" for m, v in rows.items())
            )
    size = f"{image.shape[1]}x{image.shape[0]}"
    out = [
        f"{len(rows[WHOLE])} images ({size}), {max_num_features} features, one thread.",
        "",
        "| mode | s / image median (min-max) | warps median | covered % median | "
        "warped pixels / image pixels median |",
        "|---|---|---|---|---|",
    ]
    for m, v in rows.items():
        a = np.array(v)
        out.append(
            f"| {m} | {np.median(a[:, 0]):.2f} ({a[:, 0].min():.2f}-"
            f"{a[:, 0].max():.2f}) | {np.median(a[:, 1]):.0f} | "
            f"{np.median(a[:, 2]):.0f} | {np.median(a[:, 3]):.2f} |"
        )
    return "\n".join(out) + "\n"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--num_pairs", type=int, default=12)
    p.add_argument("--min_deg", type=float, default=50.0)
    p.add_argument("--max_deg", type=float, default=90.0)
    p.add_argument("--width", type=int, default=480)
    p.add_argument("--height", type=int, default=360)
    p.add_argument("--tilt_deg", type=float, nargs=2, default=(10.0, 20.0))
    p.add_argument("--field", type=float, default=0.15)
    p.add_argument("--max_num_features", type=int, default=8192)
    p.add_argument(
        "--depth_model",
        nargs="+",
        default=[],
        metavar="NAME|PATH",
        help="add a row 'rect network (NAME)' per ONNX depth network (registry "
        "name, e.g. rectsift-lite0, or .onnx path; CPU, one thread)",
    )
    p.add_argument(
        "--depth_model_no_vp",
        action="store_true",
        help="with --depth_model: also each network without the vanishing points' "
        "orientation (vp.enabled off: ', no VP')",
    )
    p.add_argument(
        "--depth_model_vp",
        action="store_true",
        help="accepted for old commands; changes nothing (the network rows have VP)",
    )
    p.add_argument(
        "--methods",
        nargs="+",
        default=list(METHODS),
        choices=METHODS,
        help="rows to run besides the --depth_model rows (default: all)",
    )
    p.add_argument(
        "--rect_conf",
        default=None,
        help='JSON conf overrides for every rectified row, e.g. \'{"dedup": {"enabled": false}}\'',
    )
    p.add_argument("--output", type=Path, help="also write the Markdown table here")
    p.add_argument(
        "--combine",
        nargs="+",
        metavar="LABEL=records.csv:method",
        help="only merge eval_strecha records into one table (see above)",
    )
    p.add_argument("--bin_deg", type=float, default=10.0, help="with --combine")
    p.add_argument(
        "--bin_by",
        choices=("gt_rot", "viewpoint"),
        default="gt_rot",
        help="with --combine: bins of GT rotation or of viewpoint change (wide scenes)",
    )
    p.add_argument(
        "--baseline",
        metavar="LABEL",
        help="with --combine: also pair every other row against this one",
    )
    p.add_argument(
        "--timing",
        nargs="+",
        type=Path,
        metavar="SCENE",
        help="only time plain SIFT and the depth-free modes on Strecha scenes",
    )
    p.add_argument("--num_images", type=int, default=3, help="with --timing, per scene")
    args = p.parse_args(argv)
    if args.depth_model_vp and not args.depth_model:
        p.error("--depth_model_vp needs --depth_model")
    logging.basicConfig(level=logging.INFO, format="[%(asctime)s %(name)s] %(message)s")
    if args.timing:
        text = timing(args.timing, args.num_images, args.max_num_features)
    elif args.combine:
        text = combine(args.combine, args.bin_deg, args.baseline, args.bin_by)
    else:
        text = run(args)
    print(text)
    if args.output:
        args.output.parent.mkdir(parents=True, exist_ok=True)
        args.output.write_text(text)
    return 0


if __name__ == "__main__":
    sys.exit(run_script(main, "eval_vp"))
