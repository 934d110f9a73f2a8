import os

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
