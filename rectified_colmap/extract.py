"""A folder of images -> rectified SIFT in a COLMAP database and/or an hloc feature file.

This is the Python API behind ``rectified-colmap extract``::

    from rectified_colmap.extract import extract
    summary = extract(Path("images"), database=Path("db.db"), hloc_features=Path("f.h5"),
                      depth_path=Path("depths"))

Image names are paths relative to ``image_dir`` with '/' separators, as COLMAP stores them.
Cameras come, in this order, from the database (an image already there keeps its camera),
from ``camera_model``/``camera_params``, or from EXIF (pycolmap.infer_camera_from_image).
Depth comes from a file under ``depth_path`` when there is one, else from the depth network
(``depth_model``, the embedded default unless "none"), else the image gets plain SIFT.

Users' data is never lost or silently changed (docs/usage.md "What is written, and when"):

- Everything that can be checked is checked before anything is written (image folder,
  camera model and parameters, depth folder, depth model, output paths writable, output
  files valid), and reported in one line naming the file and the cause.
- Outputs are only added to. Without ``overwrite`` an image that already has features in
  one output is never re-extracted: if the other output lacks it, that one gets a copy of
  the same features (database -> hloc file or back), whoever extracted them. Features that
  another extractor wrote (e.g. ``colmap feature_extractor``) are kept and reported once.
  ``overwrite`` re-extracts, and announces at WARNING how many match and two-view geometry
  rows that deletes.
- One writer per output file (a lock, rectified_colmap.io.lock): a second run on the same
  files waits for the first, then resumes after it.
- Every image is committed on its own: its camera (when new), its row and its features in
  one database transaction, a staged HDF5 group. An interrupted run leaves valid files and
  a failed image leaves no row behind. Per-image problems (unreadable or truncated image,
  unusable depth) are reported with the image's name relative to ``image_dir``, listed in
  the summary, and the run goes on; ``Summary.ok`` is False when any image failed.
"""

from __future__ import annotations

import logging
import os
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import pycolmap
from tqdm import tqdm

from . import camera as cam_utils
from .config import DEFAULT_CAMERA_MODEL, DEFAULT_DEPTH_MODEL, DEFAULT_PNG_SCALE, ExtractConf
from .features import Features
from .io.images import ImageError, decode_image, image_size, list_images, read_image
from .pipeline import ImageResult, extract_image

logger = logging.getLogger(__name__)


@dataclass
class Summary:
    done: list[str] = field(default_factory=list)
    """Images extracted in this run."""
    copied: dict[str, str] = field(default_factory=dict)
    """Images whose existing features were copied into the output that lacked them:
    name -> "database -> hloc" or "hloc -> database"."""
    skipped: list[str] = field(default_factory=list)
    """Images that already had features in every output."""
    failed: dict[str, str] = field(default_factory=dict)
    warnings: dict[str, list[str]] = field(default_factory=dict)
    plain: list[str] = field(default_factory=list)
    """Images that got plain SIFT (no depth or no usable plane)."""
    foreign: dict[str, int] = field(default_factory=dict)
    """Output path -> number of listed images whose features another extractor wrote."""
    deleted_matches: tuple[int, int] = (0, 0)
    """(match rows, two-view geometry rows) deleted by ``overwrite``."""
    num_keypoints: int = 0
    seconds: float = 0.0
    work_seconds: float = 0.0
    """Seconds spent extracting (after planning and copies): the throughput's base."""

    @property
    def ok(self) -> bool:
        return not self.failed

    def warn(self, name: str, message: str) -> None:
        self.warnings.setdefault(name, []).append(message)
        logger.warning("%s: %s", name, message)

    def report(self) -> str:
        n = len(self.done)
        lines = [
            f"images: {n} extracted, {len(self.copied)} copied between outputs, "
            f"{len(self.skipped)} skipped (already had features), "
            f"{len(self.failed)} failed",
            f"keypoints: {self.num_keypoints} ({self.num_keypoints / max(n, 1):.0f} per "
            f"image); {len(self.plain)} image(s) with plain SIFT only",
            f"time: {self.seconds:.1f} s ({self.seconds / max(n, 1):.2f} s per image, "
            f"{n / self.work_seconds if self.work_seconds > 0 else 0:.2f} images/s "
            "while extracting)",
        ]
        lines += [
            f"kept {k} image(s) with features from another extractor in {path}"
            for path, k in self.foreign.items()
            if k
        ]
        if any(self.deleted_matches):
            lines.append(
                f"deleted {self.deleted_matches[0]} match and "
                f"{self.deleted_matches[1]} two-view geometry rows (--overwrite)"
            )
        lines += [f"WARNING {name}: {w}" for name, ws in self.warnings.items() for w in ws]
        lines += [f"FAILED {name}: {why}" for name, why in self.failed.items()]
        return "\n".join(lines)


# ---------------------------------------------------------------------------------------
# Worker side: one image, no shared state but the depth sources (built once per process).

_WORKER: dict = {}


def quiet_pycolmap() -> None:
    """pycolmap's INFO lines (one per SIFT extractor) would interleave with the progress
    bar; keep its warnings unless our own log level is DEBUG."""
    if logging.getLogger("rectified_colmap").getEffectiveLevel() > logging.DEBUG:
        pycolmap.logging.minloglevel = max(int(pycolmap.logging.minloglevel), 1)


def _depth_sources(depth_path, depth_kind, png_scale, depth_model, model_threads) -> dict:
    """{"files": FileDepthSource | None, "network": OnnxDepthSource | None}; raises with a
    one-line message naming the folder or model when one cannot be used."""
    sources = {"files": None, "network": None}
    if depth_path is not None:
        from .depth.files import FileDepthSource

        sources["files"] = FileDepthSource(depth_path, kind=depth_kind, png_scale=png_scale)
    if depth_model not in (None, "none"):
        from .depth.registry import load_depth_source

        try:
            sources["network"] = load_depth_source(depth_model, num_threads=model_threads)
        except Exception as e:  # unknown name, missing or corrupt file, onnxruntime errors
            msg = str(e)
            if str(depth_model) not in msg:
                msg = f"depth model {depth_model}: {msg}"
            raise ValueError(f"--depth_model: {msg}") from e
    return sources


def _init_worker(
    depth_path, depth_kind, png_scale, depth_model, model_threads, sources: dict | None = None
):
    cv2.setNumThreads(1)
    quiet_pycolmap()
    _WORKER.clear()
    _WORKER.update(
        sources
        if sources is not None
        else _depth_sources(depth_path, depth_kind, png_scale, depth_model, model_threads)
    )


def _process(
    name: str, path: Path, camera: pycolmap.Camera, conf: ExtractConf, keep_details: bool
) -> tuple[str, ImageResult | None, str, str | None, list[str]]:
    """-> (name, result, depth origin, error message, warnings); messages without the
    image's name (the caller adds it)."""
    warnings: list[str] = []
    try:
        rgb, warnings = decode_image(path)
        H, W = rgb.shape[:2]
        if (W, H) != (camera.width, camera.height):
            raise ImageError(f"image is {W}x{H} but its camera is {camera.width}x{camera.height}")
        depth, origin = None, "none"
        for kind in ("files", "network"):
            source = _WORKER.get(kind)
            if depth is None and source is not None:
                depth = source(rgb, camera, name)
                problem = None if depth is None else depth.problem()
                if problem is not None:
                    what = "depth file" if kind == "files" else "depth network"
                    warnings.append(f"unusable depth from the {what} ({problem}): ignored")
                    depth = None
                origin = kind if depth is not None else origin
        seed = int.from_bytes(name.encode()[-8:].rjust(8, b"\0"), "little") % (2**32)
        result = extract_image(rgb, camera, depth, conf, np.random.default_rng(seed))
        if not keep_details:
            result = ImageResult(result.features, timings=result.timings)
        return name, result, origin, None, warnings
    except Exception as e:  # reported per image; the run goes on
        logger.debug("failure on %s", name, exc_info=True)
        msg = str(e) if isinstance(e, ImageError) else f"{type(e).__name__}: {e}"
        return name, None, "none", msg, warnings


# ---------------------------------------------------------------------------------------
# Cameras


@dataclass
class _Camera:
    """A camera of the run; ``camera_id`` stays None until its first image is written
    (the camera row goes into that image's transaction: no orphan camera rows)."""

    camera: pycolmap.Camera
    prior: bool
    camera_id: int | None = None


def _new_camera(path: Path, model: str | None, params: list[float] | None) -> _Camera:
    if model and params:
        w, h = image_size(path)
        return _Camera(cam_utils.make_camera(model, params, w, h), True)
    if not path.is_file():
        raise ImageError("no such image file")
    try:
        cam, has_prior = cam_utils.infer_camera(path, model or DEFAULT_CAMERA_MODEL)
    except ValueError:
        raise ImageError("cannot decode image (corrupt or unsupported format)") from None
    return _Camera(cam, has_prior)


def _check_camera_args(camera_model: str | None, camera_params) -> None:
    """One-line errors for a bad --camera_model / --camera_params before anything runs."""
    if camera_params and not camera_model:
        raise ValueError("--camera_params needs --camera_model")
    if camera_model:
        cam_utils.num_params(camera_model)  # raises for an unknown model
        if camera_params:
            cam_utils.make_camera(camera_model, camera_params, 100, 100)


# ---------------------------------------------------------------------------------------


def extract(
    image_dir: Path,
    database: Path | None = None,
    hloc_features: Path | None = None,
    image_list: Path | list[str] | None = None,
    depth_path: Path | None = None,
    depth_kind: str = "depth",
    png_scale: float = DEFAULT_PNG_SCALE,
    depth_model: str | None = DEFAULT_DEPTH_MODEL,
    camera_model: str | None = None,
    camera_params: list[float] | str | None = None,
    single_camera: bool = False,
    conf: ExtractConf | dict | None = None,
    num_workers: int = 1,
    overwrite: bool = False,
    visualize: Path | None = None,
    progress: bool = True,
    shard: str | tuple[int, int] | None = None,
    ray_address: str | None = None,
) -> Summary:
    """Extract rectified SIFT for a folder of images; see the module docstring.

    ``shard`` ("i/n" or (i, n)): only this job's share of the images
    (rectified_colmap.distributed.shard_names); merge the shards' outputs with
    rectified_colmap.io.merge. ``ray_address``: run the per-image work as Ray actors on
    that cluster ("local": a local Ray instance); ``num_workers`` actors, or one per CPU
    of the cluster when it is 1. Results are written here, by the caller's process.

    Raises (one-line message naming the file and the cause) before writing anything when
    an argument, an input folder, the depth model or an output cannot be used."""
    if database is None and hloc_features is None:
        raise ValueError("nothing to write: give a database and/or an hloc feature file")
    conf = conf if isinstance(conf, ExtractConf) else ExtractConf.from_dict(conf)
    if isinstance(camera_params, str):
        camera_params = cam_utils.parse_camera_params(camera_params)
    _check_camera_args(camera_model, camera_params)
    image_dir = Path(image_dir)
    names = list_images(image_dir, image_list)
    if shard is not None:
        from .distributed import parse_shard, shard_names

        index, count = parse_shard(shard)
        names = shard_names(names, index, count)
        logger.info("shard %d/%d: %d image(s)", index, count, len(names))
    summary = Summary()
    t_start = time.perf_counter()
    if depth_path is None and depth_model in (None, "none") and not conf.vp.depth_free:
        logger.warning(
            "no depth source (no --depth_path, --depth_model none): every image gets plain SIFT"
        )

    from .io.colmap_db import ColmapDatabase
    from .io.hloc_h5 import HlocFeatureWriter
    from .io.lock import check_writable

    for path, what in ((database, "database"), (hloc_features, "feature file")):
        if path is not None:
            check_writable(path, what)
    parallel = num_workers > 1 or ray_address is not None
    init = (
        None if depth_path is None else Path(depth_path).absolute(),
        depth_kind,
        png_scale,
        depth_model,
        1 if parallel else None,
    )
    sources = _depth_sources(*init)  # fails here, before any output is touched
    if ray_address is not None:
        from .distributed import RayRunner

        runner = RayRunner(ray_address, num_workers, init)  # fails here without Ray
    elif num_workers > 1:
        runner = _pool_runner(num_workers, init)
    else:
        runner = _here_runner(init, sources)
    if parallel:
        sources = None  # each worker loads its own

    h5 = db = None
    try:
        h5 = HlocFeatureWriter(hloc_features) if hloc_features is not None else None
        db = ColmapDatabase(database) if database is not None else None
        todo = _plan(
            names, image_dir, db, h5, camera_model, camera_params, single_camera, overwrite, summary
        )
        jobs = [(n, image_dir.absolute() / n, c.camera) for n, c in todo.items()]
        bar = tqdm(total=len(todo), desc="rectified SIFT", unit="img", disable=not progress)
        store = _Store(db, h5, todo, summary, overwrite, visualize, image_dir)
        t_work = time.perf_counter()
        for out in runner(jobs, conf, visualize is not None):  # in the order of ``jobs``
            store(out)
            bar.update()
        bar.close()
        summary.work_seconds = time.perf_counter() - t_work
    finally:
        _WORKER.clear()
        if hasattr(runner, "close"):
            runner.close()
        if h5 is not None:
            h5.close()
        if db is not None:
            db.close()
    summary.seconds = time.perf_counter() - t_start
    return summary


Job = tuple  # (name, absolute image path, pycolmap.Camera)


def _here_runner(init: tuple, sources: dict):
    """Runs the jobs in this process; yields _process results in job order."""

    def run(jobs: list[Job], conf: ExtractConf, keep: bool):
        _init_worker(*init, sources=sources)
        for name, path, camera in jobs:
            yield _process(name, path, camera, conf, keep)

    return run


def _pool_runner(num_workers: int, init: tuple):
    """Runs the jobs in ``num_workers`` local processes; yields results in job order."""

    def run(jobs: list[Job], conf: ExtractConf, keep: bool):
        if len(jobs) <= 1:
            yield from _here_runner(init, None)(jobs, conf, keep)
            return
        os.environ.setdefault("OMP_NUM_THREADS", "1")
        with ProcessPoolExecutor(num_workers, initializer=_init_worker, initargs=init) as ex:
            futures = [ex.submit(_process, n, p, c, conf, keep) for n, p, c in jobs]
            for fut in futures:
                yield fut.result()

    return run


def _plan(
    names: list[str],
    image_dir: Path,
    db,
    h5,
    camera_model,
    camera_params,
    single_camera: bool,
    overwrite: bool,
    summary: Summary,
) -> dict[str, _Camera]:
    """Decide per image: skip, copy between outputs (done here), or extract.

    Returns the images to extract with their cameras."""
    from .io import hloc_h5

    todo: dict[str, _Camera] = {}
    shared: _Camera | None = None
    guessed: list[str] = []
    cameras: dict[int, _Camera] = {}  # database cameras by id
    ours = db.ours() if db is not None else set()
    foreign_h5 = h5.foreign() if h5 is not None else set()
    foreign_db: list[str] = []
    foreign_in_h5: list[str] = []
    replaced: list[int] = []
    for name in names:
        path = image_dir / name
        try:
            found = db.find_image(name) if db is not None else None
            in_db = found is not None and db.has_features(found[0])
            in_h5 = h5 is not None and h5.has(name)
            if in_db and found[0] not in ours:
                foreign_db.append(name)
            if in_h5 and name in foreign_h5:
                foreign_in_h5.append(name)
            if found is not None and found[1] not in cameras:
                cam = db.get_camera(found[1])
                cameras[found[1]] = _Camera(cam, cam.has_prior_focal_length, found[1])
            if found is not None and single_camera and shared is None:  # resumed run
                shared = cameras[found[1]]
            if not overwrite:
                if (db is None or in_db) and (h5 is None or in_h5):
                    summary.skipped.append(name)
                    continue
                if in_db:  # the hloc file lacks it: the database's features, as they are
                    cam = cameras[found[1]].camera
                    h5.write(
                        name,
                        db.read_features(found[0]),
                        (cam.width, cam.height),
                        extractor=hloc_h5.EXTRACTOR_NAME if found[0] in ours else None,
                    )
                    summary.copied[name] = "database -> hloc"
                    continue
            elif in_db:
                replaced.append(found[0])
            if found is not None:
                camera = cameras[found[1]]
            elif single_camera and shared is not None:
                camera = shared
                w, h = image_size(path)
                if (w, h) != (camera.camera.width, camera.camera.height):
                    raise ImageError(
                        f"{w}x{h} differs from the single camera's "
                        f"{camera.camera.width}x{camera.camera.height}"
                    )
            else:
                camera = _new_camera(path, camera_model, camera_params)
                if not camera.prior:
                    guessed.append(name)
                if single_camera:
                    shared = camera
            if in_h5 and not overwrite:  # the database lacks it: the hloc file's features
                arrays = hloc_h5.read(h5.path, name)  # read once: features and size
                feats = hloc_h5.features_from_arrays(arrays, f"{h5.path}: {name!r}")
                size = tuple(int(v) for v in arrays["image_size"])
                if size != (camera.camera.width, camera.camera.height):
                    raise ImageError(
                        f"{h5.path} says the image is {size[0]}x{size[1]}, "
                        f"its camera is {camera.camera.width}x"
                        f"{camera.camera.height}"
                    )
                _, camera.camera_id, _ = db.write_image(
                    name,
                    feats,
                    camera.camera,
                    camera.prior,
                    camera.camera_id,
                    extractor=None if name in foreign_h5 else hloc_h5.EXTRACTOR_NAME,
                )
                summary.copied[name] = "hloc -> database"
                continue
            todo[name] = camera
        except Exception as e:
            logger.debug("planning %s", name, exc_info=True)
            summary.failed[name] = (
                str(e) if isinstance(e, ImageError) else f"{type(e).__name__}: {e}"
            )
            logger.error("%s: %s", name, summary.failed[name])
    if guessed:
        logger.warning(
            "%d image(s) have no focal length in EXIF (%s%s): guessing 1.2 x the "
            "larger side, as COLMAP does. Pass --camera_model/--camera_params "
            "for better planes.",
            len(guessed),
            ", ".join(guessed[:3]),
            ", ..." if len(guessed) > 3 else "",
        )
    for output, found in ((db, foreign_db), (h5, foreign_in_h5)):
        if found:
            summary.foreign[str(output.path)] = len(found)
            if not overwrite:
                logger.warning(
                    "%s: %d image(s) have features from another extractor (%s%s); "
                    "kept as they are (--overwrite replaces them)",
                    output.path,
                    len(found),
                    ", ".join(found[:3]),
                    ", ..." if len(found) > 3 else "",
                )
    if replaced:
        n_matches, n_geoms = db.count_matches(replaced)
        summary.deleted_matches = (n_matches, n_geoms)
        if n_matches or n_geoms:
            logger.warning(
                "--overwrite: re-extracting %d image(s) of %s deletes %d match and "
                "%d two-view geometry rows that refer to their old keypoints",
                len(replaced),
                db.path,
                n_matches,
                n_geoms,
            )
    return todo


def _stored_precision(feats: Features) -> Features:
    """Keypoints and frames rounded to the float32 that a database stores, so that both
    outputs, and copies between them, hold bit-identical values however they were made."""

    def f32(a):
        return np.asarray(a, dtype=np.float32).astype(np.float64)

    return Features(f32(feats.keypoints), f32(feats.shapes), feats.descriptors, feats.patch)


class _Store:
    """Writes one worker result into the outputs (main process)."""

    def __init__(
        self,
        db,
        h5,
        cameras: dict[str, _Camera],
        summary: Summary,
        overwrite: bool,
        visualize: Path | None,
        image_dir: Path,
    ):
        self.db, self.h5, self.cameras, self.summary = db, h5, cameras, summary
        self.overwrite, self.visualize, self.image_dir = overwrite, visualize, image_dir

    def __call__(self, out) -> None:
        name, result, origin, error, warnings = out
        summary = self.summary
        for w in warnings:
            summary.warn(name, w)
        if error is not None:
            summary.failed[name] = error
            logger.error("%s: %s", name, error)
            return
        feats = _stored_precision(result.features)
        cam = self.cameras[name]
        try:
            if self.db is not None:
                _, cam.camera_id, _ = self.db.write_image(
                    name, feats, cam.camera, cam.prior, cam.camera_id, overwrite=self.overwrite
                )
            if self.h5 is not None:
                self.h5.write(
                    name, feats, (cam.camera.width, cam.camera.height), overwrite=self.overwrite
                )
        except Exception as e:
            logger.debug("writing %s", name, exc_info=True)
            summary.failed[name] = f"writing features: {type(e).__name__}: {e}"
            logger.error("%s: %s", name, summary.failed[name])
            return
        summary.done.append(name)
        summary.num_keypoints += len(feats)
        if not (feats.patch >= 0).any():
            summary.plain.append(name)
        if self.visualize is not None and result.planes is not None:
            from .viz import save_visualizations

            try:
                save_visualizations(
                    Path(self.visualize),
                    name,
                    read_image(self.image_dir / name),
                    cam.camera,
                    result,
                )
            except Exception as e:  # a picture must never fail the extraction
                logger.warning("%s: visualisation failed: %s", name, e)
