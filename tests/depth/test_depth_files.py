import cv2
import numpy as np
import pycolmap
import pytest

from rectified_colmap.depth import DepthMap
from rectified_colmap.depth.files import (
    ArrayDepthSource,
    FileDepthSource,
    candidate_paths,
    find_depth_file,
    read_colmap_array,
    read_depth_file,
    write_colmap_array,
    write_depth_file,
)


def _depth(h=12, w=16, seed=0):
    rng = np.random.default_rng(seed)
    d = rng.uniform(0.5, 20.0, (h, w)).astype(np.float32)
    d[0, :3] = 0  # invalid pixels
    return d


def _camera(w=16, h=12):
    return pycolmap.Camera(model="PINHOLE", width=w, height=h, params=[20, 20, w / 2, h / 2])


def test_colmap_bin_layout_matches_colmap_reader(tmp_path):
    # COLMAP's read_array: header "w&h&c&", data reshaped (w, h, c) in Fortran order,
    # then transposed to (h, w, c): i.e. one channel is row-major (h, w).
    d = _depth(5, 7)
    p = tmp_path / "a.jpg.geometric.bin"
    p.write_bytes(b"7&5&1&" + d.astype("<f4").tobytes())
    np.testing.assert_array_equal(read_colmap_array(p), d)
    normals = np.random.default_rng(1).standard_normal((5, 7, 3)).astype(np.float32)
    write_colmap_array(tmp_path / "n.bin", normals)
    np.testing.assert_array_equal(read_colmap_array(tmp_path / "n.bin"), normals)
    # channel-major planes for multi-channel (COLMAP stores column-major over (w, h, c))
    raw = (tmp_path / "n.bin").read_bytes()
    data = np.frombuffer(raw[raw.index(b"3&") + 2 :], "<f4")
    np.testing.assert_array_equal(data[:35].reshape(5, 7), normals[..., 0])


@pytest.mark.parametrize("suffix", [".npy", ".npz", ".png", ".bin"])
def test_round_trip(tmp_path, suffix):
    d = _depth()
    p = write_depth_file(tmp_path / f"x{suffix}", d, png_scale=0.001)
    out = read_depth_file(p, png_scale=0.001)
    assert out.kind == "depth" and out.values.shape == d.shape
    if suffix == ".png":
        assert cv2.imread(str(p), cv2.IMREAD_UNCHANGED).dtype == np.uint16
        np.testing.assert_allclose(out.values, d, atol=0.0005 + 1e-6)
    else:
        np.testing.assert_array_equal(out.values, d)
    assert np.isnan(out.to_depth()[0, :3]).all() and np.isfinite(out.to_depth()[1:]).all()


def test_png_scale_and_kind(tmp_path):
    raw = np.array([[0, 1000, 2500], [65535, 1, 7]], np.uint16)
    cv2.imwrite(str(tmp_path / "d.png"), raw)
    out = read_depth_file(tmp_path / "d.png", kind="metric", png_scale=0.01)
    assert out.kind == "metric"
    np.testing.assert_allclose(out.values, raw * 0.01, rtol=1e-6)
    assert np.isnan(out.to_depth()[0, 0])


def test_npz_key_rules(tmp_path):
    d = _depth()
    np.savez(tmp_path / "one.npz", whatever=d)
    np.testing.assert_array_equal(read_depth_file(tmp_path / "one.npz").values, d)
    np.savez(tmp_path / "named.npz", depth=d, conf=d * 0)
    np.testing.assert_array_equal(read_depth_file(tmp_path / "named.npz").values, d)
    np.savez(tmp_path / "kind.npz", depth=1 / (d + 1), kind="disparity")
    assert read_depth_file(tmp_path / "kind.npz").kind == "disparity"
    np.savez(tmp_path / "two.npz", a=d, b=d)
    with pytest.raises(ValueError, match="two.npz"):
        read_depth_file(tmp_path / "two.npz")


@pytest.mark.parametrize(
    "case",
    [
        "npy_garbage",
        "npz_garbage",
        "png_garbage",
        "png_8bit",
        "bin_truncated",
        "bin_header",
        "npy_3d",
        "npy_pickle",
    ],
)
def test_corrupt_files_raise_naming_the_file(tmp_path, case):
    d = _depth()
    if case == "npy_garbage":
        p = tmp_path / "a.npy"
        p.write_bytes(b"not numpy at all")
    elif case == "npz_garbage":
        p = tmp_path / "a.npz"
        p.write_bytes(b"PK\x03\x04garbage")
    elif case == "png_garbage":
        p = tmp_path / "a.png"
        p.write_bytes(b"\x89PNG\r\n\x1a\nbroken")
    elif case == "png_8bit":
        p = tmp_path / "a.png"
        cv2.imwrite(str(p), (d * 10).astype(np.uint8))
    elif case == "bin_truncated":
        p = write_depth_file(tmp_path / "a.bin", d)
        p.write_bytes(p.read_bytes()[:-10])
    elif case == "bin_header":
        p = tmp_path / "a.bin"
        p.write_bytes(b"\x00\x01\x02" * 100)
    elif case == "npy_3d":
        p = tmp_path / "a.npy"
        np.save(p, np.zeros((4, 5, 3)))
    else:
        p = tmp_path / "a.npy"
        np.save(p, np.array([{"a": 1}], dtype=object), allow_pickle=True)
    with pytest.raises(ValueError, match=str(p.name)):
        read_depth_file(p)


def test_lookup_order(tmp_path):
    name = "sub/0001.jpg"
    expected = [
        "sub/0001.jpg.npy",
        "sub/0001.npy",
        "sub/0001.jpg.npz",
        "sub/0001.npz",
        "sub/0001.jpg.png",
        "sub/0001.png",
        "sub/0001.jpg.geometric.bin",
        "sub/0001.jpg.photometric.bin",
        "stereo/depth_maps/sub/0001.jpg.geometric.bin",
        "stereo/depth_maps/sub/0001.jpg.photometric.bin",
    ]
    assert [p.relative_to(tmp_path).as_posix() for p in candidate_paths(tmp_path, name)] == expected
    assert find_depth_file(tmp_path, name) is None
    # create them from last to first: each new one must win
    for i, rel in enumerate(reversed(expected)):
        write_depth_file(tmp_path / rel, _depth(seed=i))
        assert find_depth_file(tmp_path, name) == tmp_path / rel


def test_file_source(tmp_path):
    d = _depth()
    write_depth_file(tmp_path / "stereo/depth_maps/a/b.jpg.photometric.bin", d)
    src = FileDepthSource(tmp_path, kind="metric")
    out = src(None, _camera(), "a/b.jpg")
    assert isinstance(out, DepthMap) and out.kind == "metric"
    np.testing.assert_array_equal(out.values, d)
    assert src(None, _camera(), "a/missing.jpg") is None
    (tmp_path / "bad.jpg.npy").write_bytes(b"junk")
    with pytest.raises(ValueError, match="bad.jpg.npy"):
        src(None, _camera(), "bad.jpg")
    np.save(tmp_path / "tr.jpg.npy", d.T)  # transposed map: wrong aspect ratio
    with pytest.raises(ValueError, match="tr.jpg.npy.*aspect"):
        src(None, _camera(), "tr.jpg")
    with pytest.raises(ValueError, match="does not exist"):
        FileDepthSource(tmp_path / "nope")


def test_array_source():
    d = _depth()
    src = ArrayDepthSource({"a.jpg": d, "b.jpg": DepthMap(1 / (d + 1), "disparity")}, kind="metric")
    assert src(None, None, "a.jpg").kind == "metric"
    assert src(None, None, "b.jpg").kind == "disparity"
    assert src(None, None, "c.jpg") is None
