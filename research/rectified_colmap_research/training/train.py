"""Training loop pieces: optimiser, schedule, one step, checkpoints (torch)."""

from __future__ import annotations

import logging
import math
from pathlib import Path

import torch

from .losses import total_loss
from .model import freeze_batchnorm

logger = logging.getLogger(__name__)


def make_optimizer(
    model, lr: float, encoder_lr_factor: float = 0.5, weight_decay: float = 1e-4
) -> torch.optim.Optimizer:
    enc = list(model.encoder.parameters())
    ids = {id(p) for p in enc}
    rest = [p for p in model.parameters() if id(p) not in ids]
    return torch.optim.AdamW(
        [
            {"params": enc, "lr": lr * encoder_lr_factor, "base": encoder_lr_factor},
            {"params": rest, "lr": lr, "base": 1.0},
        ],
        lr=lr,
        weight_decay=weight_decay,
    )


def lr_factor(progress: float, warmup: float = 0.03) -> float:
    """Linear warm-up then cosine decay to 5 %, for progress in [0, 1]."""
    if progress < warmup:
        return max(progress / warmup, 0.02)
    t = min((progress - warmup) / (1 - warmup), 1.0)
    return 0.05 + 0.95 * 0.5 * (1 + math.cos(math.pi * t))


def set_lr(opt, lr: float) -> None:
    for g in opt.param_groups:
        g["lr"] = lr * g.get("base", 1.0)


def train_step(
    model, batch: dict, opt, weights: dict | None = None, amp_dtype=None, freeze_bn=False
) -> tuple[float, dict]:
    """One optimiser step. ``amp_dtype`` (e.g. torch.bfloat16 on a GPU): the network runs
    under autocast, the losses in float32. ``freeze_bn``: BatchNorm in eval mode, fixed
    (:func:`~rectified_colmap_research.training.model.freeze_batchnorm`)."""
    model.train()
    if freeze_bn:
        freeze_batchnorm(model)
    with torch.autocast(batch["image"].device.type, amp_dtype, enabled=amp_dtype is not None):
        pred_log, sky_logit = model.forward_train(batch["image"])
    pred_log = pred_log.float()
    sky_logit = None if sky_logit is None else sky_logit.float()
    loss, parts = total_loss(pred_log, batch, sky_logit=sky_logit, **(weights or {}))
    opt.zero_grad(set_to_none=True)
    loss.backward()
    torch.nn.utils.clip_grad_norm_(model.parameters(), 1.0)
    opt.step()
    return float(loss.detach()), parts


@torch.no_grad()
def eval_loss(model, items: list[dict], weights: dict | None = None, batch: int = 8, device="cpu"):
    """Mean losses of ``items`` (dataset items, e.g. a fixed probe set) with the network
    in eval mode -> {"loss": ..., part: ...}, each weighted by item count."""
    model.eval()
    tot: dict[str, float] = {}
    for i in range(0, len(items), batch):
        chunk = items[i : i + batch]
        b = {k: torch.stack([it[k] for it in chunk]).to(device) for k in chunk[0]}
        pred_log, sky_logit = model.forward_train(b["image"])
        sky_logit = None if sky_logit is None else sky_logit.float()
        loss, parts = total_loss(pred_log.float(), b, sky_logit=sky_logit, **(weights or {}))
        for k, v in {"loss": float(loss), **parts}.items():
            tot[k] = tot.get(k, 0.0) + v * len(chunk)
    return {k: v / len(items) for k, v in tot.items()}


def save_checkpoint(path: str | Path, model, opt, step: int, width: int, extra: dict | None = None):
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp")
    torch.save(
        {
            "model": model.state_dict(),
            "opt": opt.state_dict(),
            "step": step,
            "width": width,
            "sky": bool(getattr(model, "has_sky", False)),
            **(extra or {}),
        },
        tmp,
    )
    tmp.replace(path)
