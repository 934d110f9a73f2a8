"""`rectified-colmap extract`: COLMAP-style feature extraction into a database / hloc file."""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path

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
        type=int,
        nargs="?",
        const=1,
        default=0,
        help="all new images share one camera (COLMAP semantics)",
    )
    p.add_argument(
        "--max_num_features",
        "--SiftExtraction.max_num_features",
        dest="max_num_features",
        type=int,
        default=None,
        help="feature budget per image, shared by patches and the rest "
        "(default: the configuration's, "
        f"{ExtractConf.from_dict(confs['rectsift']).sift.max_num_features} in "
        "rectsift)",
    )
    p.add_argument(
        "--conf",
        default="rectsift",
        help=f"named configuration ({', '.join(confs)}; default %(default)s; "
        "rectsift-plus: every plain SIFT feature plus rectified ones on top, the most "
        "matches on strong viewpoint changes at up to 1.75x plain SIFT's time) or a JSON "
        'file of overrides, e.g. {"rectify": {"max_viewing_angle_deg": 85}}',
    )
    p.add_argument(
        "--orientation",
        choices=["depth", "vp", "depth+vp"],
        default=None,
        help="plane orientations from depth normals only (vp.enabled off), "
        "depth refined by vanishing points (depth+vp: vp.enabled), or "
        "vanishing points also for images without depth (vp: vp.enabled "
        "and vp.depth_free; with --depth_model none: lines only). "
        "Default: as in --conf",
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
    p.add_argument("--visualize", type=Path, help="write PNGs of planes and patches here")
    p.add_argument("--no_progress", action="store_true")
    p.set_defaults(func=run)


def _load_conf(spec: str, max_num_features: int | None):
    from ..config import ExtractConf, confs

    if spec in confs:
        conf = ExtractConf.from_dict(confs[spec])
    else:
        path = Path(spec)
        if not path.is_file():
            raise SystemExit(
                f"--conf {spec!r}: neither a named configuration "
                f"({', '.join(confs)}) nor a JSON file"
            )
        try:
            conf = ExtractConf.from_dict(json.loads(path.read_text()))
        except (ValueError, KeyError) as e:
            raise SystemExit(f"--conf {path}: {e}") from None
    if max_num_features is not None:
        conf.sift.max_num_features = max_num_features
    return conf


def run(args: argparse.Namespace) -> int:
    from ..extract import extract

    if args.database is None and args.hloc_features is None:
        raise SystemExit("give --database and/or --hloc_features")
    conf = _load_conf(args.conf, args.max_num_features)
    if getattr(args, "orientation", None) is not None:
        conf.vp.enabled = args.orientation != "depth"
        conf.vp.depth_free = args.orientation == "vp"
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
        single_camera=bool(args.single_camera),
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
