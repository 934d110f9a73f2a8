"""The extraction defaults, in one place (the evaluation tools' are in eval/config.py).

Every stage takes its own small dataclass; :class:`ExtractConf` bundles them. Like hloc's
``confs``, a configuration can be given as a nested dict and merged over the defaults with
:func:`ExtractConf.from_dict`, and written back with :meth:`ExtractConf.to_dict`. One line
per field here; why each default is what it is, with the measurements: docs/configuration.md.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar


@dataclass
class NormalConf:
    """Depth -> normals (rectified_colmap.normals)."""

    work_max_size: int = 640  # max image side of depth, normals and plane labels (pixels)
    window: int = 5  # side of the square window of the local plane fit (odd)
    max_depth_jump: float = 0.1  # (max - min) / min depth in a window above this: no normal
    max_planarity: float = 0.02  # max smallest / middle eigenvalue of the window's scatter
    min_valid_frac: float = 0.9  # min fraction of valid depths in a window


@dataclass
class PlaneConf:
    """Normals -> dominant directions -> plane patches (rectified_colmap.planes)."""

    max_angle_deg: float = 20.0  # a pixel joins a direction within this angle (or antipode)
    min_area_frac: float = 0.005  # components under this fraction of the image are dropped
    inlier_angle_deg: float = 15.0  # normals further than this from every axis: outliers
    opening_radius: int = 1  # morphological opening of each label mask (work-size pixels)
    min_normals: int = 100  # fewer valid normals: no dominant directions (plain SIFT)
    fill_gaps: str = "hull"  # cells in no patch: none | hull | nearest (FILL_GAPS below)

    def __post_init__(self):
        if self.fill_gaps not in FILL_GAPS:
            raise ValueError(
                f"planes.fill_gaps must be one of {', '.join(FILL_GAPS)}, got {self.fill_gaps!r}"
            )


FILL_GAPS = ("none", "hull", "nearest")
"""``PlaneConf.fill_gaps``: cells in no patch stay out (none), join the patch whose convex
hull holds them (hull: planes.patches_filling_hulls; the view's box stays), or join the
nearest patch (nearest: planes.patches_filling_gaps)."""


VIEW_RESOLUTIONS = ("finest", "area", "coarsest")
"""``RectifyConf.view_resolution``: the image->view Jacobian's median smaller singular value
is 1 (finest: nothing shrinks, the foreshortened direction is stretched), the median product
of both is 1 (area: the view has the patch's pixels), or the median larger one is 1
(coarsest: nothing grows, the other direction is compressed, as ASIFT's tilt simulation)."""


def check_view_resolution(rule: str) -> None:
    """ValueError (one line) unless ``rule`` is one of VIEW_RESOLUTIONS."""
    if rule not in VIEW_RESOLUTIONS:
        raise ValueError(
            f"rectify.view_resolution must be one of {', '.join(VIEW_RESOLUTIONS)}, got {rule!r}"
        )


@dataclass
class RectifyConf:
    """Plane patches -> homographies and rectified views (rectified_colmap.rectify)."""

    max_viewing_angle_deg: float = 86.0  # crop pixels seen more obliquely than this
    min_rectify_angle_deg: float = 30.0  # patches seen more frontally: left to plain SIFT
    min_texture: float = 5.0  # work cells with a lower Sobel magnitude get no view pixels
    view_resolution: str = "finest"  # finest | area | coarsest (VIEW_RESOLUTIONS above)
    max_patch_side: int = 2048  # cap on a rectified view's side (pixels)
    max_view_pixels_factor: float = 2.0  # all views' pixels / the image's (as SIFT sees it;
    # budget.OPENCV_VIEW_PIXELS_RATIO x where OpenCV's SIFT runs the views)
    border: int = 6  # features closer than this to a view's border are dropped (pixels)
    tilt_steps: int = 1  # tilt neighbours per side of an oblique view (0: none)
    tilt_factor: float = 2**0.5  # ratio of neighbouring tilts (ASIFT's step)
    tilt_bank_min_angle_deg: float = 45.0  # views seen more frontally get no neighbours

    def __post_init__(self):
        check_view_resolution(self.view_resolution)


@dataclass
class DedupConf:
    """Near-duplicate keypoints and the keypoint cap (rectified_colmap.dedup)."""

    radius_px: float = 1.0  # twins lie closer than this (original-image pixels)...
    min_cosine: float = 0.9  # ...with descriptors more similar than this...
    max_scale_ratio: float = 1.5  # ...and scales within this factor
    max_plain_cosine: float = 0.9  # rectified features this similar to a plain one: look-alikes
    lookalikes_in_unused_budget: bool = True  # look-alikes (and the views over the rest of a
    # plane, blind views) only in plain SIFT's unused budget (budget.unused_room); False: never
    extra_frac: float = 0.5  # rectified features on top: at most this x plain SIFT's budget


PATCH_BACKENDS = ("colmap", "opencv")
"""``SiftConf.patch_backend``: SIFT in the rectified views of images whose views start at
octave -1 or 0 in one call (sift.opencv_views: where coarse-first does not pay, up to ~4 MP
at 8192 features): COLMAP's through pycolmap, or OpenCV's with precise upscaling
(sift.opencv_sift: the same keypoints and, in COLMAP's RootSIFT byte scale, the same
descriptors, 2.5-3x faster on one core; views from octave -1 then get
budget.OPENCV_VIEW_PIXELS_RATIO x the pixels). Plain SIFT is COLMAP's always."""


@dataclass
class SiftConf:
    """SIFT (COLMAP's, through pycolmap) and the feature budget (rectified_colmap.features)."""

    max_num_features: int = 8192  # plain SIFT's budget (COLMAP's max_num_features)
    first_octave: int = -1  # COLMAP's SiftExtraction options from here...
    peak_threshold: float = 0.0066666666666666671
    edge_threshold: float = 10.0
    max_num_orientations: int = 2
    upright: bool = False
    max_image_size: int = 3200  # ...to here (larger images are downscaled, as COLMAP)
    patch_first_octave: int = -1  # first octave in rectified views
    patch_octave0_pixels_per_feature: float = 150.0  # from here views start at octave 0; and the
    # pixels the views budget counts: this x max_num_features (budget.view_pixel_budget)
    coarse_first: bool = True  # large images: coarse octaves first (features.detect_sift)
    coarse_first_pixels_per_feature: float = 500.0  # ...from this many pixels per feature
    patch_budget_factor: float = 2.0  # views' SIFT budget / the features they may add
    patch_backend: str = "opencv"  # views from octave -1 / 0: colmap | opencv (PATCH_BACKENDS)
    pool_coarse_first_min_pixels: float = 3e6  # plain SIFT coarse-first from this many pixels

    def __post_init__(self):
        if self.patch_backend not in PATCH_BACKENDS:
            raise ValueError(
                f"sift.patch_backend must be one of {', '.join(PATCH_BACKENDS)}, "
                f"got {self.patch_backend!r}"
            )
        if self.max_num_features < 1:
            raise ValueError(
                f"sift.max_num_features must be at least 1, got {self.max_num_features}"
            )


@dataclass
class VpConf:
    """Vanishing points: orientation of the depth planes and plane hypotheses
    (rectified_colmap.vp; docs/vp.md)."""

    enabled: bool = True  # line-derived axes replace the depth directions they match
    max_image_size: int = 640  # LSD runs on the image downscaled to this side
    min_length_frac: float = 0.02  # shorter segments (fraction of the max side) dropped
    max_segments: int = 600  # only the longest segments are kept
    inlier_angle_deg: float = 2.0  # a segment supports a VP within this angle
    num_hypotheses: int = 600  # RANSAC frames (2 lines -> VP1, 1 line -> VP2)
    min_vp_segments: int = 8  # a VP is observed with at least this many segments...
    min_vp_support: float = 0.04  # ...holding at least this fraction of the length
    min_strong_support: float = 0.10  # two VPs this strong are needed to trust a frame
    max_log10_nfa: float = -1.0  # an axis is trusted up to this log10 false alarms
    max_sigma_deg: float = 1.5  # max 1-sigma uncertainty of a replacing direction
    snap_angle_deg: float = 25.0  # a depth direction within this snaps to the frame's
    seed: int = 0  # RANSAC seed
    line_hypotheses: int = 3  # plane hypotheses from pairs of VPs per image (0: off)
    num_free_vps: int = 5  # hypotheses: VPs found one after the other...
    num_free_vp_hypotheses: int = 2000  # ...each from this many segment pairs
    hypothesis_min_vp_angle_deg: float = 20.0  # closer VPs are one family: no plane
    hypothesis_merge_angle_deg: float = 10.0  # hypotheses this close to a better one: skipped
    hypothesis_min_tilt_deg: float = 50.0  # only planes tilted this much from the image


@dataclass
class ExtractConf:
    """Every stage's conf (a hloc-style nested dict: :meth:`from_dict`, :meth:`to_dict`)."""

    normals: NormalConf = field(default_factory=NormalConf)
    planes: PlaneConf = field(default_factory=PlaneConf)
    rectify: RectifyConf = field(default_factory=RectifyConf)
    sift: SiftConf = field(default_factory=SiftConf)
    vp: VpConf = field(default_factory=VpConf)
    dedup: DedupConf = field(default_factory=DedupConf)

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    def validate(self) -> "ExtractConf":
        """Each section's own checks again (values set after construction); ValueError
        naming the key. Returns self."""
        for f in dataclasses.fields(self):
            sub = getattr(self, f.name)
            if hasattr(sub, "__post_init__"):
                sub.__post_init__()
        return self

    @classmethod
    def from_dict(cls, conf: dict[str, Any] | None = None) -> "ExtractConf":
        """Defaults updated by a (possibly partial) nested dict; unknown keys raise."""
        out = cls()
        for section, values in (conf or {}).items():
            if section in RETIRED_KEYS:
                raise KeyError(f"configuration section {section!r}: {RETIRED_KEYS[section]}")
            if not hasattr(out, section):
                raise KeyError(f"unknown configuration section {section!r}")
            sub = getattr(out, section)
            for key, value in values.items():
                if f"{section}.{key}" in RETIRED_KEYS:
                    raise KeyError(f"{section}.{key}: {RETIRED_KEYS[f'{section}.{key}']}")
                if not hasattr(sub, key):
                    raise KeyError(f"unknown configuration key {section}.{key}")
                setattr(sub, key, _typed(f"{section}.{key}", getattr(sub, key), value))
            if hasattr(sub, "__post_init__"):  # the section's own validation
                sub.__post_init__()
        return out


def _typed(name: str, default: Any, value: Any) -> Any:
    """``value`` as the type of the key's ``default``; ValueError (one line) where that would
    change its meaning: a bool from anything but true / false (bool("false") is True), a
    str from a non-string, an int from a fraction or a bool, a float from a bool."""
    kind = type(default)
    ok = {
        bool: isinstance(value, bool),
        str: isinstance(value, str),
        int: isinstance(value, int | float)
        and not isinstance(value, bool)
        and float(value).is_integer(),
        float: isinstance(value, int | float) and not isinstance(value, bool),
    }.get(kind, True)
    if not ok:
        raise ValueError(f"{name} must be {_KIND_NAMES.get(kind, kind.__name__)}, got {value!r}")
    return kind(value)


_KIND_NAMES = {bool: "true or false", str: "a string", int: "an integer", float: "a number"}


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
        "rectify": {"tilt_steps": 0, "max_view_pixels_factor": 1.0},
        "sift": {"max_num_features": 4096},
    },
    # exactly plain COLMAP SIFT, whatever the depth: no patch can pass, no vanishing points
    # (no plane hypotheses), no second tier (no blind views), exact COLMAP calls
    "sift": {
        "planes": {"min_area_frac": 2.0},
        "vp": {"enabled": False, "line_hypotheses": 0},
        "dedup": {"lookalikes_in_unused_budget": False},
        "sift": {"coarse_first": False},
    },
}

_REPLACING = "retired with the replacing mode: plain SIFT's features are always all kept"
_FIXED = "retired: now a fixed constant of its module"
_DEPTH_FREE = "retired with the depth-free planes (research/: vp_planes)"
_VIEW_BUDGET = "retired: the views' pixels are rectify.max_view_pixels_factor x the image's"
RETIRED_KEYS: dict[str, str] = {
    "depth": "retired: a disparity map's shift is always fitted to orthogonal planes",
    "planes.num_samples": _FIXED + " (planes.NUM_SAMPLES)",
    "planes.num_restarts": _FIXED + " (planes.NUM_RESTARTS)",
    "planes.num_iters": _FIXED + " (planes.NUM_ITERS)",
    "rectify.keep_plain": _REPLACING,
    "rectify.tilt_bank_of": "retired: tilt neighbours are around plane hypotheses, and around"
    " depth planes where plain SIFT left budget unused (pipeline.image_views)",
    "sift.patch_upsample_in_warp": "retired: views that COLMAP's SIFT runs from octave -1 are"
    " always warped at it (sift.warp_upsampling)",
    "rectify.max_patch_area_factor": _VIEW_BUDGET,
    "rectify.max_total_area_factor": _VIEW_BUDGET,
    "rectify.max_total_pixels": _VIEW_BUDGET,
    "dedup.enabled": "retired: near-duplicates are always resolved",
    "dedup.only_across": "retired: twins are always sought across sources",
    "dedup.keep_rectified_tilt_deg": _REPLACING,
    "dedup.keep_all_plain": _REPLACING,
    "sift.pool_coarse_first": "retired: set sift.pool_coarse_first_min_pixels instead",
    "vp.num_sample_segments": _FIXED + " (vp.segments.NUM_SAMPLE_SEGMENTS)",
    "vp.num_score_segments": _FIXED + " (vp.manhattan.NUM_SCORE_SEGMENTS)",
    "vp.num_refine_iters": _FIXED + " (vp.manhattan.NUM_REFINE_ITERS)",
    "vp.num_refine_starts": _FIXED + " (vp.manhattan.NUM_REFINE_STARTS)",
    "vp.nfa_angle_deg": _FIXED + " (vp.manhattan.NFA_ANGLE_DEG)",
    "vp.nfa_window_deg": _FIXED + " (vp.manhattan.NFA_WINDOW_DEG)",
    "vp.gravity_angle_deg": "retired with the gravity prior",
    "vp.patch_min_segments": "retired with vp.fusion.check_patch",
    "vp.patch_min_inplane_frac": "retired with vp.fusion.check_patch",
    "vp.depth_free": _DEPTH_FREE,
    "vp.support_radius_frac": _DEPTH_FREE,
    "vp.support_min_lines": _DEPTH_FREE,
    "vp.depth_free_regions": _DEPTH_FREE,
}
"""Configuration keys (and sections) of earlier versions -> why they are gone (from_dict
says so instead of "unknown key")."""

RETIRED_CONFS: dict[str, str] = {
    "rectsift-wide": "its plane hypotheses from vanishing points are in the default",
    "rectsift-plus": "the default keeps every plain SIFT feature and adds rectified ones",
}
"""Names of earlier confs -> why the default replaces them (the CLI says so and runs the
default)."""


# -- depth inputs of extraction (rectified_colmap.extraction, depth.files, the CLI) ----------

DEFAULT_DEPTH_MODEL = "rectsift-lite0"
"""Depth network for images without a depth file (a name in rectified_colmap.depth.registry)."""
DEFAULT_PNG_SCALE = 0.001
"""16-bit PNG depth files: depth = value x scale (millimetres)."""
DEFAULT_CAMERA_MODEL = "SIMPLE_RADIAL"
"""COLMAP camera model of new cameras made from EXIF (as COLMAP's feature_extractor)."""


# -- the options of a run of rectified_colmap.extract (inputs, not the method) --------------


@dataclass
class ReaderConf:
    """Which images, and how their cameras are made: COLMAP's ImageReaderOptions
    (``--ImageReader.*``; rectified_colmap.extraction.plan)."""

    image_list: Path | list[str] | None = None  # names under the image folder, or a file of them
    mask_path: Path | None = None  # COLMAP's keypoint masks: <mask_path>/<name>.png
    camera_model: str | None = None  # new cameras' model (default: DEFAULT_CAMERA_MODEL, EXIF)
    camera_params: list[float] | str | None = None  # "p1,p2,..." in COLMAP's order
    single_camera: bool = False  # one camera for all new images
    single_camera_per_folder: bool = False  # one camera per folder of new images
    default_focal_length_factor: float = 1.2  # without EXIF: f = this x the larger side


@dataclass
class DepthInputConf:
    """Where depth comes from (rectified_colmap.extraction.run): a depth file, else the
    network, else none (plain SIFT)."""

    path: Path | None = None  # folder of depth files (rectified_colmap.depth.files)
    kind: str = "depth"  # what the files hold: depth, metric or disparity
    png_scale: float = DEFAULT_PNG_SCALE  # 16-bit PNG depth = value x this
    model: str | None = DEFAULT_DEPTH_MODEL  # network: registry name, .onnx path or "none"


@dataclass
class RunConf:
    """How a run goes (rectified_colmap.extraction): processes, shards, Ray, pictures."""

    num_workers: int = 1  # worker processes (with ray_address: Ray actors)
    shard: str | tuple[int, int] | None = None  # "i/n": this job's share of the images
    ray_address: str | None = None  # a Ray cluster ("local": a local instance)
    progress: bool = True  # a progress bar
    visualize: Path | None = None  # PNGs of each image's planes and features here


_Options = TypeVar("_Options", ReaderConf, DepthInputConf, RunConf)


def options(cls: type[_Options], value: _Options | dict | None) -> _Options:
    """``value`` as a ``cls`` (a ReaderConf, DepthInputConf or RunConf): itself, the defaults
    updated by a dict, or the defaults; ValueError naming an unknown key."""
    if isinstance(value, cls):
        return value
    value = dict(value or {})
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(value) - names)
    if unknown:
        raise ValueError(f"{cls.__name__}: unknown key(s) {unknown}; known: {sorted(names)}")
    return cls(**value)
