"""A small vectorised ray-caster of street canyons, for training data (fallback renderer).

Used when ``rectified_colmap.synth`` is not available. World frame: X across the street,
Y up, Z along the street; the ground is Y = 0. Buildings, kerbside objects and poles are
axis-aligned boxes; every surface is planar, so depth and normals are exact.

Outputs (camera frame x right, y down, z forward; COLMAP pixel convention: the centre of
pixel [i, j] is (j + 0.5, i + 0.5)): ``image`` (H, W, 3) uint8 RGB, ``depth`` (H, W) float32
z-depth with 0 where invalid (sky), ``normals`` (H, W, 3) float32 unit, oriented toward the
camera, 0 where invalid, ``K`` (3, 3) float64.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

logger = logging.getLogger(__name__)

MAX_DIST = 400.0


@dataclass
class Scene:
    lo: np.ndarray      # (N, 3) box minima
    hi: np.ndarray      # (N, 3) box maxima
    kind: np.ndarray    # (N,) 0 building, 1 object, 2 pole
    street_w: float
    sidewalk_w: float
    seed: int


def street(rng: np.random.Generator) -> Scene:
    """A random street canyon: two rows of buildings, optional far wall, kerbside objects."""
    w = rng.uniform(8, 30)
    side = rng.uniform(1.5, 4.0)
    lo, hi, kind = [], [], []
    for s in (-1, 1):
        if rng.random() < 0.08:
            continue  # open side (park, square)
        z = rng.uniform(-120, -60)
        while z < 200:
            length = rng.uniform(6, 40)
            if rng.random() < 0.12:  # cross street
                z += rng.uniform(8, 20)
                continue
            front = w / 2 + rng.uniform(-0.3, 1.5) * (rng.random() < 0.4)
            deep = rng.uniform(8, 20)
            height = rng.uniform(5, 40)
            x0, x1 = (front, front + deep) if s > 0 else (-front - deep, -front)
            lo.append([x0, 0, z]); hi.append([x1, height, z + length]); kind.append(0)
            if rng.random() < 0.25:  # balcony / ground-floor shop front / setback storey
                y0 = rng.uniform(2.5, max(height - 2, 3))
                d = rng.uniform(0.3, 1.5)
                bx0, bx1 = (front - d, front) if s > 0 else (-front, -front + d)
                zz = z + rng.uniform(0, length / 2)
                lo.append([bx0, y0, zz]); hi.append([bx1, y0 + rng.uniform(0.2, 1.2),
                                                      min(zz + rng.uniform(2, 10), z + length)])
                kind.append(1)
            z += length
        # kerbside objects (cars, kiosks, bins) and poles
        for _ in range(rng.integers(0, 10)):
            zc = rng.uniform(-40, 120)
            l, h, d = rng.uniform(1, 5), rng.uniform(0.5, 2.2), rng.uniform(0.6, 2.0)
            xc = s * (w / 2 - side - rng.uniform(0.2, 1.5) - d / 2)
            lo.append([xc - d / 2, 0, zc]); hi.append([xc + d / 2, h, zc + l]); kind.append(1)
        for _ in range(rng.integers(0, 6)):
            zc = rng.uniform(-20, 100)
            r, h = rng.uniform(0.05, 0.2), rng.uniform(2.5, 7)
            xc = s * (w / 2 - side + 0.5)
            lo.append([xc - r, 0, zc - r]); hi.append([xc + r, h, zc + r]); kind.append(2)
    if rng.random() < 0.5:  # building closing the street
        zf = rng.uniform(30, 200)
        lo.append([-w, 0, zf]); hi.append([w, rng.uniform(8, 40), zf + 15]); kind.append(0)
    if not lo:
        lo.append([w / 2, 0, -50]); hi.append([w / 2 + 10, 10, 50]); kind.append(0)
    return Scene(np.array(lo, float), np.array(hi, float), np.array(kind), w, side,
                 int(rng.integers(1 << 31)))


def rotation(yaw: float, pitch: float, roll: float) -> np.ndarray:
    """World-from-camera rotation (camera x right, y down, z forward; world Y up).
    yaw about world Y (positive: turn toward +X), pitch positive looks up, roll about z."""
    base = np.array([[1.0, 0, 0], [0, -1, 0], [0, 0, 1]])  # columns: camera axes in world
    cy, sy = np.cos(yaw), np.sin(yaw)
    cp, sp = np.cos(pitch), np.sin(pitch)
    cr, sr = np.cos(roll), np.sin(roll)
    r_yaw = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    r_pitch = np.array([[1, 0, 0], [0, cp, -sp], [0, sp, cp]])  # tilts +Z toward +Y (up)
    r_roll = np.array([[cr, -sr, 0], [sr, cr, 0], [0, 0, 1]])
    return r_yaw @ r_pitch @ base @ r_roll


def random_view(scene: Scene, rng: np.random.Generator, width: int, height: int
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(K, R world-from-camera, centre) of a random street-level or raised camera."""
    hfov = np.deg2rad(rng.uniform(40, 95))
    f = width / 2 / np.tan(hfov / 2)
    K = np.array([[f, 0, width / 2 + rng.normal(0, width * 0.02)],
                  [0, f, height / 2 + rng.normal(0, height * 0.02)], [0, 0, 1]])
    for _ in range(50):
        raised = rng.random() < 0.2
        cam_h = rng.uniform(4, 20) if raised else rng.uniform(1.0, 2.5)
        x = rng.uniform(-scene.street_w / 2 + 0.5, scene.street_w / 2 - 0.5)
        c = np.array([x, cam_h, rng.uniform(-10, 40)])
        inside = np.all((c > scene.lo - 0.3) & (c < scene.hi + 0.3), axis=1).any()
        if not inside:
            break
    mode = rng.random()
    if mode < 0.5:
        yaw = rng.normal(0, 0.45)  # along the street
    elif mode < 0.85:
        yaw = rng.choice([-1, 1]) * rng.uniform(0.6, 1.6)  # toward a facade
    else:
        yaw = rng.uniform(-np.pi, np.pi)
    if rng.random() < 0.5:
        yaw = yaw + np.pi if rng.random() < 0.3 else yaw
    pitch = rng.uniform(-0.6, 0.1) if raised else rng.uniform(-0.35, 0.45)
    roll = rng.normal(0, 0.06)
    return K, rotation(yaw, pitch, roll), c


def _hash(*ints: np.ndarray, seed: int = 0) -> np.ndarray:
    """Deterministic pseudo-random floats in [0, 1) from integer arrays."""
    h = np.uint64(seed * 2654435761 + 97)
    out = np.full(np.broadcast(*ints).shape, h, np.uint64)
    for k, a in enumerate(ints):
        out = out ^ (np.asarray(a).astype(np.int64).astype(np.uint64)
                     * np.uint64([73856093, 19349663, 83492791][k % 3]))
        out = (out ^ (out >> np.uint64(13))) * np.uint64(0x5bd1e995)
        out = out ^ (out >> np.uint64(15))
    return (out & np.uint64(0xFFFFFF)).astype(np.float64) / float(0x1000000)


def _value_noise(u, v, scale, seed):
    """Smooth value noise of period ~``scale`` metres."""
    x, y = u / scale, v / scale
    x0, y0 = np.floor(x), np.floor(y)
    fx, fy = x - x0, y - y0
    fx, fy = fx * fx * (3 - 2 * fx), fy * fy * (3 - 2 * fy)
    a, b = _hash(x0, y0, seed=seed), _hash(x0 + 1, y0, seed=seed)
    c, d = _hash(x0, y0 + 1, seed=seed), _hash(x0 + 1, y0 + 1, seed=seed)
    return (a * (1 - fx) + b * fx) * (1 - fy) + (c * (1 - fx) + d * fx) * fy


def _facade(u, v, rng, seed):
    """Procedural facade colour (P, 3) in [0, 1] at wall coordinates u (along), v (up)."""
    base = rng.uniform(0.15, 0.85, 3) * rng.uniform(0.6, 1.0)
    col = np.broadcast_to(base, u.shape + (3,)).copy()
    style = rng.random()
    if style < 0.35:  # bricks
        bw, bh = rng.uniform(0.2, 0.3), rng.uniform(0.06, 0.09)
        row = np.floor(v / bh)
        uu = u / bw + 0.5 * (row % 2)
        brick = _hash(np.floor(uu), row, seed=seed)[..., None]
        col = col * (0.8 + 0.4 * brick)
        mortar = (np.minimum(uu % 1, 1 - uu % 1) * bw < 0.01) | \
                 (np.minimum((v / bh) % 1, 1 - (v / bh) % 1) * bh < 0.01)
        col[mortar] = rng.uniform(0.5, 0.8)
    elif style < 0.6:  # stone blocks / panels
        pw, ph = rng.uniform(0.5, 2.0), rng.uniform(0.3, 1.0)
        cell = _hash(np.floor(u / pw), np.floor(v / ph), seed=seed)[..., None]
        col = col * (0.85 + 0.3 * cell)
        joint = (np.minimum((u / pw) % 1, 1 - (u / pw) % 1) * pw < 0.015) | \
                (np.minimum((v / ph) % 1, 1 - (v / ph) % 1) * ph < 0.015)
        col[joint] *= 0.6
    col *= (0.75 + 0.5 * _value_noise(u, v, rng.uniform(0.5, 4), seed + 1))[..., None]
    # windows on a floor grid
    if rng.random() < 0.9:
        fh, sp = rng.uniform(2.8, 4.0), rng.uniform(1.8, 4.5)
        ww, wh = rng.uniform(0.35, 0.75) * sp, rng.uniform(0.35, 0.65) * fh
        g0 = rng.uniform(0.5, 1.5) * fh  # ground floor height offset
        fu, fv = (u / sp) % 1, ((v - g0) / fh) % 1
        iu, iv = np.floor(u / sp), np.floor((v - g0) / fh)
        inu = np.abs(fu - 0.5) < ww / sp / 2
        inv = np.abs(fv - 0.45) < wh / fh / 2
        win = inu & inv & (v > g0)
        frame = (np.abs(fu - 0.5) < ww / sp / 2 + 0.08 / sp) & \
                (np.abs(fv - 0.45) < wh / fh / 2 + 0.08 / fh) & (v > g0) & ~win
        glass = rng.uniform(0.05, 0.45, 3) * np.array([0.8, 0.9, 1.0])
        lum = (0.4 + 1.2 * _hash(iu, iv, seed=seed + 2))[..., None]
        col[frame] = rng.uniform(0.3, 0.95)
        col[win] = np.clip(glass * lum[win], 0, 1)
        if rng.random() < 0.5:  # floor cornices
            cornice = (((v - g0) / fh) % 1 < 0.06) & (v > g0)
            col[cornice] = np.clip(base * 1.3, 0, 1)
        shop = (v < g0) & (np.abs((u / (2 * sp)) % 1 - 0.5) < 0.35) & (v < g0 * 0.85)
        col[shop] = glass * 0.8
    return col


def _ground(x, z, scene: Scene, rng, seed):
    asphalt = rng.uniform(0.2, 0.45)
    col = np.full(x.shape + (3,), asphalt) * rng.uniform(0.9, 1.1, 3)
    col *= (0.7 + 0.6 * _value_noise(x, z, 0.3, seed))[..., None]
    col *= (0.85 + 0.3 * _value_noise(x, z, 5.0, seed + 1))[..., None]
    side = np.abs(x) > scene.street_w / 2 - scene.sidewalk_w
    ts = rng.uniform(0.3, 0.6)
    tile = _hash(np.floor(x / ts), np.floor(z / ts), seed=seed + 3)
    grout = (np.minimum((x / ts) % 1, 1 - (x / ts) % 1) < 0.04) | \
            (np.minimum((z / ts) % 1, 1 - (z / ts) % 1) < 0.04)
    pave = rng.uniform(0.45, 0.75) * (0.85 + 0.3 * tile) * np.where(grout, 0.7, 1.0)
    col[side] = pave[side][:, None] * rng.uniform(0.9, 1.1, 3)
    lane = (np.abs(x) < 0.08) & ((z % 9) < 4.5) & ~side
    col[lane] = 0.9
    if rng.random() < 0.5:
        for xl in (-1, 1):
            edge = np.abs(x - xl * (scene.street_w / 2 - scene.sidewalk_w - 0.3)) < 0.07
            col[edge & ~side] = 0.85
    return col


class Textures:
    """Optional facade photos (a folder of JPEG/PNG), used as wall textures."""

    def __init__(self, folder: str | Path | None = None, max_side: int = 640):
        self.images = []
        if folder is not None and Path(folder).is_dir():
            for p in sorted(Path(folder).rglob("*")):
                if p.suffix.lower() in (".jpg", ".jpeg", ".png"):
                    im = cv2.imread(str(p), cv2.IMREAD_COLOR)
                    if im is None:
                        continue
                    s = max_side / max(im.shape[:2])
                    if s < 1:
                        im = cv2.resize(im, None, fx=s, fy=s, interpolation=cv2.INTER_AREA)
                    self.images.append(im[..., ::-1].astype(np.float32) / 255.0)
            logger.info("loaded %d texture photos from %s", len(self.images), folder)

    def sample(self, u, v, rng):
        im = self.images[rng.integers(len(self.images))]
        h, w = im.shape[:2]
        s = w / rng.uniform(8, 25)  # pixels per metre
        px = ((u * s + rng.uniform(0, w)) % w).astype(np.int64)
        py = ((-v * s + rng.uniform(0, h)) % h).astype(np.int64)
        return im[py, px]


def _visible_boxes(scene: Scene, origin, R, K, width, height) -> np.ndarray:
    """Indices of boxes that may appear in the image (corner projection culling)."""
    corners = np.stack([np.stack([np.where(b & 1, scene.hi[:, 0], scene.lo[:, 0]),
                                  np.where(b & 2, scene.hi[:, 1], scene.lo[:, 1]),
                                  np.where(b & 4, scene.hi[:, 2], scene.lo[:, 2])], -1)
                        for b in range(8)], 1)  # (N, 8, 3)
    pc = (corners - origin) @ R  # camera frame
    z = pc[..., 2]
    keep = (z > 0.01).any(1)
    front = np.all(z > 0.01, axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        u = K[0, 0] * pc[..., 0] / z + K[0, 2]
        v = K[1, 1] * pc[..., 1] / z + K[1, 2]
    out = front & ((u.max(1) < 0) | (u.min(1) > width) | (v.max(1) < 0) | (v.min(1) > height))
    return np.flatnonzero(keep & ~out)


def _cast(scene: Scene, origin: np.ndarray, dirs: np.ndarray, boxes=None):
    """Nearest hit of rays (P, 3) (world): t (P,), box index (P,) (-1 ground, -2 none),
    axis (P,) of the hit face, outward normal sign (P,)."""
    p = dirs.shape[0]
    d = np.where(np.abs(dirs) < 1e-9, 1e-9, dirs)
    inv = [np.ascontiguousarray(1.0 / d[:, k]) for k in range(3)]
    best_t = np.full(p, np.inf)
    best_i = np.full(p, -2)
    best_a = np.ones(p, np.int64)
    with np.errstate(divide="ignore", invalid="ignore"):
        tg = -origin[1] * inv[1]
    ground = (d[:, 1] < 0) & (tg > 0) & (tg < MAX_DIST)
    best_t[ground] = tg[ground]
    best_i[ground] = -1
    for i in (range(len(scene.lo)) if boxes is None else boxes):
        tmins, tmaxs = [], []
        for k in range(3):
            t1 = (scene.lo[i, k] - origin[k]) * inv[k]
            t2 = (scene.hi[i, k] - origin[k]) * inv[k]
            tmins.append(np.minimum(t1, t2))
            tmaxs.append(np.maximum(t1, t2))
        tnear = np.maximum(np.maximum(tmins[0], tmins[1]), tmins[2])
        tfar = np.minimum(np.minimum(tmaxs[0], tmaxs[1]), tmaxs[2])
        hit = (tnear <= tfar) & (tnear > 1e-6) & (tnear < best_t)
        if hit.any():
            best_t[hit] = tnear[hit]
            best_i[hit] = i
            tn = tnear[hit]
            best_a[hit] = np.where(tmins[0][hit] == tn, 0, np.where(tmins[1][hit] == tn, 1, 2))
    sign = -np.sign(d[np.arange(p), best_a])
    sign[best_i == -1] = 1.0
    best_a[best_i == -1] = 1
    return best_t, best_i, best_a, sign


def _shade_and_texture(scene, hit_pt, idx, axis, sign, rng, textures: Textures | None):
    p = hit_pt.shape[0]
    col = np.zeros((p, 3))
    normals = np.zeros((p, 3))
    normals[np.arange(p), axis] = sign
    g = idx == -1
    if g.any():
        col[g] = _ground(hit_pt[g, 0], hit_pt[g, 2], scene, rng, scene.seed)
    for i in np.unique(idx[idx >= 0]):
        m = idx == i
        a = axis[m]
        u = np.where(a == 0, hit_pt[m, 2], hit_pt[m, 0]) * np.where(a == 2, 1, 1)
        v = np.where(a == 1, hit_pt[m, 2], hit_pt[m, 1])
        brng = np.random.default_rng([scene.seed, int(i)])
        if scene.kind[i] == 0 and textures is not None and textures.images \
                and brng.random() < 0.6:
            col[m] = textures.sample(u, v, brng)
        elif scene.kind[i] == 2:
            col[m] = brng.uniform(0.1, 0.6, 3)
        else:
            col[m] = _facade(u, v, brng, scene.seed + 7 * int(i))
        roof = m.copy()
        roof[m] = a == 1
        col[roof] = brng.uniform(0.2, 0.5, 3)
    srng = np.random.default_rng([scene.seed, 99991])
    sun = srng.normal(size=3)
    sun[1] = abs(sun[1]) + 0.3
    sun /= np.linalg.norm(sun)
    ambient = srng.uniform(0.35, 0.7)
    light = ambient + (1 - ambient) * np.clip(normals @ sun, 0, 1)
    return col * light[:, None], normals


def _sky(dirs_w, rng):
    elev = np.clip(dirs_w[:, 1] / np.linalg.norm(dirs_w, axis=1), -1, 1)
    top = rng.uniform(0.3, 0.9, 3) * np.array([0.7, 0.85, 1.0])
    hor = np.clip(top + rng.uniform(0.1, 0.4), 0, 1)
    t = np.clip(elev, 0, 1)[:, None] ** 0.5
    return hor * (1 - t) + top * t


def render(scene: Scene, K: np.ndarray, R: np.ndarray, c: np.ndarray, width: int, height: int,
           textures: Textures | None = None, supersample: int = 2, seed: int = 0) -> dict:
    """Render image / depth / normals (see module docstring)."""
    rng = np.random.default_rng(seed)
    out = {}
    for ss in (supersample, 1):
        kk = K.copy()
        kk[:2] *= ss
        jj, ii = np.meshgrid(np.arange(width * ss) + 0.5, np.arange(height * ss) + 0.5)
        rays = np.stack([(jj - kk[0, 2]) / kk[0, 0], (ii - kk[1, 2]) / kk[1, 1],
                         np.ones_like(jj)], -1).reshape(-1, 3)
        dirs = rays @ R.T
        t, idx, axis, sign = _cast(scene, c, dirs,
                                   _visible_boxes(scene, c, R, kk, width * ss, height * ss))
        if ss == supersample:
            hit = idx > -2
            col = _sky(dirs, np.random.default_rng([scene.seed, 5]))
            if hit.any():
                pts = c + dirs[hit] * t[hit, None]
                col[hit], _ = _shade_and_texture(scene, pts, idx[hit], axis[hit], sign[hit],
                                                 rng, textures)
            img = col.reshape(height * ss, width * ss, 3)
            if ss > 1:
                img = cv2.resize(img, (width, height), interpolation=cv2.INTER_AREA)
            out["image"] = np.clip(img * 255 + 0.5, 0, 255).astype(np.uint8)
        if ss == 1:
            hit = idx > -2
            depth = np.where(hit, t, 0.0)  # rays have camera z = 1: t is z-depth
            n_w = np.zeros((len(t), 3))
            n_w[np.arange(len(t)), axis] = sign
            n_c = n_w @ R  # camera-from-world = R.T; applied to rows
            n_c[~hit] = 0
            out["depth"] = depth.reshape(height, width).astype(np.float32)
            out["normals"] = n_c.reshape(height, width, 3).astype(np.float32)
            if supersample == 1:
                break
    out["K"] = K
    out["R"] = R  # world-from-camera: its rows are the world (scene) axes in the camera frame
    return out


def random_sample(seed: int, width: int, height: int, textures: Textures | None = None,
                  supersample: int = 2, min_valid: float = 0.3) -> dict:
    """One random street view (retries until at least ``min_valid`` of the pixels hit)."""
    rng = np.random.default_rng(seed)
    for _ in range(20):
        scene = street(rng)
        K, R, c = random_view(scene, rng, width, height)
        # cheap validity check at low resolution
        s = 8
        lo = render(scene, K / np.array([[s], [s], [1]]), R, c, width // s, height // s,
                    None, supersample=1)
        if (lo["depth"] > 0).mean() >= min_valid:
            break
    return render(scene, K, R, c, width, height, textures, supersample,
                  seed=int(rng.integers(1 << 31)))
