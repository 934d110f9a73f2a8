"""One plane patch -> a virtual fronto-parallel camera, its rectified image, and the map back.

Which patches of an image get views, within what budget, and the blind patches' affine
views (ASIFT's tilt simulations): rectified_colmap.views.

A patch with normal n (facing the camera) is seen by a virtual camera with the same centre,
rotated by the smallest rotation R that takes the viewing direction -n onto +z. A ray X of
the original camera is X_v = R X in the virtual one; the virtual camera is a pinhole with
intrinsics K_v (COLMAP convention) chosen so that the patch fits in (w, h) pixels, at the
resolution of ``RectifyConf.view_resolution`` (default: nothing shrinks, the median smaller
singular value of the image->rectified Jacobian = 1) and the size is capped. For an
undistorted camera with intrinsics K the image->rectified map is the homography H = K_v R
K^-1; for other models warps go through the camera's own distortion.

Shapes: patch masks (h, w) bool on the work grid covering the image; rectified images and
masks (height, width); pixel coordinates (N, 2) in COLMAP convention in both the original
and the rectified image (conversions to OpenCV only through rectified_colmap.conventions).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field, replace

import cv2
import numpy as np
import pycolmap

from . import camera as cam_utils
from .config import RectifyConf, check_view_resolution
from .conventions import OFFSET, to_opencv_homography, to_opencv_points
from .geometry import singular_values_2x2, smallest_rotation
from .planes import Patch

logger = logging.getLogger(__name__)

MAX_FOCAL_SAMPLES = 20000
"""Patch pixels used (at most) for the median Jacobian that sets the virtual focal."""


@dataclass
class Rectification:
    R: np.ndarray
    """(3, 3) rotation original camera frame -> virtual camera frame."""
    K: np.ndarray
    """(3, 3) intrinsics of the virtual pinhole camera (COLMAP convention)."""
    size: tuple[int, int]
    """(width, height) of the rectified patch image."""
    mask: np.ndarray
    """(height, width) bool: rectified pixels that belong to the patch, are within the
    viewing-angle limit and whose rays are in front of the original camera."""
    normal: np.ndarray
    """(3,) patch normal in the original camera frame (facing the camera)."""
    patch_index: int

    @property
    def pixels(self) -> int:
        """The view's pixels, width x height (what the view budget counts)."""
        return self.size[0] * self.size[1]


def rectifying_rotation(normal: np.ndarray) -> np.ndarray:
    """Smallest rotation R with R @ (-normal) = (0, 0, 1)."""
    a = -np.asarray(normal, dtype=np.float64).reshape(3)
    na = np.linalg.norm(a)
    if not np.isfinite(na) or na == 0:
        raise ValueError(f"rectifying_rotation: invalid normal {normal}")
    # a = -z gives the half turn about x (any axis in the image plane would do)
    return smallest_rotation(a / na, np.array([0.0, 0.0, 1.0]))


def image_to_rectified_homography(camera: pycolmap.Camera, rect: Rectification) -> np.ndarray:
    """H = K_v R K^-1 between COLMAP pixel frames (pinhole part of the camera only)."""
    K = cam_utils.calibration_matrix(camera)
    return rect.K @ rect.R @ np.linalg.inv(K)


def rays_to_rectified_jacobian(R: np.ndarray, rays: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rays (N, 3) with z = 1 -> (virtual normalised coords (N, 2), d(virtual)/d(ray xy)
    (N, 2, 2)) for the rotation R (virtual focal 1)."""
    Xv = rays @ R.T
    zi = 1.0 / Xv[:, 2]
    u = Xv[:, :2] * zi[:, None]
    # d(u_i)/d(m_j) = (R[i, j] - u_i R[2, j]) / Xv_z, entry by entry (1-D arrays: faster
    # than broadcasting over (N, 2, 2))
    J = np.empty((len(rays), 2, 2))
    for i in range(2):
        for j in range(2):
            J[:, i, j] = (R[i, j] - u[:, i] * R[2, j]) * zi
    return u, J


def image_to_view_jacobian(camera: pycolmap.Camera, Ju: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """d(u)/d(image xy) (N, 2, 2) at the COLMAP pixels ``xy`` (N, 2), from ``Ju`` =
    d(u)/d(ray xy) (N, 2, 2) there: Ju @ d(ray xy)/d(image xy). A pinhole camera's is
    K^-1's 2 x 2 part, diagonal in COLMAP's models: a scaling of Ju's columns, the numbers
    of the product (its zero terms add nothing to finite Ju) without a product per cell."""
    if cam_utils.is_pinhole(camera):
        Ki = np.linalg.inv(cam_utils.calibration_matrix(camera))[:2, :2]
        if Ki[0, 1] == 0 and Ki[1, 0] == 0:
            return Ju * np.diag(Ki)
        return Ju @ Ki
    return Ju @ _image_to_ray_jacobian(camera, xy)


def _image_to_ray_jacobian(camera: pycolmap.Camera, xy: np.ndarray) -> np.ndarray:
    """d(ray xy)/d(image xy) (N, 2, 2) by central differences through the camera's
    undistortion (cameras with distortion; ``image_to_view_jacobian`` has pinholes')."""
    h = 1e-3
    J = np.empty((len(xy), 2, 2))
    for j in range(2):
        d = np.zeros(2)
        d[j] = h
        J[:, :, j] = (
            cam_utils.image_to_rays(camera, xy + d)[:, :2]
            - cam_utils.image_to_rays(camera, xy - d)[:, :2]
        ) / (2 * h)
    return J


def _rectified_pixel_rays(rect: Rectification) -> np.ndarray:
    """Rays (height, width, 3) of the original camera through the rectified pixel centres
    (not normalised; z <= 0 for rays behind the original camera)."""
    w, h = rect.size
    A = rect.R.T @ np.linalg.inv(rect.K)  # homogeneous rectified pixel -> original ray
    x = (np.arange(w) + OFFSET)[None, :]
    y = (np.arange(h) + OFFSET)[:, None]
    return np.stack([A[i, 0] * x + A[i, 1] * y + A[i, 2] for i in range(3)], -1)


def _project(camera: pycolmap.Camera, X: np.ndarray) -> np.ndarray:
    """Rays (..., 3) -> COLMAP pixels (..., 2); NaN behind the camera. Pinhole cameras in
    closed form (fast for whole rectified grids), others through pycolmap."""
    shape = X.shape[:-1]
    X = X.reshape(-1, 3)
    out = np.full((len(X), 2), np.nan)
    front = X[:, 2] > 1e-12
    if cam_utils.is_pinhole(camera):
        K = cam_utils.calibration_matrix(camera)
        zi = 1.0 / X[front, 2]
        out[front, 0] = K[0, 0] * X[front, 0] * zi + K[0, 2]
        out[front, 1] = K[1, 1] * X[front, 1] * zi + K[1, 2]
    elif front.any():
        out[front] = cam_utils.rays_to_image(camera, X[front])
    return out.reshape(shape + (2,))


def _rectified_mask(
    camera: pycolmap.Camera, rect: Rectification, patch_mask: np.ndarray, cos_max: float
) -> np.ndarray:
    """(height, width) bool: rectified pixels whose rays are in front of the camera, within
    the viewing angle, inside the image and in the patch (nearest cell of the work grid)."""
    w, h = rect.size
    Ki = np.linalg.inv(rect.K)
    # Viewing angle: -ray . n = cos of the angle of the virtual ray (u, v, 1) to +z.
    x = (np.arange(w) + OFFSET)[None, :]
    y = (np.arange(h) + OFFSET)[:, None]
    u, v = (Ki[i, 0] * x + Ki[i, 1] * y + Ki[i, 2] for i in range(2))
    ok = 1.0 + u**2 + v**2 <= 1.0 / cos_max**2
    gh, gw = patch_mask.shape
    A = rect.R.T @ Ki  # homogeneous rectified pixel -> original ray
    if cam_utils.is_pinhole(camera):
        # Nearest lookup of the work-grid mask through the homography rectified -> grid.
        ok &= A[2, 0] * x + A[2, 1] * y + A[2, 2] > 1e-12  # in front of the camera
        S = np.diag([gw / camera.width, gh / camera.height, 1.0])
        G = to_opencv_homography(S @ cam_utils.calibration_matrix(camera) @ A)
        warped = cv2.warpPerspective(
            patch_mask.astype(np.uint8),
            G,
            (w, h),
            flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP,
            borderMode=cv2.BORDER_CONSTANT,
            borderValue=0,
        )
        return ok & (warped > 0)
    X = _rectified_pixel_rays(rect)
    ok &= X[..., 2] > 1e-12
    idx = np.flatnonzero(ok)
    xy = _project(camera, X.reshape(-1, 3)[idx])
    with np.errstate(invalid="ignore"):
        inside = (
            (xy[:, 0] >= 0)
            & (xy[:, 1] >= 0)
            & (xy[:, 0] < camera.width)
            & (xy[:, 1] < camera.height)
        )
    idx, xy = idx[inside], xy[inside]
    # Beyond the distortion's monotonic range rays fold back into the image: keep the rays
    # that come back from their pixel (the undistortion's principal branch), to 0.01 px.
    m = X.reshape(-1, 3)[idx]
    back = cam_utils.image_to_rays(camera, xy)[:, :2] - m[:, :2] / m[:, 2:]
    tol = 0.01 / max(cam_utils.calibration_matrix(camera)[0, 0], 1e-12)
    same = np.abs(back).max(1) <= tol
    idx, xy = idx[same], xy[same]
    col = np.minimum((xy[:, 0] * (gw / camera.width)).astype(np.int64), gw - 1)
    row = np.minimum((xy[:, 1] * (gh / camera.height)).astype(np.int64), gh - 1)
    out = np.zeros(h * w, bool)
    out[idx[patch_mask[row, col]]] = True
    return out.reshape(h, w)


@dataclass
class PatchView:
    """The scale-independent part of plan_rectification for one patch."""

    normal: np.ndarray
    R: np.ndarray
    mask: np.ndarray
    cos_max: float
    f: float
    """Virtual focal length of the conf's view_resolution (before the caps)."""
    lo: np.ndarray
    hi: np.ndarray
    """Extent of the patch in virtual normalised coordinates (after ``A``), half a cell of
    margin."""
    A: np.ndarray = field(default_factory=lambda: np.eye(2))
    """(2, 2) map of the virtual normalised coordinates before the focal length: identity
    for a rectification, a compression for a tilt simulation (views.tilt_simulation_view)."""


def plan_rectification(
    camera: pycolmap.Camera,
    patch: Patch,
    patch_index: int,
    conf: RectifyConf = RectifyConf(),
    scale: float = 1.0,
    turn: bool = True,
) -> Rectification | None:
    """Virtual camera, size and valid mask for one patch; None if nothing usable remains
    (e.g. everything beyond the viewing-angle limit). ``scale`` multiplies the virtual focal
    length after the caps (the pipeline's budget on the total rectified area).

    The virtual focal f makes the median smaller singular value of the image->rectified
    Jacobian over the patch 1 (nothing shrinks; or the product of both, or the larger one:
    conf.view_resolution, view_focal); the size is then capped by conf.max_patch_side,
    scaling f down. (A blind patch's view: views.view_of_patch.)"""
    view = patch_view(camera, patch, conf, turn)
    if view is None:
        return None
    return finish_rectification(camera, view, patch_index, conf, scale)


def patch_view(
    camera: pycolmap.Camera, patch: Patch, conf: RectifyConf, turn: bool = True
) -> PatchView | None:
    """Rotation, focal length, extent and areas of the patch's cells within the viewing
    angle (plan_rectification without the scale); None when no cell is usable. ``turn``:
    the view turned about its axis to the smallest box (``fitting_roll``; off for upright
    SIFT, whose features take the view's up: the smallest rotation keeps about the
    image's)."""
    n = np.asarray(patch.normal, dtype=np.float64)
    n = n / np.linalg.norm(n)
    mask = np.asarray(patch.mask, bool)
    gh, gw = mask.shape
    cells = np.flatnonzero(mask)
    if len(cells) == 0:
        return None
    sx, sy = camera.width / gw, camera.height / gh
    grid = cam_utils.grid_rays(camera, gw, gh).reshape(-1, 3)  # rays, z = 1
    rx, ry = grid[cells, 0], grid[cells, 1]  # component-wise: 1-D arrays are faster here
    cos_max = np.cos(np.deg2rad(conf.max_viewing_angle_deg))
    cos_view = -(rx * n[0] + ry * n[1] + n[2]) / np.sqrt(rx**2 + ry**2 + 1.0)
    keep = np.isfinite(cos_view) & (cos_view >= cos_max) & (cos_view > 0)
    kept = np.flatnonzero(keep)
    if len(kept) == 0:
        return None
    R = rectifying_rotation(n)
    # The view's box is the box of the kept cells' hull, whose corners are among each grid
    # row's first and last kept cell: where grid rows are straight lines in the rays
    # (pinhole: the map to the view is projective, all in front) only those are needed.
    ends = kept[row_ends(cells[kept] // gw)]
    u = virtual_coords(R, grid[cells[ends]])
    box = u if cam_utils.is_pinhole(camera) else virtual_coords(R, grid[cells[kept]])
    if turn:  # to the smallest box
        Rz = fitting_roll(np.stack(u, 1))
        box = (Rz[0, 0] * box[0] + Rz[0, 1] * box[1], Rz[1, 0] * box[0] + Rz[1, 1] * box[1])
        R = Rz @ R
    # Jacobians on an even subsample of at most MAX_FOCAL_SAMPLES cells.
    sel = np.linspace(0, len(kept) - 1, min(len(kept), MAX_FOCAL_SAMPLES)).astype(np.int64)
    sample = cells[kept[sel]]
    rows, cols = np.divmod(sample, gw)
    xy = np.stack([(cols + OFFSET) * sx, (rows + OFFSET) * sy], 1)  # pixel_centers
    _, Ju = rays_to_rectified_jacobian(R, grid[sample])
    J = image_to_view_jacobian(camera, Ju, xy)  # d(u)/d(image xy), f = 1
    f = view_focal(singular_values_2x2(J), conf.view_resolution)
    if f is None:
        return None
    # Margin of half a work cell around the cell centres (virtual normalised units; one
    # product over all rows: the numbers of the per-cell products, in half the time).
    half = np.nanmax((0.5 * np.abs(J).reshape(-1, 2) @ np.array([sx, sy])).reshape(-1, 2), axis=0)
    return PatchView(
        normal=n,
        R=R,
        mask=mask,
        cos_max=cos_max,
        f=f,
        lo=np.array([box[0].min(), box[1].min()]) - half,
        hi=np.array([box[0].max(), box[1].max()]) + half,
    )


def row_ends(row: np.ndarray) -> np.ndarray:
    """Indices of each row's first and then each row's last entry in ``row`` (N,)
    non-decreasing (the grid rows of cells in grid order): the candidates for the corners
    of the cells' hull."""
    change = row[1:] != row[:-1]
    return np.concatenate(
        [np.flatnonzero(np.r_[True, change]), np.flatnonzero(np.r_[change, True])]
    )


def virtual_coords(R: np.ndarray, rays: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(x, y) virtual normalised coordinates of the rays (N, 3) with z = 1 under the
    rotation R, component-wise (1-D arrays are several times faster here than products)."""
    rx, ry = rays[:, 0], rays[:, 1]
    Xv = [R[i, 0] * rx + R[i, 1] * ry + R[i, 2] for i in range(3)]
    return Xv[0] / Xv[2], Xv[1] / Xv[2]


def fitting_roll(u: np.ndarray) -> np.ndarray:
    """(3, 3) rotation about the virtual optical axis (z) that turns the points ``u`` (N, 2)
    (virtual normalised coordinates) so that their axis-aligned bounding box is the
    smallest: the box of ``cv2.minAreaRect``, turned by at most 45 degrees (the identity
    where no turn shrinks the box). A view's size is its box: a patch seen along a diagonal
    needs fewer pixels turned, and SIFT (not upright) does not see the turn."""
    pts = np.asarray(u, np.float64)
    if len(pts) < 3:
        return np.eye(3)
    c = pts.mean(0)
    _, _, angle = cv2.minAreaRect((pts - c).astype(np.float32))
    a = -np.deg2rad(((angle + 45.0) % 90.0) - 45.0)  # the box edge onto x, |a| <= 45 deg
    R = np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])
    turned = (pts - c) @ R[:2, :2].T
    if np.prod(np.ptp(turned, 0)) >= np.prod(np.ptp(pts, 0)):
        return np.eye(3)
    return R


def view_focal(s: np.ndarray, rule: str) -> float | None:
    """Virtual focal length (normalised units -> view pixels) from the (N, 2) singular values
    (larger, smaller) of d(u)/d(image xy) at f = 1 over a patch's cells and the rule
    (config.VIEW_RESOLUTIONS: which median of the image->view Jacobian's singular values is
    1); None when they are degenerate."""
    check_view_resolution(rule)  # the conf's field may have been set after construction
    if rule == "finest":
        v = s[:, 1]
    elif rule == "area":
        v = np.sqrt(s[:, 0] * s[:, 1])
    else:  # coarsest
        v = s[:, 0]
    if not np.isfinite(v).any():
        return None
    m = float(np.nanmedian(v))
    return 1.0 / m if m > 0 else None


def view_camera(
    view: PatchView, conf: RectifyConf, scale: float
) -> tuple[np.ndarray, tuple[int, int]]:
    """The virtual intrinsics K (3, 3) and size (width, height) of a patch's view: the
    side cap of plan_rectification, then ``scale`` (at most 1)."""
    f, lo, hi = view.f, view.lo, view.hi

    def size_for(f):
        return np.ceil((hi - lo) * f + 2 * conf.border).astype(np.int64)

    size = size_for(f)
    extra_scale, scale = min(float(scale), 1.0), 1.0
    if size.max() > conf.max_patch_side:
        scale = min(scale, (conf.max_patch_side - 2 * conf.border) / ((hi - lo).max() * f))
    scale *= extra_scale
    if scale < 1.0:
        f *= max(scale, 1e-9)
        size = np.minimum(size_for(f), conf.max_patch_side)
    size = np.maximum(size, 1)
    cx, cy = conf.border - lo * f
    K = np.array([[f, 0.0, cx], [0.0, f, cy], [0.0, 0.0, 1.0]])
    K[:2, :2] = f * view.A
    return K, (int(size[0]), int(size[1]))


def finish_rectification(
    camera: pycolmap.Camera, view: PatchView, patch_index: int, conf: RectifyConf, scale: float
) -> Rectification | None:
    """plan_rectification from a patch's view: ``_view_camera``, then the valid mask; None
    when the mask is empty."""
    K, (w, h) = view_camera(view, conf, scale)
    rect = Rectification(
        R=view.R,
        K=K,
        size=(w, h),
        mask=np.zeros((h, w), bool),
        normal=view.normal,
        patch_index=patch_index,
    )
    rect.mask = _rectified_mask(camera, rect, view.mask, view.cos_max)
    if not rect.mask.any():
        return None
    return rect


def upsampled_rectification(rect: Rectification, factor: int) -> Rectification:
    """The same view at ``factor`` (integer >= 1) x its resolution: the virtual intrinsics
    scaled (COLMAP convention: rescaling pixel coordinates is a plain multiplication), the
    size and the mask (each cell repeated: the cell holding the new pixel's centre)."""
    if factor == 1:
        return rect
    w, h = rect.size
    mask = np.repeat(np.repeat(rect.mask, factor, axis=0), factor, axis=1)
    S = np.diag([float(factor), float(factor), 1.0])
    return replace(rect, K=S @ rect.K, size=(w * factor, h * factor), mask=mask)


def antialias_factor(camera: pycolmap.Camera, rect: Rectification) -> int:
    """How much finer ``warp_to_rectified`` renders an affine view (views.tilt_simulation_view
    on a pinhole camera) before averaging it down: the ceiling of its compression (the view
    -> image map's larger singular value), so a view pixel is the mean of the image pixels it
    covers, not their alias (ASIFT blurs before it subsamples); 1 for perspective views."""
    if not cam_utils.is_pinhole(camera):
        return 1
    H = image_to_rectified_homography(camera, rect)
    if np.abs(H[2, :2]).max() > 1e-12 * abs(H[2, 2]):
        return 1
    s = np.linalg.svd(np.linalg.inv(H[:2, :2] / H[2, 2]), compute_uv=False)[0]
    return max(1, int(np.ceil(s - 1e-6)))


def warp_to_rectified(
    image: np.ndarray, camera: pycolmap.Camera, rect: Rectification
) -> np.ndarray:
    """Render the rectified patch (height, width[, C]) from the original image (bilinear;
    affine views that compress, area-averaged: ``antialias_factor``); pixels outside
    rect.mask are 0."""
    image = np.asarray(image)
    if image.shape[:2] != (camera.height, camera.width):
        raise ValueError(
            f"warp_to_rectified: image is {image.shape[1]}x{image.shape[0]} but "
            f"the camera is {camera.width}x{camera.height}"
        )
    w, h = rect.size
    k = antialias_factor(camera, rect)
    if k > 1:  # k x finer, then each view pixel the mean of the image pixels it covers
        fine = warp_to_rectified(image, camera, upsampled_rectification(rect, k))
        out = cv2.resize(fine, (w, h), interpolation=cv2.INTER_AREA)
    elif cam_utils.is_pinhole(camera):
        H = to_opencv_homography(image_to_rectified_homography(camera, rect))
        out = cv2.warpPerspective(
            image, H, (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0
        )
    else:
        if max(w, h) >= 32767:
            raise ValueError(f"rectified patch {w}x{h} too large for cv2.remap")
        # Only the pixels of the mask need the camera's (slow) distortion model.
        maps = np.full((h, w, 2), -10.0, np.float32)
        X = _rectified_pixel_rays(rect)[rect.mask]
        xy = to_opencv_points(_project(camera, X))
        maps[rect.mask] = np.where(np.isfinite(xy), xy, -10.0)
        mx, my = maps[..., 0], maps[..., 1]
        out = cv2.remap(image, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
    # Also removes rays behind the source camera, which warpPerspective mirrors.
    out[~rect.mask] = 0
    return out


def rectified_to_image(
    camera: pycolmap.Camera, rect: Rectification, xy: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(N, 2) rectified COLMAP pixel coords -> ((N, 2) original image COLMAP pixel coords,
    (N, 2, 2) Jacobians d(image xy)/d(rectified xy)).

    Points whose rays lie behind the original camera map to NaN (and NaN Jacobians). The
    Jacobian is analytic through the rotation and the pinhole part; distortion is composed
    as a central-difference Jacobian of the camera's projection.
    """
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    A = rect.R.T @ np.linalg.inv(rect.K)  # rectified homogeneous pixel -> original ray
    X = xy @ A[:, :2].T + A[:, 2]
    with np.errstate(invalid="ignore", divide="ignore"):
        front = X[:, 2] > 1e-12
        zi = np.where(front, 1.0 / X[:, 2], np.nan)
    m = X[:, :2] * zi[:, None]
    # d(m_i)/d(p_j) = (A[i, j] - m_i A[2, j]) / X_z
    Jm = (A[None, :2, :2] - m[:, :, None] * A[None, 2:3, :2]) * zi[:, None, None]
    out = np.full((len(xy), 2), np.nan)
    Jp = np.full((len(xy), 2, 2), np.nan)
    if front.any():
        rays = np.concatenate([m[front], np.ones((int(front.sum()), 1))], 1)
        out[front] = cam_utils.rays_to_image(camera, rays)
        if cam_utils.is_pinhole(camera):
            Jp[front] = cam_utils.calibration_matrix(camera)[:2, :2]
        else:
            h = 1e-6
            for j in range(2):
                d = np.zeros(3)
                d[j] = h
                Jp[front, :, j] = (
                    cam_utils.rays_to_image(camera, rays + d)
                    - cam_utils.rays_to_image(camera, rays - d)
                ) / (2 * h)
    return out, Jp @ Jm
