"""A folder of images -> rectified SIFT in a COLMAP database and/or an hloc feature file.

This is the Python API behind ``rectified-colmap extract``::

    from rectified_colmap.extraction import extract
    summary = extract(Path("images"), database=Path("db.db"), hloc_features=Path("f.h5"),
                      depth={"path": Path("depths")}, run={"num_workers": 2})

Image names are paths relative to ``image_dir`` with '/' separators, as COLMAP stores them.
Cameras come, in this order, from the database (an image already there keeps its camera),
from ``reader``'s camera_model/camera_params, or from EXIF (pycolmap.infer_camera_from_image).
Depth comes from a file under ``depth.path`` when there is one, else from the depth network
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

:func:`extract` checks everything, then plans (extraction.plan: images, cameras, what is done
already), runs (extraction.run: one worker per process decodes each image once and extracts)
and writes (extraction.write: each result as it arrives, in this process); extraction.summary
holds what it reports.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

from ..config import (
    DEFAULT_DEPTH_MODEL,
    DepthInputConf,
    ExtractConf,
    ReaderConf,
    RunConf,
    options,
)
from ..io.colmap_db import ColmapDatabase
from ..io.hloc_h5 import HlocFeatureWriter
from ..progress import progress_bar
from .plan import CameraArgs, plan, select_images
from .run import Job, WorkerInit, make_runner
from .summary import Summary
from .write import Writer, check_outputs

__all__ = ["DEFAULT_DEPTH_MODEL", "DepthInputConf", "ReaderConf", "RunConf", "Summary", "extract"]

logger = logging.getLogger(__name__)


def extract(
    image_dir: Path,
    database: Path | None = None,
    hloc_features: Path | None = None,
    conf: ExtractConf | dict | None = None,
    reader: ReaderConf | dict | None = None,
    depth: DepthInputConf | dict | None = None,
    run: RunConf | dict | None = None,
    overwrite: bool = False,
) -> Summary:
    """Extract rectified SIFT for a folder of images into ``database`` and/or
    ``hloc_features``; see the module docstring.

    ``conf``: the method (ExtractConf or a nested dict over the defaults, e.g.
    ``confs["rectsift-fast"]``); ``reader``: which images and their cameras, as COLMAP's
    ImageReaderOptions (ReaderConf or a dict: image_list, mask_path, camera_model,
    camera_params, single_camera, single_camera_per_folder, default_focal_length_factor);
    ``depth``: depth files and the network (DepthInputConf: path, kind, png_scale, model);
    ``run``: processes and pictures (RunConf: num_workers, shard "i/n", ray_address,
    progress, visualize). Results are written here, by the caller's process.

    Raises (one-line message naming the file and the cause) before writing anything when
    an argument, an input folder, the depth model or an output cannot be used."""
    if database is None and hloc_features is None:
        raise ValueError("nothing to write: give a database and/or an hloc feature file")
    conf = (conf if isinstance(conf, ExtractConf) else ExtractConf.from_dict(conf)).validate()
    reader, depth = options(ReaderConf, reader), options(DepthInputConf, depth)
    run = options(RunConf, run)
    cameras = CameraArgs.checked(reader)
    image_dir = Path(image_dir)
    names = select_images(image_dir, reader.image_list, run.shard)
    if reader.mask_path is not None and not Path(reader.mask_path).is_dir():
        raise FileNotFoundError(f"{reader.mask_path}: mask path is not a folder")
    summary, t_start = Summary(), time.perf_counter()
    if depth.path is None and depth.model in (None, "none"):
        logger.warning(
            "no depth source (no --depth_path, --depth_model none): every image gets plain SIFT"
        )
    check_outputs(database, hloc_features)
    init = WorkerInit.of(depth, run)
    runner = make_runner(init, run.num_workers, run.ray_address)  # fails on a bad depth source
    h5 = db = None
    try:
        h5 = HlocFeatureWriter(hloc_features) if hloc_features is not None else None
        if h5 is not None:  # exists from now on, as the database: also with no image
            h5.create_if_missing()
        db = ColmapDatabase(database) if database is not None else None
        todo = plan(names, image_dir, db, h5, cameras, overwrite, summary)
        writer = Writer(db, h5, todo, summary, overwrite, run.visualize)
        masks = Path(reader.mask_path).absolute() if reader.mask_path is not None else None
        summary.work_seconds = _run_and_write(
            runner, todo, image_dir, masks, conf, writer, run.progress
        )
    finally:
        for closable in (runner, h5, db):
            if hasattr(closable, "close"):
                closable.close()
    summary.seconds = time.perf_counter() - t_start
    return summary


def _run_and_write(
    runner, todo: dict, image_dir: Path, masks: Path | None, conf, writer: Writer, progress
) -> float:
    """Runs the planned images and writes each result as it comes (in plan order);
    returns the seconds it took. Log lines meanwhile go above the bar, never into its line."""
    jobs = [
        Job(n, image_dir.absolute() / n, c.camera, None if masks is None else masks / f"{n}.png")
        for n, c in todo.items()
    ]
    t_work = time.perf_counter()
    with progress_bar(
        total=len(jobs), desc="rectified SIFT", unit="img", disable=not progress
    ) as bar:
        for out in runner(jobs, conf, writer.visualize is not None):
            writer(out)
            bar.update()
    return time.perf_counter() - t_work
