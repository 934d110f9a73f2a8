"""hloc feature files (``feats-*.h5``): crash-safe, resumable writer and readers.

Layout (what hloc's match_features, triangulation and localize_sfm read). One group per
image, named by the image path relative to the image root ('/' kept: nested groups), with
numeric datasets only:
- ``keypoints``   (N, 2) float32, hloc/OpenCV convention (centre of the top-left pixel at
  (0, 0); converted through rectified_colmap.conventions); attr ``uncertainty`` = 1.0;
- ``descriptors`` (128, N) RootSIFT with unit L2 norm (transposed), float16 if ``as_half``
  else float32; made from COLMAP's uint8 bytes as ``d / ||d||``;
- ``scores``      (N,) float32 zeros (SIFT has no detection score; hloc's DoG writes zeros);
- ``image_size``  (2,) int64 ``[W, H]`` of the original image;
- ``scales``      (N,) float32 COLMAP scale (Features.scales);
- ``oris``        (N,) float32 orientation in DEGREES (hloc's DoG convention).
Keypoints stay float32 even with ``as_half`` (float16 has 1 px steps above 1024).
Groups written by this tool carry the attribute ``extractor = "rectified-colmap"`` (hloc
reads datasets only), so groups from other extractors are recognised and kept.

Crash safety. The target file is never open for writing. ``write()`` puts each image into
its own small staging file (written as ``*.tmp``, fsynced, then ``os.replace``d to
``<target>.partial/<sha1(name)>.h5``). ``close()``, and opening a target that has a staging
directory, merges: the target is copied to ``<target>.merging``, the staged groups are
copied in with HDF5's object copy, the result is fsynced and atomically replaces the
target, then the staging files are deleted. A kill -9 at any moment therefore leaves the
target either as before or fully merged, and the staged work is merged on the next open.
One writer per target at a time: a writer holds ``<target>.lock`` (rectified_colmap.io.lock)
from its creation to :meth:`HlocFeatureWriter.close`; a second process waits for it.
:meth:`HlocFeatureWriter.create_if_missing` makes a valid file with no image (the same
atomic replace), so that a run with nothing to write (an empty shard) leaves one too.
"""

from __future__ import annotations

import hashlib
import logging
import os
import posixpath
import shutil
from pathlib import Path

import h5py
import numpy as np

from .. import conventions
from ..features import Features, similarity_frames
from .lock import OutputLock, check_writable

logger = logging.getLogger(__name__)

DATASETS = ("keypoints", "descriptors", "scores", "image_size", "scales", "oris")
_GROUP = "features"  # name of the image's group inside a staging file
EXTRACTOR_ATTR = "extractor"
EXTRACTOR_NAME = "rectified-colmap"
COLMAP_DESCRIPTOR_NORM = 512.0
"""COLMAP stores unit RootSIFT as min(255, round(512 d)) bytes."""


def staging_dir(path: Path) -> Path:
    path = Path(path)
    return path.with_name(path.name + ".partial")


def rootsift_unit(descriptors: np.ndarray) -> np.ndarray:
    """(N, 128) uint8 COLMAP RootSIFT bytes -> (N, 128) float32 with unit L2 norm.

    All-zero rows stay zero."""
    d = np.asarray(descriptors, dtype=np.float32)
    norm = np.linalg.norm(d, axis=1, keepdims=True)
    return d / np.where(norm > 0, norm, 1.0)


def rootsift_bytes(unit: np.ndarray, iterations: int = 3) -> np.ndarray:
    """(N, 128) unit-norm RootSIFT (e.g. read back from a feature file) -> (N, 128) uint8
    bytes as COLMAP stores them; the inverse of :func:`rootsift_unit`.

    The bytes' own norm (~512, not exactly: rounding) is not stored in the unit vector; it
    is recovered as the fixed point n = ||round(n u)||, which returns the original bytes
    exactly unless float16 storage moved a value across a rounding boundary (then by 1)."""
    u = np.clip(np.asarray(unit, dtype=np.float64), 0.0, None)
    norm = np.full((len(u), 1), COLMAP_DESCRIPTOR_NORM)
    for _ in range(iterations):
        b = np.clip(np.rint(u * norm), 0, 255)
        new = np.linalg.norm(b, axis=1, keepdims=True)
        norm = np.where(new > 0, new, COLMAP_DESCRIPTOR_NORM)
    return np.clip(np.rint(u * norm), 0, 255).astype(np.uint8)


def feature_arrays(
    features: Features, image_size: tuple[int, int], as_half: bool = True
) -> dict[str, np.ndarray]:
    """The datasets of one image's group (see the module docstring)."""
    n = len(features)
    desc = np.asarray(features.descriptors)
    if desc.dtype != np.uint8 or desc.shape != (n, 128):
        raise ValueError(f"descriptors must be uint8 ({n}, 128), got {desc.dtype} {desc.shape}")
    if np.asarray(features.keypoints).shape != (n, 2):
        raise ValueError(f"keypoints must be ({n}, 2), got {features.keypoints.shape}")
    w, h = (int(v) for v in image_size)
    if w <= 0 or h <= 0:
        raise ValueError(f"invalid image size {image_size}")
    kp = conventions.to_hloc_keypoints(features.keypoints)
    if not np.isfinite(kp).all():
        raise ValueError("non-finite keypoints")
    return {
        "keypoints": kp,
        "descriptors": np.ascontiguousarray(
            rootsift_unit(desc).T.astype(np.float16 if as_half else np.float32)
        ),
        "scores": np.zeros(n, np.float32),
        "image_size": np.array([w, h], np.int64),
        "scales": features.scales.astype(np.float32),
        "oris": np.rad2deg(features.orientations).astype(np.float32),
    }


def _check_name(name: str) -> str:
    parts = name.split("/")
    if not name or name.startswith("/") or "\\" in name or any(p in ("", ".", "..") for p in parts):
        raise ValueError(f"image name {name!r} must be a relative path with '/' separators")
    return name


def _group_names(f: h5py.File, foreign: set[str] | None = None) -> set[str]:
    """Image names in an open feature file: the parents of ``keypoints`` datasets. Names
    whose group lacks our extractor attribute are also added to ``foreign``."""
    names: set[str] = set()

    def visit(name, obj):
        if isinstance(obj, h5py.Dataset) and posixpath.basename(name) == "keypoints":
            image = posixpath.dirname(name)
            names.add(image)
            if foreign is not None and obj.parent.attrs.get(EXTRACTOR_ATTR) != EXTRACTOR_NAME:
                foreign.add(image)

    f.visititems(visit)
    return names


def _open_read(path: Path) -> h5py.File:
    try:
        return h5py.File(path, "r")
    except OSError as e:
        raise ValueError(f"{path}: not a readable HDF5 feature file ({e})") from e


def _fsync_file(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _fsync_dir(path: Path) -> None:
    try:
        _fsync_file(path)
    except OSError:  # some filesystems do not allow fsync on directories
        pass


def _write_group(group: h5py.Group, arrays: dict[str, np.ndarray], extractor: str | None) -> None:
    for key, value in arrays.items():
        group.create_dataset(key, data=value)
    group["keypoints"].attrs["uncertainty"] = 1.0
    if extractor is not None:
        group.attrs[EXTRACTOR_ATTR] = extractor


def merge_staged(path: Path) -> int:
    """Merge ``<path>.partial/*.h5`` into ``path`` atomically; returns the number merged.

    Safe to call again after a crash at any point (groups already merged are replaced by
    the same content)."""
    path = Path(path)
    stage = staging_dir(path)
    tmp = path.with_name(path.name + ".merging")
    tmp.unlink(missing_ok=True)
    if not stage.is_dir():
        return 0
    for leftover in stage.glob("*.tmp"):  # a write killed before its os.replace
        leftover.unlink()
    staged = sorted(stage.glob("*.h5"))
    if not staged:
        shutil.rmtree(stage, ignore_errors=True)
        return 0
    if path.exists():
        _open_read(path).close()  # a clear error if the target is not HDF5
        shutil.copyfile(path, tmp)
    with h5py.File(tmp, "a") as dst:
        for f in staged:
            with h5py.File(f, "r") as src:
                name = str(src.attrs["name"])
                if name in dst:
                    del dst[name]
                parent, base = posixpath.split(name)
                src.copy(src[_GROUP], dst.require_group(parent) if parent else dst, name=base)
    _fsync_file(tmp)
    os.replace(tmp, path)
    _fsync_dir(path.parent)
    for f in staged:
        f.unlink()
    shutil.rmtree(stage, ignore_errors=True)
    logger.info("%s: merged %d staged images", path, len(staged))
    return len(staged)


def create_empty(path: Path) -> None:
    """A valid feature file with no image at ``path`` (which must not exist; the caller
    holds its lock), made as ``<path>.merging`` and atomically renamed."""
    path = Path(path)
    tmp = path.with_name(path.name + ".merging")
    h5py.File(tmp, "w").close()
    _fsync_file(tmp)
    os.replace(tmp, path)
    _fsync_dir(path.parent)


class HlocFeatureWriter:
    """Write Features of many images into an hloc feature file, crash-safely.

    ``HlocFeatureWriter(path, as_half=True)``; use as a context manager or call
    :meth:`close` (which merges the staged images into ``path``). Images already in
    ``path`` (or staged by a killed run) are kept and reported by :meth:`has`; those that
    another extractor wrote by :meth:`foreign`.
    """

    def __init__(self, path: Path | str, as_half: bool = True, lock: bool = True):
        self.path = Path(path)
        self.as_half = as_half
        self._closed = True
        check_writable(self.path, "feature file")
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._lock = OutputLock(self.path) if lock else None
        if self._lock is not None:
            self._lock.acquire()
        try:
            merge_staged(self.path)  # work left by a killed run
            self._names: set[str] = set()
            self._foreign: set[str] = set()
            if self.path.exists():
                with _open_read(self.path) as f:
                    self._names = _group_names(f, self._foreign)
        except BaseException:
            self._release()
            raise
        self._stage = staging_dir(self.path)
        self._staged: set[str] = set()
        self._dirs = {
            "/".join(n.split("/")[:i]) for n in self._names for i in range(1, n.count("/") + 1)
        }
        self._closed = False

    def __enter__(self) -> "HlocFeatureWriter":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def has(self, name: str) -> bool:
        return name in self._names or name in self._staged

    def create_if_missing(self) -> None:
        """Make the target a valid feature file with no image when it does not exist yet
        (images written later are merged into it); an existing file is left as it is."""
        if self._closed:
            raise RuntimeError(f"{self.path}: writer is closed")
        if not self.path.exists():
            create_empty(self.path)

    def foreign(self) -> set[str]:
        """Names of the images in the file whose features another extractor wrote."""
        return self._foreign - self._staged

    def names(self) -> list[str]:
        return sorted(self._names | self._staged)

    def write(
        self,
        name: str,
        features: Features,
        image_size: tuple[int, int],
        overwrite: bool = False,
        extractor: str | None = EXTRACTOR_NAME,
    ) -> None:
        """Stage one image (``image_size`` = (W, H) of the original image). ``extractor``:
        recorded as the features' origin (None: not ours)."""
        self._check_new(name, overwrite)
        try:
            arrays = feature_arrays(features, image_size, self.as_half)
        except ValueError as e:
            raise ValueError(f"{self.path}: {name!r}: {e}") from e
        self._stage_group(
            name, lambda group: _write_group(group, arrays, extractor), extractor is not None
        )

    def copy_from(self, source: Path | str, name: str, overwrite: bool = False) -> None:
        """Stage one image's group exactly as it is in another feature file (datasets and
        attributes, bit for bit): merging shards."""
        self._check_new(name, overwrite)
        with _open_read(Path(source)) as src:
            if name not in src or "keypoints" not in src[name]:
                raise KeyError(f"{source}: no features for {name!r}")
            ours = src[name].attrs.get(EXTRACTOR_ATTR) == EXTRACTOR_NAME

            def fill(group):
                for key, value in src[name].attrs.items():
                    group.attrs[key] = value
                for key in src[name]:
                    src.copy(src[name][key], group, name=key)

            self._stage_group(name, fill, ours)

    def _check_new(self, name: str, overwrite: bool) -> None:
        if self._closed:
            raise RuntimeError(f"{self.path}: writer is closed")
        _check_name(name)
        parents = {"/".join(name.split("/")[:i]) for i in range(1, name.count("/") + 1)}
        if name in self._dirs or parents & (self._names | self._staged):
            raise ValueError(
                f"{self.path}: image name {name!r} clashes with a folder or an "
                "image of the same name in the file"
            )
        if self.has(name) and not overwrite:
            raise ValueError(
                f"{self.path}: {name!r} already has features (pass overwrite=True to replace them)"
            )

    def _stage_group(self, name: str, fill, ours: bool) -> None:
        """Write ``fill(group)`` into the image's staging file, atomically."""
        self._stage.mkdir(exist_ok=True)
        key = hashlib.sha1(name.encode()).hexdigest()
        final = self._stage / f"{key}.h5"
        tmp = self._stage / f"{key}.tmp"
        with h5py.File(tmp, "w") as f:
            f.attrs["name"] = name
            fill(f.create_group(_GROUP))
        _fsync_file(tmp)
        os.replace(tmp, final)
        _fsync_dir(self._stage)
        self._staged.add(name)
        self._dirs |= {"/".join(name.split("/")[:i]) for i in range(1, name.count("/") + 1)}
        if ours:
            self._foreign.discard(name)
        else:
            self._foreign.add(name)

    def flush(self) -> None:
        """Merge the staged images into the target now."""
        merge_staged(self.path)
        self._names |= self._staged
        self._staged.clear()

    def close(self) -> None:
        if not self._closed:
            try:
                self.flush()
            finally:
                self._closed = True
                self._release()

    def _release(self) -> None:
        if getattr(self, "_lock", None) is not None:
            self._lock.release()
            self._lock = None


# -- readers -------------------------------------------------------------------------------


def list_names(path: Path | str) -> list[str]:
    """Image names in a feature file (merged ones and, if any, staged ones).

    Safe to call while a writer is merging: staged files that vanish are in the target."""
    path = Path(path)
    stage = staging_dir(path)
    names: set[str] = set()
    try:
        staged = list(stage.glob("*.h5"))
    except FileNotFoundError:
        staged = []
    for s in staged:
        try:
            with h5py.File(s, "r") as f:
                names.add(str(f.attrs["name"]))
        except OSError:
            if s.exists():
                raise ValueError(f"{s}: unreadable staging file") from None
    if path.exists():  # read last: a merge that finished meanwhile has it all
        with _open_read(path) as f:
            names |= _group_names(f)
    return sorted(names)


def read(path: Path | str, name: str) -> dict[str, np.ndarray]:
    """One image's datasets as stored (descriptors (D, N)), except ``keypoints``, which come
    back in COLMAP convention (float64); ``uncertainty`` is added as a float.

    A staged (not yet merged) version of the image wins over the merged one."""
    path = Path(path)
    staged = staging_dir(path) / f"{hashlib.sha1(name.encode()).hexdigest()}.h5"
    if staged.exists():
        file, group = staged, _GROUP
    else:
        file, group = path, name
    with _open_read(file) as f:
        if group not in f or not isinstance(f[group], h5py.Group):
            raise KeyError(f"{path}: no features for {name!r}")
        g = f[group]
        out = {k: g[k][()] for k in g if isinstance(g[k], h5py.Dataset)}
        if "keypoints" not in out:
            raise KeyError(f"{path}: {name!r} has no keypoints")
        out["uncertainty"] = float(g["keypoints"].attrs.get("uncertainty", 1.0))
    out["keypoints"] = conventions.from_hloc_keypoints(out["keypoints"])
    return out


def read_features(path: Path | str, name: str) -> Features:
    """One image's features from a feature file as Features (COLMAP convention, uint8
    COLMAP-scale descriptors via :func:`rootsift_bytes`), whoever wrote them.

    Frames are similarities from ``scales`` and ``oris`` (degrees) where the file has them
    (an affine shape is not stored in hloc files), else unit scale. Raises ValueError when
    the descriptors are not 128-dimensional SIFT."""
    return features_from_arrays(read(path, name), f"{path}: {name!r}")


def features_from_arrays(g: dict[str, np.ndarray], where: str = "") -> Features:
    """:func:`read`'s datasets of one image -> Features (see :func:`read_features`);
    ``where`` names the image in errors."""
    kp = np.asarray(g["keypoints"], dtype=np.float64)
    desc = np.asarray(g["descriptors"])
    n = len(kp)
    if desc.ndim != 2 or desc.shape != (128, n):
        raise ValueError(
            f"{where}: descriptors {desc.shape} are not 128-dim SIFT for {n} keypoints"
        )
    scales = np.asarray(g.get("scales", np.ones(n)), dtype=np.float64).reshape(-1)
    oris = np.deg2rad(np.asarray(g.get("oris", np.zeros(n)), dtype=np.float64).reshape(-1))
    if len(scales) != n or len(oris) != n:
        raise ValueError(f"{where}: scales/oris do not match {n} keypoints")
    return Features(
        kp, similarity_frames(scales, oris), rootsift_bytes(desc.T), np.full(n, -1, np.int32)
    )


def validate(path: Path | str, names: list[str] | None = None) -> int:
    """Check the merged file against what hloc reads; returns the number of images.

    Raises ValueError naming the file, the image and the problem."""
    path = Path(path)
    with _open_read(path) as f:
        found = _group_names(f)
        missing = set(names or ()) - found
        if missing:
            raise ValueError(f"{path}: missing images {sorted(missing)[:5]}")
        for name in sorted(found):
            g = f[name]
            where = f"{path}: {name!r}"
            if set(g.keys()) != set(DATASETS):
                raise ValueError(
                    f"{where}: datasets {sorted(g.keys())}, expected {sorted(DATASETS)}"
                )
            kp, desc = g["keypoints"], g["descriptors"]
            n = kp.shape[0]
            if kp.shape != (n, 2) or kp.dtype != np.float32:
                raise ValueError(f"{where}: keypoints {kp.shape} {kp.dtype}")
            if desc.ndim != 2 or desc.shape[1] != n or desc.dtype.kind != "f":
                raise ValueError(
                    f"{where}: descriptors {desc.shape} {desc.dtype}, expected (D, {n}) float"
                )
            norms = np.linalg.norm(desc[()].astype(np.float32), axis=0)
            if n and not np.all((np.abs(norms - 1) < 2e-3) | (norms == 0)):
                raise ValueError(f"{where}: descriptors are not unit-norm")
            size = g["image_size"]
            if size.shape != (2,) or size.dtype.kind not in "iu" or (size[()] <= 0).any():
                raise ValueError(
                    f"{where}: image_size {size[()]} ({size.dtype}) must be "
                    "positive integers [W, H]"
                )
            for key in ("scores", "scales", "oris"):
                if g[key].shape != (n,) or g[key].dtype.kind != "f":
                    raise ValueError(f"{where}: {key} {g[key].shape} {g[key].dtype}")
        return len(found)
