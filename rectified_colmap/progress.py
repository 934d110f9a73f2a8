"""Progress bars that log lines do not break.

A tqdm bar redraws its line in place. A log record written to the same console meanwhile
lands right after the bar's text, and the bar goes on below it: a line that is half bar,
half message. :func:`progress_bar` opens a tqdm bar and, while it is open, writes what the
console handlers (``logging.StreamHandler`` on stdout or stderr, e.g. the CLI's
``logging.basicConfig`` one) of the root logger and of the ``rectified_colmap`` logger would
write through ``tqdm.write``: the bar is cleared, the record printed on its own line with
the handler's own format, level and filters, and the bar redrawn below it. Other handlers
(files, pytest's capture) are left as they are; everything is restored when the bar
closes, also on an exception.
"""

from __future__ import annotations

import contextlib
import logging
import sys
from collections.abc import Iterator

from tqdm import tqdm

PACKAGE_LOGGER = "rectified_colmap"


def is_console_handler(handler: logging.Handler) -> bool:
    """Whether ``handler`` writes to the console the bars are drawn on (stdout or stderr)."""
    return isinstance(handler, logging.StreamHandler) and getattr(handler, "stream", None) in (
        sys.stdout,
        sys.stderr,
        sys.__stdout__,
        sys.__stderr__,
    )


class AboveTheBar(logging.Handler):
    """What ``handler`` would write (its formatter, level and filters), written with
    ``tqdm.write`` to the handler's stream: above any live bar, never inside its line."""

    def __init__(self, handler: logging.StreamHandler):
        super().__init__(handler.level)
        self.handler = handler
        self.setFormatter(handler.formatter)
        self.filters = list(handler.filters)

    def emit(self, record: logging.LogRecord) -> None:
        try:
            tqdm.write(self.format(record), file=self.handler.stream)
        except Exception:
            self.handleError(record)


@contextlib.contextmanager
def logs_above_bars(names: tuple[str, ...] = ("", PACKAGE_LOGGER)) -> Iterator[None]:
    """While open, the console handlers of the loggers ``names`` ("" is the root) write
    through :class:`AboveTheBar`; restored on exit."""
    saved = []
    for name in names:
        logger = logging.getLogger(name or None)
        handlers = list(logger.handlers)
        saved.append((logger, handlers))
        logger.handlers = [AboveTheBar(h) if is_console_handler(h) else h for h in handlers]
    try:
        yield
    finally:
        for logger, handlers in saved:
            logger.handlers = handlers


@contextlib.contextmanager
def progress_bar(**kwargs) -> Iterator[tqdm]:
    """``tqdm(**kwargs)`` as a context manager, with log lines kept out of its line
    (:func:`logs_above_bars`) while it is shown; closed on exit."""
    bar = tqdm(**kwargs)
    try:
        if bar.disable:
            yield bar
        else:
            with logs_above_bars():
                yield bar
    finally:
        bar.close()
