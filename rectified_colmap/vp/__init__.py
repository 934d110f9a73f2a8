"""Vanishing points: line segments -> Manhattan frame -> fused dominant directions.

Depth-derived normals say WHICH pixels form planes; line segments say HOW those planes are
oriented, accurately even for far facades where depth is poor. This optional stage sits
between plane clustering and rectification (Toft et al. 2020 name such a hybrid as future
work). Method, measurements and decisions: docs/vp.md.

Modules, in data-flow order (each states its inputs, outputs and conventions):

- ``segments``: LSD segments of the image (COLMAP pixels) and their interpretation planes
  on the Gaussian sphere of the camera (``Segments``, ``detect_segments``,
  ``segments_on_sphere``, ``image_segments``, ``sin_errors``).
- ``manhattan``: the Manhattan frame (RANSAC + Gauss-Newton) and its a-contrario trust test
  (``ManhattanFrame``, ``fit_manhattan``, ``axis_log10_nfa``, ``log10_binomial_tail``).
- ``fusion``: frame axes fused with the depth directions, the entry point
  (``VpResult``, ``match_frame``, ``fuse_directions``, ``refine_directions``).
- ``hypotheses``: plane hypotheses from pairs of vanishing points found without a
  Manhattan frame or intrinsics, as whole-image patches (``free_vanishing_points``,
  ``plane_hypotheses``, ``hypothesis_patches``).

Depth-free planes from lines alone are research code (research/: line_planes). The names
below are re-exported for the pipeline and tools; new code may import from the modules.
"""

from .fusion import VpResult, refine_directions
from .hypotheses import free_vanishing_points, hypothesis_patches, plane_hypotheses
from .segments import image_segments

__all__ = [
    "VpResult",
    "free_vanishing_points",
    "hypothesis_patches",
    "image_segments",
    "plane_hypotheses",
    "refine_directions",
]
