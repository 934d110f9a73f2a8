"""One textured plane seen by a pinhole camera: exact images and depth for tests and
benchmarks (the geometry is known in closed form, unlike the street scenes of
rectified_colmap.demo).

Conventions: world plane z = 0 with the texture centred on the origin (texture x along
world x, texture y along world -y); cameras (K, R, t) with R, t = cam_from_world, x right,
y down, z forward; pixels in the COLMAP convention (converted for OpenCV's warp through
rectified_colmap.conventions).
"""

from __future__ import annotations

import cv2
import numpy as np

from rectified_colmap.conventions import to_opencv_homography


def textured_image(h: int, w: int, seed: int = 0) -> np.ndarray:
    """A uint8 image (h, w) with blob texture at several scales (plenty of SIFT keypoints,
    no straight lines)."""
    rng = np.random.default_rng(seed)
    img = np.zeros((h, w), np.float32)
    for sigma in (1.5, 4, 10):
        noise = rng.standard_normal((h, w)).astype(np.float32)
        img += cv2.GaussianBlur(noise, (0, 0), sigma) * sigma
    img = (img - img.min()) / (np.ptp(img) + 1e-9)
    return (img * 255).astype(np.uint8)


def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> tuple[np.ndarray, np.ndarray]:
    """(R (3, 3), t (3,)) of cam_from_world for a camera at ``eye`` looking at ``target``,
    image y down = -``up`` (rectified_colmap.demo.views.look_at gives the same as a
    pycolmap.Rigid3d, with a roll and the degenerate cases)."""
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
) -> tuple[np.ndarray, np.ndarray]:
    """The textured plane z = 0 seen by the camera (K, R, t).

    Args:
        texture: (th, tw) uint8, centred on the world origin.
        metres_per_texel: size of a texel on the plane.
        K: (3, 3) intrinsics (COLMAP pixels); R, t: cam_from_world.
        size: (w, h) of the image.
    Returns:
        image (h, w) uint8 (0 off the plane), z-depth (h, w) float32 (NaN off the plane or
        behind the camera).
    """
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
        texture, to_opencv_homography(H), (w, h), flags=cv2.INTER_LINEAR, borderValue=0
    )
    # depth: plane n_c . X = d_c in the camera frame
    n_c = R[:, 2]
    d_c = n_c @ t
    xs, ys = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    rays = np.linalg.solve(K, np.stack([xs, ys, np.ones_like(xs)], -1)[..., None])[..., 0]
    with np.errstate(divide="ignore"):
        z = d_c / (rays @ n_c)
    # inside the texture?
    uvw = np.stack([xs, ys, np.ones_like(xs)], -1) @ np.linalg.inv(H).T
    uv = uvw[..., :2] / uvw[..., 2:]
    inside = (uv[..., 0] > 0) & (uv[..., 0] < tw) & (uv[..., 1] > 0) & (uv[..., 1] < th)
    z = np.where(inside & (z > 0), z, np.nan).astype(np.float32)
    img = np.where(np.isfinite(z), img, 0).astype(np.uint8)
    return img, z
