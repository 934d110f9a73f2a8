"""`rectified-colmap localize`: offline localization against a triangulated reference."""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

from . import UsageError, methods_arg

logger = logging.getLogger(__name__)


def register(sub: argparse._SubParsersAction) -> None:
    from ..eval.config import LocalizeConf

    c = LocalizeConf()  # the defaults the help texts show
    p = sub.add_parser(
        "localize",
        help="triangulate a reference from known poses and localize queries",
        description="Database images of a posed COLMAP model are triangulated with each "
        "method's features (ratio test, matches verified against the known "
        "poses); queries are localized by 2D-3D matches and absolute-pose "
        "RANSAC. With ground truth (held-out model images) the fraction within "
        "(0.25 m, 2 deg), (0.5 m, 5 deg), (5 m, 10 deg) is reported; poses are "
        "always written as 'name qw qx qy qz tx ty tz'.",
    )
    p.add_argument(
        "--reference_model",
        type=Path,
        required=True,
        help="COLMAP model (text or binary) with cameras and poses",
    )
    p.add_argument(
        "--features",
        nargs="+",
        required=True,
        metavar="METHOD=H5",
        help="hloc feature files, one per method (database and query images)",
    )
    p.add_argument(
        "--queries",
        type=Path,
        help="query list 'name MODEL W H params...'; default: hold out model "
        "images (--holdout_every) with their poses as ground truth",
    )
    p.add_argument(
        "--holdout_every",
        type=int,
        default=3,
        help="every N-th model image (sorted by name, from the 2nd) is a query (%(default)s)",
    )
    p.add_argument(
        "--name_prefix",
        default="",
        help="prefix turning model image names into feature names, e.g. images/",
    )
    p.add_argument("--output_dir", type=Path, required=True)
    p.add_argument("--ratio", type=float, default=None, help=f"ratio test ({c.ratio})")
    p.add_argument(
        "--ransac_max_error",
        type=float,
        default=None,
        help=f"absolute-pose RANSAC threshold in pixels ({c.ransac_max_error:g})",
    )
    p.add_argument(
        "--num_retrieved",
        type=int,
        default=None,
        help=f"database images matched per query, 0 = all ({c.num_retrieved})",
    )
    p.add_argument("--no_progress", action="store_true")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import pycolmap

    from ..eval.config import LocalizeConf
    from ..eval.aachen import read_query_list
    from ..eval.localize import accuracy_table, localize_with_model, write_poses

    conf = LocalizeConf()
    for key in ("ratio", "ransac_max_error", "num_retrieved"):
        if getattr(args, key) is not None:
            setattr(conf, key, getattr(args, key))
    if not args.reference_model.is_dir():
        raise UsageError(f"--reference_model {args.reference_model}: not a directory")
    try:
        model = pycolmap.Reconstruction(str(args.reference_model))
    except Exception as e:
        raise ValueError(
            f"--reference_model {args.reference_model}: cannot read a COLMAP model ({e})"
        ) from None
    queries = read_query_list(args.queries) if args.queries else None
    methods = methods_arg(args.features)
    out = args.output_dir
    out.mkdir(parents=True, exist_ok=True)
    rows, counts = {}, {}
    for method, h5 in methods.items():
        try:
            results, acc = localize_with_model(
                model,
                h5,
                out / f"work_{method}",
                queries,
                args.holdout_every,
                args.name_prefix,
                conf,
                progress=not args.no_progress,
            )
        except (ValueError, KeyError, FileNotFoundError) as e:
            raise ValueError(f"{method}: {str(e).strip(chr(39))}") from None
        n = write_poses(out / f"poses_{method}.txt", results)
        logger.info(
            "%s: %d/%d queries localized -> %s",
            method,
            n,
            len(results),
            out / f"poses_{method}.txt",
        )
        if acc is not None:
            rows[method], counts[method] = acc, len(results)
    if rows:
        table = accuracy_table(rows, conf.thresholds, counts)
        (out / "localization.md").write_text(table)
        logger.info("accuracy\n%s", table)
    return 0
