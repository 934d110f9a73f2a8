#!/usr/bin/env python
"""Speed and memory of rectified SIFT beside plain COLMAP SIFT, in the same run.

For each image, in this one process, single-threaded, one method after the other:

- plain pycolmap SIFT with the full budget (``detect_sift``, exactly one COLMAP call). It
  runs twice: ``plain_cold`` is the first call (a new extractor allocates its scale space),
  ``plain_sift`` the second (the extractor's scale space reused, as COLMAP's extractor does
  on a folder of same-size photos). Ratios divide by ``plain_sift``, the faster one.
- rectified SIFT (``extract_image``, depth network included), with its stages. It runs
  twice as well: ``rect_cold`` is the first call, the stages and ``rect_total`` come from
  the second (the whole image's extractor warm, as the CLI keeps it from one same-size
  photo to the next; patches get new extractors either way).
- optionally OpenCV's ASIFT (``cv2.AffineFeature`` over SIFT, one ``detectAndCompute`` with
  the budget per synthesised view: rectified_colmap_research.evaluation.asift, as
  eval_homography.py runs it), the view-synthesis anchor.

Before each method the SIFT extractors (one ``Sift`` for the run) are released and the
peak resident memory of the process (VmHWM) is reset, so ``plain_MB`` / ``rect_MB`` are the
process's peak during that method (baseline of Python, pycolmap, onnxruntime and the
network included); ``rss_MB`` is the resident memory after the image (flat over many
images: no growth). Ratios are taken
within the same run, so they hold on a noisy machine better than absolute seconds.

Seconds are CPU seconds of this process (``--clock cpu``, the default: everything runs on
one thread, so on a free core they equal wall seconds, and on a shared machine they do not
count the time spent waiting for a core); ``rect_wall`` / ``plain_wall`` are wall seconds
of the same runs. ``--clock wall`` measures every column in wall seconds.

    python scripts/benchmark.py --image_path ../shared/data/strecha-dev/fountain-P11/images \\
        --camera_params 1379.74,1382.08,760.095,503.155 --max_images 4 --no_asift
    python scripts/benchmark.py ... --resize 6000x4000      # upscaled photos (memory)
    python scripts/benchmark.py --synthetic 4 --no_asift    # rendered streets, GT depth
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
import types
from pathlib import Path

for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(var, "1")

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from rectified_colmap import camera as cam_utils  # noqa: E402
from rectified_colmap import pipeline  # noqa: E402
from rectified_colmap.config import (  # noqa: E402
    DEFAULT_DEPTH_MODEL,
    ExtractConf,
    confs,
    merge_conf,
)
from rectified_colmap.depth import DepthMap  # noqa: E402
from rectified_colmap.errors import run_script  # noqa: E402
from rectified_colmap.sift import Sift, detect_sift  # noqa: E402
from rectified_colmap.io.images import list_images, read_image  # noqa: E402
from rectified_colmap.pipeline import extract_image  # noqa: E402
from rectified_colmap_research.evaluation.asift import asift_features  # noqa: E402
from rectified_colmap_research.memory import retain_freed_memory  # noqa: E402

STAGES = ["depth", "normals", "planes", "homographies", "sift_plain", "warps+sift_patches", "dedup"]
COLUMNS = STAGES + [
    "other",
    "rect_total",
    "rect_cold",
    "plain_cold",
    "plain_sift",
    "ratio",
    "asift",
    "rect_wall",
    "plain_wall",
    "kp_rect",
    "kp_plain",
    "patches",
    "rect_MB",
    "plain_MB",
    "rss_MB",
]


def memory_mb(field: str = "VmRSS") -> float:
    """Resident (VmRSS) or peak resident (VmHWM) memory of this process in MiB (Linux)."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith(field + ":"):
                    return int(line.split()[1]) / 1024
    except OSError:
        pass
    return float("nan")


def reset_peak() -> None:
    """Reset VmHWM to the current resident memory (Linux >= 4.0; ignored elsewhere)."""
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
    except OSError:
        pass


def synthetic_inputs(n: int, width: int, height: int, seed: int):
    from rectified_colmap_research import synth

    rng = np.random.default_rng(seed)
    for i in range(n):
        scene = synth.street(rng)
        camera = synth.pinhole_camera(width, height, 0.9 * width)
        pose = synth.random_view(scene, rng, camera)
        r = synth.render(scene, camera, pose)
        yield f"synthetic_{i:03d}", r.image, camera, DepthMap(r.depth, "metric"), (0.0, 0.0)


def folder_inputs(args):
    names = list_images(args.image_path, args.image_list)[: args.max_images] * args.repeat
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
            camera = cam_utils.make_camera(
                args.camera_model, cam_utils.parse_camera_params(args.camera_params), w, h
            )
        else:
            camera, _ = cam_utils.infer_camera(args.image_path / name)
        if args.resize:
            W, H = (int(v) for v in args.resize.split("x"))
            rgb = cv2.resize(rgb, (W, H), interpolation=cv2.INTER_CUBIC)
            camera.rescale(W, H)
        yield name, rgb, camera, files, network


class Clock:
    """The benchmark's clock: CPU seconds of this process or wall seconds."""

    perf_counter = staticmethod(time.process_time)


def with_depth(inputs):
    """(name, rgb, camera, files, network) -> (name, rgb, camera, depth, (seconds, wall
    seconds) of the network): depth inference is timed as a stage of rectified SIFT."""
    for name, rgb, camera, files, network in inputs:
        depth, t_depth = None, (0.0, 0.0)
        if files is not None:
            depth = files(rgb, camera, name)
        if depth is None and network is not None:
            w0, t0 = time.perf_counter(), Clock.perf_counter()
            depth = network(rgb, camera, name)
            t_depth = (Clock.perf_counter() - t0, time.perf_counter() - w0)
        yield name, rgb, camera, depth, t_depth


def main(argv=None) -> int:
    p = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("--image_path", type=Path)
    p.add_argument("--image_list", type=Path)
    p.add_argument("--depth_path", type=Path)
    p.add_argument("--depth_model", default=DEFAULT_DEPTH_MODEL)
    p.add_argument("--camera_model", default="PINHOLE")
    p.add_argument("--camera_params", help="for the images' own size (rescaled with --resize)")
    p.add_argument("--max_images", type=int, default=5)
    p.add_argument(
        "--repeat",
        type=int,
        default=1,
        help="go over the images N times (resident memory over many images)",
    )
    p.add_argument("--resize", help="resize photos to WxH first (e.g. 6000x4000)")
    p.add_argument("--synthetic", type=int, default=0, help="render N street scenes instead")
    p.add_argument("--size", default="1536x1024", help="synthetic image size WxH")
    p.add_argument("--conf", default="rectsift", choices=sorted(confs))
    p.add_argument(
        "--coarse_first",
        action="store_true",
        help="coarse_first SIFT in every part of rectified SIFT, whatever the image "
        "size (default: sift.coarse_first where it pays, see config.py)",
    )
    p.add_argument(
        "--exact_sift",
        action="store_true",
        help="exact COLMAP calls in every part (sift.coarse_first off)",
    )
    p.add_argument(
        "--retain_memory",
        action="store_true",
        help="rectified_colmap_research.memory.retain_freed_memory() first (both methods)",
    )
    p.add_argument("--patch_first_octave", type=int, help="override sift.patch_first_octave")
    p.add_argument(
        "--rect_conf",
        help="JSON overrides on top of --conf, e.g. "
        '\'{"sift": {"patch_octave0_pixels_per_feature": 100}}\'',
    )
    p.add_argument("--no_asift", action="store_true", help="skip the (slow) ASIFT anchor")
    p.add_argument(
        "--clock",
        choices=["cpu", "wall"],
        default="cpu",
        help="CPU seconds of this process (default) or wall seconds",
    )
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    cv2.setNumThreads(1)
    if args.retain_memory:
        retain_freed_memory()
    if args.clock == "wall":
        Clock.perf_counter = staticmethod(time.perf_counter)
    # the pipeline's stage timings (wall seconds) on the same clock: its module's time
    pipeline.time = types.SimpleNamespace(perf_counter=Clock.perf_counter)
    overrides = json.loads(args.rect_conf) if args.rect_conf else None
    conf = ExtractConf.from_dict(merge_conf(confs[args.conf], overrides))
    if args.coarse_first and args.exact_sift:
        p.error("--coarse_first or --exact_sift, not both")
    if args.coarse_first or args.exact_sift:
        conf.sift.coarse_first = args.coarse_first
    if args.coarse_first:
        conf.sift.coarse_first_pixels_per_feature = 0.0
    if args.patch_first_octave is not None:
        conf.sift.patch_first_octave = args.patch_first_octave

    if args.synthetic:
        w, h = (int(v) for v in args.size.split("x"))
        inputs = synthetic_inputs(args.synthetic, w, h, args.seed)
    elif args.image_path:
        inputs = with_depth(folder_inputs(args))
    else:
        p.error("give --image_path or --synthetic N")

    print(
        f"# clock: {args.clock}; load average at start: {os.getloadavg()[0]:.2f}; "
        f"RSS {memory_mb():.0f} MB; "
        f"coarse_first={conf.sift.coarse_first} "
        f"(>= {conf.sift.coarse_first_pixels_per_feature:g} px/feature); "
        f"retain_memory={args.retain_memory}; "
        f"patch_first_octave={conf.sift.patch_first_octave} "
        f"(0 from {conf.sift.patch_octave0_pixels_per_feature:g} px/feature); "
        f"rect_conf={overrides}"
    )
    rows, sift = [], Sift()
    print("| image | WxH | " + " | ".join(COLUMNS) + " |")
    print("|" + "---|" * (len(COLUMNS) + 2))
    for name, rgb, camera, depth, (t_depth, w_depth) in inputs:
        gray = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
        clock = Clock.perf_counter
        sift.release()
        reset_peak()
        t0 = clock()
        detect_sift(gray, conf.sift, sift=sift)
        t_cold = clock() - t0
        w0, t0 = time.perf_counter(), clock()
        plain = detect_sift(gray, conf.sift, sift=sift)
        t_plain, w_plain = clock() - t0, time.perf_counter() - w0
        plain_mb = memory_mb("VmHWM")

        sift.release()
        reset_peak()  # the depth network's peak was in the input generator: not counted
        t0 = clock()
        extract_image(rgb, camera, depth, conf, sift=sift)
        t_rect_cold = clock() - t0
        w0, t0 = time.perf_counter(), clock()  # again, as plain_sift: warm extractors
        res = extract_image(rgb, camera, depth, conf, sift=sift)
        t_rect, w_rect = clock() - t0, time.perf_counter() - w0
        rect_mb = memory_mb("VmHWM")

        t_asift = float("nan")
        if not args.no_asift:
            t0 = clock()
            asift_features(gray, conf.sift.max_num_features)
            t_asift = clock() - t0
        tm = dict(res.timings, depth=t_depth)
        row = {s: tm.get(s, 0.0) for s in STAGES}
        row["other"] = t_rect - sum(row[s] for s in STAGES[1:])
        row["rect_total"] = t_rect + t_depth
        row["rect_cold"] = t_rect_cold + t_depth
        row["plain_cold"] = t_cold
        row["plain_sift"] = t_plain
        row["ratio"] = (t_rect + t_depth) / t_plain
        row["asift"] = t_asift
        row["rect_wall"] = w_rect + w_depth
        row["plain_wall"] = w_plain
        row["kp_rect"] = len(res.features)
        row["kp_plain"] = len(plain)
        row["patches"] = len(res.rectifications)
        row["rect_MB"] = rect_mb
        row["plain_MB"] = plain_mb
        row["rss_MB"] = memory_mb()
        rows.append(row)
        fmt = [f"{row[c]:.3f}" if isinstance(row[c], float) else str(row[c]) for c in COLUMNS]
        fmt = [f"{row[c]:.0f}" if c.endswith("_MB") else v for c, v in zip(COLUMNS, fmt)]
        print(f"| {name} | {camera.width}x{camera.height} | " + " | ".join(fmt) + " |")
        sys.stdout.flush()
    if rows:
        mean = {c: float(np.nanmean([r[c] for r in rows])) for c in COLUMNS}
        mean["ratio"] = mean["rect_total"] / mean["plain_sift"]  # ratio of the means
        for c in ("rect_MB", "plain_MB", "rss_MB"):
            mean[c] = max(r[c] for r in rows)
        fmt = [f"{mean[c]:.0f}" if c.endswith("_MB") else f"{mean[c]:.3f}" for c in COLUMNS]
        print(f"| **mean** ({len(rows)}; MB: max) | | " + " | ".join(fmt) + " |")
        print(
            f"# load average at end: {os.getloadavg()[0]:.2f}; live SIFT extractors: {sift.live()}"
        )
    return 0


if __name__ == "__main__":
    sys.exit(run_script(main, "benchmark"))
