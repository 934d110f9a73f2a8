"""Sky pseudo-labels (training.sky) and the sky-planar metric (training.evaluate_sky)."""

from pathlib import Path

import cv2
import numpy as np
import pytest

from rectified_colmap.depth import DepthMap
from rectified_colmap_research.training.evaluate_sky import (
    IGNORE,
    find_items,
    guess_camera,
    read_mask,
    sky_planar_fraction,
    upsample_nearest,
)
from rectified_colmap_research.training.sky import (
    NOT_SKY,
    SKY,
    UNKNOWN,
    above_line,
    sky_pseudo_label,
)

LABELS = Path(__file__).resolve().parents[1] / "data" / "sky_masks"
DATA = Path("/work/shared/data")


def sky_over_texture(h: int = 240, w: int = 320, top: int = 100) -> np.ndarray:
    """(h, w, 3) uint8: a smooth light-blue gradient in rows [0, top) over strong texture
    (random orange and brown 4 x 4 blocks, like bricks)."""
    rng = np.random.default_rng(0)
    img = np.zeros((h, w, 3), np.uint8)
    t = np.linspace(0.0, 1.0, top)[:, None, None]
    img[:top] = (np.array([110, 160, 225]) * (1 - t) + np.array([150, 190, 235]) * t).astype(
        np.uint8
    )
    bricks = np.array([[200, 110, 70], [70, 35, 25]], np.uint8)  # orange / dark brown
    noise = bricks[rng.integers(0, 2, ((h - top) // 4, w // 4))]
    img[top:] = cv2.resize(noise, (w, h - top), interpolation=cv2.INTER_NEAREST)
    return img


def test_pseudo_label_sky_over_texture():
    img = sky_over_texture()
    lab = sky_pseudo_label(img)
    assert lab.shape == img.shape[:2] and lab.dtype == np.uint8
    assert set(np.unique(lab)) <= {SKY, NOT_SKY, UNKNOWN}
    assert (lab[:85] == SKY).mean() > 0.99  # the smooth band, minus the uncertain margin
    assert not (lab[100:] == SKY).any()
    # texture is NOT_SKY, except sky-coloured texture within 8 % of the image of the sky
    # (it could be branches with sky between them): UNKNOWN there
    assert (lab[130:] == NOT_SKY).mean() > 0.9  # flat clusters of equal bricks: UNKNOWN
    assert (lab[100:130] == NOT_SKY).mean() > 0.5


def test_pseudo_label_respects_horizon():
    img = sky_over_texture()
    y0 = 50.0
    for sign in (1.0, -1.0):  # either orientation of the same line y = y0 (slightly tilted)
        horizon = sign * np.array([0.01, -1.0, y0 - 0.01 * 160])
        lab = sky_pseudo_label(img, horizon)
        ys = (0.01 * np.arange(320) + horizon[2] * sign)[None, :]  # the line's y per column
        rows = np.arange(240)[:, None] + 0.5
        assert not (lab[rows > ys] == SKY).any()
        assert (lab[rows > ys + 3] == NOT_SKY).all()
        assert (lab[:40] == SKY).mean() > 0.99


def test_above_line_orientation():
    d = above_line((0.0, -1.0, 10.0), (20, 4))  # y = 10, value grows upward
    np.testing.assert_allclose(d[:, 0], 10.0 - (np.arange(20) + 0.5))
    np.testing.assert_allclose(above_line((0.0, 1.0, -10.0), (20, 4)), d)


def test_pseudo_label_no_sky_in_a_textured_image():
    rng = np.random.default_rng(1)
    img = cv2.resize(
        rng.integers(0, 256, (60, 80, 3), dtype=np.uint8),
        (320, 240),
        interpolation=cv2.INTER_NEAREST,
    )
    assert not (sky_pseudo_label(img) == SKY).any()


def _write_case(tmp_path: Path, w: int, h: int, sky_rows: int):
    img = np.full((h, w, 3), 128, np.uint8)
    ip = tmp_path / f"img_{w}.png"
    cv2.imwrite(str(ip), img)
    mask = np.zeros((h, w), np.uint8)
    mask[:sky_rows] = 1
    mask[:sky_rows, : w // 8] = IGNORE  # ignored pixels count nowhere
    mask[-4:, -w // 8 :] = IGNORE
    mp = tmp_path / f"mask_{w}.png"
    cv2.imwrite(str(mp), mask)
    return ip, mp, mask


@pytest.mark.parametrize("w,h,sky_rows", [(128, 96, 40), (1280, 960, 481)])
def test_sky_planar_fraction(tmp_path, w, h, sky_rows):
    ip, mp, mask = _write_case(tmp_path, w, h, sky_rows)
    plane = np.full((h, w), 5.0, np.float32)  # fronto-parallel plane everywhere
    res = sky_planar_fraction(lambda p, rgb: DepthMap(plane, "depth"), [(ip, mp, None)])
    assert res["pooled"]["sky_planar"] == 1.0
    assert res["pooled"]["sky_patch"] == 1.0
    assert res["pooled"]["notsky_planar"] == 1.0
    assert res["counts"]["sky"] == int((mask == 1).sum())

    holed = np.where(mask == 0, plane, 0.0).astype(np.float32)  # no depth on sky + ignore
    cut = np.where(np.arange(h)[:, None] < sky_rows, 0.0, plane).astype(np.float32)
    res = sky_planar_fraction(lambda p, rgb: DepthMap(cut, "depth"), [(ip, mp, None)] * 2)
    assert res["num_images"] == 2
    # Not-sky pixels next to the cut lose their normal (their 5 x 5 window is partly
    # invalid): two rows of the work grid, plus the image row straddling the boundary.
    s = w // min(w, 640)  # image rows per work-grid row
    lost = 2 * (2 * s + (sky_rows % s)) * w  # pixels, over the two images
    c = res["counts"]
    assert c["notsky_planar"] >= c["notsky"] - lost
    if (w, h) == (128, 96):  # the work grid is the image: exact
        assert res["pooled"]["sky_planar"] == 0.0
    else:
        # 1280 x 960 runs on a 640 x 480 work grid: grid row 240 covers image rows 480-481,
        # which straddle the sky boundary (row 481), so one image row of sky may take the
        # label of its cell; nothing else may.
        assert res["pooled"]["sky_planar"] <= 1.0 / sky_rows + 1e-12
    res = sky_planar_fraction(lambda p, rgb: DepthMap(holed, "depth"), [(ip, mp, None)])
    assert res["rows"][0]["sky"] == res["counts"]["sky"]
    if (w, h) == (128, 96):
        assert res["pooled"]["sky_planar"] == 0.0


def test_upsample_nearest_and_guess_camera():
    a = np.arange(6).reshape(2, 3)
    up = upsample_nearest(a, 6, 4)
    np.testing.assert_array_equal(up, np.repeat(np.repeat(a, 2, 0), 2, 1))
    cam = guess_camera(1024, 768)
    np.testing.assert_allclose(cam.params, [1.2 * 1024, 512.0, 384.0])


def test_sky_planar_fraction_rejects_bad_masks(tmp_path):
    ip, mp, mask = _write_case(tmp_path, 64, 48, 10)
    cv2.imwrite(str(mp), np.full((48, 64), 7, np.uint8))
    with pytest.raises(ValueError, match="outside"):
        read_mask(mp)
    cv2.imwrite(str(mp), np.zeros((40, 64), np.uint8))
    with pytest.raises(ValueError, match="mask"):
        sky_planar_fraction(lambda p, rgb: DepthMap(np.ones((48, 64)), "depth"), [(ip, mp, None)])


def test_committed_masks_are_valid():
    masks = sorted(LABELS.glob("*/*.png"))
    assert len(masks) >= 24
    if not (DATA / "real-pool").is_dir():
        pytest.skip(f"{DATA} (shared data) is absent: cannot check the mask sizes")
    items = find_items(LABELS, DATA)
    assert len(items) == len(masks)
    for image, mask_path, camera in items:
        m = read_mask(mask_path)
        H, W = cv2.imread(str(image), cv2.IMREAD_REDUCED_GRAYSCALE_2).shape
        assert abs(m.shape[0] - 2 * H) <= 1 and abs(m.shape[1] - 2 * W) <= 1, mask_path
        assert (m == SKY).any() and (m == NOT_SKY).any(), mask_path
        if camera is not None:
            assert (camera.width, camera.height) == m.shape[::-1]
        if "eurasian-cities" in str(mask_path):
            assert int(Path(mask_path).stem) % 2 == 1, "held-out split: odd indices only"
