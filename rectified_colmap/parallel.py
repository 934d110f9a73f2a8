"""Local worker processes that never inherit a live thread pool, and their log records.

Forking a process whose OpenCV, onnxruntime, OpenMP or torch thread pools have run can
hang the child for good: the pools' locks and condition variables are copied in whatever
state the parent's threads left them, and those threads do not exist in the child
(OpenCV's ``setNumThreads`` in a forked child waits forever in ``pthread_cond_destroy``).
So every pool of this package starts its workers through :func:`context`: ``forkserver``
where the platform has it (Linux, macOS: a clean server process, started once per parent
process, imports the ``preload`` modules once and forks the workers from itself), else
``spawn`` (Windows). Never ``fork``.

What that asks of callers, as any non-fork start method does:

- workers run importable functions only; their initializer, its arguments and every job
  are pickled;
- each worker imports the caller's main module again (as ``__mp_main__``): a script that
  starts workers must do it under ``if __name__ == "__main__":``. ``python -c`` and
  console scripts need nothing. :func:`check_not_bootstrapping` turns the unguarded case
  into a one-line error where it would otherwise wait on its own output locks.

Workers do not share the parent's logging set-up. :func:`capture_logs` keeps a worker's
records (made picklable) in a queue; the worker sends :func:`drain`'s list back with its
result and the parent hands them to its own loggers with :func:`replay`, so that they go
through the parent's handlers (and around a progress bar: rectified_colmap.progress).
"""

from __future__ import annotations

import logging
import logging.handlers
import multiprocessing as mp
import queue
from collections.abc import Iterable

_PRELOAD: set[str] = set()
"""Modules asked for by every :func:`context` call so far; the forkserver imports those
listed when it starts (once per parent process)."""


def start_method() -> str:
    """``forkserver`` where available, else ``spawn``; never ``fork``."""
    return "forkserver" if "forkserver" in mp.get_all_start_methods() else "spawn"


def context(preload: Iterable[str] = ()) -> mp.context.BaseContext:
    """The multiprocessing context for worker processes (see the module docstring).

    ``preload``: modules the forkserver imports once, before it forks any worker, so that
    each worker starts with them imported (dotted names; the worker functions' own modules).
    Only modules that start no thread pool at import belong there. Effective for the
    forkserver's first start in this process; later calls add to the list for nobody."""
    method = start_method()
    ctx = mp.get_context(method)
    if method == "forkserver":
        _PRELOAD.update(preload)
        ctx.set_forkserver_preload(sorted(_PRELOAD))
    return ctx


def check_not_bootstrapping() -> None:
    """RuntimeError when this process is a worker still importing the caller's main script
    (a script that starts workers without ``if __name__ == "__main__":``). Call it before
    taking any resource the parent may hold (output locks): the worker would wait for its
    parent, which waits for the worker."""
    if getattr(mp.current_process(), "_inheriting", False):
        raise RuntimeError(
            "worker processes are being started while a worker imports the main script: "
            "put the code that runs the extraction under `if __name__ == '__main__':` "
            "(or use num_workers=1)"
        )


def capture_logs(level: int, logger: str = "rectified_colmap") -> queue.SimpleQueue:
    """In a worker process: every log record from now on goes into the returned queue
    (made picklable: message formatted, exception text included, no arguments), the root
    logger's only handler. ``logger`` gets ``level`` (the parent's effective level), so
    that the worker logs what the parent would show."""
    records: queue.SimpleQueue = queue.SimpleQueue()
    root = logging.getLogger()
    for handler in list(root.handlers):
        root.removeHandler(handler)
    root.addHandler(logging.handlers.QueueHandler(records))
    logging.getLogger(logger).setLevel(level)
    return records


def drain(records: queue.SimpleQueue | None) -> list[logging.LogRecord]:
    """The records :func:`capture_logs` kept since the last call, oldest first ([] for
    None: a process that captures nothing)."""
    out = []
    while records is not None:
        try:
            out.append(records.get_nowait())
        except queue.Empty:
            break
    return out


def replay(records: Iterable[logging.LogRecord]) -> None:
    """In the parent: each worker record through the logger of its name, as if it had been
    logged here (the parent's levels and handlers decide what is shown)."""
    for record in records:
        logger = logging.getLogger(record.name)
        if logger.isEnabledFor(record.levelno):
            logger.handle(record)
