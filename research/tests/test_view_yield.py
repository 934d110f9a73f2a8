"""research/scripts/view_yield.py: the kinds of views and their yield per pixel."""

from collections import Counter

import numpy as np
import pytest

from rectified_colmap.planes import BLIND_AXIS, HYPOTHESIS_AXIS, REST_AXIS, Patch
from scripts_util import load_script


def test_view_kinds_tell_tilt_neighbours_by_their_parents_axis_and_mask_object():
    vy = load_script("view_yield")
    a, b, c = np.zeros((4, 6), bool), np.ones((4, 6), bool), np.zeros((4, 6), bool)
    n = np.array([0.0, 0.0, -1.0])
    patches = [
        Patch(a, 0, n, 0.5),
        Patch(b, HYPOTHESIS_AXIS, n, 1.0),
        Patch(a.copy(), REST_AXIS, n, 0.5),  # same mask as the depth patch: not a neighbour
        Patch(b.copy(), HYPOTHESIS_AXIS, n, 1.0),  # another hypothesis over the same cells
        Patch(b, HYPOTHESIS_AXIS, n, 1.0),  # the first one's neighbour: its mask object
        Patch(c, REST_AXIS, n, 0.5),
        Patch(c, REST_AXIS, n, 0.5),  # a rest neighbour
        Patch(b, BLIND_AXIS, n, 1.0),
        Patch(a, 0, n, 0.5),  # the depth patch's neighbour (where plain SIFT left room)
        Patch(a.copy(), 1, n, 0.5),  # another depth plane over the same cells
    ]
    assert vy.view_kinds(patches) == [
        "depth",
        "hyp",
        "rest",
        "hyp",
        "hyp-nbr",
        "rest",
        "rest-nbr",
        "blind",
        "depth-nbr",
        "depth",
    ]


def test_yield_per_pixel_counts_each_match_once_per_kind_of_its_endpoints():
    vy = load_script("view_yield")
    matches = {"hyp+hyp": 10, "hyp+plain": 4, "depth+hyp-nbr": 6}
    pixels = {"hyp": 200.0, "depth": 100.0, "hyp-nbr": 300.0}
    got = vy.per_pixel(Counter(matches), pixels, 100.0)
    # hyp: 10 + 4 matches over 2 x the images' pixels; depth 6 / 1; hyp-nbr 6 / 3
    assert got == pytest.approx({"hyp": 7.0, "depth": 6.0, "hyp-nbr": 2.0})


def test_the_pipelines_tilt_neighbours_share_their_parents_mask_object():
    """What view_kinds relies on: views.tilt_neighbours gives each its parent's mask."""
    from rectified_colmap.views import tilt_neighbours
    from rectified_colmap_research import synth

    vy = load_script("view_yield")
    camera = synth.pinhole_camera(64, 48, 60.0)
    parent = Patch(np.ones((6, 8), bool), HYPOTHESIS_AXIS, np.array([0.8, 0.0, -0.6]), 1.0)
    nbrs = tilt_neighbours(camera, parent, 2**0.5, 1)
    assert len(nbrs) == 2 and all(q.mask is parent.mask for q in nbrs)
    assert vy.view_kinds([parent, *nbrs]) == ["hyp", "hyp-nbr", "hyp-nbr"]
