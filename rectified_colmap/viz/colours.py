"""Colours of plane orientations in the pictures (a fixed function of the normal).

Normals are in the camera frame (x right, y down, z forward) and face the camera. The
image's up (-y) stands in for gravity, which the pipeline has no knowledge of. Normals
within ``HORIZONTAL_DEG`` of up are ground (green), of down ceiling (cyan); walls take a hue
from their azimuth on a continuous wheel (``wall_hue_deg``).
"""

from __future__ import annotations

import cv2
import numpy as np

from ..geometry import line_angle_deg

IMAGE_UP = np.array([0.0, -1.0, 0.0])
""""Up" in the camera frame without gravity: the image's -y."""
HORIZONTAL_DEG = 45.0
"""Normals within this angle of up (down) are ground (ceiling); the others are walls."""
GROUND_BGR = (70, 200, 70)  # green
CEILING_BGR = (220, 210, 40)  # cyan
NONE_BGR = (128, 128, 128)  # undefined normal
PLAIN_BGR = (255, 150, 30)  # blue: plain SIFT keypoints
RECTIFIED_BGR = (0, 150, 255)  # orange: keypoints found in a rectified patch
OUTLINE_BGR = (255, 255, 255)
DISPLAY_MAX_SIDE = 1600
"""Pictures are scaled down to at most this side (None in the functions: full size)."""

_WALL_HUE_FACING_CAMERA = 320.0  # pink; -90 deg (faces left) -> 230 blue, +90 -> 50 orange


def wall_hue_deg(azimuth_deg: np.ndarray) -> np.ndarray:
    """Hue in degrees [0, 360) of a vertical plane whose normal points ``azimuth_deg`` away
    from the camera's backward direction, positive towards +x (clipped to [-90, 90]): a
    continuous wheel from blue (faces left) through pink (faces the camera) and red to orange
    (faces right) that stays clear of the ground's green and the ceiling's cyan."""
    az = np.clip(np.asarray(azimuth_deg, np.float64), -90.0, 90.0)
    return (_WALL_HUE_FACING_CAMERA + az) % 360.0


def _hue_bgr(hue_deg: np.ndarray) -> np.ndarray:
    """(...) hues in degrees -> (..., 3) uint8 BGR (saturation 210, value 255)."""
    hue_deg = np.asarray(hue_deg, np.float64)
    hsv = np.empty(hue_deg.shape + (3,), np.uint8)
    hsv[..., 0] = np.round(hue_deg / 2.0).astype(np.int64) % 180  # OpenCV hue is degrees / 2
    hsv[..., 1], hsv[..., 2] = 210, 255
    flat = hsv.reshape(-1, 1, 3)
    return cv2.cvtColor(flat, cv2.COLOR_HSV2BGR).reshape(hsv.shape)


def orientation_kind(normals: np.ndarray, up: np.ndarray = IMAGE_UP):
    """(..., 3) unit normals (camera frame, facing the camera) -> (kind, azimuth_deg):
    kind (...) int8 0 = ground, 1 = ceiling, 2 = wall, -1 = undefined (NaN); azimuth (...)
    degrees of a wall's normal about ``up``, 0 = facing the camera, positive = facing right
    (towards +x when up is the image's -y), in (-180, 180]."""
    n = np.asarray(normals, np.float64)
    up = np.asarray(up, np.float64) / np.linalg.norm(up)
    # Horizontal frame about up: forward = the optical axis made horizontal, right = f x up.
    forward = np.array([0.0, 0.0, 1.0]) - up[2] * up
    if np.linalg.norm(forward) < 1e-6:  # looking straight up or down: image x is right
        forward = np.cross(np.array([1.0, 0.0, 0.0]), up)
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, up)
    elev = np.degrees(np.arcsin(np.clip(n @ up, -1.0, 1.0)))
    azimuth = np.degrees(np.arctan2(n @ right, -(n @ forward)))
    kind = np.full(n.shape[:-1], 2, np.int8)
    kind[elev >= 90.0 - HORIZONTAL_DEG] = 0
    kind[elev <= HORIZONTAL_DEG - 90.0] = 1
    kind[~np.isfinite(n).all(-1)] = -1
    return kind, azimuth


def orientation_colours(normals: np.ndarray, up: np.ndarray = IMAGE_UP) -> np.ndarray:
    """(..., 3) unit normals (camera frame, facing the camera) -> (..., 3) uint8 BGR: ground
    ``GROUND_BGR``, ceiling ``CEILING_BGR``, walls by ``wall_hue_deg`` of their azimuth,
    undefined (NaN) ``NONE_BGR``. A function of the orientation only: the same in every
    image."""
    kind, azimuth = orientation_kind(normals, up)
    out = _hue_bgr(wall_hue_deg(np.nan_to_num(azimuth)))
    out[kind == 0] = GROUND_BGR
    out[kind == 1] = CEILING_BGR
    out[kind == -1] = NONE_BGR
    return out


def orientation_text(normal: np.ndarray, up: np.ndarray = IMAGE_UP) -> str:
    """Short name of a normal's orientation: ground, ceiling, wall facing left / camera /
    right (with its azimuth)."""
    kind, az = orientation_kind(np.asarray(normal, np.float64).reshape(1, 3), up)
    kind, az = int(kind[0]), float(az[0])
    if kind < 0:
        return "undefined"
    if kind < 2:
        return ("ground", "ceiling")[kind]
    side = "left" if az < -20 else "right" if az > 20 else "camera"
    return f"wall facing {side} ({az:+.0f} deg)"


def tilt_deg(normal: np.ndarray) -> float:
    """Angle between a plane and the image plane (between the lines of its normal and the
    optical axis), in degrees in [0, 90]: 0 = fronto-parallel, 90 = seen edge-on. A plane
    facing the camera can still have a normal more than 90 degrees from -z (ground seen by
    a camera pitched up): the dihedral angle is the one a tilt label means."""
    n = np.asarray(normal, np.float64).reshape(3)
    return float(line_angle_deg(n / np.linalg.norm(n), np.array([0.0, 0.0, 1.0])))


def label_colours(directions: np.ndarray | None, up: np.ndarray = IMAGE_UP) -> np.ndarray:
    """(6, 3) uint8 BGR of the labels 2 k + s of a PlaneResult: the colour of the normal
    d_k (s = 0) or -d_k (s = 1); NONE_BGR without directions."""
    if directions is None:
        return np.tile(np.array(NONE_BGR, np.uint8), (6, 1))
    d = np.asarray(directions, np.float64)
    return orientation_colours(np.stack([d, -d], 1).reshape(6, 3), up)
