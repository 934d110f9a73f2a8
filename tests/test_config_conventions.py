import re
from dataclasses import fields
from pathlib import Path

import cv2
import numpy as np
import pytest

from rectified_colmap import conventions
from rectified_colmap.config import RETIRED_KEYS, ExtractConf, confs, merge_conf
from rectified_colmap.eval.config import EvalConf, HomographyConf, LocalizeConf


def test_conf_from_dict_merges_and_rejects_unknown():
    c = ExtractConf.from_dict({"rectify": {"max_viewing_angle_deg": 85}})
    assert c.rectify.max_viewing_angle_deg == 85.0
    assert c.normals.window == ExtractConf().normals.window
    assert ExtractConf.from_dict(c.to_dict()) == c
    with pytest.raises(KeyError):
        ExtractConf.from_dict({"rectify": {"nope": 1}})
    with pytest.raises(KeyError):
        ExtractConf.from_dict({"nope": {}})
    for name in confs:
        ExtractConf.from_dict(confs[name])


@pytest.mark.parametrize(
    "section, key, value",
    [
        ("sift", "upright", "false"),  # bool("false") would be True
        ("sift", "upright", 0),
        ("planes", "fill_gaps", False),  # a conf of the version where it was a bool
        ("sift", "max_num_features", 1024.5),
        ("sift", "max_num_features", True),
        ("rectify", "max_viewing_angle_deg", "85"),
    ],
)
def test_conf_from_dict_rejects_values_of_another_type(section, key, value):
    with pytest.raises(ValueError, match=rf"{section}\.{key} must be"):
        ExtractConf.from_dict({section: {key: value}})


def test_conf_from_dict_takes_numbers_as_the_key_needs():
    c = ExtractConf.from_dict({"sift": {"max_num_features": 1024.0}, "rectify": {"border": 4}})
    assert c.sift.max_num_features == 1024 and type(c.sift.max_num_features) is int
    c = ExtractConf.from_dict({"rectify": {"max_viewing_angle_deg": 85}})
    assert type(c.rectify.max_viewing_angle_deg) is float


def test_merge_conf_overrides_key_by_key_and_changes_no_input():
    base = {
        "vp": {"line_hypotheses": 3, "hypothesis_min_tilt_deg": 50.0},
        "rectify": {"max_viewing_angle_deg": 86.0},
        "dedup": {"extra_frac": 0.5},
        "sift": {"coarse_first": False},
    }
    before = {section: dict(values) for section, values in base.items()}
    overrides = {"vp": {"line_hypotheses": 1}, "sift": {"max_num_features": 1024}}
    merged = merge_conf(base, overrides)
    assert merged["vp"] == {"line_hypotheses": 1, "hypothesis_min_tilt_deg": 50.0}
    assert merged["sift"] == {"coarse_first": False, "max_num_features": 1024}
    assert merged["dedup"] == base["dedup"] and merged["rectify"] == base["rectify"]
    assert base == before and overrides["vp"] == {"line_hypotheses": 1}
    assert merge_conf(base, None) == base
    conf = ExtractConf.from_dict(merged)
    assert conf.vp.line_hypotheses == 1 and conf.dedup.extra_frac == 0.5


def test_retired_keys_say_why_and_are_gone():
    """A key of an earlier version (e.g. in a user's JSON conf) names the reason it was
    retired, instead of "unknown key"; none of them is a field any more."""
    for key, why in RETIRED_KEYS.items():
        section, _, name = key.partition(".")
        conf = {section: {name: 1}} if name else {section: {}}
        with pytest.raises(KeyError, match="retired") as e:
            ExtractConf.from_dict(conf)
        assert why in str(e.value)
        if name:
            assert not hasattr(getattr(ExtractConf(), section), name), key
        else:
            assert not hasattr(ExtractConf(), section), key


def test_pixel_centers():
    g = conventions.pixel_centers(2, 1, 10, 4)
    np.testing.assert_allclose(g[0, 0], [2.5, 2.0])
    np.testing.assert_allclose(g[0, 1], [7.5, 2.0])


def test_hloc_round_trip():
    xy = np.array([[0.5, 0.5], [10.25, 3.0]])
    h = conventions.to_hloc_keypoints(xy)
    assert h.dtype == np.float32
    np.testing.assert_allclose(h[0], [0, 0])
    np.testing.assert_allclose(conventions.from_hloc_keypoints(h), xy)


def test_opencv_homography_moves_pixels_as_in_colmap_frame():
    # H doubles COLMAP coordinates: the centre of pixel (0, 0) at (0.5, 0.5) goes to (1, 1),
    # which is the corner shared by pixels (0, 0) and (1, 1); the centre of pixel (3, 2),
    # (3.5, 2.5), goes to (7, 5): the corner between pixels (6..7, 4..5).
    H = np.diag([2.0, 2.0, 1.0])
    img = np.zeros((8, 8), np.float32)
    img[2, 3] = 1.0
    out = cv2.warpPerspective(
        img, conventions.to_opencv_homography(H), (16, 16), flags=cv2.INTER_LINEAR
    )
    ys, xs = np.nonzero(out > 0)
    cx = (out[ys, xs] * xs).sum() / out[ys, xs].sum() + 0.5  # back to COLMAP
    cy = (out[ys, xs] * ys).sum() / out[ys, xs].sum() + 0.5
    np.testing.assert_allclose([cx, cy], [7.0, 5.0], atol=1e-6)


def _documented_keys(section_body: str) -> dict[str, str]:
    """`key` -> `default` of a docs/configuration.md table."""
    return dict(re.findall(r"^\| `(\w+)` \| `([^`]*)`", section_body, flags=re.M))


def test_configuration_doc_lists_every_key_with_its_default_and_no_retired_one():
    doc = (Path(__file__).parents[1] / "docs" / "configuration.md").read_text()
    parts = re.split(r"^## `(\w+)`: \w+$|^## (\w+) \(.*$", doc, flags=re.M)
    bodies = {}
    for i in range(1, len(parts), 3):
        bodies[parts[i] or parts[i + 1]] = parts[i + 2]
    classes = {f.name: type(getattr(ExtractConf(), f.name)) for f in fields(ExtractConf)}
    classes |= {c.__name__: c for c in (EvalConf, HomographyConf, LocalizeConf)}
    assert set(bodies) == set(classes)
    for name, cls in classes.items():
        documented = _documented_keys(bodies[name])
        defaults = {f.name: getattr(cls(), f.name) for f in fields(cls)}
        assert documented.keys() == defaults.keys(), name
        for key, value in defaults.items():
            assert documented[key] in (repr(value), str(value)), (name, key)
