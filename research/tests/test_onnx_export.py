"""research/: the exporter of a PyTorch depth network to a contract ONNX file
(rectified_colmap_research.onnx_export) and its script (tiny networks built in the test)."""

import json

import numpy as np
import pytest

onnx = pytest.importorskip("onnx")
from onnx import TensorProto  # noqa: E402
from rectified_colmap_research import onnx_export as exporter  # noqa: E402
from scripts_util import load_script  # noqa: E402

from rectified_colmap.depth.contract import ModelSpec  # noqa: E402
from rectified_colmap.depth.onnx import OnnxDepthSource, preprocess  # noqa: E402
from tests.depth.test_depth_onnx import camera, image  # noqa: E402


@pytest.mark.parametrize("precision", ["fp32", "fp16", "fp16_storage"])
def test_export_round_trip(tmp_path, precision):
    torch = pytest.importorskip("torch")

    torch.manual_seed(0)

    class Tiny(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.enc = torch.nn.Conv2d(3, 8, 3, stride=2, padding=1)
            self.dec = torch.nn.Conv2d(8, 1, 3, padding=1)

        def forward(self, x):
            y = torch.nn.functional.interpolate(torch.relu(self.enc(x)), scale_factor=2.0)
            return torch.nn.functional.softplus(self.dec(y))  # positive depth (B, 1, H, W)

    net = Tiny()
    spec = ModelSpec(
        resize={"mode": "keep_aspect", "max_side": 64, "multiple_of": 32},
        output="depth",
        name="tiny-export",
    )
    out = tmp_path / "tiny.onnx"
    fp16, storage = precision == "fp16", precision == "fp16_storage"
    errs = exporter.export_depth_onnx(
        net, out, spec, height=64, width=96, fp16=fp16, fp16_storage=storage
    )
    assert errs["max_rel"] < {"fp32": 1e-5, "fp16": 2e-2, "fp16_storage": 3e-3}[precision]
    src = OnnxDepthSource(out)
    assert src.spec.name == "tiny-export" and src.spec.input_name == "image"
    img = image()
    d = src(img, camera())
    assert d.kind == "depth" and d.values.shape == (64, 64) and (d.values > 0).all()
    x, _ = preprocess(img, src.spec)
    with torch.no_grad():
        ref = net(torch.from_numpy(x)).numpy()[0, 0]
    np.testing.assert_allclose(
        d.values, ref, rtol=2e-2 if fp16 else 3e-3 if storage else 1e-4, atol=1e-4
    )
    if fp16 or storage:
        inits = onnx.load(str(out)).graph.initializer
        assert any(t.data_type == TensorProto.FLOAT16 for t in inits)
    if storage:  # float32 arithmetic: only the weights are rounded, and no other node runs fp16
        graph = onnx.load(str(out)).graph
        casts = [n for n in graph.node if n.op_type == "Cast"]
        assert casts and all(n.attribute[0].i == TensorProto.FLOAT for n in casts)


TINY_NET = """
import torch


class Tiny(torch.nn.Module):
    def __init__(self, channels=4):
        super().__init__()
        torch.manual_seed(0)
        self.conv = torch.nn.Conv2d(3, channels, 3, padding=1)
        self.out = torch.nn.Conv2d(channels, 1, 1)

    def forward(self, x):
        return torch.nn.functional.softplus(self.out(torch.relu(self.conv(x))))
"""


def test_export_script(tmp_path, monkeypatch, caplog):
    """research/scripts/export_depth_model.py: a factory from the user's module, weights and
    a contract JSON -> an ONNX file the depth source loads; an existing output is kept
    without --overwrite."""
    torch = pytest.importorskip("torch")
    main = load_script("export_depth_model").main

    (tmp_path / "tinynet_for_export.py").write_text(TINY_NET)
    monkeypatch.syspath_prepend(str(tmp_path))
    from tinynet_for_export import Tiny

    net = Tiny(channels=6)
    torch.nn.init.constant_(net.out.bias, 0.5)
    torch.save(net.state_dict(), tmp_path / "w.pt")
    spec = {"name": "tiny-cli", "resize": {"mode": "keep_aspect", "max_side": 64}}
    (tmp_path / "spec.json").write_text(json.dumps(spec))
    out = tmp_path / "m.onnx"
    args = ["--factory", "tinynet_for_export:Tiny"]
    args += ["--factory_kwargs", '{"channels": 6}', "--weights", str(tmp_path / "w.pt")]
    args += ["--spec", str(tmp_path / "spec.json"), "--output", str(out)]
    args += ["--height", "64", "--width", "96"]
    assert main(args) == 0
    src = OnnxDepthSource(out)
    assert src.spec.name == "tiny-cli"
    x, _ = preprocess(image(), src.spec)
    with torch.no_grad():
        ref = net(torch.from_numpy(x)).numpy()[0, 0]
    np.testing.assert_allclose(src(image(), camera()).values, ref, rtol=1e-4, atol=1e-5)
    before = out.read_bytes()
    assert main(args) == 1  # exists: kept
    assert "--overwrite" in caplog.text and out.read_bytes() == before
    assert main(args[:1] + ["no_colon"] + args[2:] + ["--overwrite"]) == 1
    assert "package.module:callable" in caplog.text and out.read_bytes() == before


def test_an_interrupted_export_leaves_the_existing_file(tmp_path, monkeypatch):
    """The file is written beside the output and renamed: a failure while saving leaves the
    earlier file (the one --overwrite would replace) as it was, and no partial file."""
    torch = pytest.importorskip("torch")
    onnx_mod = pytest.importorskip("onnx")

    out = tmp_path / "m.onnx"
    out.write_bytes(b"the earlier model")

    def failing_save(proto, path):
        with open(path, "wb") as f:
            f.write(b"half a model")
        raise OSError("disk full")

    monkeypatch.setattr(onnx_mod, "save", failing_save)
    net = torch.nn.Sequential(torch.nn.Conv2d(3, 1, 1), torch.nn.Softplus())
    spec = ModelSpec(resize={"mode": "keep_aspect", "max_side": 64}, output="depth")
    with pytest.raises(OSError, match="disk full"):
        exporter.export_depth_onnx(net, out, spec, height=32, width=32, verify=False)
    assert out.read_bytes() == b"the earlier model"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.onnx"]
