"""`rectified-colmap extract`: COLMAP-style feature extraction into a database / hloc file."""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import os
from collections.abc import Callable
from pathlib import Path
from typing import NamedTuple

from . import UsageError, bool_flag_value, positive_int

logger = logging.getLogger(__name__)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "extract",
        help="extract rectified SIFT into a COLMAP database and/or hloc HDF5",
        description="Drop-in replacement of `colmap feature_extractor`: writes rectified "
        "SIFT (keypoints with affine shape, SIFT descriptors) so that "
        "`colmap exhaustive_matcher`/`mapper` and hloc consume them unchanged.",
    )
    _add_io_options(p.add_argument_group("inputs and outputs"))
    _add_reader_options(p.add_argument_group("images and cameras (COLMAP's ImageReader)"))
    _add_depth_options(p.add_argument_group("depth"))
    _add_method_options(p.add_argument_group("method"))
    _add_run_options(p.add_argument_group("run"))
    add_colmap_sift_options(p)
    p.set_defaults(func=run)


def _add_io_options(g) -> None:
    g.add_argument(
        "--database",
        "--database_path",
        dest="database",
        type=Path,
        help="COLMAP database to create or complete",
    )
    g.add_argument("--image_path", type=Path, required=True, help="root folder of the images")
    g.add_argument("--hloc_features", type=Path, help="also write an hloc feature HDF5 file")
    g.add_argument(
        "--overwrite",
        action="store_true",
        help="re-extract images that already have features, replacing them and "
        "deleting their matches (without it, outputs are only added to)",
    )


def _add_reader_options(g) -> None:
    """Flags of ReaderConf (rectified_colmap.config), dests named as its fields."""
    from ..config import DEFAULT_CAMERA_MODEL, ReaderConf

    g.add_argument(
        "--image_list",
        "--image_list_path",
        dest="image_list",
        type=Path,
        help="text file of image names (relative to --image_path) to process",
    )
    g.add_argument(
        "--camera_model",
        "--ImageReader.camera_model",
        dest="camera_model",
        help=f"COLMAP camera model for new cameras (default: {DEFAULT_CAMERA_MODEL} from EXIF)",
    )
    g.add_argument(
        "--camera_params",
        "--ImageReader.camera_params",
        dest="camera_params",
        help="comma-separated params in COLMAP's order and pixel convention, e.g. "
        "fx,fy,cx,cy for PINHOLE",
    )
    g.add_argument(
        "--single_camera",
        "--ImageReader.single_camera",
        dest="single_camera",
        type=bool_flag_value,
        default=False,
        help="all new images share one camera (COLMAP's; alone or with 0/1)",
    )
    g.add_argument(
        "--single_camera_per_folder",
        "--ImageReader.single_camera_per_folder",
        dest="single_camera_per_folder",
        type=bool_flag_value,
        default=False,
        help="new images in the same folder share one camera (COLMAP's; 0/1)",
    )
    g.add_argument(
        "--mask_path",
        "--ImageReader.mask_path",
        dest="mask_path",
        type=Path,
        help="COLMAP's keypoint masks: MASKS/sub/0001.jpg.png for sub/0001.jpg; no features "
        "where the mask is black (images without a mask file are not masked)",
    )
    g.add_argument(
        "--default_focal_length_factor",
        "--ImageReader.default_focal_length_factor",
        dest="default_focal_length_factor",
        type=float,
        default=ReaderConf.default_focal_length_factor,
        help="focal length guess for images without EXIF: this x the larger side "
        "(COLMAP's; default %(default)s)",
    )


def _add_depth_options(g) -> None:
    """Flags of DepthInputConf: dests ``depth_<field>``."""
    from ..config import DEFAULT_DEPTH_MODEL, DEFAULT_PNG_SCALE

    g.add_argument(
        "--depth_path",
        type=Path,
        help="folder of depth maps: sub/0001.jpg -> sub/0001.jpg.npy, sub/0001.npy, "
        ".npz, 16-bit .png, COLMAP .geometric.bin/.photometric.bin",
    )
    g.add_argument(
        "--depth_kind",
        default="depth",
        choices=["depth", "metric", "disparity"],
        help="what the depth files hold (default %(default)s: z-depth up to scale)",
    )
    g.add_argument(
        "--depth_png_scale",
        dest="depth_png_scale",
        type=float,
        default=DEFAULT_PNG_SCALE,
        help="16-bit PNG depth = value x scale (default %(default)s: millimetres)",
    )
    g.add_argument(
        "--depth_model",
        default=DEFAULT_DEPTH_MODEL,
        help="depth network for images without a depth file: a registry name "
        "(`rectified-colmap models list`), a path to an .onnx, or 'none' "
        "(default %(default)s)",
    )


def _add_method_options(g) -> None:
    from ..config import ExtractConf, confs

    g.add_argument(
        "--max_num_features",
        "--SiftExtraction.max_num_features",
        dest="max_num_features",
        type=positive_int,
        default=None,
        help="plain SIFT's budget per image, as COLMAP's (it counts detected points; a "
        "point with two orientations gives two keypoints, as in COLMAP); the rectified "
        "features come on top, at most dedup.extra_frac of this budget (of plain SIFT's "
        f"keypoints where they are more; {100 * ExtractConf().dedup.extra_frac:.0f} %% in "
        "rectsift). Default: the "
        f"configuration's, {ExtractConf.from_dict(confs['rectsift']).sift.max_num_features} "
        "in rectsift",
    )
    g.add_argument(
        "--conf",
        default="rectsift",
        help=f"named configuration ({', '.join(confs)}; default %(default)s: plain SIFT's "
        "features and rectified ones on top) or a JSON file of overrides, e.g. "
        '{"sift": {"max_num_features": 4096}}',
    )
    g.add_argument(
        "--orientation",
        choices=["depth", "depth+vp"],
        default=None,
        help="plane orientations from depth normals only (vp.enabled off) or depth refined "
        "by vanishing points (depth+vp: vp.enabled). Default: as in --conf",
    )


def _add_run_options(g) -> None:
    g.add_argument(
        "--num_workers",
        type=int,
        default=1,
        help="worker processes (default %(default)s; with --ray: Ray actors, default there: "
        "one per CPU of the cluster)",
    )
    g.add_argument(
        "--shard",
        metavar="INDEX/COUNT",
        help="only this job's share of the images (INDEX from 0), e.g. a job "
        "array's task; combine the shards' outputs with `rectified-colmap "
        "merge`",
    )
    g.add_argument(
        "--ray",
        nargs="?",
        const="local",
        metavar="ADDRESS",
        help="run the per-image work on a Ray cluster (ray.init address, e.g. "
        "'auto' or ray://host:10001); without ADDRESS a local Ray instance. "
        "Needs `pip install 'rectified-colmap[ray]'`",
    )
    g.add_argument(
        "--visualize",
        type=Path,
        help="write PNGs here: keypoints (plain vs rectified), planes and rectified patches, "
        "each with a legend (docs/usage.md)",
    )
    g.add_argument("--no_progress", action="store_true", help="no progress bar")


def colmap_max_image_size(text: str) -> int:
    """``--FeatureExtraction.max_image_size`` / ``--SiftExtraction.max_image_size``: a size,
    or (COLMAP 4.x's -1) 0 or less for the extractor's default, COLMAP's 3200."""
    from ..config import SiftConf

    value = int(text)
    return value if value > 0 else SiftConf.max_image_size


FEATURE_TYPES = ("SIFT",)
"""``--FeatureExtraction.type`` values accepted: rectified SIFT is COLMAP's SIFT."""


def colmap_feature_type(text: str) -> str:
    """``--FeatureExtraction.type``: SIFT (any case); any other COLMAP type is an error."""
    if text.strip().upper() not in FEATURE_TYPES:
        raise argparse.ArgumentTypeError(
            f"{text!r}: this extractor writes SIFT only (rectified COLMAP SIFT); "
            "use `colmap feature_extractor` for other feature types"
        )
    return text.strip().upper()


class Setting(NamedTuple):
    """What a COLMAP option sets here: ``target`` (``sift.<field>`` of the configuration,
    ``num_workers`` or ``feature_type``: checked, nothing to set) and the value's type."""

    target: str
    kind: Callable[[str], object]


COLMAP_OPTIONS: dict[str, Setting | str] = {
    # COLMAP 4.x: the detector-independent options are --FeatureExtraction.*, the SIFT ones
    # stay --SiftExtraction.*; COLMAP 3.x spells them all --SiftExtraction.*
    "FeatureExtraction.type": Setting("feature_type", colmap_feature_type),
    "FeatureExtraction.max_image_size": Setting("sift.max_image_size", colmap_max_image_size),
    "SiftExtraction.max_image_size": Setting("sift.max_image_size", colmap_max_image_size),
    "FeatureExtraction.num_threads": Setting("num_workers", int),
    "SiftExtraction.num_threads": Setting("num_workers", int),
    "SiftExtraction.first_octave": Setting("sift.first_octave", int),
    "SiftExtraction.peak_threshold": Setting("sift.peak_threshold", float),
    "SiftExtraction.edge_threshold": Setting("sift.edge_threshold", float),
    "SiftExtraction.max_num_orientations": Setting("sift.max_num_orientations", int),
    "SiftExtraction.upright": Setting("sift.upright", bool_flag_value),
    # accepted, not applied (said at INFO): why
    "FeatureExtraction.use_gpu": "SIFT runs on the CPU (pycolmap); --num_workers sets the "
    "processes",
    "SiftExtraction.use_gpu": "SIFT runs on the CPU (pycolmap); --num_workers sets the processes",
    "FeatureExtraction.gpu_index": "SIFT runs on the CPU (pycolmap)",
    "SiftExtraction.gpu_index": "SIFT runs on the CPU (pycolmap)",
    "SiftExtraction.darkness_adaptivity": "COLMAP applies it on the GPU only; SIFT runs on the CPU",
    "SiftExtraction.estimate_affine_shape": "affine shapes come from the rectification",
    "SiftExtraction.domain_size_pooling": "not available in rectified SIFT",
    "SiftExtraction.dsp_min_scale": "not available in rectified SIFT",
    "SiftExtraction.dsp_max_scale": "not available in rectified SIFT",
    "SiftExtraction.dsp_num_scales": "not available in rectified SIFT",
    "SiftExtraction.num_octaves": "COLMAP's default (4) is used",
    "SiftExtraction.octave_resolution": "COLMAP's default (3) is used",
    "SiftExtraction.normalization": "descriptors are COLMAP's L1_ROOT (RootSIFT), its default",
    "descriptor_normalization": "descriptors are COLMAP's l1_root (RootSIFT), its default",
    "AlikedExtraction.max_num_features": "ALIKED features are not made here (SIFT only)",
    "AlikedExtraction.min_score": "ALIKED features are not made here (SIFT only)",
    "AlikedExtraction.n16rot_model_path": "ALIKED features are not made here (SIFT only)",
    "AlikedExtraction.n32_model_path": "ALIKED features are not made here (SIFT only)",
    "ImageReader.single_camera_per_image": "one camera per image is the default",
    "ImageReader.camera_mask_path": "not available in rectified SIFT",
    "ImageReader.existing_camera_id": "new images get new cameras (or --single_camera)",
}
"""``colmap feature_extractor``'s options (COLMAP 3.x and 4.x spellings; those with a flag
of their own, ``--ImageReader.camera_model``, ``--SiftExtraction.max_num_features``, ...,
are in :func:`register`): a :class:`Setting`, or why the option is accepted and not
applied. Spellings of one setting make one argument, the last given wins."""


def colmap_arguments() -> dict[str, list[str]]:
    """The arguments :data:`COLMAP_OPTIONS` makes: {setting target or not-applied option:
    its COLMAP spellings}, in the table's order."""
    out: dict[str, list[str]] = {}
    for option, what in COLMAP_OPTIONS.items():
        out.setdefault(what.target if isinstance(what, Setting) else option, []).append(option)
    return out


_HELP = {
    "feature_type": "SIFT (the default); any other type is an error",
    "num_workers": "= --num_workers N (0 or -1: one per CPU)",
    "sift.max_image_size": "sets sift.max_image_size of --conf (-1: COLMAP's default, 3200)",
}


def add_colmap_sift_options(p: argparse.ArgumentParser) -> None:
    """The options of :data:`COLMAP_OPTIONS`: mapped where they have a meaning here, else
    accepted and reported as not applied."""
    g = p.add_argument_group(
        "COLMAP feature_extractor options",
        "accepted as `colmap feature_extractor` spells them, COLMAP 4.x "
        "(--FeatureExtraction.*) and 3.x (--SiftExtraction.*) alike",
    )
    for key, options in colmap_arguments().items():
        what = COLMAP_OPTIONS[options[0]]
        flags = [f"--{o}" for o in options]
        if isinstance(what, Setting):
            help_text = _HELP.get(key, f"sets {key} of --conf")
            metavar = "SIFT" if key == "feature_type" else "VALUE"
            g.add_argument(*flags, dest=_dest(key), type=what.kind, metavar=metavar, help=help_text)
        else:
            g.add_argument(*flags, dest=_dest(key), metavar="VALUE", help=f"not applied: {what}")


def _dest(key: str) -> str:
    return "colmap_" + key.replace(".", "_")


def apply_colmap_options(args: argparse.Namespace, conf) -> None:
    """COLMAP's options into ``conf`` and ``args.num_workers``; those that do not apply said
    once each at INFO."""
    for key in colmap_arguments():
        value = getattr(args, _dest(key), None)
        if value is None:
            continue
        if key in COLMAP_OPTIONS and not isinstance(COLMAP_OPTIONS[key], Setting):
            logger.info("--%s %s: not applied (%s)", key, value, COLMAP_OPTIONS[key])
        elif key == "num_workers":
            args.num_workers = (os.cpu_count() or 1) if value <= 0 else value
        elif key.startswith("sift."):
            setattr(conf.sift, key.removeprefix("sift."), value)


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
    from ..config import DepthInputConf, ReaderConf, RunConf
    from ..extraction import extract

    if args.database is None and args.hloc_features is None:
        raise UsageError("give --database and/or --hloc_features")
    conf = _load_conf(args.conf, args.max_num_features)
    apply_colmap_options(args, conf)
    if getattr(args, "orientation", None) is not None:
        conf.vp.enabled = args.orientation != "depth"
    reader = ReaderConf(**{f.name: getattr(args, f.name) for f in dataclasses.fields(ReaderConf)})
    depth = DepthInputConf(
        **{f.name: getattr(args, f"depth_{f.name}") for f in dataclasses.fields(DepthInputConf)}
    )
    options = RunConf(
        num_workers=args.num_workers,
        shard=args.shard,
        ray_address=args.ray,
        progress=not args.no_progress,
        visualize=args.visualize,
    )
    summary = extract(
        args.image_path,
        args.database,
        args.hloc_features,
        conf,
        reader,
        depth,
        options,
        overwrite=args.overwrite,
    )
    (logger.info if summary.ok else logger.error)("summary\n%s", summary.report())
    return 0 if summary.ok else 1
