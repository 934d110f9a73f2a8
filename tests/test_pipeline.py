"""Pipeline behaviour on views of a textured plane with known depth and homographies."""

import types

import numpy as np
import pytest

from rectified_colmap import camera as cam_utils
from rectified_colmap import pipeline
from rectified_colmap.config import ExtractConf
from rectified_colmap.depth import DepthMap
from rectified_colmap.sift import detect_sift
from rectified_colmap.pipeline import extract_image, timed
from rectified_colmap.planes import BLIND_AXIS, Patch
from rectified_colmap.rectify import patch_view
from rectified_colmap.views import (
    MIN_VIEW_AREA_FRAC,
    TEXTURE_MARGIN,
    patches_worth_rectifying,
    textured_patches,
    viewing_angles,
    without_specks,
)
from tests.conftest import look_at, plane_view, textured_image
from tests.scenes import SINGLE_VIEW

K = np.array([[420.0, 0, 240], [0, 420, 180], [0, 0, 1]])
SIZE = (480, 360)
CAMERA = cam_utils.make_camera("PINHOLE", [420, 420, 240, 180], *SIZE)


def mutual_ratio_matches(d0, d1, ratio=0.8):
    f0 = d0.astype(np.float32)
    f1 = d1.astype(np.float32)
    f0 /= np.linalg.norm(f0, axis=1, keepdims=True)
    f1 /= np.linalg.norm(f1, axis=1, keepdims=True)
    sim = f0 @ f1.T
    nn = np.argsort(-sim, axis=1)[:, :2]
    s1 = sim[np.arange(len(f0)), nn[:, 0]]
    s2 = sim[np.arange(len(f0)), nn[:, 1]]
    ok = np.sqrt(np.maximum(2 - 2 * s1, 0)) < ratio * np.sqrt(np.maximum(2 - 2 * s2, 0))
    back = np.argmax(sim, axis=0)
    ok &= back[nn[:, 0]] == np.arange(len(f0))
    return np.stack([np.flatnonzero(ok), nn[ok, 0]], 1)


def plane_homography(R0, t0, R1, t1):
    """Image 0 -> image 1 homography of the world plane z = 0 (COLMAP pixels)."""
    H0 = K @ np.stack([R0[:, 0], R0[:, 1], t0], 1)
    H1 = K @ np.stack([R1[:, 0], R1[:, 1], t1], 1)
    return H1 @ np.linalg.inv(H0)


def correct_matches(f0, f1, H, thresh=3.0):
    m = mutual_ratio_matches(f0.descriptors, f1.descriptors)
    if len(m) == 0:
        return 0
    p = np.c_[f0.keypoints[m[:, 0]], np.ones(len(m))] @ H.T
    err = np.linalg.norm(p[:, :2] / p[:, 2:] - f1.keypoints[m[:, 1]], axis=1)
    return int((err < thresh).sum())


@pytest.fixture(scope="module")
def texture():
    return textured_image(900, 900, 11)


def test_no_depth_gives_exactly_plain_sift_no_plane_blind_views_on_top(texture):
    """No depth: exactly plain SIFT. A depth with no usable plane: plain SIFT's features all
    kept, and views only blind ones (BLIND_AXIS: plain SIFT leaves part of its budget unused
    on this image); with the second tier off, exactly plain SIFT."""
    R, t = look_at([1, -4, 3], [0, 0, 0])
    img, z = plane_view(texture, 0.01, K, R, t, SIZE)
    plain = detect_sift(img)
    assert len(plain) < ExtractConf().sift.max_num_features
    single = ExtractConf.from_dict(SINGLE_VIEW)
    no_second = {**SINGLE_VIEW, "dedup": {"lookalikes_in_unused_budget": False}}
    no_second = ExtractConf.from_dict(no_second)

    def assert_plain(f):
        np.testing.assert_array_equal(f.keypoints, plain.keypoints)
        np.testing.assert_array_equal(f.descriptors, plain.descriptors)
        np.testing.assert_array_equal(f.shapes, plain.shapes)

    for depth in (
        None,
        DepthMap(np.full((30, 40), np.nan)),  # no valid depth
        DepthMap(np.random.default_rng(0).uniform(1, 50, (90, 120))),
    ):  # noise
        res = extract_image(img, CAMERA, depth, single)
        if depth is None:
            assert not res.rectifications
            assert_plain(res.features)
        else:
            assert res.rectifications
            axes = {res.planes.patches[r.patch_index].axis for r in res.rectifications}
            assert axes == {BLIND_AXIS}
            assert_plain(res.features.subset(res.features.patch < 0))
        res = extract_image(img, CAMERA, depth, no_second)
        assert not res.rectifications
        assert_plain(res.features)
        # the default may add views from vanishing points, on top of every plain feature
        out = extract_image(img, CAMERA, depth).features
        assert_plain(out.subset(out.patch < 0))


def test_rectified_keypoints_lie_on_the_plane_consistently(texture):
    """Keypoints from a rectified patch map to the same plane points as their affine frames
    predict: A = J A_rect, checked against the homography between two views."""
    R0, t0 = look_at([0.5, -5, 3.5], [0, 0, 0])
    img, z = plane_view(texture, 0.01, K, R0, t0, SIZE)
    conf = ExtractConf.from_dict(SINGLE_VIEW)
    res = extract_image(img, CAMERA, DepthMap(z, "metric"), conf)
    assert len(res.rectifications) == 1
    rect = res.rectifications[0]
    assert np.degrees(np.arccos(abs(rect.normal @ R0[:, 2]))) < 0.5
    f = res.features
    on_patch = f.patch >= 0
    assert on_patch.sum() > 0.2 * (~on_patch).sum()  # on top of plain SIFT's
    # rectified keypoint frames are not similarities any more (foreshortening undone)
    A = f.shapes[on_patch]
    sv = np.linalg.svd(A, compute_uv=False)
    assert np.median(sv[:, 0] / sv[:, 1]) > 1.3


def test_rectified_sift_matches_more_than_plain_at_strong_viewpoint_change(texture):
    """A ground plane seen from pairs of directions 60-90 degrees apart at grazing angles:
    rectified SIFT (exact depth) must find clearly more correct matches than plain SIFT."""
    rng = np.random.default_rng(5)
    wins, plain_total, rect_total = 0, 0, 0
    n_pairs = 6
    for _ in range(n_pairs):
        az0 = rng.uniform(0, 2 * np.pi)
        az1 = az0 + np.deg2rad(rng.uniform(60, 90)) * rng.choice([-1, 1])
        elev = np.deg2rad(rng.uniform(25, 35))
        views = []
        for az in (az0, az1):
            eye = 4.5 * np.array(
                [np.cos(az) * np.cos(elev), np.sin(az) * np.cos(elev), np.sin(elev)]
            )
            R, t = look_at(eye, [0, 0, 0])
            img, z = plane_view(texture, 0.01, K, R, t, SIZE)
            views.append((R, t, img, z))
        H = plane_homography(views[0][0], views[0][1], views[1][0], views[1][1])
        p = [detect_sift(v[2]) for v in views]
        r = [extract_image(v[2], CAMERA, DepthMap(v[3], "metric")).features for v in views]
        cp, cr = correct_matches(p[0], p[1], H), correct_matches(r[0], r[1], H)
        plain_total += cp
        rect_total += cr
        wins += cr > cp
    assert wins >= n_pairs - 1
    assert rect_total > 1.5 * plain_total


def test_patches_start_at_octave_0_from_the_pixels_per_feature_threshold(texture):
    """480x360 with 4000 features: 43 pixels per feature. A threshold at or below that
    gives exactly the features of patch_first_octave = 0; above it, the upsampled octave."""
    R0, t0 = look_at([0.5, -5, 3.5], [0, 0, 0])
    img, z = plane_view(texture, 0.01, K, R0, t0, SIZE)

    def patch_features(**sift):
        conf = ExtractConf()
        conf.sift.max_num_features = 4000
        conf.sift.coarse_first = False
        for key, value in sift.items():
            setattr(conf.sift, key, value)
        f = extract_image(img, CAMERA, DepthMap(z, "metric"), conf).features
        return f.subset(f.patch >= 0)

    # the threshold also counts the image's pixels for the views' budget
    # (budget.view_pixel_budget): the runs compared share it
    at_threshold = patch_features(patch_octave0_pixels_per_feature=43.0)
    octave0 = patch_features(patch_first_octave=0, patch_octave0_pixels_per_feature=43.0)
    upsampled = patch_features(patch_octave0_pixels_per_feature=44.0)
    assert len(at_threshold) > 100
    np.testing.assert_array_equal(at_threshold.keypoints, octave0.keypoints)
    np.testing.assert_array_equal(at_threshold.descriptors, octave0.descriptors)
    # the upsampled octave finds more and finer points (the smallest scales, original
    # pixels). Plain SIFT fills its 4000 here, so only the depth plane has a view (no plane
    # hypotheses: pipeline.UNUSED_BUDGET_AXES); measured 2142 against 824 points, 10 %
    # scale quantile 0.81 against 1.00
    assert len(upsampled) > 1.5 * len(octave0)
    assert np.quantile(upsampled.scales, 0.1) < 0.9 * np.quantile(octave0.scales, 0.1)


def test_viewing_angles_texture_masks_and_which_patches_get_views():
    h, w = 36, 48  # work grid of the 480x360 camera (10 px cells)
    centre = np.zeros((h, w), bool)
    centre[17:19, 23:25] = True  # the 4 cells around the principal point (240, 180)
    tilt = np.deg2rad(40.0)
    n = np.array([np.sin(tilt), 0.0, -np.cos(tilt)])  # faces the camera, 40 deg tilt
    frontal = np.array([0, 0, -1.0])
    angle = viewing_angles(CAMERA, [Patch(centre, 0, n, 0.0), Patch(centre, 1, frontal, 0.0)])
    # Cells are 5 px (0.7 deg) from the axis: the angles are 40 and ~1 degrees.
    assert abs(angle[0] - 40.0) < 1.0 and angle[1] < 1.5
    # a textured left half, a blank right half: each patch keeps its textured cells and
    # TEXTURE_MARGIN more (the image's texture_map is measured on the same grid)
    img = textured_image(SIZE[1], SIZE[0], 3)
    img[:, SIZE[0] // 2 :] = 128
    whole = np.ones((h, w), bool)
    steep = np.array([np.sin(1.2), 0.0, -np.cos(1.2)])  # 69 deg
    patches = [Patch(whole, 0, steep, 1.0), Patch(whole, 1, frontal, 1.0)]
    cut = textured_patches(img, patches, min_texture=5.0)
    cols = np.flatnonzero(cut[0].mask.any(0))
    assert cols.min() == 0 and w // 2 <= cols.max() <= w // 2 + TEXTURE_MARGIN
    assert cut[0].mask.all(0)[: w // 2 - 1].all() and cut[0].area_frac < 0.6
    conf = ExtractConf().rectify  # rectified from 30 degrees: the frontal patch is left
    assert patches_worth_rectifying(CAMERA, cut, conf) == [0]
    blank = np.full((SIZE[1], SIZE[0]), 128, np.uint8)
    assert not textured_patches(blank, patches, 5.0)[0].mask.any()
    assert patches_worth_rectifying(CAMERA, textured_patches(blank, patches, 5.0), conf) == []


def test_without_specks_drops_components_too_small_for_a_view_of_their_own():
    mask = np.zeros((40, 50), bool)  # 2000 cells: MIN_VIEW_AREA_FRAC x 2000 = 10
    mask[2:4, 2:7] = True  # 10 cells: kept
    mask[10:13, 10:13] = True  # 9 cells: dropped
    mask[20, 20] = mask[21, 21] = mask[22, 22] = mask[23, 23] = mask[24, 24] = True
    mask[25:30, 25] = True  # 10 cells joined by a corner (8-connected): kept
    kept = without_specks(mask, MIN_VIEW_AREA_FRAC)
    expected = mask.copy()
    expected[10:13, 10:13] = False
    np.testing.assert_array_equal(kept, expected)
    assert not without_specks(np.zeros((4, 4), bool), 0.1).any()


def test_texture_specks_do_not_widen_a_view():
    # a textured left half on a blank right half with a few specks of noise: a view of a
    # steep plane over the whole image keeps the textured half only, as large as without
    # the specks (a speck near the plane's horizon would have widened its box: views of
    # generated pairs grew 40x over specks of background noise, then lost their
    # resolution to the pixel budget); the work grid of the depth network (1.25 px cells)
    h, w = 288, 384
    img = textured_image(SIZE[1], SIZE[0], 3)
    img[:, SIZE[0] // 2 :] = 128
    clean = img.copy()
    for x, y in [(300, 40), (340, 200), (455, 330), (440, 90)]:
        img[y : y + 4, x : x + 4] = 255
    steep = np.array([np.sin(1.2), 0.0, -np.cos(1.2)])  # 69 deg, the right half farther
    whole = [Patch(np.ones((h, w), bool), 0, steep, 1.0)]
    cut = textured_patches(img, whole, min_texture=5.0)[0]
    np.testing.assert_array_equal(cut.mask, textured_patches(clean, whole, 5.0)[0].mask)
    assert w // 2 <= np.flatnonzero(cut.mask.any(0)).max() <= w // 2 + TEXTURE_MARGIN
    conf = ExtractConf().rectify
    view = patch_view(CAMERA, cut, conf)
    speckled = cut.mask.copy()
    speckled[156:166, 268:278] = True  # the speck at (340, 200), dilated, as kept before
    wide = patch_view(CAMERA, Patch(speckled, 0, steep, 1.0), conf)
    box = np.prod(view.hi - view.lo) * view.f**2
    assert np.prod(wide.hi - wide.lo) * wide.f**2 > 3 * box


def test_frontal_plane_is_left_to_plain_sift_oblique_one_is_rectified(texture):
    conf = ExtractConf.from_dict(SINGLE_VIEW)
    conf.rectify.min_rectify_angle_deg = 30.0
    R, t = look_at([0.3, -0.2, 4.0], [0, 0, 0], up=(0, 1, 0))  # ~5 deg: near-frontal
    img, z = plane_view(texture, 0.01, K, R, t, SIZE)
    res = extract_image(img, CAMERA, DepthMap(z, "metric"), conf)
    # the plane gets no view; where plain SIFT leaves budget unused, the image gets blind
    # ones (the second tier), none without it
    assert {res.planes.patches[r.patch_index].axis for r in res.rectifications} <= {BLIND_AXIS}
    plain = detect_sift(img)
    kept = res.features.subset(res.features.patch < 0)
    np.testing.assert_array_equal(kept.keypoints, plain.keypoints)
    conf.dedup.lookalikes_in_unused_budget = False
    res = extract_image(img, CAMERA, DepthMap(z, "metric"), conf)
    assert not res.rectifications
    np.testing.assert_array_equal(res.features.keypoints, plain.keypoints)
    R, t = look_at([0.5, -5, 3.5], [0, 0, 0])  # ~55 deg
    img, z = plane_view(texture, 0.01, K, R, t, SIZE)
    res = extract_image(img, CAMERA, DepthMap(z, "metric"), conf)
    assert len(res.rectifications) == 1 and (res.features.patch >= 0).sum() > 100


def test_timed_adds_the_seconds_of_the_block_on_the_module_clock(monkeypatch):
    ticks = iter([1.0, 3.5, 10.0, 10.25])
    monkeypatch.setattr(pipeline, "time", types.SimpleNamespace(perf_counter=lambda: next(ticks)))
    t = {}
    with timed(t, "a"):
        pass
    assert t == {"a": 2.5}
    with timed(t, "a"):
        pass
    assert t == {"a": 2.75}


def test_timings_keys(texture):
    R, t = look_at([3.0, -0.5, 2.5], [0, 0, 0], up=(0, 1, 0))
    img, z = plane_view(texture, 0.01, K, R, t, SIZE)
    res = extract_image(img, CAMERA, DepthMap(z, "metric"))
    assert res.rectifications
    assert list(res.timings) == [
        "normals",
        "planes",
        "sift_plain",  # before the vanishing points: the plane hypotheses need its count
        "vp",
        "homographies",
        "warps+sift_patches",
        "dedup",
    ]


def test_sift_conf_is_plain_sift_whatever_the_depth():
    """`--conf sift` is the plain-SIFT baseline even with a depth network or files: no
    depth patch, no plane hypothesis from vanishing points (the default's are whole-image
    views that need no depth patch), exact COLMAP calls. The same view with the default
    conf is rectified, so the test sees the difference."""
    from rectified_colmap.camera import make_camera
    from rectified_colmap.config import confs
    from tests.scenes import street_pair

    view, _ = street_pair(3)
    h, w = view["depth"].shape
    K = view["camera"].calibration_matrix()
    camera = make_camera("PINHOLE", [K[0, 0], K[1, 1], K[0, 2], K[1, 2]], w, h)
    depth = DepthMap(view["depth"].astype(np.float32), "depth")
    plain = extract_image(view["image"], camera, None, ExtractConf.from_dict(confs["sift"]))
    res = extract_image(view["image"], camera, depth, ExtractConf.from_dict(confs["sift"]))
    assert not res.rectifications
    np.testing.assert_array_equal(res.features.keypoints, plain.features.keypoints)
    np.testing.assert_array_equal(res.features.descriptors, plain.features.descriptors)
    assert extract_image(view["image"], camera, depth).rectifications  # the default rectifies


def test_planes_the_lines_do_not_confirm_share_their_pixels_and_room_with_blind_views(texture):
    """An oblique textured plane without straight lines: its depth plane's view comes with
    blind views (BLIND_AXIS: lines_support is False, budget.blind_share), the depth view
    within 1 - UNSUPPORTED_BLIND_SHARE of the pixel budget and the blind ones within what it
    leaves (to a view's border), every plain feature kept first and the rectified ones
    within the room. Without lines in the conf (vp.enabled false): the depth view alone.
    Where plain SIFT fills its budget, the same features either way."""
    from rectified_colmap.budget import UNSUPPORTED_BLIND_SHARE, rectified_room, view_pixel_budget

    R, t = look_at([0.5, -5, 3.5], [0, 0, 0])
    img, z = plane_view(texture, 0.01, K, R, t, SIZE)
    depth = DepthMap(z, "metric")
    lines = {"vp": {"line_hypotheses": 0}, "rectify": {"tilt_steps": 0}}
    conf = ExtractConf.from_dict(lines)
    plain = detect_sift(img)
    res = extract_image(img, CAMERA, depth, conf)
    axes = np.array([res.planes.patches[r.patch_index].axis for r in res.rectifications])
    pixels = np.array([r.size[0] * r.size[1] for r in res.rectifications], float)
    budget = view_pixel_budget(img.shape, conf)
    blind = axes == BLIND_AXIS
    assert blind.any() and (~blind).sum() == 1
    assert pixels[~blind].sum() <= (1 - UNSUPPORTED_BLIND_SHARE) * budget
    border = 2 * conf.rectify.border * np.sqrt(pixels).sum()  # tiny views' borders
    assert pixels.sum() <= budget + border
    f = res.features
    np.testing.assert_array_equal(f.keypoints[: len(plain)], plain.keypoints)
    assert (f.patch[: len(plain)] < 0).all() and (f.patch[len(plain) :] >= 0).all()
    assert len(f) - len(plain) <= rectified_room(len(plain), conf)
    blind_patches = [r.patch_index for r, b in zip(res.rectifications, blind) if b]
    assert np.isin(f.patch, blind_patches).any()  # blind features kept
    alone = extract_image(img, CAMERA, depth, ExtractConf.from_dict(SINGLE_VIEW))
    assert len(alone.rectifications) == 1
    full = {"sift": {"max_num_features": len(plain) // 2}}
    a = extract_image(img, CAMERA, depth, ExtractConf.from_dict({**lines, **full}))
    b = extract_image(img, CAMERA, depth, ExtractConf.from_dict({**SINGLE_VIEW, **full}))
    np.testing.assert_array_equal(a.features.keypoints, b.features.keypoints)
    np.testing.assert_array_equal(a.features.descriptors, b.features.descriptors)


def test_depth_planes_views_get_tilt_neighbours_only_where_plain_sift_left_budget_unused(
    texture,
):
    """pipeline.image_views: a depth plane's view seen at 60 degrees gets its two tilt
    neighbours (t x or / sqrt 2, its axis) where plain SIFT's keypoints left part of its
    budget unused, none where they fill it, and none with rectify.tilt_steps 0."""
    R, t = look_at([0.0, -5, 3.0], [0, 0, 0])
    img, _ = plane_view(texture, 0.01, K, R, t, SIZE)
    shape = (45, 60)
    v = np.array([0.0, 0.0, 1.0])  # the ray through the image centre
    normal = np.array([-np.sin(np.pi / 3), 0.0, -np.cos(np.pi / 3)])  # 60 degrees from it
    patch = Patch(np.ones(shape, bool), 0, normal, 1.0)
    conf = ExtractConf()
    budget = conf.sift.max_num_features
    room = pipeline.image_views(img, CAMERA, [patch], shape, budget // 2, conf)
    assert [p.axis for p in room.patches] == [0, 0, 0] and len(room.rects) == 3
    tilts = sorted(1.0 / -(p.normal @ v) for p in room.patches)
    np.testing.assert_allclose(tilts, [2 / np.sqrt(2), 2.0, 2 * np.sqrt(2)], rtol=0.05)
    full = pipeline.image_views(img, CAMERA, [patch], shape, budget, conf)
    assert len(full.patches) == 1 and len(full.rects) == 1
    off = ExtractConf.from_dict({"rectify": {"tilt_steps": 0}})
    alone = pipeline.image_views(img, CAMERA, [patch], shape, budget // 2, off)
    assert len(alone.patches) == 1 and len(alone.rects) == 1


def test_lines_support_is_a_hypothesis_or_a_normal_the_lines_changed():
    """pipeline.lines_support: True where the lines added a plane hypothesis or turned a
    depth patch's normal; False where they left every patch as the depth gave it."""
    from rectified_colmap.planes import HYPOTHESIS_AXIS

    conf = ExtractConf()  # the lines on (vp.enabled)
    mask = np.ones((4, 5), bool)
    depth_patch = Patch(mask, 0, np.array([0.0, 0.0, -1.0]), 1.0)
    planes = types.SimpleNamespace(patches=[depth_patch])
    same = types.SimpleNamespace(patches=[Patch(mask, 0, np.array([0.0, 0.0, -1.0]), 1.0)])
    assert not pipeline.lines_support(planes, same, conf)
    turned = Patch(mask, 0, np.array([0.0, 0.1, -1.0]) / np.hypot(0.1, 1.0), 1.0)
    assert pipeline.lines_support(planes, types.SimpleNamespace(patches=[turned]), conf)
    hyp = Patch(mask, HYPOTHESIS_AXIS, np.array([1.0, 0.0, -1.0]) / np.sqrt(2), 1.0)
    assert pipeline.lines_support(planes, types.SimpleNamespace(patches=[depth_patch, hyp]), conf)
    assert not pipeline.lines_support(types.SimpleNamespace(patches=[]), planes, conf)
