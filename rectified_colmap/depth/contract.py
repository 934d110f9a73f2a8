"""The self-describing ONNX depth-model contract.

An ONNX depth model carries, in its ``metadata_props``, everything needed to run it:
keys under the namespace ``rectified_colmap.`` (all values are strings):

===============================  ======================================================
``contract_version``             "1"
``input_name`` / ``output_name`` graph input / output (default: the only one)
``layout``                       "NCHW" | "NHWC" (input tensor, batch first)
``color``                        "RGB" | "BGR" (channel order fed to the network)
``scale``                        float; x = pixel_uint8 * scale, applied first
``mean`` / ``std``               JSON lists (1 or 3 values); x = (x - mean) / std after scale
``resize``                       JSON, one of
                                 {"mode": "fixed", "width": W, "height": H}
                                 {"mode": "keep_aspect", "max_side": N, "multiple_of": M}
                                 {"mode": "letterbox", "width": W, "height": H,
                                 "multiple_of": M}
``output``                       "metric" | "depth" | "disparity" | "metric_canonical"
``canonical_focal``              float px; metric_canonical: metric = out * f / canonical_focal
                                 with f the focal length (px) of the *network input*
``name`` / ``licence`` /         free text
``description``
===============================  ======================================================

A JSON sidecar next to the model (``model.json`` or ``model.onnx.json``) adds or overrides
keys, written without the prefix and with native JSON values
(``{"output": "disparity", "mean": [0.5, 0.5, 0.5], "resize": {...}}``): this is how to run
a model exported by others without rewriting it.

Precedence (lowest first): :class:`ModelSpec` defaults < ``fallback`` spec (e.g. the
registry's, used only when the file carries no contract) < file metadata < sidecar.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

logger = logging.getLogger(__name__)

PREFIX = "rectified_colmap."
CONTRACT_VERSION = "1"
LAYOUTS = ("NCHW", "NHWC")
COLORS = ("RGB", "BGR")
OUTPUTS = ("metric", "depth", "disparity", "metric_canonical")
RESIZE_MODES = {
    "fixed": ("width", "height"),
    "keep_aspect": ("max_side", "multiple_of"),
    "letterbox": ("width", "height", "multiple_of"),
}
IMAGENET_MEAN = [0.485, 0.456, 0.406]
IMAGENET_STD = [0.229, 0.224, 0.225]


@dataclass
class ModelSpec:
    """How to feed an ONNX depth model and read its output (see module docstring)."""

    input_name: str | None = None
    """None: the graph's only input."""
    output_name: str | None = None
    """None: the graph's first output."""
    layout: str = "NCHW"
    color: str = "RGB"
    scale: float = 1.0 / 255.0
    mean: list[float] = field(default_factory=lambda: list(IMAGENET_MEAN))
    std: list[float] = field(default_factory=lambda: list(IMAGENET_STD))
    resize: dict[str, Any] = field(
        default_factory=lambda: {"mode": "keep_aspect", "max_side": 512, "multiple_of": 32}
    )
    output: str = "depth"
    canonical_focal: float | None = None
    name: str = ""
    licence: str = ""
    description: str = ""
    contract_version: str = CONTRACT_VERSION

    # -- validation ---------------------------------------------------------------------
    def validate(self, origin: str = "model spec") -> "ModelSpec":
        """Raise ValueError (naming ``origin``) on any inconsistent field; returns self."""

        def bad(msg):
            raise ValueError(f"{origin}: {msg}")

        if str(self.contract_version) != CONTRACT_VERSION:
            bad(
                f"contract_version {self.contract_version!r} is not supported "
                f"(this version reads {CONTRACT_VERSION!r})"
            )
        if self.layout not in LAYOUTS:
            bad(f"layout {self.layout!r} not in {LAYOUTS}")
        if self.color not in COLORS:
            bad(f"color {self.color!r} not in {COLORS}")
        if self.output not in OUTPUTS:
            bad(f"output {self.output!r} not in {OUTPUTS}")
        if not (math.isfinite(self.scale) and self.scale != 0):
            bad(f"scale must be a finite non-zero float, got {self.scale}")
        for key in ("mean", "std"):
            v = getattr(self, key)
            if len(v) not in (1, 3) or not all(math.isfinite(x) for x in v):
                bad(f"{key} must be a list of 1 or 3 finite floats, got {v}")
        if any(s == 0 for s in self.std):
            bad(f"std must be non-zero, got {self.std}")
        mode = self.resize.get("mode")
        if mode not in RESIZE_MODES:
            bad(f"resize mode {mode!r} not in {tuple(RESIZE_MODES)}")
        for key in RESIZE_MODES[mode]:
            v = self.resize.get(key, 1 if key == "multiple_of" else None)
            if not isinstance(v, int) or isinstance(v, bool) or v <= 0:
                bad(f"resize {mode}: {key} must be a positive integer, got {v!r}")
        if self.output == "metric_canonical" and not (self.canonical_focal or 0) > 0:
            bad("output 'metric_canonical' needs a positive canonical_focal")
        return self

    # -- (de)serialisation --------------------------------------------------------------
    def to_metadata(self) -> dict[str, str]:
        """Prefixed string metadata for an ONNX file's metadata_props (None fields omitted)."""
        out = {}
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if v is None:
                continue
            if isinstance(v, (list, dict)):
                v = json.dumps(v)
            out[PREFIX + f.name] = str(v) if not isinstance(v, float) else repr(v)
        return out

    @classmethod
    def from_dict(
        cls, values: dict[str, Any], base: "ModelSpec | None" = None, origin: str = "model spec"
    ) -> "ModelSpec":
        """``base`` (default: defaults) updated by ``values``: keys with or without the
        prefix, values as strings (metadata) or native JSON types (sidecar). Unknown keys
        under the prefix raise; other keys are ignored."""
        spec = dataclasses.replace(base) if base is not None else cls()
        names = {f.name for f in dataclasses.fields(cls)}
        for key, value in values.items():
            k = key[len(PREFIX) :] if key.startswith(PREFIX) else key
            if k not in names:
                if key.startswith(PREFIX):
                    raise ValueError(f"{origin}: unknown contract key {key!r}")
                continue
            try:
                setattr(spec, k, _parse(k, value))
            except (ValueError, TypeError) as e:
                raise ValueError(f"{origin}: bad value for {k!r}: {value!r} ({e})") from None
        return spec

    @classmethod
    def from_onnx(
        cls,
        path: str | Path,
        fallback: "ModelSpec | None" = None,
        metadata: dict[str, str] | None = None,
    ) -> "ModelSpec":
        """Spec of an ONNX file: its metadata (read with onnxruntime unless ``metadata`` is
        given), else ``fallback``, then the sidecar JSON; validated."""
        path = Path(path)
        if metadata is None:
            metadata = read_onnx_metadata(path)
        ours = {k: v for k, v in metadata.items() if k.startswith(PREFIX)}
        if ours:
            spec = cls.from_dict(ours, origin=str(path))
        else:
            spec = dataclasses.replace(fallback) if fallback is not None else cls()
            if fallback is None:
                logger.warning(
                    "%s carries no %s* metadata and has no registry entry: "
                    "using the default contract %s",
                    path,
                    PREFIX,
                    spec,
                )
        sidecar = find_sidecar(path)
        if sidecar is not None:
            try:
                values = json.loads(sidecar.read_text())
            except (OSError, ValueError) as e:
                raise ValueError(f"{sidecar}: unreadable sidecar JSON ({e})") from None
            if not isinstance(values, dict):
                raise ValueError(f"{sidecar}: sidecar must be a JSON object")
            spec = cls.from_dict(values, base=spec, origin=str(sidecar))
            logger.info("contract of %s overridden by %s", path.name, sidecar)
        return spec.validate(str(sidecar or path))


def _parse(key: str, value: Any) -> Any:
    if key in ("mean", "std"):
        v = json.loads(value) if isinstance(value, str) else value
        v = [v] if isinstance(v, (int, float)) else v
        return [float(x) for x in v]
    if key == "resize":
        v = json.loads(value) if isinstance(value, str) else value
        if not isinstance(v, dict):
            raise TypeError("resize must be a JSON object")
        return dict(v)
    if key == "scale":
        return float(value)
    if key == "canonical_focal":
        return None if value in (None, "", "null") else float(value)
    return None if value is None else str(value)


def find_sidecar(model_path: str | Path) -> Path | None:
    """``model.json`` or ``model.onnx.json`` next to ``model.onnx``, or None."""
    p = Path(model_path)
    for c in (p.with_suffix(".json"), Path(f"{p}.json")):
        if c.is_file():
            return c
    return None


def read_onnx_metadata(path: str | Path) -> dict[str, str]:
    """metadata_props of an ONNX file as a dict (through onnxruntime: no onnx needed)."""
    import onnxruntime as ort

    path = Path(path)
    if not path.is_file():
        raise ValueError(f"{path}: ONNX model does not exist")
    try:
        sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    except Exception as e:
        raise ValueError(f"{path}: not a loadable ONNX model ({e})") from None
    return dict(sess.get_modelmeta().custom_metadata_map)


def attach_metadata(model, spec: ModelSpec):
    """Write ``spec`` into an ``onnx.ModelProto``'s metadata_props (replacing any previous
    contract keys; other keys kept). Returns the same proto."""
    import onnx  # noqa: F401  (only the proto API is used; imported for a clear error)

    spec.validate(spec.name or "spec to attach")
    keep = [(p.key, p.value) for p in model.metadata_props if not p.key.startswith(PREFIX)]
    del model.metadata_props[:]
    for k, v in keep + list(spec.to_metadata().items()):
        entry = model.metadata_props.add()
        entry.key, entry.value = k, v
    return model
