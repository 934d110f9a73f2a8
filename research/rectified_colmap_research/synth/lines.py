"""Line drawings of a Manhattan street with an exact frame: 3D segments of window edges
and ground tiles (plus random clutter), projected through a pycolmap camera and drawn
anti-aliased with noise, for tests and benchmarks of the vanishing-point stage
(``rectified_colmap.vp``). World z up, the street along y, facades at x = +-6 m.
Rotations are cam_from_world (camera x right, y down, z forward); pixels in COLMAP's
convention."""

from __future__ import annotations

import cv2
import numpy as np

from rectified_colmap.camera import rays_to_image
from rectified_colmap.conventions import to_opencv_points


def random_rotation(rng):
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


def rot(axis, deg):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    return cv2.Rodrigues(axis.reshape(3, 1) * np.deg2rad(deg))[0]


def axis_errors_deg(D, R):
    """Angle from each true axis (rows of R) to the nearest row of D, either sign."""
    return np.degrees(np.arccos(np.clip(np.abs(R @ D.T).max(1), 0, 1)))


def street_camera(rng, yaw=None, pitch=None, roll=None):
    """cam_from_world rotation of a camera in a street (world z up, street along y)."""
    yaw = rng.uniform(-50, 50) if yaw is None else yaw
    pitch = rng.uniform(-15, 15) if pitch is None else pitch
    roll = rng.uniform(-8, 8) if roll is None else roll
    base = np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]])  # looks along +y, y down = -z
    return rot([0, 0, 1], roll) @ rot([1, 0, 0], pitch) @ rot([0, 1, 0], yaw) @ base


def street_segments(rng, clutter=0.3, n=150):
    """3D segments (M, 2, 3) of a street canyon: window edges on two facades (x = +-6,
    along y and z), ground tiles (along x and y), plus ``clutter`` x random directions."""
    segs = []
    for side in (-6.0, 6.0):
        y = rng.uniform(2, 40, n // 3)
        z = rng.uniform(0.5, 12, n // 3)
        wdt, hgt = rng.uniform(0.6, 1.5, (2, n // 3))
        x = np.full(n // 3, side)
        for dy0, dz0, dy1, dz1 in ((0, 0, 1, 0), (0, 1, 1, 1), (0, 0, 0, 1), (1, 0, 1, 1)):
            segs.append(
                np.stack(
                    [
                        np.stack([x, y + dy0 * wdt, z + dz0 * hgt], 1),
                        np.stack([x, y + dy1 * wdt, z + dz1 * hgt], 1),
                    ],
                    1,
                )
            )
    gx, gy = rng.uniform(-5, 5, n // 3), rng.uniform(2, 30, n // 3)
    L = rng.uniform(0.5, 2, n // 3)
    segs.append(np.stack([np.stack([gx, gy, 0 * gx], 1), np.stack([gx + L, gy, 0 * gx], 1)], 1))
    segs.append(np.stack([np.stack([gx, gy, 0 * gx], 1), np.stack([gx, gy + L, 0 * gx], 1)], 1))
    S = np.concatenate(segs)
    m = int(clutter * len(S))
    if m:
        c = np.stack([rng.uniform(-5, 5, m), rng.uniform(3, 30, m), rng.uniform(0, 8, m)], 1)
        d = rng.normal(size=(m, 3))
        d *= rng.uniform(0.5, 2, (m, 1)) / np.linalg.norm(d, axis=1, keepdims=True)
        S = np.concatenate([S, np.stack([c, c + d], 1)])
    return S


def project_segments(camera, R, t, S, clip=0.3):
    """3D segments -> (N, 2, 2) COLMAP pixels (clipped to z > clip and to the image)."""
    P = S @ R.T + t
    z0, z1 = P[:, 0, 2], P[:, 1, 2]
    keep = (z0 > clip) | (z1 > clip)
    P, z0, z1 = P[keep], z0[keep], z1[keep]
    a = np.clip((clip - z0) / np.where(z1 != z0, z1 - z0, 1), 0, 1)[:, None]
    b = np.clip((clip - z1) / np.where(z0 != z1, z0 - z1, 1), 0, 1)[:, None]
    p0 = np.where((z0 < clip)[:, None], P[:, 0] + a * (P[:, 1] - P[:, 0]), P[:, 0])
    p1 = np.where((z1 < clip)[:, None], P[:, 1] + b * (P[:, 0] - P[:, 1]), P[:, 1])
    xy = np.stack([rays_to_image(camera, p0), rays_to_image(camera, p1)], 1)
    ok = np.isfinite(xy).all((1, 2))
    xy = xy[ok]
    inside = (
        (xy[..., 0] > 0)
        & (xy[..., 0] < camera.width)
        & (xy[..., 1] > 0)
        & (xy[..., 1] < camera.height)
    ).all(1)
    return xy[inside]


def render_street(camera, R, rng, clutter=0.3, noise=6.0):
    """A grey image of the street's line drawing (anti-aliased, noisy) for LSD."""
    t = -R @ np.array([0.0, 0.0, 1.6])
    xy = project_segments(camera, R, t, street_segments(rng, clutter))
    img = np.full((camera.height, camera.width), 170, np.uint8)
    for p, q in np.round(to_opencv_points(xy) * 16).astype(int):
        cv2.line(img, tuple(map(int, p)), tuple(map(int, q)), 40, 2, cv2.LINE_AA, shift=4)
    img = img.astype(np.float32) + rng.normal(scale=noise, size=img.shape)
    return np.clip(img, 0, 255).astype(np.uint8)
