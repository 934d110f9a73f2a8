"""Write step of extraction: everything that goes into the outputs, in the caller's process.

:class:`Writer` takes each run outcome as it arrives and commits the image on its own (its
camera when new, its row and features in one database transaction; a staged HDF5 group),
then draws its pictures with ``visualize``. :func:`copy_db_to_h5` and
:func:`copy_h5_to_db` give an image that has features in one output the same features in
the other (called by the plan step, rectified_colmap.extraction.plan).
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pycolmap

from ..features import Features
from ..sift import MIN_SIFT_SIDE
from ..io import hloc_h5
from ..io.images import ImageError
from ..io.lock import check_writable
from ..viz import save_visualizations
from .summary import Summary

logger = logging.getLogger(__package__)


def check_outputs(database: Path | None, hloc_features: Path | None) -> None:
    """One-line errors, before anything runs, for outputs that cannot be written."""
    for path, what in ((database, "database"), (hloc_features, "feature file")):
        if path is not None:
            check_writable(path, what)


def stored_precision(feats: Features) -> Features:
    """Keypoints and frames rounded to the float32 that a database stores, so that both
    outputs, and copies between them, hold bit-identical values however they were made."""

    def f32(a):
        return np.asarray(a, dtype=np.float32).astype(np.float64)

    return Features(f32(feats.keypoints), f32(feats.shapes), feats.descriptors, feats.patch)


def copy_db_to_h5(db, h5, name: str, image_id: int, camera: pycolmap.Camera, ours: bool):
    """The database's features of ``name``, as they are, into the hloc file (marked as
    ours when this extractor wrote them)."""
    h5.write(
        name,
        db.read_features(image_id),
        (camera.width, camera.height),
        extractor=hloc_h5.EXTRACTOR_NAME if ours else None,
    )


def copy_h5_to_db(db, h5, name: str, camera, ours: bool) -> None:
    """The hloc file's features of ``name`` into the database with ``camera`` (a
    PlannedCamera, whose ``camera_id`` is set when its row is new); ImageError when the
    file's image size is not the camera's."""
    arrays = hloc_h5.read(h5.path, name)  # read once: features and size
    feats = hloc_h5.features_from_arrays(arrays, f"{h5.path}: {name!r}")
    size = tuple(int(v) for v in arrays["image_size"])
    cam = camera.camera
    if size != (cam.width, cam.height):
        raise ImageError(
            f"{h5.path} says the image is {size[0]}x{size[1]}, "
            f"its camera is {cam.width}x{cam.height}"
        )
    _, camera.camera_id, _ = db.write_image(
        name,
        feats,
        cam,
        camera.prior,
        camera.camera_id,
        extractor=hloc_h5.EXTRACTOR_NAME if ours else None,
    )


class Writer:
    """Writes each run outcome (rectified_colmap.extraction.run.Outcome) into the outputs and
    the summary. ``cameras``: name -> PlannedCamera of the images to extract."""

    def __init__(
        self,
        db,
        h5,
        cameras: dict,
        summary: Summary,
        overwrite: bool,
        visualize: Path | None,
    ):
        self.db, self.h5, self.cameras, self.summary = db, h5, cameras, summary
        self.overwrite, self.visualize = overwrite, visualize

    def __call__(self, out) -> None:
        """Warnings and failure into the summary; else write, count, draw."""
        for w in out.warnings:
            self.summary.warn(out.name, w)
        if out.error is not None:
            self.summary.fail(out.name, out.error)
            return
        feats = stored_precision(out.result.features)
        if len(feats) == 0:  # not recorded as done: a later run tries it again
            self.summary.fail(out.name, self._no_features(out.name))
            return
        if not self._write(out.name, feats):
            return
        self._count(out.name, feats)
        if self.visualize is not None:
            self._draw(out)

    def _write(self, name: str, feats: Features) -> bool:
        """Commit the image to each output; False (and a failure) when that fails."""
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
            self.summary.fail(name, f"writing features: {type(e).__name__}: {e}")
            return False
        return True

    def _no_features(self, name: str) -> str:
        """Why an image yielded no features, in one line."""
        cam = self.cameras[name].camera
        if min(cam.width, cam.height) < MIN_SIFT_SIDE:
            return (
                f"no features: the image is {cam.width}x{cam.height}, SIFT needs at least "
                f"{MIN_SIFT_SIDE} pixels a side; nothing written"
            )
        return "no features: SIFT found none (blank, featureless or fully masked image); " + (
            "nothing written"
        )

    def _count(self, name: str, feats: Features) -> None:
        summary = self.summary
        summary.done.append(name)
        summary.num_keypoints += len(feats)
        if not (feats.patch >= 0).any():
            summary.plain.append(name)

    def _draw(self, out) -> None:
        """The image's PNGs, from the pixels the worker decoded (never read again)."""
        try:
            camera = self.cameras[out.name].camera
            save_visualizations(Path(self.visualize), out.name, out.rgb, camera, out.result)
        except Exception as e:  # a picture must never fail the extraction
            logger.warning("%s: visualisation failed: %s", out.name, e)
