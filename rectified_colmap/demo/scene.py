"""Scenes of planar textured quads and their builder.

World frame: metres, **z up**, the ground is z = 0 (streets run along +y).

A quad ``q`` is the rectangle ``origin + a * eu + b * ev`` for ``0 <= a <= size[0]``,
``0 <= b <= size[1]`` with ``eu``, ``ev`` orthonormal; its texture (index ``tex``) is mapped
with ``texel`` metres per texel: texel ``(col, row) = (a, b) / texel + tex_offset`` (row 0
at ``origin``; for walls ``ev`` points down so row 0 is the top). ``normal`` is the outward
unit normal (used only for shading; renders orient normals toward the camera).

Scenes are built with :class:`SceneBuilder` (quads, boxes, ground tiles, textures; all
deterministic from a numpy Generator). Layouts: the demo's street
(rectified_colmap.demo.street, with the facade rows, clutter and trees helpers); the corner,
square and rubble scenes of rectified_colmap_research.synth.scenes. Each scene also knows
where cameras may stand (``free_lo``/``free_hi`` box minus the ``blockers`` oriented boxes)
for the view helpers.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from . import textures as tx

logger = logging.getLogger(__name__)

UP = np.array([0.0, 0.0, 1.0])

# quad kinds
GROUND, FACADE, WALL, RELIEF, CLUTTER, ROOF, RUBBLE, VEGETATION = range(8)
KIND_NAMES = ["ground", "facade", "wall", "relief", "clutter", "roof", "rubble", "vegetation"]


@dataclass
class TextureSpec:
    kind: str
    seed: int
    height: int
    width: int
    ppm: float
    photo: int = -1
    """Index into the scene's photos, -1: procedural."""


@dataclass
class Scene:
    origin: np.ndarray  # (N, 3)
    eu: np.ndarray  # (N, 3) unit
    ev: np.ndarray  # (N, 3) unit, orthogonal to eu
    size: np.ndarray  # (N, 2) metres along eu, ev
    normal: np.ndarray  # (N, 3) outward unit normal
    kind: np.ndarray  # (N,) int
    tex: np.ndarray  # (N,) int index into ``textures``
    texel: np.ndarray  # (N,) metres per texel
    tex_offset: np.ndarray  # (N, 2) texels
    albedo: np.ndarray  # (N,) brightness factor (shading and per-quad variation)
    textures: list[TextureSpec]
    sky: np.ndarray  # (2, 3) horizon and zenith colours, [0, 1]
    free_lo: np.ndarray  # (3,) box where cameras may stand...
    free_hi: np.ndarray
    blockers: np.ndarray  # (M, 4, 3) ...outside these oriented boxes (corner, 3 edges)
    seed: int
    name: str = "scene"
    photos: tuple = ()
    meta: dict = field(default_factory=dict)
    clouds: float = 0.0
    """Cloud cover of the sky in [0, 1] (0: a clear gradient sky; synth.render)."""
    _pyramids: dict = field(default_factory=dict, repr=False, compare=False)

    def __len__(self) -> int:
        return len(self.origin)

    @property
    def corners(self) -> np.ndarray:
        """(N, 4, 3) corners: origin, +u, +u+v, +v."""
        a = self.eu * self.size[:, :1]
        b = self.ev * self.size[:, 1:]
        o = self.origin
        return np.stack([o, o + a, o + a + b, o + b], 1)

    @property
    def area(self) -> np.ndarray:
        return self.size[:, 0] * self.size[:, 1]

    def pyramid(self, i: int) -> list[np.ndarray]:
        """Mip pyramid of texture ``i`` (generated on first use; level k: 2^-k size)."""
        if i not in self._pyramids:
            import cv2

            spec = self.textures[i]
            photo = self.photos[spec.photo] if spec.photo >= 0 else None
            img = tx.make_texture(spec.kind, spec.seed, spec.height, spec.width, spec.ppm, photo)
            levels = [img]
            while (
                min(levels[-1].shape[:2]) >= 4
                and levels[-1].shape[0] % 2 == 0
                and levels[-1].shape[1] % 2 == 0
            ):
                h, w = levels[-1].shape[:2]
                levels.append(
                    cv2.resize(levels[-1], (w // 2, h // 2), interpolation=cv2.INTER_AREA)
                )
            self._pyramids[i] = levels
        return self._pyramids[i]

    def inside_blocker(self, points: np.ndarray, margin: float = 0.3) -> np.ndarray:
        """(P, 3) -> (P,) bool: inside (or within ``margin`` of) any blocker box."""
        points = np.asarray(points, float).reshape(-1, 3)
        out = np.zeros(len(points), bool)
        for c, *edges in self.blockers:
            d = points - c
            inside = np.ones(len(points), bool)
            for e in edges:
                L = np.linalg.norm(e)
                s = d @ (e / L)
                inside &= (s > -margin) & (s < L + margin)
            out |= inside
        return out

    def in_free_space(self, points: np.ndarray, margin: float = 0.3) -> np.ndarray:
        points = np.asarray(points, float).reshape(-1, 3)
        box = np.all((points >= self.free_lo) & (points <= self.free_hi), axis=1)
        return box & ~self.inside_blocker(points, margin)

    def sample_points(
        self,
        rng: np.random.Generator,
        n: int,
        kinds=None,
        min_area: float = 0.0,
        border: float = 0.5,
    ) -> tuple[np.ndarray, np.ndarray]:
        """``n`` random points on quads of the given kinds (area-weighted), at least
        ``border`` metres from the quad edges where possible. Returns (points, quad ids)."""
        ok = np.ones(len(self), bool) if kinds is None else np.isin(self.kind, list(kinds))
        ok &= self.area >= min_area
        ids = np.flatnonzero(ok)
        if len(ids) == 0:
            raise ValueError(f"scene {self.name}: no quads of kinds {kinds}")
        q = rng.choice(ids, n, p=self.area[ids] / self.area[ids].sum())
        b = np.minimum(border, 0.25 * self.size[q])
        a = b + rng.random((n, 2)) * (self.size[q] - 2 * b)
        pts = self.origin[q] + self.eu[q] * a[:, :1] + self.ev[q] * a[:, 1:]
        return pts, q


# -- construction ----------------------------------------------------------------------------


class SceneBuilder:
    """Accumulates quads and textures; one texture per quad unless shared."""

    def __init__(
        self,
        rng: np.random.Generator,
        max_tex: int = 1024,
        texel: float = 0.025,
        photos: tuple = (),
        photo_prob: float = 0.0,
    ):
        self.rng, self.max_tex, self.base_texel = rng, max_tex, texel
        self.q: dict[str, list] = {
            k: []
            for k in (
                "origin",
                "eu",
                "ev",
                "size",
                "normal",
                "kind",
                "tex",
                "texel",
                "tex_offset",
                "albedo",
            )
        }
        self.textures: list[TextureSpec] = []
        self.blockers: list[np.ndarray] = []
        self.photos, self.photo_prob = photos, photo_prob

    def texture(
        self,
        kind: str,
        width_m: float,
        height_m: float,
        texel: float | None = None,
        max_tex: int | None = None,
    ) -> tuple[int, float]:
        """A new texture covering width_m x height_m; returns (index, texel size)."""
        texel = texel or self.base_texel
        cap = max_tex or self.max_tex
        texel = max(texel, max(width_m, height_m) / cap)
        w = int(np.clip(np.ceil(width_m / texel / 16) * 16, 16, cap))
        h = int(np.clip(np.ceil(height_m / texel / 16) * 16, 16, cap))
        photo = -1
        if kind == "facade" and self.photos and self.rng.random() < self.photo_prob:
            photo = int(self.rng.integers(len(self.photos)))
        self.textures.append(
            TextureSpec(kind, int(self.rng.integers(1 << 31)), h, w, 1.0 / texel, photo)
        )
        return len(self.textures) - 1, texel

    def quad(
        self,
        origin,
        u_vec,
        v_vec,
        normal,
        kind: int,
        tex: tuple[int, float] | str,
        albedo: float | None = None,
        tex_offset=(0.0, 0.0),
    ) -> int:
        origin, u_vec, v_vec = (np.asarray(x, float) for x in (origin, u_vec, v_vec))
        su, sv = np.linalg.norm(u_vec), np.linalg.norm(v_vec)
        if su < 1e-6 or sv < 1e-6:
            return -1
        if isinstance(tex, str):
            tex = self.texture(tex, su, sv)
        q = self.q
        q["origin"].append(origin)
        q["eu"].append(u_vec / su)
        q["ev"].append(v_vec / sv)
        q["size"].append([su, sv])
        n = np.asarray(normal, float)
        q["normal"].append(n / np.linalg.norm(n))
        q["kind"].append(kind)
        q["tex"].append(tex[0])
        q["texel"].append(tex[1])
        q["tex_offset"].append(tex_offset)
        q["albedo"].append(self.rng.uniform(0.85, 1.1) if albedo is None else albedo)
        return len(q["origin"]) - 1

    def box(
        self,
        corner,
        e1,
        e2,
        height: float,
        kinds=(WALL, WALL, WALL, WALL, ROOF),
        textures=("plaster",) * 4 + ("roof",),
        blocker: bool = True,
    ) -> list[int]:
        """A box on its base (corner + s e1 + t e2, horizontal e1, e2), up to ``height``:
        four vertical walls and a top (no bottom). Walls are textured upright (row 0 at
        the top, columns left to right seen from outside)."""
        corner, e1, e2 = (np.asarray(x, float) for x in (corner, e1, e2))
        if np.cross(e1, e2)[2] < 0:
            e1, e2 = e2, e1
        h = UP * height
        base = [corner, corner + e1, corner + e1 + e2, corner + e2]
        ids = []
        for k in range(4):  # counter-clockwise seen from above: outward = edge x up
            p0, p1 = base[k], base[(k + 1) % 4]
            edge = p1 - p0
            n = np.cross(edge, UP)
            # seen from outside, left-to-right runs along edge; top-left corner is p0 + h
            ids.append(self.quad(p0 + h, edge, -h, n, kinds[k], textures[k]))
        ids.append(self.quad(corner + h, e1, e2, UP, kinds[4], textures[4]))
        if blocker:
            self.blockers.append(np.stack([corner, e1, e2, h]))
        return ids

    def ground(self, x0, x1, y0, y1, kind: str, tile: float = 12.0, texel: float = 0.03):
        """Ground z = 0 over [x0, x1] x [y0, y1] in tiles, each with its own texture."""
        xs = np.linspace(x0, x1, max(1, int(np.ceil((x1 - x0) / tile))) + 1)
        ys = np.linspace(y0, y1, max(1, int(np.ceil((y1 - y0) / tile))) + 1)
        for i in range(len(xs) - 1):
            for j in range(len(ys) - 1):
                self.quad(
                    [xs[i], ys[j], 0.0],
                    [xs[i + 1] - xs[i], 0, 0],
                    [0, ys[j + 1] - ys[j], 0],
                    UP,
                    GROUND,
                    self.texture(kind, xs[i + 1] - xs[i], ys[j + 1] - ys[j], texel, 512),
                )

    def finish(self, name: str, seed: int, free_lo, free_hi, meta=None) -> Scene:
        q = {k: np.asarray(v, float) for k, v in self.q.items()}
        rng = self.rng
        sun = np.array([rng.normal(), rng.normal(), rng.uniform(0.4, 1.5)])
        sun /= np.linalg.norm(sun)
        ambient = rng.uniform(0.45, 0.7)
        shade = ambient + (1 - ambient) * np.clip(q["normal"] @ sun, 0, 1)
        zenith = rng.uniform(0.35, 0.8) * np.array([0.6, 0.75, 1.0]) * rng.uniform(0.9, 1.1, 3)
        horizon = np.clip(zenith + rng.uniform(0.15, 0.4), 0, 1)
        return Scene(
            origin=q["origin"],
            eu=q["eu"],
            ev=q["ev"],
            size=q["size"],
            normal=q["normal"],
            kind=q["kind"].astype(np.int32),
            tex=q["tex"].astype(np.int32),
            texel=q["texel"],
            tex_offset=q["tex_offset"],
            albedo=(q["albedo"] * shade).astype(np.float32),
            textures=self.textures,
            sky=np.stack([horizon, zenith]).astype(np.float32),
            free_lo=np.asarray(free_lo, float),
            free_hi=np.asarray(free_hi, float),
            blockers=np.asarray(self.blockers, float).reshape(-1, 4, 3),
            seed=seed,
            name=name,
            photos=self.photos,
            meta=meta or {},
        )


def texture_photos(texture_dir) -> tuple:
    return tx.load_photos(str(texture_dir)) if texture_dir is not None else ()
