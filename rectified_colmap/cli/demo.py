"""`rectified-colmap demo`: render a street, extract with the embedded model, map."""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path

logger = logging.getLogger(__name__)


def register(sub: argparse._SubParsersAction) -> None:
    from ..config import DEFAULT_DEPTH_MODEL

    p = sub.add_parser("demo", help="run the whole job on a rendered street (no data needed)")
    p.add_argument(
        "--output",
        type=Path,
        default=Path("demo"),
        help="output folder: renders, database, features, model (default %(default)s)",
    )
    p.add_argument("--num_images", type=int, default=8, help="rendered views (default %(default)s)")
    p.add_argument(
        "--depth_model", default=DEFAULT_DEPTH_MODEL, help="depth network (default %(default)s)"
    )
    p.add_argument(
        "--num_workers", type=int, default=1, help="worker processes (default %(default)s)"
    )
    p.add_argument("--overwrite", action="store_true", help="start from an empty folder")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from ..demo import RESULT_KEYS, run_demo

    res = run_demo(args.output, args.num_images, args.depth_model, args.overwrite, args.num_workers)
    print(json.dumps(res, indent=2))
    print("\n".join(f"  {key}: {meaning}" for key, meaning in RESULT_KEYS.items()))
    ok = res["extraction_ok"] and res["registered"] == res["images"]
    if not ok:
        logger.error("demo: not every image was registered")
    return 0 if ok else 1
