"""Running the COLMAP executable for SfM evaluations: commands, timing, databases, models.

Shared by ``scripts/eval_colmap_sfm.py`` (all images of a scene) and
``scripts/eval_sparse_sfm.py`` (sparse subsets: :func:`parse_subset`, also
``scripts/eval_global_mapper.py``'s). Plain COLMAP SIFT is ``colmap
feature_extractor``; rectified SIFT is ``rectified-colmap extract`` run as a subprocess with
the same camera flags and budget.
"""

from __future__ import annotations

import json
import sqlite3
import subprocess
import time
from contextlib import contextmanager
from itertools import combinations
from pathlib import Path

import numpy as np
import pycolmap

from rectified_colmap.geometry import rotation_angle_deg

from .methods import parse_variants

VERIFIED = (2, 3, 4, 5, 6)  # CALIBRATED, UNCALIBRATED, PLANAR, PANORAMIC, PLANAR_OR_PANORAMIC


# -- subsets ------------------------------------------------------------------------------


def parse_subset(spec: str) -> slice:
    """``START::STEP`` (e.g. ``0::2``, ``1::2``, ``0::3``; ``0::1`` is all) -> a slice.
    Raises ValueError for anything else."""
    start, sep, step = spec.partition("::")
    if not sep or not start.isdigit() or not step.isdigit() or int(step) < 1:
        raise ValueError(f"subset {spec!r}: expected START::STEP, e.g. 0::2")
    return slice(int(start), None, int(step))


def subset_names(names: list[str], spec: str) -> list[str]:
    """The subset ``spec`` of the images ``names`` in name order."""
    return sorted(names)[parse_subset(spec)]


def subset_label(spec: str) -> str:
    return "all" if parse_subset(spec) == slice(0, None, 1) else spec


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


def copy_database(src: Path, dst: Path) -> None:
    """A copy of a SQLite database through SQLite's backup API (with what is still in its
    -wal file, which a file copy would miss)."""
    with connect(src) as a, connect(dst) as b:
        a.backup(b)


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


def parse_methods(methods: list[str], variants: list[str]) -> dict[str, str | dict | None]:
    """{method: spec} for :func:`conf_args`: ``sift`` (COLMAP's extractor) and ``rectsift``
    (the default) with no spec, other named configurations by name, ``NAME=JSON`` /
    ``NAME=CONF`` variants with their overrides (methods.parse_variants). Raises ValueError
    (one line) for a bad variant."""
    out: dict[str, str | dict | None] = {
        m: (None if m in ("sift", "rectsift") else m) for m in methods
    }
    out.update(parse_variants(variants, taken=tuple(out)))
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
