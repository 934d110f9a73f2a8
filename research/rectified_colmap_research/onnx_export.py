"""Export a PyTorch depth network to ONNX with the rectified_colmap contract metadata.

The network maps a preprocessed image batch (B, 3, H, W) (or NHWC per the spec) to depth
(B, 1, H', W') / (B, H', W'). The ONNX file gets opset 17, dynamic batch/height/width (or a
fixed size), the ``rectified_colmap.*`` metadata of the given ModelSpec, optionally fp16
(``fp16``: fp16 arithmetic, inputs/outputs stay float32; ``fp16_storage``: fp16 weights in the
file, cast to float32 when the session loads, so half the size and float32 arithmetic), and
is checked against PyTorch with onnxruntime.

Research only (torch and onnx: ``pip install -e 'research/[train]'``); the extractor reads
the files it writes and never needs torch. From Python::

    from rectified_colmap_research.onnx_export import export_depth_onnx
    export_depth_onnx(net, "model.onnx", ModelSpec(...), height=256, width=320)

From the command line (a factory "package.module:callable" building the network)::

    python research/scripts/export_depth_model.py --factory mypackage.model:DepthNet \
        --weights ckpt.pt --spec spec.json --output model.onnx
"""

from __future__ import annotations

import importlib
import json
import logging
import os
import tempfile
from pathlib import Path

import numpy as np

from rectified_colmap.depth.contract import ModelSpec, attach_metadata

logger = logging.getLogger(__name__)
OPSET = 17


def _example(spec: ModelSpec, batch: int, height: int, width: int, seed: int = 0):
    import torch

    g = torch.Generator().manual_seed(seed)
    shape = (batch, 3, height, width) if spec.layout == "NCHW" else (batch, height, width, 3)
    return torch.randn(shape, generator=g)


def _spatial_axes(rank: int, last_is_channel: bool) -> tuple[int, int]:
    return (rank - 3, rank - 2) if last_is_channel else (rank - 2, rank - 1)


def compare_outputs(ref: np.ndarray, out: np.ndarray) -> dict[str, float]:
    """Max absolute error and max error relative to the largest reference magnitude."""
    ref = np.asarray(ref, np.float64).reshape(out.shape)
    err = np.abs(np.asarray(out, np.float64) - ref)
    return {
        "max_abs": float(err.max()),
        "max_rel": float(err.max() / max(np.abs(ref).max(), 1e-12)),
    }


def export_depth_onnx(
    model,
    output: str | Path,
    spec: ModelSpec,
    height: int = 256,
    width: int = 320,
    dynamic: bool = True,
    fp16: bool = False,
    verify: bool = True,
    opset: int = OPSET,
    fp16_storage: bool = False,
) -> dict[str, float]:
    """Export ``model`` (torch.nn.Module) to ``output`` with ``spec`` attached.

    ``height``/``width``: the example (and, when not ``dynamic``, the fixed) input size.
    Returns the verification errors {"max_abs", "max_rel"} (empty when not verified)."""
    torch = import_torch()
    import onnx

    output = Path(output)
    output.parent.mkdir(parents=True, exist_ok=True)
    spec = ModelSpec(**vars(spec))
    spec.input_name = spec.input_name or "image"
    spec.output_name = spec.output_name or "depth"
    if not dynamic and spec.resize.get("mode") != "fixed":
        spec.resize = {"mode": "fixed", "width": width, "height": height}
    spec.validate(str(output))
    model = model.eval().float()
    x = _example(spec, 1, height, width)
    with torch.no_grad():
        y = model(x)
    if isinstance(y, (tuple, list)):
        raise ValueError("the network must return a single depth tensor")
    rank, last_ch = y.dim(), y.shape[-1] == 1 and y.dim() == 4
    dyn = None
    if dynamic:
        ia = (2, 3) if spec.layout == "NCHW" else (1, 2)
        oa = _spatial_axes(rank, last_ch)
        dyn = {
            spec.input_name: {0: "batch", ia[0]: "height", ia[1]: "width"},
            spec.output_name: {0: "batch", oa[0]: "out_height", oa[1]: "out_width"},
        }
    with tempfile.TemporaryDirectory() as tmp:
        raw = Path(tmp) / "raw.onnx"
        torch.onnx.export(
            model,
            (x,),
            str(raw),
            opset_version=opset,
            input_names=[spec.input_name],
            output_names=[spec.output_name],
            dynamic_axes=dyn,
            do_constant_folding=True,
            dynamo=False,
        )
        proto = onnx.load(str(raw))
    if fp16:
        from onnxruntime.transformers.float16 import convert_float_to_float16

        proto = convert_float_to_float16(proto, keep_io_types=True)
        _toposort(proto.graph)  # the converter appends its input casts at the end
    elif fp16_storage:
        store_weights_fp16(proto)
    attach_metadata(proto, spec)
    onnx.checker.check_model(proto)
    # written beside and renamed: an interrupted export never leaves a partial file at
    # ``output`` (nor destroys the one an --overwrite replaces)
    partial = output.with_name(output.name + ".partial")
    try:
        onnx.save(proto, str(partial))
        os.replace(partial, output)
    finally:
        partial.unlink(missing_ok=True)
    logger.info(
        "wrote %s (%.1f MB, opset %d, %s%s)",
        output,
        output.stat().st_size / 1e6,
        opset,
        "dynamic" if dynamic else f"fixed {width}x{height}",
        ", fp16" if fp16 else ", fp16 storage" if fp16_storage else "",
    )
    if not verify:
        return {}
    return verify_export(model, output, spec, height, width, dynamic)


def store_weights_fp16(proto, min_elements: int = 64) -> int:
    """Store float32 initializers of at least ``min_elements`` values as float16, each read
    through a Cast back to float32 (in place): the file halves, the arithmetic stays float32
    (onnxruntime folds the casts when the session loads). Returns how many were converted."""
    import onnx
    from onnx import TensorProto, helper, numpy_helper

    graph = proto.graph
    casts, count = [], 0
    for init in graph.initializer:
        if init.data_type != TensorProto.FLOAT:
            continue
        arr = numpy_helper.to_array(init)
        if arr.size < min_elements:
            continue
        name = init.name
        init.CopyFrom(numpy_helper.from_array(arr.astype("float16"), name + "_fp16"))
        casts.append(
            helper.make_node(
                "Cast", [name + "_fp16"], [name], to=TensorProto.FLOAT, name=name + "_to_fp32"
            )
        )
        count += 1
    graph.node.extend(casts)
    _toposort(graph)
    onnx.checker.check_model(proto)
    return count


def _toposort(graph) -> None:
    """Reorder a graph's nodes topologically (in place; subgraphs are left alone)."""
    ready = {i.name for i in graph.input} | {t.name for t in graph.initializer} | {""}
    pending, ordered = list(graph.node), []
    while pending:
        rest = [n for n in pending if not set(n.input) <= ready]
        done = [n for n in pending if set(n.input) <= ready]
        if not done:
            raise ValueError(f"graph has a cycle or dangling inputs at {rest[0].name}")
        for n in done:
            ready.update(n.output)
        ordered += done
        pending = rest
    nodes = [type(graph.node[0])() for _ in ordered]
    for dst, src in zip(nodes, ordered):
        dst.CopyFrom(src)
    del graph.node[:]
    graph.node.extend(nodes)


def verify_export(
    model, path: Path, spec: ModelSpec, height: int, width: int, dynamic: bool
) -> dict[str, float]:
    """Run PyTorch and onnxruntime on the same input (another size when dynamic, batch 2)."""
    import onnxruntime as ort
    import torch

    m = int(spec.resize.get("multiple_of", 1) or 1)
    h, w = (height + 2 * max(m, 32), width - max(m, 32)) if dynamic else (height, width)
    batch = 2 if dynamic else 1
    x = _example(spec, batch, h, w, seed=1)
    with torch.no_grad():
        ref = model(x).numpy()
    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    (out,) = sess.run([spec.output_name], {spec.input_name: x.numpy()})
    errs = compare_outputs(ref, out)
    print(
        f"onnxruntime vs PyTorch on {tuple(x.shape)}: max abs error {errs['max_abs']:.3g}, "
        f"max rel error {errs['max_rel']:.3g}"
    )
    return errs


def import_torch():
    """torch, or ImportError with the extra to install (the runtime does not depend on it)."""
    try:
        import torch
    except ImportError:
        raise ImportError(
            "exporting a network needs PyTorch: pip install -e 'research/[train]'"
        ) from None
    return torch


def load_factory(factory: str):
    """'package.module:callable' -> the callable (ValueError naming the expected form)."""
    module, _, attr = factory.partition(":")
    if not module or not attr:
        raise ValueError(f"--factory {factory!r}: expected 'package.module:callable'")
    try:
        return getattr(importlib.import_module(module), attr)
    except (ImportError, AttributeError) as e:
        raise ValueError(f"--factory {factory!r}: {e}") from None


def export_from_factory(
    factory: str,
    output: str | Path,
    factory_kwargs: dict | None = None,
    weights: str | Path | None = None,
    spec: str | Path | None = None,
    height: int = 256,
    width: int = 320,
    dynamic: bool = True,
    fp16: bool = False,
    fp16_storage: bool = False,
    verify: bool = True,
) -> dict[str, float]:
    """Build the network with ``factory(**factory_kwargs)``, load the ``weights`` state_dict
    (a checkpoint dict with "model" or the state_dict itself), read the contract from the
    ``spec`` JSON (keys without prefix) and export it (:func:`export_depth_onnx`)."""
    torch = import_torch()
    net = load_factory(factory)(**(factory_kwargs or {}))
    if weights:
        state = torch.load(weights, map_location="cpu")
        net.load_state_dict(state.get("model", state) if isinstance(state, dict) else state)
    model_spec = ModelSpec()
    if spec:
        model_spec = ModelSpec.from_dict(json.loads(Path(spec).read_text()), origin=str(spec))
    return export_depth_onnx(
        net,
        output,
        model_spec,
        height,
        width,
        dynamic=dynamic,
        fp16=fp16,
        verify=verify,
        fp16_storage=fp16_storage,
    )
