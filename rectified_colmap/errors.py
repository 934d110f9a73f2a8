"""One-line error messages for users: the CLI and the scripts report a bad input so.

A bad argument, a missing file or folder, or a corrupt input stops a command with one line
naming the file and the cause, and exit code 2 (``EXIT_ERROR``); the traceback only at
DEBUG. Errors of these types are expected (the message is the whole story); anything else is
a bug and is named by its type.
"""

from __future__ import annotations

import logging
import sys
from collections.abc import Callable

EXIT_ERROR = 2
"""Exit code of a command that stopped on an error before or instead of doing its work."""

EXPECTED = (ValueError, OSError, KeyError, RuntimeError)
"""Exceptions whose message is the whole story (bad input, missing file, failed step)."""


def one_line(e: BaseException) -> str:
    """The user's line for ``e``: its message (a KeyError's without quotes), prefixed by
    its type when it is not one of ``EXPECTED``."""
    msg = str(e).strip("'\"") if isinstance(e, KeyError) else str(e)
    msg = " ".join(msg.split())  # one line
    return msg if isinstance(e, EXPECTED) else f"{type(e).__name__}: {msg}"


def run_script(main: Callable[[], int | None], prog: str) -> int:
    """Runs a script's ``main()``: its exit code, or, on an exception, one line
    ``prog: error: ...`` on stderr and EXIT_ERROR (the traceback at DEBUG logging)."""
    try:
        return int(main() or 0)
    except SystemExit as e:  # argparse's own (exit 2) or a script's SystemExit("message")
        if not isinstance(e.code, str):
            return int(e.code or 0)
        print(f"{prog}: error: {' '.join(e.code.split())}", file=sys.stderr)
        return EXIT_ERROR
    except KeyboardInterrupt:
        print(f"{prog}: interrupted", file=sys.stderr)
        return 130
    except Exception as e:
        logging.getLogger(prog).debug("traceback", exc_info=True)
        print(f"{prog}: error: {one_line(e)}", file=sys.stderr)
        return EXIT_ERROR
