"""Measure the vanishing-point stage (rectified_colmap.vp).

1. Rendered street line drawings (the renderer of tests/test_vp.py), depth directions
   perturbed by 10-20 degrees: angular error of the three directions with and without VP
   refinement; the same with the lines removed (nothing may snap to clutter).
2. Cost of refine_directions on a 1536x1024 photo.
3. Real photos (Strecha): the frame of each image rotated to the world by the GT pose;
   consistency across the images of a scene.

    python scripts/bench_vp.py /work/shared/data/strecha-dev [--viz OUT_DIR]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pycolmap

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from rectified_colmap.camera import make_camera  # noqa: E402
from rectified_colmap.config import VpConf  # noqa: E402
from rectified_colmap.synth.lines import axis_errors_deg, render_street, rot, street_camera  # noqa: E402
from rectified_colmap.vp import (draw_directions, draw_segments, manhattan_from_image,  # noqa
                                 refine_directions, save_png)


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
    return dict(before=np.percentile(b, [50, 90]).round(2), after=np.percentile(a, [50, 90, 100])
                .round(2), mean_snapped=np.mean(snapped).round(2),
                frac_scenes_all3_snapped=float(np.mean(np.array(snapped) == 3)),
                frac_scenes_worse_by_1deg=worse,
                mean_contradicted=np.mean(contra).round(2))


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
            save_png(viz / f"{scene.name}_{Path(img.name).stem}.segments.png",
                     draw_segments(gray, res))
            save_png(viz / f"{scene.name}_{Path(img.name).stem}.directions.png",
                     draw_directions(gray, camera, res))
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
    return dict(images=len(frames), confident_axes=num_conf,
                pair_axis_angle_median=float(np.median(ang)) if len(ang) else None,
                pair_axis_angle_p90=float(np.percentile(ang, 90)) if len(ang) else None,
                frac_under_1deg=float((ang < 1).mean()) if len(ang) else None,
                frac_under_2deg=float((ang < 2).mean()) if len(ang) else None,
                sigma_deg=sig)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("strecha", type=Path)
    ap.add_argument("--viz", type=Path)
    ap.add_argument("--skip-synth", action="store_true")
    args = ap.parse_args()
    cv2.setNumThreads(1)
    conf = VpConf()
    if not args.skip_synth:
        for clutter in (0.3, 0.6):
            print(f"synthetic renders, clutter {clutter}:", synthetic(conf, clutter=clutter))
        print("clutter only (no Manhattan lines):", synthetic(conf, lines=False))
    scenes = sorted(p for p in args.strecha.iterdir() if (p / "sparse").is_dir())
    rec = pycolmap.Reconstruction(str(scenes[0] / "sparse"))
    img = sorted(rec.images.values(), key=lambda i: i.name)[0]
    t = timing(scenes[0] / "images" / img.name, rec.cameras[img.camera_id], conf)
    print(f"refine_directions on 1536x1024: {t[0] * 1000:.1f} ms median, {t[1] * 1000:.1f} ms "
          "min of 7")
    for scene in scenes:
        print(scene.name, strecha(scene, conf, args.viz))


if __name__ == "__main__":
    main()
