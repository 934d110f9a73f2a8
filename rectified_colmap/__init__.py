"""rectified-colmap: SIFT on depth-rectified planes, for COLMAP and hloc."""

import logging

__version__ = "0.1.0"

logger = logging.getLogger("rectified_colmap")
logger.addHandler(logging.NullHandler())
