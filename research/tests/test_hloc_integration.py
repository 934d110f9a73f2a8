"""Research code through the REAL hloc (docs/hloc.md) on hloc's Sacre Coeur photos:
LightGlue orientations against pycolmap's SIFT angles, and scripts/eval_hloc_sfm.py over
mapper seeds. The user scripts (scripts/aachen_hloc.py, scripts/hloc_sfm.py) are tested end
to end in tests/scripts/.

Needs hloc (``pip install --no-deps`` a copy of ../shared/vendor/hloc) and its imports
(torch, kornia, scipy, plotly), and the shared data beside the checkout (``../shared``, or
the folder in ``RECTIFIED_COLMAP_SHARED``). Skipped, with the reason, without them. Kept
small for the suite: the 7 photos of the main facade cluster at 640 px, 1024 features.
"""

import json
import os
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pycolmap
import pytest
from scripts_util import load_script

from rectified_colmap.eval.hloc_compat import HlocError, import_hloc
from rectified_colmap_research.evaluation.lightglue import convert_oris_for_lightglue

ROOT = Path(__file__).resolve().parents[2]
SHARED = Path(os.environ.get("RECTIFIED_COLMAP_SHARED", ROOT.parent / "shared"))
SACRE_COEUR = SHARED / "vendor" / "hloc" / "datasets" / "sacre_coeur" / "mapping"
MAX_SIZE = 640
NUM_FEATURES = 1024
# Sacre Coeur: 3 of the 10 photos see another part of the church (few matches to the rest);
# the tests use the 7 of the main cluster (21 pairs).
OTHER_CLUSTER = ("10265353", "32809961", "60584745")

try:
    import_hloc()
    HLOC_MISSING = None
except HlocError as e:
    HLOC_MISSING = str(e)

pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(HLOC_MISSING is not None, reason=f"{HLOC_MISSING}"),
]


@pytest.fixture(scope="module")
def sacre_coeur(tmp_path_factory):
    """The 7 photos downscaled to MAX_SIZE, and this tool's plain SIFT of them in an hloc
    feature file."""
    import cv2

    from rectified_colmap import ExtractConf, confs, extract

    if not SACRE_COEUR.is_dir():
        pytest.skip(
            f"{SACRE_COEUR} not found (shared data beside the checkout, or set "
            "RECTIFIED_COLMAP_SHARED)"
        )
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
    feats = root / "feats-sift.h5"
    conf = ExtractConf.from_dict(confs["sift"])
    conf.sift.max_num_features = NUM_FEATURES
    summary = extract(
        images, hloc_features=feats, conf=conf, depth={"model": None}, run={"progress": False}
    )
    assert not summary.failed, summary.failed
    return SimpleNamespace(images=images, sift=SimpleNamespace(features=feats))


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
    assert convert_oris_for_lightglue(sacre_coeur.sift.features, dst) == 7
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
        convert_oris_for_lightglue(dst, dst.with_name("twice.h5"))


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
