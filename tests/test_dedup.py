"""Near-duplicate keypoints: grid-hash neighbours, twin rules, budget fill, and the pipeline."""

import numpy as np
import pytest

from rectified_colmap import camera as cam_utils
from rectified_colmap.config import DedupConf, ExtractConf
from rectified_colmap.dedup import (
    duplicate_fraction,
    duplicate_pairs,
    fill_from_plain,
    frame_anisotropy,
    keypoint_cap,
    max_cosine,
    near_duplicate_mask,
    neighbour_pairs,
)
from rectified_colmap.depth import DepthMap
from rectified_colmap.features import (
    Features,
    coarse_first_pays,
    detect_sift,
    pool_coarse_first,
    similarity_frames,
)
from rectified_colmap.pipeline import extract_image
from tests.conftest import look_at, plane_view, textured_image
from tests.scenes import REPLACING


REPLACE = REPLACING["dedup"]
"""The replacing mode (rectified twins and features take plain ones' places): what these
unit tests of fill_from_plain exercise; the default keeps every plain feature."""


def brute_pairs(xy, r):
    d = np.linalg.norm(xy[:, None] - xy[None], axis=-1)
    i, j = np.nonzero(np.triu(d < r, 1))
    return {(a, b) for a, b in zip(i.tolist(), j.tolist())}


@pytest.mark.parametrize("radius", [0.5, 1.0, 3.0])
def test_neighbour_pairs_equal_brute_force(radius):
    rng = np.random.default_rng(1)
    xy = rng.uniform(0, 40, (600, 2))
    xy[:100] = xy[100:200] + rng.normal(0, 0.4, (100, 2))  # many near twins
    xy[200:210] = xy[210:220]  # exact coincidences
    xy[300] = [np.nan, 3.0]  # ignored
    xy[301] = -xy[301]  # negative coordinates too
    got = {tuple(p) for p in neighbour_pairs(xy, radius).tolist()}
    ok = np.isfinite(xy).all(1)
    ref = brute_pairs(np.where(ok[:, None], xy, 1e9), radius)
    assert got == ref and len(ref) > 100


def test_neighbour_pairs_at_cell_boundaries():
    # Distances just under / over the radius across cell borders (cells of side radius).
    xy = np.array([[0.999, 0.0], [1.998, 0.0], [5.0, 5.0], [6.0, 5.0], [2.999, 2.999], [3.7, 3.7]])
    got = {tuple(p) for p in neighbour_pairs(xy, 1.0).tolist()}
    assert got == {(0, 1), (4, 5)}  # (2, 3) are exactly 1 apart: not closer than 1


def make_features(xy, scales, angles, desc, patch, stretch=None):
    shapes = similarity_frames(np.asarray(scales, float), np.asarray(angles, float))
    if stretch is not None:  # rectified keypoints: A = J A_rect with J = diag(1, cos tilt)
        shapes = np.asarray(stretch) @ shapes
    return Features(
        np.asarray(xy, float), shapes, np.asarray(desc, np.uint8), np.asarray(patch, np.int32)
    )


def random_desc(rng, n):
    return rng.integers(0, 256, (n, 128)).astype(np.uint8)


def test_twin_rules_location_descriptor_scale_source():
    rng = np.random.default_rng(2)
    d = random_desc(rng, 6)
    desc = np.concatenate([d, d])  # index k and k + 6 share a descriptor
    desc[11] = 255 - desc[11]  # ...except pair (5, 11): different descriptor
    xy = np.array([[10, 10], [30, 10], [50, 10], [70, 10], [90, 10], [110, 10]], float)
    xy2 = xy + [[0.5, 0], [1.5, 0], [0, 0.3], [0.2, 0.2], [0.1, 0], [0, 0]]
    scales = [2, 2, 2, 2, 2, 2] + [2.2, 2, 5, 2, 2, 2]
    patch = [-1] * 6 + [0, 0, 0, 0, -1, 0]
    f = make_features(np.concatenate([xy, xy2]), scales, np.zeros(12), desc, patch)
    got = {tuple(p) for p in duplicate_pairs(f, DedupConf()).tolist()}
    # 0: twin; 1: 1.5 px away; 2: scale x2.5; 3: twin; 4: same source; 5: other descriptor
    assert got == {(0, 6), (3, 9)}
    got_all = {tuple(p) for p in duplicate_pairs(f, DedupConf(), only_across=False).tolist()}
    assert got_all == {(0, 6), (3, 9), (4, 10)}


def test_oblique_patch_keeps_the_rectified_twin_frontal_keeps_plain():
    rng = np.random.default_rng(3)
    d = random_desc(rng, 2)
    conf = DedupConf(keep_rectified_tilt_deg=25.0, **REPLACE)
    for tilt, rect_wins in ((60.0, True), (10.0, False)):
        J = np.diag([1.0, np.cos(np.deg2rad(tilt))])
        plain = make_features([[5, 5], [20, 5]], [2, 2], [0, 0], d, [-1, -1])
        rect = make_features([[5.2, 5], [20, 5.1]], [2, 2], [0.3, 0.3], d, [1, 1], J)
        assert np.allclose(frame_anisotropy(rect.shapes), 1 / np.cos(np.deg2rad(tilt)))
        for order in ((plain, rect), (rect, plain)):  # independent of the order
            both = Features.concatenate(list(order))
            keep = near_duplicate_mask(both, conf)
            assert keep.sum() == 2
            assert np.all((both.patch[keep] >= 0) == rect_wins)


def _rows_of(plain, kept):
    """Sorted indices of the plain features whose keypoints ``kept`` holds (exact rows)."""
    return np.sort([np.flatnonzero((plain.keypoints == k).all(1))[0] for k in kept.keypoints])


def test_fill_from_plain_keeps_target_and_drops_smallest_plain_scales():
    rng = np.random.default_rng(4)
    n = 200
    xy = rng.uniform(0, 500, (n, 2))
    plain = make_features(
        xy, rng.uniform(1, 10, n), np.zeros(n), random_desc(rng, n), np.full(n, -1)
    )
    # 30 rectified twins of plain keypoints (oblique: they win) and 20 new rectified ones.
    tw = rng.choice(n, 30, replace=False)
    J = np.diag([1.0, 0.5])
    rect = Features.concatenate(
        [
            make_features(
                xy[tw] + 0.3,
                plain.scales[tw],
                np.zeros(30),
                plain.descriptors[tw],
                np.zeros(30),
                J @ np.eye(2) / np.sqrt(0.5),
            ),
            make_features(
                rng.uniform(0, 500, (20, 2)),
                np.full(20, 3.0),
                np.zeros(20),
                random_desc(rng, 20),
                np.zeros(20),
            ),
        ]
    )
    out = fill_from_plain(rect, plain, n, DedupConf(**REPLACE))
    assert len(out) == n
    assert (out.patch >= 0).sum() == 50  # every rectified feature kept
    kept_plain = out.subset(out.patch < 0)
    assert duplicate_fraction(out) == 0.0
    assert duplicate_fraction(Features.concatenate([plain, rect])) > 0.2
    # The 30 twins removed, then the 20 smallest remaining plain scales.
    rest = np.setdiff1d(np.arange(n), tw)
    expect = np.sort(rest[np.argsort(-plain.scales[rest], kind="stable")[:150]])
    got = _rows_of(plain, kept_plain)
    np.testing.assert_array_equal(got, expect)
    # Patches that yield nothing leave the whole budget to plain SIFT.
    assert len(fill_from_plain(Features.empty(), plain, 150, DedupConf(**REPLACE))) == 150
    assert len(fill_from_plain(Features.empty(), plain, 500, DedupConf(**REPLACE))) == n
    # extra_frac: the rectified features come on top of plain SIFT's up to that fraction
    # (170 plain features are left after the twins, 50 rectified ones).
    for extra, num_plain in ((0.25, 170), (0.1, 170), (0.05, 160), (0.0, 150)):
        cap = keypoint_cap(n, DedupConf(**{**REPLACE, "extra_frac": extra}))
        assert cap == round(n * (1 + extra))
        out = fill_from_plain(rect, plain, cap, DedupConf(**REPLACE))
        assert (out.patch >= 0).sum() == 50 and (out.patch < 0).sum() == num_plain
        got = _rows_of(plain, out.subset(out.patch < 0))
        expect = np.sort(rest[np.argsort(-plain.scales[rest], kind="stable")[:num_plain]])
        np.testing.assert_array_equal(got, expect)  # the largest remaining plain scales


def test_keep_all_plain_is_plain_sift_plus_the_largest_rectified_scales():
    """keep_all_plain: every plain feature stays (twins included: the plain one wins), and
    rectified features beyond target - plain count are cut, smallest scales first; plain
    features never make room, whatever the rectified count (issue 30: rectsift-plus lost
    plain features when a warp gave a few more rectified ones)."""
    rng = np.random.default_rng(7)
    n = 100
    xy = rng.uniform(0, 500, (n, 2))
    plain = make_features(xy, rng.uniform(1, 10, n), np.zeros(n), random_desc(rng, n), [-1] * n)
    tw = rng.choice(n, 10, replace=False)  # 10 oblique rectified twins of plain keypoints
    stretch = np.diag([1.0, 0.3]) / np.sqrt(0.3)
    twins = make_features(
        xy[tw] + 0.2, plain.scales[tw], np.zeros(10), plain.descriptors[tw], [0] * 10, stretch
    )
    m = 40
    new = make_features(
        rng.uniform(0, 500, (m, 2)),
        rng.uniform(1, 10, m),
        np.zeros(m),
        random_desc(rng, m),
        [1] * m,
    )
    rect = Features.concatenate([twins, new])
    conf = DedupConf(keep_all_plain=True, extra_frac=0.15)
    for cap_extra in (0.15, 0.6):  # rectified below / above their cap
        target = round(n * (1 + cap_extra))
        out = fill_from_plain(rect, plain, target, conf)
        np.testing.assert_array_equal(_rows_of(plain, out.subset(out.patch < 0)), np.arange(n))
        got_new = out.subset(out.patch >= 0)
        assert (got_new.patch == 1).all()  # the twins lost to their plain features
        room = min(m, target - n)
        expect = np.sort(np.argsort(-new.scales, kind="stable")[:room])
        np.testing.assert_array_equal(_rows_of(new, got_new), expect)
    # without keep_all_plain the oblique twins win and plain features make room
    out = fill_from_plain(rect, plain, n, DedupConf(**REPLACE))
    assert (out.patch < 0).sum() < n


def test_max_cosine_equals_brute_force():
    rng = np.random.default_rng(7)
    a, b = random_desc(rng, 50), random_desc(rng, 2100)
    a[0] = 0  # a zero descriptor has cosine 0 with everything
    ua = a / np.maximum(np.linalg.norm(a.astype(float), axis=1, keepdims=True), 1e-12)
    ub = b / np.linalg.norm(b.astype(float), axis=1, keepdims=True)
    np.testing.assert_allclose(max_cosine(a, b, chunk=16), (ua @ ub.T).max(1), atol=1e-5)
    assert (max_cosine(a, b[:0]) == -1).all() and len(max_cosine(a[:0], b)) == 0


def test_fill_from_plain_drops_rectified_features_that_crowd_a_plain_one():
    """A rectified feature whose descriptor is close to a plain feature's ANYWHERE in the
    image (not a twin: 200 px away) is dropped with max_plain_cosine, and plain SIFT fills
    its place; the others stay. Plain twins that win are compared too, not the lost ones."""
    rng = np.random.default_rng(5)
    n = 100
    plain = make_features(
        rng.uniform(0, 500, (n, 2)),
        rng.uniform(1, 10, n),
        np.zeros(n),
        random_desc(rng, n),
        np.full(n, -1),
    )
    desc = random_desc(rng, 10)
    desc[:4] = plain.descriptors[:4]  # the same look as plain features 0-3, elsewhere
    desc[4] = np.clip(plain.descriptors[4].astype(int) + rng.integers(-3, 4, 128), 0, 255)
    rect = make_features(
        plain.keypoints[:10] + 200.0, np.full(10, 3.0), np.zeros(10), desc, np.zeros(10)
    )
    cos = max_cosine(rect.descriptors, plain.descriptors)
    assert (cos[:5] > 0.99).all() and (cos[5:] < 0.9).all()
    out = fill_from_plain(rect, plain, n, DedupConf(**{**REPLACE, "max_plain_cosine": 0.9}))
    got = out.subset(out.patch >= 0)
    np.testing.assert_array_equal(got.keypoints, rect.keypoints[5:])
    assert len(out) == n and (out.patch < 0).sum() == n - 5
    # off (the default): every rectified feature stays
    assert ((fill_from_plain(rect, plain, n, DedupConf(**REPLACE)).patch >= 0).sum()) == 10
    # with extra_frac the dropped ones are not replaced: plain SIFT's features all stay
    out = fill_from_plain(
        rect,
        plain,
        keypoint_cap(n, DedupConf(**{**REPLACE, "extra_frac": 0.5})),
        DedupConf(**{**REPLACE, "max_plain_cosine": 0.9}),
    )
    assert (out.patch < 0).sum() == n and (out.patch >= 0).sum() == 5


K = np.array([[420.0, 0, 240], [0, 420, 180], [0, 0, 1]])
SIZE = (480, 360)
CAMERA = cam_utils.make_camera("PINHOLE", [420, 420, 240, 180], *SIZE)


def test_pipeline_output_has_no_cross_source_twins_and_plain_sift_count():
    """A mildly tilted plane (the case that made twins): with dedup the output has no twin
    between plain and rectified keypoints and, in the replacing mode, as many keypoints as
    plain SIFT; without it, a large fraction are twins."""
    texture = textured_image(900, 900, 11)
    R, t = look_at([0.8, -4.0, 4.5], [0, 0, 0])  # ~40 degrees from the plane normal
    img, z = plane_view(texture, 0.01, K, R, t, SIZE)
    conf = ExtractConf.from_dict(REPLACING)
    conf.sift.max_num_features = 2000
    plain = detect_sift(img, conf.sift)
    on = extract_image(img, CAMERA, DepthMap(z, "metric"), conf).features
    conf.dedup.enabled = False
    off = extract_image(img, CAMERA, DepthMap(z, "metric"), conf).features
    assert (on.patch >= 0).sum() > 200 and (on.patch < 0).sum() > 200
    before, after = duplicate_fraction(off), duplicate_fraction(on)
    assert before > 0.05
    assert len(duplicate_pairs(on, DedupConf())) == 0
    assert after <= duplicate_fraction(plain) + 0.01
    assert len(on) == len(plain)


def test_pipeline_extra_frac_keeps_plain_sift_and_adds_rectified_features():
    """With dedup.extra_frac the output is plain SIFT's keypoints (all of them but the twins
    a rectified feature replaced) plus rectified ones, at most (1 + extra_frac) x as many."""
    texture = textured_image(900, 900, 11)
    R, t = look_at([0.8, -4.0, 4.5], [0, 0, 0])
    img, z = plane_view(texture, 0.01, K, R, t, SIZE)
    conf = ExtractConf.from_dict(REPLACING)
    conf.sift.max_num_features = 2000
    conf.dedup.extra_frac = 0.5
    plain = detect_sift(img, conf.sift)
    out = extract_image(img, CAMERA, DepthMap(z, "metric"), conf).features
    rect = out.subset(out.patch >= 0)
    assert len(plain) < len(out) <= round(1.5 * len(plain)) and len(rect) > 200
    # every plain keypoint is in the output, or a kept rectified twin lies within 1 px
    kept = out.subset(out.patch < 0)
    d_kept = np.linalg.norm(plain.keypoints[:, None] - kept.keypoints[None], axis=-1).min(1)
    d_rect = np.linalg.norm(plain.keypoints[:, None] - rect.keypoints[None], axis=-1).min(1)
    assert np.all((d_kept == 0) | (d_rect < DedupConf().radius_px))
    assert len(duplicate_pairs(out, DedupConf())) == 0
    # without extra_frac the rectified features replace plain ones beyond the twins
    conf.dedup.extra_frac = 0.0
    parity = extract_image(img, CAMERA, DepthMap(z, "metric"), conf).features
    assert len(parity) == len(plain) and (parity.patch < 0).sum() < len(kept)


def test_pipeline_default_is_plain_sift_plus_uncrowded_features():
    """The default dedup (plain features all kept, no rectified feature within cosine 0.9 of
    a plain one, up to +50 %): the output holds every plain SIFT feature, unchanged, and
    rectified ones on top, none of which crowds a plain feature."""
    texture = textured_image(900, 900, 11)
    R, t = look_at([0.8, -4.0, 4.5], [0, 0, 0])
    img, z = plane_view(texture, 0.01, K, R, t, SIZE)
    conf = ExtractConf()
    assert conf.dedup.keep_all_plain and conf.dedup.max_plain_cosine == 0.9
    conf.sift.max_num_features = 2000
    plain = detect_sift(img, conf.sift)
    out = extract_image(img, CAMERA, DepthMap(z, "metric"), conf).features
    kept, rect = out.subset(out.patch < 0), out.subset(out.patch >= 0)

    def key(f):
        return {k.tobytes() + d.tobytes() for k, d in zip(f.keypoints, f.descriptors)}

    assert key(kept) == key(plain) and len(kept) == len(plain)
    assert len(rect) > 50
    assert (max_cosine(rect.descriptors, plain.descriptors) <= 0.9).all()
    # without the cosine rule more rectified features come, some of them crowding
    conf.dedup.max_plain_cosine = 1.0
    more = extract_image(img, CAMERA, DepthMap(z, "metric"), conf).features
    more_rect = more.subset(more.patch >= 0)
    assert len(more_rect) >= len(rect)
    assert (max_cosine(more_rect.descriptors, plain.descriptors) > 0.9).any()


def test_pipeline_exact_pool_is_plain_sift_where_coarse_first_pays():
    """With a budget small enough for coarse-first (>= 500 pixels per feature), the default
    pool of an image under ``sift.pool_coarse_first_min_pixels`` is still exactly plain
    COLMAP SIFT's features; a coarse-first pool is not (close, but not bit-identical)."""
    texture = textured_image(900, 900, 11)
    R, t = look_at([0.8, -4.0, 4.5], [0, 0, 0])
    img, z = plane_view(texture, 0.01, K, R, t, SIZE)
    conf = ExtractConf()
    conf.sift.max_num_features = 300
    assert coarse_first_pays(img.shape, 300, conf.sift) and conf.sift.pool_coarse_first
    assert not pool_coarse_first(img.shape, 300, conf.sift)  # 480x360: under 3 MP
    plain = detect_sift(img, conf.sift)  # one exact COLMAP call

    def plain_part(c):
        out = extract_image(img, CAMERA, DepthMap(z, "metric"), c).features
        assert (out.patch >= 0).any()  # rectified features on top
        kept = out.subset(out.patch < 0)
        return {k.tobytes() + d.tobytes() for k, d in zip(kept.keypoints, kept.descriptors)}

    exact = {k.tobytes() + d.tobytes() for k, d in zip(plain.keypoints, plain.descriptors)}
    assert plain_part(conf) == exact
    conf.sift.pool_coarse_first_min_pixels = 0  # as on a photo of 3 MP or more
    assert pool_coarse_first(img.shape, 300, conf.sift)
    assert plain_part(conf) != exact
