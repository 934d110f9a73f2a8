"""Scale-invariant depth losses and a normal loss (torch).

Shapes: ``pred_log`` (B, 1, H, W) predicted log-depth (up to an additive constant, i.e. depth
up to scale); ``depth`` (B, 1, H, W) ground-truth z-depth, invalid (sky) where <= 0 or not
finite; ``normals`` (B, 3, H, W) ground-truth unit normals in the camera frame (x right,
y down, z forward) oriented toward the camera, zero where invalid; ``K`` (B, 3, 3)
intrinsics in the COLMAP pixel convention (pixel [i, j] has centre (j + 0.5, i + 0.5)).

All three losses are exactly zero for a perfect prediction and invariant to adding a
per-image constant to ``pred_log`` (a global scale of the depth).
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from rectified_colmap.conventions import OFFSET


def valid_mask(depth: torch.Tensor) -> torch.Tensor:
    return torch.isfinite(depth) & (depth > 0)


def log_residual(pred_log, depth):
    """(d, mask): d = pred_log - log(depth), 0 where invalid."""
    mask = valid_mask(depth)
    d = torch.where(
        mask,
        pred_log - torch.log(torch.where(mask, depth, torch.ones_like(depth))),
        torch.zeros_like(pred_log),
    )
    return d, mask


def si_log_loss(pred_log, depth, min_points: int = 10):
    """Scale-invariant log loss: per-image variance of the log residual over valid pixels,
    averaged over the images with at least ``min_points`` valid pixels (sparse depth of real
    photos: images without SfM points do not dilute it)."""
    d, mask = log_residual(pred_log, depth)
    m = mask.float()
    cnt = m.sum((1, 2, 3))
    n = cnt.clamp(min=1)
    mean = d.sum((1, 2, 3)) / n
    var = ((d - mean[:, None, None, None]) ** 2 * m).sum((1, 2, 3)) / n
    use = (cnt >= min_points).float()
    return (var * use).sum() / use.sum().clamp(min=1)


def gradient_loss(pred_log, depth, scales: int = 4):
    """Multi-scale gradient matching of the log residual (MiDaS-style, on log-depth)."""
    d, mask = log_residual(pred_log, depth)
    m = mask.float()
    total = pred_log.new_zeros(())
    for k in range(scales):
        if k:
            d, m = d[:, :, ::2, ::2], m[:, :, ::2, ::2]
        mx = m[..., 1:] * m[..., :-1]
        my = m[..., 1:, :] * m[..., :-1, :]
        gx = (d[..., 1:] - d[..., :-1]).abs() * mx
        gy = (d[..., 1:, :] - d[..., :-1, :]).abs() * my
        total = total + (gx.sum() + gy.sum()) / (mx.sum() + my.sum()).clamp(min=1)
    return total / scales


def pixel_rays(K, h: int, w: int):
    """(B, 3, h, w) rays with z = 1 through the pixel centres (COLMAP convention)."""
    dev, dt = K.device, K.dtype
    v, u = torch.meshgrid(
        torch.arange(h, device=dev, dtype=dt) + OFFSET,
        torch.arange(w, device=dev, dtype=dt) + OFFSET,
        indexing="ij",
    )
    x = (u[None] - K[:, 0, 2, None, None]) / K[:, 0, 0, None, None]
    y = (v[None] - K[:, 1, 2, None, None]) / K[:, 1, 1, None, None]
    return torch.stack([x, y, torch.ones_like(x)], 1)


def normals_from_log_depth(pred_log, K):
    """Unit normals (B, 3, H-2, W-2) of the interior pixels from central differences of the
    back-projected points, oriented toward the camera for a surface seen from the front."""
    b, _, h, w = pred_log.shape
    z = torch.exp(pred_log - pred_log.detach().mean((1, 2, 3), keepdim=True))
    pts = pixel_rays(K, h, w) * z
    du = pts[:, :, 1:-1, 2:] - pts[:, :, 1:-1, :-2]
    dv = pts[:, :, 2:, 1:-1] - pts[:, :, :-2, 1:-1]
    n = torch.cross(dv, du, dim=1)
    return n / n.norm(dim=1, keepdim=True).clamp(min=1e-12)


def interior_normal_mask(inv_depth, valid, normals, tol: float = 1e-3):
    """(B, 1, H-2, W-2): valid GT pixels that lie on one plane with their 4 neighbours: same
    normal, and inverse depth (affine on a plane) equal to the mean of each opposite pair."""
    ok = (
        valid[:, :, 1:-1, 1:-1]
        & valid[:, :, 1:-1, 2:]
        & valid[:, :, 1:-1, :-2]
        & valid[:, :, 2:, 1:-1]
        & valid[:, :, :-2, 1:-1]
    )
    c = normals[:, :, 1:-1, 1:-1]
    for nb in (
        normals[:, :, 1:-1, 2:],
        normals[:, :, 1:-1, :-2],
        normals[:, :, 2:, 1:-1],
        normals[:, :, :-2, 1:-1],
    ):
        ok = ok & ((c * nb).sum(1, keepdim=True) > 0.999)
    q = inv_depth[:, :, 1:-1, 1:-1]
    for a, b in (
        (inv_depth[:, :, 1:-1, 2:], inv_depth[:, :, 1:-1, :-2]),
        (inv_depth[:, :, 2:, 1:-1], inv_depth[:, :, :-2, 1:-1]),
    ):
        ok = ok & ((a + b - 2 * q).abs() <= tol * q.abs())
    return ok


def downsample_level(pred_log, inv_depth, valid, normals, K):
    """Halve the resolution exactly for planes: inverse depth (affine in the pixel
    coordinates on a plane) is 2x2-averaged, so the coarse value is the one at the block
    centre, i.e. at the coarse pixel centre with K/2. GT normals: block mean, kept only
    where the 4 pixels are valid and share one normal."""
    inv = F.avg_pool2d(torch.exp(-(pred_log - pred_log.detach().mean((1, 2, 3), keepdim=True))), 2)
    pred_log = -torch.log(inv.clamp(min=1e-12))
    nm = F.avg_pool2d(normals, 2)
    norm = nm.norm(dim=1, keepdim=True)
    valid = (-F.max_pool2d(-valid.float(), 2) > 0.5) & (norm > 0.9995)
    normals = torch.where(valid, nm / norm.clamp(min=1e-12), torch.zeros_like(nm))
    inv_depth = F.avg_pool2d(inv_depth, 2)
    K = K.clone()
    K[:, :2] = K[:, :2] / 2
    return pred_log, inv_depth, valid, normals, K


def normal_loss(pred_log, depth, normals, K, scales: int = 2, pred_normals=None):
    """Mean (1 - cos) between normals of the predicted depth and GT normals on planar GT
    pixels, at ``scales`` resolutions (see :func:`downsample_level`). ``pred_normals``:
    ``normals_from_log_depth(pred_log, K)`` when the caller has it already (full scale)."""
    total = pred_log.new_zeros(())
    valid = valid_mask(depth)
    inv_depth = torch.where(
        valid, 1.0 / torch.where(valid, depth, torch.ones_like(depth)), torch.zeros_like(depth)
    )
    for k in range(scales):
        if k:
            pred_log, inv_depth, valid, normals, K = downsample_level(
                pred_log, inv_depth, valid, normals, K
            )
        n = pred_normals if k == 0 and pred_normals is not None else None
        if n is None:
            n = normals_from_log_depth(pred_log, K)
        mask = interior_normal_mask(inv_depth, valid, normals).float()
        cos = (n * normals[:, :, 1:-1, 1:-1]).sum(1, keepdim=True)
        total = total + ((1 - cos) * mask).sum() / mask.sum().clamp(min=1)
    return total / scales


def label_normal_loss(pred_log, normals, K, real, pred_normals=None):
    """Mean (1 - cos) between normals of the predicted depth and LABEL normals (real photos:
    line-support planes of the Manhattan frame), on the labelled pixels of the images with
    ``real`` (B,) > 0. Zero when nothing is labelled. ``pred_normals``: as in
    :func:`normal_loss`."""
    n = normals_from_log_depth(pred_log, K) if pred_normals is None else pred_normals
    lab = normals[:, :, 1:-1, 1:-1]
    mask = ((lab.abs().sum(1, keepdim=True) > 0) & (real[:, None, None, None] > 0)).float()
    cos = (n * lab).sum(1, keepdim=True)
    return ((1 - cos) * mask).sum() / mask.sum().clamp(min=1)


def frame_axis_loss(pred_log, frame, K, sky=None, max_angle_deg: float = 30.0, pred_normals=None):
    """Mean (1 - max_k |cos(n, d_k)|): how far the normals of the predicted depth are from
    the nearest axis d_k of each image's Manhattan frame ``frame`` (B, 3, 3) (rows: unit
    directions; NaN: no frame, the image does not count).

    Only on pixels whose predicted normal is already within ``max_angle_deg`` of an axis (the
    gate is not differentiated): planar surfaces of a Manhattan scene lie on its axes, while
    trees, cars and people, far from every axis, are left alone. Pixels labelled sky in
    ``sky`` (B, 1, H, W; 1 = sky) never count. Zero when nothing counts. ``pred_normals``:
    as in :func:`normal_loss`."""
    n = normals_from_log_depth(pred_log, K) if pred_normals is None else pred_normals
    has = torch.isfinite(frame).all(2).all(1)
    cos = torch.einsum("bkc,bchw->bkhw", torch.nan_to_num(frame), n).abs().amax(1, keepdim=True)
    gate = (cos.detach() >= math.cos(math.radians(max_angle_deg))) & has[:, None, None, None]
    if sky is not None:
        gate = gate & (sky[:, :, 1:-1, 1:-1] != 1)
    gate = gate.float()
    return ((1 - cos) * gate).sum() / gate.sum().clamp(min=1)


def sky_loss(sky_logit, sky):
    """Binary cross-entropy of the sky logit (B, 1, H, W) against ``sky`` (B, 1, H, W):
    1 sky, 0 not sky, 255 unknown (ignored)."""
    known = (sky != 255).float()
    target = (sky == 1).float()
    bce = F.binary_cross_entropy_with_logits(sky_logit, target, reduction="none")
    return (bce * known).sum() / known.sum().clamp(min=1)


def total_loss(
    pred_log,
    batch,
    w_si: float = 1.0,
    w_grad: float = 1.0,
    w_normal: float = 1.0,
    w_lines: float = 1.0,
    w_sky: float = 0.5,
    sky_logit=None,
    w_axis: float = 0.0,
) -> tuple[torch.Tensor, dict[str, float]]:
    """Weighted sum of the losses -> (loss, parts as floats). Batches with ``real`` (B,)
    and ``sky`` (B, 1, H, W) (training.data) add the label-normal loss on real photos and,
    given ``sky_logit``, the sky loss; with ``frame`` (B, 3, 3) and ``w_axis`` > 0, the
    frame-axis loss."""
    depth, normals, K = batch["depth"], batch["normals"], batch["K"]
    n = normals_from_log_depth(pred_log, K)  # once for the three normal losses
    parts = {
        "si": si_log_loss(pred_log, depth),
        "grad": gradient_loss(pred_log, depth),
        "normal": normal_loss(pred_log, depth, normals, K, pred_normals=n),
    }
    weights = {"si": w_si, "grad": w_grad, "normal": w_normal}
    if "real" in batch:
        parts["lines"] = label_normal_loss(pred_log, normals, K, batch["real"], pred_normals=n)
        weights["lines"] = w_lines
    if sky_logit is not None and "sky" in batch:
        parts["sky"] = sky_loss(sky_logit, batch["sky"])
        weights["sky"] = w_sky
    if w_axis > 0 and "frame" in batch:
        parts["axis"] = frame_axis_loss(
            pred_log, batch["frame"], K, batch.get("sky"), pred_normals=n
        )
        weights["axis"] = w_axis
    loss = sum(weights[k] * v for k, v in parts.items())
    return loss, {k: float(v.detach()) for k, v in parts.items()}
