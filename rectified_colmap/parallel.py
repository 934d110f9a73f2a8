"""Local worker processes that never inherit a live thread pool, and their log records.

Forking a process whose OpenCV, onnxruntime, OpenMP or torch thread pools have run can
hang the child for good: the pools' locks and condition variables are copied in whatever
state the parent's threads left them, and those threads do not exist in the child
(OpenCV's ``setNumThreads`` in a forked child waits forever in ``pthread_cond_destroy``).
So every pool of this package starts its workers through :func:`context`: ``forkserver``
where the platform has it (Linux, macOS: a clean server process, started once per parent
process, imports the ``preload`` modules once and forks the workers from itself), else
``spawn`` (Windows). Never ``fork``.

The caller's main module. A non-fork worker normally imports the caller's ``__main__``
again (as ``__mp_main__``), which breaks where that module is no importable file: a script
read from standard input (``python - <<EOF``: each worker looks for a file ``<stdin>``,
fails, and the pool breaks), and which re-runs every line of a script without an
``if __name__ == "__main__":`` guard. The processes of :func:`context` decide it when they
start (``Process.start``, under a lock: the main module's ``__file__`` / ``__spec__`` are
hidden from multiprocessing's preparation data for that moment only):

- ``import_main=False`` (the package's own pools, whose worker functions, initializers and
  jobs are all importable from the package): the workers never import the caller's main
  module. Extraction from a script with or without the guard, from standard input,
  ``python -c``, a notebook or the console script works the same, and no line of the
  caller's script runs again in a worker;
- ``import_main=True`` (the default, for callers whose worker functions live in their main
  script, e.g. research/scripts/build_real_pool.py): multiprocessing's own rule (the
  script must guard its main code), except that a main module that is no file (standard
  input, an interactive session) is not imported, instead of breaking the pool.
  :func:`check_not_bootstrapping` turns an unguarded script that starts workers from its
  workers into a one-line error where it would otherwise wait on its own output locks.

Either way, workers run importable functions only; their initializer, its arguments and
every job are pickled. A worker stopped by its pool (the pool shutting down after another
worker died) ends quietly: each worker restores the default SIGTERM action before its
target runs (pycolmap's glog failure handler would print a C-level stack dump).

Workers do not share the parent's logging set-up. :func:`capture_logs` keeps a worker's
records (made picklable) in a queue; the worker sends :func:`drain`'s list back with its
result and the parent hands them to its own loggers with :func:`replay`, so that they go
through the parent's handlers (and around a progress bar: rectified_colmap.progress).
"""

from __future__ import annotations

import logging
import logging.handlers
import multiprocessing as mp
import os
import queue
import signal
import sys
import threading
from collections.abc import Iterable, Iterator
from contextlib import contextmanager

_PRELOAD: set[str] = set()
"""Modules asked for by every :func:`context` call so far; the forkserver imports those
listed when it starts (once per parent process)."""


def start_method() -> str:
    """``forkserver`` where available, else ``spawn``; never ``fork``."""
    return "forkserver" if "forkserver" in mp.get_all_start_methods() else "spawn"


def context(preload: Iterable[str] = (), import_main: bool = True) -> mp.context.BaseContext:
    """The multiprocessing context for worker processes (see the module docstring).

    ``preload``: modules the forkserver imports once, before it forks any worker, so that
    each worker starts with them imported (dotted names; the worker functions' own modules).
    Only modules that start no thread pool at import belong there. Effective for the
    forkserver's first start in this process; later calls add to the list for nobody.

    ``import_main``: whether the workers import the caller's main module (False where every
    function the workers run is importable from a module: then they never do)."""
    method = start_method()
    base = mp.get_context(method)
    if method == "forkserver":
        _PRELOAD.update(preload)
        base.set_forkserver_preload(sorted(_PRELOAD))
    ctx = type(base)()  # a context of its own, so that its Process class is ours
    ctx.Process = _PROCESSES[(method, bool(import_main))]
    return ctx


_MAIN_LOCK = threading.Lock()
"""Held while a worker process starts with the main module's attributes hidden."""


def _main_is_importable(main) -> bool:
    """Whether a worker could import ``main`` again: by its module name (``python -m``),
    or from its file; False for standard input, ``python -c`` and interactive sessions."""
    if getattr(getattr(main, "__spec__", None), "name", None) is not None:
        return True
    path = getattr(main, "__file__", None)
    if path is None:
        return False
    if not os.path.isabs(path):
        path = os.path.join(mp.process.ORIGINAL_DIR or os.getcwd(), path)
    return os.path.isfile(path)


@contextmanager
def _main_module_seen_by_workers(import_main: bool) -> Iterator[None]:
    """While a worker starts: the caller's main module without ``__file__`` and with
    ``__spec__`` None (what multiprocessing reads to import it in the worker) when the
    worker must not import it (``import_main`` False) or cannot (no file); then restored."""
    with _MAIN_LOCK:
        main = sys.modules.get("__main__")
        hide = main is not None and not (import_main and _main_is_importable(main))
        saved = {}
        if hide:
            for attr in ("__file__", "__spec__"):
                if attr in vars(main):
                    saved[attr] = vars(main)[attr]
            main.__spec__ = None
            main.__dict__.pop("__file__", None)
        try:
            yield
        finally:
            if hide:
                main.__dict__.pop("__spec__", None)
                main.__dict__.update(saved)


class _WorkerProcess:
    """What the processes of :func:`context` add to multiprocessing's (module docstring):
    the main module as the context asks at start, the default SIGTERM in the worker."""

    import_main = True

    def start(self) -> None:
        with _main_module_seen_by_workers(self.import_main):
            super().start()

    def run(self) -> None:
        signal.signal(signal.SIGTERM, signal.SIG_DFL)  # no C-level stack dump when stopped
        super().run()


class _SpawnProcess(_WorkerProcess, mp.context.SpawnProcess):
    pass


class _SpawnProcessNoMain(_SpawnProcess):
    import_main = False


_PROCESSES: dict[tuple[str, bool], type] = {
    ("spawn", True): _SpawnProcess,
    ("spawn", False): _SpawnProcessNoMain,
}

if hasattr(mp.context, "ForkServerProcess"):  # not on Windows

    class _ForkServerProcess(_WorkerProcess, mp.context.ForkServerProcess):
        pass

    class _ForkServerProcessNoMain(_ForkServerProcess):
        import_main = False

    _PROCESSES[("forkserver", True)] = _ForkServerProcess
    _PROCESSES[("forkserver", False)] = _ForkServerProcessNoMain


def check_not_bootstrapping() -> None:
    """RuntimeError when this process is a worker still importing the caller's main script
    (a script that starts workers without ``if __name__ == "__main__":`` from workers of a
    pool that imports it: ``import_main=True``, e.g. the caller's own). Call it before
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
