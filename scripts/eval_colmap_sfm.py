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
import sqlite3
import subprocess
import sys
import time
from contextlib import contextmanager
from itertools import combinations
from pathlib import Path

import numpy as np
import pycolmap

from rectified_colmap.geometry import rotation_angle_deg
from rectified_colmap.errors import run_script

VERIFIED = (2, 3, 4, 5, 6)  # CALIBRATED, UNCALIBRATED, PLANAR, PANORAMIC, PLANAR_OR_PANORAMIC


def run(cmd: list[str], log: Path, allow: str | None = None) -> float:
    """Run ``cmd`` with its output appended to ``log``; wall seconds. Raises on failure,
    unless the failed command's output contains ``allow``."""
    t0 = time.perf_counter()
    with open(log, "a") as f:
        start = f.tell()
        f.write("$ " + " ".join(cmd) + "\n")
        f.flush()
        r = subprocess.run(cmd, stdout=f, stderr=subprocess.STDOUT)
    if r.returncode != 0:
        with open(log, errors="replace") as f:
            f.seek(start)
            if allow is None or allow not in f.read():
                raise RuntimeError(f"{cmd[0]} {cmd[1]} failed ({r.returncode}); see {log}")
    return time.perf_counter() - t0


@contextmanager
def connect(database: Path):
    """A connection to a COLMAP database, in one transaction, closed on exit: ``with
    sqlite3.connect()`` alone leaves it open until garbage collection, and an open connection
    keeps another process's writes in the -wal file (COLMAP's databases are in WAL mode),
    where a plain file copy misses them."""
    con = sqlite3.connect(database)
    try:
        with con:
            yield con
    finally:
        con.close()


def verified_matches(database: Path) -> tuple[int, int]:
    """(inlier matches, image pairs) of the two-view geometries COLMAP verified."""
    with connect(database) as con:
        rows = con.execute("SELECT rows, config FROM two_view_geometries").fetchall()
    ok = [r for r, c in rows if c in VERIFIED and r > 0]
    return int(sum(ok)), len(ok)


def rotation_errors(rec: pycolmap.Reconstruction, gt: pycolmap.Reconstruction) -> np.ndarray:
    """Angles (degrees) between estimated and ground-truth relative rotations of every pair
    of registered images (matched by name)."""
    gt_by_name = {im.name: im for im in gt.images.values()}
    ims = [im for im in rec.images.values() if im.name in gt_by_name]

    def rot(im):
        return im.cam_from_world().rotation.matrix()

    errs = []
    for a, b in combinations(ims, 2):
        r_est = rot(b) @ rot(a).T
        r_gt = rot(gt_by_name[b.name]) @ rot(gt_by_name[a.name]).T
        errs.append(rotation_angle_deg(r_est.T @ r_gt))
    return np.asarray(errs)


def best_model(sparse: Path) -> pycolmap.Reconstruction | None:
    models = [pycolmap.Reconstruction(d) for d in sorted(sparse.iterdir()) if d.is_dir()]
    return max(models, key=lambda r: r.num_reg_images(), default=None)


def pinhole_camera_args(gt: pycolmap.Reconstruction) -> list[str]:
    """COLMAP --ImageReader flags (also ``rectified-colmap extract``'s) for the ground
    truth's first camera as one PINHOLE camera shared by all images."""
    cam = next(iter(gt.cameras.values()))
    params = ",".join(f"{v:.6f}" for v in cam.params)
    return [
        "--ImageReader.camera_model",
        "PINHOLE",
        "--ImageReader.single_camera",
        "1",
        "--ImageReader.camera_params",
        params,
    ]


def sift_command(db: Path, images: Path, max_num_features: int, camera=()) -> list[str]:
    """``colmap feature_extractor`` on the CPU with ``camera`` (--ImageReader flags)."""
    return [
        "colmap",
        "feature_extractor",
        "--database_path",
        str(db),
        "--image_path",
        str(images),
        *camera,
        "--SiftExtraction.use_gpu",
        "0",
        "--SiftExtraction.max_num_features",
        str(max_num_features),
    ]


def rectified_command(
    db: Path, images: Path, max_num_features: int, num_workers: int, conf=(), camera=()
) -> list[str]:
    """``rectified-colmap extract`` with ``conf`` (see :func:`conf_args`) and ``camera``."""
    return [
        "rectified-colmap",
        "extract",
        "--database_path",
        str(db),
        "--image_path",
        str(images),
        *camera,
        "--max_num_features",
        str(max_num_features),
        "--no_progress",
        "--num_workers",
        str(num_workers),
        *conf,
    ]


def conf_args(spec: str | dict | None, work: Path) -> list[str]:
    """``--conf`` of a rectified method: none for the default, a named configuration as it
    is, JSON overrides (a dict or its text) through ``work/conf.json``."""
    from rectified_colmap.config import confs

    if spec is None:
        return []
    if isinstance(spec, str) and spec in confs:
        return ["--conf", spec]
    overrides = json.loads(spec) if isinstance(spec, str) else spec
    conf_file = work / "conf.json"
    conf_file.write_text(json.dumps(overrides))
    return ["--conf", str(conf_file)]


def parse_methods(methods: list[str], variants: list[str]) -> dict[str, str | None]:
    """{method: spec}: ``sift`` (COLMAP's extractor) and ``rectsift`` (the default) with no
    spec, other named configurations by name, ``NAME=JSON`` / ``NAME=CONF`` variants with
    theirs. Raises ValueError (one line) for a bad variant."""
    from rectified_colmap.config import confs

    out = {m: (None if m in ("sift", "rectsift") else m) for m in methods}
    for v in variants:
        name, sep, spec = v.partition("=")
        if not sep or not name or name in out:
            raise ValueError(f"--variant {v!r}: expected a new NAME=JSON or NAME=CONF")
        if spec not in confs:
            try:
                json.loads(spec)
            except json.JSONDecodeError as e:
                msg = f"--variant {name}: not a configuration name nor JSON ({e})"
                raise ValueError(msg) from None
        out[name] = spec
    return out


def match_and_map(
    db: Path, images: Path, sparse: Path, log: Path, mapper=(), match=True
) -> tuple[float, float]:
    """``colmap exhaustive_matcher`` (CPU; skipped with ``match=False``) and ``colmap
    mapper`` (one thread, plus the ``mapper`` flags) into ``sparse``; their wall seconds.
    A mapper that finds no model leaves ``sparse`` empty."""
    t_match = 0.0
    if match:
        t_match = run(
            [
                "colmap",
                "exhaustive_matcher",
                "--database_path",
                str(db),
                "--SiftMatching.use_gpu",
                "0",
            ],
            log,
        )
    sparse.mkdir(parents=True, exist_ok=True)
    t_map = run(
        [
            "colmap",
            "mapper",
            "--database_path",
            str(db),
            "--image_path",
            str(images),
            "--output_path",
            str(sparse),
            "--Mapper.num_threads",
            "1",
            *mapper,
        ],
        log,
        allow="failed to create sparse model",  # COLMAP 3.8's exit 1 for no model
    )
    return t_match, t_map


def model_stats(rec: pycolmap.Reconstruction | None) -> dict:
    """Registered images, 3D points, mean track length and reprojection error of a model
    (zeros and NaN without one)."""
    if rec is None:
        return {"registered": 0, "points": 0, "track_length": 0.0, "reproj_px": float("nan")}
    return {
        "registered": rec.num_reg_images(),
        "points": rec.num_points3D(),
        "track_length": rec.compute_mean_track_length(),
        "reproj_px": rec.compute_mean_reprojection_error(),
    }


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
    p.add_argument(
        "--variant",
        action="append",
        default=[],
        metavar="NAME=JSON|CONF",
        help="an extra rectified method: conf overrides as JSON, or a named configuration",
    )
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
