"""Depth from arrays and files: .npy, .npz, 16-bit PNG, COLMAP dense depth maps (.bin).

Conventions: a depth file holds one (H, W) map covering the whole image, indexed [row, col];
any resolution (the pipeline resamples it), but the same aspect ratio as the image.
Values are z-depth (or disparity, by ``kind``); 0, negative, NaN and inf are invalid.

- ``.npy``: one 2-D array (a singleton channel axis is squeezed);
- ``.npz``: the array under key ``depth``, or the only array in the file; an optional
  string entry ``kind`` ("metric" | "depth" | "disparity") is used when no kind is given;
- ``.png``: 16-bit single channel, depth = value * png_scale, 0 = invalid;
- ``.bin``: COLMAP's dense format (``stereo/depth_maps/<name>.geometric.bin``): an ASCII
  header ``width&height&channels&`` then width*height*channels float32 little-endian, stored
  column-major over (width, height, channels), i.e. row-major (H, W) for one channel.

Lookup for image ``sub/0001.jpg`` under ``depth_root`` (first hit wins), see
:func:`candidate_paths`.
"""

from __future__ import annotations

import logging
from pathlib import Path

import cv2
import numpy as np
import pycolmap

from ..config import DEFAULT_PNG_SCALE
from . import DEPTH_KINDS, DepthMap

logger = logging.getLogger(__name__)

SUFFIXES = (".npy", ".npz", ".png", ".bin")
MAX_ASPECT_MISMATCH = 0.05
"""Relative difference of aspect ratios (depth map vs image) above which a file is rejected."""


# ---------------------------------------------------------------------------------------
# COLMAP .bin


def read_colmap_array(path: Path) -> np.ndarray:
    """COLMAP dense array (depth (H, W) or normals (H, W, 3)) as float32."""
    path = Path(path)
    raw = path.read_bytes()
    fields, pos = [], 0
    while len(fields) < 3:
        end = raw.find(b"&", pos, pos + 32)
        if end < 0:
            raise ValueError(
                f"{path}: not a COLMAP dense array (bad header "
                f"{raw[:40]!r}, expected 'width&height&channels&')"
            )
        fields.append(raw[pos:end])
        pos = end + 1
    try:
        width, height, channels = (int(f.decode("ascii")) for f in fields)
    except (UnicodeDecodeError, ValueError):
        raise ValueError(f"{path}: not a COLMAP dense array (bad header {raw[:pos]!r})") from None
    if width <= 0 or height <= 0 or channels <= 0:
        raise ValueError(f"{path}: bad COLMAP array size {width}x{height}x{channels}")
    n = width * height * channels
    if len(raw) - pos != 4 * n:
        raise ValueError(
            f"{path}: COLMAP array {width}x{height}x{channels} needs {4 * n} "
            f"bytes of data, file has {len(raw) - pos} (truncated or corrupt)"
        )
    data = np.frombuffer(raw, dtype="<f4", count=n, offset=pos)
    arr = data.reshape((width, height, channels), order="F").transpose(1, 0, 2)
    return np.ascontiguousarray(arr.squeeze(axis=2) if channels == 1 else arr, np.float32)


def write_colmap_array(path: Path, array: np.ndarray) -> None:
    """Write (H, W) or (H, W, C) float32 in COLMAP's dense format (inverse of the reader)."""
    a = np.asarray(array, dtype="<f4")
    if a.ndim == 2:
        a = a[:, :, None]
    h, w, c = a.shape
    with open(path, "wb") as f:
        f.write(f"{w}&{h}&{c}&".encode("ascii"))
        f.write(a.transpose(1, 0, 2).reshape(-1, order="F").tobytes())


# ---------------------------------------------------------------------------------------
# Readers


def _as_2d(arr: np.ndarray, path: Path) -> np.ndarray:
    arr = np.asarray(arr)
    if arr.ndim == 3 and 1 in (arr.shape[0], arr.shape[-1]):
        arr = arr.reshape(arr.shape[1:] if arr.shape[0] == 1 else arr.shape[:2])
    if arr.ndim != 2 or min(arr.shape) < 2:
        raise ValueError(f"{path}: expected a 2-D depth map, got shape {arr.shape}")
    if not (np.issubdtype(arr.dtype, np.floating) or np.issubdtype(arr.dtype, np.integer)):
        raise ValueError(f"{path}: depth must be numeric, got dtype {arr.dtype}")
    return arr.astype(np.float32)


def _read_npz(path: Path) -> tuple[np.ndarray, str | None]:
    with np.load(path, allow_pickle=False) as z:
        keys = list(z.files)
        kind = None
        if "kind" in keys:
            kind = str(z["kind"])
            keys.remove("kind")
        if "depth" in keys:
            return z["depth"], kind
        if len(keys) == 1:
            return z[keys[0]], kind
    raise ValueError(
        f"{path}: .npz needs an array named 'depth' or exactly one array, found {keys}"
    )


def _read_png(path: Path, png_scale: float) -> np.ndarray:
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise ValueError(f"{path}: cannot decode PNG (corrupt or not an image)")
    if img.ndim != 2:
        raise ValueError(f"{path}: depth PNG must have one channel, got shape {img.shape}")
    if img.dtype != np.uint16:
        raise ValueError(
            f"{path}: depth PNG must be 16-bit (depth = value x scale), got "
            f"{img.dtype} (an 8-bit PNG is a visualisation, not depth)"
        )
    return img.astype(np.float32) * np.float32(png_scale)


def read_depth_file(
    path: str | Path, kind: str | None = None, png_scale: float = DEFAULT_PNG_SCALE
) -> DepthMap:
    """Read one depth file (see module docstring) -> DepthMap.

    ``kind``: what the values are (default: the .npz's ``kind`` entry, else "depth").
    Raises ValueError naming the file when it is unreadable, corrupt or not a depth map."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in SUFFIXES:
        raise ValueError(f"{path}: unknown depth file type {suffix!r}, expected one of {SUFFIXES}")
    if not path.is_file():
        raise ValueError(f"{path}: depth file does not exist")
    file_kind = None
    try:
        if suffix == ".npy":
            arr = np.load(path, allow_pickle=False)
        elif suffix == ".npz":
            arr, file_kind = _read_npz(path)
        elif suffix == ".png":
            arr = _read_png(path, png_scale)
        else:
            arr = read_colmap_array(path)
    except ValueError as e:
        if str(path) in str(e):
            raise
        raise ValueError(f"{path}: cannot read depth ({e})") from None
    except (OSError, EOFError) as e:
        raise ValueError(f"{path}: cannot read depth ({e})") from None
    except Exception as e:  # zipfile.BadZipFile, pickle errors, ...
        raise ValueError(f"{path}: corrupt depth file ({type(e).__name__}: {e})") from None
    kind = kind or file_kind or "depth"
    if kind not in DEPTH_KINDS:
        raise ValueError(f"{path}: unknown depth kind {kind!r}, expected one of {DEPTH_KINDS}")
    return DepthMap(_as_2d(arr, path), kind)


def write_depth_file(
    path: str | Path, depth: np.ndarray, png_scale: float = DEFAULT_PNG_SCALE
) -> Path:
    """Write a (H, W) depth map in the format given by the suffix (for tests and tools).
    PNG: round(depth / png_scale) as uint16, invalid -> 0."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    depth = np.asarray(depth, np.float32)
    suffix = path.suffix.lower()
    if suffix == ".npy":
        np.save(path, depth)
    elif suffix == ".npz":
        np.savez_compressed(path, depth=depth)
    elif suffix == ".png":
        v = np.where(np.isfinite(depth) & (depth > 0), np.round(depth / png_scale), 0)
        if v.max(initial=0) > 65535:
            raise ValueError(
                f"{path}: depth {depth[np.isfinite(depth)].max()} overflows "
                f"16 bits at scale {png_scale}"
            )
        if not cv2.imwrite(str(path), v.astype(np.uint16)):
            raise ValueError(f"{path}: cannot write PNG")
    elif suffix == ".bin":
        write_colmap_array(path, depth)
    else:
        raise ValueError(f"{path}: unknown depth file type {suffix!r}")
    return path


# ---------------------------------------------------------------------------------------
# Lookup


def candidate_paths(depth_root: str | Path, image_name: str) -> list[Path]:
    """Depth files tried for ``image_name`` (e.g. ``sub/0001.jpg``), in order:
    ``sub/0001.jpg.npy``, ``sub/0001.npy``, ``.jpg.npz``, ``.npz``, ``sub/0001.jpg.png``,
    ``sub/0001.png``, ``sub/0001.jpg.geometric.bin``, ``.photometric.bin``, then the two
    COLMAP files under ``depth_root/stereo/depth_maps/`` (a COLMAP dense workspace)."""
    root = Path(depth_root)
    full, stem = root / image_name, (root / image_name).with_suffix("")
    out = []
    for ext in (".npy", ".npz", ".png"):
        out += [Path(f"{full}{ext}"), Path(f"{stem}{ext}")]
    for base in (root, root / "stereo" / "depth_maps"):
        for kind in ("geometric", "photometric"):
            out.append(Path(f"{base / image_name}.{kind}.bin"))
    seen, unique = set(), []
    for p in out:  # an image without suffix gives duplicates
        if p not in seen:
            seen.add(p)
            unique.append(p)
    return unique


def find_depth_file(depth_root: str | Path, image_name: str) -> Path | None:
    """First existing file of :func:`candidate_paths`, or None."""
    for p in candidate_paths(depth_root, image_name):
        if p.is_file():
            return p
    return None


def check_aspect(depth: DepthMap, width: int, height: int, origin: str) -> None:
    """Raise ValueError when a depth map cannot cover a width x height image."""
    h, w = depth.values.shape
    a, b = w / h, width / height
    if abs(a / b - 1) > MAX_ASPECT_MISMATCH:
        raise ValueError(
            f"{origin}: depth map {w}x{h} does not match the aspect ratio of "
            f"its image {width}x{height} (transposed or cropped?)"
        )


# ---------------------------------------------------------------------------------------
# Sources


class ArrayDepthSource:
    """Depth source over in-memory maps: ``{image_name: (H, W) array | DepthMap}``.
    Arrays get ``kind``; DepthMaps keep theirs. Missing names -> None."""

    def __init__(self, depths: dict[str, np.ndarray | DepthMap], kind: str = "depth"):
        if kind not in DEPTH_KINDS:
            raise ValueError(f"unknown depth kind {kind!r}, expected one of {DEPTH_KINDS}")
        self.depths = dict(depths)
        self.kind = kind

    def __call__(
        self, image: np.ndarray | None, camera: pycolmap.Camera | None, name: str
    ) -> DepthMap | None:
        d = self.depths.get(name)
        if d is None:
            return None
        return d if isinstance(d, DepthMap) else DepthMap(d, self.kind)


class FileDepthSource:
    """Depth source over a folder of depth files (lookup: :func:`candidate_paths`).

    Returns None (no error) when an image has no file; raises ValueError naming the file
    when it exists but is unreadable, corrupt, or of the wrong aspect ratio."""

    def __init__(
        self, depth_root: str | Path, kind: str = "depth", png_scale: float = DEFAULT_PNG_SCALE
    ):
        self.root = Path(depth_root)
        if not self.root.is_dir():
            raise ValueError(f"{self.root}: depth folder does not exist")
        if kind not in DEPTH_KINDS:
            raise ValueError(f"unknown depth kind {kind!r}, expected one of {DEPTH_KINDS}")
        if not png_scale > 0:
            raise ValueError(f"png_scale must be positive, got {png_scale}")
        self.kind = kind
        self.png_scale = float(png_scale)

    def find(self, name: str) -> Path | None:
        return find_depth_file(self.root, name)

    def __call__(
        self, image: np.ndarray | None, camera: pycolmap.Camera | None, name: str
    ) -> DepthMap | None:
        path = self.find(name)
        if path is None:
            logger.debug("no depth file for %s under %s", name, self.root)
            return None
        depth = read_depth_file(path, self.kind, self.png_scale)
        if camera is not None:
            check_aspect(depth, camera.width, camera.height, str(path))
        elif image is not None:
            check_aspect(depth, image.shape[1], image.shape[0], str(path))
        return depth
