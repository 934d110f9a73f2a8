"""Homography evaluation of features on planar image pairs (HPatches / EVD protocol).

Per pair and method: ratio-test matching (rectified_colmap.eval.matching, mutual by
default), a homography estimated with RANSAC (OpenCV, fixed iterations and confidence:
deterministic), and its error against the ground-truth homography:

- ``corner_err``: mean distance (pixels of image 1) between the four corners of image 0
  mapped by the estimate and by the ground truth (HPatches' corner error);
- ``visible_err``: mean distance over a grid of image-0 points whose ground-truth position
  lands inside image 1 (in extreme views corners can map near the horizon, which makes the
  corner error meaningless there); ``success`` = visible_err below ``success_px`` (10);
- ``num_gt``: matches consistent with the ground truth (|H_gt x0 - x1| < ``gt_threshold``,
  3 px): this does not depend on RANSAC;

A pair may give the **region** of image 0 that the homography governs (a plane of a 3D
scene, e.g. the pairs of scripts/build_plane_pairs.py): then only grid points inside it
count in ``visible_err``, and only matches whose image-0 point is inside it in ``num_gt``
(matches off the plane are not wrong, H just does not say where they go). Without a region
(EVD, HPatches: the whole image is the plane) both are as before. ``region_ransac``
(HomographyConf, off by default) also estimates the homography from those matches only.
- ``num_inliers``: RANSAC inliers of the estimate.

A failed estimation (fewer than 4 matches, no model, a point mapped behind the camera)
gives errors of ``inf``.

Pixel conventions: keypoints from FeatureSource are COLMAP pixels; ground-truth
homographies are read in either convention (EVD and HPatches publish OpenCV's, 0-based
centres) and converted once, through rectified_colmap.conventions, to a map between COLMAP
pixel frames. All errors are in pixels of image 1.

Pair files: a JSON list of objects with ``im0``, ``im1`` (feature names), ``H`` (3x3 row
major, image 0 -> image 1), optional ``pair`` (a label), ``size0``/``size1`` ([W, H]; else
read from the images with ``image_root``) and ``convention`` ("opencv", the default, or
"colmap"): shared/data/evd-dev/pairs.json is one. Optional ``region0``: the region, a list
of polygons (each a list of [x, y] image-0 pixels in the file's convention; their union,
even-odd rule inside each), and ``region1``, the same in image 1 (else ``region0`` mapped by
H: a homography maps a polygon in front of both cameras onto a polygon); the reverse
direction uses ``region1``. Other keys are kept in ``HomographyPair.info``.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from .config import HomographyConf  # noqa: F401 (part of this module's API)
from ..conventions import from_opencv_points
from .matching import FeatureSource, match_ratio

logger = logging.getLogger(__name__)


@dataclass
class HomographyPair:
    name: str
    im0: str
    im1: str
    H: np.ndarray
    """(3, 3) image 0 -> image 1 between COLMAP pixel frames."""
    size0: tuple[int, int]
    size1: tuple[int, int]
    """(W, H) of each image."""
    region0: list[np.ndarray] | None = None
    """Polygons (K_i, 2), COLMAP pixels of image 0, whose union is where H holds; None: the
    whole image."""
    region1: list[np.ndarray] | None = None
    """The same region in image 1 (used by :meth:`reverse`)."""
    info: dict = field(default_factory=dict)
    """The pair file's other keys (e.g. a set name or a band), unused here."""

    def reverse(self) -> HomographyPair:
        """The pair from image 1 to image 0 (H^-1, regions swapped)."""
        return HomographyPair(
            self.name,
            self.im1,
            self.im0,
            np.linalg.inv(self.H),
            self.size1,
            self.size0,
            self.region1,
            self.region0,
            self.info,
        )


def colmap_homography_from_opencv(H: np.ndarray) -> np.ndarray:
    """A homography between OpenCV pixel frames (centre of the top-left pixel at 0) -> the
    same map between COLMAP frames (centre at 0.5): T H T^-1, T the translation that
    conventions.from_opencv_points applies (the inverse of conventions.to_opencv_homography).
    """
    T = np.eye(3)
    T[:2, 2] = from_opencv_points(np.zeros(2))
    return T @ np.asarray(H, np.float64) @ np.linalg.inv(T)


def points_in_region(xy: np.ndarray, region: list[np.ndarray] | None) -> np.ndarray:
    """(N,) bool: which of the (N, 2) points lie in the union of the polygons of ``region``
    (each (K, 2) vertices in order, closed implicitly; even-odd rule, so a self-crossing
    polygon's doubly covered parts are outside). None: every point. Points exactly on an
    edge may fall either side."""
    xy = np.asarray(xy, np.float64).reshape(-1, 2)
    if region is None:
        return np.ones(len(xy), bool)
    out = np.zeros(len(xy), bool)
    x, y = xy[:, 0:1], xy[:, 1:2]
    for poly in region:
        a = np.asarray(poly, np.float64).reshape(-1, 2)
        b = np.roll(a, -1, axis=0)  # edge k: a[k] -> b[k]
        straddle = (a[:, 1] > y) != (b[:, 1] > y)  # (N, K): the edge crosses the row y
        with np.errstate(divide="ignore", invalid="ignore"):
            xc = a[:, 0] + (y - a[:, 1]) * (b[:, 0] - a[:, 0]) / (b[:, 1] - a[:, 1])
        out |= (straddle & (x < xc)).sum(1) % 2 == 1  # crossings to the right of the point
    return out


def _read_region(value, H: np.ndarray | None, conv: str, where: str) -> list[np.ndarray]:
    """Polygons of a pair file (file convention) -> COLMAP pixels, mapped by ``H`` if given."""
    try:
        polys = [np.asarray(p, np.float64).reshape(-1, 2) for p in value]
    except (TypeError, ValueError) as e:
        raise ValueError(f"{where}: a region is a list of polygons of [x, y] ({e})") from None
    if not polys or any(len(p) < 3 for p in polys):
        raise ValueError(f"{where}: a region needs polygons of at least 3 vertices")
    if conv == "opencv":
        polys = [from_opencv_points(p) for p in polys]
    if H is not None:
        polys = [apply_homography(H, p) for p in polys]
        if not all(np.isfinite(p).all() for p in polys):
            raise ValueError(f"{where}: region0 maps behind camera 1; give region1")
    return polys


def read_homography_pairs(
    path: Path | str, image_root: Path | str | None = None
) -> list[HomographyPair]:
    """Pairs of a JSON pair file (see the module docstring)."""
    path = Path(path)
    items = json.loads(path.read_text())
    if not isinstance(items, list):
        raise ValueError(f"{path}: expected a JSON list of pairs")
    out = []
    for k, it in enumerate(items):
        try:
            H = np.asarray(it["H"], np.float64).reshape(3, 3)
            im0, im1 = str(it["im0"]), str(it["im1"])
        except (KeyError, ValueError) as e:
            raise ValueError(f"{path}: pair {k}: needs im0, im1 and a 3x3 H ({e})") from None
        conv = it.get("convention", "opencv")
        if conv not in ("opencv", "colmap"):
            raise ValueError(f"{path}: pair {k}: convention must be opencv or colmap")
        if conv == "opencv":
            H = colmap_homography_from_opencv(H)
        where = f"{path}: pair {k}"
        sizes = [
            _pair_size(it, key, im, image_root, where)
            for key, im in (("size0", im0), ("size1", im1))
        ]
        H, region0, region1 = _pair_regions(it, H, conv, where)
        known = {"pair", "im0", "im1", "H", "size0", "size1", "convention", "region0", "region1"}
        out.append(
            HomographyPair(
                str(it.get("pair", f"{im0}--{im1}")),
                im0,
                im1,
                H,
                sizes[0],
                sizes[1],
                region0,
                region1,
                {key: v for key, v in it.items() if key not in known},
            )
        )
    return out


def _pair_size(item: dict, key: str, name: str, image_root, where: str) -> tuple[int, int]:
    """(W, H) of a pair file's image: its ``size0``/``size1`` entry, else read from the
    image under ``image_root``."""
    if key in item:
        return int(item[key][0]), int(item[key][1])
    if image_root is None:
        raise ValueError(f"{where}: no {key} and no image_root to read it")
    img = cv2.imread(str(Path(image_root) / name), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise ValueError(f"{where}: cannot read {name} under {image_root}")
    return img.shape[1], img.shape[0]


def _pair_regions(item: dict, H: np.ndarray, conv: str, where: str):
    """(H, region0, region1) of a pair file's entry: H with the sign of the regions the
    entry gives (both: ``overlap_positive_homography``; one: ``positive_homography`` of
    region0's vertices, or of region1's, whose sign through H^-1 is H's), else of image 0's
    centre; each region as given, the missing one mapped from the other through H (None,
    None without a region)."""
    region0 = region1 = None
    if "region0" in item:
        region0 = _read_region(item["region0"], None, conv, where)
    if "region1" in item:
        region1 = _read_region(item["region1"], None, conv, where)
    if region0 is not None and region1 is not None:
        H = overlap_positive_homography(H, region0, region1)
    elif region0 is not None:
        H = positive_homography(H, points0=np.concatenate(region0))
    elif region1 is not None:
        H = np.linalg.inv(positive_homography(np.linalg.inv(H), points0=np.concatenate(region1)))
    else:
        H = positive_homography(H, item.get("size0"))
    if region0 is not None and region1 is None:
        region1 = [apply_homography(H, p) for p in region0]
        if not all(np.isfinite(p).all() for p in region1):
            raise ValueError(f"{where}: region0 maps behind camera 1; give region1")
    elif region1 is not None and region0 is None:
        region0 = [apply_homography(np.linalg.inv(H), p) for p in region1]
        if not all(np.isfinite(p).all() for p in region0):
            raise ValueError(f"{where}: region1 maps behind camera 0; give region0")
    return H, region0, region1


def overlap_positive_homography(
    H: np.ndarray, region0: list[np.ndarray], region1: list[np.ndarray], n: int = 64
) -> np.ndarray:
    """H up to scale, with the sign under which the points of ``region0`` (the plane in
    image 0) that H maps into ``region1`` (the plane in image 1) map to w > 0: on an
    n x n grid over region0's box. Exact by construction: a plane's points in front of
    camera 1 project to one side of its horizon line, those behind it to the other, and
    region1 holds only points seen in front; so only the right sign maps any point of
    region0 into region1 with w > 0. Needed where region0 reaches beyond camera 1's horizon
    (a texture seen whole by an oblique view 0), where most of its vertices may map behind
    camera 1. Where the regions do not overlap: ``positive_homography`` of region0's
    vertices."""
    vertices = np.concatenate(region0)
    lo, hi = vertices.min(0), vertices.max(0)
    u, v = np.meshgrid(np.linspace(lo[0], hi[0], n), np.linspace(lo[1], hi[1], n))
    g = np.stack([u.ravel(), v.ravel()], 1)
    g = g[points_in_region(g, region0)]
    w = np.c_[g, np.ones(len(g))] @ H.T
    with np.errstate(divide="ignore", invalid="ignore"):
        inside = points_in_region(w[:, :2] / w[:, 2:], region1)
    front, behind = np.sum(inside & (w[:, 2] > 0)), np.sum(inside & (w[:, 2] < 0))
    if front == behind:
        return positive_homography(H, points0=vertices)
    return H if front > behind else -H


def positive_homography(H: np.ndarray, size0=None, points0: np.ndarray | None = None) -> np.ndarray:
    """H up to scale, with the sign under which the plane's points in front of both cameras
    map to w > 0: a homography's scale includes its sign, and points map behind the camera
    (w <= 0) only for the sign that says so. The sign is taken from ``points0`` ((N, 2)
    image-0 points known to show the plane in both images, e.g. a pair's region: most of
    them must map to w > 0), else from the centre of image 0 (W, H = ``size0``; else the
    origin), which is right only where that centre sees the plane in front of camera 1 (at
    extreme tilts it may lie beyond the plane's horizon)."""
    if points0 is not None and len(points0):
        w = np.c_[points0, np.ones(len(points0))] @ H[2]
        return -H if np.sum(np.sign(w)) < 0 else H
    c = np.array([size0[0] / 2, size0[1] / 2, 1.0]) if size0 is not None else np.eye(3)[2]
    return -H if (H @ c)[2] < 0 else H


def apply_homography(H: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """(N, 2) points -> (N, 2) mapped points; NaN where the point maps to w <= 0 (behind)."""
    p = np.asarray(xy, np.float64) @ H[:, :2].T + H[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        out = p[:, :2] / p[:, 2:]
    out[p[:, 2] <= 1e-12] = np.nan
    return out


def corners(size: tuple[int, int]) -> np.ndarray:
    """(4, 2) COLMAP coordinates of the image corners (outer pixel edges) for (W, H)."""
    W, H = size
    return np.array([[0.0, 0.0], [W, 0.0], [W, H], [0.0, H]])


def visible_grid(pair: HomographyPair, step: int) -> np.ndarray:
    """(M, 2) image-0 points on a grid (``step`` px) whose ground-truth position lies in
    image 1 (in front of its camera) and, when the pair has one, inside its region."""
    W, H = pair.size0
    xs = np.arange(step / 2, W, step)
    ys = np.arange(step / 2, H, step)
    g = np.stack(np.meshgrid(xs, ys), -1).reshape(-1, 2)
    m = apply_homography(pair.H, g)
    W1, H1 = pair.size1
    with np.errstate(invalid="ignore"):
        ok = (m[:, 0] >= 0) & (m[:, 0] <= W1) & (m[:, 1] >= 0) & (m[:, 1] <= H1)
    if pair.region0 is not None:
        ok &= points_in_region(g, pair.region0)
    return g[ok]


def homography_errors(
    H_est: np.ndarray | None, pair: HomographyPair, step: int = 10
) -> tuple[float, float]:
    """(corner error, visible-overlap error): mean distances in pixels of image 1 between
    the estimate's and the ground truth's images of the corners / the visible grid; inf
    when there is no estimate or it maps a point behind the camera."""
    if H_est is None:
        return np.inf, np.inf
    out = []
    for pts in (corners(pair.size0), visible_grid(pair, step)):
        if len(pts) == 0:
            out.append(np.nan)
            continue
        d = np.linalg.norm(apply_homography(H_est, pts) - apply_homography(pair.H, pts), axis=1)
        out.append(float(d.mean()) if np.isfinite(d).all() else np.inf)
    return out[0], out[1]


def estimate_homography(
    x0: np.ndarray, x1: np.ndarray, conf: HomographyConf
) -> tuple[np.ndarray | None, np.ndarray]:
    """RANSAC homography between COLMAP pixel frames from (N, 2) matched points ->
    (H or None, (N,) bool inliers). OpenCV's RANSAC is run in COLMAP coordinates directly:
    a homography between the same frames, so no conversion is needed. H's sign is the one
    under which its inliers map to w > 0 (positive_homography), as the ground truth's."""
    if len(x0) < 4:
        return None, np.zeros(len(x0), bool)
    cv2.setRNGSeed(0)
    H, inl = cv2.findHomography(
        x0.astype(np.float64),
        x1.astype(np.float64),
        cv2.RANSAC,
        conf.ransac_threshold,
        maxIters=conf.ransac_iters,
        confidence=conf.ransac_confidence,
    )
    if H is None or not np.isfinite(H).all():
        return None, np.zeros(len(x0), bool)
    inl = inl.ravel().astype(bool)
    # OpenCV's H[2, 2] = 1 takes the sign by image 0's origin, which at extreme tilts sees
    # the plane behind camera 1: the inliers, seen by both cameras, set it instead.
    return positive_homography(H, points0=x0[inl]), inl


def match_gt_errors(
    pair: HomographyPair, f0: Mapping, f1: Mapping, conf: HomographyConf
) -> tuple[np.ndarray, np.ndarray]:
    """The matches of one pair and method (f0/f1 as ``evaluate_pair``'s): (M, 2) index pairs
    (ratio test, ``conf.mutual``) and (M,) their distances |H_gt x0 - x1| (COLMAP px), inf
    where the image-0 point is outside ``pair.region0``: the GT-consistent ones are those
    under ``conf.gt_threshold``."""
    m = match_ratio(f0["descriptors"], f1["descriptors"], conf.ratio, conf.mutual)
    x0, x1 = f0["keypoints"][m[:, 0]], f1["keypoints"][m[:, 1]]
    err = np.linalg.norm(apply_homography(pair.H, x0) - x1, axis=1) if len(m) else np.zeros(0)
    if pair.region0 is not None and len(m):
        err[~points_in_region(x0, pair.region0)] = np.inf
    return m, err


def evaluate_pair(pair: HomographyPair, f0: Mapping, f1: Mapping, conf: HomographyConf) -> dict:
    """One pair, one method: f0/f1 dicts with ``keypoints`` (N, 2) COLMAP px and
    ``descriptors`` (N, D). Returns a record (plain dict); with a region, ``num_gt`` counts
    only matches whose image-0 point is in it, and with ``conf.region_ransac`` only they
    estimate the homography (``num_inliers`` among them)."""
    m, err = match_gt_errors(pair, f0, f1, conf)
    x0, x1 = f0["keypoints"][m[:, 0]], f1["keypoints"][m[:, 1]]
    use = np.ones(len(m), bool)
    if pair.region0 is not None and len(m) and conf.region_ransac:
        use = points_in_region(x0, pair.region0)
    H, inl = estimate_homography(x0[use], x1[use], conf)
    ce, ve = homography_errors(H, pair, conf.grid_step)
    return {
        "pair": pair.name,
        "num_kp0": len(f0["keypoints"]),
        "num_kp1": len(f1["keypoints"]),
        "num_matches": int(len(m)),
        "num_gt": int(np.sum(err < conf.gt_threshold)),
        "num_inliers": int(inl.sum()),
        "corner_err": ce,
        "visible_err": ve,
        "success": bool(ve < conf.success_px),
    }


def evaluate_homography_pairs(
    pairs: list[HomographyPair],
    methods: Mapping[str, Path | str | Mapping],
    conf: HomographyConf = HomographyConf(),
    both_directions: bool = True,
) -> list[dict]:
    """Records for every pair (and, with ``both_directions``, its reverse: H^-1, image 1
    matched to image 0; RANSAC and errors are not symmetric) and method."""
    sources = {k: FeatureSource(v) for k, v in methods.items()}
    records = []
    for pair in pairs:
        cases = [(pair, "0->1")]
        if both_directions:
            cases.append((pair.reverse(), "1->0"))
        for case, direction in cases:
            for method, src in sources.items():
                for im in (case.im0, case.im1):
                    if im not in src:
                        raise KeyError(f"{method}: no features for {im!r}")
                rec = evaluate_pair(case, src[case.im0], src[case.im1], conf)
                rec.update(method=method, direction=direction)
                records.append(rec)
    return records


def _fmt(v: float) -> str:
    return "fail" if not np.isfinite(v) else f"{v:.1f}"


def homography_markdown(records: list[dict], conf: HomographyConf = HomographyConf()) -> str:
    """Summary per method (cases solved, pairs solved in at least one direction, median
    GT-consistent matches) and a per-case table."""
    methods = list(dict.fromkeys(r["method"] for r in records))
    lines = [
        f"| method | cases | solved (visible err < {conf.success_px:g} px) | pairs solved "
        "(either direction) | median GT-consistent | median corner err (px) | "
        "median visible err (px) |",
        "|---|---|---|---|---|---|---|",
    ]
    for m in methods:
        rs = [r for r in records if r["method"] == m]
        pairs = {r["pair"] for r in rs}
        solved_pairs = {r["pair"] for r in rs if r["success"]}
        lines.append(
            f"| {m} | {len(rs)} | {sum(r['success'] for r in rs)} | "
            f"{len(solved_pairs)} of {len(pairs)} | {np.median([r['num_gt'] for r in rs]):.0f} | "
            f"{_fmt(np.median([r['corner_err'] for r in rs]))} | "
            f"{_fmt(np.median([r['visible_err'] for r in rs]))} |"
        )
    lines += [
        "",
        "| pair | direction | "
        + " | ".join(f"{m} GT-consistent / inliers / visible err" for m in methods)
        + " |",
        "|---|---|" + "---|" * len(methods),
    ]
    keys = list(dict.fromkeys((r["pair"], r["direction"]) for r in records))
    by = {(r["pair"], r["direction"], r["method"]): r for r in records}
    for p, d in keys:
        cells = []
        for m in methods:
            r = by.get((p, d, m))
            cells.append(
                "-"
                if r is None
                else f"{r['num_gt']} / {r['num_inliers']} / {_fmt(r['visible_err'])}"
                + (" **ok**" if r["success"] else "")
            )
        lines.append(f"| {p} | {d} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def homography_group_markdown(
    records: list[dict], groups: Mapping[str, str], conf: HomographyConf = HomographyConf()
) -> str:
    """Summary per group of pairs and method: ``groups`` maps a pair name to its group (e.g.
    a viewpoint band; pairs without one are "-"). Pairs solved in at least one direction,
    cases (pair and direction) solved, median and mean GT-consistent matches per case."""
    methods = list(dict.fromkeys(r["method"] for r in records))
    names = list(dict.fromkeys(groups.get(r["pair"], "-") for r in records))
    lines = [
        f"| group | method | pairs solved (visible err < {conf.success_px:g} px, either "
        "direction) | cases solved | GT-consistent per case: median / mean |",
        "|---|---|---|---|---|",
    ]
    for g in names:
        for m in methods:
            rs = [r for r in records if r["method"] == m and groups.get(r["pair"], "-") == g]
            pairs = {r["pair"] for r in rs}
            solved = {r["pair"] for r in rs if r["success"]}
            gt = [r["num_gt"] for r in rs]
            lines.append(
                f"| {g} | {m} | {len(solved)} of {len(pairs)} | "
                f"{sum(r['success'] for r in rs)} of {len(rs)} | "
                f"{np.median(gt):.0f} / {np.mean(gt):.1f} |"
            )
    return "\n".join(lines) + "\n"
