"""Depth from an ONNX network through onnxruntime, driven by the model's contract.

Shapes: images (H, W, 3) uint8 RGB; the network input is (B, 3, h, w) or (B, h, w, 3)
float32 per :class:`~rectified_colmap.depth.contract.ModelSpec`; the output (B, 1, h', w'),
(B, h', w'), (B, h', w', 1) or (h', w') may have another resolution than the input.

Returned depth maps stay at the *network output resolution*, covering the whole image
(letterbox padding removed): the pipeline calls :func:`~rectified_colmap.depth.resample_depth`
to bring them to its work grid. Output kinds: ``metric`` / ``depth`` / ``disparity`` map to
the DepthMap kind of the same name; ``metric_canonical`` becomes ``metric``:
out * f / canonical_focal with f the camera focal length (px) rescaled to the network input.

Disparity (affine-invariant, p = s/z + t) is returned as it is, kind ``disparity``: choosing
its shift is a stage of its own (:func:`rectified_colmap.disparity.resolve_disparity`).
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pycolmap

from . import DepthMap
from .contract import ModelSpec

logger = logging.getLogger(__name__)


@dataclass
class InputGeometry:
    """Where the image lies inside the network input."""

    width: int
    """Network input width (pixels)."""
    height: int
    x0: int
    """Image content box inside the input (letterbox; else the full input)."""
    y0: int
    content_width: int
    content_height: int


def _round_multiple(x: float, m: int) -> int:
    return max(m, int(round(x / m)) * m)


def input_geometry(spec: ModelSpec, width: int, height: int) -> InputGeometry:
    """Network input size and content box for an image of width x height."""
    r = spec.resize
    mode, m = r["mode"], int(r.get("multiple_of", 1))
    if mode == "fixed":
        W, H = int(r["width"]), int(r["height"])
        return InputGeometry(W, H, 0, 0, W, H)
    if mode == "keep_aspect":
        s = r["max_side"] / max(width, height)
        W, H = _round_multiple(width * s, m), _round_multiple(height * s, m)
        return InputGeometry(W, H, 0, 0, W, H)
    # letterbox: uniform scale into W x H (rounded up to the multiple), content at the
    # top-left, zero padding (after normalisation) right and bottom: a strided output then
    # splits exactly at the content border
    W = -(-int(r["width"]) // m) * m
    H = -(-int(r["height"]) // m) * m
    s = min(W / width, H / height)
    cw, ch = min(W, max(1, round(width * s))), min(H, max(1, round(height * s)))
    return InputGeometry(W, H, 0, 0, cw, ch)


def preprocess(image: np.ndarray, spec: ModelSpec) -> tuple[np.ndarray, InputGeometry]:
    """(H, W, 3) uint8 RGB -> network input (1, C, h, w) / (1, h, w, C) float32, geometry."""
    if image.ndim != 3 or image.shape[2] != 3:
        raise ValueError(f"depth network needs an (H, W, 3) RGB image, got {image.shape}")
    height, width = image.shape[:2]
    g = input_geometry(spec, width, height)
    if (g.content_width, g.content_height) != (width, height):
        down = g.content_width * g.content_height < width * height
        img = cv2.resize(
            image,
            (g.content_width, g.content_height),
            interpolation=cv2.INTER_AREA if down else cv2.INTER_LINEAR,
        )
    else:
        img = image
    if spec.color == "BGR":
        img = img[..., ::-1]
    x = img.astype(np.float32) * np.float32(spec.scale)
    x = (x - np.asarray(spec.mean, np.float32)) / np.asarray(spec.std, np.float32)
    if (g.content_width, g.content_height) != (g.width, g.height):
        canvas = np.zeros((g.height, g.width, 3), np.float32)
        canvas[g.y0 : g.y0 + g.content_height, g.x0 : g.x0 + g.content_width] = x
        x = canvas
    x = x[None] if spec.layout == "NHWC" else x.transpose(2, 0, 1)[None]
    return np.ascontiguousarray(x, np.float32), g


def _squeeze_output(out: np.ndarray, batch: int, origin: str) -> np.ndarray:
    """Any of (B,1,h,w), (B,h,w), (B,h,w,1), (h,w) -> (B, h, w)."""
    out = np.asarray(out)
    if out.ndim == 2 and batch == 1:
        out = out[None]
    elif out.ndim == 4 and out.shape[1] == 1:
        out = out[:, 0]
    elif out.ndim == 4 and out.shape[3] == 1:
        out = out[..., 0]
    if out.ndim != 3 or out.shape[0] != batch:
        raise ValueError(
            f"{origin}: unexpected depth output shape {out.shape} for a batch "
            f"of {batch} (expected (B,1,h,w), (B,h,w) or (B,h,w,1))"
        )
    return out.astype(np.float32)


def postprocess(out: np.ndarray, g: InputGeometry) -> np.ndarray:
    """(h', w') network output -> the part covering the image (letterbox removed)."""
    oh, ow = out.shape
    if (g.content_width, g.content_height) == (g.width, g.height):
        return out
    # inner crop: output cells that straddle padding and content are dropped
    sx, sy = ow / g.width, oh / g.height
    x0, y0 = math.ceil(g.x0 * sx - 1e-6), math.ceil(g.y0 * sy - 1e-6)
    x1 = max(x0 + 1, math.floor((g.x0 + g.content_width) * sx + 1e-6))
    y1 = max(y0 + 1, math.floor((g.y0 + g.content_height) * sy + 1e-6))
    return out[y0:y1, x0:x1]


def input_focal(camera: pycolmap.Camera, g: InputGeometry) -> float:
    """Focal length (px) of the camera rescaled to the network input."""
    idx = list(camera.focal_length_idxs())
    params = np.asarray(camera.params, np.float64)
    fx = params[idx[0]]
    fy = params[idx[1]] if len(idx) > 1 else fx
    sx, sy = g.content_width / camera.width, g.content_height / camera.height
    return float(np.sqrt(fx * sx * fy * sy))


def default_providers() -> list[str]:
    import onnxruntime as ort

    avail = ort.get_available_providers()
    if "CUDAExecutionProvider" in avail:
        return ["CUDAExecutionProvider", "CPUExecutionProvider"]
    return ["CPUExecutionProvider"]


class OnnxDepthSource:
    """Depth source running an ONNX depth network (see module docstring).

    ``spec``: contract to use when the file carries none (e.g. from the registry); the
    file's metadata and a sidecar JSON take precedence. ``providers``: onnxruntime
    execution providers (default CUDA when available, else CPU). ``num_threads``: intra-op
    threads (None: onnxruntime's default)."""

    def __init__(
        self,
        model_path: str | Path,
        providers: list[str] | None = None,
        num_threads: int | None = None,
        spec: ModelSpec | None = None,
        max_batch: int = 8,
    ):
        import onnxruntime as ort

        self.path = Path(model_path)
        if not self.path.is_file():
            raise FileNotFoundError(f"{self.path}: ONNX depth model does not exist")
        self.max_batch = max(1, int(max_batch))
        opts = ort.SessionOptions()
        if num_threads:
            opts.intra_op_num_threads = int(num_threads)
            opts.inter_op_num_threads = 1
        self.providers = providers or default_providers()
        try:
            self.session = ort.InferenceSession(
                str(self.path), sess_options=opts, providers=self.providers
            )
        except Exception as e:
            raise ValueError(f"{self.path}: onnxruntime cannot load the model ({e})") from None
        meta = dict(self.session.get_modelmeta().custom_metadata_map)
        self.spec = ModelSpec.from_onnx(self.path, fallback=spec, metadata=meta)
        inputs = {i.name: i for i in self.session.get_inputs()}
        outputs = [o.name for o in self.session.get_outputs()]
        if self.spec.input_name is None:
            if len(inputs) != 1:
                raise ValueError(
                    f"{self.path}: model has inputs {list(inputs)}; name one "
                    f"with input_name in the metadata or sidecar"
                )
            self.spec.input_name = next(iter(inputs))
        if self.spec.input_name not in inputs:
            raise ValueError(
                f"{self.path}: no input {self.spec.input_name!r}, the model has {list(inputs)}"
            )
        if self.spec.output_name is None:
            self.spec.output_name = outputs[0]
        if self.spec.output_name not in outputs:
            raise ValueError(
                f"{self.path}: no output {self.spec.output_name!r}, the model has {outputs}"
            )
        shape = list(inputs[self.spec.input_name].shape)
        self._static = [d if isinstance(d, int) else None for d in shape]
        self._adapt_to_static_size()
        logger.info(
            "depth model %s (%s, output %s, resize %s) on %s",
            self.path.name,
            self.spec.name or "unnamed",
            self.spec.output,
            self.spec.resize,
            self.session.get_providers()[0],
        )

    def _adapt_to_static_size(self) -> None:
        """A model with a fixed input size runs at that size: keep_aspect (or a letterbox
        of another size) becomes a letterbox of the fixed size."""
        if len(self._static) != 4:
            return
        hw = self._static[2:4] if self.spec.layout == "NCHW" else self._static[1:3]
        if None in hw:
            return
        H, W = hw
        r = self.spec.resize
        if r["mode"] == "fixed" or (
            r["mode"] == "letterbox" and (r["width"], r["height"]) == (W, H)
        ):
            return
        logger.info(
            "%s has a fixed input size %dx%d: resize %s -> letterbox", self.path.name, W, H, r
        )
        self.spec.resize = {"mode": "letterbox", "width": W, "height": H, "multiple_of": 1}

    @property
    def batchable(self) -> bool:
        return self._static[0] is None

    def _check_input(self, x: np.ndarray) -> None:
        for d, (want, got) in enumerate(zip(self._static, x.shape)):
            if want is not None and want != got and d > 0:
                raise ValueError(
                    f"{self.path}: the model takes a fixed input shape {self._static}, the "
                    f"contract's resize {self.spec.resize} gives {list(x.shape)}; set resize "
                    f"to {{'mode': 'fixed', ...}} in the metadata or a sidecar JSON"
                )

    def run(self, x: np.ndarray) -> np.ndarray:
        """Raw network call: input batch -> (B, h', w') float32."""
        self._check_input(x)
        t = time.perf_counter()
        try:
            (out,) = self.session.run([self.spec.output_name], {self.spec.input_name: x})
        except Exception as e:
            raise RuntimeError(f"{self.path}: inference failed on input {x.shape} ({e})") from None
        logger.debug("depth network %s: %.3f s", x.shape, time.perf_counter() - t)
        return _squeeze_output(out, len(x), str(self.path))

    def _to_depthmap(
        self, out: np.ndarray, g: InputGeometry, camera: pycolmap.Camera | None
    ) -> DepthMap:
        v = postprocess(out, g)
        kind = self.spec.output
        if kind == "metric_canonical":
            if camera is None:
                raise ValueError(f"{self.path}: output 'metric_canonical' needs the camera")
            v = v * np.float32(input_focal(camera, g) / self.spec.canonical_focal)
            kind = "metric"
        return DepthMap(v, kind)

    def __call__(
        self, image: np.ndarray, camera: pycolmap.Camera | None = None, name: str | None = None
    ) -> DepthMap:
        x, g = preprocess(image, self.spec)
        return self._to_depthmap(self.run(x)[0], g, camera)

    def predict_batch(
        self, images: list[np.ndarray], cameras: list[pycolmap.Camera | None] | None = None
    ) -> list[DepthMap]:
        """Depth of several images; images with the same network input size run as one
        batch (up to ``max_batch``) when the model's batch dimension is dynamic."""
        cameras = cameras if cameras is not None else [None] * len(images)
        if len(cameras) != len(images):
            raise ValueError(f"{len(images)} images but {len(cameras)} cameras")
        prepared = [preprocess(im, self.spec) for im in images]
        groups: dict[tuple, list[int]] = {}
        for i, (x, _) in enumerate(prepared):
            groups.setdefault(x.shape, []).append(i)
        step = self.max_batch if self.batchable else 1
        out: list[DepthMap | None] = [None] * len(images)
        for idx in groups.values():
            for k in range(0, len(idx), step):
                chunk = idx[k : k + step]
                y = self.run(np.concatenate([prepared[i][0] for i in chunk]))
                for j, i in enumerate(chunk):
                    out[i] = self._to_depthmap(y[j], prepared[i][1], cameras[i])
        return out
