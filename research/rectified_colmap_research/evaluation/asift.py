"""OpenCV's ASIFT as an evaluation anchor, in this package's feature format.

ASIFT (Morel and Yu, 2009) synthesises views of the whole image at sampled tilts and
longitudes, blindly, and runs SIFT in each: the view-synthesis baseline the issues compare
against ("ASIFT solves 4 of 7 held-out extreme pairs"). ``cv2.AffineFeature`` over
``cv2.SIFT`` is OpenCV's implementation (its default tilts 1, sqrt 2, ..., 4 sqrt 2 and
longitude steps 72 / t degrees); the keypoints come back in the input image's frame.

:func:`asift_features` converts them to :class:`rectified_colmap.features.Features`, so
that every evaluation (hloc files, ``eval.homography``) treats ASIFT as one more method:
keypoints in COLMAP's pixel convention, similarity frames, and OpenCV's SIFT descriptors as
RootSIFT bytes on COLMAP's scale (L1-normalised, square-rooted: what COLMAP's default
``L1_ROOT`` normalisation stores).
"""

from __future__ import annotations

import cv2
import numpy as np

from rectified_colmap.conventions import from_opencv_points
from rectified_colmap.features import Features, similarity_frames
from rectified_colmap.io.hloc_h5 import rootsift_bytes


def opencv_sift_to_rootsift_bytes(descriptors: np.ndarray) -> np.ndarray:
    """(N, 128) OpenCV SIFT descriptors (float, any positive scale) -> (N, 128) uint8
    RootSIFT as COLMAP stores it (``rootsift_bytes`` of the unit-norm root of the
    L1-normalised descriptor). All-zero rows stay zero."""
    d = np.clip(np.asarray(descriptors, np.float64), 0.0, None)
    l1 = d.sum(1, keepdims=True)
    return rootsift_bytes(np.sqrt(d / np.where(l1 > 0, l1, 1.0)))


def features_from_opencv(keypoints, descriptors: np.ndarray | None) -> Features:
    """cv2.KeyPoint list and their (N, 128) float descriptors -> Features: keypoints in
    COLMAP convention (+0.5), frames of scale ``size / 2`` and OpenCV's angle (degrees),
    patch -1 (none)."""
    if not keypoints or descriptors is None or len(descriptors) == 0:
        return Features.empty()
    xy = from_opencv_points(np.array([k.pt for k in keypoints], np.float64))
    size = np.array([k.size for k in keypoints], np.float64)
    angle = np.deg2rad(np.array([k.angle for k in keypoints], np.float64))
    return Features(
        xy,
        similarity_frames(size / 2.0, angle),
        opencv_sift_to_rootsift_bytes(descriptors),
        np.full(len(keypoints), -1, np.int32),
    )


def asift_features(gray: np.ndarray, max_num_features: int = 8192) -> Features:
    """ASIFT on a (h, w) uint8 image: cv2.AffineFeature over cv2.SIFT with
    ``max_num_features`` per synthesised view (OpenCV's defaults otherwise)."""
    if gray.ndim != 2 or gray.dtype != np.uint8:
        raise ValueError(f"ASIFT needs a (h, w) uint8 image, got {gray.shape} {gray.dtype}")
    asift = cv2.AffineFeature.create(cv2.SIFT.create(nfeatures=int(max_num_features)))
    keypoints, descriptors = asift.detectAndCompute(gray, None)
    return features_from_opencv(keypoints, descriptors)
