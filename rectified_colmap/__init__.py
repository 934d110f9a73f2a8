"""rectified-colmap: SIFT on depth-rectified planes, for COLMAP and hloc.

The public API (docs/usage.md, "Python")::

    from rectified_colmap import extract, extract_image, ExtractConf, confs

    extract("images/", database="db.db", conf=confs["rectsift-fast"])   # a folder -> COLMAP
    result = extract_image(image, camera, depth, ExtractConf())           # one image

Everything else is reachable through its module (rectified_colmap.io.colmap_db, ...), but
only the names in ``__all__`` are promised to stay.
"""

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

from .config import (  # noqa: E402  (after zlib)
    DedupConf,
    DepthInputConf,
    ExtractConf,
    NormalConf,
    PlaneConf,
    ReaderConf,
    RectifyConf,
    RunConf,
    SiftConf,
    VpConf,
    confs,
    merge_conf,
)
from .depth import DepthMap  # noqa: E402
from .extraction import extract  # noqa: E402
from .features import Features  # noqa: E402
from .pipeline import ImageResult, extract_image  # noqa: E402
from .sift import Sift  # noqa: E402

__all__ = [
    # entry points: a folder of images -> COLMAP database / hloc HDF5; one image -> features
    "extract",
    "extract_image",
    # the options of a run of extract: images and cameras, depth inputs, processes
    "ReaderConf",
    "DepthInputConf",
    "RunConf",
    # SIFT extractors kept warm across extract_image calls
    "Sift",
    # what they return
    "ImageResult",
    "Features",
    "DepthMap",
    # configuration (docs/configuration.md)
    "ExtractConf",
    "NormalConf",
    "PlaneConf",
    "RectifyConf",
    "SiftConf",
    "DedupConf",
    "VpConf",
    "confs",
    "merge_conf",
]
