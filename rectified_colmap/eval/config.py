"""Defaults of the evaluation and localization tools (rectified_colmap.eval, the CLI's
``evaluate-pairs``, ``evaluate-homography`` and ``localize``), apart from the extraction
confs of rectified_colmap.config. One line per field; the reasons: docs/configuration.md."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass
class EvalConf:
    """Relative-pose evaluation on image pairs (rectified_colmap.eval.relpose)."""

    ratio: float = 0.8  # Lowe's ratio test (the paper's value; hloc's NN-ratio)
    mutual: bool = False  # also require mutual nearest neighbours
    ransac_max_error: float = 2.0  # essential-matrix RANSAC threshold (pixels)
    ransac_seed: int = 0  # first RANSAC seed (fixed: reproducible tables)
    ransac_runs: int = 1  # RANSAC runs per pair (seeds + 0, 1, ...): medians are reported
    success_deg: float = 5.0  # a pair succeeds under this rotation error (the paper's)
    bin_deg: float = 10.0  # width of the ground-truth rotation bins (the paper's)
    auc_thresholds: tuple = (5.0, 10.0, 20.0)  # pose AUC thresholds (degrees)
    epipolar_threshold: float = 3.0  # GT-correct: Sampson error under the GT below this (px)
    min_correct: int = 20  # degeneracy-aware success: at least this many GT-correct matches

    def __post_init__(self):
        if int(self.ransac_runs) < 1:
            raise ValueError(f"ransac_runs must be at least 1, got {self.ransac_runs}")


@dataclass
class HomographyConf:
    """Planar-pair evaluation (rectified_colmap.eval.homography, evaluate-homography)."""

    ratio: float = 0.8  # Lowe's ratio test
    mutual: bool = True  # also require mutual nearest neighbours
    ransac_threshold: float = 3.0  # RANSAC reprojection threshold (pixels of image 1)
    ransac_iters: int = 10000  # homography RANSAC iterations
    ransac_confidence: float = 0.9999  # homography RANSAC confidence
    gt_threshold: float = 3.0  # GT-consistent: H_gt maps x0 within this of x1 (pixels)
    success_px: float = 10.0  # solved: error over the visible overlap below this (pixels)
    grid_step: int = 10  # spacing of the grid behind visible_err (pixels of image 0)
    region_ransac: bool = False  # RANSAC only on matches in the pair's region (if it has one)


@dataclass
class LocalizeConf:
    """Offline localization against a triangulated reference (rectified_colmap.eval.localize)."""

    ratio: float = 0.8  # Lowe's ratio test
    mutual: bool = False  # also require mutual nearest neighbours
    verify_max_error: float = 4.0  # reference matches: Sampson error under the poses (px)
    min_track_length: int = 2  # reference 3D points need this many observations
    ransac_max_error: float = 12.0  # absolute-pose RANSAC threshold (hloc's localize_sfm)
    num_retrieved: int = 0  # database images matched per query (0: all)
    thresholds: tuple = ((0.25, 2.0), (0.5, 5.0), (5.0, 10.0))  # (m, deg) accuracy bins
