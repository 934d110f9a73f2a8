#!/usr/bin/env python
"""Export a PyTorch depth network to an ONNX file with the rectified_colmap contract metadata.

Opset 17, dynamic size unless ``--fixed``, checked against PyTorch with onnxruntime (max
abs/rel error printed; ``--no_verify`` skips it). Needs torch and onnx
(``pip install -e 'research/[train]'``). The contract keys are in docs/depth-models.md; the
file this writes goes to ``rectified-colmap extract --depth_model PATH``.

    python research/scripts/export_depth_model.py \\
        --factory rectified_colmap_research.training.model:build_model \\
        --factory_kwargs '{"pretrained": false}' --weights ckpt.pt --spec spec.json \\
        --output rectified_colmap/models/rectsift-depth-lite0.onnx
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path

from rectified_colmap.errors import run_script
from rectified_colmap_research.onnx_export import export_from_factory

logger = logging.getLogger("export_depth_model")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument(
        "--factory", required=True, help="'package.module:callable' building the nn.Module"
    )
    p.add_argument("--factory_kwargs", default="{}", help="JSON kwargs for the factory")
    p.add_argument("--weights", type=Path, help="state_dict (.pt) to load")
    p.add_argument("--spec", type=Path, help="JSON of contract keys (without prefix)")
    p.add_argument("--output", type=Path, required=True, help="the .onnx file to write")
    p.add_argument("--height", type=int, default=256, help="example input height")
    p.add_argument("--width", type=int, default=320, help="example input width")
    p.add_argument("--fixed", action="store_true", help="fixed input size (default: dynamic)")
    p.add_argument("--fp16", action="store_true", help="fp16 weights, float32 inputs/outputs")
    p.add_argument(
        "--fp16_storage",
        action="store_true",
        help="fp16 weights in the file, float32 arithmetic (half the size)",
    )
    p.add_argument("--no_verify", action="store_true", help="skip the onnxruntime check")
    p.add_argument("--overwrite", action="store_true", help="replace --output if it exists already")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="[%(asctime)s %(name)s] %(message)s")
    if args.output.exists() and not args.overwrite:
        logger.error("%s: exists already (pass --overwrite to replace it)", args.output)
        return 1
    try:
        kwargs = json.loads(args.factory_kwargs)
    except json.JSONDecodeError as e:
        logger.error("--factory_kwargs: not JSON (%s)", e)
        return 1
    try:
        export_from_factory(
            args.factory,
            args.output,
            factory_kwargs=kwargs,
            weights=args.weights,
            spec=args.spec,
            height=args.height,
            width=args.width,
            dynamic=not args.fixed,
            fp16=args.fp16,
            fp16_storage=args.fp16_storage,
            verify=not args.no_verify,
        )
    except (ValueError, FileNotFoundError, ImportError) as e:
        logger.error("%s", e)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(run_script(main, "export_depth_model"))
