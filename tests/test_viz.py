"""The --visualize pictures (rectified_colmap.viz): colours that mean one orientation in every
image, a caption and a legend on each picture, the overview of plain vs rectified keypoints.

Synthetic ImageResults on a 160x120 pinhole camera (no SIFT, no depth network) keep these
fast; one extraction without depth checks that every image gets its overview."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from rectified_colmap import camera as cam_utils
from rectified_colmap import viz
from rectified_colmap.extraction import extract
from rectified_colmap.features import Features
from rectified_colmap.pipeline import ImageResult
from rectified_colmap.planes import Patch, PlaneResult
from rectified_colmap.rectify import plan_rectification, rectified_to_image
from rectified_colmap.views import viewing_coverage, viewing_masks

W, H = 160, 120
GRID = (30, 40)  # work grid (h, w)
CAMERA = cam_utils.make_camera("PINHOLE", [100, 100, 80, 60], W, H)
GREY = np.full((H, W, 3), 128, np.uint8)


def _pitch(deg: float) -> np.ndarray:
    """Rotation about the camera's x axis (a camera pitched up or down)."""
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


R = _pitch(20.0)
GROUND = R @ np.array([0.0, -1.0, 0.0])  # faces up (the image's -y) and the camera
WALL = R @ np.array([0.6, 0.0, -0.8])  # a facade facing right (normal towards +x)
THIRD = np.cross(GROUND, WALL)


def _grid_halves():
    top = np.zeros(GRID, bool)
    top[: GRID[0] // 2] = True
    return top, ~top


def _result(directions, wall_label, ground_label, features=None, ground_axis=1) -> ImageResult:
    """Wall on the top half, ground on the bottom half, the ground rectified (patch 0); its
    labels and directions as given (the cluster indices differ from image to image)."""
    top, bottom = _grid_halves()
    labels = np.where(top, wall_label, ground_label).astype(np.int8)
    patches = [Patch(bottom, ground_axis, GROUND, 0.5)]
    rect = plan_rectification(CAMERA, patches[0], 0)
    assert rect is not None
    cover = viewing_coverage(viewing_masks(CAMERA, [rect], patches, GRID, 80.0))
    planes = PlaneResult(np.asarray(directions), np.ones(3) / 3, labels, patches)
    return ImageResult(
        features if features is not None else Features.empty(), planes, [rect], cover
    )


def _picture(result) -> np.ndarray:
    """The image part (above the band) of the planes picture."""
    return viz.draw_planes(GREY, result)[:H, :W]


def test_a_plane_orientation_has_one_colour_in_every_image():
    # image 1: the wall is direction 0 (+), the ground direction 1 (+)
    a = _result([WALL, GROUND, THIRD], wall_label=0, ground_label=2)
    # image 2: other cluster indices and signs for the same two planes
    b = _result([-GROUND, THIRD, WALL], wall_label=4, ground_label=1)
    pa, pb = _picture(a), _picture(b)
    assert np.array_equal(pa, pb)
    # inside each half, away from the outline and tags: one colour per plane
    wall, ground = pa[15, 10], pa[100, 10]
    assert not np.array_equal(wall, ground)
    # what the labels' colours are made of: the normals, whatever their order
    lut = viz.label_colours(np.array([WALL, GROUND, THIRD]))
    lut2 = viz.label_colours(np.array([-GROUND, THIRD, WALL]))
    assert np.array_equal(lut[0], lut2[4]) and np.array_equal(lut[2], lut2[1])


def test_ground_is_the_ground_colour_and_walls_take_their_facing():
    a = _result([WALL, GROUND, THIRD], wall_label=0, ground_label=2)
    ground_px = _picture(a)[100, 10].astype(float)
    expected = 0.5 * 128 + 0.5 * np.array(viz.GROUND_BGR)
    assert np.abs(ground_px - expected).max() <= 1
    colours = viz.orientation_colours(
        np.array(
            [
                [0.0, -1.0, 0.0],  # ground seen level
                GROUND,  # ground seen pitched
                [0.0, 1.0, 0.0],  # ceiling
                [0.0, 0.0, -1.0],  # wall facing the camera
                [-1.0, 0.0, 0.0],  # wall facing left
                [1.0, 0.0, 0.0],  # wall facing right
                [np.nan] * 3,
            ]
        )
    )
    assert (colours[:2] == viz.GROUND_BGR).all()
    assert (colours[2] == viz.CEILING_BGR).all()
    assert (colours[6] == viz.NONE_BGR).all()
    walls = colours[3:6].astype(int)
    assert len({tuple(c) for c in walls}) == 3  # left, camera, right: three colours
    for special in (viz.GROUND_BGR, viz.CEILING_BGR):  # no wall looks like ground or ceiling
        assert (np.abs(walls - special).sum(1) > 100).all()
    # a continuous wheel: 5 degrees of azimuth, a small change of colour
    az = np.radians([30.0, 35.0])
    near = viz.orientation_colours(np.stack([np.sin(az), [0, 0], -np.cos(az)], 1)).astype(int)
    assert np.abs(near[0] - near[1]).max() < 40
    assert viz.orientation_text(GROUND) == "ground"
    assert viz.orientation_text(WALL).startswith("wall facing right")
    assert viz.tilt_deg(np.array([0.0, 0.0, -1.0])) == pytest.approx(0.0)
    # ground seen by a camera pitched up by 2 degrees: the normal is 92 degrees from -z, the
    # plane 88 degrees from the image plane; labels stay within 0-90
    up = np.array([0.0, -np.cos(np.radians(2.0)), np.sin(np.radians(2.0))])
    assert viz.tilt_deg(up) == pytest.approx(88.0)
    rng = np.random.default_rng(0)
    tilts = [viz.tilt_deg(n) for n in rng.normal(size=(200, 3))]
    assert 0.0 <= min(tilts) and max(tilts) <= 90.0
    assert viz.tilt_deg(WALL) == pytest.approx(np.degrees(np.arccos(0.8 * np.cos(0.349066))), 1e-3)


def _features() -> tuple[Features, np.ndarray, np.ndarray]:
    """Plain keypoints on the wall (top), rectified ones on the ground (bottom, patch 0)."""
    plain = np.array([[30.5, 20.5], [120.5, 30.5]])
    rect = np.array([[40.5, 95.5], [110.5, 105.5]])
    xy = np.concatenate([plain, rect])
    n = len(xy)
    f = Features(
        xy, np.tile(2 * np.eye(2), (n, 1, 1)), np.zeros((n, 128), np.uint8), np.r_[-1, -1, 0, 0]
    )
    return f, plain, rect


def test_overview_colours_plain_and_rectified_keypoints():
    f, plain, rect = _features()
    out = viz.draw_overview(GREY, _result([WALL, GROUND, THIRD], 0, 2, f))
    assert out.shape[0] > H
    for xy in plain:
        x, y = np.round(xy - 0.5).astype(int)  # COLMAP -> OpenCV pixel
        assert tuple(out[y, x]) == viz.PLAIN_BGR
    for xy in rect:
        x, y = np.round(xy - 0.5).astype(int)
        assert tuple(out[y, x]) == viz.RECTIFIED_BGR


def _band_has_text(band: np.ndarray) -> bool:
    bg = np.array(viz.BAND_BGR)
    text = (band.astype(int) - bg).sum(-1) > 300  # light text on the dark band
    return text.sum() > 50 and (band == bg).all(-1).mean() > 0.5


def test_each_picture_has_a_caption_and_legend_band(tmp_path):
    f, _, _ = _features()
    result = _result([WALL, GROUND, THIRD], 0, 2, f)
    paths = viz.save_visualizations(tmp_path, "sub/a.png", GREY, CAMERA, result)
    names = sorted(p.name for p in paths)
    assert names == ["sub_a.png.overview.png", "sub_a.png.patches.png", "sub_a.png.planes.png"]
    for p in paths:
        img = cv2.imread(str(p))
        if p.name.endswith("patches.png"):
            # tiles of at most 300 px, their two-line headers, then the band
            assert img.shape[0] > 300
            band = img[-img.shape[0] // 4 :]
        else:
            assert img.shape[0] > H and img.shape[1] >= W
            band = img[H:]
        assert _band_has_text(band), p.name


def test_plane_hypotheses_from_vanishing_points_are_dashed():
    solid = viz.draw_planes(GREY, _result([WALL, GROUND, THIRD], 0, 2))[:H, :W]
    dashed = viz.draw_planes(GREY, _result([WALL, GROUND, THIRD], 0, 2, ground_axis=-1))[:H, :W]
    outline = (solid == viz.OUTLINE_BGR).all(-1)
    outline[70:110] = False  # the tag "#0" inside the region
    assert outline.sum() > 100
    kept = (dashed[outline] == viz.OUTLINE_BGR).all(-1).mean()
    assert 0.2 < kept < 0.8


def test_patch_dots_are_where_their_features_are():
    a = _result([WALL, GROUND, THIRD], 0, 2)
    rect = a.rectifications[0]
    w, h = rect.size
    xy_rect = np.array([[0.3 * w, 0.4 * h], [0.7 * w, 0.8 * h]])
    xy_img, _ = rectified_to_image(CAMERA, rect, xy_rect)
    np.testing.assert_allclose(viz._to_rectified(CAMERA, rect, xy_img), xy_rect, atol=1e-6)


def test_images_without_planes_get_an_overview(tmp_path):
    images = tmp_path / "images"
    images.mkdir()
    rng = np.random.default_rng(0)
    noise = cv2.GaussianBlur(rng.integers(0, 255, (H, W), np.uint8), (0, 0), 1.5)
    cv2.imwrite(str(images / "a.png"), cv2.normalize(noise, None, 0, 255, cv2.NORM_MINMAX))
    s = extract(
        images,
        database=tmp_path / "db.db",
        reader={"camera_model": "PINHOLE", "camera_params": "100,100,80,60"},
        depth={"model": "none"},
        run={"visualize": tmp_path / "viz", "progress": False},
    )
    assert s.ok and s.done == ["a.png"]
    assert sorted(p.name for p in (tmp_path / "viz").iterdir()) == ["a.png.overview.png"]


def test_label_overlay_without_directions_is_grey():
    labels = np.zeros(GRID, np.int8)
    out = viz.label_overlay(GREY, labels, None)
    expected = 0.5 * 128 + 0.5 * np.array(viz.NONE_BGR)
    assert np.abs(out.reshape(-1, 3) - expected).max() <= 1
