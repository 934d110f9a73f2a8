"""`rectified-colmap` console script: a thin layer of subcommands over the Python API.

Each subcommand lives in its own module with ``register(subparsers)``, which adds its parser
and sets ``func`` to a callable taking the parsed args and returning an exit code.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys

SUBCOMMANDS = ["extract", "merge", "models", "evaluate", "localize", "demo"]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="rectified-colmap",
        description="Rectified SIFT (Toft et al., ECCV 2020) for COLMAP and hloc.",
    )
    parser.add_argument(
        "--log_level", default="INFO", choices=["DEBUG", "INFO", "WARNING", "ERROR"]
    )
    sub = parser.add_subparsers(dest="command", required=True)
    for name in SUBCOMMANDS:
        try:
            module = importlib.import_module(f"{__name__}.{name}")
        except ModuleNotFoundError as e:  # a subcommand not built yet
            if e.name != f"{__name__}.{name}":
                raise
            continue
        module.register(sub)
    return parser


def methods_arg(specs: list[str]) -> dict:
    """``--features METHOD=H5 ...`` -> {method: Path} (eval.matching.parse_methods); an error
    stops the command with its message (SystemExit)."""
    from ..eval.matching import parse_methods

    try:
        return parse_methods(specs)
    except ValueError as e:
        raise SystemExit(str(e)) from None


EXIT_ERROR = 2
"""Exit code of a run that stopped on an error before or instead of doing its work (a run
that went through but had failed images exits with 1)."""


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=getattr(logging, args.log_level),
        format="[%(asctime)s %(name)s %(levelname)s] %(message)s",
        datefmt="%Y/%m/%d %H:%M:%S",
    )
    log = logging.getLogger("rectified_colmap")
    try:
        return int(args.func(args) or 0)
    except KeyboardInterrupt:
        log.error("interrupted")
        return 130
    except Exception as e:  # one line for the user; the traceback at DEBUG
        log.debug("traceback", exc_info=True)
        known = isinstance(e, (ValueError, OSError, KeyError, RuntimeError))
        msg = str(e).strip("'\"") if isinstance(e, KeyError) else str(e)
        log.error(
            "%s%s%s",
            "" if known else f"{type(e).__name__}: ",
            msg,
            ""
            if args.log_level == "DEBUG"
            else ("" if known else " (--log_level DEBUG shows the traceback)"),
        )
        return EXIT_ERROR


if __name__ == "__main__":
    sys.exit(main())
