"""The layout of a new COLMAP database, and COLMAP's ids (rectified_colmap.io.colmap_db).

A new database gets the layout that COLMAP 3.8 creates, extended the way COLMAP/pycolmap
4.x migrates such a database when it opens it: ``descriptors.type INTEGER NOT NULL
DEFAULT 0`` (0 = SIFT), ``two_view_geometries.camera1/camera2`` and the empty 4.x tables
(rigs, rig_sensors, frames, frame_data, pose_priors); plus the provenance table of the
images whose features this tool wrote (``PROVENANCE_TABLE``).
"""

from __future__ import annotations

import os
import sqlite3
from pathlib import Path

MAX_IMAGE_ID = 2147483647
"""COLMAP's pair-id base: image ids are in [1, MAX_IMAGE_ID)."""
SIFT_TYPE = 0
"""descriptors.type of SIFT (FeatureExtractorType.SIFT)."""
CAMERA_SENSOR = 0
"""SensorType.CAMERA in rigs/frame_data."""
MAX_COLMAP38_MODEL = 10
"""Camera model ids 0..10 (SIMPLE_PINHOLE..THIN_PRISM_FISHEYE) mean the same in 3.8 and 4.x."""
SCHEMA_VERSION = 3800
"""user_version of a new database (COLMAP 3.8's; 4.x bumps it when it opens the file)."""

# COLMAP 3.8's tables, with the columns 4.x adds when it migrates such a database.
_SCHEMA = [
    """CREATE TABLE IF NOT EXISTS cameras (
        camera_id INTEGER PRIMARY KEY AUTOINCREMENT NOT NULL,
        model INTEGER NOT NULL, width INTEGER NOT NULL, height INTEGER NOT NULL,
        params BLOB, prior_focal_length INTEGER NOT NULL)""",
    """CREATE TABLE IF NOT EXISTS images (
        image_id INTEGER PRIMARY KEY AUTOINCREMENT NOT NULL,
        name TEXT NOT NULL UNIQUE, camera_id INTEGER NOT NULL,
        prior_qw REAL, prior_qx REAL, prior_qy REAL, prior_qz REAL,
        prior_tx REAL, prior_ty REAL, prior_tz REAL,
        CONSTRAINT image_id_check CHECK(image_id >= 0 and image_id < 2147483647),
        FOREIGN KEY(camera_id) REFERENCES cameras(camera_id))""",
    "CREATE UNIQUE INDEX IF NOT EXISTS index_name ON images(name)",
    """CREATE TABLE IF NOT EXISTS keypoints (
        image_id INTEGER PRIMARY KEY NOT NULL,
        rows INTEGER NOT NULL, cols INTEGER NOT NULL, data BLOB,
        FOREIGN KEY(image_id) REFERENCES images(image_id) ON DELETE CASCADE)""",
    """CREATE TABLE IF NOT EXISTS descriptors (
        image_id INTEGER PRIMARY KEY NOT NULL,
        rows INTEGER NOT NULL, cols INTEGER NOT NULL, data BLOB,
        type INTEGER NOT NULL DEFAULT 0,
        FOREIGN KEY(image_id) REFERENCES images(image_id) ON DELETE CASCADE)""",
    """CREATE TABLE IF NOT EXISTS matches (
        pair_id INTEGER PRIMARY KEY NOT NULL,
        rows INTEGER NOT NULL, cols INTEGER NOT NULL, data BLOB)""",
    """CREATE TABLE IF NOT EXISTS two_view_geometries (
        pair_id INTEGER PRIMARY KEY NOT NULL,
        rows INTEGER NOT NULL, cols INTEGER NOT NULL, data BLOB,
        config INTEGER NOT NULL, F BLOB, E BLOB, H BLOB, qvec BLOB, tvec BLOB,
        camera1 BLOB, camera2 BLOB)""",
    # COLMAP 4.x tables (left empty unless the caller's database uses rigs/frames).
    """CREATE TABLE IF NOT EXISTS rigs (
        rig_id INTEGER PRIMARY KEY AUTOINCREMENT NOT NULL,
        ref_sensor_id INTEGER NOT NULL, ref_sensor_type INTEGER NOT NULL)""",
    """CREATE UNIQUE INDEX IF NOT EXISTS rig_ref_sensor_assignment ON
        rigs(ref_sensor_id, ref_sensor_type)""",
    """CREATE TABLE IF NOT EXISTS rig_sensors (
        rig_id INTEGER NOT NULL, sensor_id INTEGER NOT NULL, sensor_type INTEGER NOT NULL,
        sensor_from_rig BLOB,
        FOREIGN KEY(rig_id) REFERENCES rigs(rig_id) ON DELETE CASCADE)""",
    """CREATE UNIQUE INDEX IF NOT EXISTS rig_sensor_assignment ON
        rig_sensors(sensor_id, sensor_type)""",
    """CREATE TABLE IF NOT EXISTS frames (
        frame_id INTEGER PRIMARY KEY AUTOINCREMENT NOT NULL, rig_id INTEGER NOT NULL,
        FOREIGN KEY(rig_id) REFERENCES rigs(rig_id) ON DELETE CASCADE)""",
    """CREATE TABLE IF NOT EXISTS frame_data (
        frame_id INTEGER NOT NULL, data_id INTEGER NOT NULL,
        sensor_id INTEGER NOT NULL, sensor_type INTEGER NOT NULL,
        FOREIGN KEY(frame_id) REFERENCES frames(frame_id) ON DELETE CASCADE)""",
    """CREATE UNIQUE INDEX IF NOT EXISTS frame_sensor_assignment ON
        frame_data(data_id, sensor_type)""",
    """CREATE TABLE IF NOT EXISTS pose_priors (
        pose_prior_id INTEGER PRIMARY KEY NOT NULL,
        corr_data_id INTEGER NOT NULL, corr_sensor_id INTEGER NOT NULL,
        corr_sensor_type INTEGER NOT NULL, position BLOB, position_covariance BLOB,
        gravity BLOB, coordinate_system INTEGER NOT NULL)""",
    """CREATE UNIQUE INDEX IF NOT EXISTS pose_prior_data_assignment ON
        pose_priors(corr_data_id, corr_sensor_id, corr_sensor_type)""",
]
PROVENANCE_TABLE = "rectified_colmap_features"
_PROVENANCE_SQL = (
    f"CREATE TABLE IF NOT EXISTS {PROVENANCE_TABLE} ("
    "image_id INTEGER PRIMARY KEY NOT NULL, extractor TEXT NOT NULL)"
)
EXTRACTOR_NAME = "rectified-colmap"

_REQUIRED = {
    "cameras": {"camera_id", "model", "width", "height", "params", "prior_focal_length"},
    "images": {"image_id", "name", "camera_id"},
    "keypoints": {"image_id", "rows", "cols", "data"},
    "descriptors": {"image_id", "rows", "cols", "data"},
}


def image_ids_to_pair_id(image_id1: int, image_id2: int) -> int:
    """COLMAP's pair id (order-independent)."""
    a, b = sorted((int(image_id1), int(image_id2)))
    return a * MAX_IMAGE_ID + b


def create_database(path: Path) -> None:
    """Create a new, empty database with the layout described in the module docstring."""
    path = Path(path)
    if path.exists():
        raise FileExistsError(f"{path}: already exists")
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f"{path.name}.{os.getpid()}.creating")
    tmp.unlink(missing_ok=True)
    con = sqlite3.connect(tmp, isolation_level=None)
    try:
        _init_schema(con)
    finally:
        con.close()
    tmp.replace(path)  # atomic: a kill never leaves a half-created schema behind


def _init_schema(con: sqlite3.Connection) -> None:
    """COLMAP's tables on an empty database, in one transaction."""
    with Transaction(con):
        for sql in _SCHEMA:
            con.execute(sql)
        con.execute(f"PRAGMA user_version = {SCHEMA_VERSION}")


class Transaction:
    """BEGIN IMMEDIATE ... COMMIT (ROLLBACK on error) on an autocommit connection."""

    def __init__(self, con: sqlite3.Connection):
        self.con = con

    def __enter__(self):
        self.con.execute("BEGIN IMMEDIATE")
        return self.con

    def __exit__(self, exc_type, exc, tb):
        self.con.execute("ROLLBACK" if exc_type is not None else "COMMIT")
        return False
