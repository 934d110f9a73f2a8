"""ONNX depth runtime: contract parsing, preprocessing per resize mode, output kinds,
sidecar overrides, batching (tiny models built in the test)."""

import dataclasses
import json

import numpy as np
import pycolmap
import pytest

onnx = pytest.importorskip("onnx")
from onnx import TensorProto, helper  # noqa: E402

from rectified_colmap.depth.contract import PREFIX, ModelSpec, attach_metadata  # noqa: E402
from rectified_colmap.depth.onnx import OnnxDepthSource, input_geometry, preprocess  # noqa: E402

H, W = 48, 64
R_LEFT, R_RIGHT = 200, 50


def make_model(
    path,
    spec: ModelSpec | None,
    layout="NCHW",
    static=None,
    pool=False,
    input_name="image",
    output_name="depth",
):
    """Network: output = input channel 0 (after preprocessing), optionally 2x2-pooled."""
    if static:
        shape = [1, 3, *static] if layout == "NCHW" else [1, *static, 3]
    else:
        shape = ["N", 3, "H", "W"] if layout == "NCHW" else ["N", "H", "W", 3]
    x = helper.make_tensor_value_info(input_name, TensorProto.FLOAT, shape)
    y = helper.make_tensor_value_info(output_name, TensorProto.FLOAT, None)
    inits = [
        helper.make_tensor("idx", TensorProto.INT64, [], [0]),
        helper.make_tensor("ax", TensorProto.INT64, [1], [1]),
    ]
    nodes = [
        helper.make_node("Gather", [input_name, "idx"], ["g"], axis=1 if layout == "NCHW" else 3),
        helper.make_node("Unsqueeze", ["g", "ax"], ["u" if pool else output_name]),
    ]
    if pool:
        nodes.append(
            helper.make_node(
                "AveragePool", ["u"], [output_name], kernel_shape=[2, 2], strides=[2, 2]
            )
        )
    graph = helper.make_graph(nodes, "tiny", [x], [y], inits)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 9
    if spec is not None:
        attach_metadata(model, spec)
    onnx.save(model, str(path))
    return path


def image(seed=0, h=H, w=W):
    rng = np.random.default_rng(seed)
    img = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
    img[:, : w // 2, 0] = R_LEFT
    img[:, w // 2 :, 0] = R_RIGHT
    return img


def camera(f=80.0, h=H, w=W):
    return pycolmap.Camera(model="SIMPLE_PINHOLE", width=w, height=h, params=[f, w / 2, h / 2])


SPEC = ModelSpec(scale=1 / 255, mean=[0.0], std=[1.0], output="depth", name="tiny")
RESIZES = {
    "fixed": ({"mode": "fixed", "width": 40, "height": 40}, (40, 40)),
    "keep_aspect": ({"mode": "keep_aspect", "max_side": 32, "multiple_of": 8}, (24, 32)),
    "letterbox": ({"mode": "letterbox", "width": 40, "height": 40, "multiple_of": 8}, (30, 40)),
}


def check_halves(values, left, right, tol=1e-3):
    h, w = values.shape
    q = max(1, w // 8)
    np.testing.assert_allclose(values[:, : w // 2 - q], left, atol=tol)
    np.testing.assert_allclose(values[:, w // 2 + q :], right, atol=tol)


@pytest.mark.parametrize("mode", list(RESIZES))
@pytest.mark.parametrize("output", ["metric", "depth", "disparity", "metric_canonical"])
def test_resize_modes_and_output_kinds(tmp_path, mode, output):
    resize, shape = RESIZES[mode]
    spec = dataclasses.replace(
        SPEC,
        resize=resize,
        output=output,
        canonical_focal=100.0 if output == "metric_canonical" else None,
    )
    src = OnnxDepthSource(make_model(tmp_path / "m.onnx", spec))
    d = src(image(), camera(), "a.jpg")
    assert d.values.shape == shape  # network resolution, letterbox padding removed
    assert d.kind == ("metric" if output == "metric_canonical" else output)
    factor = 1.0
    if output == "metric_canonical":
        g = input_geometry(src.spec, W, H)
        fx, fy = 80 * g.content_width / W, 80 * g.content_height / H
        factor = np.sqrt(fx * fy) / 100.0
    check_halves(d.values, R_LEFT / 255 * factor, R_RIGHT / 255 * factor)


def test_letterbox_geometry_with_lower_resolution_output(tmp_path):
    spec = dataclasses.replace(SPEC, resize=RESIZES["letterbox"][0])
    src = OnnxDepthSource(make_model(tmp_path / "m.onnx", spec, pool=True))
    g = input_geometry(src.spec, W, H)
    assert (g.width, g.height, g.x0, g.y0, g.content_width, g.content_height) == (
        40,
        40,
        0,
        0,
        40,
        30,
    )
    d = src(image(), camera(), "a.jpg")
    assert d.values.shape == (15, 20)
    assert d.values.min() > 0.1  # no zero padding left
    check_halves(d.values, R_LEFT / 255, R_RIGHT / 255)


def test_nhwc_bgr_and_normalisation(tmp_path):
    spec = dataclasses.replace(
        SPEC,
        layout="NHWC",
        color="BGR",
        mean=[0.1, 0.2, 0.3],
        std=[0.5, 0.25, 2.0],
        output="metric",
        resize=RESIZES["keep_aspect"][0],
    )
    img = image()
    img[..., 2] = 230  # B channel: BGR puts it first
    d = OnnxDepthSource(make_model(tmp_path / "m.onnx", spec, layout="NHWC"))(img, None)
    np.testing.assert_allclose(d.values, (230 / 255 - 0.1) / 0.5, atol=1e-5)


def test_sidecar_overrides_and_unprefixed_defaults(tmp_path):
    spec = dataclasses.replace(SPEC, resize=RESIZES["fixed"][0])
    path = make_model(tmp_path / "m.onnx", spec)
    (tmp_path / "m.json").write_text(
        json.dumps({"output": "disparity", "scale": 2 / 255, "resize": RESIZES["keep_aspect"][0]})
    )
    d = OnnxDepthSource(path)(image(), camera())
    assert d.kind == "disparity" and d.values.shape == (24, 32)
    check_halves(d.values, 2 * R_LEFT / 255, 2 * R_RIGHT / 255)
    (tmp_path / "m.json").write_text(json.dumps({"layout": "CHW"}))
    with pytest.raises(ValueError, match="m.json.*layout"):
        OnnxDepthSource(path)


def test_model_without_metadata_uses_fallback_and_infers_names(tmp_path):
    path = make_model(
        tmp_path / "plain.onnx", None, input_name="pixel_values", output_name="predicted_depth"
    )
    fallback = dataclasses.replace(SPEC, output="disparity", resize=RESIZES["fixed"][0])
    src = OnnxDepthSource(path, spec=fallback)
    assert (src.spec.input_name, src.spec.output_name) == ("pixel_values", "predicted_depth")
    d = src(image(), camera())
    assert d.kind == "disparity" and d.values.shape == (40, 40)


def test_static_input_size_becomes_letterbox(tmp_path):
    spec = dataclasses.replace(SPEC, resize=RESIZES["keep_aspect"][0])
    src = OnnxDepthSource(make_model(tmp_path / "m.onnx", spec, static=(40, 40)))
    assert src.spec.resize["mode"] == "letterbox" and not src.batchable
    d = src(image(), camera())
    assert d.values.shape == (30, 40)
    check_halves(d.values, R_LEFT / 255, R_RIGHT / 255)
    out = src.predict_batch([image(1), image(2)])
    assert [o.values.shape for o in out] == [(30, 40)] * 2


def test_predict_batch_groups_by_size(tmp_path):
    spec = dataclasses.replace(SPEC, resize=RESIZES["keep_aspect"][0])
    src = OnnxDepthSource(make_model(tmp_path / "m.onnx", spec), max_batch=4)
    calls = []
    run = src.run
    src.run = lambda x: calls.append(x.shape[0]) or run(x)
    imgs = [image(0), image(1, h=64, w=64), image(2)]
    out = src.predict_batch(imgs, [camera(), camera(h=64, w=64), camera()])
    assert sorted(calls) == [1, 2]
    for im, o in zip(imgs, out):
        np.testing.assert_allclose(o.values, run(preprocess(im, src.spec)[0])[0], atol=1e-6)


def test_contract_round_trip_and_errors(tmp_path):
    spec = dataclasses.replace(
        SPEC,
        output="metric_canonical",
        canonical_focal=1000.0,
        resize=RESIZES["letterbox"][0],
        licence="MIT",
    )
    meta = spec.to_metadata()
    assert all(k.startswith(PREFIX) and isinstance(v, str) for k, v in meta.items())
    assert meta[PREFIX + "contract_version"] == "1"
    assert ModelSpec.from_dict(meta) == spec
    with pytest.raises(ValueError, match="canonical_focal"):
        ModelSpec(output="metric_canonical").validate()
    with pytest.raises(ValueError, match="contract_version"):
        ModelSpec.from_dict({PREFIX + "contract_version": "7"}).validate()
    with pytest.raises(ValueError, match="unknown contract key"):
        ModelSpec.from_dict({PREFIX + "colour": "RGB"})
    bad = dataclasses.replace(SPEC, input_name="nope")
    with pytest.raises(ValueError, match="m.onnx.*nope"):
        OnnxDepthSource(make_model(tmp_path / "m.onnx", bad))
    (tmp_path / "junk.onnx").write_bytes(b"junk")
    with pytest.raises(ValueError, match="junk.onnx"):
        OnnxDepthSource(tmp_path / "junk.onnx")


def test_embedded_network_gives_no_depth_on_sky():
    """The shipped network's sky head (docs/training.md, stage 3): on held-out renders
    (seeds never in a training pool) the true sky has no depth, surfaces keep theirs."""
    from rectified_colmap_research import synth
    from rectified_colmap.depth.registry import model_path

    src = OnnxDepthSource(model_path("rectsift-lite0"), num_threads=1)
    checked = 0
    for seed in (900_000_000, 900_000_003, 900_000_005):
        r = synth.random_sample(np.random.default_rng(seed), 384, 288, None, 1)
        sky = ~np.isfinite(r.depth)
        assert sky.mean() > 0.1  # these views show sky
        no_depth = ~np.isfinite(src(r.image).to_depth())
        assert no_depth.shape == sky.shape
        assert no_depth[sky].mean() > 0.9, seed
        assert no_depth[~sky].mean() < 0.02, seed
        checked += 1
    assert checked == 3
