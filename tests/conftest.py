import os
import sqlite3

import cv2
import numpy as np
import pytest

os.environ.setdefault("OMP_NUM_THREADS", "1")
cv2.setNumThreads(1)


def textured_image(h: int, w: int, seed: int = 0) -> np.ndarray:
    """A uint8 image with blob texture at several scales (plenty of SIFT keypoints)."""
    rng = np.random.default_rng(seed)
    img = np.zeros((h, w), np.float32)
    for sigma in (1.5, 4, 10):
        noise = rng.standard_normal((h, w)).astype(np.float32)
        img += cv2.GaussianBlur(noise, (0, 0), sigma) * sigma
    img = (img - img.min()) / (np.ptp(img) + 1e-9)
    return (img * 255).astype(np.uint8)


@pytest.fixture
def texture():
    return textured_image


def look_at(eye, target, up=(0.0, 0.0, 1.0)):
    """(R, t) of cam_from_world for a camera at ``eye`` looking at ``target`` (y down)."""
    eye, target, up = (np.asarray(v, float) for v in (eye, target, up))
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    return R, -R @ eye


def plane_view(
    texture: np.ndarray,
    metres_per_texel: float,
    K: np.ndarray,
    R: np.ndarray,
    t: np.ndarray,
    size: tuple[int, int],
):
    """A camera (K, R, t; COLMAP pixel convention) looking at the textured plane z = 0 of the
    world, the texture centred on the origin. Returns (image uint8, z-depth float32 with
    NaN off the plane or behind the camera)."""
    from rectified_colmap.conventions import to_opencv_homography

    w, h = size
    th, tw = texture.shape[:2]
    # texture pixel (COLMAP convention) -> world (x, y, 0)
    S = np.array(
        [
            [metres_per_texel, 0, -tw / 2 * metres_per_texel],
            [0, -metres_per_texel, th / 2 * metres_per_texel],
            [0, 0, 1],
        ]
    )
    H = K @ np.stack([R[:, 0], R[:, 1], t], 1) @ S
    img = cv2.warpPerspective(
        texture,
        to_opencv_homography(H),
        (w, h),
        flags=cv2.INTER_AREA if False else cv2.INTER_LINEAR,
        borderValue=0,
    )
    # depth: plane n_c . X = d_c in the camera frame
    n_c = R[:, 2]
    d_c = n_c @ t
    xs, ys = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    rays = np.linalg.solve(K, np.stack([xs, ys, np.ones_like(xs)], -1)[..., None])[..., 0]
    with np.errstate(divide="ignore"):
        z = d_c / (rays @ n_c)
    # inside the texture?
    Hinv = np.linalg.inv(H)
    uvw = np.stack([xs, ys, np.ones_like(xs)], -1) @ Hinv.T
    uv = uvw[..., :2] / uvw[..., 2:]
    inside = (uv[..., 0] > 0) & (uv[..., 0] < tw) & (uv[..., 1] > 0) & (uv[..., 1] < th)
    z = np.where(inside & (z > 0), z, np.nan).astype(np.float32)
    img = np.where(np.isfinite(z), img, 0).astype(np.uint8)
    return img, z


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
