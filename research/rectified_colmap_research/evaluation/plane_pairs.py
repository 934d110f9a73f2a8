"""Planar image pairs with known homographies from a reconstruction (extreme viewpoints).

A plane fitted to a model's 3D points (rectified_colmap_research.training.real.fit_planes) and the
poses and intrinsics of two registered images give the homography the plane induces between
them; the observations of the plane's points validate it, and their image-0 positions give
the region where it holds. scripts/build_plane_pairs.py writes such pairs in the pair-file
format of :mod:`rectified_colmap.eval.homography` (docs/evaluation.md, "Extreme plane pairs
from real-pool").

Conventions: cam_from_world maps a world point X to X_c = R X + t; a plane is (4,) (n, d)
with n . X + d = 0 (|n| = 1); intrinsics K (3, 3) and pixels in COLMAP's convention (the
centre of the top-left pixel at (0.5, 0.5)); cameras are pinhole (undistort first); angles
in degrees; (N, 2) / (N, 3) arrays of points.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from rectified_colmap.eval.homography import apply_homography, points_in_region
from rectified_colmap.eval.wide_pairs import viewing_angles_deg

BANDS = {"strong": (30.0, 50.0), "extreme": (50.0, 85.0)}
"""Viewpoint-change bands (degrees, [low, high)) of the pairs kept."""


# -- geometry --------------------------------------------------------------------------------
def plane_in_camera(plane: np.ndarray, R: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, float]:
    """A world plane (n, d) in the frame of the camera (R, t) -> (n_c (3,), d_c) with
    n_c . X_c + d_c = 0."""
    n = R @ np.asarray(plane[:3], np.float64)
    return n, float(plane[3] - n @ np.asarray(t, np.float64))


def plane_homography(
    K0: np.ndarray,
    K1: np.ndarray,
    R0: np.ndarray,
    t0: np.ndarray,
    R1: np.ndarray,
    t1: np.ndarray,
    plane: np.ndarray,
) -> np.ndarray:
    """(3, 3) homography the world ``plane`` induces from image 0 to image 1 (pixels of K0,
    K1): H = K1 (R_rel - t_rel n0^T / d0) K0^-1, with R_rel = R1 R0^T, t_rel = t1 - R_rel t0
    (camera 0 -> camera 1) and (n0, d0) the plane in camera 0 (n0 . X0 + d0 = 0, so
    -n0^T X0 / d0 = 1 on it). Scale: as it comes (w > 0 for plane points in front of both
    cameras when they are on the same side of it)."""
    R_rel = R1 @ R0.T
    t_rel = np.asarray(t1, np.float64) - R_rel @ np.asarray(t0, np.float64)
    n0, d0 = plane_in_camera(plane, R0, t0)
    return K1 @ (R_rel - np.outer(t_rel, n0) / d0) @ np.linalg.inv(K0)


def viewpoint_change_deg(center0: np.ndarray, center1: np.ndarray, point: np.ndarray) -> float:
    """Angle between the viewing directions of the two camera centres (3,) to ``point``
    (3,), e.g. the centroid of a plane's observed points: 0 from the same direction."""
    return float(viewing_angles_deg(center0, center1, np.reshape(point, (1, 3)))[0])


def tilt_deg(center: np.ndarray, point: np.ndarray, normal: np.ndarray) -> float:
    """Angle between the plane normal (3,) and the ray from ``point`` on it to the camera
    ``center``: 0 seen frontally, 90 grazing."""
    v = np.asarray(center, np.float64) - np.asarray(point, np.float64)
    c = abs(float(v @ normal)) / (np.linalg.norm(v) * np.linalg.norm(normal))
    return float(np.degrees(np.arccos(min(c, 1.0))))


def transfer_errors(H: np.ndarray, x0: np.ndarray, x1: np.ndarray) -> np.ndarray:
    """(N,) distance between H x0 and x1 (pixels of image 1); inf where x0 maps behind."""
    d = np.linalg.norm(apply_homography(H, x0) - np.asarray(x1, np.float64).reshape(-1, 2), axis=1)
    return np.where(np.isfinite(d), d, np.inf)


def homography_jacobian(H: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """(N, 2, 2) Jacobian of the map x -> H x at the (N, 2) points: the local affine map
    between the images there (NaN where a point maps to w <= 0)."""
    p = np.c_[np.asarray(xy, np.float64).reshape(-1, 2), np.ones(len(xy))] @ H.T
    w = np.where(p[:, 2] > 1e-12, p[:, 2], np.nan)[:, None, None]
    # d(p_i / w) / dx_j = (H_ij w - p_i H_2j) / w^2
    return (H[None, :2, :2] * w - p[:, :2, None] * H[None, 2:3, :2]) / w**2


def transition_tilt(H: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """(N,) anisotropy of the local affine map (ratio of its singular values, >= 1) at the
    (N, 2) image-0 points: ASIFT's transition tilt, what a local feature must absorb. It is
    ~1 when both views are tilted alike (e.g. 35 degrees on either side of the normal,
    70 degrees apart), 1 / cos(theta) for a frontal view and one at theta; evd-dev's pairs
    have 3.6-46 (median over their visible grids)."""
    s = np.linalg.svd(homography_jacobian(H, xy), compute_uv=False)
    return s[:, 0] / s[:, 1]


# -- regions --------------------------------------------------------------------------------
def link_components(xy: np.ndarray, link: float) -> np.ndarray:
    """(N,) int component of each of the (N, 2) points, where points closer than ``link``
    are in one component (single linkage); components numbered 0.. by first point."""
    xy = np.asarray(xy, np.float64).reshape(-1, 2)
    if len(xy) == 0:
        return np.zeros(0, int)
    adj = np.linalg.norm(xy[:, None] - xy[None], axis=-1) < link
    lab = np.arange(len(xy))
    while True:  # each point takes the smallest label among its neighbours, until stable
        new = np.where(adj, lab[None, :], len(xy)).min(1)
        if (new == lab).all():
            break
        lab = new
    return np.unique(lab, return_inverse=True)[1].ravel()


def dilated_hull(xy: np.ndarray, radius: float, sides: int = 16) -> np.ndarray:
    """(K, 2) convex polygon (vertices in order): the convex hull of the (N, 2) points, each
    replaced by a ``sides``-gon of circumradius ``radius`` (the hull grown by ~radius)."""
    a = 2 * np.pi * np.arange(sides) / sides
    ring = radius * np.stack([np.cos(a), np.sin(a)], 1)
    pts = (np.asarray(xy, np.float64).reshape(-1, 1, 2) + ring).reshape(-1, 2)
    return cv2.convexHull(pts.astype(np.float32))[:, 0].astype(np.float64)


def plane_region(
    x_plane: np.ndarray,
    x_all: np.ndarray,
    err_all: np.ndarray,
    link: float,
    radius: float,
    min_cluster: int = 6,
    min_purity: float = 0.8,
    max_err: float = 3.0,
) -> list[np.ndarray]:
    """Where a plane's homography holds in an image -> list of polygons (maybe empty).

    ``x_plane`` (M, 2): the image positions of the plane's points seen in both images;
    they are split into components (:func:`link_components`, ``link``), and each component of
    at least ``min_cluster`` points gives its :func:`dilated_hull` (``radius``). A polygon is
    kept when at least ``min_purity`` of ALL points seen in both images that fall in it
    (``x_all`` (N, 2), with transfer errors ``err_all`` (N,) under the homography) transfer
    within ``max_err``: occluders and other surfaces inside a hull reject it."""
    comp = link_components(x_plane, link)
    out = []
    for c in range(comp.max() + 1 if len(comp) else 0):
        pts = np.asarray(x_plane)[comp == c]
        if len(pts) < min_cluster:
            continue
        poly = dilated_hull(pts, radius)
        inside = points_in_region(x_all, [poly])
        if inside.any() and np.mean(np.asarray(err_all)[inside] < max_err) >= min_purity:
            out.append(poly)
    return out


def region_fraction(region: list[np.ndarray], size: tuple[int, int], step: float = 10.0) -> float:
    """Fraction of an image (W, H) = ``size`` inside the region (on a ``step`` px grid)."""
    W, H = size
    g = np.stack(np.meshgrid(np.arange(step / 2, W, step), np.arange(step / 2, H, step)), -1)
    return float(points_in_region(g.reshape(-1, 2), region).mean()) if region else 0.0


# -- candidates from a reconstruction and the selection --------------------------------------
@dataclass
class ViewData:
    """One registered pinhole image of a model."""

    name: str
    K: np.ndarray
    """(3, 3) COLMAP convention."""
    R: np.ndarray
    t: np.ndarray
    size: tuple[int, int]
    """(W, H)."""
    points: np.ndarray
    """(n,) sorted indices of the model points it observes."""
    xy: np.ndarray
    """(n, 2) their observations (COLMAP pixels)."""

    @property
    def center(self) -> np.ndarray:
        return -self.R.T @ self.t


@dataclass
class PlanePair:
    """A plane seen by two images, its homography and how it was validated."""

    name0: str
    name1: str
    plane: int
    """Index into the model's planes."""
    H: np.ndarray
    """(3, 3) image 0 -> image 1, COLMAP pixel frames."""
    size0: tuple[int, int]
    size1: tuple[int, int]
    region0: list[np.ndarray]
    """Polygons in image 0 (COLMAP pixels) where H holds."""
    angle_deg: float
    """Viewpoint change on the plane (:func:`viewpoint_change_deg` at the centroid)."""
    tilt0_deg: float
    tilt1_deg: float
    num_points: int
    """Plane points seen in both images with their image-0 position in the region."""
    median_err: float
    """Median transfer error (px, image 1) of the plane's points seen in both images."""
    p90_err: float
    frac0: float
    """Fraction of image 0 / image 1 covered by the region."""
    frac1: float
    tilt_ratio: float
    """Median :func:`transition_tilt` at the plane's image-0 points in the region."""
    K0: np.ndarray = field(repr=False)
    K1: np.ndarray = field(repr=False)
    """(3, 3) intrinsics of the two images (COLMAP convention)."""


def pair_candidates(
    v0: ViewData,
    v1: ViewData,
    xyz: np.ndarray,
    planes: np.ndarray,
    labels: np.ndarray,
    min_points: int = 30,
    angle_range: tuple[float, float] = (30.0, 85.0),
    max_median_err: float = 2.0,
    min_frac: float = 0.03,
    link_frac: float = 0.08,
    radius_frac: float = 0.015,
) -> list[PlanePair]:
    """Every plane of the model that two views both see enough of, as a PlanePair.

    ``xyz`` (P, 3) model points, ``planes`` (Q, 4), ``labels`` (P,) plane of each point (-1:
    none). A plane is kept when at least ``min_points`` of its points are seen in both
    views, the viewpoint change at their centroid is in ``angle_range``, the median
    transfer error of their observations under the plane's homography is at most
    ``max_median_err`` px, and the region (:func:`plane_region`, link / radius as fractions
    of image 0's longer side) holds at least ``min_points`` of them and covers at least
    ``min_frac`` of each image."""
    common, i0, i1 = np.intersect1d(v0.points, v1.points, return_indices=True)
    x0_all, x1_all = v0.xy[i0], v1.xy[i1]
    lab = np.asarray(labels)[common]
    out = []
    side = max(v0.size)
    for p in np.unique(lab[lab >= 0]):
        on = lab == p
        if on.sum() < min_points:
            continue
        centroid = xyz[common[on]].mean(0)
        angle = viewpoint_change_deg(v0.center, v1.center, centroid)
        if not angle_range[0] <= angle < angle_range[1]:
            continue
        H = plane_homography(v0.K, v1.K, v0.R, v0.t, v1.R, v1.t, planes[p])
        w = (H @ np.append(x0_all[on].mean(0), 1.0))[2]
        if not np.isfinite(w) or w <= 0:  # the cameras are on opposite sides of the plane
            continue
        H = H / w
        err_all = transfer_errors(H, x0_all, x1_all)
        err = err_all[on]
        if np.median(err) > max_median_err:
            continue
        region = plane_region(x0_all[on], x0_all, err_all, link_frac * side, radius_frac * side)
        if not region:
            continue
        in_region = points_in_region(x0_all[on], region)
        num = int(in_region.sum())
        region1 = [apply_homography(H, q) for q in region]
        f0, f1 = region_fraction(region, v0.size), region_fraction(region1, v1.size)
        if num < min_points or min(f0, f1) < min_frac:
            continue
        out.append(
            PlanePair(
                v0.name,
                v1.name,
                int(p),
                H,
                v0.size,
                v1.size,
                region,
                angle,
                tilt_deg(v0.center, centroid, planes[p][:3]),
                tilt_deg(v1.center, centroid, planes[p][:3]),
                num,
                float(np.median(err)),
                float(np.percentile(err, 90)),
                f0,
                f1,
                float(np.median(transition_tilt(H, x0_all[on][in_region]))) if num else np.nan,
                v0.K,
                v1.K,
            )
        )
    return out


def band_of(angle_deg: float, bands: dict = BANDS) -> str | None:
    """Name of the band [low, high) holding the angle, or None."""
    for name, (lo, hi) in bands.items():
        if lo <= angle_deg < hi:
            return name
    return None


def best_plane_per_pair(candidates: list[PlanePair]) -> list[PlanePair]:
    """Per image pair, the candidate plane with the most points in its region (ties: the
    first); in the order of first appearance."""
    best: dict[tuple[str, str], PlanePair] = {}
    for c in candidates:
        key = (c.name0, c.name1)
        if key not in best or c.num_points > best[key].num_points:
            best[key] = c
    return list(best.values())


def select_pairs(
    candidates: list[PlanePair], max_per_image: int = 4, max_per_plane: int = 6
) -> list[PlanePair]:
    """Greedily by points in the region (most first; ties by names), the pairs that keep
    every image under ``max_per_image`` pairs and every plane under ``max_per_plane``. Run it
    per set (plane indices are per model) and band, after :func:`best_plane_per_pair`."""
    order = sorted(candidates, key=lambda c: (-c.num_points, c.name0, c.name1, c.plane))
    per_image: dict[str, int] = {}
    per_plane: dict[int, int] = {}
    out = []
    for c in order:
        if per_plane.get(c.plane, 0) >= max_per_plane:
            continue
        if max(per_image.get(c.name0, 0), per_image.get(c.name1, 0)) >= max_per_image:
            continue
        per_plane[c.plane] = per_plane.get(c.plane, 0) + 1
        for n in (c.name0, c.name1):
            per_image[n] = per_image.get(n, 0) + 1
        out.append(c)
    return out


def is_pinhole(camera, tol: float = 1e-6) -> bool:
    """Whether a pycolmap.Camera projects as its calibration matrix does (no distortion):
    tested on rays to a 5 x 5 grid over the image."""
    K = camera.calibration_matrix()
    g = np.stack(np.meshgrid(np.linspace(0, camera.width, 5), np.linspace(0, camera.height, 5)), -1)
    rays = np.c_[g.reshape(-1, 2), np.ones(25)] @ np.linalg.inv(K).T
    return bool(np.abs(camera.img_from_cam(rays) - g.reshape(-1, 2)).max() < tol * max(K[0, 0], 1))


def views_of_model(rec) -> tuple[list[ViewData], np.ndarray]:
    """(views sorted by name, points (P, 3)) of a pycolmap.Reconstruction whose cameras have
    no distortion (:func:`is_pinhole`: undistort first); ViewData.points index the rows."""
    bad = sorted(c.model.name for c in rec.cameras.values() if not is_pinhole(c))
    if bad:
        raise ValueError(f"cameras must be pinhole (undistort first), got {bad}")
    ids = np.array(sorted(rec.points3D), np.int64)
    xyz = np.array([rec.points3D[int(i)].xyz for i in ids], np.float64).reshape(-1, 3)
    index = {int(i): k for k, i in enumerate(ids)}
    views = []
    for im in sorted((im for im in rec.images.values() if im.has_pose), key=lambda im: im.name):
        cam = rec.cameras[im.camera_id]
        obs = [(index[p.point3D_id], p.xy) for p in im.points2D if p.has_point3D()]
        k = np.array([o[0] for o in obs], np.int64)
        xy = np.array([o[1] for o in obs], np.float64).reshape(-1, 2)
        order = np.argsort(k)
        pose = im.cam_from_world()
        views.append(
            ViewData(
                im.name,
                cam.calibration_matrix(),
                pose.rotation.matrix(),
                np.asarray(pose.translation, np.float64),
                (cam.width, cam.height),
                k[order],
                xy[order],
            )
        )
    return views, xyz
