"""research/scripts/diagnose_orientation.py: the orientation error of the patches on the
plane, exact where the depth is the plane's."""

import numpy as np
import pytest
from scripts_util import load_script

from rectified_colmap.geometry import axis_angle_rotation
from rectified_colmap.planes import HYPOTHESIS_AXIS, Patch
from rectified_colmap_research.evaluation.extreme_pairs import pinhole_camera
from rectified_colmap_research.evaluation.oracle import plane_depth

diag = load_script("diagnose_orientation")


def test_region_mask_is_the_cells_whose_centre_is_inside():
    left = [np.array([[-0.5, -0.5], [320.0, -0.5], [320.0, 480.5], [-0.5, 480.5]])]
    mask = diag.region_mask(left, (640, 480), (30, 40))
    assert mask[:, :20].all() and not mask[:, 20:].any()


def test_best_patch_error_counts_patches_on_the_plane_only():
    n = np.array([0.0, -0.6, -0.8])
    on = np.zeros((10, 10), bool)
    on[:, :5] = True
    inside, outside = np.zeros_like(on), np.zeros_like(on)
    inside[2:6, 1:4] = True
    outside[2:6, 6:9] = True
    off10 = axis_angle_rotation(np.array([1.0, 0.0, 0.0]), np.deg2rad(10.0)) @ n
    patches = [Patch(outside, 0, n, 0.1), Patch(inside, 1, off10, 0.1)]
    assert diag.best_patch_error(patches, on, n) == pytest.approx(10.0, abs=1e-9)
    assert diag.best_patch_error(patches[:1], on, n) != diag.best_patch_error(patches[:1], on, n)
    flipped = [Patch(inside, HYPOTHESIS_AXIS, -n, 0.1)]  # sign-free
    assert diag.best_patch_error(flipped, on, n) == pytest.approx(0.0, abs=1e-6)


def test_upright_turns_undo_the_roll():
    assert [diag.upright_turns(r) for r in (0, 90, 180, 270, 350, 85, 200)] == [0, 3, 2, 1, 0, 3, 2]
    img = np.arange(12).reshape(3, 4)
    # a view rolled by 90 shows its content turned a quarter counter-clockwise: rot90 k=1
    rolled = np.rot90(img, 1)
    assert np.array_equal(np.rot90(rolled, diag.upright_turns(90)), img)


def test_exact_plane_depth_gives_the_true_normal():
    camera = pinhole_camera(500.0, (640, 480))
    n = np.array([0.5, -0.2, -0.84])
    n /= np.linalg.norm(n)
    rng = np.random.default_rng(0)
    rgb = rng.integers(0, 255, (480, 640, 3), dtype=np.uint8)
    region = [np.array([[-0.5, -0.5], [639.5, -0.5], [639.5, 479.5], [-0.5, 479.5]])]

    def network(image, cam):  # a depth sensor on the plane
        return plane_depth(camera, n, (240, 320))

    from rectified_colmap.config import ExtractConf

    errors = diag.image_errors(rgb, camera, n, region, 0.0, network, ExtractConf())
    assert errors["network"] < 1.0, errors
    assert errors["upright"] == errors["network"]
    assert errors["lines"] == errors["network"]  # noise has no lines: the patches stay
    assert np.isnan(errors["hypotheses"])
