"""rectified-colmap: SIFT on depth-rectified planes, for COLMAP and hloc."""

# Python's zlib must be loaded before pycolmap: the pycolmap 4.2.1 wheel exports zlib
# symbols of its own, and a process that loads zlib after it (every PNG save through
# matplotlib or PIL) can abort with "free(): invalid pointer". Every module of this package
# imports pycolmap after this line. A program that imports pycolmap before this package
# should `import zlib` first itself (docs/hloc.md).
import logging
import zlib  # noqa: F401  (load order, see above)

__version__ = "0.1.0"

logger = logging.getLogger("rectified_colmap")
logger.addHandler(logging.NullHandler())
