"""`rectified-colmap merge`: combine sharded outputs into one database and one feature file."""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

logger = logging.getLogger(__name__)

_SQLITE = b"SQLite format 3\x00"
_HDF5 = b"\x89HDF\r\n\x1a\n"


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "merge",
        help="merge the outputs of `extract --shard i/n` runs",
        description="Adds every image with features of the input COLMAP databases and hloc "
        "feature files to one database and one feature file, as one run over "
        "all images would have written them. Refuses images with the same name "
        "and different features, and inputs that already hold matches.",
    )
    p.add_argument(
        "inputs",
        nargs="+",
        type=Path,
        help="shard outputs: COLMAP databases and/or hloc .h5 files (told apart by their content)",
    )
    p.add_argument(
        "--database",
        "--database_path",
        dest="database",
        type=Path,
        help="merged COLMAP database (created or completed)",
    )
    p.add_argument("--hloc_features", type=Path, help="merged hloc feature file")
    p.add_argument(
        "--single_camera",
        type=int,
        nargs="?",
        const=1,
        default=0,
        help="unify identical cameras: merge the shards of an `extract "
        "--single_camera` run with it (default: every input camera stays one "
        "camera)",
    )
    p.set_defaults(func=run)


def _kind(path: Path) -> str:
    if path.is_dir() or not path.exists():
        if Path(str(path) + ".partial").is_dir():
            return "h5"  # a killed shard's staged images only
        raise FileNotFoundError(f"{path}: no such file")
    with open(path, "rb") as f:
        head = f.read(16)
    if head.startswith(_SQLITE):
        return "db"
    if head.startswith(_HDF5):
        return "h5"
    raise ValueError(f"{path}: neither a COLMAP database (SQLite) nor an hloc feature file (HDF5)")


def run(args: argparse.Namespace) -> int:
    from ..io.merge import merge_databases, merge_feature_files

    kinds = {p: _kind(p) for p in args.inputs}
    dbs = [p for p, k in kinds.items() if k == "db"]
    h5s = [p for p, k in kinds.items() if k == "h5"]
    if dbs and args.database is None:
        raise ValueError(f"{dbs[0]} is a database: give --database_path for the merged one")
    if h5s and args.hloc_features is None:
        raise ValueError(f"{h5s[0]} is a feature file: give --hloc_features for the merged one")
    if args.database is not None and not dbs:
        raise ValueError("--database_path given but no input database")
    if args.hloc_features is not None and not h5s:
        raise ValueError("--hloc_features given but no input feature file")
    if dbs:
        s = merge_databases(args.database, dbs, single_camera=bool(args.single_camera))
        logger.info("%s", s.report(args.database))
    if h5s:
        s = merge_feature_files(args.hloc_features, h5s)
        logger.info("%s", s.report(args.hloc_features))
    return 0
