"""Model registry: cache folder, download (against a local HTTP server), verification,
resolution, and the `models` CLI."""

import hashlib
import http.server
import logging
import socket
import threading

import numpy as np
import pytest

from rectified_colmap.depth import registry
from rectified_colmap.depth.contract import ModelSpec
from rectified_colmap.depth.registry import ModelDownloadError, ModelEntry

onnx = pytest.importorskip("onnx")


def tiny_onnx_bytes() -> bytes:
    """(N, 3, H, W) -> mean over channels (N, 1, H, W); no metadata."""
    from onnx import TensorProto, helper

    x = helper.make_tensor_value_info("x", TensorProto.FLOAT, ["N", 3, "H", "W"])
    y = helper.make_tensor_value_info("y", TensorProto.FLOAT, None)
    node = helper.make_node("ReduceMean", ["x"], ["y"], axes=[1], keepdims=1)
    model = helper.make_model(
        helper.make_graph([node], "t", [x], [y]), opset_imports=[helper.make_opsetid("", 17)]
    )
    model.ir_version = 9
    return model.SerializeToString()


PAYLOAD = tiny_onnx_bytes()
SHA = hashlib.sha256(PAYLOAD).hexdigest()


class Handler(http.server.BaseHTTPRequestHandler):
    requests: list[str] = []

    def do_GET(self):
        Handler.requests.append(self.path)
        if self.path == "/model.onnx":
            self.send_response(200)
            self.send_header("Content-Length", str(len(PAYLOAD)))
            self.end_headers()
            self.wfile.write(PAYLOAD)
        elif self.path == "/truncated.onnx":
            self.send_response(200)
            self.send_header("Content-Length", str(len(PAYLOAD) + 1000))
            self.end_headers()
            self.wfile.write(PAYLOAD[: len(PAYLOAD) // 2])
            self.wfile.flush()
            self.close_connection = True
        elif self.path == "/corrupt.onnx":
            data = bytearray(PAYLOAD)
            data[10] ^= 0xFF
            self.send_response(200)
            self.send_header("Content-Length", str(len(data)))
            self.end_headers()
            self.wfile.write(bytes(data))
        else:
            self.send_error(404)

    def log_message(self, *args):
        pass


@pytest.fixture(scope="module")
def server():
    srv = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Handler)
    t = threading.Thread(target=srv.serve_forever, daemon=True)
    t.start()
    yield f"http://127.0.0.1:{srv.server_address[1]}"
    srv.shutdown()
    srv.server_close()


@pytest.fixture
def cache(tmp_path, monkeypatch):
    d = tmp_path / "cache"
    monkeypatch.setenv("RECTIFIED_COLMAP_CACHE", str(d))
    return d


def add_entry(monkeypatch, url, name="test-model", sha256=None, size=None, spec=None):
    entry = ModelEntry(
        name=name,
        filename=f"{name}.onnx",
        licence="MIT",
        description="test",
        url=url,
        sha256=sha256,
        size=size,
        spec=spec,
    )
    monkeypatch.setitem(registry.REGISTRY, name, entry)
    return entry


def test_cache_dir_env(tmp_path, monkeypatch):
    monkeypatch.setenv("RECTIFIED_COLMAP_CACHE", str(tmp_path / "a"))
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert registry.cache_dir() == tmp_path / "a"
    monkeypatch.delenv("RECTIFIED_COLMAP_CACHE")
    assert registry.cache_dir() == tmp_path / "xdg" / "rectified-colmap"
    monkeypatch.delenv("XDG_CACHE_HOME")
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    assert registry.cache_dir() == tmp_path / "home" / ".cache" / "rectified-colmap"


def test_builtin_entries():
    for name in ("rectsift-lite0", "depth-anything-v2-small", "midas-v2.1-small"):
        e = registry.get_entry(name)
        assert e.licence and e.filename.endswith(".onnx")
    assert registry.get_entry("rectsift-lite0").embedded
    da = registry.get_entry("depth-anything-v2-small")
    assert da.url.startswith("https://") and da.spec.output == "disparity"
    assert da.spec.resize["multiple_of"] == 14
    assert registry.get_entry("midas-v2.1-small").url.endswith("model-small.onnx")


def test_download_unpinned_warns_and_caches(server, cache, monkeypatch, caplog):
    add_entry(monkeypatch, f"{server}/model.onnx")
    Handler.requests.clear()
    with caplog.at_level(logging.WARNING, logger="rectified_colmap.depth.registry"):
        path = registry.download("test-model", progress=False)
    assert path == cache / "test-model.onnx" and path.read_bytes() == PAYLOAD
    assert SHA in caplog.text and "RECTIFIED_COLMAP_SHA256_TEST_MODEL" in caplog.text
    assert registry.download("test-model") == path and Handler.requests == ["/model.onnx"]
    assert sorted(p.name for p in cache.iterdir()) == ["test-model.onnx"]


def test_download_pinned_by_env(server, cache, monkeypatch, caplog):
    add_entry(monkeypatch, f"{server}/model.onnx", sha256="0" * 64)
    monkeypatch.setenv("RECTIFIED_COLMAP_SHA256_TEST_MODEL", SHA.upper())
    with caplog.at_level(logging.WARNING):
        path = registry.download("test-model", progress=False)
    assert path.read_bytes() == PAYLOAD and "NO pinned" not in caplog.text


@pytest.mark.parametrize("case", ["sha_mismatch", "corrupt", "truncated", "size", "404"])
def test_download_failures_leave_nothing(server, cache, monkeypatch, case):
    url = {"truncated": "/truncated.onnx", "corrupt": "/corrupt.onnx", "404": "/missing.onnx"}.get(
        case, "/model.onnx"
    )
    add_entry(
        monkeypatch,
        server + url,
        sha256="ab" * 32 if case == "sha_mismatch" else SHA if case == "corrupt" else None,
        size=len(PAYLOAD) + 1 if case == "size" else None,
    )
    match = {
        "sha_mismatch": "sha256 mismatch",
        "corrupt": "sha256 mismatch",
        "truncated": "truncated|closed|IncompleteRead|bytes",
        "size": "expected",
        "404": "404",
    }[case]
    with pytest.raises(ModelDownloadError, match=match) as e:
        registry.download("test-model", progress=False)
    assert url in str(e.value)
    assert list(cache.iterdir()) == []  # no partial or unverified file


def test_offline_error_is_clear(cache, monkeypatch):
    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()  # nothing listens there
    url = f"http://127.0.0.1:{port}/model.onnx"
    add_entry(monkeypatch, url, sha256=SHA)
    with pytest.raises(ModelDownloadError) as e:
        registry.download("test-model", progress=False, timeout=5)
    msg = str(e.value)
    assert url in msg and str(cache / "test-model.onnx") in msg and SHA in msg
    assert "place it" in msg
    assert not any(cache.iterdir())


def test_resolve_model(tmp_path, cache, monkeypatch):
    f = tmp_path / "mine.onnx"
    f.write_bytes(PAYLOAD)
    assert registry.resolve_model(str(f)) == f
    with pytest.raises(ValueError, match="unknown depth model 'nonsense'.*rectsift-lite0"):
        registry.resolve_model("nonsense")
    with pytest.raises(FileNotFoundError, match="missing.onnx"):
        registry.resolve_model(tmp_path / "missing.onnx")
    monkeypatch.setattr(registry, "PACKAGE_MODELS", tmp_path / "pkg")
    with pytest.raises(FileNotFoundError, match="embedded depth model 'rectsift-lite0'"):
        registry.resolve_model("rectsift-lite0")
    add_entry(monkeypatch, "http://127.0.0.1:9/none.onnx")
    with pytest.raises(FileNotFoundError, match="models download test-model"):
        registry.resolve_model("test-model", download_missing=False)


def test_load_depth_source_uses_registry_spec(server, cache, monkeypatch):
    spec = ModelSpec(
        scale=1.0,
        mean=[0.0],
        std=[1.0],
        output="disparity",
        resize={"mode": "fixed", "width": 32, "height": 24},
    )
    add_entry(monkeypatch, f"{server}/model.onnx", sha256=SHA, spec=spec)
    src = registry.load_depth_source("test-model", num_threads=1)
    img = np.full((30, 40, 3), 90, np.uint8)
    d = src(img, None, "a.jpg")
    assert d.kind == "disparity" and d.values.shape == (24, 32)
    np.testing.assert_allclose(d.values, 90.0)


def test_models_cli(server, cache, monkeypatch, capsys):
    from rectified_colmap.cli import main

    add_entry(monkeypatch, f"{server}/model.onnx", sha256=SHA, spec=ModelSpec(output="disparity"))
    assert main(["models", "list"]) == 0
    out = capsys.readouterr().out
    assert "depth-anything-v2-small" in out and "Apache-2.0" in out and str(cache) in out
    assert main(["models", "download", "test-model", "--no_progress"]) == 0
    assert (cache / "test-model.onnx").is_file()
    capsys.readouterr()
    assert main(["models", "info", "test-model"]) == 0
    out = capsys.readouterr().out
    assert '"output": "disparity"' in out and SHA in out
    assert main(["models", "download", "no-such-model"]) == 1
