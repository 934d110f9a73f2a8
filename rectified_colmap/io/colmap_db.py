"""COLMAP database writer: cameras, images and features, one transaction per image.

Schema (rectified_colmap.io.colmap_schema): a new database gets COLMAP 3.8's layout with
what COLMAP/pycolmap 4.x adds when it migrates one; COLMAP 3.8 and pycolmap 4.2.1 both read
and write it. Databases made by either version are opened as they are and never migrated
here: every statement names its columns, ``type`` is written only where the column exists.

Rigs and frames. pycolmap 4.x accepts a database with no rig/frame rows (it makes one rig
per camera and one frame per image when loading) or with rows for every image, never a
mix. We write rig/frame rows for new images if and only if the database already uses them
(it has frames, or rigs but no images yet).

Data written per image (all in COLMAP conventions, see rectified_colmap.features):
- keypoints: (N, 6) float32 [x, y, a11, a12, a21, a22], centre of the top-left pixel at
  (0.5, 0.5);
- descriptors: (N, 128) uint8 RootSIFT at COLMAP's byte scale (L2 norm ~512), type SIFT.

Crash safety: every public write is one SQLite transaction that is committed before the
call returns, so a kill -9 leaves a valid database holding every image completed so far.
:meth:`ColmapDatabase.write_image` adds an image's camera (when new), its row and its
features in ONE transaction: a failed image leaves no row behind.

Provenance: the ids of the images whose features this tool wrote are kept in an extra
table ``rectified_colmap_features(image_id, extractor)``. COLMAP 3.8 and pycolmap 4.x
ignore tables they do not know, so images with features from another extractor (e.g.
``colmap feature_extractor``) are recognised and kept.

One writer at a time: a ColmapDatabase holds ``<path>.lock`` (rectified_colmap.io.lock)
while it is open; a second process waits for it. An empty file (0 bytes, or SQLite with
no tables) is initialised like COLMAP does.
"""

from __future__ import annotations

import logging
import sqlite3
from pathlib import Path

import numpy as np
import pycolmap

from ..features import Features, similarity_frames
from .colmap_schema import (
    _PROVENANCE_SQL,
    _REQUIRED,
    CAMERA_SENSOR,
    EXTRACTOR_NAME,
    MAX_COLMAP38_MODEL,
    MAX_IMAGE_ID,
    PROVENANCE_TABLE,
    SIFT_TYPE,
    Transaction,
    _init_schema,
    create_database,
    image_ids_to_pair_id,
)
from .lock import OutputLock, check_writable

__all__ = ["EXTRACTOR_NAME", "PROVENANCE_TABLE", "ColmapDatabase", "create_database"]
__all__ += ["image_ids_to_pair_id"]

logger = logging.getLogger(__name__)


class ColmapDatabase:
    """A COLMAP database opened for adding cameras, images and features.

    ``ColmapDatabase(path)`` creates the database if it does not exist, otherwise opens it
    as it is (made by COLMAP 3.8, 4.x, pycolmap or us). Use as a context manager or call
    :meth:`close`. Every method commits before it returns.
    """

    def __init__(self, path: Path | str, lock: bool = True):
        self.path = Path(path)
        self._con = None
        check_writable(self.path, "database")
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._lock = OutputLock(self.path) if lock else None
        if self._lock is not None:
            self._lock.acquire()
        try:
            self._open()
        except BaseException:
            self.close()
            raise

    def _open(self) -> None:
        for leftover in self.path.parent.glob(f"{self.path.name}.*.creating"):
            leftover.unlink(missing_ok=True)  # a creation killed before its rename
        if not self.path.exists():
            create_database(self.path)
            logger.info("created COLMAP database %s", self.path)
        try:
            self._con = sqlite3.connect(self.path, isolation_level=None, timeout=60.0)
            tables = {
                r[0]
                for r in self._con.execute("SELECT name FROM sqlite_master WHERE type = 'table'")
            }
            if not tables:  # an empty file (e.g. `touch db.db`): initialise it as COLMAP does
                _init_schema(self._con)
                logger.info("initialised empty database %s", self.path)
                tables = {
                    r[0]
                    for r in self._con.execute(
                        "SELECT name FROM sqlite_master WHERE type = 'table'"
                    )
                }
        except sqlite3.DatabaseError as e:
            raise ValueError(f"{self.path}: not a valid SQLite/COLMAP database ({e})") from e
        self._columns = {
            t: {r[1] for r in self._con.execute(f"PRAGMA table_info({t})")} for t in tables
        }
        for table, cols in _REQUIRED.items():
            missing = cols - self._columns.get(table, set())
            if missing:
                raise ValueError(
                    f"{self.path}: not a COLMAP database (table {table!r} lacks {sorted(missing)})"
                )
        self._has_type = "type" in self._columns["descriptors"]
        self._has_frames = {"rigs", "frames", "frame_data"} <= tables
        self._has_provenance = PROVENANCE_TABLE in tables

    # -- context manager ----------------------------------------------------------------
    def __enter__(self) -> "ColmapDatabase":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        if getattr(self, "_con", None) is not None:
            self._con.close()
            self._con = None
        if getattr(self, "_lock", None) is not None:
            self._lock.release()
            self._lock = None

    def _one(self, sql: str, args=()):
        return self._con.execute(sql, args).fetchone()

    def _transaction(self):
        return Transaction(self._con)

    # -- cameras --------------------------------------------------------------------------
    def add_camera(self, camera: pycolmap.Camera, prior_focal_length: bool) -> int:
        """Insert a camera (its camera_id is ignored) and return the new camera_id."""
        with self._transaction():
            return self._insert_camera(camera, prior_focal_length)

    def _insert_camera(self, camera: pycolmap.Camera, prior_focal_length: bool) -> int:
        model = int(camera.model.value)
        params = np.asarray(camera.params, dtype=np.float64)
        if not camera.verify_params() or not np.isfinite(params).all():
            raise ValueError(f"{self.path}: invalid {camera.model.name} parameters {params}")
        if model > MAX_COLMAP38_MODEL:
            logger.warning(
                "%s: camera model %s is unknown to COLMAP 3.8", self.path, camera.model.name
            )
        cur = self._con.execute(
            "INSERT INTO cameras(model, width, height, params, prior_focal_length) "
            "VALUES(?, ?, ?, ?, ?)",
            (
                model,
                int(camera.width),
                int(camera.height),
                params.tobytes(),
                int(bool(prior_focal_length)),
            ),
        )
        return int(cur.lastrowid)

    def find_camera(self, camera: pycolmap.Camera, prior_focal_length: bool) -> int | None:
        """Id of a camera row identical to ``camera`` (model, size, params, prior), or None:
        lets a resumed single-camera run reuse its camera."""
        params = np.asarray(camera.params, dtype=np.float64).tobytes()
        row = self._one(
            "SELECT camera_id FROM cameras WHERE model = ? AND width = ? AND "
            "height = ? AND params = ? AND prior_focal_length = ? "
            "ORDER BY camera_id LIMIT 1",
            (
                int(camera.model.value),
                int(camera.width),
                int(camera.height),
                params,
                int(bool(prior_focal_length)),
            ),
        )
        return None if row is None else int(row[0])

    def get_camera(self, camera_id: int) -> pycolmap.Camera:
        row = self._one(
            "SELECT model, width, height, params, prior_focal_length FROM cameras"
            " WHERE camera_id = ?",
            (int(camera_id),),
        )
        if row is None:
            raise KeyError(f"{self.path}: no camera with id {camera_id}")
        model, width, height, params, prior = row
        cam = pycolmap.Camera(
            model=pycolmap.CameraModelId(model),
            width=width,
            height=height,
            params=np.frombuffer(params, dtype=np.float64).copy(),
        )
        cam.camera_id = int(camera_id)
        cam.has_prior_focal_length = bool(prior)
        return cam

    def camera_ids(self) -> list[int]:
        return [r[0] for r in self._con.execute("SELECT camera_id FROM cameras ORDER BY 1")]

    # -- images ---------------------------------------------------------------------------
    def find_image(self, name: str) -> tuple[int, int] | None:
        """(image_id, camera_id) of the image called ``name``, or None."""
        row = self._one("SELECT image_id, camera_id FROM images WHERE name = ?", (name,))
        return None if row is None else (int(row[0]), int(row[1]))

    def uses_frames(self) -> bool:
        """Whether new images need rig/frame rows (see the module docstring)."""
        if not self._has_frames:
            return False
        if self._one("SELECT 1 FROM frames LIMIT 1") is not None:
            return True
        return (
            self._one("SELECT 1 FROM images LIMIT 1") is None
            and self._one("SELECT 1 FROM rigs LIMIT 1") is not None
        )

    def add_image(self, name: str, camera_id: int) -> int:
        """Insert an image (and its rig/frame rows where the database uses them)."""
        with self._transaction():
            return self._insert_image(name, camera_id)

    def _insert_image(self, name: str, camera_id: int) -> int:
        if not name or name.startswith("/") or "\\" in name:
            raise ValueError(
                f"{self.path}: image name {name!r} must be a relative path with '/' separators"
            )
        if self._one("SELECT 1 FROM cameras WHERE camera_id = ?", (int(camera_id),)) is None:
            raise KeyError(f"{self.path}: image {name!r}: no camera with id {camera_id}")
        frames = self.uses_frames()
        try:
            cur = self._con.execute(
                "INSERT INTO images(name, camera_id) VALUES(?, ?)", (name, int(camera_id))
            )
        except sqlite3.IntegrityError as e:
            raise ValueError(f"{self.path}: cannot add image {name!r} ({e})") from e
        image_id = int(cur.lastrowid)
        if frames:
            row = self._one(
                "SELECT rig_id FROM rigs WHERE ref_sensor_id = ? AND ref_sensor_type = ?",
                (int(camera_id), CAMERA_SENSOR),
            )
            if row is None:
                row = self._one(
                    "SELECT rig_id FROM rig_sensors WHERE sensor_id = ? AND sensor_type = ?",
                    (int(camera_id), CAMERA_SENSOR),
                )
            if row is None:
                rig_id = self._con.execute(
                    "INSERT INTO rigs(ref_sensor_id, ref_sensor_type) VALUES(?, ?)",
                    (int(camera_id), CAMERA_SENSOR),
                ).lastrowid
            else:
                rig_id = row[0]
            frame_id = self._con.execute(
                "INSERT INTO frames(rig_id) VALUES(?)", (rig_id,)
            ).lastrowid
            self._con.execute(
                "INSERT INTO frame_data(frame_id, data_id, sensor_id, "
                "sensor_type) VALUES(?, ?, ?, ?)",
                (frame_id, image_id, int(camera_id), CAMERA_SENSOR),
            )
        return image_id

    def image_names(self) -> dict[int, str]:
        return dict(self._con.execute("SELECT image_id, name FROM images"))

    # -- features -------------------------------------------------------------------------
    def has_features(self, image_id: int) -> bool:
        return (
            self._one(
                "SELECT 1 FROM keypoints k JOIN descriptors d USING(image_id) WHERE image_id = ?",
                (int(image_id),),
            )
            is not None
        )

    def image_ids_with_features(self) -> set[int]:
        return {
            r[0]
            for r in self._con.execute(
                "SELECT image_id FROM keypoints JOIN descriptors USING(image_id)"
            )
        }

    def ours(self) -> set[int]:
        """Ids of the images whose current features this tool wrote (provenance table)."""
        if not self._has_provenance:
            return set()
        return {r[0] for r in self._con.execute(f"SELECT image_id FROM {PROVENANCE_TABLE}")}

    def count_matches(self, image_ids) -> tuple[int, int]:
        """(match rows, two-view geometry rows) that involve any of ``image_ids``."""
        ids = sorted({int(i) for i in image_ids})
        counts = []
        for table in ("matches", "two_view_geometries"):
            n = 0
            for k in range(0, len(ids), 500):  # SQLite's variable limit
                chunk = ids[k : k + 500]
                marks = ",".join("?" * len(chunk))
                n += self._one(
                    f"SELECT COUNT(*) FROM {table} WHERE pair_id / {MAX_IMAGE_ID} "
                    f"IN ({marks}) OR pair_id % {MAX_IMAGE_ID} IN ({marks})",
                    chunk + chunk,
                )[0]
            counts.append(n)
        return counts[0], counts[1]

    def write_features(
        self,
        image_id: int,
        features: Features,
        overwrite: bool = False,
        extractor: str | None = EXTRACTOR_NAME,
    ) -> tuple[int, int]:
        """Keypoints (N x 6) and SIFT descriptors (N x 128 uint8) of one image, in one
        transaction. With ``overwrite``, existing features are replaced and the matches and
        two-view geometries of the image (indices into the old keypoints) are deleted.
        ``extractor``: recorded as the features' origin (None: not ours, no record).
        Returns the numbers of deleted (match, two-view geometry) rows."""
        with self._transaction():
            return self._insert_features(int(image_id), features, overwrite, extractor)

    def write_image(
        self,
        name: str,
        features: Features,
        camera: pycolmap.Camera | None = None,
        prior_focal_length: bool = False,
        camera_id: int | None = None,
        overwrite: bool = False,
        extractor: str | None = EXTRACTOR_NAME,
    ) -> tuple[int, int, tuple[int, int]]:
        """One image's camera (inserted when ``camera_id`` is None), row (when the name is
        new) and features, all in ONE transaction: on any error nothing is left behind.

        Returns (image_id, camera_id, deleted (match, two-view geometry) rows)."""
        with self._transaction():
            found = self.find_image(name)
            if found is not None:
                image_id, camera_id = found
            else:
                if camera_id is None:
                    if camera is None:
                        raise ValueError(f"{self.path}: image {name!r}: no camera given")
                    camera_id = self._insert_camera(camera, prior_focal_length)
                image_id = self._insert_image(name, camera_id)
            deleted = self._insert_features(image_id, features, overwrite, extractor)
        return image_id, camera_id, deleted

    def _insert_features(
        self, image_id: int, features: Features, overwrite: bool, extractor: str | None
    ) -> tuple[int, int]:
        kp, desc = self._checked_arrays(image_id, features)
        if self._one("SELECT 1 FROM images WHERE image_id = ?", (image_id,)) is None:
            raise KeyError(f"{self.path}: no image with id {image_id}")
        deleted = self._delete_features(image_id, overwrite)
        self._con.execute(
            "INSERT INTO keypoints(image_id, rows, cols, data) VALUES(?, ?, ?, ?)",
            (image_id, *kp.shape, kp.tobytes()),
        )
        if self._has_type:
            self._con.execute(
                "INSERT INTO descriptors(image_id, rows, cols, data, type) VALUES(?, ?, ?, ?, ?)",
                (image_id, *desc.shape, desc.tobytes(), SIFT_TYPE),
            )
        else:
            self._con.execute(
                "INSERT INTO descriptors(image_id, rows, cols, data) VALUES(?, ?, ?, ?)",
                (image_id, *desc.shape, desc.tobytes()),
            )
        if extractor is not None or self._has_provenance:
            self._con.execute(_PROVENANCE_SQL)
            self._has_provenance = True
            self._con.execute(f"DELETE FROM {PROVENANCE_TABLE} WHERE image_id = ?", (image_id,))
            if extractor is not None:
                self._con.execute(
                    f"INSERT INTO {PROVENANCE_TABLE}(image_id, extractor) VALUES(?, ?)",
                    (image_id, extractor),
                )
        return deleted

    def _checked_arrays(self, image_id: int, features: Features) -> tuple[np.ndarray, np.ndarray]:
        """(keypoints (N, 6) float32, descriptors (N, 128) uint8) as stored; ValueError
        naming the database and image for anything COLMAP could not read."""
        kp = np.ascontiguousarray(features.colmap_keypoints(), dtype=np.float32)
        desc = features.descriptors
        if desc.dtype != np.uint8 or desc.ndim != 2 or desc.shape[1] != 128:
            raise ValueError(
                f"{self.path}: image {image_id}: descriptors must be uint8 "
                f"(N, 128), got {desc.dtype} {desc.shape}"
            )
        if len(desc) != len(kp):
            raise ValueError(
                f"{self.path}: image {image_id}: {len(kp)} keypoints but {len(desc)} descriptors"
            )
        if not np.isfinite(kp).all():
            raise ValueError(f"{self.path}: image {image_id}: non-finite keypoints")
        return kp, np.ascontiguousarray(desc)

    def _delete_features(self, image_id: int, overwrite: bool) -> tuple[int, int]:
        """An image's features and the match rows indexing them, with ``overwrite`` (else
        ValueError when it has features) -> deleted (match, two-view geometry) rows."""
        exists = self._one("SELECT 1 FROM keypoints WHERE image_id = ?", (image_id,)) or self._one(
            "SELECT 1 FROM descriptors WHERE image_id = ?", (image_id,)
        )
        deleted = [0, 0]
        if not exists:
            return 0, 0
        if not overwrite:
            raise ValueError(
                f"{self.path}: image {image_id} already has features "
                "(pass overwrite=True to replace them)"
            )
        self._con.execute("DELETE FROM keypoints WHERE image_id = ?", (image_id,))
        self._con.execute("DELETE FROM descriptors WHERE image_id = ?", (image_id,))
        for i, table in enumerate(("matches", "two_view_geometries")):
            deleted[i] = self._con.execute(
                f"DELETE FROM {table} WHERE pair_id / {MAX_IMAGE_ID} = ? OR "
                f"pair_id % {MAX_IMAGE_ID} = ?",
                (image_id, image_id),
            ).rowcount
        if any(deleted):
            logger.info(
                "%s: image %d: deleted %d match and %d two-view geometry rows "
                "(they indexed the replaced keypoints)",
                self.path,
                image_id,
                *deleted,
            )
        return deleted[0], deleted[1]

    def read_keypoints(self, image_id: int) -> np.ndarray:
        """(N, cols) float32 keypoints as stored."""
        row = self._one(
            "SELECT rows, cols, data FROM keypoints WHERE image_id = ?", (int(image_id),)
        )
        if row is None:
            raise KeyError(f"{self.path}: image {image_id} has no keypoints")
        return np.frombuffer(row[2], dtype=np.float32).reshape(row[0], row[1]).copy()

    def read_descriptors(self, image_id: int) -> np.ndarray:
        """(N, 128) uint8 descriptors as stored."""
        row = self._one(
            "SELECT rows, cols, data FROM descriptors WHERE image_id = ?", (int(image_id),)
        )
        if row is None:
            raise KeyError(f"{self.path}: image {image_id} has no descriptors")
        return np.frombuffer(row[2], dtype=np.uint8).reshape(row[0], row[1]).copy()

    def read_features(self, image_id: int) -> Features:
        """An image's features as Features (COLMAP convention), whoever wrote them.

        Keypoints of 2 columns (x, y) get unit scale, 4 columns (x, y, scale, orientation)
        a similarity frame, 6 columns their affine frame. Raises ValueError when the
        descriptors are not SIFT (uint8, 128 per keypoint)."""
        kp = self.read_keypoints(image_id).astype(np.float64)
        if self._has_type:
            (kind,) = self._one("SELECT type FROM descriptors WHERE image_id = ?", (int(image_id),))
            if kind != SIFT_TYPE:
                raise ValueError(
                    f"{self.path}: image {image_id}: descriptors of type {kind} are not SIFT"
                )
        row = self._one(
            "SELECT rows, cols, length(data) FROM descriptors WHERE image_id = ?", (int(image_id),)
        )
        if row[1] != 128 or row[2] != row[0] * 128 or row[0] != len(kp):
            raise ValueError(
                f"{self.path}: image {image_id}: {row[0]}x{row[1]} descriptors "
                f"({row[2]} bytes) for {len(kp)} keypoints are not COLMAP SIFT"
            )
        desc = self.read_descriptors(image_id)
        n, cols = kp.shape
        if cols == 6:
            shapes = kp[:, 2:].reshape(n, 2, 2)
        elif cols == 4:
            shapes = similarity_frames(kp[:, 2], kp[:, 3])
        elif cols == 2:
            shapes = similarity_frames(np.ones(n), np.zeros(n))
        else:
            raise ValueError(f"{self.path}: image {image_id}: keypoints with {cols} columns")
        return Features(kp[:, :2].copy(), shapes, desc, np.full(n, -1, np.int32))
