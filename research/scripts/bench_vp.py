"""Measure the vanishing-point stage (rectified_colmap.vp).

1. Rendered street line drawings (the renderer of tests/test_vp.py), depth directions
   perturbed by 10-20 degrees: angular error of the three directions with and without VP
   refinement; the same with the lines removed (nothing may snap to clutter).
2. Cost of refine_directions on a 1536x1024 photo.
3. Real photos (Strecha): the frame of each image rotated to the world by the GT pose;
   consistency across the images of a scene.
4. ``--trust``: which frame axes are trusted (with and without the chance-level test,
   vp.manhattan.axis_log10_nfa) on line-free blob textures in perspective, on
   rubble (randomly oriented quads), on rendered streets (GT axes) and on real photos
   (Strecha, EVD, York Urban with GT VPs; folders that are missing are skipped).

    python scripts/bench_vp.py /work/shared/data/strecha-dev [--viz OUT_DIR]
    python scripts/bench_vp.py /work/shared/data/strecha-dev --trust [--num_textures 30]
"""

from __future__ import annotations

import argparse
import sys
import json
import time
from pathlib import Path

import cv2
import numpy as np
import pycolmap

from rectified_colmap.camera import make_camera
from rectified_colmap.config import VpConf
from rectified_colmap_research.synth.planar import look_at, plane_view, textured_image
from rectified_colmap_research.synth.lines import axis_errors_deg, render_street, rot, street_camera
from rectified_colmap.viz import draw_directions, draw_segments, save_png
from rectified_colmap.vp.fusion import refine_directions
from rectified_colmap_research.line_planes import manhattan_from_image
from rectified_colmap.errors import run_script


def synthetic(conf: VpConf, num: int = 40, clutter: float = 0.3, lines: bool = True):
    rng = np.random.default_rng(0)
    camera = make_camera("PINHOLE", [850.0, 850.0, 512.0, 341.5], 1024, 683)
    before, after, snapped, contra = [], [], [], []
    for _ in range(num):
        R = street_camera(rng)
        img = render_street(camera, R, rng, clutter=clutter)
        if not lines:  # clutter only: random segments, no Manhattan structure
            img = render_clutter(camera, rng)
        G = R.T.copy()
        D = G @ rot(rng.normal(size=3), rng.uniform(10, 20)).T
        res = refine_directions(img, camera, D, conf)
        before.append(axis_errors_deg(D, G))
        after.append(axis_errors_deg(res.directions, G))
        snapped.append(res.snapped.sum())
        contra.append(res.contradicted.sum())
    b, a = np.concatenate(before), np.concatenate(after)
    worse = float(np.mean(np.array(after).max(1) > np.array(before).max(1) + 1.0))
    return dict(
        before=np.percentile(b, [50, 90]).round(2),
        after=np.percentile(a, [50, 90, 100]).round(2),
        mean_snapped=np.mean(snapped).round(2),
        frac_scenes_all3_snapped=float(np.mean(np.array(snapped) == 3)),
        frac_scenes_worse_by_1deg=worse,
        mean_contradicted=np.mean(contra).round(2),
    )


def render_clutter(camera, rng, n=250):
    img = np.full((camera.height, camera.width), 170, np.uint8)
    p = rng.uniform([0, 0], [camera.width, camera.height], (n, 2))
    ang = rng.uniform(0, np.pi, n)
    L = rng.uniform(20, 120, n)
    q = p + L[:, None] * np.stack([np.cos(ang), np.sin(ang)], 1)
    for a, b in zip(np.round(p * 16).astype(int), np.round(q * 16).astype(int)):
        cv2.line(img, tuple(map(int, a)), tuple(map(int, b)), 40, 2, cv2.LINE_AA, shift=4)
    noise = rng.normal(scale=6, size=img.shape)
    return np.clip(img + noise, 0, 255).astype(np.uint8)


def timing(path: Path, camera: pycolmap.Camera, conf: VpConf, reps: int = 7):
    gray = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    D = np.eye(3)
    refine_directions(gray, camera, D, conf)
    ts = []
    for _ in range(reps):
        t0 = time.perf_counter()
        refine_directions(gray, camera, D, conf)
        ts.append(time.perf_counter() - t0)
    return float(np.median(ts)), float(np.min(ts))


def strecha(scene: Path, conf: VpConf, viz: Path | None):
    rec = pycolmap.Reconstruction(str(scene / "sparse"))
    frames, names = [], []
    for img in sorted(rec.images.values(), key=lambda i: i.name):
        camera = rec.cameras[img.camera_id]
        gray = cv2.imread(str(scene / "images" / img.name), cv2.IMREAD_GRAYSCALE)
        res = manhattan_from_image(gray, camera, conf)
        Rcw = np.asarray(img.cam_from_world().rotation.matrix())
        if res.frame is None:
            frames.append(None)
        else:
            conf_axes = res.manhattan.sigma_deg <= conf.max_sigma_deg
            frames.append((res.frame @ Rcw, conf_axes, res.manhattan.sigma_deg))
        names.append(img.name)
        if viz is not None:
            save_png(
                viz / f"{scene.name}_{Path(img.name).stem}.segments.png", draw_segments(gray, res)
            )
            save_png(
                viz / f"{scene.name}_{Path(img.name).stem}.directions.png",
                draw_directions(gray, camera, res),
            )
    # pairwise: for each confident axis of image i, angle to the nearest axis of image j
    ang = []
    for i, fi in enumerate(frames):
        for j, fj in enumerate(frames):
            if i >= j or fi is None or fj is None:
                continue
            Fi, ci, _ = fi
            Fj, cj, _ = fj
            for k in np.flatnonzero(ci):
                c = np.abs(Fj @ Fi[k])
                m = int(np.argmax(c))
                if cj[m]:
                    ang.append(np.degrees(np.arccos(min(1.0, c[m]))))
    ang = np.array(ang)
    num_conf = [0 if f is None else int(f[1].sum()) for f in frames]
    sig = [np.round(f[2], 2).tolist() if f is not None else None for f in frames]
    return dict(
        images=len(frames),
        confident_axes=num_conf,
        pair_axis_angle_median=float(np.median(ang)) if len(ang) else None,
        pair_axis_angle_p90=float(np.percentile(ang, 90)) if len(ang) else None,
        frac_under_1deg=float((ang < 1).mean()) if len(ang) else None,
        frac_under_2deg=float((ang < 2).mean()) if len(ang) else None,
        sigma_deg=sig,
    )


# -- line-free blob textures in perspective (the helpers of tests/conftest.py, copied so that
# the script runs from the installed package without the test folder) ----------------------


def _trust_sets(data: Path, num_textures: int):
    """Yields (set name, name, gray (H, W) uint8, camera, GT axes (3, 3) rows or None)."""
    from rectified_colmap_research import synth

    K = np.array([[400.0, 0, 200], [0, 400, 150], [0, 0, 1]])
    cam = make_camera("PINHOLE", [400.0, 400.0, 200.0, 150.0], 400, 300)
    eyes = [[2.5, -4.0, 2.0], [-2.0, -4.0, 1.5], [0.5, -3.5, 3.5], [3.5, -1.0, 1.0]]
    for seed in range(num_textures):  # tests/test_extract_cli geometry, more textures
        tex = textured_image(600, 600, seed)
        for i, eye in enumerate(eyes):
            for mpt in (0.01, 0.02):
                R, t = look_at(eye, [0, 0, 0])
                yield (
                    "blob texture",
                    f"{seed}/{i}/{mpt}",
                    plane_view(tex, mpt, K, R, t, (400, 300))[0],
                    cam,
                    None,
                )
    camera = synth.pinhole_camera(480, 360, 0.9 * 480)
    for seed in range(6):
        rng = np.random.default_rng(100 + seed)
        scene = synth.rubble(rng)
        for j in range(2):
            r = synth.render(scene, camera, synth.random_view(scene, rng, camera))
            yield "rubble", f"{seed}/{j}", cv2.cvtColor(r.image, cv2.COLOR_RGB2GRAY), camera, None
    for seed in range(12):
        rng = np.random.default_rng(seed)
        tex = data / "textures" / "facades" if (data / "textures" / "facades").is_dir() else None
        scene = synth.street(rng, texture_dir=tex)
        target = ("facade", "ground")[seed % 2]
        for j, pose in enumerate(
            synth.view_pair(scene, rng, 50, 90, target=target, camera=camera)[:2]
        ):
            r = synth.render(scene, camera, pose)
            G = np.asarray(pose.rotation.matrix()).T.copy()
            yield (
                f"streets ({target})",
                f"{seed}/{j}",
                cv2.cvtColor(r.image, cv2.COLOR_RGB2GRAY),
                camera,
                G,
            )
    for scene in sorted((data / "data" / "strecha-dev").glob("*/sparse")):
        rec = pycolmap.Reconstruction(str(scene))
        for im in sorted(rec.images.values(), key=lambda i: i.name):
            gray = cv2.imread(str(scene.parent / "images" / im.name), cv2.IMREAD_GRAYSCALE)
            yield "Strecha", f"{scene.parent.name}/{im.name}", gray, rec.cameras[im.camera_id], None
    evd = data / "data" / "evd-dev"
    if (evd / "pairs.json").exists():
        for q in json.loads((evd / "pairs.json").read_text()):
            for key in ("im0", "im1"):
                gray = cv2.imread(str(evd / q[key]), cv2.IMREAD_GRAYSCALE)
                h, w = gray.shape
                f = 1.2 * max(w, h)  # the guess of scripts/eval_homography.py
                yield "EVD", q[key], gray, make_camera("PINHOLE", [f, f, w / 2, h / 2], w, h), None
    for sub in ("yorkurban", "yorkurban-indoor"):
        root = data / "data" / "real-pool" / sub
        if not (root / "cameras.json").exists():
            continue
        gt = json.loads((root / "gt" / "gt_vps.json").read_text())["images"]
        for name, c in sorted(json.loads((root / "cameras.json").read_text()).items()):
            gray = cv2.imread(str(root / "images" / name), cv2.IMREAD_GRAYSCALE)
            camera = make_camera(
                "PINHOLE", [c["focal_px"], c["focal_px"], c["cx"], c["cy"]], c["width"], c["height"]
            )
            g = gt.get(Path(name).stem)
            G = None
            if g is not None:  # columns = VPs, camera frame with y UP
                V = g["vp_orthogonal"]
                G = np.array(json.loads(V) if isinstance(V, str) else V).T * [1.0, -1.0, 1.0]
            yield f"York Urban ({sub})", name, gray, camera, G


def trust(data: Path, confs: dict[str, VpConf], num_textures: int = 30) -> str:
    """Markdown table: per image set and conf, images with >= 1 / >= 2 trusted axes and the
    error of the trusted axes to the GT (nearest GT axis; sets with GT only)."""
    rows: dict[tuple[str, str], list] = {}
    for set_name, _, gray, camera, G in _trust_sets(data, num_textures):
        for cname, conf in confs.items():
            mf = refine_directions(gray, camera, None, conf).manhattan
            trusted = mf.sigma_deg <= conf.max_sigma_deg
            err = []
            if G is not None and mf.frame is not None and trusted.any():
                G = G / np.linalg.norm(G, axis=1, keepdims=True)
                err = np.degrees(
                    np.arccos(np.clip(np.abs(mf.frame[trusted] @ G.T).max(1), 0, 1))
                ).tolist()
            nfa = np.sort(mf.log10_nfa)[:2] if mf.frame is not None else np.full(2, np.inf)
            rows.setdefault((set_name, cname), []).append((int(trusted.sum()), err, nfa))
    out = [
        "| images | conf | n | >= 1 trusted axis | >= 2 | trusted axes / image | "
        "GT error of trusted axes median / p90 / max (deg) | log10 NFA, first axis: min / "
        "median / max | second axis: min / median / max |",
        "|---" * 9 + "|",
    ]
    for (set_name, cname), r in rows.items():
        n = np.array([a for a, _, _ in r])
        err = np.concatenate([e for _, e, _ in r]) if any(e for _, e, _ in r) else np.zeros(0)
        e = " / ".join(f"{v:.2f}" for v in np.percentile(err, [50, 90, 100])) if len(err) else "-"
        nfa = np.array([x for _, _, x in r])
        q = [
            " / ".join(f"{v:.1f}" for v in np.percentile(nfa[:, i], [0, 50, 100])) for i in range(2)
        ]
        out.append(
            f"| {set_name} | {cname} | {len(n)} | {(n >= 1).sum()} | {(n >= 2).sum()} | "
            f"{n.mean():.2f} | {e} | {q[0]} | {q[1]} |"
        )
    return "\n".join(out)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("strecha", type=Path)
    ap.add_argument("--viz", type=Path)
    ap.add_argument("--skip-synth", action="store_true")
    ap.add_argument(
        "--trust",
        action="store_true",
        help="only the trust table (section 4); data = the folder above strecha's (.../shared)",
    )
    ap.add_argument("--num_textures", type=int, default=30)
    args = ap.parse_args()
    cv2.setNumThreads(1)
    conf = VpConf()
    if args.trust:
        shared = args.strecha.resolve().parents[1]
        print(
            trust(
                shared,
                {"no chance test": VpConf(max_log10_nfa=np.inf), "default": conf},
                args.num_textures,
            )
        )
        return
    if not args.skip_synth:
        for clutter in (0.3, 0.6):
            print(f"synthetic renders, clutter {clutter}:", synthetic(conf, clutter=clutter))
        print("clutter only (no Manhattan lines):", synthetic(conf, lines=False))
    scenes = sorted(p for p in args.strecha.iterdir() if (p / "sparse").is_dir())
    rec = pycolmap.Reconstruction(str(scenes[0] / "sparse"))
    img = sorted(rec.images.values(), key=lambda i: i.name)[0]
    t = timing(scenes[0] / "images" / img.name, rec.cameras[img.camera_id], conf)
    print(
        f"refine_directions on 1536x1024: {t[0] * 1000:.1f} ms median, {t[1] * 1000:.1f} ms "
        "min of 7"
    )
    for scene in scenes:
        print(scene.name, strecha(scene, conf, args.viz))


if __name__ == "__main__":
    sys.exit(run_script(main, "bench_vp"))
