"""Rendered street scenes with exact depth and poses for the pipeline tests.

World frame of the renderer: X across the street, Y up, Z along it; ground Y = 0. Poses
here are (R world-from-camera, c centre); ``to_pair`` turns two views into an evaluation
Pair (T_0to1 maps camera-0 points to camera 1).
"""

from __future__ import annotations

import numpy as np

from rectified_colmap.eval.pairs import Pair
from rectified_colmap.synth import render as _render
from rectified_colmap.synth import street as _street

UP = np.array([0.0, 1.0, 0.0])


def look_at(c: np.ndarray, target: np.ndarray) -> np.ndarray:
    """World-from-camera rotation of a level camera at c looking at target (y down)."""
    z = target - c
    z = z / np.linalg.norm(z)
    x = np.cross(-UP, z)  # right-handed, camera y down
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return np.stack([x, y, z], 1)


def intrinsics(width: int, height: int, f_factor: float = 0.9) -> np.ndarray:
    f = f_factor * width
    return np.array([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1.0]])


def render_view(scene, K, R, c, width, height):
    r = _render(scene, K, R, c, width, height, None, supersample=2, seed=scene.seed)
    depth = np.where(r["depth"] > 0, r["depth"], np.nan).astype(np.float32)
    return {"image": r["image"], "depth": depth, "K": K, "R": R, "c": np.asarray(c, float)}


def _inside_box(scene, c, margin=0.5):
    return bool(np.all((c > scene.lo - margin) & (c < scene.hi + margin), axis=1).any())


def _visible(view, X, tol=0.05):
    """X is seen (not occluded) at the image centre region of the view."""
    K, R, c = view["K"], view["R"], view["c"]
    Xc = R.T @ (X - c)
    if Xc[2] <= 0:
        return False
    u = K @ (Xc / Xc[2])
    h, w = view["depth"].shape
    col, row = int(u[0]), int(u[1])
    if not (0 <= col < w and 0 <= row < h):
        return False
    d = view["depth"][row, col]
    return bool(np.isfinite(d) and abs(d - Xc[2]) < tol * Xc[2])


def street_pair(seed: int, min_deg: float = 50, max_deg: float = 90, width: int = 480,
                height: int = 360, target: str = "facade"):
    """Two views of one street point 50-90 degrees apart (angle between the horizontal
    viewing directions to the point). Returns (view0, view1) or None if none was found."""
    rng = np.random.default_rng(seed)
    K = intrinsics(width, height)
    for _ in range(40):
        scene = _street(rng)
        delta = np.deg2rad(rng.uniform(min_deg, max_deg))
        w = scene.street_w
        if target == "facade":
            fronts = np.flatnonzero((scene.kind == 0) & (scene.hi[:, 1] > 5)
                                    & (np.abs(scene.hi[:, 0] - scene.lo[:, 0]) > 3))
            if len(fronts) == 0:
                continue
            b = rng.choice(fronts)
            side = 1.0 if scene.lo[b, 0] > 0 else -1.0
            xf = scene.lo[b, 0] if side > 0 else scene.hi[b, 0]
            zlen = scene.hi[b, 2] - scene.lo[b, 2]
            if zlen < 6:
                continue
            X = np.array([xf, rng.uniform(2.5, min(scene.hi[b, 1], 9)),
                          rng.uniform(scene.lo[b, 2] + 2, scene.hi[b, 2] - 2)])
            n = np.array([-side, 0.0, 0.0])
            dist = rng.uniform(0.5, 0.85) * w
            phis = np.array([-delta / 2, delta / 2]) + rng.normal(0, 0.1)
            eyes = [X + dist * (np.cos(p) * n + np.sin(p) * np.array([0, 0, 1.0]))
                    for p in phis]
            for e in eyes:
                e[1] = rng.uniform(1.5, 3.0)
        else:
            X = np.array([rng.uniform(-w / 4, w / 4), 0.0, rng.uniform(0, 60)])
            dist = rng.uniform(5, 9)
            az0 = rng.uniform(0, 2 * np.pi)
            eyes = [X + dist * np.array([np.sin(a), 0, np.cos(a)]) for a in (az0, az0 + delta)]
            for e in eyes:
                e[1] = rng.uniform(1.5, 2.5)
        if any(_inside_box(scene, e) or abs(e[0]) > w / 2 - 0.3 for e in eyes):
            continue
        views = [render_view(scene, K, look_at(e, X), e, width, height) for e in eyes]
        if all(_visible(v, X) for v in views):
            return views
    return None


def street_orbit(seed: int, num: int = 6, width: int = 480, height: int = 360):
    """A camera walking along the street, looking obliquely at one row of facades."""
    rng = np.random.default_rng(seed)
    K = intrinsics(width, height, 0.7)
    for _ in range(40):
        scene = _street(rng)
        side = rng.choice([-1.0, 1.0])
        x = -side * scene.street_w * 0.25
        z0 = rng.uniform(0, 40)
        views = []
        for i in range(num):
            c = np.array([x, 1.7, z0 + 1.5 * i])
            yaw = side * np.deg2rad(35 + 25 * i / max(num - 1, 1))  # turn toward the facades
            target = c + np.array([np.sin(yaw), -0.05, np.cos(yaw)])
            views.append(render_view(scene, K, look_at(c, target), c, width, height))
        if all(np.isfinite(v["depth"]).mean() > 0.6 for v in views):
            return views
    raise RuntimeError("no orbit found")


def to_pair(view0, view1, name0="0", name1="1") -> Pair:
    R0, c0, R1, c1 = view0["R"], view0["c"], view1["R"], view1["c"]
    T = np.eye(4)
    T[:3, :3] = R1.T @ R0  # X1 = R1^T (R0 X0 + c0 - c1)
    T[:3, 3] = R1.T @ (c0 - c1)
    return Pair(name0, name1, view0["K"], view1["K"], T)
