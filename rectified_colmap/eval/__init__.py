"""Evaluation: relative pose on image pairs (pairs, matching, relpose, report), offline
localization (localize), the hloc-free parts of the Aachen pipeline (aachen) and hloc under
the pycolmap 4.2 pin (hloc_compat; hloc imported on use).

Every function takes features by image name (an hloc feature file or a mapping), so plain
and rectified SIFT are scored by identical code. See docs/evaluation.md.
"""
