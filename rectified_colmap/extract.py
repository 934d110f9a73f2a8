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

Every image is committed on its own (database transaction, staged HDF5 group), so an
interrupted run leaves valid files and the next run resumes (images that already have
features are skipped unless ``overwrite``). A bad image is reported and skipped; the rest of
the work goes on.
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
from .config import ExtractConf
from .depth import DepthMap
from .pipeline import ImageResult, extract_image

logger = logging.getLogger(__name__)

IMAGE_EXTENSIONS = {".jpg", ".jpeg", ".png", ".tif", ".tiff", ".bmp", ".ppm", ".pgm", ".webp"}
DEFAULT_DEPTH_MODEL = "rectsift-lite0"


@dataclass
class Summary:
    done: list[str] = field(default_factory=list)
    skipped: list[str] = field(default_factory=list)
    failed: dict[str, str] = field(default_factory=dict)
    plain: list[str] = field(default_factory=list)
    """Images that got plain SIFT (no depth or no usable plane)."""
    num_keypoints: int = 0
    seconds: float = 0.0

    @property
    def ok(self) -> bool:
        return not self.failed

    def report(self) -> str:
        n = len(self.done)
        lines = [f"images: {n} done, {len(self.skipped)} skipped (already had features), "
                 f"{len(self.failed)} failed",
                 f"keypoints: {self.num_keypoints} ({self.num_keypoints / max(n, 1):.0f} per "
                 f"image); {len(self.plain)} image(s) with plain SIFT only",
                 f"time: {self.seconds:.1f} s ({self.seconds / max(n, 1):.2f} s per image)"]
        lines += [f"FAILED {name}: {why}" for name, why in self.failed.items()]
        return "\n".join(lines)


def list_images(image_dir: Path, image_list: Path | list[str] | None = None) -> list[str]:
    """Names (relative, '/'-separated) of the images to process, sorted like COLMAP."""
    image_dir = Path(image_dir)
    if not image_dir.is_dir():
        raise FileNotFoundError(f"image path {image_dir} is not a directory")
    if image_list is not None:
        if isinstance(image_list, (str, Path)):
            text = Path(image_list).read_text().splitlines()
            names = [ln.strip() for ln in text if ln.strip() and not ln.startswith("#")]
        else:
            names = list(image_list)
        return names
    names = [p.relative_to(image_dir).as_posix() for p in image_dir.rglob("*")
             if p.suffix.lower() in IMAGE_EXTENSIONS and p.is_file()]
    return sorted(names)


def read_image(path: Path) -> np.ndarray:
    """RGB uint8 (H, W, 3), EXIF orientation ignored (as COLMAP reads pixels)."""
    img = cv2.imread(str(path), cv2.IMREAD_COLOR | cv2.IMREAD_IGNORE_ORIENTATION)
    if img is None:
        if not Path(path).exists():
            raise FileNotFoundError(f"{path}: no such image file")
        raise ValueError(f"{path}: cannot decode image (corrupt or unsupported format)")
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


# ---------------------------------------------------------------------------------------
# Worker side: one image, no shared state but the depth sources (built once per process).

_WORKER: dict = {}


def quiet_pycolmap() -> None:
    """pycolmap's INFO lines (one per SIFT extractor) would interleave with the progress
    bar; keep its warnings unless our own log level is DEBUG."""
    if logging.getLogger("rectified_colmap").getEffectiveLevel() > logging.DEBUG:
        pycolmap.logging.minloglevel = max(int(pycolmap.logging.minloglevel), 1)


def _init_worker(depth_path, depth_kind, png_scale, depth_model, model_threads):
    cv2.setNumThreads(1)
    quiet_pycolmap()
    _WORKER.clear()
    _WORKER["files"] = None
    _WORKER["network"] = None
    if depth_path is not None:
        from .depth.files import FileDepthSource

        _WORKER["files"] = FileDepthSource(depth_path, kind=depth_kind, png_scale=png_scale)
    if depth_model not in (None, "none"):
        from .depth.registry import load_depth_source

        _WORKER["network"] = load_depth_source(depth_model, num_threads=model_threads)


def _process(name: str, path: Path, camera: pycolmap.Camera, conf: ExtractConf,
             keep_details: bool) -> tuple[str, ImageResult | None, str, str | None]:
    """-> (name, result, depth origin, error message)."""
    try:
        rgb = read_image(path)
        H, W = rgb.shape[:2]
        if (W, H) != (camera.width, camera.height):
            raise ValueError(f"{path}: image is {W}x{H} but its camera is "
                             f"{camera.width}x{camera.height}")
        depth, origin = None, "none"
        if _WORKER.get("files") is not None:
            depth = _WORKER["files"](rgb, camera, name)
            origin = "file" if depth is not None else origin
        if depth is None and _WORKER.get("network") is not None:
            depth = _WORKER["network"](rgb, camera, name)
            origin = "network" if depth is not None else origin
        seed = int.from_bytes(name.encode()[-8:].rjust(8, b"\0"), "little") % (2**32)
        result = extract_image(rgb, camera, depth, conf, np.random.default_rng(seed))
        if not keep_details:
            result = ImageResult(result.features, timings=result.timings)
        return name, result, origin, None
    except Exception as e:  # reported per image; the run goes on
        logger.debug("failure on %s", name, exc_info=True)
        return name, None, "none", f"{type(e).__name__}: {e}"


# ---------------------------------------------------------------------------------------
# Cameras


def _camera_for(path: Path, model: str | None, params: list[float] | None) -> tuple:
    if model and params:
        h, w = _image_size(path)
        return cam_utils.make_camera(model, params, w, h), True
    cam, has_prior = cam_utils.infer_camera(path, model or "SIMPLE_RADIAL")
    if not has_prior:
        logger.warning("%s: no focal length in EXIF; guessing %.1f px (1.2 x max side), as "
                       "COLMAP does. Pass --camera_params for better planes.",
                       path.name, cam.mean_focal_length())
    return cam, has_prior


def _image_size(path: Path) -> tuple[int, int]:
    img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE | cv2.IMREAD_IGNORE_ORIENTATION)
    if img is None:
        raise ValueError(f"{path}: cannot decode image")
    return img.shape[:2]


# ---------------------------------------------------------------------------------------


def extract(image_dir: Path, database: Path | None = None, hloc_features: Path | None = None,
            image_list: Path | list[str] | None = None, depth_path: Path | None = None,
            depth_kind: str = "depth", png_scale: float = 0.001,
            depth_model: str | None = DEFAULT_DEPTH_MODEL,
            camera_model: str | None = None, camera_params: list[float] | str | None = None,
            single_camera: bool = False, conf: ExtractConf | dict | None = None,
            num_workers: int = 1, overwrite: bool = False, visualize: Path | None = None,
            progress: bool = True) -> Summary:
    """Extract rectified SIFT for a folder of images; see the module docstring."""
    if database is None and hloc_features is None:
        raise ValueError("nothing to write: give a database and/or an hloc feature file")
    conf = conf if isinstance(conf, ExtractConf) else ExtractConf.from_dict(conf)
    if isinstance(camera_params, str):
        camera_params = cam_utils.parse_camera_params(camera_params)
    image_dir = Path(image_dir)
    names = list_images(image_dir, image_list)
    summary = Summary()
    t_start = time.perf_counter()
    if depth_path is None and depth_model in (None, "none") and not conf.vp.depth_free:
        logger.warning("no depth source (no --depth_path, --depth_model none): every image "
                       "gets plain SIFT")

    from .io.colmap_db import ColmapDatabase
    from .io.hloc_h5 import HlocFeatureWriter

    db = ColmapDatabase(database) if database is not None else None
    h5 = HlocFeatureWriter(hloc_features) if hloc_features is not None else None
    try:
        # 1. Cameras and the work list (main process: the database is ours alone).
        todo: list[tuple[str, Path, pycolmap.Camera, int | None]] = []
        shared_cam: tuple | None = None
        for name in names:
            path = image_dir / name
            try:
                image_id, camera = None, None
                if db is not None:
                    found = db.find_image(name)
                    if found is not None:
                        image_id = found[0]
                        camera = db.get_camera(found[1])
                        if single_camera and shared_cam is None:  # resumed run
                            shared_cam = (camera, camera.has_prior_focal_length, found[1])
                done_db = db is None or (image_id is not None and db.has_features(image_id))
                done_h5 = h5 is None or h5.has(name)
                if done_db and done_h5 and not overwrite:
                    summary.skipped.append(name)
                    continue
                if camera is None:
                    if not path.is_file():
                        raise FileNotFoundError(f"{path}: no such image file")
                    if single_camera and shared_cam is not None:
                        camera, prior, cam_id = shared_cam
                        h, w = _image_size(path)
                        if (w, h) != (camera.width, camera.height):
                            raise ValueError(f"{path}: {w}x{h} differs from the single "
                                             f"camera's {camera.width}x{camera.height}")
                    else:
                        camera, prior = _camera_for(path, camera_model, camera_params)
                        cam_id = db.add_camera(camera, prior) if db is not None else None
                        if single_camera:
                            shared_cam = (camera, prior, cam_id)
                    if db is not None:
                        image_id = db.add_image(name, cam_id)
                        camera.camera_id = cam_id
                todo.append((name, path, camera, image_id))
            except Exception as e:
                summary.failed[name] = f"{type(e).__name__}: {e}"
                logger.error("%s: %s", name, summary.failed[name])

        # 2. Features, in worker processes when asked.
        init = (depth_path, depth_kind, png_scale, depth_model, 1 if num_workers > 1 else None)
        keep = visualize is not None
        ids = {name: image_id for name, _, _, image_id in todo}
        cams = {name: camera for name, _, camera, _ in todo}
        bar = tqdm(total=len(todo), desc="rectified SIFT", unit="img", disable=not progress)
        if num_workers > 1 and len(todo) > 1:
            os.environ.setdefault("OMP_NUM_THREADS", "1")
            with ProcessPoolExecutor(num_workers, initializer=_init_worker, initargs=init) as ex:
                futures = [ex.submit(_process, n, p, c, conf, keep) for n, p, c, _ in todo]
                for fut in futures:
                    _store(fut.result(), db, h5, ids, cams, summary, overwrite, visualize,
                           image_dir)
                    bar.update()
        else:
            _init_worker(*init)
            for n, p, c, _ in todo:
                _store(_process(n, p, c, conf, keep), db, h5, ids, cams, summary, overwrite,
                       visualize, image_dir)
                bar.update()
        bar.close()
    finally:
        if h5 is not None:
            h5.close()
        if db is not None:
            db.close()
    summary.seconds = time.perf_counter() - t_start
    return summary


def _store(out, db, h5, ids, cams, summary: Summary, overwrite: bool, visualize, image_dir):
    name, result, origin, error = out
    if error is not None:
        summary.failed[name] = error
        logger.error("%s: %s", name, error)
        return
    feats = result.features
    camera = cams[name]
    try:
        if db is not None:
            db.write_features(ids[name], feats, overwrite=True)
        if h5 is not None:
            h5.write(name, feats, (camera.width, camera.height), overwrite=True)
    except Exception as e:
        summary.failed[name] = f"writing features: {type(e).__name__}: {e}"
        logger.error("%s: %s", name, summary.failed[name])
        return
    summary.done.append(name)
    summary.num_keypoints += len(feats)
    if not (feats.patch >= 0).any():
        summary.plain.append(name)
    if visualize is not None and result.planes is not None:
        from .viz import save_visualizations

        try:
            save_visualizations(Path(visualize), name, read_image(image_dir / name), camera,
                                result)
        except Exception as e:  # a picture must never fail the extraction
            logger.warning("%s: visualisation failed: %s", name, e)
