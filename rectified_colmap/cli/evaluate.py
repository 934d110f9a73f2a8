"""`rectified-colmap evaluate-pairs`: relative-pose evaluation of hloc feature files."""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

from . import UsageError, methods_arg

logger = logging.getLogger(__name__)


def register(sub: argparse._SubParsersAction) -> None:
    _register_pairs(sub)
    _register_homography(sub)


def _register_pairs(sub: argparse._SubParsersAction) -> None:
    from ..eval.config import EvalConf

    e = EvalConf()  # the defaults the help texts show
    p = sub.add_parser(
        "evaluate-pairs",
        help="relative-pose evaluation of feature files on image pairs",
        description="Match each method's features (ratio test), estimate the essential "
        "matrix with the known intrinsics and report success (rotation error "
        f"under {e.success_deg:g} deg) per ground-truth rotation bin, pose AUC "
        "and GT-correct matches. Writes records.csv, summary.md and success.png.",
    )
    _add_pair_sources(p.add_mutually_exclusive_group(required=True))
    p.add_argument(
        "--features",
        nargs="+",
        required=True,
        metavar="METHOD=H5",
        help="hloc feature files, one per method, e.g. sift=f1.h5 rectsift=f2.h5",
    )
    p.add_argument("--output_dir", type=Path, required=True)
    p.add_argument("--ratio", type=float, default=None, help=f"ratio test ({e.ratio})")
    p.add_argument("--mutual", action="store_true", help="mutual nearest neighbours too")
    p.add_argument(
        "--ransac_max_error",
        type=float,
        default=None,
        help=f"essential-matrix RANSAC threshold in pixels ({e.ransac_max_error})",
    )
    p.add_argument(
        "--ransac_runs",
        type=int,
        default=None,
        help=f"RANSAC runs per pair, seeds 0, 1, ... ({e.ransac_runs}): pose errors are their "
        "medians, success the majority's, plus the mean success over runs",
    )
    p.add_argument(
        "--bin_deg",
        type=float,
        default=None,
        help=f"width of the GT rotation bins ({e.bin_deg:g}; e.g. 30 for coarser bins)",
    )
    p.add_argument(
        "--epipolar_threshold",
        type=float,
        default=None,
        help=f"Sampson error (px) under which a match is GT-correct ({e.epipolar_threshold})",
    )
    p.add_argument("--num_workers", type=int, default=1)
    p.add_argument("--max_pairs", type=int, default=None, help="only the first N pairs")
    p.add_argument("--no_plot", action="store_true", help="skip the PNG (no matplotlib)")
    p.add_argument("--title", default="")
    p.add_argument("--no_progress", action="store_true")
    p.set_defaults(func=run)


def _add_pair_sources(src) -> None:
    src.add_argument(
        "--pairs",
        type=Path,
        nargs="+",
        help="pair file(s) in the SuperGlue format (name0 name1 rot0 rot1 K0 K1 T_0to1)",
    )
    src.add_argument(
        "--svc_root",
        type=Path,
        help="root of the Strong Viewpoint Changes dataset (best-effort reader)",
    )


def _register_homography(sub: argparse._SubParsersAction) -> None:
    from ..eval.config import HomographyConf

    hc = HomographyConf()  # the defaults the help texts show
    h = sub.add_parser(
        "evaluate-homography",
        help="homography evaluation of feature files on planar pairs",
        description="Match each method's features (mutual NN + ratio test), estimate a "
        "homography (RANSAC) and report, per pair and direction, the corner "
        "error (HPatches), the error over the visible overlap (solved: under "
        f"{hc.success_px:g} px) and the matches consistent with the ground-truth "
        "homography. Writes records.csv and summary.md.",
    )
    h.add_argument(
        "--pairs",
        type=Path,
        required=True,
        help="JSON list of {im0, im1, H[, pair, size0, size1, convention]}; H maps "
        "im0 -> im1, OpenCV pixel convention unless convention = colmap "
        "(e.g. shared/data/evd-dev/pairs.json)",
    )
    h.add_argument(
        "--image_root",
        type=Path,
        default=None,
        help="where im0/im1 are (only to read image sizes missing in the file)",
    )
    h.add_argument("--features", nargs="+", required=True, metavar="METHOD=H5")
    h.add_argument("--output_dir", type=Path, required=True)
    h.add_argument("--ratio", type=float, default=None, help=f"ratio test ({hc.ratio})")
    h.add_argument("--no_mutual", action="store_true", help="no mutual check")
    h.add_argument(
        "--ransac_threshold", type=float, default=None, help=f"pixels ({hc.ransac_threshold})"
    )
    h.add_argument(
        "--success_px",
        type=float,
        default=None,
        help=f"solved when the visible-overlap error is under this ({hc.success_px:g})",
    )
    h.add_argument(
        "--one_direction", action="store_true", help="only im0 -> im1 (default: both directions)"
    )
    h.set_defaults(func=run_homography)


def run_homography(args: argparse.Namespace) -> int:
    import csv

    from ..eval.homography import (
        HomographyConf,
        evaluate_homography_pairs,
        homography_markdown,
        read_homography_pairs,
    )

    methods = methods_arg(args.features)
    conf = HomographyConf()
    for key in ("ratio", "ransac_threshold", "success_px"):
        if getattr(args, key) is not None:
            setattr(conf, key, getattr(args, key))
    conf.mutual = not args.no_mutual
    # a bad pair file or feature file: ValueError / KeyError / OSError, one line (main)
    pairs = read_homography_pairs(args.pairs, args.image_root)
    records = evaluate_homography_pairs(pairs, methods, conf, not args.one_direction)
    args.output_dir.mkdir(parents=True, exist_ok=True)
    if records:
        with open(args.output_dir / "records.csv", "w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=list(records[0]))
            w.writeheader()
            w.writerows(records)
    table = homography_markdown(records, conf)
    (args.output_dir / "summary.md").write_text(table)
    logger.info("%d pairs, %d methods -> %s\n%s", len(pairs), len(methods), args.output_dir, table)
    return 0


def make_conf(args: argparse.Namespace):
    from ..eval.config import EvalConf

    conf = EvalConf()
    for key in ("ratio", "ransac_max_error", "ransac_runs", "bin_deg", "epipolar_threshold"):
        if getattr(args, key, None) is not None:
            setattr(conf, key, getattr(args, key))
    conf.mutual = bool(getattr(args, "mutual", False))
    conf.__post_init__()  # the section's own validation (ValueError: a one-line error)
    return conf


def check_matplotlib() -> None:
    try:
        import matplotlib  # noqa: F401
    except ImportError:
        raise UsageError(
            "the plot needs matplotlib: pip install 'rectified-colmap[eval]' (or pass --no_plot)"
        ) from None


def run(args: argparse.Namespace) -> int:
    from ..eval.pairs import read_pairs_with_gt, read_strong_viewpoint_changes
    from ..eval.relpose import evaluate_pairs
    from ..eval.report import write_outputs

    if not args.no_plot:
        check_matplotlib()
    methods = methods_arg(args.features)
    if args.svc_root is not None:
        pairs = read_strong_viewpoint_changes(args.svc_root)
    else:
        pairs = [p for f in args.pairs for p in read_pairs_with_gt(f)]
    if args.max_pairs:
        pairs = pairs[: args.max_pairs]
    conf = make_conf(args)
    # a bad pair file or feature file: ValueError / KeyError / OSError, one line (main)
    records = evaluate_pairs(pairs, methods, conf, args.num_workers, progress=not args.no_progress)
    table = write_outputs(records, args.output_dir, conf, not args.no_plot, args.title)
    logger.info("%d pairs, %d methods -> %s\n%s", len(pairs), len(methods), args.output_dir, table)
    return 0
