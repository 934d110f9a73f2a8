"""Near-duplicate keypoints: grid-hash neighbours, twin rules, which rectified features may
come on top of plain SIFT, and the pipeline."""

import numpy as np
import pytest

from rectified_colmap import camera as cam_utils
from rectified_colmap.budget import (
    UNSUPPORTED_BLIND_SHARE,
    blind_share,
    BLIND_YIELD_FRAC,
    OPENCV_VIEW_PIXELS_RATIO,
    cut_to_room,
    fits_either_tier,
    largest_scales,
    rectified_room,
    split_budget,
    unused_room,
    view_budgets,
    view_pixel_budget,
    wants_blind_views,
    without_share,
)
from rectified_colmap.config import DedupConf, ExtractConf, merge_conf
from rectified_colmap.sift import opencv_views
from rectified_colmap.dedup import (
    duplicate_fraction,
    duplicate_pairs,
    frame_anisotropy,
    max_cosine,
    near_duplicate_mask,
    neighbour_pairs,
    distinct_from_plain,
    lookalikes,
)
from rectified_colmap.depth import DepthMap
from rectified_colmap.features import Features, similarity_frames
from rectified_colmap.pipeline import extract_image, patches_with_room
from rectified_colmap.planes import HYPOTHESIS_AXIS, REST_AXIS, Patch
from rectified_colmap.sift import coarse_first_pays, detect_sift, pool_coarse_first
from tests.conftest import look_at, plane_view, textured_image


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


def test_plain_twins_always_win_and_the_more_oblique_rectified_twin_wins():
    """A plain keypoint beats its rectified twin however oblique the view (plain SIFT's
    features are all kept); of two rectified twins from different views the more strongly
    rectified one stays; neither depends on the order."""
    rng = np.random.default_rng(3)
    d = random_desc(rng, 2)
    for tilt in (60.0, 10.0):
        J = np.diag([1.0, np.cos(np.deg2rad(tilt))])
        plain = make_features([[5, 5], [20, 5]], [2, 2], [0, 0], d, [-1, -1])
        rect = make_features([[5.2, 5], [20, 5.1]], [2, 2], [0.3, 0.3], d, [1, 1], J)
        assert np.allclose(frame_anisotropy(rect.shapes), 1 / np.cos(np.deg2rad(tilt)))
        for order in ((plain, rect), (rect, plain)):
            both = Features.concatenate(list(order))
            keep = near_duplicate_mask(both)
            assert keep.sum() == 2 and (both.patch[keep] < 0).all()
    J = np.diag([1.0, 0.5])
    mild = make_features([[5, 5]], [2], [0], d[:1], [0], np.diag([1.0, 0.9]))
    steep = make_features([[5.3, 5]], [2], [0], d[:1], [1], J)
    for order in ((mild, steep), (steep, mild)):
        both = Features.concatenate(list(order))
        assert both.patch[near_duplicate_mask(both)].tolist() == [1]


def test_candidates_drop_twins_and_flag_lookalikes_of_plain_ones():
    """A rectified feature is a candidate unless it twins a plain one; a candidate is a
    look-alike where its descriptor is within max_plain_cosine of a plain feature's
    ANYWHERE in the image (not a twin: 200 px away: it can crowd that feature out of the
    ratio test)."""
    rng = np.random.default_rng(5)
    n = 100
    plain = make_features(
        rng.uniform(0, 500, (n, 2)),
        rng.uniform(1, 10, n),
        np.zeros(n),
        random_desc(rng, n),
        np.full(n, -1),
    )
    desc = random_desc(rng, 12)
    desc[:4] = plain.descriptors[:4]  # the same look as plain features 0-3, elsewhere
    desc[4] = np.clip(plain.descriptors[4].astype(int) + rng.integers(-3, 4, 128), 0, 255)
    desc[10:] = plain.descriptors[10:12]  # 10, 11: twins of plain 10, 11
    xy = plain.keypoints[:12] + 200.0
    xy[10:] = plain.keypoints[10:12] + 0.3
    rect = make_features(xy, plain.scales[:12], np.zeros(12), desc, np.zeros(12))
    cos = max_cosine(rect.descriptors, plain.descriptors)
    assert (cos[:5] > 0.99).all() and (cos[5:10] < 0.9).all()
    index = distinct_from_plain(rect, plain)
    lookalike = lookalikes(rect, index, plain)
    np.testing.assert_array_equal(index, np.arange(10))
    np.testing.assert_array_equal(lookalike, np.arange(10) < 5)
    # max_plain_cosine 1: no look-alikes, the twins still go
    no_test = DedupConf(max_plain_cosine=1.0)
    index = distinct_from_plain(rect, plain, no_test)
    lookalike = lookalikes(rect, index, plain, no_test)
    np.testing.assert_array_equal(index, np.arange(10))
    assert not lookalike.any()


def ranked_features(rng, m):
    """m rectified features (view 0) of distinct scales 1..m in random order."""
    return make_features(
        rng.uniform(0, 500, (m, 2)),
        rng.permutation(m) + 1.0,
        np.zeros(m),
        random_desc(rng, m),
        np.zeros(m),
    )


def test_lookalikes_only_fill_the_budget_plain_sift_left_unused():
    """cut_to_room: the features unlike any plain one first (largest major scales) up to
    the room; then look-alikes (largest major scales) up to the room left, and at most the
    part of plain SIFT's budget its keypoints left unused: none where plain SIFT fills it
    (the cut of before, exactly), none with lookalikes_in_unused_budget False."""
    conf = ExtractConf()
    conf.sift.max_num_features = 100  # room = 0.5 x max(count, 100)
    rng = np.random.default_rng(3)
    m = 120
    feats = ranked_features(rng, m)
    index = np.arange(0, m, 1)
    lookalike = np.arange(m) % 3 != 0  # 80 look-alikes, 40 others
    others, looks = index[~lookalike], index[lookalike]

    def top(ix, k):  # the k largest scales of ix, sorted
        return np.sort(ix[np.argsort(-feats.scales[ix], kind="stable")[:k]])

    # room 50 (75 at 150 keypoints): the 40 others, then up to 10 (35) look-alikes
    for count, expect_looks in ((100, 0), (150, 0), (95, 5), (70, 10), (0, 10)):
        assert unused_room(count, conf) == max(0, 100 - count)
        got = cut_to_room(feats, index, lookalike, count, conf)
        expect = np.sort(np.concatenate([others, top(looks, expect_looks)]))
        np.testing.assert_array_equal(got, expect)
        if expect_looks == 0:  # plain SIFT fills its budget: no look-alike at all
            room = rectified_room(count, conf)
            np.testing.assert_array_equal(got, largest_scales(feats, others, room))
    conf.dedup.extra_frac = 0.3  # room 30 < the 40 others: their 30 largest, no look-alike
    np.testing.assert_array_equal(cut_to_room(feats, index, lookalike, 0, conf), top(others, 30))
    conf.dedup.extra_frac = 1.2  # room 120: 40 others, then 80 look-alikes (unused 100)
    np.testing.assert_array_equal(cut_to_room(feats, index, lookalike, 0, conf), index)
    assert len(cut_to_room(feats, index, lookalike, 30, conf)) == 40 + 70
    conf.dedup.lookalikes_in_unused_budget = False  # the switch: none
    assert unused_room(0, conf) == 0
    np.testing.assert_array_equal(cut_to_room(feats, index, lookalike, 0, conf), others)


def test_every_candidate_kept_whichever_tier_exactly_where_they_fit_either():
    """budget.fits_either_tier: where it holds, cut_to_room keeps every candidate whatever
    their tiers (so the pipeline may skip the look-alike test); one candidate more and the
    cut drops one where all are second tier (the bound is tight)."""
    conf = ExtractConf()
    conf.sift.max_num_features = 100  # room 50 (65 at 130 keypoints), unused 100 - count
    rng = np.random.default_rng(4)
    m = 120
    feats = ranked_features(rng, m)
    for count, bound in ((0, 50), (60, 40), (95, 5), (100, 0), (130, 0)):
        for n in (bound, bound + 1):
            index = np.sort(rng.choice(m, n, replace=False))
            assert fits_either_tier(n, count, conf) == (n == bound)
            for p in (0.0, 0.3, 0.7, 1.0):
                got = cut_to_room(feats, index, rng.random(n) < p, count, conf)
                if n == bound:
                    np.testing.assert_array_equal(got, index)
            if n > bound:
                assert len(cut_to_room(feats, index, np.ones(n, bool), count, conf)) < n
    conf.dedup.lookalikes_in_unused_budget = False  # no second tier: only no candidate fits
    assert fits_either_tier(0, 0, conf) and not fits_either_tier(1, 0, conf)


def test_pipeline_skips_the_lookalike_test_only_where_it_changes_nothing(monkeypatch):
    """rectified_to_keep runs dedup.lookalikes only where not every candidate fits
    (budget.fits_either_tier): the features are exactly those
    of the path that always runs it, where the budget has room (test skipped) and where
    plain SIFT fills it (test run)."""
    from rectified_colmap import pipeline

    texture = textured_image(900, 900, 11)
    R, t = look_at([0.8, -4.0, 4.5], [0, 0, 0])
    img, z = plane_view(texture, 0.01, K, R, t, SIZE)
    calls = []
    real = pipeline.lookalikes

    def counted(*args, **kw):
        calls.append(len(args[1]))
        return real(*args, **kw)

    monkeypatch.setattr(pipeline, "lookalikes", counted)
    conf = ExtractConf()
    for budget, tested in ((12000, False), (400, True)):
        conf.sift.max_num_features = budget
        calls.clear()
        out = extract_image(img, CAMERA, DepthMap(z, "metric"), conf).features
        assert bool(calls) == tested and (out.patch >= 0).sum() > 50
        with monkeypatch.context() as always:  # the look-alike test wherever it can run
            always.setattr(pipeline, "fits_either_tier", lambda *a: False)
            ref = extract_image(img, CAMERA, DepthMap(z, "metric"), conf).features
        for name in ("keypoints", "shapes", "descriptors", "patch"):
            np.testing.assert_array_equal(getattr(out, name), getattr(ref, name))


def test_views_over_the_rest_of_a_plane_only_fill_plain_sifts_unused_budget():
    """The views over the rest of a plane (REST_AXIS) and of the plane hypotheses
    (HYPOTHESIS_AXIS) get no patch where plain SIFT fills its budget (the depth's views
    exactly as without them); the rest views else get a SIFT budget of
    patch_budget_factor x the part of the room plain SIFT left unused, shared by area."""
    conf = ExtractConf()
    conf.sift.max_num_features = 100  # room = 50; SIFT budgets 2 x what views may add
    areas = np.array([10, 30, 20])
    rest = np.array([False, True, False])
    alone = split_budget(100, areas[~rest])
    for count, rest_budget in ((100, 0), (130, 0), (80, 40), (60, 80), (0, 100)):
        got = view_budgets(count, areas, rest, conf)
        if count <= 100:
            np.testing.assert_array_equal(got[~rest], alone)
        assert got[1] == rest_budget
    np.testing.assert_array_equal(
        view_budgets(60, areas, np.zeros(3, bool), conf), split_budget(100, areas)
    )
    mask = np.ones((4, 6), bool)
    normal = np.array([0.6, 0.0, -0.8])
    patches = [Patch(mask, a, normal, 1.0) for a in (0, HYPOTHESIS_AXIS, REST_AXIS)]
    assert patches_with_room(patches, 99, conf) == patches
    # where plain SIFT fills its budget the plane hypotheses get no view either
    assert patches_with_room(patches, 100, conf) == patches[:1]
    conf.dedup.lookalikes_in_unused_budget = False  # the switch: no second tier at all
    assert patches_with_room(patches, 0, conf) == patches[:1]


def test_the_cut_keeps_the_largest_major_scales_within_the_cap():
    """The room above plain SIFT is extra_frac x the larger of its budget and its keypoint
    count (an image with few plain features gets a full image's room); the rectified features
    beyond the room are cut smallest major scale first (the larger singular value of A,
    which a steep view does not shrink), in index order."""
    conf = ExtractConf()
    conf.sift.max_num_features = 1000
    got = []
    for e, n in ((0.0, 200), (0.15, 200), (0.5, 200), (0.5, 999), (0.5, 3000)):
        conf.dedup.extra_frac = e
        got.append(rectified_room(n, conf))
    assert got == [0, 150, 500, 500, 1500]
    rng = np.random.default_rng(7)
    m = 40
    stretch = np.diag([1.0, 0.3])  # major scale = scale, |det| = 0.3 scale^2
    feats = make_features(
        rng.uniform(0, 500, (m, 2)),
        rng.uniform(1, 10, m),
        np.zeros(m),
        random_desc(rng, m),
        [1] * m,
        stretch,
    )
    index = np.arange(0, m, 2)  # a subset, as distinct_from_plain gives
    for room in (0, 7, 20, 50):
        got = largest_scales(feats, index, room)
        expect = np.sort(index[np.argsort(-feats.scales[index] / 0.65, kind="stable")[:room]])
        np.testing.assert_array_equal(got, expect)


def test_max_cosine_equals_brute_force():
    rng = np.random.default_rng(7)
    a, b = random_desc(rng, 50), random_desc(rng, 2100)
    a[0] = 0  # a zero descriptor has cosine 0 with everything
    ua = a / np.maximum(np.linalg.norm(a.astype(float), axis=1, keepdims=True), 1e-12)
    ub = b / np.linalg.norm(b.astype(float), axis=1, keepdims=True)
    np.testing.assert_allclose(max_cosine(a, b, chunk=16), (ua @ ub.T).max(1), atol=1e-5)
    assert (max_cosine(a, b[:0]) == -1).all() and len(max_cosine(a[:0], b)) == 0


K = np.array([[420.0, 0, 240], [0, 420, 180], [0, 0, 1]])
SIZE = (480, 360)
CAMERA = cam_utils.make_camera("PINHOLE", [420, 420, 240, 180], *SIZE)


def test_pipeline_default_is_plain_sift_plus_features_that_crowd_none_where_sift_is_full():
    """The default dedup (plain features all kept, up to +50 %, look-alikes of plain
    features, cosine above 0.9, only in plain SIFT's unused budget): the output holds every
    plain SIFT feature, unchanged, and rectified ones on top; where plain SIFT fills its
    budget none of them looks like a plain feature, where it leaves budget unused at most
    that many do, and with the switch off none."""
    texture = textured_image(900, 900, 11)
    R, t = look_at([0.8, -4.0, 4.5], [0, 0, 0])
    img, z = plane_view(texture, 0.01, K, R, t, SIZE)
    depth = DepthMap(z, "metric")

    def key(f):
        return {k.tobytes() + d.tobytes() for k, d in zip(f.keypoints, f.descriptors)}

    def run(conf):
        plain = detect_sift(img, conf.sift)
        out = extract_image(img, CAMERA, depth, conf).features
        kept, rect = out.subset(out.patch < 0), out.subset(out.patch >= 0)
        assert key(kept) == key(plain) and len(kept) == len(plain)
        assert len(duplicate_pairs(out, DedupConf())) == 0  # no twin across sources
        assert len(out) <= len(plain) + rectified_room(len(plain), conf)
        looks = int((max_cosine(rect.descriptors, plain.descriptors) > 0.9).sum())
        return plain, rect, looks

    conf = ExtractConf()
    assert conf.dedup.max_plain_cosine == 0.9 and conf.dedup.lookalikes_in_unused_budget
    conf.sift.max_num_features = 400  # plain SIFT fills it: no look-alike
    plain, rect, looks = run(conf)
    assert len(plain) >= 400 and len(rect) > 50 and looks == 0
    conf.sift.max_num_features = 12000  # plain SIFT leaves much of it unused
    plain, rect, looks = run(conf)
    assert len(plain) < 12000 and 0 < looks <= unused_room(len(plain), conf)
    both = Features.concatenate([plain, rect])
    assert duplicate_fraction(both) <= duplicate_fraction(plain) + 0.01
    conf.dedup.lookalikes_in_unused_budget = False
    plain, fewer, looks = run(conf)
    assert looks == 0 and 50 < len(fewer) < len(rect)


def test_pipeline_exact_pool_is_plain_sift_where_coarse_first_pays():
    """With a budget small enough for coarse-first (>= 500 pixels per feature), the default
    pool of an image under ``sift.pool_coarse_first_min_pixels`` is still exactly plain
    COLMAP SIFT's features; a coarse-first pool is not (close, but not bit-identical)."""
    texture = textured_image(900, 900, 11)
    R, t = look_at([0.8, -4.0, 4.5], [0, 0, 0])
    img, z = plane_view(texture, 0.01, K, R, t, SIZE)
    conf = ExtractConf()
    conf.sift.max_num_features = 300
    assert coarse_first_pays(img.shape, 300, conf.sift)
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


def test_view_pixel_budget_is_relative_to_the_image_up_to_what_sift_can_use():
    """The views' pixels: rectify.max_view_pixels_factor x the image's pixels as SIFT sees
    it (sift.max_image_size), counted up to sift.max_num_features x
    sift.patch_octave0_pixels_per_feature."""
    conf = ExtractConf.from_dict(
        {
            "rectify": {"max_view_pixels_factor": 2.0},
            "sift": {
                "max_num_features": 8192,
                "patch_octave0_pixels_per_feature": 150.0,
                "patch_backend": "colmap",
            },
        }
    )
    assert view_pixel_budget((480, 640), conf) == 2.0 * 640 * 480
    assert view_pixel_budget((1000, 1000), conf) == 2.0 * 1000 * 1000
    assert view_pixel_budget((1024, 1536), conf) == 2.0 * 8192 * 150  # 1.57 MP > 1.23 MP
    assert view_pixel_budget((4000, 6000), conf) == 2.0 * 8192 * 150
    fewer = ExtractConf.from_dict({"sift": {"max_num_features": 1024, "patch_backend": "colmap"}})
    assert view_pixel_budget((480, 640), fewer) == pytest.approx(
        fewer.rectify.max_view_pixels_factor * 1024 * fewer.sift.patch_octave0_pixels_per_feature
    )
    downscaled = ExtractConf.from_dict({"sift": {"max_image_size": 640}})
    assert view_pixel_budget((1024, 1536), downscaled) == pytest.approx(
        downscaled.rectify.max_view_pixels_factor * OPENCV_VIEW_PIXELS_RATIO * 640 * 427
    )


def test_views_run_by_opencv_sift_get_their_own_pixel_factor():
    """Where OpenCV's SIFT runs the views from the upsampled octave (sift.patch_backend
    "opencv", below sift.patch_octave0_pixels_per_feature pixels per feature) they have
    OPENCV_VIEW_PIXELS_RATIO x rectify.max_view_pixels_factor x the image's pixels; where it
    runs them from octave 0, elsewhere, and with COLMAP's SIFT or upright SIFT,
    rectify.max_view_pixels_factor x."""
    conf = ExtractConf.from_dict(
        {
            "rectify": {"max_view_pixels_factor": 2.0},
            "sift": {"max_num_features": 8192, "patch_backend": "opencv"},
        }
    )
    assert opencv_views((480, 640), conf.sift)
    assert view_pixel_budget((480, 640), conf) == 2.0 * OPENCV_VIEW_PIXELS_RATIO * 640 * 480
    assert opencv_views((1024, 1536), conf.sift)  # 192 px per feature: octave 0
    assert view_pixel_budget((1024, 1536), conf) == 2.0 * 8192 * 150
    assert not opencv_views((4000, 6000), conf.sift)  # coarse-first pays
    for other in ({"patch_backend": "colmap"}, {"upright": True}):
        off = ExtractConf.from_dict(merge_conf(conf.to_dict(), {"sift": other}))
        assert not opencv_views((480, 640), off.sift)
        assert view_pixel_budget((480, 640), off) == 2.0 * 640 * 480


def test_blind_views_where_the_views_add_at_most_a_fraction_of_plain_sift():
    """budget.wants_blind_views: where the views of the estimates added at most
    BLIND_YIELD_FRAC x plain SIFT's keypoints (none where there is no view), and only where
    plain SIFT left part of its budget unused (the blind views are second tier)."""
    conf = ExtractConf()
    conf.sift.max_num_features = 1000
    most = int(BLIND_YIELD_FRAC * 800)
    assert wants_blind_views(0, 800, conf) and wants_blind_views(most, 800, conf)
    assert not wants_blind_views(most + 1, 800, conf)
    assert wants_blind_views(0, 0, conf)  # no plain feature, no view: blind views
    assert not wants_blind_views(0, 1000, conf) and not wants_blind_views(0, 1200, conf)
    conf.dedup.lookalikes_in_unused_budget = False
    assert not wants_blind_views(0, 800, conf)


def test_blind_features_come_on_top_of_every_kept_feature_within_what_is_left():
    """pipeline.blind_on_top: the kept features stay as they are (first, the same rows); a
    blind feature twinning a kept one (plain or rectified) is dropped; the others come
    within budget.blind_room, the largest major scales first."""
    from rectified_colmap.budget import blind_room
    from rectified_colmap.pipeline import blind_on_top

    conf = ExtractConf()
    conf.sift.max_num_features = 10  # rectified room 5
    rng = np.random.default_rng(0)

    def feats(xy, scale, patch):
        n = len(xy)
        d = rng.integers(0, 255, (n, 128)).astype(np.uint8)
        return Features(
            np.asarray(xy, float),
            scale * np.tile(np.eye(2), (n, 1, 1)),
            d,
            np.full(n, patch, np.int32),
        )

    plain = feats(np.c_[np.arange(6) * 20.0, np.zeros(6)], 2.0, -1)
    rect = feats([[0.0, 50.0]], 2.0, 0)
    kept = Features.concatenate([plain, rect])  # 7 kept: 3 left of plain SIFT's budget
    assert blind_room(7, 6, conf) == 3 and blind_room(11, 6, conf) == 0
    twin = feats([[0.0, 50.0]], 2.0, 1)
    twin.descriptors[:] = rect.descriptors  # the rectified feature's twin
    others = feats([[300.0, 300.0], [400.0, 300.0], [500.0, 300.0], [600.0, 300.0]], 1.0, 1)
    others.shapes[:, 0, 0] = [1.0, 4.0, 3.0, 2.0]  # major scales 1, 4, 3, 2
    out = blind_on_top(kept, Features.concatenate([twin, others]), 6, conf)
    np.testing.assert_array_equal(out.keypoints[:7], kept.keypoints)
    np.testing.assert_array_equal(out.keypoints[7:, 0], [400.0, 500.0, 600.0])
    others.descriptors[1] = plain.descriptors[0]  # 400: a look-alike of a plain feature
    out = blind_on_top(kept, others, 6, conf)  # room 3 of 4: the look-alike goes
    np.testing.assert_array_equal(out.keypoints[7:, 0], [300.0, 500.0, 600.0])
    out = blind_on_top(plain, others, 6, conf)  # room 4 (blind_room): all four, in order
    assert blind_room(6, 6, conf) == 4
    np.testing.assert_array_equal(out.keypoints[6:, 0], [300.0, 400.0, 500.0, 600.0])


def test_blind_share_where_the_lines_confirm_no_plane_and_plain_sift_leaves_budget():
    """budget.blind_share: UNSUPPORTED_BLIND_SHARE for an image whose plane estimates its
    lines do not support, where plain SIFT left part of its budget unused (the blind views
    are second tier); 0 where the lines support them, where plain SIFT fills its budget, and
    with the second tier off. without_share cuts the estimates' views' room by that share
    (conf itself for 0), so that the two together keep the image's room."""
    conf = ExtractConf()
    conf.sift.max_num_features = 1000
    assert blind_share(800, True, conf) == 0.0 and without_share(conf, 0.0) is conf
    assert blind_share(800, False, conf) == UNSUPPORTED_BLIND_SHARE == 0.5
    assert blind_share(1000, False, conf) == 0.0 and blind_share(1200, False, conf) == 0.0
    own = without_share(conf, 0.25)
    assert rectified_room(800, own) == 375 and rectified_room(800, conf) == 500
    assert conf.dedup.extra_frac == 0.5  # conf itself unchanged
    conf.dedup.lookalikes_in_unused_budget = False
    assert blind_share(800, False, conf) == 0.0
