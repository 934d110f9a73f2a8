"""Image files: listing a folder like COLMAP, decoding pixels, reading sizes cheaply.

Names are paths relative to the image folder with '/' separators, as COLMAP stores them.
Pixels are decoded as COLMAP reads them: EXIF orientation ignored. Sizes are (W, H) of
the stored pixels, read from the file header for JPEG and PNG (no decode; a 24-megapixel
JPEG takes ~0.3 s to decode) and by decoding for other formats.

Errors about one image are :class:`ImageError` with the cause only: callers that report
per image add the image's name (rectified_colmap.extraction). A truncated JPEG is decoded with
this module's one-line warning only: libjpeg's own ``Premature end of JPEG file``, which
the C library inside OpenCV prints on the process's stderr, is silenced
(:func:`c_stderr_silenced`).
"""

from __future__ import annotations

import contextlib
import logging
import os
import struct
import sys
import threading
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np

logger = logging.getLogger(__name__)

IMAGE_EXTENSIONS = {".jpg", ".jpeg", ".png", ".tif", ".tiff", ".bmp", ".ppm", ".pgm", ".webp"}


class ImageError(ValueError):
    """A problem with one image (its cause only; the caller adds the image's name)."""


def list_images(image_dir: Path, image_list: Path | list[str] | None = None) -> list[str]:
    """Names (relative, '/'-separated) of the images to process, sorted like COLMAP.

    A name listed twice is processed once."""
    image_dir = Path(image_dir)
    if not image_dir.is_dir():
        raise FileNotFoundError(f"{image_dir}: image path is not a folder")
    if image_list is not None:
        if isinstance(image_list, (str, Path)):
            try:
                text = Path(image_list).read_text().splitlines()
            except (OSError, UnicodeDecodeError) as e:
                raise FileNotFoundError(
                    f"{image_list}: cannot read the image list ({type(e).__name__}: {e})"
                ) from None
            names = [ln.strip() for ln in text if ln.strip() and not ln.startswith("#")]
        else:
            names = list(image_list)
        unique = list(dict.fromkeys(names))
        if len(unique) < len(names):
            logger.warning(
                "%s: %d duplicate name(s) in the image list, each processed once",
                image_list if isinstance(image_list, (str, Path)) else "image list",
                len(names) - len(unique),
            )
        return unique
    names = [
        p.relative_to(image_dir).as_posix()
        for p in image_dir.rglob("*")
        if p.suffix.lower() in IMAGE_EXTENSIONS and p.is_file()
    ]
    return sorted(names)


def decode_image(path: Path) -> tuple[np.ndarray, list[str]]:
    """-> (RGB uint8 (H, W, 3), warnings). EXIF orientation ignored (as COLMAP reads pixels).

    Raises ImageError (cause only) when the file is missing or cannot be decoded. A JPEG
    without its end-of-image marker (truncated: the decoder fills the rest with grey) is
    decoded with a warning."""
    path = Path(path)
    if not path.is_file():
        raise ImageError("no such image file")
    truncated = path.suffix.lower() in (".jpg", ".jpeg") and not _jpeg_complete(path)
    with c_stderr_silenced() if truncated else contextlib.nullcontext():  # libjpeg's warning
        img = cv2.imread(str(path), cv2.IMREAD_COLOR | cv2.IMREAD_IGNORE_ORIENTATION)
    if img is None:
        raise ImageError("cannot decode image (corrupt or unsupported format)")
    warnings = []
    if truncated:
        warnings.append("truncated JPEG (no end-of-image marker): the missing part decodes as grey")
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB), warnings


def read_mask(path: Path, size: tuple[int, int]) -> np.ndarray | None:
    """COLMAP's keypoint mask (--ImageReader.mask_path): (H, W) bool, False where the file is
    black (0: no features there); None when there is no such file (COLMAP: no mask).

    Raises ImageError for a mask that cannot be decoded or whose size differs from the
    image's ``size`` (W, H)."""
    path = Path(path)
    if not path.is_file():
        return None
    mask = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE | cv2.IMREAD_IGNORE_ORIENTATION)
    if mask is None:
        raise ImageError(f"mask {path}: cannot decode it")
    if (mask.shape[1], mask.shape[0]) != tuple(size):
        raise ImageError(
            f"mask {path} is {mask.shape[1]}x{mask.shape[0]} but the image is {size[0]}x{size[1]}"
        )
    return mask > 0


def keypoints_on_mask(xy: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """(N,) bool: COLMAP-convention keypoints (N, 2) on a True pixel of ``mask`` (H, W), the
    pixel being (int(x), int(y)) as COLMAP's MaskKeypoints reads it; outside: False."""
    col = np.floor(xy[:, 0]).astype(np.int64)
    row = np.floor(xy[:, 1]).astype(np.int64)
    inside = (col >= 0) & (row >= 0) & (col < mask.shape[1]) & (row < mask.shape[0])
    out = np.zeros(len(xy), bool)
    out[inside] = mask[row[inside], col[inside]]
    return out


class _StderrSilencer:
    """Points file descriptor 2 to os.devnull while at least one user is inside; the first
    to enter redirects, the last to leave restores (a lock keeps concurrent and nested
    uses from restoring the wrong descriptor)."""

    def __init__(self):
        self._lock = threading.Lock()
        self._users = 0
        self._saved: int | None = None

    def enter(self) -> None:
        with self._lock:
            if self._users == 0:
                self._saved = _redirect_fd2_to_devnull()
            self._users += 1

    def leave(self) -> None:
        with self._lock:
            self._users -= 1
            if self._users == 0 and self._saved is not None:
                os.dup2(self._saved, 2)
                os.close(self._saved)
                self._saved = None


def _redirect_fd2_to_devnull() -> int | None:
    """fd 2 -> os.devnull; returns a duplicate of the old fd 2 (None, and nothing changed,
    when the process has no usable fd 2)."""
    with contextlib.suppress(AttributeError, OSError, ValueError):
        sys.stderr.flush()  # Python's pending output goes out before, not into devnull
    try:
        saved = os.dup(2)
    except OSError:
        return None
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, 2)
    finally:
        os.close(devnull)
    return saved


_SILENCER = _StderrSilencer()


@contextlib.contextmanager
def c_stderr_silenced() -> Iterator[None]:
    """While open, whatever is written to file descriptor 2 (C libraries' messages, such as
    libjpeg's through OpenCV) is dropped; fd 2 is restored on exit, also on an exception.
    Thread-safe (concurrent and nested uses share one redirection), but process-wide:
    keep it around a single C call. Python's own sys.stderr is flushed first."""
    _SILENCER.enter()
    try:
        yield
    finally:
        _SILENCER.leave()


def _jpeg_complete(path: Path) -> bool:
    """Whether a JPEG file ends with its EOI marker (FF D9), trailing padding allowed."""
    with open(path, "rb") as f:
        f.seek(0, os.SEEK_END)
        f.seek(max(0, f.tell() - 4096))
        tail = f.read().rstrip(b"\0\r\n ")
    return tail.endswith(b"\xff\xd9")


def image_size(path: Path) -> tuple[int, int]:
    """(W, H) of an image file's stored pixels (what COLMAP's camera size is).

    Read from the header for JPEG and PNG; other formats, and headers that do not parse,
    are decoded. Raises ImageError when the file is missing or not an image."""
    path = Path(path)
    if not path.is_file():
        raise ImageError("no such image file")
    size = _header_size(path)
    if size is not None:
        return size
    img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE | cv2.IMREAD_IGNORE_ORIENTATION)
    if img is None:
        raise ImageError("cannot decode image (corrupt or unsupported format)")
    return img.shape[1], img.shape[0]


_SOF = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}
"""JPEG start-of-frame markers (baseline, progressive, lossless, arithmetic)."""


def _header_size(path: Path) -> tuple[int, int] | None:
    """(W, H) from a PNG IHDR or a JPEG SOF segment, or None."""
    with open(path, "rb") as f:
        head = f.read(26)
        if head[:8] == b"\x89PNG\r\n\x1a\n" and head[12:16] == b"IHDR":
            w, h = struct.unpack(">II", head[16:24])
            return (w, h) if w > 0 and h > 0 else None
        if head[:2] != b"\xff\xd8":
            return None
        f.seek(2)
        while True:
            marker = f.read(2)
            if len(marker) < 2 or marker[0] != 0xFF:
                return None
            while marker[1] == 0xFF:  # fill bytes
                marker = marker[1:] + f.read(1)
            code = marker[1]
            if code in (0xD8, 0x01) or 0xD0 <= code <= 0xD7:  # no length field
                continue
            length = f.read(2)
            if len(length) < 2:
                return None
            (n,) = struct.unpack(">H", length)
            if code in _SOF:
                data = f.read(5)
                if len(data) < 5:
                    return None
                h, w = struct.unpack(">HH", data[1:5])
                return (w, h) if w > 0 and h > 0 else None
            if code == 0xDA or n < 2:  # scan data before any frame header
                return None
            f.seek(n - 2, os.SEEK_CUR)


def read_image(path: Path) -> np.ndarray:
    """RGB uint8 (H, W, 3), EXIF orientation ignored (as COLMAP reads pixels). Raises
    FileNotFoundError / ValueError naming the file."""
    try:
        return decode_image(path)[0]
    except ImageError as e:
        if not Path(path).is_file():
            raise FileNotFoundError(f"{path}: {e}") from None
        raise ValueError(f"{path}: {e}") from None
