"""scripts/aachen_hloc.py: its checks of the hloc installation, and end to end through the
REAL hloc on a mini Aachen from Strecha fountain-P11 (triangulation + localize_sfm, the
pycolmap 4.2 trap and both hloc API generations).

The end-to-end tests need hloc (docs/hloc.md) and its imports (torch, kornia, scipy,
plotly), and fountain-P11 in the shared data (tests/scripts/user_scripts.py); skipped, with
the reason, without them. Kept small for the suite: images downscaled to 640 px, 1024
features, two held-out queries. Every comparison is against this tool's plain SIFT through
the same hloc calls; the tolerances reflect the measured state (docs/hloc.md), not a goal.
"""

import sys
from types import SimpleNamespace

import numpy as np
import pycolmap
import pytest
from user_scripts import FOUNTAIN, hloc_missing, load_user_script, needs

from rectified_colmap.eval import aachen as A
from rectified_colmap.eval import hloc_compat as H

MAX_SIZE = 640
NUM_FEATURES = 1024
NUM_QUERIES = 2


def test_script_says_how_to_install_hloc(monkeypatch):
    mod = load_user_script("aachen_hloc")
    monkeypatch.setitem(sys.modules, "hloc", None)  # import hloc -> ImportError
    with pytest.raises(SystemExit, match="hloc is not installed.*not on PyPI"):
        mod.require_hloc()


def test_method_conf_and_depth():
    mod = load_user_script("aachen_hloc")
    assert mod.method_conf("sift", None, 1024)["sift"]["max_num_features"] == 1024
    assert mod.method_conf("rectsift", "rectsift-fast", None)["rectify"]["tilt_steps"] == 0
    assert mod.depth_args("sift", "x.onnx", None) == {"model": None, "path": None}
    assert mod.depth_args("rectsift", None, None)["model"] == "rectsift-lite0"


@pytest.fixture(scope="module")
def mini(tmp_path_factory):
    """scripts/aachen_hloc.py as documented, for rectified SIFT and plain SIFT."""
    missing = hloc_missing()
    if missing:
        pytest.skip(missing)
    needs(FOUNTAIN)
    root = tmp_path_factory.mktemp("mini_aachen")
    script = load_user_script("aachen_hloc")
    out = {}
    for method in ("rectsift", "sift"):
        argv = ["--dataset", str(root / "dataset"), "--outputs", str(root / method)]
        argv += ["--method", method, "--max_num_features", str(NUM_FEATURES)]
        argv += ["--num_workers", "1"]
        if method == "rectsift":  # the first run builds the dataset
            argv += ["--make_mini_from", str(FOUNTAIN), "--max_size", str(MAX_SIZE)]
            argv += ["--num_queries", str(NUM_QUERIES)]
        out[method] = script.run(script.parser().parse_args(argv))
    return SimpleNamespace(root=root, dataset=root / "dataset", script=script, **out)


@pytest.mark.slow
def test_mini_aachen_localizes_held_out_queries(mini):
    s = mini.rectsift
    assert s["database_images"] == 7 and s["queries"] == NUM_QUERIES
    assert s["registered_images"] == 7
    assert s["points3D"] > 300
    assert s["missing"] == [] and s["not_localized"] == []
    for name, (dt, dr) in s["errors_m_deg"].items():
        assert dt < 0.25 and dr < 2.0, (name, dt, dr)
    assert s["recall"]["0.25m,2deg"] == 1.0
    lines = mini.script.summary_lines(s)
    assert lines[0] == f"reference model: 7 of 7 database images, {s['points3D']} 3D points"
    assert "(0.25m,2deg) 100%" in lines[2]
    # database images were extracted with the reference model's intrinsics (no guess)
    ref = pycolmap.Reconstruction(str(mini.dataset / "3D-models" / "reference"))
    with pycolmap.Database.open(mini.root / "rectsift" / "cameras-rectsift.db") as db:
        cams = {im.name: db.read_camera(im.camera_id) for im in db.read_all_images()}
    for im in ref.images.values():
        np.testing.assert_allclose(cams[im.name].params, ref.cameras[im.camera_id].params)


@pytest.mark.slow
def test_mini_aachen_against_plain_sift(mini):
    """Same hloc calls, this tool's plain SIFT: both localize every query; rectified SIFT
    keeps at least 80% of plain SIFT's triangulated points (measured: docs/hloc.md)."""
    r, s = mini.rectsift, mini.sift
    assert s["registered_images"] == r["registered_images"] == 7
    assert s["recall"]["0.25m,2deg"] == 1.0
    assert r["points3D"] >= 0.8 * s["points3D"], (r["points3D"], s["points3D"])


@pytest.mark.slow
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
    assert H.two_view_counts(tmp_path / "stock" / "database.db")["undefined_pairs"] > 0
    results = tmp_path / "stock.txt"
    localize_sfm.main(
        stock,
        d / "queries" / "*_time_queries_with_intrinsics.txt",
        d / "pairs-query-exhaustive.txt",
        feats,
        o / "matches-loc.h5",
        results,
    )
    fallbacks = H.localize_sfm_fallbacks(results)
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
    ours = H.triangulate_with_hloc(ref, tmp_path / "ours", images, pairs, feats, matches)
    assert ours.num_points3D() == mini.sift["points3D"]
    assert est.num_points3D() > 0.5 * ours.num_points3D()


def _older_hloc_triangulation():
    """hloc.triangulation as before 2025-09-22: the same functions behind database-path
    signatures."""
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

    return SimpleNamespace(
        create_db_from_model=new.create_db_from_model,
        import_features=import_features,
        import_matches=import_matches,
        geometric_verification=geometric_verification,
        run_triangulation=new.run_triangulation,
    )


@pytest.mark.slow
def test_older_hloc_api_generation(mini, tmp_path, monkeypatch):
    """hloc before 2025-09-22 took database paths (same version string): detected by
    signature and driven the same way, same points."""
    import hloc
    from hloc import triangulation as new

    old = _older_hloc_triangulation()
    assert H.hloc_generation(new) == "db" and H.hloc_generation(old) == "path"
    monkeypatch.setattr(hloc, "triangulation", old)
    monkeypatch.setitem(sys.modules, "hloc.triangulation", old)
    d, o = mini.dataset, mini.root / "sift"
    rec = H.triangulate_with_hloc(
        d / "3D-models" / "reference",
        tmp_path / "old",
        d / "images" / "images_upright",
        o / "pairs-db-exhaustive.txt",
        o / "feats-sift.h5",
        o / "matches-db.h5",
    )
    assert rec.num_points3D() == mini.sift["points3D"]
