"""Our feature files through the REAL hloc (docs/hloc.md): match_features, reconstruction.main,
triangulation + localize_sfm, and scripts/aachen_hloc.py end to end on a mini Aachen.

Needs hloc (``pip install --no-deps ../shared/vendor/hloc``) and its imports (torch, kornia,
scipy, plotly), and the shared data beside the checkout (``../shared``, or the folder in
``RECTIFIED_COLMAP_SHARED``): the Sacre Coeur photos of the vendored hloc and Strecha
fountain-P11. Skipped, with the reason, without them. Kept small for the suite: images
downscaled to 640 px, 1024 features, two held-out queries.

Every comparison is against this tool's plain SIFT through the same hloc calls. The
tolerances reflect the measured state (docs/hloc.md), not a goal.
"""

import json
import os
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pycolmap
import pytest
from scripts_util import load_script

from rectified_colmap.eval import aachen as A

ROOT = Path(__file__).resolve().parents[2]
SHARED = Path(os.environ.get("RECTIFIED_COLMAP_SHARED", ROOT.parent / "shared"))
SACRE_COEUR = SHARED / "vendor" / "hloc" / "datasets" / "sacre_coeur" / "mapping"
FOUNTAIN = SHARED / "data" / "strecha-dev" / "fountain-P11"
MAX_SIZE = 640
NUM_FEATURES = 1024
NUM_QUERIES = 2
# Sacre Coeur: 3 of the 10 photos see another part of the church (few matches to the rest);
# the test uses the 7 of the main cluster (21 pairs).
OTHER_CLUSTER = ("10265353", "32809961", "60584745")

try:
    A.import_hloc()
    HLOC_MISSING = None
except A.HlocError as e:
    HLOC_MISSING = str(e)

pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(HLOC_MISSING is not None, reason=f"{HLOC_MISSING}"),
]


def needs(path: Path):
    if not path.is_dir():
        pytest.skip(
            f"{path} not found (shared data beside the checkout, or set RECTIFIED_COLMAP_SHARED)"
        )


# -- mini Aachen from Strecha fountain-P11 ---------------------------------------------------


@pytest.fixture(scope="module")
def mini(tmp_path_factory):
    """scripts/aachen_hloc.py as documented, for rectified SIFT and plain SIFT."""
    needs(FOUNTAIN)
    root = tmp_path_factory.mktemp("mini_aachen")
    script = load_script("aachen_hloc")
    out = {}
    for method in ("rectsift", "sift"):
        argv = [
            "--dataset",
            str(root / "dataset"),
            "--outputs",
            str(root / method),
            "--method",
            method,
            "--max_num_features",
            str(NUM_FEATURES),
            "--num_workers",
            "1",
        ]
        if method == "rectsift":  # the first run builds the dataset
            argv += [
                "--make_mini_from",
                str(FOUNTAIN),
                "--max_size",
                str(MAX_SIZE),
                "--num_queries",
                str(NUM_QUERIES),
            ]
        out[method] = script.run(script.parser().parse_args(argv))
    return SimpleNamespace(root=root, dataset=root / "dataset", **out)


def test_mini_aachen_localizes_held_out_queries(mini):
    s = mini.rectsift
    assert s["database_images"] == 7 and s["queries"] == NUM_QUERIES
    assert s["registered_images"] == 7
    assert s["points3D"] > 300
    assert s["missing"] == [] and s["not_localized"] == []
    for name, (dt, dr) in s["errors_m_deg"].items():
        assert dt < 0.25 and dr < 2.0, (name, dt, dr)
    assert s["recall"]["0.25m,2deg"] == 1.0
    # database images were extracted with the reference model's intrinsics (no guess)
    ref = pycolmap.Reconstruction(str(mini.dataset / "3D-models" / "reference"))
    with pycolmap.Database.open(mini.root / "rectsift" / "cameras-rectsift.db") as db:
        cams = {im.name: db.read_camera(im.camera_id) for im in db.read_all_images()}
    for im in ref.images.values():
        np.testing.assert_allclose(cams[im.name].params, ref.cameras[im.camera_id].params)


def test_mini_aachen_against_plain_sift(mini):
    """Same hloc calls, this tool's plain SIFT: both localize every query; rectified SIFT
    keeps at least 80% of plain SIFT's triangulated points (measured: docs/hloc.md)."""
    r, s = mini.rectsift, mini.sift
    assert s["registered_images"] == r["registered_images"] == 7
    assert s["recall"]["0.25m,2deg"] == 1.0
    assert r["points3D"] >= 0.8 * s["points3D"], (r["points3D"], s["points3D"])


def test_stock_triangulation_trap_and_fixes(mini, tmp_path):
    """Stock hloc.triangulation.main triangulates 0 points under pycolmap 4.2 and
    localize_sfm then silently gives every query its first retrieved image's pose; our
    path and hloc's estimate_two_view_geometries=True both triangulate."""
    from hloc import localize_sfm, triangulation

    d, o = mini.dataset, mini.root / "sift"
    ref = d / "3D-models" / "reference"
    pairs, feats, matches = o / "pairs-db-exhaustive.txt", o / "feats-sift.h5", o / "matches-db.h5"
    images = d / "images" / "images_upright"
    stock = triangulation.main(tmp_path / "stock", ref, images, pairs, feats, matches)
    assert stock.num_points3D() == 0, "hloc/pycolmap fixed the UNDEFINED trap: update docs"
    results = tmp_path / "stock.txt"
    localize_sfm.main(
        stock,
        d / "queries" / "*_time_queries_with_intrinsics.txt",
        d / "pairs-query-exhaustive.txt",
        feats,
        o / "matches-loc.h5",
        results,
    )
    fallbacks = A.localize_sfm_fallbacks(results)
    assert len(fallbacks) == NUM_QUERIES  # every query "localized" at a database pose
    errors = A.localization_errors(results, d / "ground_truth.txt")
    assert all(dt > 0.25 for dt, _ in errors.values()), errors
    assert A.recall(errors, failed=fallbacks) == [0.0, 0.0, 0.0]

    est = triangulation.main(
        tmp_path / "estimated",
        ref,
        images,
        pairs,
        feats,
        matches,
        estimate_two_view_geometries=True,
    )
    ours = A.triangulate_with_hloc(ref, tmp_path / "ours", images, pairs, feats, matches)
    assert ours.num_points3D() == mini.sift["points3D"]
    assert est.num_points3D() > 0.5 * ours.num_points3D()


def test_older_hloc_api_generation(mini, tmp_path, monkeypatch):
    """hloc before 2025-09-22 took database paths (same version string): detected by
    signature and driven the same way, same points."""
    import hloc
    from hloc import triangulation as new

    def import_features(image_ids, database_path, features_path):
        with pycolmap.Database.open(database_path) as db:
            new.import_features(image_ids, db, features_path)

    def import_matches(
        image_ids,
        database_path,
        pairs_path,
        matches_path,
        min_match_score=None,
        skip_geometric_verification=False,
    ):
        with pycolmap.Database.open(database_path) as db:
            new.import_matches(
                image_ids,
                db,
                pairs_path,
                matches_path,
                min_match_score,
                skip_geometric_verification,
            )

    def geometric_verification(
        image_ids, reference, database_path, features_path, pairs_path, matches_path, max_error=4.0
    ):
        with pycolmap.Database.open(database_path) as db:
            new.geometric_verification(
                image_ids, reference, db, features_path, pairs_path, matches_path, max_error
            )

    old = SimpleNamespace(
        create_db_from_model=new.create_db_from_model,
        import_features=import_features,
        import_matches=import_matches,
        geometric_verification=geometric_verification,
        run_triangulation=new.run_triangulation,
    )
    assert A.hloc_generation(new) == "db" and A.hloc_generation(old) == "path"
    monkeypatch.setattr(hloc, "triangulation", old)
    monkeypatch.setitem(sys.modules, "hloc.triangulation", old)
    d, o = mini.dataset, mini.root / "sift"
    rec = A.triangulate_with_hloc(
        d / "3D-models" / "reference",
        tmp_path / "old",
        d / "images" / "images_upright",
        o / "pairs-db-exhaustive.txt",
        o / "feats-sift.h5",
        o / "matches-db.h5",
    )
    assert rec.num_points3D() == mini.sift["points3D"]


# -- Sacre Coeur (hloc's demo photos): match_features + reconstruction.main ------------------


@pytest.fixture(scope="module")
def sacre_coeur(tmp_path_factory):
    """Features (rectified, plain) through hloc's exhaustive pairs, match_features and
    reconstruction.main, on 7 photos downscaled to MAX_SIZE."""
    import cv2
    from hloc import match_features, pairs_from_exhaustive, reconstruction

    from rectified_colmap.config import ExtractConf, confs
    from rectified_colmap.extraction import DEFAULT_DEPTH_MODEL, extract

    needs(SACRE_COEUR)
    root = tmp_path_factory.mktemp("sacre_coeur")
    images = root / "images"
    images.mkdir()
    for p in sorted(SACRE_COEUR.glob("*.jpg")):
        if p.name.split("_")[0] in OTHER_CLUSTER:
            continue
        img = cv2.imread(str(p))
        h, w = img.shape[:2]
        s = MAX_SIZE / max(h, w)
        if s < 1:
            img = cv2.resize(img, (round(w * s), round(h * s)), interpolation=cv2.INTER_AREA)
        cv2.imwrite(str(images / p.name), img, [cv2.IMWRITE_JPEG_QUALITY, 95])
    out = {}
    for method in ("rectsift", "sift"):
        feats = root / f"feats-{method}.h5"
        conf = ExtractConf.from_dict(confs[method])
        conf.sift.max_num_features = NUM_FEATURES
        summary = extract(
            images,
            hloc_features=feats,
            conf=conf,
            progress=False,
            depth_model=DEFAULT_DEPTH_MODEL if method == "rectsift" else None,
        )
        assert not summary.failed, summary.failed
        pairs = root / f"pairs-{method}.txt"
        pairs_from_exhaustive.main(pairs, features=feats)
        matches = root / f"matches-{method}.h5"
        match_features.main(
            match_features.confs["NN-ratio"], pairs, features=feats, matches=matches
        )
        rec = reconstruction.main(root / f"sfm-{method}", images, pairs, feats, matches)
        out[method] = SimpleNamespace(
            features=feats,
            pairs=pairs,
            matches=matches,
            rec=rec,
            rec_dir=root / f"sfm-{method}",
            summary=summary,
        )
    return SimpleNamespace(images=images, **out)


def test_match_features_reads_our_file(sacre_coeur):
    from hloc.utils.io import get_keypoints, get_matches
    from hloc.utils.parsers import parse_retrieval

    r = sacre_coeur.rectsift
    pairs = [(a, b) for a, bs in parse_retrieval(r.pairs).items() for b in bs]
    assert len(pairs) == 21
    counts = []
    for a, b in pairs:
        m, scores = get_matches(r.matches, a, b)
        assert m.ndim == 2 and m.shape[1] == 2 and len(scores) == len(m)
        if len(m):
            assert m[:, 0].max() < len(get_keypoints(r.features, a))
            assert m[:, 1].max() < len(get_keypoints(r.features, b))
            assert len(np.unique(m[:, 0])) == len(m)  # mutual nearest neighbours
        counts.append(len(m))
    assert np.median(counts) >= 20


def _verified_inliers(sfm_dir: Path) -> int:
    with pycolmap.Database.open(sfm_dir / "database.db") as db:
        return sum(len(g.inlier_matches) for g in db.read_two_view_geometries()[1])


def test_sacre_coeur_reconstruction_against_plain_sift(sacre_coeur):
    """reconstruction.main runs on our files; the matches it verifies (pycolmap's
    verify_matches, in its database): rectified SIFT keeps at least 85% of plain SIFT's
    inliers (measured 95% here, 101% at the default budget: docs/hloc.md).

    Registered images and 3D points are not compared at this size: with 10 photos and ~1500
    keypoints each, COLMAP's incremental mapper stalls at 2-3 images for seeds and methods
    alike (this tool's plain SIFT included; docs/hloc.md), so the count says more about
    the initial pair than about the features. The mini Aachen tests compare points."""
    r, s = sacre_coeur.rectsift, sacre_coeur.sift
    for x in (r, s):
        assert x.rec is not None and x.rec.num_reg_images() >= 2
    ri, si = _verified_inliers(r.rec_dir), _verified_inliers(s.rec_dir)
    assert si > 800, si
    assert ri >= 0.85 * si, (ri, si)


def test_lightglue_orientation_convention(sacre_coeur):
    """LightGlue's SIFT (pycolmap backend) passes COLMAP's keypoint angle in radians;
    converted oris match it for plain SIFT keypoints at the same place and scale."""
    import cv2
    import h5py

    name = "02928139_3448003521.jpg"
    img = cv2.imread(str(sacre_coeur.images / name), cv2.IMREAD_GRAYSCALE)
    sift = pycolmap.Sift(
        options=pycolmap.FeatureExtractionOptions(
            sift=pycolmap.SiftExtractionOptions(max_num_features=NUM_FEATURES)
        )
    )
    kp, _ = sift.extract(img.astype(np.float32) / 255)
    dst = sacre_coeur.images.parent / "feats-sift-lightglue.h5"
    assert A.convert_oris_for_lightglue(sacre_coeur.sift.features, dst) == 7
    with h5py.File(dst) as f, h5py.File(sacre_coeur.sift.features) as g:
        xy = f[name]["keypoints"][()] + 0.5  # hloc -> COLMAP convention
        ori = f[name]["oris"][()]
        assert f[name]["oris"].attrs["oris_unit"] == "rad"
        np.testing.assert_allclose(ori, np.deg2rad(g[name]["oris"][()]), atol=1e-6)
        np.testing.assert_array_equal(f[name]["descriptors"][()], g[name]["descriptors"][()])
    d = np.linalg.norm(xy[:, None] - kp[None, :, :2], axis=-1)
    i, j = np.nonzero(d < 0.05)
    diff = np.abs(np.angle(np.exp(1j * (ori[i] - kp[j, 3]))))
    # a place with two orientations has two candidates: the nearest angle must agree
    best = {}
    for k, v in zip(i, diff):
        best[k] = min(best.get(k, np.inf), v)
    assert len(best) > 100
    assert np.median(list(best.values())) < 1e-3
    with pytest.raises(ValueError, match="already in radians"):
        A.convert_oris_for_lightglue(dst, dst.with_name("twice.h5"))


# -- scripts/eval_hloc_sfm.py: hloc SfM over mapper seeds ------------------------------------


def test_eval_hloc_sfm_script_over_seeds(sacre_coeur, tmp_path, capsys):
    """The script through the real hloc on the downscaled photos, plain SIFT and a named
    variant over two mapper seeds: one model per method and seed, the JSON and the table
    agree with the models on disk, and a second run reuses the feature and match files."""
    script = load_script("eval_hloc_sfm")
    out = tmp_path / "out"
    argv = ["--images", str(sacre_coeur.images), "--output_dir", str(out), "--methods", "sift"]
    argv += ["--variant", "fast=rectsift-fast", "--max_num_features", str(NUM_FEATURES)]
    assert script.main(argv + ["--seeds", "0", "1"]) == 0
    rows = json.loads((out / "hloc_sfm.json").read_text())
    assert [(r["method"], r["seed"]) for r in rows] == [
        ("sift", 0),
        ("sift", 1),
        ("fast", 0),
        ("fast", 1),
    ]
    for r in rows:
        rec = pycolmap.Reconstruction(str(out / r["method"] / f"sfm-{r['seed']}"))
        assert (r["registered"], r["points"]) == (rec.num_reg_images(), rec.num_points3D())
        assert r["registered"] >= 2  # a model, not a quality bar: on these 7 small photos
        # hloc's mapper varies from run to run (even seeded); one run gave 3 images, 0 points
    assert sum(r["points"] for r in rows) > 0
    table = capsys.readouterr().out
    for m in ("sift", "fast"):
        pts = " ".join(str(r["points"]) for r in rows if r["method"] == m)
        assert f"| {m} | " in table and f" | {pts} | " in table
    stamp = {f: f.stat().st_mtime_ns for f in out.glob("*/*.h5")}
    assert len(stamp) == 4  # features and matches of both methods
    assert script.main(argv + ["--seeds", "2"]) == 0
    assert {f: f.stat().st_mtime_ns for f in out.glob("*/*.h5")} == stamp
