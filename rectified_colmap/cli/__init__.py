"""`rectified-colmap` console script: a thin layer of subcommands over the Python API.

Each subcommand lives in its own module with ``register(subparsers)``, which adds its parser
and sets ``func`` to a callable taking the parsed args and returning an exit code.
"""

from __future__ import annotations

import argparse
import difflib
import importlib
import logging
import sys

from ..errors import EXIT_ERROR, EXPECTED, one_line

SUBCOMMANDS = ["extract", "merge", "models", "evaluate", "localize", "demo"]

LOG_LEVELS = ["DEBUG", "INFO", "WARNING", "ERROR"]

# EXIT_ERROR (2): a run that stopped on an error before or instead of doing its work (a bad
# argument included, as argparse's own); a run that went through but had failed images
# exits with 1.

BOOL_FLAGS = ("--single_camera", "--ImageReader.single_camera")
"""Flags that take an optional COLMAP-style 0/1 value: ``--single_camera`` alone means 1,
``--single_camera 0`` / ``1`` as COLMAP writes it; any other next word is not theirs (a
path after the flag stays a positional argument)."""

_BOOL_WORDS = {"0": "0", "1": "1", "false": "0", "true": "1"}


class UsageError(ValueError):
    """A bad argument found after parsing (a missing output, a bad --conf): one line, exit 2."""


def bool_flag_value(text: str) -> bool:
    """argparse type of BOOL_FLAGS: '1'/'true' -> True, '0'/'false' -> False."""
    try:
        return _BOOL_WORDS[text.strip().lower()] == "1"
    except KeyError:
        raise argparse.ArgumentTypeError(f"expected 0 or 1, got {text!r}") from None


def positive_int(text: str) -> int:
    """argparse type of counts that must be at least 1 (a budget of 0 gives no features)."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {value}")
    return value


def normalize_bool_flags(argv: list[str]) -> list[str]:
    """``--single_camera`` [0|1] -> ``--single_camera=V``, so that the flag never takes a
    following path as its value (``merge --single_camera a.db b.db``)."""
    out, i = [], 0
    while i < len(argv):
        arg = argv[i]
        if arg in BOOL_FLAGS:
            nxt = argv[i + 1].strip().lower() if i + 1 < len(argv) else None
            if nxt in _BOOL_WORDS:
                out.append(f"{arg}={_BOOL_WORDS[nxt]}")
                i += 2
                continue
            arg = f"{arg}=1"
        out.append(arg)
        i += 1
    return out


class Parser(argparse.ArgumentParser):
    """argparse with one-line errors that name the (sub)command and point to its --help,
    and BOOL_FLAGS normalised (subcommand parsers are of this class too)."""

    def error(self, message: str):
        self.exit(
            EXIT_ERROR, f"{self.prog}: error: {message} (`{self.prog} --help` lists the options)\n"
        )

    def parse_known_args(self, args=None, namespace=None):
        args = sys.argv[1:] if args is None else list(args)
        return super().parse_known_args(normalize_bool_flags(args), namespace)


def add_common_options(parser: argparse.ArgumentParser, top: bool) -> None:
    """--log_level, before or after the subcommand (a subcommand's value wins)."""
    parser.add_argument(
        "--log_level",
        choices=LOG_LEVELS,
        default="INFO" if top else argparse.SUPPRESS,
        help="log messages from this level up (default INFO; DEBUG also shows tracebacks)",
    )


def build_parser() -> Parser:
    parser = Parser(
        prog="rectified-colmap",
        description="Rectified SIFT (Toft et al., ECCV 2020) for COLMAP and hloc.",
    )
    add_common_options(parser, top=True)
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name in SUBCOMMANDS:
        try:
            module = importlib.import_module(f"{__name__}.{name}")
        except ModuleNotFoundError as e:  # a subcommand not built yet
            if e.name != f"{__name__}.{name}":
                raise
            continue
        module.register(sub)
    for subparser in sub.choices.values():
        add_common_options(subparser, top=False)
    return parser


def option_strings(parser: argparse.ArgumentParser) -> list[str]:
    """Every --option a parser accepts."""
    return [s for a in parser._actions for s in a.option_strings if s.startswith("--")]


def unknown_arguments_message(extra: list[str], parser: argparse.ArgumentParser) -> str:
    """'unrecognized argument(s) ...' with the closest option for each misspelled one."""
    hints = []
    for arg in extra:
        if not arg.startswith("-"):
            continue
        name = arg.split("=", 1)[0]
        close = difflib.get_close_matches(name, option_strings(parser), n=1, cutoff=0.6)
        if close:
            hints.append(f"{name}: did you mean {close[0]}?")
    s = "s" if len(extra) > 1 else ""
    return f"unrecognized argument{s}: {' '.join(extra)}" + (
        f" ({'; '.join(hints)})" if hints else ""
    )


def subcommand_parser(parser: argparse.ArgumentParser, argv: list[str]) -> argparse.ArgumentParser:
    """The deepest (sub)command parser that ``argv`` names (for its error messages)."""
    current = parser
    for word in argv:
        subs = [a for a in current._actions if isinstance(a, argparse._SubParsersAction)]
        if subs and word in subs[0].choices:
            current = subs[0].choices[word]
    return current


def methods_arg(specs: list[str]) -> dict:
    """``--features METHOD=H5 ...`` -> {method: Path} (eval.matching.parse_methods); a bad
    spec is a UsageError."""
    from ..eval.matching import parse_methods

    try:
        return parse_methods(specs)
    except ValueError as e:
        raise UsageError(str(e)) from None


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    parser = build_parser()
    try:
        args, extra = parser.parse_known_args(argv)
        command_parser = subcommand_parser(parser, argv)
        if extra:
            command_parser.error(unknown_arguments_message(extra, command_parser))
    except SystemExit as e:  # argparse: --help (0) or a usage error (2)
        return int(e.code or 0) if not isinstance(e.code, str) else EXIT_ERROR
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
    except UsageError as e:
        try:
            command_parser.error(str(e))
        except SystemExit:
            return EXIT_ERROR
    except Exception as e:  # one line for the user; the traceback at DEBUG
        log.debug("traceback", exc_info=True)
        hint = not isinstance(e, EXPECTED) and args.log_level != "DEBUG"
        log.error("%s%s", one_line(e), " (--log_level DEBUG shows the traceback)" if hint else "")
        return EXIT_ERROR


if __name__ == "__main__":
    sys.exit(main())
