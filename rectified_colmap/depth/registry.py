"""Named depth models: the embedded default and public ONNX models fetched on demand.

Each :class:`ModelEntry` has a URL, a sha256 (None where upstream publishes none: the first
download then warns loudly and logs the computed digest so that it can be pinned), its
licence and a :class:`~rectified_colmap.depth.contract.ModelSpec` used when the file
carries no contract metadata.

Cache folder (first set wins): ``$RECTIFIED_COLMAP_CACHE``,
``$XDG_CACHE_HOME/rectified-colmap``, ``~/.cache/rectified-colmap``.

Pinning a digest: environment variable ``RECTIFIED_COLMAP_SHA256_<NAME>`` (name upper-cased,
non-alphanumerics as ``_``, e.g. ``RECTIFIED_COLMAP_SHA256_MIDAS_V2_1_SMALL``) or
:func:`pin_sha256`. Other models: :func:`register_model`, or just a path to an .onnx file.
"""

from __future__ import annotations

import dataclasses
import hashlib
import http.client
import logging
import os
import re
import tempfile
import urllib.error
import urllib.request
from dataclasses import dataclass
from pathlib import Path

from .contract import IMAGENET_MEAN, IMAGENET_STD, ModelSpec
from .onnx import OnnxDepthSource

logger = logging.getLogger(__name__)

PACKAGE_MODELS = Path(__file__).resolve().parent.parent / "models"
CHUNK = 1 << 20


class ModelDownloadError(RuntimeError):
    """A model could not be fetched or failed verification."""


@dataclass
class ModelEntry:
    name: str
    filename: str
    licence: str
    description: str
    url: str | None = None
    """None: embedded in the package (``rectified_colmap/models/<filename>``)."""
    sha256: str | None = None
    size: int | None = None
    """Exact size in bytes when known (verified), else None."""
    approx_mb: float | None = None
    """For display only."""
    spec: ModelSpec | None = None
    """Contract to use when the file carries no ``rectified_colmap.*`` metadata."""

    @property
    def embedded(self) -> bool:
        return self.url is None


REGISTRY: dict[str, ModelEntry] = {}


def register_model(entry: ModelEntry, overwrite: bool = False) -> ModelEntry:
    if entry.name in REGISTRY and not overwrite:
        raise ValueError(f"model {entry.name!r} is already registered")
    REGISTRY[entry.name] = entry
    return entry


register_model(
    ModelEntry(
        name="rectsift-lite0",
        filename="rectsift-depth-lite0.onnx",
        licence="BSD-3-Clause",
        description="embedded default: EfficientNet-Lite0 U-Net trained by this project on "
        "rendered street scenes and real photos (z-depth up to scale, 0 on sky)",
        approx_mb=None,
    )
)
register_model(
    ModelEntry(
        name="depth-anything-v2-small",
        filename="depth_anything_v2_vits.onnx",
        licence="Apache-2.0",
        description="Depth Anything V2 Small (ViT-S), affine-invariant disparity; "
        "fabio-sim/Depth-Anything-ONNX release v2.0.0",
        url="https://github.com/fabio-sim/Depth-Anything-ONNX/releases/download/v2.0.0/"
        "depth_anything_v2_vits.onnx",
        approx_mb=99,
        spec=ModelSpec(
            input_name="image",
            output_name="depth",
            layout="NCHW",
            color="RGB",
            scale=1 / 255,
            mean=list(IMAGENET_MEAN),
            std=list(IMAGENET_STD),
            resize={"mode": "keep_aspect", "max_side": 518, "multiple_of": 14},
            output="disparity",
            name="depth-anything-v2-small",
            licence="Apache-2.0",
            description="Depth Anything V2 Small, relative disparity",
        ),
    )
)
register_model(
    ModelEntry(
        name="midas-v2.1-small",
        filename="midas_v21_small_model-small.onnx",
        licence="MIT",
        description="MiDaS v2.1 small (EfficientNet-Lite3 encoder), relative disparity; "
        "isl-org/MiDaS release v2_1",
        url="https://github.com/isl-org/MiDaS/releases/download/v2_1/model-small.onnx",
        approx_mb=66,
        spec=ModelSpec(
            layout="NCHW",
            color="RGB",
            scale=1 / 255,
            mean=list(IMAGENET_MEAN),
            std=list(IMAGENET_STD),
            resize={"mode": "fixed", "width": 256, "height": 256},
            output="disparity",
            name="midas-v2.1-small",
            licence="MIT",
            description="MiDaS v2.1 small, relative disparity",
        ),
    )
)


# ---------------------------------------------------------------------------------------
# Cache and pinning


def cache_dir() -> Path:
    """The model cache folder (see module docstring); not created here."""
    if os.environ.get("RECTIFIED_COLMAP_CACHE"):
        return Path(os.environ["RECTIFIED_COLMAP_CACHE"]).expanduser()
    if os.environ.get("XDG_CACHE_HOME"):
        return Path(os.environ["XDG_CACHE_HOME"]).expanduser() / "rectified-colmap"
    return Path.home() / ".cache" / "rectified-colmap"


def _env_key(name: str) -> str:
    return "RECTIFIED_COLMAP_SHA256_" + re.sub(r"[^A-Za-z0-9]", "_", name).upper()


def pin_sha256(name: str, sha256: str) -> None:
    """Pin the digest of a registered model (for this process)."""
    get_entry(name).sha256 = sha256.lower()


def expected_sha256(entry: ModelEntry) -> str | None:
    sha = os.environ.get(_env_key(entry.name)) or entry.sha256
    return sha.strip().lower() if sha else None


def get_entry(name: str) -> ModelEntry:
    try:
        return REGISTRY[name]
    except KeyError:
        raise ValueError(
            f"unknown depth model {name!r}; known: {', '.join(REGISTRY)} "
            f"(or give a path to an .onnx file)"
        ) from None


def model_path(name: str) -> Path:
    """Where a registered model lives (package folder or cache), existing or not."""
    entry = get_entry(name)
    return (PACKAGE_MODELS if entry.embedded else cache_dir()) / entry.filename


def sha256_file(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(CHUNK), b""):
            h.update(block)
    return h.hexdigest()


# ---------------------------------------------------------------------------------------
# Download


def _manual_hint(entry: ModelEntry, dest: Path) -> str:
    sha = expected_sha256(entry)
    return (
        f"download {entry.url} by other means and place it at {dest}"
        + (f" (sha256 {sha})" if sha else "")
        + f", or set RECTIFIED_COLMAP_CACHE to a folder holding {entry.filename}"
    )


def download(name: str, force: bool = False, progress: bool = True, timeout: float = 30.0) -> Path:
    """Fetch a registered model into the cache (no-op when present) and return its path.

    Streams to a temporary file in the cache folder, verifies size and sha256, then moves it
    into place atomically; nothing is left behind on failure."""
    entry = get_entry(name)
    dest = model_path(name)
    if entry.embedded:
        if not dest.is_file():
            raise FileNotFoundError(
                f"the embedded depth model {name!r} is missing from the package ({dest}); "
                f"this build does not ship it: train/export it (docs/training.md) or use "
                f"another model (`rectified-colmap models list`) or a path to an .onnx"
            )
        return dest
    if dest.is_file() and not force:
        if entry.size is None or dest.stat().st_size == entry.size:
            return dest
        logger.warning(
            "%s has size %d, expected %d: downloading again", dest, dest.stat().st_size, entry.size
        )
    try:
        dest.parent.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise ModelDownloadError(
            f"cannot create the model cache {dest.parent} ({e}); set "
            f"RECTIFIED_COLMAP_CACHE to a writable folder"
        ) from None
    logger.info("downloading %s (%s) from %s to %s", name, entry.licence, entry.url, dest)
    digest, n = _fetch_verified(entry, dest, timeout, progress)
    logger.info("saved %s (%d bytes, sha256 %s)", dest, n, digest)
    return dest


def _fetch_verified(
    entry: ModelEntry, dest: Path, timeout: float, progress: bool
) -> tuple[str, int]:
    """Stream ``entry.url`` into a temporary file beside ``dest``, check its size and
    sha256, move it onto ``dest`` -> (sha256 hex, bytes); ModelDownloadError saying what to
    do otherwise, the temporary file removed either way."""
    name, sha = entry.name, expected_sha256(entry)
    fd, tmp_name = tempfile.mkstemp(prefix=f".{entry.filename}.", suffix=".part", dir=dest.parent)
    tmp = Path(tmp_name)
    try:
        digest, n = _stream(entry.url, fd, timeout, progress, entry.filename)
        if entry.size is not None and n != entry.size:
            raise ModelDownloadError(
                f"{entry.url}: got {n} bytes, expected {entry.size} (truncated or changed upstream)"
            )
        if sha is not None and digest != sha:
            raise ModelDownloadError(
                f"{entry.url}: sha256 mismatch: got {digest}, expected "
                f"{sha}; the file was discarded"
            )
        if sha is None:
            logger.warning(
                "!!! %s has NO pinned sha256 (upstream publishes none): the downloaded file "
                "is unverified. Its sha256 is %s; pin it with %s=%s !!!",
                name,
                digest,
                _env_key(name),
                digest,
            )
        os.replace(tmp, dest)
    except urllib.error.HTTPError as e:
        raise ModelDownloadError(
            f"cannot download depth model {name!r} from {entry.url}: HTTP {e.code} "
            f"{e.reason}; {_manual_hint(entry, dest)}"
        ) from None
    except urllib.error.URLError as e:
        raise ModelDownloadError(
            f"cannot download depth model {name!r} from {entry.url} "
            f"({getattr(e, 'reason', e)}): offline? {_manual_hint(entry, dest)}"
        ) from None
    except (OSError, http.client.HTTPException) as e:
        raise ModelDownloadError(
            f"download of {name!r} from {entry.url} failed ({type(e).__name__}: {e}); "
            f"{_manual_hint(entry, dest)}"
        ) from None
    finally:
        if tmp.exists():
            tmp.unlink()
    return digest, n


def _stream(url: str, fd: int, timeout: float, progress: bool, label: str) -> tuple[str, int]:
    """Copy ``url`` into the open file descriptor ``fd`` -> (sha256 hex, byte count).
    Raises when fewer bytes arrive than the server announced."""
    from tqdm import tqdm

    h, n = hashlib.sha256(), 0
    with os.fdopen(fd, "wb") as f, urllib.request.urlopen(url, timeout=timeout) as r:
        total = r.headers.get("Content-Length")
        total = int(total) if total and total.isdigit() else None
        with tqdm(total=total, unit="B", unit_scale=True, desc=label, disable=not progress) as bar:
            while True:
                block = r.read(CHUNK)
                if not block:
                    break
                f.write(block)
                h.update(block)
                n += len(block)
                bar.update(len(block))
        if total is not None and n != total:
            raise ModelDownloadError(f"{url}: connection closed after {n} of {total} bytes")
    return h.hexdigest(), n


# ---------------------------------------------------------------------------------------
# Resolution


def resolve_model(name_or_path: str | Path, download_missing: bool = True) -> Path:
    """A registry name or a path -> path of an existing .onnx file (downloading when
    needed and allowed)."""
    s = str(name_or_path)
    if s in REGISTRY:
        entry = REGISTRY[s]
        path = model_path(s)
        if path.is_file():
            return path
        if entry.embedded or download_missing:
            return download(s)
        raise FileNotFoundError(
            f"depth model {s!r} is not in the cache ({path}); run "
            f"`rectified-colmap models download {s}`"
        )
    path = Path(name_or_path).expanduser()
    if path.is_file():
        return path
    if path.suffix == ".onnx" or os.sep in s or "/" in s:
        raise FileNotFoundError(f"{path}: depth model file does not exist")
    raise ValueError(
        f"unknown depth model {s!r}; known: {', '.join(REGISTRY)} (or give a path to an .onnx file)"
    )


def load_depth_source(name_or_path: str | Path, **kwargs):
    """OnnxDepthSource for a registry name or a path; ``kwargs`` go to OnnxDepthSource
    (providers, num_threads, ...). The registry's spec is the fallback contract."""
    path = resolve_model(name_or_path)
    entry = REGISTRY.get(str(name_or_path))
    if entry is not None and entry.spec is not None and "spec" not in kwargs:
        kwargs["spec"] = dataclasses.replace(entry.spec)
    return OnnxDepthSource(path, **kwargs)
