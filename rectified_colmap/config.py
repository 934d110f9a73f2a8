"""All configuration defaults, in one place.

Every stage takes its own small dataclass; :class:`ExtractConf` bundles them. Like hloc's
``confs``, a configuration can be given as a nested dict and merged over the defaults with
:func:`ExtractConf.from_dict`, and written back with :meth:`ExtractConf.to_dict`.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any


@dataclass
class NormalConf:
    """Depth -> normals (rectified_colmap.normals)."""

    work_max_size: int = 640
    """Depth, normals and plane labels are computed at this max image side (pixels)."""
    window: int = 5
    """Side of the square window of the local plane fit (odd)."""
    max_depth_jump: float = 0.1
    """A window whose (max-min)/min depth exceeds this is a discontinuity: no normal."""
    max_planarity: float = 0.02
    """Max ratio of the smallest to the middle eigenvalue of the window's scatter matrix."""
    min_valid_frac: float = 0.9
    """A window needs at least this fraction of valid depths (of its pixels inside the grid)."""


@dataclass
class PlaneConf:
    """Normals -> dominant directions -> plane patches (rectified_colmap.planes)."""

    max_angle_deg: float = 20.0
    """A pixel joins a direction when its normal is within this angle of it (or its antipode)."""
    min_area_frac: float = 0.005
    """Connected components smaller than this fraction of the image are dropped."""
    num_samples: int = 8000
    """Normals subsampled for fitting the three directions."""
    num_restarts: int = 4
    """Initialisations of the orthogonal k-means (best inlier count wins)."""
    num_iters: int = 15
    inlier_angle_deg: float = 15.0
    """Normals further than this from every axis are outliers while fitting."""
    opening_radius: int = 1
    """Morphological opening of each label mask before components (pixels at work size)."""
    min_normals: int = 100
    """Fewer valid normals than this: no dominant directions (plain SIFT)."""


@dataclass
class RectifyConf:
    """Plane patches -> homographies and rectified images (rectified_colmap.rectify)."""

    max_viewing_angle_deg: float = 86.0
    """Crop: drop pixels whose viewing ray makes more than this angle with the normal (an
    extreme pair overlaps where each view sees the plane most obliquely: evd-dev 3 -> 5
    pairs from 80 to 86 with the true orientation)."""
    min_rectify_angle_deg: float = 30.0
    """Patches whose median viewing angle (ray to normal, over the patch) is under this are
    left to plain SIFT: seen near-frontally, the warp changes little. Strecha, 1024
    features: GT-correct matches / plain SIFT's (median) 0.87 with 0, 0.96 with 30, 0.97
    with 45; rendered streets keep their gains with 30 (docs/evaluation.md, issue 9)."""
    min_texture: float = 5.0
    """Patches whose median Sobel gradient magnitude on the work grid is under this are left
    to plain SIFT (sky, blank walls; Strecha facades ~40, cobblestones ~15)."""
    max_patch_side: int = 2048
    """Cap on the side of a rectified patch (pixels)."""
    max_patch_area_factor: float = 1.0
    """Cap on the rectified area of a patch, as a multiple of its area in the original image."""
    max_total_area_factor: float = 0.8
    """Budget on the summed size (w x h) of all rectified patches of an image, as a multiple
    of the image's area; patches are scaled down together when over it (bounds the cost of
    SIFT in patches to about that of plain SIFT on the image)."""
    max_total_pixels: float = 2e6
    """Cap on the summed size of all rectified views of an image, in pixels, whatever the
    image size: the views' SIFT costs at most about that of one 2 MP photo. Small photos
    keep views several times their size (evd-dev, 0.3-0.7 MP: 1.2-5 MP of views, which its
    extreme pairs need); a 1536x1024 photo's oblique views are scaled down together."""
    border: int = 6
    """Features closer than this to the border of the warped region are dropped (pixels)."""
    keep_plain: bool = True
    """Also keep plain SIFT on rectified pixels (they share the budget half and half): a
    safety net when the depth, and so the patch orientation, is unreliable."""
    tilt_steps: int = 1
    """Views beside each rectification seen at ``tilt_bank_min_angle_deg`` or more: its
    mask rectified as if its tilt t = 1 / cos(viewing angle) were t x ``tilt_factor``**k,
    k = +-1..+-tilt_steps (rectify.tilt_neighbours): robustness to orientation errors, which
    at 70-80 degrees leave residual tilts SIFT does not absorb (0: off)."""
    tilt_factor: float = 2**0.5
    """Ratio of neighbouring tilts of the bank (ASIFT's sampling step)."""
    tilt_bank_min_angle_deg: float = 45.0
    """Rectifications seen more frontally than this get no tilt neighbours."""


@dataclass
class DedupConf:
    """Near-duplicate keypoints (rectified_colmap.dedup): one feature per location and scale."""

    enabled: bool = True
    """Drop near-duplicates between plain SIFT and rectified patches (and between patches)
    and fill the budget from plain SIFT. Off: the concatenation as before (issue 9)."""
    radius_px: float = 1.0
    """Two keypoints closer than this (original-image pixels) may be twins..."""
    min_cosine: float = 0.9
    """...when their descriptors' cosine similarity exceeds this..."""
    max_scale_ratio: float = 1.5
    """...and their scales (sqrt |det A|) are within this factor."""
    only_across: bool = True
    """Only twins from different sources (plain SIFT, patch k): SIFT's own twins inside one
    detection (e.g. orientations) are left as plain COLMAP SIFT has them."""
    keep_rectified_tilt_deg: float = 25.0
    """Of two twins the rectified one is kept where its patch is seen more obliquely than
    this there (frame anisotropy > 1 / cos), else the plain one."""
    max_plain_cosine: float = 0.9
    """Rectified features whose descriptor has a cosine similarity above this with any kept
    plain feature of the image are dropped (1: none). Such a feature, wherever it lies,
    crowds that plain feature's true match out of Lowe's ratio test as its second-nearest
    neighbour (eval.match_sources; on Sacre Coeur a superset without this rule lost 2.9 % of
    plain SIFT's matches, with 0.9 it keeps 99.4 %: docs/evaluation.md, "Crowding")."""
    extra_frac: float = 0.5
    """Rectified features may come on top of plain SIFT's, up to this fraction of its
    keypoint count (dedup.keypoint_cap); without ``keep_all_plain`` plain features then
    make room (0: as many keypoints as plain SIFT with the same budget)."""
    keep_all_plain: bool = True
    """Every plain feature is kept, whatever the rectified ones: a plain twin always wins,
    and where the rectified features exceed ``extra_frac`` x plain SIFT's count, the
    rectified ones are cut (smallest scales first) instead of plain ones making room. The
    output is then plain SIFT plus at most ``extra_frac`` more, by construction."""


@dataclass
class SiftConf:
    """SIFT (COLMAP's, through pycolmap) and the feature budget."""

    max_num_features: int = 8192
    """Budget for the whole image, shared between patches and the non-planar remainder."""
    first_octave: int = -1
    peak_threshold: float = 0.0066666666666666671
    edge_threshold: float = 10.0
    max_num_orientations: int = 2
    upright: bool = False
    max_image_size: int = 3200
    """Images larger than this are downscaled for SIFT (COLMAP's default)."""
    patch_first_octave: int = -1
    """first_octave inside rectified patches, except in the band below; with -1,
    ``coarse_first`` still skips the upsampled octave in patches whose coarser octaves fill
    their budget."""
    patch_octave0_pixels_per_feature: float = 150.0
    """Images with at least this many pixels per budgeted feature (after
    ``max_image_size``), but fewer than ``coarse_first_pixels_per_feature``, start their
    patches at octave 0 (features.patch_first_octave; inf: never): the patches are already
    enlarged so that no pixel shrinks, and there the upsampled octave costs ~3/4 of their
    SIFT time. Strecha at 8192 features (192 px / feature): GT-correct matches on 42 pairs
    more and 24 fewer than with -1, success equal; rendered streets at 1536x1024: 8.7 %
    fewer GT-correct, the same poses; 2.3-3x less time in patches. Smaller images (EVD,
    Sacre Coeur: <= 101 px / feature; 480x360 renders: 21) keep -1 (docs/benchmarks.md)."""
    coarse_first: bool = True
    """Where an image has at least ``coarse_first_pixels_per_feature`` pixels per budgeted
    feature (after ``max_image_size``), its coarser octaves fill the budget and COLMAP would
    drop the upsampled first octave anyway: compute them alone (features.detect_sift
    ``coarse_first``), ~1/4 of the time and ~1/3 of the memory of one COLMAP call, about the
    same points (not bit-identical). Smaller images get exact COLMAP calls."""
    coarse_first_pixels_per_feature: float = 500.0
    """Strecha photos give one coarse-octave SIFT point per ~370 pixels (8192 features fill
    from ~3 MP up); 500 leaves a margin."""
    patch_budget_factor: float = 2.0
    """With ``dedup.keep_all_plain``: the rectified views' SIFT budgets sum to this x the
    features they may add (dedup.keypoint_cap minus plain SIFT's count), shared by area;
    twins and crowding features go, the cap cuts the rest."""
    pool_coarse_first: bool = True
    """``coarse_first`` also for plain SIFT on the whole image (the pool that fills what the
    patches leave, and images without planes), on images of at least
    ``pool_coarse_first_min_pixels``. False: exact COLMAP calls there at every size, so the
    pool's features are exactly plain COLMAP SIFT's, at COLMAP's time and memory for the
    pool (patches keep ``coarse_first``). Strecha at 1024 features, where coarse-first pays:
    the coarse-first pool alone has fewer GT-correct matches than plain SIFT on 80 pairs,
    more on 36 (docs/benchmarks.md)."""
    pool_coarse_first_min_pixels: float = 3e6
    """The pool runs coarse-first only on images of at least this many pixels (after
    ``max_image_size``), where the budget is filled from the coarser octaves: Strecha
    upscaled to 3072x2048 (6.3 MP), 8192 features, 5 RANSAC runs: success 100 vs 100 %,
    GT-correct more / fewer on 54 / 68 pairs (sign p = 0.24), median ratio 1.00, 2.5x less
    time (docs/benchmarks.md "The exact pool at 3-24 MP"). Below, exact COLMAP calls."""


DISPARITY_SHIFTS = ("zero", "orthogonal")
"""Values of ``DepthConf.disparity_shift`` (rectified_colmap.disparity)."""


@dataclass
class DepthConf:
    """How disparity is turned into depth (rectified_colmap.disparity)."""

    disparity_shift: str = "orthogonal"
    """'zero' (t = 0) or 'orthogonal' (shift from two orthogonal dominant planes; falls back
    to 0 without two planes). Only for disparity (affine-invariant) models. On rendered
    streets with smooth 5% depth errors, 'orthogonal' keeps normal errors ~5.6 deg whatever
    the true shift, 'zero' grows to 7.4 / 15.5 deg at shifts 0.3 / 1.0 x median(1/z)."""

    def __post_init__(self):
        if self.disparity_shift not in DISPARITY_SHIFTS:
            raise ValueError(
                f"depth.disparity_shift must be one of {DISPARITY_SHIFTS}, "
                f"got {self.disparity_shift!r}"
            )


@dataclass
class VpConf:
    """Vanishing-point refinement of the dominant directions (rectified_colmap.vp)."""

    enabled: bool = True
    """Depth + VP: line-derived axes replace the depth directions they match (on since
    2026-11-30, when the chance-level test below stopped false frames on line-free
    textures; measured on Strecha, EVD and rendered streets in docs/vp.md)."""
    max_image_size: int = 640
    """Line segments (LSD) are detected on the image downscaled to this max side."""
    min_length_frac: float = 0.02
    """Segments shorter than this fraction of the image's max side are dropped."""
    max_segments: int = 600
    """Only the longest segments are kept."""
    inlier_angle_deg: float = 2.0
    """A segment supports a VP when the line from its midpoint to the VP is within this
    angle of it (measured on the sphere, around the midpoint ray)."""
    num_hypotheses: int = 600
    """RANSAC frames (2 lines -> VP1, 1 line -> VP2 orthogonal, VP3 = cross)."""
    num_sample_segments: int = 200
    """Hypotheses are drawn from the longest segments, with probability ~ length."""
    num_score_segments: int = 300
    """Hypotheses are scored on the longest segments only (the refinement uses all)."""
    num_refine_iters: int = 6
    """Gauss-Newton iterations (with re-assignment) refining the rotation."""
    num_refine_starts: int = 3
    """The best RANSAC frames refined; the tightest soft inlier length wins."""
    min_vp_segments: int = 8
    """A VP is observed when at least this many segments support it..."""
    min_vp_support: float = 0.04
    """...and they hold at least this fraction of the total segment length."""
    min_strong_support: float = 0.10
    """Frame directions are trusted (finite sigma) only with two VPs holding at least this
    length fraction each (one such VP: only its own direction). Random clutter alone gives
    <= 0.07 per VP; streets and Strecha facades >= 0.11 for the two strongest."""
    nfa_angle_deg: float = 1.0
    """Chance-level test of each frame axis (vp.axis_log10_nfa): segments within this
    angle of the VP count as its support..."""
    nfa_window_deg: float = 10.0
    """...against those within this angle (null: orientations locally uniform in it)."""
    max_log10_nfa: float = -1.0
    """An axis is trusted only when log10 of its number of false alarms (nested over the
    frame's axes) is at most this (inf: no test). Measured (docs/vp.md): 240 views of
    line-free blob textures in perspective give >= -3.6 for the first axis and >= -0.7 for
    the second (5 views keep one trusted axis, none two); the second axis of Strecha and
    York Urban frames <= -4.0; rendered street views of the ground: 3 of 12 lose it."""
    max_sigma_deg: float = 1.5
    """A frame direction may replace a depth direction only when its 1-sigma angular
    uncertainty (from the refinement's covariance) is below this."""
    snap_angle_deg: float = 25.0
    """A depth direction snaps to the matching frame direction when within this angle;
    a confident frame direction further away contradicts it."""
    gravity_angle_deg: float = 10.0
    """With a gravity prior, frames with no axis within this angle of it are rejected."""
    patch_min_segments: int = 5
    """check_patch: fewer labelled segments in the patch: no verdict."""
    patch_min_inplane_frac: float = 0.6
    """check_patch: min length fraction of the patch's segments whose VP lies in the plane."""
    seed: int = 0
    drop_contradicted: bool = False
    """Drop the patches of a depth direction that a confident frame axis contradicts (else
    they keep their depth normal). On rendered streets, clutter-only views (cobblestones)
    can yield a false confident frame: dropping then removed every patch."""
    depth_free: bool = False
    """Images without depth get planes from lines alone (vp.depth_free_planes): each frame
    axis is the normal of the regions where segments of BOTH other VPs are dense."""
    support_radius_frac: float = 0.06
    """Depth-free regions: segment density is averaged over a square window of this
    half-side (fraction of the work grid's max side)..."""
    support_min_lines: float = 0.5
    """...and a cell needs, for each of the two in-plane VPs, at least this many
    window-crossing lengths of its segments in the window."""
    depth_free_regions: str = "lines"
    """Depth-free patches: 'lines' = line-support regions (disjoint, vp.line_support_patches)
    or 'whole' = the paper's VP baseline, whole-image warps (per trusted axis, each side of
    its vanishing line entirely; overlapping, vp.whole_image_patches). See docs/vp.md."""
    line_hypotheses: int = 3
    """Plane hypotheses from pairs of vanishing points (vp.hypotheses; no Manhattan frame, no
    intrinsics needed): whole-image warps for up to this many of the strongest, beside the
    patches of depth (0: off). See docs/vp.md "Plane hypotheses"."""
    num_free_vps: int = 5
    """Plane hypotheses: vanishing points found one after the other (sequential RANSAC)..."""
    num_free_vp_hypotheses: int = 2000
    """...each from this many candidates (pairs of segments)."""
    hypothesis_min_vp_angle_deg: float = 20.0
    """Two VPs closer than this are one family split in two: no plane."""
    hypothesis_merge_angle_deg: float = 10.0
    """A hypothesis within this angle of a better one, or of a patch the image already has,
    is skipped."""
    hypotheses_only_unoriented: bool = False
    """Plane hypotheses only for images whose depth directions no vanishing direction
    snapped to (where the lines already oriented the planes, they are trusted)."""
    hypothesis_min_tilt_deg: float = 50.0
    """Only hypotheses whose plane is tilted at least this much from the image plane (angle
    between the normal and the optical axis) get a patch."""

    def __post_init__(self):
        if self.depth_free_regions not in ("lines", "whole"):
            raise ValueError(
                f"vp.depth_free_regions must be 'lines' or 'whole', got {self.depth_free_regions!r}"
            )


@dataclass
class ExtractConf:
    normals: NormalConf = field(default_factory=NormalConf)
    planes: PlaneConf = field(default_factory=PlaneConf)
    rectify: RectifyConf = field(default_factory=RectifyConf)
    sift: SiftConf = field(default_factory=SiftConf)
    depth: DepthConf = field(default_factory=DepthConf)
    vp: VpConf = field(default_factory=VpConf)
    dedup: DedupConf = field(default_factory=DedupConf)

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, conf: dict[str, Any] | None = None) -> "ExtractConf":
        """Defaults updated by a (possibly partial) nested dict; unknown keys raise."""
        out = cls()
        for section, values in (conf or {}).items():
            if not hasattr(out, section):
                raise KeyError(f"unknown configuration section {section!r}")
            sub = getattr(out, section)
            for key, value in values.items():
                if not hasattr(sub, key):
                    raise KeyError(f"unknown configuration key {section}.{key}")
                setattr(sub, key, type(getattr(sub, key))(value))
            if hasattr(sub, "__post_init__"):  # the section's own validation
                sub.__post_init__()
        return out


def merge_conf(base: dict[str, Any], overrides: dict[str, Any] | None) -> dict[str, Any]:
    """A nested conf dict (e.g. ``confs[name]``) with ``overrides`` on top, section by
    section; neither input is changed."""
    out = {section: dict(values) for section, values in base.items()}
    for section, values in (overrides or {}).items():
        out.setdefault(section, {}).update(values)
    return out


# hloc-style named configurations.
confs: dict[str, dict[str, Any]] = {
    # the default: exact plain SIFT, and rectified features on top (depth patches, plane
    # hypotheses from vanishing points, tilt neighbours): docs/evaluation.md "One default"
    "rectsift": {},
    # cheaper: a coarser work grid, half the budget, one hypothesis, no tilt neighbours
    "rectsift-fast": {
        "normals": {"work_max_size": 480},
        "vp": {"line_hypotheses": 1},
        "rectify": {"tilt_steps": 0, "max_total_pixels": 0.5e6},
        "sift": {"max_num_features": 4096},
    },
    # exactly plain COLMAP SIFT, whatever the depth: no patch can pass, no vanishing points
    # (no plane hypotheses), exact COLMAP calls
    "sift": {
        "planes": {"min_area_frac": 2.0},
        "vp": {"enabled": False, "line_hypotheses": 0},
        "sift": {"coarse_first": False},
    },
}

RETIRED_CONFS: dict[str, str] = {
    "rectsift-wide": "its plane hypotheses from vanishing points are in the default",
    "rectsift-plus": "the default keeps every plain SIFT feature and adds rectified ones",
}
"""Names of earlier confs -> why the default replaces them (the CLI says so and runs the
default)."""


# -- evaluation and localization (rectified_colmap.eval) ----------------------------------


@dataclass
class EvalConf:
    """Relative-pose evaluation on image pairs (rectified_colmap.eval.relpose)."""

    ratio: float = 0.8
    """Lowe's ratio test (the paper's value; hloc's NN-ratio)."""
    mutual: bool = False
    """Also require mutual nearest neighbours."""
    ransac_max_error: float = 2.0
    """Essential-matrix RANSAC threshold (pixels)."""
    ransac_seed: int = 0
    """RANSAC random seed (fixed: reproducible tables)."""
    ransac_runs: int = 1
    """RANSAC runs per pair, with seeds ``ransac_seed`` + 0, 1, ...: the pose errors and
    inlier counts are their medians, so ``success`` is the majority's (odd counts), and
    ``success_rate`` the fraction of runs that succeed. On pairs with few correct matches
    one run's outcome is chance: Strecha's 108-degree pair at 8192 features succeeds in 30
    of 40 seeds with plain SIFT, 36 of 40 with ``rectsift-plus``, and seed 0 splits them."""
    success_deg: float = 5.0
    """A pair succeeds when its rotation error is under this (the paper's criterion)."""
    bin_deg: float = 10.0
    """Width of the ground-truth rotation bins (the paper: 10 degrees, 18 bins)."""
    auc_thresholds: tuple = (5.0, 10.0, 20.0)
    """Pose AUC thresholds (degrees) on max(rotation error, translation-angle error)."""
    epipolar_threshold: float = 3.0
    """A match is correct when its Sampson error under the GT geometry is below this (px)."""
    min_correct: int = 20
    """Degeneracy-aware success: at least this many GT-correct matches."""

    def __post_init__(self):
        if int(self.ransac_runs) < 1:
            raise ValueError(f"ransac_runs must be at least 1, got {self.ransac_runs}")


@dataclass
class HomographyConf:
    """Planar-pair evaluation (rectified_colmap.eval.homography, evaluate-homography)."""

    ratio: float = 0.8
    mutual: bool = True
    ransac_threshold: float = 3.0
    """RANSAC reprojection threshold (pixels of image 1)."""
    ransac_iters: int = 10000
    ransac_confidence: float = 0.9999
    gt_threshold: float = 3.0
    """A match is GT-consistent when H_gt maps x0 within this of x1 (pixels)."""
    success_px: float = 10.0
    """A pair is solved when the error over the visible overlap is below this."""
    grid_step: int = 10
    """Spacing (pixels of image 0) of the grid behind ``visible_err``."""
    region_ransac: bool = False
    """Estimate the homography from the matches whose image-0 point is in the pair's region
    only (pairs without a region: all). For scenes with several planes, e.g. a facade of
    parallel layers (scripts/build_plane_pairs.py), where RANSAC on all matches may
    rightly pick another plane than the one the ground truth is for."""


@dataclass
class LocalizeConf:
    """Offline localization against a triangulated reference (rectified_colmap.eval.localize)."""

    ratio: float = 0.8
    mutual: bool = False
    verify_max_error: float = 4.0
    """Reference matches are kept when their Sampson error under the known poses is below
    this (pixels), as hloc's triangulation.geometric_verification."""
    min_track_length: int = 2
    ransac_max_error: float = 12.0
    """Absolute-pose RANSAC threshold (pixels; hloc's localize_sfm default)."""
    num_retrieved: int = 0
    """Database images matched per query: 0 = all of them."""
    thresholds: tuple = ((0.25, 2.0), (0.5, 5.0), (5.0, 10.0))
    """(metres, degrees) accuracy thresholds (Aachen Day-Night)."""


# -- depth inputs of extraction (rectified_colmap.extract, depth.files, the CLI) ----------

DEFAULT_DEPTH_MODEL = "rectsift-lite0"
"""Depth network for images without a depth file (a name in rectified_colmap.depth.registry)."""
DEFAULT_PNG_SCALE = 0.001
"""16-bit PNG depth files: depth = value x scale (millimetres)."""
DEFAULT_CAMERA_MODEL = "SIMPLE_RADIAL"
"""COLMAP camera model of new cameras made from EXIF (as COLMAP's feature_extractor)."""
