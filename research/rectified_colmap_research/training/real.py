"""Real-photo training samples without a depth sensor (numpy, OpenCV, pycolmap; no torch).

A real sample has the pool format of :mod:`rectified_colmap_research.training.data` plus a sky map:

- ``image`` (h, w, 3) uint8 RGB: the photo, resized to cover (w, h) and centre-cropped;
- ``K`` (3, 3): its pinhole intrinsics after the crop (COLMAP pixel convention);
- ``depth`` (h, w) float32: SPARSE z-depth, the z of the 3D points of a COLMAP model seen
  in the image (nearest point per pixel), 0 elsewhere (images without a model: all 0);
- ``normals`` (h, w, 3) float32: camera-frame unit normals toward the camera, 0 elsewhere,
  from two sources: planes fitted to the model's 3D points (:func:`fit_planes`, where the
  image's points of one plane are dense, :func:`plane_normal_map`), and where the
  line-derived Manhattan frame is confident (its trust test,
  :func:`rectified_colmap_research.line_planes.manhattan_from_image`) and segments of two of its
  families are dense (:func:`rectified_colmap_research.line_planes.line_support_patches`: a plane
  containing lines of two vanishing points has the third axis as normal); plane fits win
  where both exist, and a pixel where they disagree gets neither
  (:func:`merge_normal_labels`);
- ``sky`` (h, w) uint8: 1 sky, 0 not sky, 255 unknown (:mod:`rectified_colmap_research.training.sky`
  pseudo-labels; where they say sky, line-support normals are dropped; pixels with a 3D
  point or a remaining normal are not sky).

Depth is up to scale per image (a Euclidean SfM model), so only scale-invariant losses use
it. Stored compactly by :func:`save_real_sample` (JPEG image, sparse depth as a point list,
normals as a label map and its 6-row table) so a pool of a few hundred photos is a few MB.
"""

from __future__ import annotations

import io
import json
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pycolmap

from rectified_colmap import camera as cam_utils
from rectified_colmap.config import VpConf
from rectified_colmap.geometry import rays_from_K
from rectified_colmap.conventions import (
    from_opencv_points,
    pixel_centers,
    to_opencv_homography,
    to_opencv_points,
)
from rectified_colmap_research.line_planes import line_support_patches, manhattan_from_image
from .sky import NOT_SKY, SKY, UNKNOWN


@dataclass
class RealItem:
    """One real photo to turn into a training sample."""

    path: Path
    camera: pycolmap.Camera | None
    """Its camera (focal known); None: no orientation labels (sky only)."""
    points: np.ndarray | None = None
    """(N, 3) float world points seen in the image (from a COLMAP model), or None."""
    cam_from_world: pycolmap.Rigid3d | None = None
    horizon: np.ndarray | None = None
    """(3,) line a x + b y + c = 0 in stored-image pixels (0-based), if known."""
    planes: np.ndarray | None = None
    """(P, 4) world planes (n, d), n . X + d = 0, |n| = 1, fitted to the model's points."""
    point_planes: np.ndarray | None = None
    """(N,) int index into ``planes`` of each of ``points``, -1 on none."""


def cover_crop_affine(width: int, height: int, out_w: int, out_h: int) -> np.ndarray:
    """(2, 3) affine taking COLMAP pixel coordinates of a (width, height) image to those of
    an (out_w, out_h) image that the source covers after uniform scaling and centre crop."""
    s = max(out_w / width, out_h / height)
    return np.array(
        [[s, 0.0, (out_w - s * width) / 2], [0.0, s, (out_h - s * height) / 2]], np.float64
    )


def source_coords(
    camera: pycolmap.Camera | None, a: np.ndarray, out_w: int, out_h: int
) -> tuple[np.ndarray, np.ndarray]:
    """Where each output pixel centre comes from -> (xy (out_h, out_w, 2) COLMAP coordinates
    in the source image, K (3, 3) of the output).

    With a camera the output is an undistorted pinhole view: K is the affine ``a`` applied to
    the camera's focal lengths and principal point, and the source position of a pixel is
    the camera's projection of its ray (distortion included). Without one, the output is
    the affine crop (K all NaN)."""
    A = np.vstack([a, [0.0, 0.0, 1.0]])
    uv1 = np.concatenate([pixel_centers(out_w, out_h), np.ones((out_h, out_w, 1))], -1)
    if camera is None:
        return uv1 @ np.linalg.inv(A)[:2].T, np.full((3, 3), np.nan)
    fx, fy = camera.focal_length_x, camera.focal_length_y
    K = A @ np.array(
        [[fx, 0, camera.principal_point_x], [0, fy, camera.principal_point_y], [0, 0, 1.0]]
    )
    rays = uv1 @ np.linalg.inv(K).T
    xy = camera.img_from_cam(rays.reshape(-1, 3)).reshape(out_h, out_w, 2)
    return xy, K


def resample(image: np.ndarray, xy: np.ndarray, scale: float) -> np.ndarray:
    """Sample ``image`` at COLMAP coordinates ``xy`` (h, w, 2); ``scale`` (< 1: a shrink) is
    the approximate output / source resolution: the source is area-shrunk first, then
    sampled bilinearly (no aliasing)."""
    H, W = image.shape[:2]
    if scale < 1:
        w2, h2 = max(1, round(W * scale)), max(1, round(H * scale))
        image = cv2.resize(image, (w2, h2), interpolation=cv2.INTER_AREA)
        xy = xy * np.array([w2 / W, h2 / H])
    m = to_opencv_points(xy).astype(np.float32)
    return cv2.remap(image, m[..., 0], m[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


def sparse_depth_map(
    points: np.ndarray, cam_from_world: pycolmap.Rigid3d, K: np.ndarray, out_w: int, out_h: int
) -> np.ndarray:
    """(out_h, out_w) float32 z-depth of the world ``points`` (N, 3) projected by the pinhole
    ``K`` (COLMAP convention); the nearest point per pixel, 0 elsewhere."""
    depth = np.zeros((out_h, out_w), np.float32)
    if points is None or len(points) == 0:
        return depth
    X = np.asarray(points, np.float64) @ cam_from_world.rotation.matrix().T
    X = X + cam_from_world.translation
    X = X[X[:, 2] > 1e-6]
    uv = X @ K.T
    uv = uv[:, :2] / uv[:, 2:]
    col, row = np.floor(uv[:, 0]).astype(int), np.floor(uv[:, 1]).astype(int)
    ok = (col >= 0) & (col < out_w) & (row >= 0) & (row < out_h)
    z, col, row = X[ok, 2], col[ok], row[ok]
    order = np.argsort(-z)  # far first: the nearest point is written last and wins
    depth[row[order], col[order]] = z[order]
    return depth


def line_normal_map(
    gray: np.ndarray,
    camera: pycolmap.Camera,
    xy: np.ndarray,
    conf: VpConf = VpConf(),
    work_max_side: int = 640,
) -> tuple[np.ndarray, np.ndarray | None]:
    """Orientation labels from lines -> (normals (h, w, 3) float32 at the output pixels whose
    source positions are ``xy`` (h, w, 2), 0 where none; the confident frame (3, 3) or None).

    The Manhattan frame of the full image (only when its trust test passes) and its
    line-support planes on a work grid of the image (max side ``work_max_side``), read at
    the nearest work-grid cell."""
    normals = np.zeros(xy.shape[:2] + (3,), np.float32)
    res = manhattan_from_image(gray, camera, conf, rng=np.random.default_rng(0))
    if res.directions is None:
        return normals, None
    H, W = gray.shape
    s = work_max_side / max(H, W)
    gh, gw = max(1, round(H * s)), max(1, round(W * s))
    patches, labels = line_support_patches(res, camera, (gh, gw))
    if not patches:
        return normals, res.directions
    table = np.zeros((7, 3), np.float32)  # label 2k + s -> normal facing the camera; -1 -> 0
    for k in range(3):
        table[2 * k] = res.directions[k]
        table[2 * k + 1] = -res.directions[k]
    ci = np.clip(np.floor(xy[..., 0] * gw / W).astype(int), 0, gw - 1)
    ri = np.clip(np.floor(xy[..., 1] * gh / H).astype(int), 0, gh - 1)
    lab = labels[ri, ci].astype(int)
    return table[np.where(lab >= 0, lab, 6)], res.directions


# -- normal labels from planes fitted to a model's 3D points --------------------------------
def fit_planes(
    points: np.ndarray,
    threshold: float,
    min_inliers: int = 40,
    max_planes: int = 12,
    hypotheses: int = 512,
    rng: np.random.Generator | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Sequential RANSAC planes of the world ``points`` (N, 3) -> (planes (P, 4) rows
    (n, d) with n . X + d = 0 and |n| = 1, labels (N,) int plane index, -1 on none).

    Each round scores ``hypotheses`` random point triples at once, refits the best by least
    squares on its inliers (distance <= ``threshold``, twice) and removes them; it stops
    when the best plane has fewer than ``min_inliers`` points or after ``max_planes``."""
    rng = np.random.default_rng(0) if rng is None else rng
    X = np.asarray(points, np.float64).reshape(-1, 3)
    labels = np.full(len(X), -1, int)
    planes = []
    free = np.arange(len(X))
    while len(planes) < max_planes and len(free) >= max(3, min_inliers):
        P = X[free]
        tri = P[rng.integers(0, len(P), (hypotheses, 3))]
        n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        norm = np.linalg.norm(n, axis=1)
        ok = norm > 1e-12
        if not ok.any():
            break
        n = n[ok] / norm[ok, None]
        d = -(n * tri[ok, 0]).sum(1)
        counts = (np.abs(P @ n.T + d) <= threshold).sum(0)
        best = int(np.argmax(counts))
        plane = np.append(n[best], d[best])
        for _ in range(2):  # least-squares refit on the inliers
            inl = np.abs(P @ plane[:3] + plane[3]) <= threshold
            if inl.sum() < 3:
                break
            c = P[inl].mean(0)
            normal = np.linalg.svd(P[inl] - c, full_matrices=False)[2][-1]
            plane = np.append(normal, -normal @ c)
        inl = np.abs(P @ plane[:3] + plane[3]) <= threshold
        if inl.sum() < min_inliers:
            break
        labels[free[inl]] = len(planes)
        planes.append(plane)
        free = free[~inl]
    return np.array(planes, np.float64).reshape(-1, 4), labels


def plane_normal_map(
    points: np.ndarray,
    point_planes: np.ndarray,
    planes: np.ndarray,
    cam_from_world: pycolmap.Rigid3d,
    K: np.ndarray,
    out_w: int,
    out_h: int,
    **kwargs,
) -> np.ndarray:
    """Normal labels from fitted planes on a pinhole view -> (out_h, out_w, 3) float32
    camera-frame unit normals toward the camera, 0 where none.

    ``points`` (N, 3) are the world points the image observes, ``point_planes`` (N,) their
    plane (-1: none), ``planes`` (P, 4) world (n, d); they are projected with ``K`` (COLMAP
    convention). ``kwargs``: the label rule of :func:`plane_normals_on_grid`."""
    X = _to_camera(points, cam_from_world)
    uv = X @ K.T
    uv = uv[:, :2] / np.where(X[:, 2:] > 1e-6, uv[:, 2:], np.nan)
    rays = rays_from_K(K, out_w, out_h)
    return plane_normals_on_grid(
        uv, point_planes, _planes_facing(planes, cam_from_world), rays, **kwargs
    )


def plane_normal_map_camera(
    points: np.ndarray,
    point_planes: np.ndarray,
    planes: np.ndarray,
    cam_from_world: pycolmap.Rigid3d,
    camera: pycolmap.Camera,
    width: int,
    height: int,
    **kwargs,
) -> np.ndarray:
    """:func:`plane_normal_map` on a ``width`` x ``height`` grid covering the whole image of
    any COLMAP ``camera`` (distortion included): the grid of ``normals.depth_to_normals``,
    so that a depth network's normals can be scored against the plane labels."""
    X = _to_camera(points, cam_from_world)
    front = X[:, 2] > 1e-6
    uv = np.full((len(X), 2), np.nan)
    if front.any():
        uv[front] = camera.img_from_cam(X[front]) * np.array(
            [width / camera.width, height / camera.height]
        )
    rays = cam_utils.grid_rays(camera, width, height)
    return plane_normals_on_grid(
        uv, point_planes, _planes_facing(planes, cam_from_world), rays, **kwargs
    )


def _to_camera(points: np.ndarray, cam_from_world: pycolmap.Rigid3d) -> np.ndarray:
    X = np.asarray(points, np.float64).reshape(-1, 3)
    return X @ cam_from_world.rotation.matrix().T + cam_from_world.translation


def _planes_facing(planes: np.ndarray, cam_from_world: pycolmap.Rigid3d) -> np.ndarray:
    """(P, 3) camera-frame unit normals of world planes (n, d), oriented toward the camera
    centre C: n . C + d > 0."""
    R = cam_from_world.rotation.matrix()
    C = -R.T @ np.asarray(cam_from_world.translation, np.float64)
    planes = np.asarray(planes, np.float64).reshape(-1, 4)
    sign = np.where(planes[:, :3] @ C + planes[:, 3] >= 0, 1.0, -1.0)
    return (planes[:, :3] @ R.T) * sign[:, None]


def plane_normals_on_grid(
    uv: np.ndarray,
    point_planes: np.ndarray,
    plane_normals: np.ndarray,
    rays: np.ndarray,
    radius: int = 10,
    min_points: int = 3,
    purity: float = 0.9,
    max_incidence_deg: float = 80.0,
) -> np.ndarray:
    """The label rule: ``uv`` (N, 2) COLMAP coordinates on the (h, w) grid of ``rays``
    (h, w, 3) of the observed points (NaN: not seen), ``point_planes`` (N,) their plane
    (-1: none), ``plane_normals`` (P, 3) camera-frame normals facing the camera. A pixel
    gets plane p when the (2 radius + 1)^2 window around it holds at least ``min_points``
    points of p and they are at least ``purity`` of all points there (occluders, clutter and
    plane boundaries fail this), and its ray meets the plane at most ``max_incidence_deg``
    from the normal (grazing views are left out). -> (h, w, 3) float32, 0 where none."""
    h, w = rays.shape[:2]
    normals = np.zeros((h, w, 3), np.float32)
    ok = np.isfinite(uv).all(1)
    col = np.floor(np.where(ok, uv[:, 0], -1)).astype(int)
    row = np.floor(np.where(ok, uv[:, 1], -1)).astype(int)
    ok &= (col >= 0) & (col < w) & (row >= 0) & (row < h)
    lab = np.asarray(point_planes)[ok]
    flat = row[ok] * w + col[ok]
    present = np.unique(lab[lab >= 0])
    if len(present) == 0:
        return normals
    k = 2 * radius + 1

    def window_count(sel):
        c = np.bincount(flat[sel], minlength=h * w).reshape(h, w)
        return cv2.boxFilter(c.astype(np.float32), -1, (k, k), normalize=False)

    total = window_count(np.ones(len(flat), bool))
    counts = np.stack([window_count(lab == p) for p in present])
    best = np.argmax(counts, 0)
    cbest = np.take_along_axis(counts, best[None], 0)[0]
    use = (cbest >= min_points) & (cbest >= purity * total - 1e-6)
    n_pix = np.asarray(plane_normals, np.float64)[present][best]
    unit = rays / np.linalg.norm(rays, axis=-1, keepdims=True)
    use &= -(n_pix * unit).sum(-1) >= np.cos(np.radians(max_incidence_deg))
    normals[use] = n_pix[use]
    return normals


def merge_normal_labels(
    planes: np.ndarray, lines: np.ndarray, max_disagreement_deg: float = 20.0
) -> np.ndarray:
    """Plane-fit labels (metric, from the points) where they exist, line-support labels
    elsewhere; pixels where both exist and disagree by more than ``max_disagreement_deg``
    get none (one of them is wrong). Both (h, w, 3), 0 = no label."""
    hp = np.abs(planes).sum(-1) > 0
    hl = np.abs(lines).sum(-1) > 0
    out = np.where(hp[..., None], planes, lines).astype(np.float32)
    cos = (planes * lines).sum(-1)
    out[hp & hl & (cos < np.cos(np.radians(max_disagreement_deg)))] = 0
    return out


def map_line(line: np.ndarray, a: np.ndarray) -> np.ndarray:
    """A line (a, b, c), a x + b y + c = 0 in 0-based source pixels, through the COLMAP
    affine ``a`` -> the same line in 0-based output pixels (0-based = COLMAP - 0.5)."""
    M = to_opencv_homography(np.vstack([a, [0.0, 0.0, 1.0]]))  # 0-based -> 0-based
    return np.linalg.inv(M).T @ np.asarray(line, np.float64)


def make_real_sample(
    item: RealItem,
    out_w: int = 320,
    out_h: int = 240,
    conf: VpConf = VpConf(),
    sky_fn=None,
) -> dict:
    """One real training sample (module docstring) from a photo and what is known of it.

    ``sky_fn(rgb (h, w, 3) uint8, horizon (3,) or None) -> (h, w) uint8`` gives the sky
    pseudo-labels on the output image (default: none, all unknown). A horizon is only used
    for cameras without distortion (it is mapped by the crop affine)."""
    bgr = cv2.imread(str(item.path), cv2.IMREAD_COLOR)
    if bgr is None:
        raise ValueError(f"{item.path}: cannot read image")
    H, W = bgr.shape[:2]
    cam = item.camera
    if cam is not None and (cam.width, cam.height) != (W, H):
        raise ValueError(f"{item.path}: camera is {cam.width}x{cam.height}, image {W}x{H}")
    a = cover_crop_affine(W, H, out_w, out_h)
    xy, K = source_coords(cam, a, out_w, out_h)
    rgb = np.ascontiguousarray(resample(bgr, xy, a[0, 0])[..., ::-1])
    normals = np.zeros((out_h, out_w, 3), np.float32)
    depth = np.zeros((out_h, out_w), np.float32)
    frame = None
    if cam is not None:
        normals, frame = line_normal_map(cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY), cam, xy, conf)
        if item.points is not None:
            depth = sparse_depth_map(item.points, item.cam_from_world, K, out_w, out_h)
        if item.planes is not None and item.point_planes is not None:
            fitted = plane_normal_map(
                item.points, item.point_planes, item.planes, item.cam_from_world, K, out_w, out_h
            )
            normals = merge_normal_labels(fitted, normals)
    horizon = None if item.horizon is None else map_line(item.horizon, a)
    sky = np.full((out_h, out_w), UNKNOWN, np.uint8)
    if sky_fn is not None:
        sky = np.asarray(sky_fn(rgb, horizon), np.uint8)
    normals[sky == SKY] = 0  # the sky labels are high-precision; line support can bleed
    sky[(depth > 0) | (np.abs(normals).sum(-1) > 0)] = NOT_SKY
    return {
        "image": rgb,
        "K": K,
        "depth": depth,
        "normals": normals,
        "sky": sky,
        "frame": frame if frame is not None else np.full((3, 3), np.nan),
        "name": str(item.path),
    }


def save_real_sample(path: str | Path, s: dict) -> None:
    """Compact .npz: JPEG (q95) image, sparse depth as (row, col, z), normals as a label map
    (uint8, 255 = none) with its table, sky map; written atomically."""
    path = Path(path)
    n = s["normals"].reshape(-1, 3)
    has = np.abs(n).sum(1) > 0
    table, inv = np.unique(n[has], axis=0, return_inverse=True)
    if len(table) > 254:
        raise ValueError(f"{path}: {len(table)} distinct normals, not a label map")
    lab = np.full(len(n), 255, np.uint8)
    lab[has] = inv.ravel()
    r, c = np.nonzero(s["depth"] > 0)
    ok, jpg = cv2.imencode(".jpg", s["image"][..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, 95])
    if not ok:
        raise ValueError(f"{path}: JPEG encoding failed")
    buf = io.BytesIO()
    np.savez_compressed(
        buf,
        image_jpg=np.frombuffer(jpg.tobytes(), np.uint8),
        K=s["K"],
        points=np.stack([r, c, s["depth"][r, c]], 1).astype(np.float32),
        normal_labels=lab.reshape(s["depth"].shape),
        normal_table=table.astype(np.float32),
        sky=s["sky"],
        frame=s["frame"],
        meta=np.array(json.dumps({"name": s["name"], "shape": list(s["depth"].shape)})),
    )
    tmp = path.with_suffix(".tmp")
    tmp.write_bytes(buf.getvalue())
    tmp.replace(path)


def load_real_sample(path: str | Path) -> dict:
    """Inverse of :func:`save_real_sample` (dense maps, as :func:`make_real_sample` gives)."""
    try:
        with np.load(path) as z:
            meta = json.loads(str(z["meta"]))
            h, w = meta["shape"]
            img = cv2.imdecode(z["image_jpg"], cv2.IMREAD_COLOR)[..., ::-1]
            depth = np.zeros((h, w), np.float32)
            p = z["points"]
            depth[p[:, 0].astype(int), p[:, 1].astype(int)] = p[:, 2]
            table = np.vstack([z["normal_table"].reshape(-1, 3), np.zeros((1, 3), np.float32)])
            lab = z["normal_labels"].astype(int)
            normals = table[np.where(lab == 255, len(table) - 1, lab)]
            return {
                "image": np.ascontiguousarray(img),
                "K": z["K"],
                "depth": depth,
                "normals": normals.astype(np.float32),
                "sky": z["sky"],
                "frame": z["frame"],
                "name": meta["name"],
            }
    except (OSError, KeyError, ValueError) as e:
        raise ValueError(f"{path}: not a real training sample ({e})") from None


# -- the real-pool sets --------------------------------------------------------------------
def focal_from_horizon_zenith(horizon: np.ndarray, zenith: np.ndarray, pp: np.ndarray) -> float:
    """Focal (px) from the horizon line (a, b, c) and the zenith vanishing point (x, y): the
    vertical direction at angle t from the optical axis has its vanishing point f tan t from
    the principal point and its vanishing line f / tan t from it, so f^2 = d_zenith d_horizon.
    Returns NaN when either distance is not finite or positive."""
    a, b, c = np.asarray(horizon, np.float64)
    d_h = abs(a * pp[0] + b * pp[1] + c) / np.hypot(a, b)
    d_z = float(np.hypot(*(np.asarray(zenith, np.float64) - pp)))
    f2 = d_h * d_z
    return float(np.sqrt(f2)) if np.isfinite(f2) and f2 > 0 else float("nan")


def camera_from_record(rec: dict, focal: float | None = None) -> pycolmap.Camera | None:
    """Camera of a real-pool ``cameras.json`` record (None when no focal is known)."""
    f = rec.get("focal_px") if focal is None else focal
    if f is None or not np.isfinite(f):
        return None
    w, h = rec["width"], rec["height"]
    if rec.get("cx") is None or rec.get("cy") is None:
        pp = np.array([w / 2, h / 2])
    else:  # cameras.json gives a calibrated principal point 0-based
        pp = from_opencv_points(np.array([rec["cx"], rec["cy"]], np.float64))
    return cam_utils.make_camera("SIMPLE_PINHOLE", [float(f), *pp], w, h)


PLANE_THRESHOLD = 0.01
"""Plane inlier distance as a fraction of the model's median point depth (SfM points of a
facade scatter ~0.2-0.5 % of their depth; 1 % keeps shallow reliefs on their wall)."""


def items_from_model(set_dir: Path) -> list[RealItem]:
    """Items of a real-pool set with a COLMAP model (``colmap_sparse/``): the model's
    camera, pose and the 3D points each image observes, the model's planes
    (:func:`fit_planes`, inlier distance :data:`PLANE_THRESHOLD` x the median depth of the
    observations) and each observed point's plane."""
    rec = pycolmap.Reconstruction(str(set_dir / "colmap_sparse"))
    ids = np.array(sorted(rec.points3D))
    xyz = np.array([rec.points3D[i].xyz for i in ids]).reshape(-1, 3)
    index = {int(i): k for k, i in enumerate(ids)}
    images = sorted(rec.images.values(), key=lambda im: im.name)
    seen = {
        im.image_id: np.array([index[p.point3D_id] for p in im.points2D if p.has_point3D()], int)
        for im in images
    }
    planes = labels = None
    if len(xyz):
        depths = np.concatenate(
            [(im.cam_from_world() * xyz[seen[im.image_id]])[:, 2] for im in images]
        )
        planes, labels = fit_planes(xyz, PLANE_THRESHOLD * float(np.median(depths)))
    items = []
    for im in images:
        k = seen[im.image_id]
        items.append(
            RealItem(
                set_dir / "images" / im.name,
                rec.cameras[im.camera_id],
                xyz[k],
                im.cam_from_world(),
                planes=planes,
                point_planes=None if labels is None else labels[k],
            )
        )
    return items


PERMISSIVE_SMALL_GROUPS = ("gluestick_", "lightglue_", "roma_", "dedode_", "metric3d_")
"""small-groups items whose repositories state MIT / Apache-2.0 / BSD (MANIFEST.md); the
ETH3D terrace pair (CC BY-NC-SA at its source) is left out."""


def real_pool_items(root: str | Path) -> list[RealItem]:
    """The real-pool photos that may train the shipped network, with what is known of them.

    - opensfm-lund, opensfm-berlin (BSD-2), sceaux-castle (terms unstated; named in the
      model card): COLMAP models -> camera, pose, 3D points;
    - yorkurban, yorkurban-indoor (research data, named in the model card): the ECCV08
      TRAIN split only (its test split is held out), calibrated cameras;
    - eurasian-cities (research data, named in the model card): EVEN indices only (odd
      ones are held out; the two near-duplicate pairs fall on one side), focal from the
      ground-truth horizon and zenith, horizon for the sky labels;
    - phototourism-samples (Apache-2.0), small-groups' permissive items: no focal -> sky
      labels only.
    Left out: sacre-coeur (the hloc evaluation images), british-museum, nle-tower,
    kitti-demo (non-commercial terms)."""
    root = Path(root)
    items: list[RealItem] = []
    for name in ("opensfm-lund", "opensfm-berlin", "sceaux-castle"):
        items += items_from_model(root / name)
    for name in ("yorkurban", "yorkurban-indoor"):
        recs = json.loads((root / name / "cameras.json").read_text())
        gt = json.loads((root / name / "gt" / "gt_vps.json").read_text())["images"]
        for fname, rec in sorted(recs.items()):
            if gt.get(Path(fname).stem, {}).get("eccv_split") == "train":
                items.append(RealItem(root / name / "images" / fname, camera_from_record(rec)))
    recs = json.loads((root / "eurasian-cities" / "cameras.json").read_text())
    hz = json.loads((root / "eurasian-cities" / "gt" / "gt_horizon_zenith.json").read_text())
    for fname, rec in sorted(recs.items()):
        if int(Path(fname).stem) % 2:
            continue
        g = hz["images"][fname]
        pp = to_opencv_points(np.array([rec["width"], rec["height"]]) / 2)  # the horizon's frame
        f = focal_from_horizon_zenith(g["horizon_abc_out"], g["zenith_xy_out"], pp)
        ok = 0.5 * max(rec["width"], rec["height"]) <= f <= 2.5 * max(rec["width"], rec["height"])
        cam = camera_from_record(rec, f) if ok else None
        items.append(
            RealItem(root / "eurasian-cities" / "images" / fname, cam, horizon=g["horizon_abc_out"])
        )
    for name, prefixes in (
        ("phototourism-samples", ("",)),
        ("small-groups", PERMISSIVE_SMALL_GROUPS),
    ):
        recs = json.loads((root / name / "cameras.json").read_text())
        for fname in sorted(recs):
            if fname.startswith(prefixes):
                items.append(
                    RealItem(root / name / "images" / fname, camera_from_record(recs[fname]))
                )
    return items
