"""Image files: sizes from headers agree with decoding; listing and decoding errors."""

import glob
import os
import struct
from pathlib import Path

import cv2
import numpy as np
import pytest

from rectified_colmap.io.images import (
    ImageError,
    _header_size,
    decode_image,
    image_size,
    list_images,
)

SHARED = Path(__file__).resolve().parents[3] / "shared" / "data"


@pytest.mark.parametrize(
    "ext,params",
    [
        (".jpg", []),
        (".jpg", [cv2.IMWRITE_JPEG_PROGRESSIVE, 1]),
        (".png", []),
        (".tif", []),
        (".bmp", []),
        (".webp", []),
    ],
)
def test_size_from_header_equals_decoded_size(tmp_path, ext, params):
    rng = np.random.default_rng(0)
    for w, h in ((457, 123), (1, 300), (2048, 1536)):
        img = rng.integers(0, 255, (h, w, 3), dtype=np.uint8)
        path = tmp_path / f"a{ext}"
        assert cv2.imwrite(str(path), img, params)
        assert image_size(path) == (w, h)
        if ext in (".jpg", ".png"):
            assert _header_size(path) == (w, h)  # no decode needed


def test_jpeg_with_exif_and_other_segments_before_the_frame(tmp_path):
    data = cv2.imencode(".jpg", np.zeros((77, 99, 3), np.uint8))[1].tobytes()
    exif = b"Exif\x00\x00" + bytes(200)
    app1 = b"\xff\xe1" + struct.pack(">H", len(exif) + 2) + exif
    com = b"\xff\xfe" + struct.pack(">H", 7) + b"hello"
    path = tmp_path / "e.jpg"
    path.write_bytes(data[:2] + app1 + b"\xff\xff" + com + data[2:])  # with a fill byte
    assert _header_size(path) == (99, 77)
    assert decode_image(path)[0].shape == (77, 99, 3)


@pytest.mark.skipif(not SHARED.is_dir(), reason="needs ../shared/data (real photos)")
def test_header_sizes_of_real_photos():
    paths = sorted(glob.glob(str(SHARED / "**" / "*.jpg"), recursive=True))[:150]
    assert paths
    for p in paths:
        im = cv2.imread(p, cv2.IMREAD_GRAYSCALE | cv2.IMREAD_IGNORE_ORIENTATION)
        assert _header_size(Path(p)) == (im.shape[1], im.shape[0]), p


def test_not_images_and_listing(tmp_path):
    (tmp_path / "x.jpg").write_bytes(b"\xff\xd8\xff\xe0garbage")
    (tmp_path / "y.png").write_bytes(b"not a png")
    for name in ("x.jpg", "y.png"):
        with pytest.raises(ImageError, match="cannot decode"):
            image_size(tmp_path / name)
    with pytest.raises(ImageError, match="no such image file"):
        image_size(tmp_path / "missing.jpg")
    (tmp_path / "sub").mkdir()
    cv2.imwrite(str(tmp_path / "sub" / "b.PNG"), np.zeros((8, 8), np.uint8))
    (tmp_path / "notes.txt").write_text("x")
    assert list_images(tmp_path) == ["sub/b.PNG", "x.jpg", "y.png"]
    assert list_images(tmp_path, ["b", "a", "b"]) == ["b", "a"]
    with pytest.raises(FileNotFoundError, match="not a folder"):
        list_images(tmp_path / "nope")


def _truncated_jpeg(path: Path) -> Path:
    """A JPEG cut at 60 % of its bytes (no end-of-image marker)."""
    rng = np.random.default_rng(0)
    ok, buf = cv2.imencode(".jpg", rng.integers(0, 255, (240, 320, 3), np.uint8))
    data = buf.tobytes()
    path.write_bytes(data[: len(data) * 6 // 10])
    return path


def test_truncated_jpeg_gives_only_our_warning(tmp_path, capfd, monkeypatch):
    """libjpeg's own 'Premature end of JPEG file' (printed by the C library on fd 2) is
    silenced; the project's one-line warning stays. fd 2 works again afterwards, also
    after a decode that raised, and after concurrent decodes in threads."""
    from concurrent.futures import ThreadPoolExecutor

    import rectified_colmap.io.images as images

    cut = _truncated_jpeg(tmp_path / "cut.jpg")
    rgb, warnings = decode_image(cut)
    assert rgb.shape == (240, 320, 3)
    assert warnings == ["truncated JPEG (no end-of-image marker): the missing part decodes as grey"]
    with ThreadPoolExecutor(4) as ex:  # concurrent decodes share one redirection
        assert all(w == warnings for _, w in ex.map(decode_image, [cut] * 16))

    def failing_imread(*args):
        raise RuntimeError("decoder crashed")

    monkeypatch.setattr(images.cv2, "imread", failing_imread)
    with pytest.raises(RuntimeError, match="decoder crashed"):
        decode_image(cut)
    monkeypatch.undo()
    os.write(2, b"fd 2 is back\n")
    err = capfd.readouterr().err
    assert "JPEG" not in err
    assert err == "fd 2 is back\n"
