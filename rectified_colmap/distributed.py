"""Extraction beyond one process: shards of an image list, and Ray actors.

Two ways to spread ``rectified-colmap extract`` over machines; both give exactly what a
single-process run gives (tests/test_distributed.py):

- **Shards** (any cluster, e.g. a job array): ``--shard i/n`` keeps the images whose name
  hashes to ``i`` modulo ``n`` (:func:`shard_names`: deterministic, independent of the
  order and of the other names, so adding images never moves one between shards). Each
  job writes its own database / feature file; ``rectified-colmap merge`` combines them
  (rectified_colmap.io.merge).
- **Ray** (``--ray [ADDRESS]``): the per-image work runs as Ray actors (:class:`RayRunner`)
  on an existing cluster (``ray.init(address=ADDRESS)``) or a local instance. Each actor
  holds its depth network and SIFT extractor across images; images are read by the actors
  from the path given (every node must see it). Results come back to the driver in the
  order of the image list and are written there through the crash-safe writers, so resume,
  ``--overwrite`` and every data-safety rule hold as in a local run.

Ray is optional: ``pip install 'rectified-colmap[ray]'``.
"""

from __future__ import annotations

import hashlib
import logging
import re
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from .extract.run import WorkerInit

logger = logging.getLogger(__name__)


def parse_shard(shard: str | tuple[int, int]) -> tuple[int, int]:
    """ "i/n" or (i, n) -> (i, n) with 0 <= i < n; ValueError with the accepted form."""
    if isinstance(shard, str):
        m = re.fullmatch(r"\s*(\d+)\s*/\s*(\d+)\s*", shard)
        if m is None:
            raise ValueError(
                f"--shard {shard!r}: expected INDEX/COUNT, e.g. 0/8 (INDEX from 0 to COUNT-1)"
            )
        shard = (int(m.group(1)), int(m.group(2)))
    index, count = (int(v) for v in shard)
    if count < 1 or not 0 <= index < count:
        raise ValueError(f"--shard {index}/{count}: INDEX must be in 0..COUNT-1")
    return index, count


def shard_of(name: str, count: int) -> int:
    """The shard (0..count-1) of an image name: first 8 bytes of its SHA-1, modulo count."""
    return int.from_bytes(hashlib.sha1(name.encode()).digest()[:8], "big") % count


def shard_names(names: list[str], index: int, count: int) -> list[str]:
    """The names of shard ``index`` of ``count``, in their given order."""
    return [n for n in names if shard_of(n, count) == index]


def _import_ray():
    try:
        import ray
    except ImportError:
        raise RuntimeError(
            "--ray needs Ray, which is not installed: pip install 'rectified-colmap[ray]'"
        ) from None
    return ray


class RayRunner:
    """Runs extraction jobs on Ray actors; a callable like the local runners of
    rectified_colmap.extract.run: ``runner(jobs, conf, keep)`` yields the per-image
    outcomes in job order. ``address``: a Ray cluster address, or "local" / "" for a local
    instance (started here, stopped by :meth:`close`). ``num_workers`` actors (1 CPU each);
    1 or less means one per CPU of the cluster. ``init``: what each actor builds its
    extract.run.Worker from."""

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
    images (the same state a local worker process holds: extract.run.Worker)."""

    def __init__(self, init: WorkerInit):
        from .extract.run import Worker

        self.worker = Worker(init)

    def process(self, job, conf, keep):
        return self.worker.process(job, conf, keep)
