import os
import sqlite3

import cv2
import pytest

from rectified_colmap_research.synth.planar import look_at, plane_view, textured_image  # noqa: F401

os.environ.setdefault("OMP_NUM_THREADS", "1")
cv2.setNumThreads(1)


@pytest.fixture
def texture():
    return textured_image


def images_with_features(db) -> int:
    """Images with keypoints in a COLMAP database that another process may be writing
    (read-only, no waiting; 0 while it does not exist or is locked)."""
    try:
        con = sqlite3.connect(f"file:{db}?mode=ro", uri=True, timeout=0.1)
        try:
            return con.execute("SELECT COUNT(*) FROM keypoints").fetchone()[0]
        finally:
            con.close()
    except sqlite3.Error:
        return 0
