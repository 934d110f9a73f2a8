"""Throughput of `extract` with 1 and 2 workers: local processes, Ray actors, shards.

    python scripts/bench_scaleout.py --images DIR [--num_images 16] [--out /tmp/scaleout]
    python scripts/bench_scaleout.py --render 16      # a rendered street, 640x480

Every configuration extracts the same images into fresh outputs with the default
configuration (embedded depth network) and must give outputs identical to the first
(checked); prints images per second while extracting (after imports and, for Ray, after
the cluster started) and the whole command's wall time.
"""

from __future__ import annotations

import argparse
import sys
import shutil
import sqlite3
import time
from pathlib import Path

from rectified_colmap.errors import run_script


def features(db: Path) -> dict:
    con = sqlite3.connect(db)
    try:
        return {
            r[0]: r[1:]
            for r in con.execute(
                "SELECT i.name, k.data, d.data FROM images i JOIN keypoints k USING(image_id) "
                "JOIN descriptors d USING(image_id)"
            )
        }
    finally:
        con.close()


def main() -> None:
    from rectified_colmap.extraction import extract
    from rectified_colmap.io.images import list_images

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--images", type=Path)
    ap.add_argument("--render", type=int, default=0, help="render this many street images")
    ap.add_argument("--num_images", type=int, default=16)
    ap.add_argument("--out", type=Path, default=Path("/tmp/scaleout"))
    ap.add_argument("--configs", default="local1,local2,ray1,ray2,shards2")
    args = ap.parse_args()
    shutil.rmtree(args.out, ignore_errors=True)
    args.out.mkdir(parents=True)
    cams = {}  # ReaderConf's camera keys
    if args.render:
        from rectified_colmap.demo import render_walk

        images = args.out / "images"
        _, camera, _ = render_walk(images, num_images=args.render)
        cams = dict(
            camera_model="PINHOLE",
            single_camera=True,
            camera_params=",".join(map(str, camera.params)),
        )
    else:
        images = args.images
    names = list_images(images)[: args.num_images]
    rows, reference = [], None
    for config in args.configs.split(","):
        out = args.out / config
        workers = int(config[-1])
        t0 = time.perf_counter()
        if config.startswith("shards"):
            from rectified_colmap.io.merge import merge_databases

            work = 0.0
            for i in range(workers):  # one after the other: each shard's own throughput
                s = extract(
                    images,
                    database=out / f"s{i}.db",
                    reader={"image_list": names, **cams},
                    run={"shard": (i, workers), "progress": False},
                )
                work = max(work, s.work_seconds)
            merge_databases(
                out / "db.db", [out / f"s{i}.db" for i in range(workers)], single_camera=bool(cams)
            )
            ips = len(names) / work  # shards run side by side on separate machines
        else:
            s = extract(
                images,
                database=out / "db.db",
                reader={"image_list": names, **cams},
                run={
                    "progress": False,
                    "num_workers": workers,
                    "ray_address": "local" if "ray" in config else None,
                },
            )
            assert s.ok, s.report()
            ips = len(s.done) / s.work_seconds
        wall = time.perf_counter() - t0
        feats = features(out / "db.db")
        reference = reference or feats
        same = feats == reference
        rows.append((config, ips, wall, same))
        print(f"{config}: {ips:.2f} images/s, {wall:.1f} s, identical: {same}", flush=True)
    print(f"\n{len(names)} images from {images}\n")
    print("| run | workers | images/s while extracting | whole command (s) | outputs identical |")
    print("|---|---|---|---|---|")
    for config, ips, wall, same in rows:
        kind = {
            "local": "local processes",
            "ray": "Ray, local instance",
            "shards": "shards (largest shard; run side by side)",
        }[config.rstrip("0123456789")]
        print(f"| {kind} | {config[-1]} | {ips:.2f} | {wall:.1f} | {'yes' if same else 'NO'} |")


if __name__ == "__main__":
    sys.exit(run_script(main, "bench_scaleout"))
