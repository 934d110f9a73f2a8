"""Run step of extraction: the per-image work, one :class:`Outcome` per job, in job order.

A :class:`Worker` holds what a process keeps across images (its depth sources, the
network loaded once, its SIFT extractors kept warm) and processes one image: decode it (the
only decode of its pixels in the whole extraction), find its depth, run
``pipeline.extract_image``. Runners give it the
jobs: :class:`HereRunner` in this process, :class:`PoolRunner` in worker processes, and
:class:`RayRunner` on Ray actors (``--ray [ADDRESS]``: an existing cluster or a local
instance; each actor holds its Worker across images, reads the images from the path given,
and results come back to the driver in job order, written there through the crash-safe
writers, so resume, ``--overwrite`` and every data-safety rule hold as in a local run; Ray
is optional: ``pip install 'rectified-colmap[ray]'``); each is a callable
``runner(jobs, conf, keep)`` yielding outcomes in job order, with an optional ``close()``.

Worker processes are never forked from the caller (rectified_colmap.parallel: a fork of a
process whose OpenCV, onnxruntime or torch thread pools have run can hang): they start
from a forkserver that has imported this module, never import the caller's main module
(everything they run is in this package: a script without a main guard, standard input,
``python -c`` and notebooks all work), and their log records come back with their
outcomes, to go through the caller's handlers.
"""

from __future__ import annotations

import logging
import os
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import NamedTuple

import cv2
import numpy as np
import pycolmap

from ..config import DepthInputConf, ExtractConf, RunConf
from ..depth.registry import load_depth_source
from ..io.images import ImageError, decode_image, keypoints_on_mask, read_mask
from ..parallel import capture_logs, check_not_bootstrapping, context, drain, replay
from ..pipeline import ImageResult, extract_image
from ..sift import Sift
from .summary import error_message

logger = logging.getLogger(__package__)


def quiet_pycolmap() -> None:
    """pycolmap's INFO lines (one per SIFT extractor) would interleave with the progress
    bar; keep its warnings unless our own log level is DEBUG."""
    if logging.getLogger("rectified_colmap").getEffectiveLevel() > logging.DEBUG:
        pycolmap.logging.minloglevel = max(int(pycolmap.logging.minloglevel), 1)


class Job(NamedTuple):
    """One image to extract, as sent to a worker."""

    name: str
    path: Path
    """Absolute: workers may run elsewhere (another process, a Ray node)."""
    camera: pycolmap.Camera
    mask: Path | None = None
    """COLMAP's keypoint mask file (absolute; it may not exist: then no mask)."""


@dataclass
class Outcome:
    """What a worker sends back for one image; messages without the image's name."""

    name: str
    result: ImageResult | None = None
    origin: str = "none"
    """Where the depth came from: "files", "network" or "none"."""
    error: str | None = None
    warnings: list[str] = field(default_factory=list)
    rgb: np.ndarray | None = None
    """The decoded image, kept (with the result's details) for the visualisation."""
    logs: list[logging.LogRecord] = field(default_factory=list)
    """A worker process's log records since its previous outcome (replayed by the
    caller's process, then dropped)."""


@dataclass(frozen=True)
class WorkerInit:
    """What a worker builds its depth sources from (sent to worker processes and actors)."""

    depth_path: Path | None
    depth_kind: str
    png_scale: float
    depth_model: str | None
    model_threads: int | None
    """Threads of the depth network; None: its default (one process does everything)."""

    @classmethod
    def of(cls, depth: DepthInputConf, run: RunConf) -> WorkerInit:
        """For a run with these settings: the depth folder made absolute (workers may
        run elsewhere), one network thread per worker when there are several."""
        parallel = run.num_workers > 1 or run.ray_address is not None
        path = None if depth.path is None else Path(depth.path).absolute()
        return cls(path, depth.kind, depth.png_scale, depth.model, 1 if parallel else None)

    def depth_sources(self) -> dict:
        """{"files": FileDepthSource | None, "network": OnnxDepthSource | None}; raises
        with a one-line message naming the folder or model when one cannot be used."""
        sources = {"files": None, "network": None}
        if self.depth_path is not None:
            from ..depth.files import FileDepthSource

            sources["files"] = FileDepthSource(
                self.depth_path, kind=self.depth_kind, png_scale=self.png_scale
            )
        if self.depth_model not in (None, "none"):
            sources["network"] = self._network()
        return sources

    def _network(self):
        """The depth network, or ValueError naming ``--depth_model``."""
        try:
            return load_depth_source(self.depth_model, num_threads=self.model_threads)
        except Exception as e:  # unknown name, missing or corrupt file, onnxruntime errors
            msg = str(e)
            if str(self.depth_model) not in msg:
                msg = f"depth model {self.depth_model}: {msg}"
            raise ValueError(f"--depth_model: {msg}") from e


class Worker:
    """One process's state across images: one OpenCV thread, quiet pycolmap, its depth
    sources (``sources`` when given, else built from ``init``), its SIFT extractors."""

    def __init__(self, init: WorkerInit, sources: dict | None = None):
        cv2.setNumThreads(1)
        quiet_pycolmap()
        self.sources = sources if sources is not None else init.depth_sources()
        self.sift = Sift()

    def process(self, job: Job, conf: ExtractConf, keep: bool) -> Outcome:
        """Decode, depth, extract; an error becomes the outcome's message (the run goes
        on). ``keep``: keep the result's details and the pixels (for the pictures)."""
        out = Outcome(job.name)
        try:
            rgb, out.warnings = decode_image(job.path)
            H, W = rgb.shape[:2]
            if (W, H) != (job.camera.width, job.camera.height):
                raise ImageError(
                    f"image is {W}x{H} but its camera is {job.camera.width}x{job.camera.height}"
                )
            depth, out.origin = self._depth(rgb, job, out.warnings)
            rng = np.random.default_rng(_seed(job.name))
            result = extract_image(rgb, job.camera, depth, conf, rng, self.sift)
            if job.mask is not None:
                mask = read_mask(job.mask, (W, H))
                if mask is not None:  # COLMAP: no features where the mask is black
                    feats = result.features
                    result.features = feats.subset(keypoints_on_mask(feats.keypoints, mask))
        except Exception as e:  # reported per image; the run goes on
            logger.debug("failure on %s", job.name, exc_info=True)
            out.error, out.origin = error_message(e), "none"
            return out
        if keep:
            out.result, out.rgb = result, rgb
        else:
            out.result = ImageResult(result.features, timings=result.timings)
        return out

    def _depth(self, rgb: np.ndarray, job: Job, warnings: list[str]):
        """-> (depth, origin): a depth file's, else the network's; unusable ones are
        ignored with a warning."""
        for kind in ("files", "network"):
            source = self.sources.get(kind)
            if source is None:
                continue
            depth = source(rgb, job.camera, job.name)
            problem = None if depth is None else depth.problem()
            if problem is None and depth is not None:
                return depth, kind
            if problem is not None:
                what = "depth file" if kind == "files" else "depth network"
                warnings.append(f"unusable depth from the {what} ({problem}): ignored")
        return None, "none"


def _seed(name: str) -> int:
    """The image's random seed: from its name, the same in any worker and any run."""
    return int.from_bytes(name.encode()[-8:].rjust(8, b"\0"), "little") % (2**32)


def make_runner(init: WorkerInit, num_workers: int, ray_address: str | None):
    """The runner for these settings. The depth sources are built here first, so that a
    bad depth folder or model fails before any output is touched (parallel workers then
    build their own)."""
    sources = init.depth_sources()
    if ray_address is not None:
        return RayRunner(ray_address, num_workers, init)  # fails here without Ray
    if num_workers > 1:
        check_not_bootstrapping()
        return PoolRunner(num_workers, init)
    return HereRunner(init, sources)


class HereRunner:
    """Runs the jobs in this process, one Worker for all of them."""

    def __init__(self, init: WorkerInit, sources: dict | None = None):
        self.init, self.sources = init, sources

    def __call__(self, jobs: list[Job], conf: ExtractConf, keep: bool):
        worker = Worker(self.init, self.sources)
        for job in jobs:
            yield worker.process(job, conf, keep)


class PoolRunner:
    """Runs the jobs in ``num_workers`` local processes, one Worker each (a single job
    runs here). Workers start from a forkserver (spawn without one), never by forking
    this process: rectified_colmap.parallel."""

    def __init__(self, num_workers: int, init: WorkerInit):
        self.num_workers, self.init = num_workers, init

    def __call__(self, jobs: list[Job], conf: ExtractConf, keep: bool):
        if len(jobs) <= 1:
            yield from HereRunner(self.init)(jobs, conf, keep)
            return
        os.environ.setdefault("OMP_NUM_THREADS", "1")  # read when the forkserver starts
        level = logging.getLogger("rectified_colmap").getEffectiveLevel()
        with ProcessPoolExecutor(
            self.num_workers,
            mp_context=context([__name__], import_main=False),
            initializer=_start_pool_worker,
            initargs=(self.init, level),
        ) as ex:
            futures = [ex.submit(_pool_process, job, conf, keep) for job in jobs]
            for fut in futures:
                out = fut.result()
                replay(out.logs)
                out.logs = []
                yield out


_pool_worker: Worker | None = None
"""The Worker of a pool process, made by the pool's initializer in that process only
(the caller's process never sets it; its runner holds its own Worker)."""
_pool_logs = None
"""The pool process's captured log records (rectified_colmap.parallel.capture_logs)."""


def _start_pool_worker(init: WorkerInit, level: int) -> None:
    """The pool's initializer: this process's log capture at the caller's ``level``, then
    its Worker (records of its start go back with its first outcome)."""
    global _pool_worker, _pool_logs
    _pool_logs = capture_logs(level)
    _pool_worker = Worker(init)


def _pool_process(job: Job, conf: ExtractConf, keep: bool) -> Outcome:
    out = _pool_worker.process(job, conf, keep)
    out.logs = drain(_pool_logs)
    return out


def _import_ray():
    try:
        import ray
    except ImportError:
        raise RuntimeError(
            "--ray needs Ray, which is not installed: pip install 'rectified-colmap[ray]'"
        ) from None
    return ray


class RayRunner:
    """Runs extraction jobs on Ray actors; a callable like :class:`HereRunner` and
    :class:`PoolRunner`: ``runner(jobs, conf, keep)`` yields the per-image outcomes in job
    order. ``address``: a Ray cluster address, or "local" / "" for a local
    instance (started here, stopped by :meth:`close`). ``num_workers`` actors (1 CPU each);
    1 or less means one per CPU of the cluster. ``init``: what each actor builds its
    Worker from."""

    def __init__(self, address: str | None, num_workers: int, init: WorkerInit):
        self.ray = _import_ray()
        self.address = None if address in (None, "", "local") else address
        self.num_workers = int(num_workers)
        self.init = init
        self._started = False

    def _connect(self):
        ray = self.ray
        if not ray.is_initialized():
            kwargs = {"address": self.address, "log_to_driver": False}
            if self.address is None:
                kwargs.update(include_dashboard=False)
                if self.num_workers > 1:
                    kwargs["num_cpus"] = self.num_workers
            try:
                ray.init(**kwargs)
            except Exception as e:
                raise RuntimeError(
                    f"--ray {self.address or 'local'}: cannot start or reach "
                    f"Ray ({type(e).__name__}: {e})"
                ) from None
            self._started = True
        cpus = int(ray.cluster_resources().get("CPU", 1))
        return max(1, self.num_workers if self.num_workers > 1 else cpus)

    def __call__(self, jobs: list, conf, keep: bool):
        if not jobs:
            return
        ray = self.ray
        from ray.util import ActorPool

        n = min(self._connect(), len(jobs))
        logger.info("Ray: %d actor(s) on %s", n, self.address or "a local instance")
        actor = ray.remote(num_cpus=1)(_Worker)
        pool = ActorPool([actor.remote(self.init) for _ in range(n)])
        conf_ref = ray.put(conf)
        yield from pool.map(lambda a, job: a.process.remote(job, conf_ref, keep), jobs)

    def close(self) -> None:
        if self._started:
            self.ray.shutdown()
            self._started = False


class _Worker:
    """A Ray actor: one worker process's depth sources and SIFT extractor, kept across
    images (the same state a local worker process holds: Worker)."""

    def __init__(self, init: WorkerInit):
        self.worker = Worker(init)

    def process(self, job, conf, keep):
        return self.worker.process(job, conf, keep)
