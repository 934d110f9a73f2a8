"""scripts/hloc_sfm.py end to end through the REAL hloc on hloc's Sacre Coeur photos:
rectified and plain SIFT through the same calls (pairs_from_exhaustive, match_features,
reconstruction.main).

Needs hloc (docs/hloc.md) and its imports, and the vendored hloc's photos in the shared data
(tests/scripts/user_scripts.py); skipped, with the reason, without them. Kept small for the
suite: the 7 photos of the main facade cluster (the 3 others see another part of the church,
with few matches to the rest), downscaled to 640 px, 1024 features.
"""

import json
from types import SimpleNamespace

import numpy as np
import pycolmap
import pytest
from user_scripts import SACRE_COEUR, hloc_missing, load_user_script, needs

MAX_SIZE = 640
NUM_FEATURES = 1024
OTHER_CLUSTER = ("10265353", "32809961", "60584745")

pytestmark = pytest.mark.slow


def test_script_says_how_to_install_hloc(monkeypatch):
    import sys

    mod = load_user_script("hloc_sfm")
    monkeypatch.setitem(sys.modules, "hloc", None)
    with pytest.raises(SystemExit, match="hloc_sfm: hloc is not installed.*not on PyPI"):
        mod.require_hloc()


def _downscaled_copy(src, dst, max_size: int, skip: tuple[str, ...]) -> None:
    import cv2

    dst.mkdir(parents=True)
    for p in sorted(src.glob("*.jpg")):
        if p.name.split("_")[0] in skip:
            continue
        img = cv2.imread(str(p))
        h, w = img.shape[:2]
        s = max_size / max(h, w)
        if s < 1:
            img = cv2.resize(img, (round(w * s), round(h * s)), interpolation=cv2.INTER_AREA)
        cv2.imwrite(str(dst / p.name), img, [cv2.IMWRITE_JPEG_QUALITY, 95])


@pytest.fixture(scope="module")
def sacre_coeur(tmp_path_factory):
    """The script as documented, for rectified SIFT and plain SIFT, into one folder."""
    missing = hloc_missing()
    if missing:
        pytest.skip(missing)
    needs(SACRE_COEUR)
    root = tmp_path_factory.mktemp("sacre_coeur")
    _downscaled_copy(SACRE_COEUR, root / "images", MAX_SIZE, OTHER_CLUSTER)
    script = load_user_script("hloc_sfm")
    out = {}
    for method in ("rectsift", "sift"):
        argv = ["--images", str(root / "images"), "--outputs", str(root / method)]
        argv += ["--method", method, "--max_num_features", str(NUM_FEATURES), "--seed", "0"]
        out[method] = script.run(script.parser().parse_args(argv))
    return SimpleNamespace(root=root, images=root / "images", script=script, **out)


def _database_inliers(sfm_dir) -> int:
    with pycolmap.Database.open(sfm_dir / "database.db") as db:
        return sum(len(g.inlier_matches) for g in db.read_two_view_geometries()[1])


def test_summary_is_the_model_on_disk(sacre_coeur):
    for method in ("rectsift", "sift"):
        s = sacre_coeur.__dict__[method]
        out = sacre_coeur.root / method
        assert json.loads((out / "summary.json").read_text()) == s
        assert s["method"] == method and s["images"] == 7
        assert s["model"] == str(out / f"sfm-{method}")
        rec = pycolmap.Reconstruction(s["model"])
        assert (s["registered_images"], s["points3D"]) == (rec.num_reg_images(), rec.num_points3D())
        # a model, not a quality bar: at this size COLMAP's incremental mapper stalls at 2-3
        # images for seeds and methods alike (docs/hloc.md); inliers are compared below
        assert s["registered_images"] >= 2
        assert s["undefined_pairs"] == 0  # reconstruction.main verifies with a configuration
        assert 0 < s["verified_inliers"] <= _database_inliers(out / f"sfm-{method}")


def test_match_features_reads_our_file(sacre_coeur):
    from hloc.utils.io import get_keypoints, get_matches
    from hloc.utils.parsers import parse_retrieval

    out = sacre_coeur.root / "rectsift"
    feats, matches = out / "feats-rectsift.h5", out / "matches-rectsift.h5"
    pairs = [(a, b) for a, bs in parse_retrieval(out / "pairs.txt").items() for b in bs]
    assert len(pairs) == 21
    counts = []
    for a, b in pairs:
        m, scores = get_matches(matches, a, b)
        assert m.ndim == 2 and m.shape[1] == 2 and len(scores) == len(m)
        if len(m):
            assert m[:, 0].max() < len(get_keypoints(feats, a))
            assert m[:, 1].max() < len(get_keypoints(feats, b))
            assert len(np.unique(m[:, 0])) == len(m)  # mutual nearest neighbours
        counts.append(len(m))
    assert np.median(counts) >= 20


def test_rectified_keeps_plain_sifts_verified_inliers(sacre_coeur):
    """reconstruction.main's verified matches (pycolmap's verify_matches): rectified SIFT
    keeps at least 85% of plain SIFT's inliers (measured 95% here, 101% at the default
    budget: docs/hloc.md). Registered images and 3D points are not compared at this size
    (the mapper stall above says more about the initial pair than about the features)."""
    r, s = sacre_coeur.rectsift, sacre_coeur.sift
    assert s["verified_inliers"] > 800, s
    assert r["verified_inliers"] >= 0.85 * s["verified_inliers"], (r, s)


def test_second_run_reuses_features_and_matches(sacre_coeur, capsys):
    """main() as a user runs it again: the feature and match files stay as they are, a new
    model and the summary printed."""
    out = sacre_coeur.root / "sift"
    stamp = {f: f.stat().st_mtime_ns for f in out.glob("*.h5")}
    assert len(stamp) == 2
    argv = ["--images", str(sacre_coeur.images), "--outputs", str(out), "--method", "sift"]
    argv += ["--max_num_features", str(NUM_FEATURES), "--seed", "0"]
    assert sacre_coeur.script.main(argv) == 0
    assert {f: f.stat().st_mtime_ns for f in out.glob("*.h5")} == stamp
    s = json.loads((out / "summary.json").read_text())
    printed = capsys.readouterr().out
    assert f"{s['registered_images']} of 7 images registered, {s['points3D']} 3D points" in printed
    assert (
        f"{s['verified_pairs']} verified pairs, {s['verified_inliers']} inlier matches" in printed
    )
