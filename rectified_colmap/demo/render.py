"""Vectorised ray casting of quad scenes: image, exact z-depth, normals, plane ids.

Cameras are pycolmap PINHOLE / SIMPLE_PINHOLE cameras (COLMAP pixel convention: the centre
of pixel [i, j] is (j + 0.5, i + 0.5)); poses are ``cam_from_world`` pycolmap.Rigid3d.
Camera frame x right, y down, z forward. Rays through pixel centres are (x, y, 1), so the
ray parameter of a hit is its z-depth.

Per quad, only the pixels of the bounding box of its (near-clipped) projection are
tested: ray-plane parameter, inside test, z-buffer (min depth). Colour: supersampled rays,
texture sampled from a mip pyramid at the level of the per-pixel footprint (trilinear, two
cv2.remap per level), per-quad shading, sky gradient, area-downsampled. Depth, normals and
plane ids come from a separate pass through the final pixel centres (exact, no blending).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import cv2
import numpy as np
import pycolmap

from ..camera import model_name
from ..conventions import OFFSET, to_opencv_points
from .scene import Scene

logger = logging.getLogger(__name__)

NEAR = 1e-3
_CHUNK = 4096  # cv2.remap needs dimensions < 32767


@dataclass
class RenderResult:
    image: np.ndarray  # (H, W, 3) uint8 RGB
    depth: np.ndarray  # (H, W) float32 z-depth, NaN = sky
    normals: np.ndarray  # (H, W, 3) float32 camera frame, unit, toward the camera; NaN sky
    plane_id: np.ndarray  # (H, W) int32 quad index, -1 = sky
    camera: pycolmap.Camera
    cam_from_world: pycolmap.Rigid3d
    kind: np.ndarray | None = None  # (H, W) int8 quad kind (scene.KIND_NAMES), -1 = sky

    @property
    def K(self) -> np.ndarray:
        return np.asarray(self.camera.calibration_matrix(), np.float64)

    @property
    def valid(self) -> np.ndarray:
        return self.plane_id >= 0


def pinhole_K(camera: pycolmap.Camera) -> np.ndarray:
    name = model_name(camera)
    if name not in ("PINHOLE", "SIMPLE_PINHOLE"):
        raise ValueError(
            f"render: camera model {name} is not supported (PINHOLE or SIMPLE_PINHOLE only)"
        )
    return np.asarray(camera.calibration_matrix(), np.float64)


def _pose_Rt(cam_from_world: pycolmap.Rigid3d) -> tuple[np.ndarray, np.ndarray]:
    m = np.asarray(cam_from_world.matrix(), np.float64)
    return m[:, :3], m[:, 3]


def _quads_in_camera(scene: Scene, R, t):
    o = scene.origin @ R.T + t
    return o, scene.eu @ R.T, scene.ev @ R.T, np.cross(scene.eu, scene.ev) @ R.T


def _bboxes(scene: Scene, R, t, K, W, H) -> np.ndarray:
    """(N, 4) int pixel bounding boxes [i0, i1, j0, j1) of the quads' near-clipped
    projections (empty boxes for quads out of view)."""
    corners = scene.corners @ R.T + t  # (N, 4, 3)
    z = corners[..., 2]
    out = np.zeros((len(scene), 4), np.int64)
    front = (z > NEAR).all(1)
    some = (z > NEAR).any(1) & ~front
    pts = [None] * len(scene)
    for i in np.flatnonzero(some):  # Sutherland-Hodgman against z = NEAR (few quads)
        poly, c = [], corners[i]
        for k in range(4):
            a, b = c[k], c[(k + 1) % 4]
            if a[2] > NEAR:
                poly.append(a)
            if (a[2] > NEAR) != (b[2] > NEAR):
                s = (NEAR - a[2]) / (b[2] - a[2])
                poly.append(a + s * (b - a))
        pts[i] = np.array(poly)
    lo = np.full((len(scene), 2), np.inf)
    hi = np.full((len(scene), 2), -np.inf)
    if front.any():
        c = corners[front]
        xy = c[..., :2] / c[..., 2:]
        lo[front], hi[front] = xy.min(1), xy.max(1)
    for i in np.flatnonzero(some):
        xy = pts[i][:, :2] / pts[i][:, 2:]
        lo[i], hi[i] = xy.min(0), xy.max(0)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    with np.errstate(invalid="ignore"):
        j0 = np.floor(np.clip(lo[:, 0] * fx + cx - 1, -1, W + 1))
        j1 = np.ceil(np.clip(hi[:, 0] * fx + cx + 1, -1, W + 1))
        i0 = np.floor(np.clip(lo[:, 1] * fy + cy - 1, -1, H + 1))
        i1 = np.ceil(np.clip(hi[:, 1] * fy + cy + 1, -1, H + 1))
    box = np.stack([i0, i1, j0, j1], 1)
    box = np.nan_to_num(box, nan=-1)
    box[:, :2] = np.clip(box[:, :2], 0, H)
    box[:, 2:] = np.clip(box[:, 2:], 0, W)
    out[:] = box
    out[~(front | some)] = 0
    return out


def cast(
    scene: Scene,
    K: np.ndarray,
    R: np.ndarray,
    t: np.ndarray,
    width: int,
    height: int,
    uv: bool = False,
    dtype=np.float64,
):
    """Primary rays through the pixel centres of a width x height grid with intrinsics K.

    Returns depth (H, W) (inf: no hit), quad id (H, W) int32 (-1), and with ``uv`` the quad
    coordinates u, v (H, W) (metres) and n . ray (H, W); floats of ``dtype``."""
    rx = ((np.arange(width) + OFFSET - K[0, 2]) / K[0, 0]).astype(dtype)
    ry = ((np.arange(height) + OFFSET - K[1, 2]) / K[1, 1])[:, None].astype(dtype)
    o, eu, ev, n = _quads_in_camera(scene, R, t)
    dn = np.einsum("ij,ij->i", n, o)
    ou = np.einsum("ij,ij->i", eu, o)
    ov = np.einsum("ij,ij->i", ev, o)
    o, eu, ev, n, dn, ou, ov = (a.astype(dtype) for a in (o, eu, ev, n, dn, ou, ov))
    depth = np.full((height, width), np.inf, dtype)
    qid = np.full((height, width), -1, np.int32)
    if uv:
        U = np.zeros((height, width), dtype)
        V = np.zeros((height, width), dtype)
        D = np.ones((height, width), dtype)
    boxes = _bboxes(scene, R, t, K, width, height)
    todo = np.flatnonzero(
        (boxes[:, 1] > boxes[:, 0]) & (boxes[:, 3] > boxes[:, 2]) & (np.abs(dn) > 1e-9)
    )
    su, sv = scene.size[:, 0].astype(dtype), scene.size[:, 1].astype(dtype)
    with np.errstate(divide="ignore", invalid="ignore"):
        for q in todo:
            i0, i1, j0, j1 = boxes[q]
            x, y = rx[j0:j1], ry[i0:i1]
            den = n[q, 0] * x + n[q, 1] * y + n[q, 2]
            tq = dn[q] / den
            u = tq * (eu[q, 0] * x + eu[q, 1] * y + eu[q, 2]) - ou[q]
            v = tq * (ev[q, 0] * x + ev[q, 1] * y + ev[q, 2]) - ov[q]
            zb = depth[i0:i1, j0:j1]
            ok = (tq > NEAR) & (tq < zb) & (u >= 0) & (u <= su[q]) & (v >= 0) & (v <= sv[q])
            if not ok.any():
                continue
            np.copyto(zb, tq, where=ok)
            qid[i0:i1, j0:j1][ok] = q
            if uv:
                np.copyto(U[i0:i1, j0:j1], u, where=ok)
                np.copyto(V[i0:i1, j0:j1], v, where=ok)
                np.copyto(D[i0:i1, j0:j1], den, where=ok)
    if uv:
        return depth, qid, U, V, D
    return depth, qid


def _remap(img: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Bilinear, wrapped (tiled) sampling of img at OpenCV coordinates (P,) -> (P, 3)."""
    h, w = img.shape[:2]
    p = len(x)
    n = p + (-p) % _CHUNK
    maps = []
    for c, period in ((x, w), (y, h)):
        m = np.zeros(n, np.float32)
        m[:p] = c
        if p and (m.min() < -30000 or m.max() > 30000):  # cv2 maps go through int16
            m -= np.floor(m / period) * period
        maps.append(m.reshape(-1, _CHUNK))
    out = cv2.remap(img, maps[0], maps[1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)
    return out.reshape(-1, 3)[:p]


def _texture_colours(scene: Scene, q: np.ndarray, u, v, depth, den, f: float) -> np.ndarray:
    """Colours (P, 3) float32 at quad coordinates u, v (metres) of quads q (P,): trilinear
    mip mapping at the level of each pixel's footprint (f: focal length of the grid, px).

    A pixel at z-depth z on a plane with n . (x, y, 1) = den covers z^2 / (f^2 |den|) m^2;
    the level is log2 of its side in texels, mildly enlarged for obliquity."""
    texel = scene.texel[q].astype(np.float32)
    s = u / texel + scene.tex_offset[q, 0].astype(np.float32)
    r = v / texel + scene.tex_offset[q, 1].astype(np.float32)
    cos = np.clip(np.abs(den), np.float32(1e-3), np.float32(1.0))
    level = np.log2(np.maximum(depth / (np.float32(f) * texel), np.float32(1e-6))) - np.float32(
        0.75
    ) * np.log2(cos)
    # group pixels by (quad, level): two remaps (levels l0, l0 + 1) per group
    quads = np.unique(q)
    nlev = np.zeros(len(scene), np.float32)
    for qq in quads:
        nlev[qq] = len(scene.pyramid(int(scene.tex[qq])))
    level = np.clip(level, np.float32(0), nlev[q] - 1)
    l0 = level.astype(np.int32)
    w1 = level - l0
    key = q * 16 + l0  # levels < 16 (textures <= 32k texels)
    key = key.astype(np.int16) if len(scene) < 2048 else key
    order = np.argsort(key, kind="stable")  # radix sort for int16
    ks = key[order]
    bounds = np.flatnonzero(ks[1:] != ks[:-1]) + 1
    starts = np.concatenate([[0], bounds])
    ends = np.concatenate([bounds, [len(ks)]])
    s, r, w1 = s[order], r[order], w1[order]
    out = np.empty((len(q), 3), np.float32)
    for a, b in zip(starts, ends):
        qq, lv = divmod(int(ks[a]), 16)
        pyr = scene.pyramid(int(scene.tex[qq]))
        acc = None
        for k in (lv, lv + 1):
            if k >= len(pyr):
                continue
            img = pyr[k]
            sc = np.float32(2.0**-k)
            c = _remap(img, to_opencv_points(s[a:b] * sc), to_opencv_points(r[a:b] * sc))
            wk = (1 - w1[a:b]) if k == lv else w1[a:b]
            acc = c * wk[:, None] if acc is None else acc + c * wk[:, None]
        out[a:b] = acc * scene.albedo[qq]
    res = np.empty_like(out)
    res[order] = out
    return res


def _sky(scene: Scene, R: np.ndarray, K: np.ndarray, W: int, H: int) -> np.ndarray:
    """Sky colour (H, W, 3) float32 from the elevation of each ray (world z up)."""
    rx = ((np.arange(W) + OFFSET - K[0, 2]) / K[0, 0]).astype(np.float32)
    ry = ((np.arange(H) + OFFSET - K[1, 2]) / K[1, 1]).astype(np.float32)
    # world z of the ray direction: R^T (x, y, 1) . e_z = R[:, 2] . (x, y, 1)
    dz = R[0, 2] * rx[None, :] + R[1, 2] * ry[:, None] + R[2, 2]
    norm = np.sqrt(rx[None, :] ** 2 + ry[:, None] ** 2 + 1.0)
    e = np.clip(dz / norm, -1, 1)
    t = (np.clip(e, 0, 1) ** 0.6)[..., None].astype(np.float32)
    horizon, zenith = scene.sky
    sky = horizon * (1 - t) + zenith * t
    if scene.clouds > 0:
        # world direction of each ray: azimuth and elevation index a fixed cloud map
        dx = R[0, 0] * rx[None, :] + R[1, 0] * ry[:, None] + R[2, 0]
        dy = R[0, 1] * rx[None, :] + R[1, 1] * ry[:, None] + R[2, 1]
        cmap = _cloud_map(scene)
        h, w = cmap.shape
        col = (np.arctan2(dy, dx) / (2 * np.pi) % 1.0) * w
        row = (1 - np.clip(e, 0, 1)) * (h - 1)
        dens = cv2.remap(
            cmap,
            to_opencv_points(col).astype(np.float32),
            to_opencv_points(row).astype(np.float32),
            cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_WRAP,
        )[..., None]
        grey = np.float32(0.7 + 0.3 * (scene.seed % 1000) / 1000)
        sky = sky * (1 - dens) + grey * (1 - 0.25 * dens) * dens
    below = (e < 0)[..., None]
    return np.where(below, horizon * 0.8, sky).astype(np.float32)


def _cloud_map(scene: Scene, h: int = 256, w: int = 1024) -> np.ndarray:
    """(h, w) float32 cloud density over (elevation 90 -> 0 deg, azimuth 0 -> 360 deg),
    periodic in azimuth, deterministic from the scene's seed; cover ``scene.clouds``."""
    if "clouds" not in scene._pyramids:
        from .textures.blocks import value_noise

        rng = np.random.default_rng(scene.seed + 17)
        pad = w // 4
        n = value_noise(rng, h, w + pad, rng.uniform(0.15, 0.4) * w, 6)
        a = np.linspace(0, 1, pad, dtype=np.float32)[None]
        n[:, :pad] = n[:, :pad] * a + n[:, w:] * (1 - a)  # cross-fade: periodic in azimuth
        n = n[:, :w]
        lo = np.quantile(n, 1 - scene.clouds)  # the densest ``clouds`` of the sky is cloud
        scene._pyramids["clouds"] = np.clip((n - lo) / 0.12, 0, 1).astype(np.float32)
    return scene._pyramids["clouds"]


def render(
    scene: Scene,
    camera: pycolmap.Camera,
    cam_from_world: pycolmap.Rigid3d,
    supersample: int = 2,
    noise: float = 0.0,
    seed: int = 0,
) -> RenderResult:
    """Render a view (see the module docstring). ``noise``: std of additive Gaussian
    pixel noise (grey levels, 0-255), from ``seed``."""
    if supersample < 1:
        raise ValueError(f"supersample must be >= 1, got {supersample}")
    K = pinhole_K(camera)
    R, t = _pose_Rt(cam_from_world)
    W, H = int(camera.width), int(camera.height)
    # geometry at the pixel centres (float64)
    ss = int(supersample)
    if ss == 1:
        depth, qid, U, V, D = cast(scene, K, R, t, W, H, uv=True)
    else:
        depth, qid = cast(scene, K, R, t, W, H)
    hit = qid >= 0
    o, eu, ev, n = _quads_in_camera(scene, R, t)
    flip = np.einsum("ij,ij->i", n, o) > 0  # camera on the back side: flip the normal
    n = np.where(flip[:, None], -n, n)
    normals = np.full((H, W, 3), np.nan, np.float32)
    normals[hit] = n[qid[hit]]
    depth32 = np.where(hit, depth, np.nan).astype(np.float32)
    # colour from supersampled rays (float32), sky composited at the final resolution
    Ks = K.copy()
    Ks[:2] *= ss
    Ws, Hs = W * ss, H * ss
    if ss == 1:
        d, q, U, V, D = (
            a.astype(np.float32) if a.dtype == np.float64 else a for a in (depth, qid, U, V, D)
        )
    else:
        d, q, U, V, D = cast(scene, Ks, R, t, Ws, Hs, uv=True, dtype=np.float32)
    hs = q >= 0
    col = np.zeros((Hs, Ws, 3), np.float32)
    if hs.any():
        f = float(np.sqrt(Ks[0, 0] * Ks[1, 1]))
        col[hs] = _texture_colours(scene, q[hs], U[hs], V[hs], d[hs], D[hs], f)
    cover = hs.astype(np.float32)
    if ss > 1:
        col = cv2.resize(col, (W, H), interpolation=cv2.INTER_AREA)
        cover = cv2.resize(cover, (W, H), interpolation=cv2.INTER_AREA)
    img = col + _sky(scene, R, K, W, H) * (1 - cover)[..., None]
    img = img * 255.0
    if noise > 0:
        img = img + np.random.default_rng(seed).normal(0, noise, img.shape).astype(np.float32)
    image = np.clip(img + 0.5, 0, 255).astype(np.uint8)
    kind = np.where(qid >= 0, scene.kind[np.maximum(qid, 0)], -1).astype(np.int8)
    return RenderResult(image, depth32, normals, qid.astype(np.int32), camera, cam_from_world, kind)
