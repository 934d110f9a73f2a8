"""Sky labelled planar: how much of the GT sky gets a plane label (issue 10's sky target).

    python -m rectified_colmap_research.training.evaluate_sky MODEL.onnx \\
        --labels research/data/sky_masks \\
        [--data /work/shared/data] [--output results.json]

For each image with a hand-checked sky mask (``research/data/sky_masks/<set>/<stem>.png``: uint8,
0 = not sky, 1 = sky, 255 = ignore, at the stored image size) the depth runs through the
same stages as extraction (:func:`rectified_colmap.pipeline.extract_image`):
:func:`~rectified_colmap.disparity.resolve_disparity`,
:func:`~rectified_colmap.normals.depth_to_normals` on the work grid and
:func:`~rectified_colmap.planes.detect_planes`. The plane labels (work grid, -1 =
non-planar) are upsampled nearest to the mask size. Reported per image and pooled over all
pixels of all images (255 ignored):

- ``sky_planar``: (# sky pixels with a plane label >= 0) / (# sky pixels), the target
  (issue 10: <= 2 %);
- ``sky_patch``: the same for pixels inside a kept plane patch (labels that survive the
  opening and the minimum area: the pixels rectification can use);
- ``notsky_planar``: (# not-sky pixels with a plane label) / (# not-sky pixels), so that a
  model that labels nothing planar is visible.

Labels count before vanishing-point orientation and line hypotheses (which re-orient or add
patches but never change which pixels the depth labels planar).

Cameras: the set's own where known (Strecha's ``sparse/``), else the guess the CLI makes
for images without EXIF: a SIMPLE_PINHOLE with focal 1.2 * max(W, H) and a centred
principal point (pycolmap.infer_camera_from_image).
"""

from __future__ import annotations

import argparse
import json
import logging
from collections.abc import Callable, Iterable
from pathlib import Path

import cv2
import numpy as np
import pycolmap

from rectified_colmap import camera as cam_utils
from rectified_colmap.config import ExtractConf
from rectified_colmap.depth import DepthMap
from rectified_colmap.disparity import resolve_disparity
from rectified_colmap.normals import depth_to_normals
from rectified_colmap.planes import detect_planes
from .sky import NOT_SKY, SKY, UNKNOWN

logger = logging.getLogger(__name__)

IGNORE = UNKNOWN
"""Mask value of pixels left out of the metric (the pseudo-labels' UNKNOWN)."""
DEFAULT_DATA = Path("/work/shared/data")
GUESS_FOCAL = 1.2
"""Focal of the guessed camera, times the longer side (COLMAP's default without EXIF)."""

SKY_MASKS = Path(__file__).resolve().parents[2] / "data" / "sky_masks"
"""The hand-checked sky masks of the research folder (research/data/sky_masks)."""


def guess_camera(width: int, height: int) -> pycolmap.Camera:
    """SIMPLE_PINHOLE, focal GUESS_FOCAL * max(W, H), principal point at the centre."""
    f = GUESS_FOCAL * max(width, height)
    return cam_utils.make_camera("SIMPLE_PINHOLE", [f, width / 2.0, height / 2.0], width, height)


def plane_labels(
    depth: DepthMap,
    camera: pycolmap.Camera,
    conf: ExtractConf | None = None,
    rng: np.random.Generator | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Depth -> (labels (h, w) int8 on the work grid, -1 = non-planar; in_patch (h, w) bool:
    inside a kept plane patch), through the stages extraction uses."""
    conf = conf or ExtractConf()
    rng = rng if rng is not None else np.random.default_rng(0)
    depth = resolve_disparity(depth, camera, conf)
    normals = depth_to_normals(depth, camera, conf.normals)
    planes = detect_planes(normals, conf.planes, rng)
    in_patch = np.zeros(planes.labels.shape, bool)
    for p in planes.patches:
        in_patch |= p.mask
    return planes.labels, in_patch


def upsample_nearest(a: np.ndarray, width: int, height: int) -> np.ndarray:
    """(h, w) grid covering the image -> (height, width), each pixel taking the cell its
    centre falls in (the convention of conventions.pixel_centers)."""
    h, w = a.shape
    rows = np.minimum(((np.arange(height) + 0.5) * h / height).astype(int), h - 1)
    cols = np.minimum(((np.arange(width) + 0.5) * w / width).astype(int), w - 1)
    return a[rows[:, None], cols[None, :]]


def _counts(mask: np.ndarray, planar: np.ndarray, in_patch: np.ndarray) -> dict[str, int]:
    sky, not_sky = mask == SKY, mask == NOT_SKY
    return {
        "sky": int(sky.sum()),
        "sky_planar": int((sky & planar).sum()),
        "sky_patch": int((sky & in_patch).sum()),
        "notsky": int(not_sky.sum()),
        "notsky_planar": int((not_sky & planar).sum()),
    }


def _fractions(c: dict[str, int]) -> dict[str, float]:
    def frac(a, b):
        return c[a] / c[b] if c[b] else float("nan")

    return {
        "sky_planar": frac("sky_planar", "sky"),
        "sky_patch": frac("sky_patch", "sky"),
        "notsky_planar": frac("notsky_planar", "notsky"),
    }


def read_mask(path: str | Path) -> np.ndarray:
    """(H, W) uint8 mask with values in {0, 1, 255}; ValueError otherwise."""
    m = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if m is None or m.ndim != 2 or m.dtype != np.uint8:
        raise ValueError(f"{path}: not a single-channel uint8 PNG")
    bad = ~np.isin(m, (NOT_SKY, SKY, IGNORE))
    if bad.any():
        raise ValueError(f"{path}: values {np.unique(m[bad])[:5]} outside {{0, 1, 255}}")
    return m


def sky_planar_fraction(
    depth_for: Callable[[Path, np.ndarray], DepthMap],
    items: Iterable[tuple[str | Path, str | Path, pycolmap.Camera | None]],
    conf: ExtractConf | None = None,
) -> dict:
    """Fraction of GT sky pixels labelled planar, per image and pooled.

    depth_for(path, rgb) -> DepthMap of one image (rgb (H, W, 3) uint8). items: (image path,
    mask path, camera or None for the guessed camera, see :func:`guess_camera`); the mask
    must have the image's size. Returns {"rows": [per image: image, mask, counts and
    fractions], "pooled": fractions over all pixels, "mean": mean of the per-image
    fractions (NaN rows skipped), "median_sky_planar", "max_sky_planar", "num_images"}.
    """
    conf = conf or ExtractConf()
    rows, total = [], None
    for image_path, mask_path, camera in items:
        image_path = Path(image_path)
        bgr = cv2.imread(str(image_path), cv2.IMREAD_COLOR)
        if bgr is None:
            raise ValueError(f"{image_path}: cannot read image")
        rgb = np.ascontiguousarray(bgr[..., ::-1])
        H, W = rgb.shape[:2]
        mask = read_mask(mask_path)
        if mask.shape != (H, W):
            raise ValueError(f"{mask_path}: mask {mask.shape} but image {(H, W)}")
        camera = camera if camera is not None else guess_camera(W, H)
        if (camera.width, camera.height) != (W, H):
            raise ValueError(f"{image_path}: image {W}x{H}, camera {camera.width}x{camera.height}")
        labels, in_patch = plane_labels(depth_for(image_path, rgb), camera, conf)
        planar = upsample_nearest(labels >= 0, W, H)
        c = _counts(mask, planar, upsample_nearest(in_patch, W, H))
        total = c if total is None else {k: total[k] + v for k, v in c.items()}
        rows.append({"image": str(image_path), "mask": str(mask_path), **c, **_fractions(c)})
        logger.info(
            "%s: sky planar %.3f (in patches %.3f), not-sky planar %.3f",
            image_path.name,
            *(rows[-1][k] for k in ("sky_planar", "sky_patch", "notsky_planar")),
        )
    if not rows:
        raise ValueError("sky_planar_fraction: no items")
    keys = ("sky_planar", "sky_patch", "notsky_planar")
    sky_fracs = np.array([r["sky_planar"] for r in rows], float)
    sky_fracs = sky_fracs[np.isfinite(sky_fracs)]
    return {
        "num_images": len(rows),
        "pooled": _fractions(total),
        "mean": {k: float(np.nanmean([r[k] for r in rows])) for k in keys},
        "median_sky_planar": float(np.median(sky_fracs)) if sky_fracs.size else float("nan"),
        "max_sky_planar": float(sky_fracs.max()) if sky_fracs.size else float("nan"),
        "counts": total,
        "rows": rows,
    }


def find_items(
    labels: str | Path, data: str | Path = DEFAULT_DATA
) -> list[tuple[Path, Path, pycolmap.Camera | None]]:
    """Masks ``labels/<set>/<stem>.png`` -> (image, mask, camera) items. ``eurasian-cities``
    -> ``data/real-pool/eurasian-cities/images/<stem>.jpg`` (guessed camera: no EXIF, no
    focal); a Strecha scene ``<scene>`` -> ``data/strecha-dev/<scene>/images/<stem>.jpg`` with
    its camera from ``sparse/``; any other set -> ``data/real-pool/<set>/images`` (guessed
    camera)."""
    labels, data = Path(labels), Path(data)
    items = []
    for set_dir in sorted(p for p in labels.iterdir() if p.is_dir()):
        strecha = data / "strecha-dev" / set_dir.name
        cams = {}
        if strecha.is_dir():
            image_dir = strecha / "images"
            rec = pycolmap.Reconstruction(str(strecha / "sparse"))
            cams = {im.name: rec.cameras[im.camera_id] for im in rec.images.values()}
        else:
            image_dir = data / "real-pool" / set_dir.name / "images"
        for mask in sorted(set_dir.glob("*.png")):
            found = [p for p in image_dir.glob(mask.stem + ".*") if p.suffix.lower() != ".png"]
            if not found:
                raise FileNotFoundError(f"{mask}: no image {mask.stem}.* in {image_dir}")
            items.append((found[0], mask, cams.get(found[0].name)))
    if not items:
        raise ValueError(f"{labels}: no masks (<set>/<stem>.png)")
    return items


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description="fraction of GT sky pixels labelled planar")
    p.add_argument("model", type=Path, help="ONNX depth model")
    p.add_argument("--labels", type=Path, default=SKY_MASKS)
    p.add_argument("--data", type=Path, default=DEFAULT_DATA, help="shared data root")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--output", type=Path, default=None, help="JSON of the results")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(message)s")
    from rectified_colmap.depth.onnx import OnnxDepthSource

    items = find_items(args.labels, args.data)
    cameras = {Path(i): c for i, _, c in items}
    src = OnnxDepthSource(args.model, providers=["CPUExecutionProvider"], num_threads=args.threads)
    res = sky_planar_fraction(lambda path, rgb: src(rgb, cameras.get(Path(path))), items)
    res["model"] = str(args.model)
    print(f"{'image':<34} {'sky px':>8} {'sky planar':>10} {'in patch':>9} {'not-sky planar':>14}")
    for r in res["rows"]:
        name = "/".join(Path(r["image"]).parts[-3::2])
        print(
            f"{name:<34} {r['sky']:>8d} {r['sky_planar']:>10.3f} {r['sky_patch']:>9.3f} "
            f"{r['notsky_planar']:>14.3f}"
        )
    pooled, mean = res["pooled"], res["mean"]
    print(
        f"{'pooled':<34} {res['counts']['sky']:>8d} {pooled['sky_planar']:>10.3f} "
        f"{pooled['sky_patch']:>9.3f} {pooled['notsky_planar']:>14.3f}"
    )
    print(
        f"{'mean over images':<34} {'':>8} {mean['sky_planar']:>10.3f} "
        f"{mean['sky_patch']:>9.3f} {mean['notsky_planar']:>14.3f}"
    )
    print(
        f"sky planar per image: median {res['median_sky_planar']:.3f}, "
        f"max {res['max_sky_planar']:.3f} ({res['num_images']} images)"
    )
    if args.output:
        args.output.write_text(json.dumps(res, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
