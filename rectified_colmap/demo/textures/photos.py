"""Photo textures: photos (e.g. of facades) loaded from a folder, cropped and resized."""

from __future__ import annotations

import functools
import logging
from pathlib import Path

import cv2
import numpy as np

logger = logging.getLogger(__name__)


@functools.lru_cache(maxsize=4)
def load_photos(folder: str, max_side: int = 1024) -> tuple[np.ndarray, ...]:
    """All JPEG/PNG images under a folder (recursively) as float32 RGB, downscaled to
    ``max_side``."""
    path = Path(folder)
    if not path.is_dir():
        raise FileNotFoundError(f"{folder}: texture folder does not exist")
    out = []
    for p in sorted(path.rglob("*")):
        if p.suffix.lower() not in (".jpg", ".jpeg", ".png"):
            continue
        im = cv2.imread(str(p), cv2.IMREAD_COLOR)
        if im is None:
            logger.warning("%s: cannot read image, skipped", p)
            continue
        s = max_side / max(im.shape[:2])
        if s < 1:
            im = cv2.resize(im, None, fx=s, fy=s, interpolation=cv2.INTER_AREA)
        out.append(np.ascontiguousarray(im[..., ::-1], np.float32) / 255.0)
    if not out:
        raise ValueError(f"{folder}: no readable .jpg/.jpeg/.png textures")
    logger.info("loaded %d texture photos from %s", len(out), folder)
    return tuple(out)


def photo_texture(photo: np.ndarray, rng, h, w) -> np.ndarray:
    """A random crop of a photo with the aspect ratio h:w, resized to (h, w)."""
    ph, pw = photo.shape[:2]
    s = min(ph / h, pw / w) * rng.uniform(0.7, 1.0)
    ch, cw = max(2, int(h * s)), max(2, int(w * s))
    y0, x0 = int(rng.integers(0, ph - ch + 1)), int(rng.integers(0, pw - cw + 1))
    crop = photo[y0 : y0 + ch, x0 : x0 + cw]
    interp = cv2.INTER_AREA if s > 1 else cv2.INTER_CUBIC
    return np.clip(cv2.resize(crop, (w, h), interpolation=interp), 0, 1).astype(np.float32)
