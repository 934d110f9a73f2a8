"""Plan step of extraction: which images, with which cameras, and what is already done.

:func:`select_images` lists the folder (or the list) and keeps this job's shard
(``--shard i/n``: the images whose name hashes to ``i`` modulo ``n``, :func:`shard_names`:
deterministic, independent of the order and of the other names, so adding images never
moves one between shards; each job writes its own outputs, ``rectified-colmap merge``
combines them: rectified_colmap.io.merge).
:func:`plan` goes once over the images against the outputs: an image with features in
every output is skipped; one with features in only one output gets a copy in the other
right away (rectified_colmap.extraction.write, never re-extracted, unless ``overwrite``); the
rest are returned with their cameras for the run step. Cameras come from the database (an
image already there keeps its camera), from ``camera_model``/``camera_params`` (the size
read from the file header, no decode) or from EXIF (pycolmap.infer_camera_from_image,
which reads the file itself).
"""

from __future__ import annotations

import hashlib
import logging
import re
from dataclasses import dataclass
from pathlib import Path

import pycolmap

from .. import camera as cam_utils
from ..config import DEFAULT_CAMERA_MODEL, ReaderConf
from ..io.images import IMAGE_EXTENSIONS, ImageError, image_size, list_images
from .summary import Summary, error_message
from .write import copy_db_to_h5, copy_h5_to_db

logger = logging.getLogger(__package__)


@dataclass
class PlannedCamera:
    """A camera of the run; ``camera_id`` stays None until its first image is written
    (the camera row goes into that image's transaction: no orphan camera rows)."""

    camera: pycolmap.Camera
    prior: bool
    camera_id: int | None = None


@dataclass(frozen=True)
class CameraArgs:
    """How new cameras are made, as COLMAP's --ImageReader options: ``model`` and ``params``;
    ``single``: one camera shared by all new images; ``per_folder``: one per folder;
    ``focal_factor``: the focal length guess (x the larger side) without EXIF."""

    model: str | None = None
    params: list[float] | None = None
    single: bool = False
    per_folder: bool = False
    focal_factor: float = 1.2

    @classmethod
    def checked(cls, reader: ReaderConf) -> CameraArgs:
        """From a ReaderConf: parses 'p1,p2,...' params; one-line errors for a bad
        --camera_model / --camera_params / focal factor, before anything runs."""
        model, params = reader.camera_model, reader.camera_params
        focal_factor = reader.default_focal_length_factor
        if isinstance(params, str):
            params = cam_utils.parse_camera_params(params)
        if params and not model:
            raise ValueError("--camera_params needs --camera_model")
        if model:
            cam_utils.num_params(model)  # raises for an unknown model
            if params:
                cam_utils.make_camera(model, params, 100, 100)
        if not focal_factor > 0:
            raise ValueError(f"--default_focal_length_factor must be positive, got {focal_factor}")
        single, per_folder = reader.single_camera, reader.single_camera_per_folder
        return cls(model, params, bool(single), bool(per_folder), float(focal_factor))

    def new_camera(self, path: Path) -> PlannedCamera:
        """The camera of a new image: from the params and the header's size, else as COLMAP
        makes it (EXIF or guessed focal length, ``model`` or COLMAP's default model)."""
        if self.model and self.params:
            w, h = image_size(path)
            return PlannedCamera(cam_utils.make_camera(self.model, self.params, w, h), True)
        if not path.is_file():
            raise ImageError("no such image file")
        try:
            cam, has_prior = cam_utils.infer_camera(
                path, self.model or DEFAULT_CAMERA_MODEL, self.focal_factor
            )
        except ValueError:
            raise ImageError("cannot decode image (corrupt or unsupported format)") from None
        return PlannedCamera(cam, has_prior)

    def group(self, name: str) -> str | None:
        """The key of the camera ``name`` shares (None: its own camera)."""
        if self.single:
            return ""
        if self.per_folder:
            return name.rsplit("/", 1)[0] if "/" in name else ""
        return None


def parse_shard(shard: str | tuple[int, int]) -> tuple[int, int]:
    """ "i/n" or (i, n) -> (i, n) with 0 <= i < n; ValueError with the accepted form."""
    if isinstance(shard, str):
        m = re.fullmatch(r"\s*(\d+)\s*/\s*(\d+)\s*", shard)
        if m is None:
            raise ValueError(
                f"--shard {shard!r}: expected INDEX/COUNT, e.g. 0/8 (INDEX from 0 to COUNT-1)"
            )
        shard = (int(m.group(1)), int(m.group(2)))
    index, count = (int(v) for v in shard)
    if count < 1 or not 0 <= index < count:
        raise ValueError(f"--shard {index}/{count}: INDEX must be in 0..COUNT-1")
    return index, count


def shard_of(name: str, count: int) -> int:
    """The shard (0..count-1) of an image name: first 8 bytes of its SHA-1, modulo count."""
    return int.from_bytes(hashlib.sha1(name.encode()).digest()[:8], "big") % count


def shard_names(names: list[str], index: int, count: int) -> list[str]:
    """The names of shard ``index`` of ``count``, in their given order."""
    return [n for n in names if shard_of(n, count) == index]


def select_images(
    image_dir: Path, image_list: Path | list[str] | None, shard: str | tuple[int, int] | None
) -> list[str]:
    """The names to process: the folder's images (or the list's), this shard's share.
    ValueError when there is nothing to process at all (an empty or wrong folder or list);
    a shard may get no image (its outputs are then valid and empty)."""
    names = list_images(image_dir, image_list)
    if not names:
        if image_list is not None:
            where = image_list if isinstance(image_list, (str, Path)) else "the image list"
            raise ValueError(f"{where}: no image names in it")
        raise ValueError(
            f"{image_dir}: no images found in the folder or its subfolders "
            f"({', '.join(sorted(IMAGE_EXTENSIONS))})"
        )
    if shard is not None:
        index, count = parse_shard(shard)
        names = shard_names(names, index, count)
        logger.info("shard %d/%d: %d image(s)", index, count, len(names))
    return names


def plan(
    names: list[str],
    image_dir: Path,
    db,
    h5,
    cameras: CameraArgs,
    overwrite: bool,
    summary: Summary,
) -> dict[str, PlannedCamera]:
    """Decide per image: skip, copy between outputs (done here), or extract. Per-image
    problems go to ``summary.failed``. Returns the images to extract with their cameras."""
    planner = _Planner(image_dir, db, h5, cameras, overwrite, summary)
    todo: dict[str, PlannedCamera] = {}
    for name in names:
        try:
            camera = planner.image(name)
        except Exception as e:
            logger.debug("planning %s", name, exc_info=True)
            summary.fail(name, error_message(e))
            continue
        if camera is not None:
            todo[name] = camera
    planner.report()
    return todo


def _first(names: list[str]) -> str:
    return ", ".join(names[:3]) + (", ..." if len(names) > 3 else "")


class _Planner:
    """The state of one pass of :func:`plan`: cameras met so far, and what its closing
    warnings report (guessed focal lengths, foreign features, matches to delete)."""

    def __init__(self, image_dir, db, h5, cameras: CameraArgs, overwrite, summary):
        self.image_dir, self.db, self.h5 = image_dir, db, h5
        self.args, self.overwrite, self.summary = cameras, overwrite, summary
        self.shared: dict[str, PlannedCamera] = {}  # by CameraArgs.group
        self.known: dict[int, PlannedCamera] = {}  # database cameras by id
        self.ours = db.ours() if db is not None else set()
        self.foreign_h5 = h5.foreign() if h5 is not None else set()
        self.guessed: list[str] = []
        self.foreign_db: list[str] = []
        self.foreign_in_h5: list[str] = []
        self.replaced: list[int] = []

    def image(self, name: str) -> PlannedCamera | None:
        """The camera to extract ``name`` with, or None when it is skipped or copied."""
        db, h5 = self.db, self.h5
        found = db.find_image(name) if db is not None else None  # (image_id, camera_id)
        in_db = found is not None and db.has_features(found[0])
        in_h5 = h5 is not None and h5.has(name)
        if in_db and found[0] not in self.ours:
            self.foreign_db.append(name)
        if in_h5 and name in self.foreign_h5:
            self.foreign_in_h5.append(name)
        if found is not None:
            known = self._db_camera(found[1])
            group = self.args.group(name)
            if group is not None:  # a resumed run: new images join this camera
                self.shared.setdefault(group, known)
        if not self.overwrite:
            if (db is None or in_db) and (h5 is None or in_h5):
                self.summary.skipped.append(name)
                return None
            if in_db:  # the hloc file lacks it: the database's features, as they are
                cam = self.known[found[1]].camera
                copy_db_to_h5(db, h5, name, found[0], cam, found[0] in self.ours)
                self.summary.copied[name] = "database -> hloc"
                return None
        elif in_db:
            self.replaced.append(found[0])
        camera = self.known[found[1]] if found is not None else self._new_camera(name)
        if in_h5 and not self.overwrite:  # the database lacks it: the hloc file's features
            copy_h5_to_db(db, h5, name, camera, name not in self.foreign_h5)
            self.summary.copied[name] = "hloc -> database"
            return None
        return camera

    def _db_camera(self, camera_id: int) -> PlannedCamera:
        """The database's camera ``camera_id``, read once."""
        if camera_id not in self.known:
            cam = self.db.get_camera(camera_id)
            self.known[camera_id] = PlannedCamera(cam, cam.has_prior_focal_length, camera_id)
        return self.known[camera_id]

    def _new_camera(self, name: str) -> PlannedCamera:
        """The camera of an image not in the database: the one its group shares (same size
        required) or a new one."""
        path = self.image_dir / name
        group = self.args.group(name)
        shared = self.shared.get(group) if group is not None else None
        if shared is not None:
            w, h = image_size(path)
            if (w, h) != (shared.camera.width, shared.camera.height):
                raise ImageError(
                    f"{w}x{h} differs from the shared camera's "
                    f"{shared.camera.width}x{shared.camera.height}"
                )
            return shared
        camera = self.args.new_camera(path)
        if not camera.prior:
            self.guessed.append(name)
        if group is not None:
            self.shared[group] = camera
        return camera

    def report(self) -> None:
        """The plan's warnings, each once for all images; the counts into the summary."""
        if self.guessed:
            logger.warning(
                "%d image(s) have no focal length in EXIF (%s): guessing %g x the "
                "larger side, as COLMAP does. Pass --camera_model/--camera_params "
                "for better planes.",
                len(self.guessed),
                _first(self.guessed),
                self.args.focal_factor,
            )
        for output, found in ((self.db, self.foreign_db), (self.h5, self.foreign_in_h5)):
            if found:
                self.summary.foreign[str(output.path)] = len(found)
                if not self.overwrite:
                    logger.warning(
                        "%s: %d image(s) have features from another extractor (%s); "
                        "kept as they are (--overwrite replaces them)",
                        output.path,
                        len(found),
                        _first(found),
                    )
        if self.replaced:
            self._report_replaced()

    def _report_replaced(self) -> None:
        """How many match rows re-extracting the replaced images deletes."""
        n_matches, n_geoms = self.db.count_matches(self.replaced)
        self.summary.deleted_matches = (n_matches, n_geoms)
        if n_matches or n_geoms:
            logger.warning(
                "--overwrite: re-extracting %d image(s) of %s deletes %d match and "
                "%d two-view geometry rows that refer to their old keypoints",
                len(self.replaced),
                self.db.path,
                n_matches,
                n_geoms,
            )
