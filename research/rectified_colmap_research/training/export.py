"""Export a trained DepthNet to ONNX with the rectified_colmap contract metadata.

Through the research exporter (rectified_colmap_research.onnx_export: opset 17, dynamic
H/W, optional fp16, onnxruntime verification).
"""

from __future__ import annotations

import logging
from pathlib import Path

from rectified_colmap.depth.contract import ModelSpec
from rectified_colmap_research.onnx_export import export_depth_onnx
from .model import INPUT_MEAN, INPUT_SCALE, INPUT_STD

logger = logging.getLogger(__name__)

MODEL_NAME = "rectsift-depth-lite0"


def model_spec(max_side: int = 384, description: str = "", sky: bool = True) -> ModelSpec:
    """The contract of the project's network (``sky``: its graph outputs depth 0 on sky)."""
    return ModelSpec(
        input_name="image",
        output_name="depth",
        layout="NCHW",
        color="RGB",
        scale=INPUT_SCALE,
        mean=list(INPUT_MEAN),
        std=list(INPUT_STD),
        resize={"mode": "keep_aspect", "max_side": int(max_side), "multiple_of": 32},
        output="depth",
        name=MODEL_NAME,
        licence="BSD-3-Clause (encoder initialised from EfficientNet-Lite0 ImageNet weights, "
        "Apache-2.0); trained by rectified_colmap on procedural renders and real photos "
        "(data and their terms: docs/training.md)",
        description=description
        or "EfficientNet-Lite0 + fusion decoder trained on synthetic street scenes and real "
        "photos (sparse SfM depth, line-derived orientations); positive z-depth up to "
        "scale, for normals and planes"
        + ("; 0 where its sky head sees sky (no depth, no plane)" if sky else ""),
    )


def export_onnx(
    model,
    output: str | Path,
    spec: ModelSpec | None = None,
    height: int = 256,
    width: int = 320,
    fp16: bool = False,
    verify: bool = True,
    fp16_storage: bool = False,
) -> dict:
    """Write ``model`` (eval mode, positive depth output) to ``output``; returns the
    onnxruntime-vs-torch errors when verified."""
    spec = spec or model_spec()
    output = Path(output)
    output.parent.mkdir(parents=True, exist_ok=True)
    was_training = model.training
    model.eval()
    try:
        return export_depth_onnx(
            model,
            output,
            spec,
            height=height,
            width=width,
            dynamic=True,
            fp16=fp16,
            verify=verify,
            fp16_storage=fp16_storage,
        )
    finally:
        model.train(was_training)
