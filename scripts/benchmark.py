#!/usr/bin/env python
"""Speed of rectified SIFT beside plain COLMAP SIFT and OpenCV's ASIFT, in the same run.

Prints, per image and on average, the time of each stage of rectified SIFT (depth network,
normals, planes, homographies, plain SIFT on non-planar pixels, warps + SIFT in patches),
the total, plain pycolmap SIFT on the same image, and cv2.AffineFeature(SIFT) (ASIFT, the
view-synthesis anchor). Every method runs single-threaded in this process, one after the
other on each image, so the ratios are comparable even on a noisy machine.

    python scripts/benchmark.py --image_path ../shared/data/strecha-dev/fountain-P11/images \
        --camera_params 1382,1382,768,512 [--depth_path D | --depth_model rectsift-lite0]
    python scripts/benchmark.py --synthetic 6          # rendered street scenes, GT depth
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(var, "1")

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from rectified_colmap import camera as cam_utils  # noqa: E402
from rectified_colmap.config import ExtractConf, confs  # noqa: E402
from rectified_colmap.depth import DepthMap  # noqa: E402
from rectified_colmap.extract import list_images, read_image  # noqa: E402
from rectified_colmap.features import detect_sift  # noqa: E402
from rectified_colmap.pipeline import extract_image  # noqa: E402


def synthetic_inputs(n: int, width: int, height: int, seed: int):
    from rectified_colmap import synth

    rng = np.random.default_rng(seed)
    for i in range(n):
        scene = synth.street(rng)
        camera = synth.pinhole_camera(width, height, 0.9 * width)
        pose = synth.random_view(scene, rng, camera)
        r = synth.render(scene, camera, pose)
        yield f"synthetic_{i:03d}", r.image, camera, DepthMap(r.depth, "metric")


def folder_inputs(args):
    names = list_images(args.image_path, args.image_list)[: args.max_images]
    files = network = None
    if args.depth_path:
        from rectified_colmap.depth.files import FileDepthSource

        files = FileDepthSource(args.depth_path)
    if args.depth_model != "none":
        from rectified_colmap.depth.registry import load_depth_source

        network = load_depth_source(args.depth_model, num_threads=1)
    for name in names:
        rgb = read_image(args.image_path / name)
        h, w = rgb.shape[:2]
        if args.camera_params:
            camera = cam_utils.make_camera(args.camera_model,
                                           cam_utils.parse_camera_params(args.camera_params),
                                           w, h)
        else:
            camera, _ = cam_utils.infer_camera(args.image_path / name)
        depth, t_depth = None, 0.0
        if files is not None:
            depth = files(rgb, camera, name)
        if depth is None and network is not None:
            t0 = time.perf_counter()
            depth = network(rgb, camera, name)
            t_depth = time.perf_counter() - t0
        yield name, rgb, camera, depth, t_depth


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--image_path", type=Path)
    p.add_argument("--image_list", type=Path)
    p.add_argument("--depth_path", type=Path)
    p.add_argument("--depth_model", default="rectsift-lite0")
    p.add_argument("--camera_model", default="PINHOLE")
    p.add_argument("--camera_params")
    p.add_argument("--max_images", type=int, default=5)
    p.add_argument("--synthetic", type=int, default=0, help="render N street scenes instead")
    p.add_argument("--size", default="1536x1024", help="synthetic image size WxH")
    p.add_argument("--conf", default="rectsift", choices=sorted(confs))
    p.add_argument("--no_asift", action="store_true", help="skip the (slow) ASIFT anchor")
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    cv2.setNumThreads(1)
    conf = ExtractConf.from_dict(confs[args.conf])

    if args.synthetic:
        w, h = (int(v) for v in args.size.split("x"))
        inputs = ((n, img, cam, d, 0.0) for n, img, cam, d in
                  synthetic_inputs(args.synthetic, w, h, args.seed))
    elif args.image_path:
        inputs = folder_inputs(args)
    else:
        p.error("give --image_path or --synthetic N")

    stages = ["depth", "normals", "planes", "homographies", "sift_plain", "warps+sift_patches"]
    cols = stages + ["rect_geom", "rect_total", "plain_sift", "ratio", "asift", "kp_rect",
                     "kp_plain", "patches"]
    rows = []
    print("| image | WxH | " + " | ".join(cols) + " |")
    print("|" + "---|" * (len(cols) + 2))
    for name, rgb, camera, depth, t_depth in inputs:
        gray = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
        detect_sift(gray[:64, :64], conf.sift)  # warm the extractor cache
        t0 = time.perf_counter()
        plain = detect_sift(gray, conf.sift)
        t_plain = time.perf_counter() - t0
        t0 = time.perf_counter()
        res = extract_image(rgb, camera, depth, conf)
        t_rect = time.perf_counter() - t0
        t_asift, n_asift = float("nan"), 0
        if not args.no_asift:
            asift = cv2.AffineFeature.create(cv2.SIFT.create(nfeatures=conf.sift.max_num_features))
            t0 = time.perf_counter()
            kp = asift.detect(gray, None)
            kp, _ = asift.compute(gray, kp)
            t_asift, n_asift = time.perf_counter() - t0, len(kp)
        tm = dict(res.timings, depth=t_depth)
        row = {s: tm.get(s, 0.0) for s in stages}
        row["rect_geom"] = sum(tm.get(s, 0.0) for s in ("normals", "planes", "homographies"))
        row["rect_total"] = t_rect + t_depth
        row["plain_sift"] = t_plain
        row["ratio"] = (t_rect + t_depth) / t_plain
        row["asift"] = t_asift
        row["kp_rect"] = len(res.features)
        row["kp_plain"] = len(plain)
        row["patches"] = len(res.rectifications)
        rows.append(row)
        fmt = [f"{row[c]:.3f}" if isinstance(row[c], float) else str(row[c]) for c in cols]
        print(f"| {name} | {camera.width}x{camera.height} | " + " | ".join(fmt) + " |")
        sys.stdout.flush()
    if rows:
        mean = {c: float(np.nanmean([r[c] for r in rows])) for c in cols}
        fmt = [f"{mean[c]:.3f}" for c in cols]
        print(f"| **mean** ({len(rows)}) | | " + " | ".join(fmt) + " |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
