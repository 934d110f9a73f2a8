"""rectified_colmap_research.evaluation.extreme_pairs: generated extreme pairs, exact
ground truth, anti-aliased rendering, labels, split, rejection."""

import cv2
import numpy as np
import pytest
from rectified_colmap_research.evaluation.extreme_pairs import (
    ExtremeConf,
    ViewParams,
    bin_label,
    build_view,
    clip_polygon,
    compression,
    draw_pair,
    homogeneous_map,
    is_both_oblique,
    labels,
    pair_overlap,
    pair_rotation_class,
    polygon_area,
    rejection,
    render_view,
    rotation_class,
    sees_texture,
    singular_values,
    split_of,
    texture_pyramid,
    texture_region,
    SCALE_BINS,
    TILT_BINS,
)
from rectified_colmap_research.evaluation.plane_pairs import homography_jacobian

from rectified_colmap.conventions import pixel_centers, to_opencv_homography
from rectified_colmap.eval.homography import points_in_region

TEX = (900, 600)  # (W, H) of the texture in the geometric tests


def view(anchor=(450.0, 300.0), **kw):
    p = dict(
        tilt=2.5,
        direction_deg=30.0,
        rotation_deg=0.0,
        scale=1.0,
        focal=900.0,
        size=(640, 480),
        anchor_px=(300.0, 260.0),
    )
    p.update(kw)
    return build_view(np.asarray(anchor, float), ViewParams(**p))


# -- geometry --------------------------------------------------------------------------------
def test_view_has_the_drawn_tilt_scale_anchor_and_normal():
    anchor = np.array([420.0, 250.0])
    for tilt, direction, rot, scale in [(1.0, 0, 0, 1.0), (3.0, 30, 90, 1.5), (8.0, 250, 33, 0.4)]:
        v = view(anchor, tilt=tilt, direction_deg=direction, rotation_deg=rot, scale=scale)
        xy, w = homogeneous_map(v.G, anchor[None])
        np.testing.assert_allclose(xy[0], v.params.anchor_px, atol=1e-9)
        assert w[0] > 0
        ray = v.center - np.r_[anchor, 0.0]
        assert 1 / (ray @ [0, 0, -1] / np.linalg.norm(ray)) == pytest.approx(tilt, rel=1e-9)
        s = singular_values(homography_jacobian(v.G, anchor[None]))[0]
        assert s[0] == pytest.approx(scale, rel=1e-9)
        np.testing.assert_allclose(s, np.linalg.svd(homography_jacobian(v.G, anchor[None])[0])[1])
        # the normal faces the camera: n . X_c < 0 for plane points, and is the plane's
        X = np.array([[0.0, 0, 0], [900, 0, 0], [0, 600, 0]])
        Xc = X @ v.R.T + v.t
        assert (Xc @ v.normal < 0).all()
        np.testing.assert_allclose((Xc - Xc[0]) @ v.normal, 0, atol=1e-6)
        np.testing.assert_allclose(v.R @ v.R.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(v.R) == pytest.approx(1.0)


def test_anchor_on_the_axis_gives_anisotropy_equal_to_the_tilt():
    v = view(tilt=4.0, anchor_px=(320.0, 240.0))  # the principal point
    s = singular_values(homography_jacobian(v.G, np.array([[450.0, 300.0]])))[0]
    assert s[0] / s[1] == pytest.approx(4.0, rel=1e-9)


def test_in_plane_rotation_turns_the_scene_by_minus_psi():
    """Frontal views: psi = 0 keeps texture x along image x; psi = 90 puts it along image
    -y (the image's vertical is the scene's horizontal); psi = 180 turns it upside down."""
    a = np.array([450.0, 300.0])
    for psi, expect in [(0, (1, 0)), (90, (0, -1)), (180, (-1, 0)), (270, (0, 1))]:
        v = view(a, tilt=1.0, rotation_deg=psi, anchor_px=(320.0, 240.0))
        xy, _ = homogeneous_map(v.G, np.array([a, a + [10.0, 0.0]]))
        d = (xy[1] - xy[0]) / np.linalg.norm(xy[1] - xy[0])
        np.testing.assert_allclose(d, expect, atol=1e-9)


def test_pair_homography_and_true_normals_agree_with_the_decomposition():
    """H = G1 G0^-1 maps every texture point's view-0 image onto its view-1 image, and the
    true normals are a solution of the decomposition of H with the true intrinsics."""
    rng = np.random.default_rng(0)
    for both in (True, False, True):
        d = draw_pair(rng, TEX, ExtremeConf(), both)
        uv = rng.uniform([0, 0], TEX, (200, 2))
        x0, _ = homogeneous_map(d.v0.G, uv)
        x1, _ = homogeneous_map(d.v1.G, uv)
        ok = np.isfinite(x0).all(1) & np.isfinite(x1).all(1)
        np.testing.assert_allclose(homogeneous_map(d.H, x0[ok])[0], x1[ok], atol=1e-6)
        Hn = np.linalg.inv(d.v1.K) @ d.H @ d.v0.K
        _, Rs, _, ns = cv2.decomposeHomographyMat(Hn / np.cbrt(np.linalg.det(Hn)), np.eye(3))
        n0s = [-n.ravel() / np.linalg.norm(n) for n in ns]
        k = int(np.argmin([np.linalg.norm(n - d.v0.normal) for n in n0s]))
        np.testing.assert_allclose(n0s[k], d.v0.normal, atol=1e-6)
        np.testing.assert_allclose(Rs[k] @ n0s[k], d.v1.normal, atol=1e-6)


# -- rendering -------------------------------------------------------------------------------
def dots_texture(spacing=60, sigma=2.5):
    """(600, 900) float texture of Gaussian dots at known COLMAP positions -> (image, (N, 2))."""
    W, H = TEX
    c = np.stack(
        np.meshgrid(np.arange(spacing, W - spacing + 1, spacing), np.arange(spacing, H, spacing)),
        -1,
    ).reshape(-1, 2) + [0.3, 0.7]  # off the pixel grid
    xy = pixel_centers(W, H)
    img = np.zeros((H, W), np.float64)
    for p in c:  # a few dozen dots
        img += np.exp(-((xy - p) ** 2).sum(-1) / (2 * sigma**2))
    return np.clip(img * 250, 0, 255).round().astype(np.uint8), c


def blob_centroids(img, thresh=4):
    """Intensity-weighted centroids (COLMAP pixels) of the bright blobs of ``img``, and
    whether each touches the border."""
    n, lab, stats, _ = cv2.connectedComponentsWithStats((img > thresh).astype(np.uint8))
    xy = pixel_centers(img.shape[1], img.shape[0])
    out, border = [], []
    for k in range(1, n):
        m = lab == k
        w = img[m].astype(np.float64)
        out.append((xy[m] * w[:, None]).sum(0) / w.sum())
        x, y, ww, hh = stats[k, :4]
        border.append(x <= 1 or y <= 1 or x + ww >= img.shape[1] - 1 or y + hh >= img.shape[0] - 1)
    return np.array(out).reshape(-1, 2), np.array(border, bool)


def ideal_dots(G, size, centres, sigma=2.5, ss=4, radius=20):
    """The dots texture seen through G in closed form: each pixel the mean of ss x ss point
    samples of the analytic Gaussians (no interpolation, no quantisation), near each dot
    (the dots are far apart: each window holds its own dot only)."""
    W, H = size
    img = np.zeros((H, W))
    pred, _ = homogeneous_map(G, centres)
    Ginv = np.linalg.inv(G)
    for p, c in zip(pred, centres):
        if not np.isfinite(p).all():
            continue
        x0, y0 = np.maximum(np.floor(p - radius).astype(int), 0)
        x1, y1 = np.minimum(np.ceil(p + radius).astype(int), [W, H])
        if x1 <= x0 or y1 <= y0:
            continue
        xy = pixel_centers((x1 - x0) * ss, (y1 - y0) * ss, x1 - x0, y1 - y0) + [x0, y0]
        uv, _ = homogeneous_map(Ginv, xy.reshape(-1, 2))
        val = np.exp(-((uv - c) ** 2).sum(-1) / (2 * sigma**2)) * 250
        img[y0:y1, x0:x1] += val.reshape(y1 - y0, ss, x1 - x0, ss).mean((1, 3))
    return img


def test_rendered_dots_land_where_the_homographies_say():
    """Dots of a texture, rendered into two views: each view's image of a dot is where its G
    maps the dot's centre, and H = G1 G0^-1 maps its view-0 image onto its view-1 image,
    within a small fraction of a pixel (what is left is the centroid of a perspective
    image of a Gaussian, not its centre's image); the rendering itself matches the
    closed-form image of the dots to 0.06 px."""
    tex, centres = dots_texture()
    v0 = view(tilt=1.6, direction_deg=20.0, rotation_deg=90.0, scale=1.3, anchor_px=(330, 250))
    v1 = view(tilt=1.9, direction_deg=150.0, rotation_deg=37.0, scale=1.8, anchor_px=(300, 230))
    found = []
    for v in (v0, v1):
        img = render_view(tex, v.G, v.params.size, fill=0.0)
        c, border = blob_centroids(img)
        c, pred = c[~border], homogeneous_map(v.G, centres)[0]
        dist = np.linalg.norm(c[:, None] - pred[None], axis=-1)
        nearest = dist.argmin(1)
        err = dist[np.arange(len(c)), nearest]
        assert len(err) >= 15
        assert err.max() < 0.15 and err.mean() < 0.05, np.sort(err)[-5:]
        found.append(dict(zip(nearest, c)))
        ideal, ib = blob_centroids(ideal_dots(v.G, v.params.size, centres))
        d = np.linalg.norm(c[:, None] - ideal[~ib][None], axis=-1).min(1)
        d = d[d < 1]  # the same dots (not cut by the border in one of the two)
        assert len(d) >= 15 and d.max() < 0.06, np.sort(d)[-5:]
    common = sorted(set(found[0]) & set(found[1]))
    assert len(common) >= 8
    H = v1.G @ np.linalg.inv(v0.G)
    a = np.array([found[0][k] for k in common])
    b = np.array([found[1][k] for k in common])
    assert np.linalg.norm(homogeneous_map(H, a)[0] - b, axis=1).max() < 0.25


@pytest.mark.parametrize("tilt, scale", [(2.0, 0.3), (1.2, 0.08)])
def test_strong_compression_is_antialiased_and_the_outside_is_the_fill(tilt, scale):
    """A 1-texel checkerboard seen minified 3-8x (supersampling) and 12x (beyond its cap:
    the pyramid's share): the rendering is its mean grey (a plain warp aliases into moire),
    and where the view sees no texture it is the fill."""
    W, H = TEX
    yy, xx = np.mgrid[0:H, 0:W]
    tex = (((xx + yy) % 2) * 255).astype(np.uint8)
    v = view(tilt=tilt, scale=scale, anchor_px=(320.0, 240.0), direction_deg=0.0)
    img = render_view(tex, v.G, v.params.size, fill=77.0)
    g = pixel_centers(640, 480).reshape(-1, 2)
    seen = sees_texture(v.G, TEX, g).reshape(480, 640)
    inner = cv2.erode(seen.astype(np.uint8), np.ones((5, 5))).astype(bool)
    assert inner.mean() > 0.005
    assert abs(img[inner].mean() - 127.5) < 2 and img[inner].std() < 3
    assert (img[~cv2.dilate(seen.astype(np.uint8), np.ones((5, 5))).astype(bool)] == 77).all()
    naive = cv2.warpPerspective(tex, to_opencv_homography(v.G), (640, 480), flags=cv2.INTER_LINEAR)
    assert naive[inner].std() > 30


def test_anisotropic_compression_is_supersampled():
    """A sine grating (period 2.5 texels, across the tilt) in a view at tilt 6: where the
    view compresses it 3-8x (beyond its Nyquist rate) the rendering keeps a small fraction
    of its contrast (a box filter's side lobes), a plain warp keeps aliased contrast."""
    W, H = TEX
    xx = np.mgrid[0:H, 0:W][1]
    tex = (127.5 + 120 * np.sin(2 * np.pi * (xx + 0.5) / 2.5)).round().astype(np.uint8)
    v = view(tilt=6.0, scale=1.5, anchor_px=(320.0, 240.0), direction_deg=0.0)
    img = render_view(tex, v.G, v.params.size)
    g = pixel_centers(640, 480).reshape(-1, 2)
    seen = sees_texture(v.G, TEX, g).reshape(480, 640)
    s = compression(v.G, g).reshape(480, 640, 2)
    zone = cv2.erode(seen.astype(np.uint8), np.ones((5, 5))).astype(bool)
    zone &= (s[..., 0] >= 3) & (s[..., 0] <= 8) & (s[..., 1] < 1)
    assert zone.mean() > 0.05
    naive = cv2.warpPerspective(tex, to_opencv_homography(v.G), (640, 480), flags=cv2.INTER_LINEAR)
    assert naive[zone].std() > 40  # the grating's own std: 85
    assert abs(img[zone].mean() - 127.5) < 2 and img[zone].std() < 12


def test_beyond_the_horizon_is_the_fill_not_mirrored_content():
    """A view at 83 degrees whose image holds the plane's horizon: pixels whose rays miss
    the plane (behind the camera) are the fill."""
    tex = np.full((600, 900), 200, np.uint8)
    v = view(tilt=8.0, direction_deg=90.0, scale=2.0, focal=400.0, anchor_px=(320.0, 400.0))
    g = pixel_centers(640, 480).reshape(-1, 2)
    _, w = homogeneous_map(np.linalg.inv(v.G), g)
    behind = (w <= 0).reshape(480, 640)
    assert behind.mean() > 0.05
    img = render_view(tex, v.G, (640, 480), fill=10.0)
    assert (img[behind] == 10).all()


def test_pyramid_levels_are_exact_block_means():
    t = np.arange(7 * 9, dtype=np.uint8).reshape(7, 9) * 3
    p = texture_pyramid(t, 2)
    assert [q.shape for q in p] == [(7, 9), (3, 4), (1, 2)]
    np.testing.assert_array_equal(p[1][0, 0], np.round(t[:2, :2].mean()))
    np.testing.assert_array_equal(p[1][2, 3], np.round(t[4:6, 6:8].mean()))


# -- regions ---------------------------------------------------------------------------------
def test_clip_polygon_keeps_the_half_plane():
    sq = np.array([[0.0, 0], [2, 0], [2, 2], [0, 2]])
    half = clip_polygon(sq, 1.0, 0.0, -1.0)  # x >= 1
    assert polygon_area(half) == pytest.approx(2.0)
    assert (half[:, 0] >= 1 - 1e-12).all()
    assert len(clip_polygon(sq, 1.0, 0.0, -5.0)) == 0
    np.testing.assert_allclose(clip_polygon(sq, 1.0, 0.0, 1.0), sq)


@pytest.mark.parametrize(
    "kw",
    [
        dict(tilt=1.2, scale=0.5, anchor_px=(320.0, 240.0)),  # the whole texture inside
        dict(tilt=1.0, scale=3.0),  # the image inside the texture
        dict(tilt=3.0, scale=1.2, direction_deg=200.0, rotation_deg=90.0),
        dict(tilt=8.0, direction_deg=90.0, scale=2.0, focal=400.0, anchor_px=(320.0, 400.0)),
    ],
)
def test_texture_region_is_where_the_view_sees_the_texture(kw):
    v = view(**kw)
    poly = texture_region(v, TEX)
    assert len(poly) >= 3 and np.isfinite(poly).all()
    g = pixel_centers(640, 480).reshape(-1, 2)
    inside = points_in_region(g, [poly])
    seen = sees_texture(v.G, TEX, g)
    assert np.mean(inside == seen) > 0.995
    assert polygon_area(poly) / (640 * 480) == pytest.approx(seen.mean(), abs=0.01)


def test_whole_texture_in_view_gives_its_mapped_corners():
    v = view(tilt=1.2, scale=0.5, anchor_px=(320.0, 240.0))
    corners = np.array([[0.0, 0], [900, 0], [900, 600], [0, 600]])
    poly = texture_region(v, TEX)
    assert len(poly) == 4
    np.testing.assert_allclose(poly, homogeneous_map(v.G, corners)[0], atol=1e-9)


# -- labels, split, rejection, determinism ---------------------------------------------------
def test_bins_and_rotation_classes():
    assert [bin_label(t, TILT_BINS) for t in (1.0, 1.99, 2.0, 3.9, 4.0, 8.0)] == [
        "<2",
        "<2",
        "2-4",
        "2-4",
        "4-8",
        "4-8",
    ]
    assert [bin_label(c, SCALE_BINS) for c in (1.0, 2.0, 3.99, 4.0, 6.0)] == [
        "<2x",
        "2-4x",
        "2-4x",
        ">4x",
        ">4x",
    ]
    assert [rotation_class(d) for d in (0, 90, 270, 180, 359.5, -90, 45, 92)] == [
        "0",
        "90",
        "90",
        "180",
        "0",
        "90",
        "other",
        "other",
    ]
    assert pair_rotation_class(0, 270) == "90"
    assert pair_rotation_class(180, 33) == "180"
    assert pair_rotation_class(33, 0) == "other"
    assert pair_rotation_class(0, 360) == "0"


def test_both_oblique_needs_two_tilts_over_two_in_different_directions():
    conf = ExtremeConf()

    def p(t, d):
        return ViewParams(t, d, 0.0, 1.0, 900.0, (640, 480), (320.0, 240.0))

    assert is_both_oblique(p(2.0, 10), p(5.0, 350), conf) is False  # 20 degrees apart
    assert is_both_oblique(p(2.0, 10), p(5.0, 300), conf) is True
    assert is_both_oblique(p(1.9, 10), p(5.0, 190), conf) is False
    rng = np.random.default_rng(3)
    for both in (True, False):
        for _ in range(5):
            d = draw_pair(rng, TEX, conf, both)
            assert labels(d, conf)["both_oblique"] == ("yes" if both else "no")
    assert conf.both_oblique_frac >= 0.5


def test_split_is_a_stable_hash_of_the_group():
    assert split_of("strecha-dev/entry-P10") == split_of("strecha-dev/entry-P10")
    # fixed values: changing the rule moves photos between halves (docs/evaluation.md)
    assert split_of("strecha-dev/entry-P10") == "choose"
    assert split_of("strecha-dev/fountain-P11") == "check"
    assert split_of("real-pool/british-museum") == "choose"  # both of its photos
    halves = [split_of(f"group{k}") for k in range(200)]
    assert 70 < halves.count("check") < 130


def test_rejection_rule():
    conf = ExtremeConf()
    ok = dict(
        viewpoint_deg=70.0,
        coverage0=0.5,
        coverage1=0.4,
        overlap01=0.9,
        overlap10=0.1,
        common0=0.4,
        common1=0.05,
    )
    assert rejection(ok, conf) is None
    assert rejection(ok | {"viewpoint_deg": 120.0}, conf) == "viewpoint"
    assert rejection(ok | {"coverage1": 0.1}, conf) == "coverage"
    assert rejection(ok | {"overlap10": 0.01}, conf) == "overlap"
    assert rejection(ok | {"overlap01": 0.2}, conf) == "overlap"
    assert rejection(ok | {"common1": 0.01}, conf) == "common"


def test_overlap_of_views_around_distant_anchors_is_rejected():
    v0 = view((150.0, 150.0), tilt=1.0, scale=2.0)  # footprints 320 x 240 texels
    v1 = view((750.0, 450.0), tilt=1.0, scale=2.0)
    s = pair_overlap(v0, v1, TEX) | {"viewpoint_deg": 10.0}
    assert s["overlap01"] == 0 and s["overlap10"] == 0
    assert rejection(s, ExtremeConf()) == "overlap"
    small = view(scale=0.1)  # the texture a speck in the image
    s = pair_overlap(small, v0, TEX) | {"viewpoint_deg": 10.0}
    assert s["coverage0"] < 0.2 and rejection(s, ExtremeConf()) == "coverage"


def test_kept_pairs_obey_the_rule_and_draws_are_deterministic():
    conf = ExtremeConf()
    a = [draw_pair(np.random.default_rng(7), TEX, conf, b) for b in (True, False)]
    b = [draw_pair(np.random.default_rng(7), TEX, conf, b) for b in (True, False)]
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x.H, y.H)
        assert x.v0.params == y.v0.params and x.stats == y.stats
        again = pair_overlap(x.v0, x.v1, TEX) | {"viewpoint_deg": x.stats["viewpoint_deg"]}
        assert rejection(again, conf) is None
    c = draw_pair(np.random.default_rng(8), TEX, conf, True)
    assert not np.allclose(c.H, a[0].H)


def test_extract_guessed_is_rectsift_with_the_guessed_camera(tmp_path):
    """extract_guessed: the image read from disk, f = 1.2 x its longer side, the depth
    source's depth, seed 0: the features of that composition, call for call."""
    from rectified_colmap.config import ExtractConf
    from rectified_colmap.depth.registry import load_depth_source
    from rectified_colmap.io.images import read_image
    from rectified_colmap.pipeline import extract_image
    from rectified_colmap_research.evaluation.extreme_pairs import extract_guessed, guessed_camera
    from rectified_colmap_research.synth.planar import textured_image

    cv2.imwrite(str(tmp_path / "a.png"), textured_image(240, 320, seed=3))
    source, conf = load_depth_source("rectsift-lite0", num_threads=1), ExtractConf()
    res, cam = extract_guessed(tmp_path, "a.png", source, conf)
    assert (cam.width, cam.height) == (320, 240) and cam.params[0] == pytest.approx(384.0)
    rgb = read_image(tmp_path / "a.png")
    ref = extract_image(
        rgb, guessed_camera(320, 240), source(rgb, cam, "a.png"), conf, np.random.default_rng(0)
    )
    np.testing.assert_array_equal(res.features.keypoints, ref.features.keypoints)
    np.testing.assert_array_equal(res.features.descriptors, ref.features.descriptors)
