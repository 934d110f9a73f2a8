#!/usr/bin/env python
"""Whole-CLI extraction cost: `rectified-colmap extract` beside plain COLMAP SIFT.

Each method runs as its own process on the same image folder, into a new COLMAP database,
one after the other, single-threaded (one worker, one SIFT thread, one network thread), as
a user would run it:

- ``pycolmap``: ``pycolmap.extract_features`` (COLMAP SIFT, CPU, ``num_threads=1``), the
  plain baseline with the same budget;
- ``colmap``: ``colmap feature_extractor --SiftExtraction.use_gpu 0 --num_threads 1``
  where the ``colmap`` executable is installed;
- ``rectified``: ``rectified-colmap extract`` with the default configuration and the
  embedded network (``--conf`` / ``--orientation`` to compare others).

Everything a user waits for is counted: start-up and imports, decoding, camera setup, the
network, SIFT, writing. Columns per image: CPU seconds of the process and its children
(``os.wait4``; on a shared machine CPU seconds leave out the time waiting for a core, wall
seconds do not), wall seconds, the process's peak resident memory, keypoints (from the
database). ``ratio`` divides by the ``pycolmap`` row of the same run. Each method also runs
on the first image alone: ``start-up s`` (CPU seconds of that run less one image's) and
``CPU s / image after`` ((CPU of all - CPU of the first alone) / (N - 1)) split off what a
long run amortises; ``ratio after`` compares the latter (the steady state of a folder of
hundreds of photos). ``--num_workers 1 2`` runs ``rectified`` once per worker count
(``rectified xN`` rows): ``peak MB`` is then the largest single process (``ru_maxrss``),
``tree MB`` the peak of the summed resident memory of the process and its children
(sampled from /proc every 0.1 s).

``--rounds N`` runs every method N times, in alternating order (forward, backward, ...), so
that a drift of the machine's speed falls on all methods alike: each column is then the
median over the rounds, ``CPU ratio`` the median of the rounds' ratios (each round's
method against the ``pycolmap`` run of the same round) and ``CPU ratio range`` their
smallest and largest (on a 2-core machine one run's ratio moves by 10 % or more).

    python scripts/bench_cli.py --image_path ../shared/data/strecha-dev/fountain-P11/images \\
        --max_images 6 --camera_params 1379.74,1382.08,760.095,503.155
    python scripts/bench_cli.py ... --resize 3072x2048      # upscaled copies
    python scripts/bench_cli.py --synthetic 6               # rendered streets (PNG)
    python scripts/bench_cli.py --synthetic 6 --depth_files # ... with their exact depth
    python scripts/bench_cli.py ... --methods pycolmap rectified --num_workers 1 2
    python scripts/bench_cli.py ... --resize 640x480 --rounds 5   # medians of 5 rounds
"""

from __future__ import annotations

import argparse
import os
import shutil
import sqlite3
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import cv2
import numpy as np

from rectified_colmap.errors import run_script
from rectified_colmap.io.images import image_size, list_images

PLAIN = """
import sys, pycolmap
db, images, n, names = sys.argv[1], sys.argv[2], int(sys.argv[3]), sys.argv[4].split(",")
opts = pycolmap.FeatureExtractionOptions()
opts.num_threads = 1
opts.sift.max_num_features = n
pycolmap.extract_features(db, images, image_names=names, extraction_options=opts,
                          device=pycolmap.Device.cpu)
"""


def tree_rss_mb(root: int) -> float:
    """Summed resident memory (MiB) of process ``root`` and its descendants (/proc)."""
    parent, rss = {}, {}
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            stat = (d / "stat").read_text()
            statm = (d / "statm").read_text().split()
        except OSError:  # the process ended meanwhile
            continue
        parent[int(d.name)] = int(stat[stat.rindex(")") + 2 :].split()[1])
        rss[int(d.name)] = int(statm[1]) * os.sysconf("SC_PAGE_SIZE")
    tree, todo = set(), [root]
    while todo:
        pid = todo.pop()
        tree.add(pid)
        todo += [c for c, pp in parent.items() if pp == pid and c not in tree]
    return sum(rss.get(pid, 0) for pid in tree) / 2**20


def run_measured(cmd: list[str], env: dict | None = None) -> dict:
    """Run ``cmd``; its wall seconds, CPU seconds (user + system, with its children), peak
    resident memory of its largest process and peak of the summed resident memory of its
    process tree (MiB). Raises with its output when it fails."""
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, env=env)
    peak_tree = [0.0]
    done = threading.Event()

    def sample():
        while not done.wait(0.1):
            peak_tree[0] = max(peak_tree[0], tree_rss_mb(proc.pid))

    sampler = threading.Thread(target=sample, daemon=True)
    sampler.start()
    out = proc.stdout.read()
    done.set()
    sampler.join()
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t0
    proc.returncode = os.waitstatus_to_exitcode(status)
    if proc.returncode != 0:
        raise RuntimeError(f"{cmd[0]} failed ({proc.returncode}):\n{out.decode()[-3000:]}")
    return {
        "wall": wall,
        "cpu": usage.ru_utime + usage.ru_stime,
        "peak_MB": usage.ru_maxrss / 1024,
        "tree_MB": peak_tree[0],
    }


def keypoints_per_image(database: Path) -> float:
    with sqlite3.connect(database) as con:
        rows = con.execute("SELECT rows FROM keypoints").fetchall()
    return float(np.mean([r[0] for r in rows])) if rows else 0.0


def prepare_images(args, folder: Path) -> list[str]:
    """The benchmark's images in ``folder`` (copies, resized copies or renders)."""
    if args.synthetic:
        from rectified_colmap_research import synth

        rng = np.random.default_rng(args.seed)
        w, h = (int(v) for v in args.size.split("x"))
        names = []
        for i in range(args.synthetic):
            scene = synth.street(rng)
            camera = synth.pinhole_camera(w, h, 0.9 * w)
            r = synth.render(scene, camera, synth.random_view(scene, rng, camera))
            names.append(f"street_{i:03d}.png")
            cv2.imwrite(str(folder / names[-1]), r.image[:, :, ::-1])
            if args.depth_files:  # beside the images: <name>.npy, metric depth
                depth = folder.parent / "depth"
                depth.mkdir(exist_ok=True)
                np.save(depth / f"{names[-1]}.npy", r.depth.astype(np.float32))
        return names
    names = list_images(Path(args.image_path))[: args.max_images]
    for name in names:
        (folder / name).parent.mkdir(parents=True, exist_ok=True)
        if args.resize:
            w, h = (int(v) for v in args.resize.split("x"))
            img = cv2.imread(str(Path(args.image_path) / name), cv2.IMREAD_COLOR)
            cv2.imwrite(
                str(folder / name),
                cv2.resize(img, (w, h), interpolation=cv2.INTER_CUBIC),
                [cv2.IMWRITE_JPEG_QUALITY, 95],
            )
        else:
            shutil.copy(Path(args.image_path) / name, folder / name)
    return names


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--image_path", type=Path)
    p.add_argument("--max_images", type=int, default=6)
    p.add_argument("--resize", help="resize copies of the photos to WxH first (JPEG q95)")
    p.add_argument("--synthetic", type=int, default=0, help="render N street views instead")
    p.add_argument("--size", default="1536x1024", help="rendered image size WxH")
    p.add_argument(
        "--depth_files",
        action="store_true",
        help="with --synthetic: write each render's exact depth (.npy) and run "
        "rectified-colmap with --depth_path (no network)",
    )
    p.add_argument("--seed", type=int, default=0)
    p.add_argument(
        "--camera_params",
        help="passed to rectified-colmap (PINHOLE fx,fy,cx,cy "
        "of the original size; scaled with --resize)",
    )
    p.add_argument("--max_num_features", type=int, default=8192)
    p.add_argument("--conf", help="--conf of rectified-colmap (default: its default)")
    p.add_argument("--orientation", help="--orientation of rectified-colmap")
    p.add_argument(
        "--num_workers",
        type=int,
        nargs="+",
        help="run rectified once per worker count (default: once, with its default)",
    )
    p.add_argument(
        "--methods",
        nargs="+",
        default=["pycolmap", "colmap", "rectified"],
        choices=["pycolmap", "colmap", "rectified"],
    )
    p.add_argument(
        "--rounds",
        type=int,
        default=1,
        help="run every method this many times, in alternating order; columns are medians",
    )
    args = p.parse_args(argv)
    if not args.synthetic and args.image_path is None:
        p.error("--image_path or --synthetic")
    if args.depth_files and not args.synthetic:
        p.error("--depth_files needs --synthetic")
    if args.rounds < 1:
        p.error("--rounds must be at least 1")
    return args


def build_runs(args, tmp: Path, images: Path, names: list[str], size) -> list[tuple]:
    """(name, command, command on the first image alone) per measured method; ``None`` in
    a command stands for its database path."""
    n = args.max_num_features
    cmds = {
        "pycolmap": [sys.executable, "-c", PLAIN, None, str(images), str(n), ",".join(names)],
        "colmap": [
            "colmap",
            "feature_extractor",
            "--database_path",
            None,
            "--image_path",
            str(images),
            "--SiftExtraction.use_gpu",
            "0",
            "--SiftExtraction.num_threads",
            "1",
            "--SiftExtraction.max_num_features",
            str(n),
        ],
        "rectified": [
            "rectified-colmap",
            "extract",
            "--database",
            None,
            "--image_path",
            str(images),
            "--max_num_features",
            str(n),
            "--no_progress",
        ],
    }
    if args.camera_params:
        params = [float(v) for v in args.camera_params.split(",")]
        if args.resize and args.image_path:
            w0, _ = image_size(Path(args.image_path) / names[0])
            params = [v * size[0] / w0 for v in params]
        cmds["rectified"] += [
            "--camera_model",
            "PINHOLE",
            "--camera_params",
            ",".join(f"{v:.6g}" for v in params),
        ]
    if args.depth_files:
        cmds["rectified"] += ["--depth_path", str(tmp / "depth")]
    for flag in ("conf", "orientation"):
        if getattr(args, flag):
            cmds["rectified"] += [f"--{flag}", getattr(args, flag)]
    if shutil.which("colmap") is None and "colmap" in args.methods:
        print("colmap executable not found: skipping that row", file=sys.stderr)
        args.methods.remove("colmap")

    first = tmp / "first.txt"
    first.write_text(names[0] + "\n")
    alone = {  # the same command on the first image only
        "pycolmap": lambda c: c[:-1] + [names[0]],
        "colmap": lambda c: c + ["--image_list_path", str(first)],
        "rectified": lambda c: c + ["--image_list", str(first)],
    }
    runs = []
    for method in args.methods:
        if method == "rectified" and args.num_workers:
            for w in args.num_workers:
                command = cmds[method] + ["--num_workers", str(w)]
                runs.append((f"rectified x{w}", command, alone[method](command)))
        else:
            runs.append((method, cmds[method], alone[method](cmds[method])))
    return runs


def measure(runs: list[tuple], tmp: Path, n_images: int, env: dict, rounds: int) -> dict:
    """name -> one measured row per round (``run_measured`` plus keypoints per image and,
    with more than one image, ``after`` / ``startup``). Odd rounds run the methods in
    reverse order."""
    out: dict[str, list[dict]] = {name: [] for name, _, _ in runs}
    for r in range(rounds):
        order = list(enumerate(runs))
        for i, (name, command, command_first) in order[:: -1 if r % 2 else 1]:
            db, db_first = tmp / f"run{r}_{i}.db", tmp / f"run{r}_{i}_first.db"
            cmd = [db.as_posix() if c is None else c for c in command]
            row = run_measured(cmd, env) | {"kp": keypoints_per_image(db)}
            if n_images > 1:
                cmd = [db_first.as_posix() if c is None else c for c in command_first]
                one = run_measured(cmd, env)["cpu"]
                row["after"] = (row["cpu"] - one) / (n_images - 1)
                row["startup"] = one - row["after"]
            out[name].append(row)
            print(f"{name}, round {r + 1}: {row['wall']:.1f} s wall", file=sys.stderr, flush=True)
    return out


def summarise(measured: dict[str, list[dict]], base: str = "pycolmap") -> dict[str, dict]:
    """name -> the median of each measured value over the rounds, and ``ratios``: each
    round's CPU ratio to ``base`` in the same round (empty without ``base``)."""
    rows = {}
    for name, per_round in measured.items():
        row = {k: float(np.median([r[k] for r in per_round])) for k in per_round[0]}
        row["ratios"] = [r["cpu"] / b["cpu"] for r, b in zip(per_round, measured.get(base, []))]
        rows[name] = row
    return rows


def print_table(rows: dict[str, dict], k: int) -> None:
    """The markdown table of ``summarise``'s rows, per image of ``k``."""
    print(
        "| method | CPU s / image | wall s / image | CPU ratio | CPU ratio range | wall ratio "
        "| start-up s | CPU s / image after | ratio after | peak MB | tree MB "
        "| keypoints / image |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    base = rows.get("pycolmap")
    for method, r in rows.items():
        ratio = np.median(r["ratios"]) if r["ratios"] else None  # of the rounds' ratios
        cpu_ratio = f"{ratio:.2f}x" if ratio is not None else "-"
        wall_ratio = f"{r['wall'] / base['wall']:.2f}x" if base else "-"
        span = f"{min(r['ratios']):.2f}-{max(r['ratios']):.2f}x" if r["ratios"] else "-"
        after, startup, after_ratio = "-", "-", "-"
        if "after" in r:
            after, startup = f"{r['after']:.2f}", f"{r['startup']:.2f}"
            if base:
                after_ratio = f"{r['after'] / base['after']:.2f}x"
        print(
            f"| {method} | {r['cpu'] / k:.2f} | {r['wall'] / k:.2f} | {cpu_ratio} | {span} "
            f"| {wall_ratio} | {startup} | {after} | {after_ratio} | {r['peak_MB']:.0f} "
            f"| {r['tree_MB']:.0f} | {r['kp']:.0f} |"
        )


def main(argv=None):
    args = parse_args(argv)
    if "rectified" in args.methods and shutil.which("rectified-colmap") is None:
        # before any run: the console script is what is measured, as a user runs it
        raise ValueError("rectified-colmap is not on PATH: activate its environment")
    env = dict(os.environ, OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1")
    tmp = Path(tempfile.mkdtemp(prefix="bench_cli_"))
    try:
        images = tmp / "images"
        images.mkdir()
        names = prepare_images(args, images)
        size = image_size(images / names[0])
        runs = build_runs(args, tmp, images, names, size)
        rows = summarise(measure(runs, tmp, len(names), env, args.rounds))
    finally:
        shutil.rmtree(tmp, ignore_errors=True)

    what = f"{args.synthetic} rendered streets" if args.synthetic else f"{len(names)} images"
    if args.depth_files:
        what += " with depth files"
    if args.rounds > 1:
        what += f", medians of {args.rounds} rounds"
    with open("/proc/loadavg") as f:
        load = f.read().split()[0]
    n = args.max_num_features
    print(f"\n{what}, {size[0]}x{size[1]}, budget {n}; load average at end {load}\n")
    print_table(rows, len(names))


if __name__ == "__main__":
    sys.exit(run_script(main, "bench_cli"))
