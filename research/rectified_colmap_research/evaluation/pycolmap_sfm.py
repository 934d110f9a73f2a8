"""SfM through pycolmap 4.x for the mapper comparison: COLMAP 4's extractor, exhaustive
matcher, incremental mapper and global mapper (GLOMAP, merged into COLMAP 4), timed.

Used by ``scripts/eval_global_mapper.py``. Everything runs on the CPU with one thread
(``num_threads = 1``; the caller sets ``OMP_NUM_THREADS=1``) and a fixed random seed, so that
a run is repeatable and its seconds compare between methods. The global mapper's own default
is a GPU bundle adjustment; it is switched off here (the CPU build would only warn and fall
back to the CPU).

A subset of a scene is mapped from its own database (:func:`subset_database`): the scene's
matched database without the other images, their features, rig/frame rows and the pairs
that involve them. Matching and verification are per pair, so that equals matching the
subset alone, and every mapper of a subset reads the same database.
"""

from __future__ import annotations

import shutil
import time
from pathlib import Path

import numpy as np
import pycolmap

from rectified_colmap.io.colmap_schema import MAX_IMAGE_ID

from .colmap_sfm import connect, copy_database, rotation_errors

MAPPERS = ("incremental", "global", "global+calibration")
"""``incremental``: pycolmap.incremental_mapping (``colmap mapper``); ``global``:
pycolmap.global_mapping (``colmap global_mapper``); ``global+calibration``:
pycolmap.calibrate_view_graph (``colmap view_graph_calibrator``: focal lengths from the
fundamental matrices, every camera then marked as having a prior) on a copy of the
database, then the global mapper (its seconds include the calibration's)."""

MIN_MODEL_SIZE = 3
"""Smallest model either mapper keeps (the global mapper's default; the incremental one's
is 10, which would drop a model of every image of a 4-image subset)."""


def plain_features(
    database: Path,
    images: Path,
    camera_model: str,
    camera_params: list[float] | None,
    max_num_features: int,
) -> float:
    """COLMAP 4's feature extractor (pycolmap.extract_features, CPU, one thread) into a new
    ``database``: one camera for all images with ``camera_params``, else COLMAP's default
    cameras (EXIF or a guessed focal length). Returns its seconds."""
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = camera_model
    mode = pycolmap.CameraMode.AUTO
    if camera_params is not None:
        reader.camera_params = ",".join(f"{v:.6f}" for v in camera_params)
        mode = pycolmap.CameraMode.SINGLE
    opts = pycolmap.FeatureExtractionOptions()
    opts.num_threads = 1
    opts.sift.max_num_features = max_num_features
    t0 = time.perf_counter()
    pycolmap.extract_features(
        database,
        images,
        camera_mode=mode,
        reader_options=reader,
        extraction_options=opts,
        device=pycolmap.Device.cpu,
    )
    return time.perf_counter() - t0


def strip_features(database: Path) -> None:
    """Delete every image's features and matches (cameras, images, rigs and frames stay)."""
    with connect(database) as con:
        for table in ("keypoints", "descriptors", "matches", "two_view_geometries"):
            con.execute(f"DELETE FROM {table}")


def match(database: Path) -> float:
    """pycolmap.match_exhaustive (``colmap exhaustive_matcher``) on the CPU, one thread,
    COLMAP's default matching and verification; its seconds."""
    opts = pycolmap.FeatureMatchingOptions()
    opts.num_threads = 1
    t0 = time.perf_counter()
    pycolmap.match_exhaustive(database, matching_options=opts, device=pycolmap.Device.cpu)
    return time.perf_counter() - t0


def subset_database(matched: Path, names: list[str], out: Path) -> None:
    """``out``: a copy of the database ``matched`` with only the images ``names`` (their
    features, rig/frame rows and pairs among them); see the module docstring."""
    copy_database(matched, out)
    with connect(out) as con:
        ids = dict(con.execute("SELECT name, image_id FROM images"))
        drop = [(i,) for n, i in ids.items() if n not in set(names)]
        tables = {r[0] for r in con.execute("SELECT name FROM sqlite_master WHERE type='table'")}
        for table in ("images", "keypoints", "descriptors", "rectified_colmap_features"):
            if table in tables:
                con.executemany(f"DELETE FROM {table} WHERE image_id = ?", drop)
        base = MAX_IMAGE_ID  # COLMAP's pair id: smaller id x base + larger id
        for table in ("matches", "two_view_geometries"):
            con.executemany(
                f"DELETE FROM {table} WHERE pair_id / {base} = ? OR pair_id % {base} = ?",
                [(i, i) for (i,) in drop],
            )
        if "frame_data" in tables:
            con.executemany("DELETE FROM frame_data WHERE data_id = ? AND sensor_type = 0", drop)
            con.execute(
                "DELETE FROM frames WHERE frame_id NOT IN (SELECT frame_id FROM frame_data)"
            )
        con.execute("DELETE FROM cameras WHERE camera_id NOT IN (SELECT camera_id FROM images)")
        if "rigs" in tables:
            con.execute(
                "DELETE FROM rigs WHERE ref_sensor_type = 0 AND "
                "ref_sensor_id NOT IN (SELECT camera_id FROM cameras)"
            )


def _global_options(seed: int) -> pycolmap.GlobalPipelineOptions:
    opts = pycolmap.GlobalPipelineOptions()
    opts.num_threads = 1
    opts.random_seed = seed
    opts.min_model_size = MIN_MODEL_SIZE
    opts.mapper.global_positioning.use_gpu = False
    opts.mapper.bundle_adjustment.ceres.use_gpu = False
    return opts


def _incremental_options(seed: int) -> pycolmap.IncrementalPipelineOptions:
    opts = pycolmap.IncrementalPipelineOptions()
    opts.num_threads = 1
    opts.random_seed = seed
    opts.min_model_size = MIN_MODEL_SIZE
    return opts


def map_database(
    mapper: str, database: Path, images: Path, out: Path, seed: int
) -> tuple[pycolmap.Reconstruction | None, float]:
    """Map ``database`` with ``mapper`` (one of :data:`MAPPERS`) into ``out`` (emptied
    first): the model with the most registered images (None without one) and the seconds."""
    if mapper not in MAPPERS:
        raise ValueError(f"mapper {mapper!r}: expected one of {', '.join(MAPPERS)}")
    if out.exists():
        shutil.rmtree(out)
    out.mkdir(parents=True)
    t0 = time.perf_counter()
    if mapper == "incremental":
        models = pycolmap.incremental_mapping(
            database, images, out, options=_incremental_options(seed)
        )
    else:
        if mapper == "global+calibration":
            calibrated = out / "calibrated.db"
            copy_database(database, calibrated)
            opts = pycolmap.ViewGraphCalibrationOptions()
            opts.random_seed = seed
            pycolmap.calibrate_view_graph(calibrated, opts)
            database = calibrated
        models = pycolmap.global_mapping(database, images, out, options=_global_options(seed))
    seconds = time.perf_counter() - t0
    best = max(models.values(), key=lambda r: r.num_reg_images(), default=None)
    return best, seconds


def model_row(rec: pycolmap.Reconstruction | None, gt: pycolmap.Reconstruction | None) -> dict:
    """Registered images, 3D points, mean reprojection error and (with a ground truth) the
    median relative-rotation error of all pairs of registered images, in degrees."""
    nan = float("nan")
    if rec is None:
        return {"registered": 0, "points": 0, "reproj_px": nan, "rot_err_med_deg": nan}
    errs = rotation_errors(rec, gt) if gt is not None else np.array([])
    return {
        "registered": rec.num_reg_images(),
        "points": rec.num_points3D(),
        "reproj_px": rec.compute_mean_reprojection_error(),
        "rot_err_med_deg": float(np.median(errs)) if len(errs) else nan,
    }


def prior_focal_share(database: Path) -> float:
    """The share of the database's cameras that claim a prior focal length."""
    with connect(database) as con:
        rows = [r[0] for r in con.execute("SELECT prior_focal_length FROM cameras")]
    return float(np.mean(rows)) if rows else float("nan")
