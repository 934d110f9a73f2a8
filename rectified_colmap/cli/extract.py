"""`rectified-colmap extract`: COLMAP-style feature extraction into a database / hloc file."""

from __future__ import annotations

import argparse
import json
import logging
import os
from pathlib import Path

from . import UsageError, bool_flag_value, positive_int

logger = logging.getLogger(__name__)


def register(sub: argparse._SubParsersAction) -> None:
    from ..config import (
        DEFAULT_CAMERA_MODEL,
        DEFAULT_DEPTH_MODEL,
        DEFAULT_PNG_SCALE,
        ExtractConf,
        confs,
    )

    p = sub.add_parser(
        "extract",
        help="extract rectified SIFT into a COLMAP database and/or hloc HDF5",
        description="Drop-in replacement of `colmap feature_extractor`: writes rectified "
        "SIFT (keypoints with affine shape, SIFT descriptors) so that "
        "`colmap exhaustive_matcher`/`mapper` and hloc consume them unchanged.",
    )
    p.add_argument(
        "--database",
        "--database_path",
        dest="database",
        type=Path,
        help="COLMAP database to create or complete",
    )
    p.add_argument("--image_path", type=Path, required=True, help="root folder of the images")
    p.add_argument(
        "--image_list",
        "--image_list_path",
        dest="image_list",
        type=Path,
        help="text file of image names (relative to --image_path) to process",
    )
    p.add_argument("--hloc_features", type=Path, help="also write an hloc feature HDF5 file")
    p.add_argument(
        "--depth_path",
        type=Path,
        help="folder of depth maps: sub/0001.jpg -> sub/0001.jpg.npy, sub/0001.npy, "
        ".npz, 16-bit .png, COLMAP .geometric.bin/.photometric.bin",
    )
    p.add_argument(
        "--depth_kind",
        default="depth",
        choices=["depth", "metric", "disparity"],
        help="what the depth files hold (default %(default)s: z-depth up to scale)",
    )
    p.add_argument(
        "--depth_png_scale",
        type=float,
        default=DEFAULT_PNG_SCALE,
        help="16-bit PNG depth = value x scale (default %(default)s: millimetres)",
    )
    p.add_argument(
        "--depth_model",
        default=DEFAULT_DEPTH_MODEL,
        help="depth network for images without a depth file: a registry name "
        "(`rectified-colmap models list`), a path to an .onnx, or 'none' "
        "(default %(default)s)",
    )
    p.add_argument(
        "--camera_model",
        "--ImageReader.camera_model",
        dest="camera_model",
        help=f"COLMAP camera model for new cameras (default: {DEFAULT_CAMERA_MODEL} from EXIF)",
    )
    p.add_argument(
        "--camera_params",
        "--ImageReader.camera_params",
        dest="camera_params",
        help="comma-separated params in COLMAP's order and pixel convention, e.g. "
        "fx,fy,cx,cy for PINHOLE",
    )
    p.add_argument(
        "--single_camera",
        "--ImageReader.single_camera",
        dest="single_camera",
        type=bool_flag_value,
        default=False,
        help="all new images share one camera (COLMAP's; alone or with 0/1)",
    )
    p.add_argument(
        "--single_camera_per_folder",
        "--ImageReader.single_camera_per_folder",
        dest="single_camera_per_folder",
        type=bool_flag_value,
        default=False,
        help="new images in the same folder share one camera (COLMAP's; 0/1)",
    )
    p.add_argument(
        "--mask_path",
        "--ImageReader.mask_path",
        dest="mask_path",
        type=Path,
        help="COLMAP's keypoint masks: MASKS/sub/0001.jpg.png for sub/0001.jpg; no features "
        "where the mask is black (images without a mask file are not masked)",
    )
    p.add_argument(
        "--default_focal_length_factor",
        "--ImageReader.default_focal_length_factor",
        dest="default_focal_length_factor",
        type=float,
        default=1.2,
        help="focal length guess for images without EXIF: this x the larger side "
        "(COLMAP's; default %(default)s)",
    )
    p.add_argument(
        "--max_num_features",
        "--SiftExtraction.max_num_features",
        dest="max_num_features",
        type=positive_int,
        default=None,
        help="plain SIFT's budget per image, as COLMAP's (it counts detected points; a "
        "point with two orientations gives two keypoints, as in COLMAP); the rectified "
        "features come on top, at most dedup.extra_frac of plain SIFT's keypoints "
        f"({100 * ExtractConf().dedup.extra_frac:.0f} %% in rectsift). Default: the "
        f"configuration's, {ExtractConf.from_dict(confs['rectsift']).sift.max_num_features} "
        "in rectsift",
    )
    p.add_argument(
        "--conf",
        default="rectsift",
        help=f"named configuration ({', '.join(confs)}; default %(default)s: plain SIFT's "
        "features and rectified ones on top) or a JSON file of overrides, e.g. "
        '{"sift": {"max_num_features": 4096}}',
    )
    p.add_argument(
        "--orientation",
        choices=["depth", "depth+vp"],
        default=None,
        help="plane orientations from depth normals only (vp.enabled off) or depth refined "
        "by vanishing points (depth+vp: vp.enabled). Default: as in --conf",
    )
    p.add_argument(
        "--num_workers",
        type=int,
        default=1,
        help="worker processes (default %(default)s; with --ray: Ray actors, default there: "
        "one per CPU of the cluster)",
    )
    p.add_argument(
        "--shard",
        metavar="INDEX/COUNT",
        help="only this job's share of the images (INDEX from 0), e.g. a job "
        "array's task; combine the shards' outputs with `rectified-colmap "
        "merge`",
    )
    p.add_argument(
        "--ray",
        nargs="?",
        const="local",
        metavar="ADDRESS",
        help="run the per-image work on a Ray cluster (ray.init address, e.g. "
        "'auto' or ray://host:10001); without ADDRESS a local Ray instance. "
        "Needs `pip install 'rectified-colmap[ray]'`",
    )
    p.add_argument(
        "--overwrite",
        action="store_true",
        help="re-extract images that already have features, replacing them and "
        "deleting their matches (without it, outputs are only added to)",
    )
    p.add_argument(
        "--visualize",
        type=Path,
        help="write PNGs here: keypoints (plain vs rectified), planes and rectified patches, "
        "each with a legend (docs/usage.md)",
    )
    p.add_argument("--no_progress", action="store_true", help="no progress bar")
    add_colmap_sift_options(p)
    p.set_defaults(func=run)


COLMAP_SIFT_OPTIONS = {
    "max_image_size": int,
    "first_octave": int,
    "peak_threshold": float,
    "edge_threshold": float,
    "max_num_orientations": int,
    "upright": bool_flag_value,
}
"""COLMAP's --SiftExtraction.X options that set ``sift.X`` of the configuration."""

NOT_APPLIED = {
    "SiftExtraction.use_gpu": "SIFT runs on the CPU (pycolmap); --num_workers sets the processes",
    "SiftExtraction.gpu_index": "SIFT runs on the CPU (pycolmap)",
    "ImageReader.single_camera_per_image": "one camera per image is the default",
    "descriptor_normalization": "descriptors are COLMAP's l1_root (RootSIFT), as its default",
    "SiftExtraction.estimate_affine_shape": "affine shapes come from the rectification",
    "SiftExtraction.domain_size_pooling": "not available in rectified SIFT",
    "SiftExtraction.dsp_min_scale": "not available in rectified SIFT",
    "SiftExtraction.dsp_max_scale": "not available in rectified SIFT",
    "SiftExtraction.dsp_num_scales": "not available in rectified SIFT",
    "SiftExtraction.num_octaves": "COLMAP's default (4) is used",
    "SiftExtraction.octave_resolution": "COLMAP's default (3) is used",
    "ImageReader.camera_mask_path": "not available in rectified SIFT",
    "ImageReader.existing_camera_id": "new images get new cameras (or --single_camera)",
}
"""COLMAP feature_extractor options accepted and not applied, with why (said at INFO)."""


def add_colmap_sift_options(p: argparse.ArgumentParser) -> None:
    """COLMAP's SiftExtraction / ImageReader spellings: mapped where they have a meaning
    here, else accepted and reported as not applied."""
    g = p.add_argument_group(
        "COLMAP feature_extractor options",
        "accepted as `colmap feature_extractor` spells them; --SiftExtraction.num_threads "
        "is --num_workers (-1: one per CPU)",
    )
    g.add_argument(
        "--SiftExtraction.num_threads", dest="num_threads", type=int, help=argparse.SUPPRESS
    )
    for key, kind in COLMAP_SIFT_OPTIONS.items():
        g.add_argument(
            f"--SiftExtraction.{key}",
            dest=f"sift_{key}",
            type=kind,
            default=None,
            help=f"sets sift.{key} of --conf",
        )
    for option, why in NOT_APPLIED.items():
        g.add_argument(
            f"--{option}", dest=_not_applied_dest(option), default=None, help=f"ignored: {why}"
        )


def _not_applied_dest(option: str) -> str:
    return "not_applied_" + option.replace(".", "_")


def apply_colmap_options(args: argparse.Namespace, conf) -> None:
    """COLMAP's options into ``conf`` and ``args.num_workers``; those that do not apply said
    once each at INFO."""
    for key in COLMAP_SIFT_OPTIONS:
        value = getattr(args, f"sift_{key}", None)
        if value is not None:
            setattr(conf.sift, key, value)
    if args.num_threads is not None:
        args.num_workers = (os.cpu_count() or 1) if args.num_threads <= 0 else args.num_threads
    for option, why in NOT_APPLIED.items():
        value = getattr(args, _not_applied_dest(option), None)
        if value is not None:
            logger.info("--%s %s: not applied (%s)", option, value, why)


def _load_conf(spec: str, max_num_features: int | None):
    from ..config import RETIRED_CONFS, ExtractConf, confs

    if spec in RETIRED_CONFS:
        logger.warning("--conf %s is retired: %s; running the default", spec, RETIRED_CONFS[spec])
        spec = "rectsift"
    if spec in confs:
        conf = ExtractConf.from_dict(confs[spec])
    else:
        path = Path(spec)
        if not path.is_file():
            raise UsageError(
                f"--conf {spec!r}: neither a named configuration "
                f"({', '.join(confs)}) nor a JSON file"
            )
        try:
            conf = ExtractConf.from_dict(json.loads(path.read_text()))
        except (ValueError, KeyError) as e:
            raise UsageError(f"--conf {path}: {e}") from None
    if max_num_features is not None:
        conf.sift.max_num_features = max_num_features
    return conf


def run(args: argparse.Namespace) -> int:
    from ..extraction import extract

    if args.database is None and args.hloc_features is None:
        raise UsageError("give --database and/or --hloc_features")
    conf = _load_conf(args.conf, args.max_num_features)
    apply_colmap_options(args, conf)
    if getattr(args, "orientation", None) is not None:
        conf.vp.enabled = args.orientation != "depth"
    summary = extract(
        args.image_path,
        database=args.database,
        hloc_features=args.hloc_features,
        image_list=args.image_list,
        depth_path=args.depth_path,
        depth_kind=args.depth_kind,
        png_scale=args.depth_png_scale,
        depth_model=args.depth_model,
        camera_model=args.camera_model,
        camera_params=args.camera_params,
        single_camera=args.single_camera,
        single_camera_per_folder=args.single_camera_per_folder,
        focal_length_factor=args.default_focal_length_factor,
        mask_path=args.mask_path,
        conf=conf,
        num_workers=args.num_workers,
        overwrite=args.overwrite,
        visualize=args.visualize,
        progress=not args.no_progress,
        shard=args.shard,
        ray_address=args.ray,
    )
    (logger.info if summary.ok else logger.error)("summary\n%s", summary.report())
    return 0 if summary.ok else 1
