"""Training data: a pool of pre-rendered street views (.npz) + on-the-fly augmentation.

A sample (numpy, as stored): ``image`` (H, W, 3) uint8 RGB, ``depth`` (H, W) float32 z-depth
(0 = invalid/sky), ``normals`` (H, W, 3) float16 camera-frame unit normals toward the camera
(0 = invalid), ``K`` (3, 3) float64 in the COLMAP pixel convention (centre of the top-left
pixel at (0.5, 0.5)).

A training item (torch, from :class:`PoolDataset`): ``image`` (3, h, w) float32 normalised
as the network expects (``p / 128 - 127 / 128``), ``depth`` (1, h, w), ``normals`` (3, h, w),
``K`` (3, 3) float32 of the crop, ``sky`` (1, h, w) (1 sky, 0 not, 255 unknown), ``real`` ()
1 for real photos, ``frame`` (3, 3) float32 the photo's trusted Manhattan frame in the crop's
camera frame (rows: unit directions; NaN where none, and on renders). Geometric
augmentation (random zoom-crop, horizontal flip) keeps K, depth, normals and frame exact;
photometric augmentation (exposure, gamma, colour, saturation, haze, blur, noise, JPEG)
touches only the image.

Views are rendered by :func:`render_pool` with ``rectified_colmap_research.synth`` (street,
corner and square scenes, procedural or photo facades, random cameras: :func:`synth_sample`).
"""

from __future__ import annotations

import logging
from pathlib import Path

import cv2
import numpy as np

from rectified_colmap_research import synth
from rectified_colmap.conventions import to_opencv_homography
from rectified_colmap.parallel import context
from rectified_colmap.demo.render import pinhole_K

logger = logging.getLogger(__name__)

_TEXTURE_DIR: str | None = None
_TREE_PROB = 0.0
_CLOUD_PROB = 0.0


def synth_sample(
    seed: int,
    width: int,
    height: int,
    texture_dir: str | Path | None = None,
    supersample: int = 2,
    tree_prob: float = 0.0,
    cloud_prob: float = 0.0,
) -> dict:
    """One training view from ``rectified_colmap_research.synth.random_sample`` in the pool
    format (see the module docstring), plus ``R`` (3, 3): cam_from_world rotation (the
    scenes are built on the world axes, so ``R.T``'s rows are the true dominant directions;
    trees, with ``tree_prob``, have no direction)."""
    r = synth.random_sample(
        np.random.default_rng(seed),
        width,
        height,
        None if texture_dir is None else str(texture_dir),
        supersample,
        tree_prob=tree_prob,
        cloud_prob=cloud_prob,
    )
    valid = np.isfinite(r.depth)
    return {
        "image": r.image,
        "depth": np.where(valid, r.depth, 0).astype(np.float32),
        "normals": np.where(valid[..., None], r.normals, 0).astype(np.float32),
        "K": pinhole_K(r.camera),
        "R": r.cam_from_world.rotation.matrix(),
    }


def _init_worker(texture_dir, tree_prob=0.0, cloud_prob=0.0):
    global _TEXTURE_DIR, _TREE_PROB, _CLOUD_PROB
    cv2.setNumThreads(1)
    _TEXTURE_DIR = None if texture_dir is None else str(texture_dir)
    _TREE_PROB, _CLOUD_PROB = float(tree_prob), float(cloud_prob)


def _render_one(args) -> str:
    seed, width, height, out_dir = args
    path = Path(out_dir) / f"{seed:08d}.npz"
    if path.exists():
        return str(path)
    s = synth_sample(
        seed, width, height, _TEXTURE_DIR, tree_prob=_TREE_PROB, cloud_prob=_CLOUD_PROB
    )
    tmp = path.with_suffix(".tmp.npz")
    np.savez(
        tmp, image=s["image"], depth=s["depth"], normals=s["normals"].astype(np.float16), K=s["K"]
    )
    tmp.replace(path)
    return str(path)


def render_pool(
    out_dir: str | Path,
    seeds,
    width: int = 320,
    height: int = 240,
    texture_dir: str | Path | None = None,
    processes: int = 2,
    tree_prob: float = 0.0,
    cloud_prob: float = 0.0,
) -> list[Path]:
    """Render (or reuse) one view per seed into ``out_dir/<seed>.npz``; returns the paths.
    A file already there is reused whatever ``tree_prob`` / ``cloud_prob`` made it: one
    folder per setting."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    jobs = [(int(s), width, height, str(out_dir)) for s in seeds]
    if processes <= 1:
        _init_worker(texture_dir, tree_prob, cloud_prob)
        paths = [_render_one(j) for j in jobs]
    else:
        with context([__name__]).Pool(  # never forked: rectified_colmap.parallel
            processes, _init_worker, (texture_dir, tree_prob, cloud_prob)
        ) as pool:
            paths = []
            for i, p in enumerate(pool.imap(_render_one, jobs, chunksize=4)):
                paths.append(p)
                if (i + 1) % 200 == 0:
                    logger.info("rendered %d / %d views", i + 1, len(jobs))
    return [Path(p) for p in paths]


def load_sample(path: str | Path) -> dict:
    try:
        with np.load(path) as z:
            return {k: z[k] for k in ("image", "depth", "normals", "K")}
    except (OSError, KeyError, ValueError) as e:
        raise ValueError(f"{path}: not a training sample ({e})") from None


# -- augmentation ------------------------------------------------------------------------
def random_zoom_crop(
    s: dict, rng: np.random.Generator, out_h: int, out_w: int, min_zoom: float = 1.0
) -> dict:
    """Crop a random window and resize it to (out_h, out_w); K follows exactly."""
    h, w = s["depth"].shape
    zmax = min(h / out_h, w / out_w)
    scale = rng.uniform(min(min_zoom, zmax), zmax)  # source pixels per output pixel
    ch, cw = out_h * scale, out_w * scale
    y0, x0 = rng.uniform(0, h - ch), rng.uniform(0, w - cw)
    a = np.array([[1 / scale, 0, -x0 / scale], [0, 1 / scale, -y0 / scale]])
    # a maps COLMAP coordinates of the source to the output; cv2 wants OpenCV coordinates
    a_cv = to_opencv_homography(np.vstack([a, [0.0, 0.0, 1.0]]))[:2]
    warp = dict(dsize=(out_w, out_h), borderMode=cv2.BORDER_REPLICATE)
    out = {
        "image": cv2.warpAffine(
            s["image"], a_cv, flags=cv2.INTER_AREA if scale > 1.3 else cv2.INTER_LINEAR, **warp
        ),
        "depth": cv2.warpAffine(s["depth"], a_cv, flags=cv2.INTER_NEAREST, **warp),
        "normals": cv2.warpAffine(
            s["normals"].astype(np.float32), a_cv, flags=cv2.INTER_NEAREST, **warp
        ),
    }
    if "sky" in s:
        out["sky"] = cv2.warpAffine(s["sky"], a_cv, flags=cv2.INTER_NEAREST, **warp)
    if "frame" in s:  # a zoom and a shift of the pixels: camera directions do not change
        out["frame"] = s["frame"]
    K = np.array(s["K"], np.float64).copy()
    K[:2] = np.concatenate([a[:, :2] @ K[:2, :2], (a[:, :2] @ K[:2, 2:] + a[:, 2:])], 1)
    out["K"] = K
    return out


def hflip(s: dict) -> dict:
    w = s["depth"].shape[1]
    n = s["normals"][:, ::-1].copy()
    n[..., 0] *= -1
    K = s["K"].copy()
    K[0, 2] = w - K[0, 2]
    out = {
        "image": s["image"][:, ::-1].copy(),
        "depth": s["depth"][:, ::-1].copy(),
        "normals": n,
        "K": K,
    }
    if "sky" in s:
        out["sky"] = s["sky"][:, ::-1].copy()
    if "frame" in s:  # rows are directions: mirror their x
        out["frame"] = s["frame"] * np.array([-1.0, 1.0, 1.0])
    return out


def photometric(image: np.ndarray, depth: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Heavy photometric augmentation of a uint8 RGB image (uses depth only for haze)."""
    x = image.astype(np.float32) / 255.0
    if rng.random() < 0.3:  # haze: x * t + A (1 - t), t = exp(-beta z); sky fully hazed
        z = np.where(depth > 0, depth, np.inf)
        zm = np.median(depth[depth > 0]) if (depth > 0).any() else 10.0
        beta = -np.log(rng.uniform(0.5, 0.95)) / max(zm, 1e-3)
        t = np.exp(-beta * z)[..., None]
        sky = (depth <= 0)[..., None]
        air = rng.uniform(0.6, 1.0) * rng.uniform(0.9, 1.0, 3)
        x = np.where(sky, x, x * t + air * (1 - t))
    x = x * rng.uniform(0.5, 1.6)  # exposure
    x = x * rng.uniform(0.85, 1.15, 3)  # white balance / colour
    grey = x.mean(-1, keepdims=True)
    sat = 0.0 if rng.random() < 0.1 else rng.uniform(0.5, 1.5)
    x = grey + (x - grey) * sat
    x = np.clip(x, 0, 1) ** rng.uniform(0.7, 1.4)  # gamma
    if rng.random() < 0.3:  # vignetting
        h, w = x.shape[:2]
        yy, xx = np.mgrid[:h, :w]
        r2 = ((xx - w / 2) ** 2 + (yy - h / 2) ** 2) / (w * w / 4 + h * h / 4)
        x = x * (1 - rng.uniform(0, 0.4) * r2)[..., None]
    if rng.random() < 0.5:
        x = cv2.GaussianBlur(x, (0, 0), rng.uniform(0.3, 1.5))
    if rng.random() < 0.7:
        x = x + rng.normal(0, rng.uniform(0.003, 0.04), x.shape).astype(np.float32)
    out = np.clip(x * 255 + 0.5, 0, 255).astype(np.uint8)
    if rng.random() < 0.5:
        ok, buf = cv2.imencode(
            ".jpg", out[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, int(rng.integers(25, 96))]
        )
        out = cv2.imdecode(buf, cv2.IMREAD_COLOR)[..., ::-1]
    return np.ascontiguousarray(out)


def normalise(image: np.ndarray) -> np.ndarray:
    """uint8 (H, W, 3) RGB -> float32 (3, H, W) as the network expects."""
    return image.astype(np.float32).transpose(2, 0, 1) / 128.0 - 127.0 / 128.0


def augment(
    s: dict, rng: np.random.Generator, out_h: int, out_w: int, photometric_aug: bool = True
) -> dict:
    s = random_zoom_crop(s, rng, out_h, out_w)
    if rng.random() < 0.5:
        s = hflip(s)
    real = "sky" in s  # real photos: sparse depth, so no depth-dependent haze
    haze_depth = np.zeros_like(s["depth"]) if real else s["depth"]
    img = photometric(s["image"], haze_depth, rng) if photometric_aug else s["image"]
    sky = s["sky"] if real else np.where(s["depth"] > 0, 0, 1).astype(np.uint8)
    return {
        "image": normalise(img),
        "depth": s["depth"][None].astype(np.float32),
        "normals": np.ascontiguousarray(s["normals"].transpose(2, 0, 1), np.float32),
        "K": s["K"].astype(np.float32),
        "sky": sky[None].astype(np.float32),
        "real": np.float32(real),
        "frame": np.asarray(s.get("frame", np.full((3, 3), np.nan)), np.float32),
    }


class PoolDataset:
    """Map-style dataset over pool files, augmented per item, optionally mixed with real
    photos (:mod:`rectified_colmap_research.training.real` samples) at rate ``real_frac``.

    ``paths``: render files, loaded once into memory; or ``pool_dir``: a folder that may
    still be growing (renderers running beside training), re-listed every
    ``refresh_every`` items per worker, each item read from disk. ``__len__`` is
    ``length``; the randomness of item ``i`` depends only on (seed, i) and the files
    present, so a run over a fixed pool is reproducible from its seed."""

    def __init__(
        self,
        paths=(),
        out_h: int = 192,
        out_w: int = 256,
        seed: int = 0,
        length: int = 10**7,
        photometric_aug: bool = True,
        real_paths=(),
        real_frac: float = 0.0,
        pool_dir: str | Path | None = None,
        refresh_every: int = 200,
    ):
        import torch  # noqa: F401  (torch tensors returned)

        from .real import load_real_sample

        self.samples = [load_sample(p) for p in paths]
        self.pool_dir = None if pool_dir is None else Path(pool_dir)
        self.files: list[Path] = []
        self.refresh_every, self._since = refresh_every, None
        self.real = [load_real_sample(p) for p in real_paths]
        for r in self.real:  # camera-less photos: any valid K (they carry no geometry)
            if not np.isfinite(r["K"]).all():
                h, w = r["depth"].shape
                r["K"] = np.array([[w, 0, w / 2], [0, w, h / 2], [0, 0, 1.0]])
        self.real_frac = real_frac if self.real else 0.0
        if not self.samples and self.pool_dir is None:
            raise ValueError("PoolDataset: no training samples")
        self.out_h, self.out_w, self.seed, self.length = out_h, out_w, seed, length
        self.photometric_aug = photometric_aug

    def __len__(self):
        return self.length

    def _render(self, rng: np.random.Generator) -> dict:
        if self.samples:
            return self.samples[rng.integers(len(self.samples))]
        if self._since is None or self._since >= self.refresh_every or not self.files:
            self.files = sorted(self.pool_dir.glob("*[0-9].npz"))
            self._since = 0
            if not self.files:
                raise ValueError(f"{self.pool_dir}: no rendered views yet")
        self._since += 1
        return load_sample(self.files[rng.integers(len(self.files))])

    def __getitem__(self, i):
        import torch

        rng = np.random.default_rng([self.seed, i])
        if self.real_frac and rng.random() < self.real_frac:
            s = self.real[rng.integers(len(self.real))]
        else:
            s = self._render(rng)
        a = augment(s, rng, self.out_h, self.out_w, self.photometric_aug)
        return {k: torch.from_numpy(np.ascontiguousarray(v)) for k, v in a.items()}
