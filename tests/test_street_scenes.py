"""Statistical and end-to-end tests on rendered street scenes with exact depth and poses."""

import os
import shutil
import subprocess

import cv2
import numpy as np
import pycolmap
import pytest

from rectified_colmap.cli import main
from rectified_colmap.eval.config import EvalConf
from rectified_colmap.depth import DepthMap
from rectified_colmap.eval.matching import FeatureSource
from rectified_colmap.eval.relpose import evaluate_pair
from rectified_colmap.sift import detect_sift
from rectified_colmap.io.hloc_h5 import rootsift_unit
from rectified_colmap.pipeline import extract_image
from tests.scenes import street_orbit, street_pair, to_pair

W, H = 480, 360


def _as_source(f):
    return {"keypoints": f.keypoints, "descriptors": rootsift_unit(f.descriptors).T}


@pytest.mark.slow
def test_rectified_sift_beats_plain_sift_on_street_pairs_50_to_90_degrees():
    """Ground and facade points seen from directions 50-90 degrees apart. With exact depth,
    rectified SIFT must give clearly more GT-correct matches and more pose successes
    (rotation error < 5 deg) than plain SIFT on the same pairs."""
    records = []
    for target, seeds in (("ground", range(6)), ("facade", range(4))):
        for seed in seeds:
            views = street_pair(seed, 50, 90, W, H, target)
            assert views is not None
            feats = {"plain": {}, "rect": {}}
            for name, v in zip("01", views):
                gray = cv2.cvtColor(v["image"], cv2.COLOR_RGB2GRAY)
                feats["plain"][name] = _as_source(detect_sift(gray))
                res = extract_image(v["image"], v["camera"], DepthMap(v["depth"], "metric"))
                feats["rect"][name] = _as_source(res.features)
            records += evaluate_pair(
                to_pair(*views), {k: FeatureSource(s) for k, s in feats.items()}, EvalConf()
            )
    by = {m: [r for r in records if r["method"] == m] for m in ("plain", "rect")}
    succ = {m: sum(r["success"] for r in rs) for m, rs in by.items()}
    correct = {m: sum(r["num_correct"] for r in rs) for m, rs in by.items()}
    wins = sum(r["num_correct"] > p["num_correct"] for r, p in zip(by["rect"], by["plain"]))
    # Sign test: P(>= 8 of 10 wins | no difference) = 0.055; with the totals below it is
    # far beyond chance.
    assert wins >= 8, (wins, records)
    assert correct["rect"] > 2 * correct["plain"], correct
    assert succ["rect"] >= succ["plain"] + 4, succ


def _extract_orbit(tmp_path, num=6):
    """`rectified-colmap extract` on a rendered street sequence with depth files."""
    views = street_orbit(3, num=num, width=W, height=H)
    images, depths = tmp_path / "images", tmp_path / "depths"
    images.mkdir()
    depths.mkdir()
    for i, v in enumerate(views):
        cv2.imwrite(str(images / f"{i:03d}.png"), v["image"][..., ::-1])
        np.save(depths / f"{i:03d}.npy", v["depth"])
    K = views[0]["camera"].calibration_matrix()
    db = tmp_path / "database.db"
    assert (
        main(
            [
                "extract",
                "--database_path",
                str(db),
                "--image_path",
                str(images),
                "--depth_path",
                str(depths),
                "--depth_model",
                "none",
                "--camera_model",
                "PINHOLE",
                "--single_camera",
                "--camera_params",
                f"{K[0, 0]},{K[1, 1]},{K[0, 2]},{K[1, 2]}",
                "--no_progress",
            ]
        )
        == 0
    )
    return views, images, db


@pytest.mark.slow
@pytest.mark.skipif(shutil.which("colmap") is None, reason="colmap command line not installed")
def test_cli_database_is_mapped_by_colmap_command_line(tmp_path):
    """The COLMAP command line (Debian's 3.8) matches and maps a database written by the CLI."""
    views, images, db = _extract_orbit(tmp_path)
    env = dict(os.environ, QT_QPA_PLATFORM="offscreen")
    (tmp_path / "sparse").mkdir()
    run = [
        [
            "exhaustive_matcher",
            "--database_path",
            str(db),
            "--SiftMatching.use_gpu",
            "0",
            "--SiftMatching.num_threads",
            "1",
        ],
        [
            "mapper",
            "--database_path",
            str(db),
            "--image_path",
            str(images),
            "--output_path",
            str(tmp_path / "sparse"),
            "--Mapper.num_threads",
            "1",
            "--Mapper.ba_refine_focal_length",
            "0",
        ],
        [
            "model_converter",
            "--input_path",
            str(tmp_path / "sparse" / "0"),
            "--output_path",
            str(tmp_path),
            "--output_type",
            "TXT",
        ],
    ]
    for args in run:
        out = subprocess.run(
            ["colmap", *args], env=env, capture_output=True, text=True, timeout=300
        )
        assert out.returncode == 0, out.stderr[-2000:]
    lines = [
        ln
        for ln in (tmp_path / "images.txt").read_text().splitlines()
        if ln and not ln.startswith("#")
    ]
    assert len(lines) // 2 == len(views)  # two lines per registered image


@pytest.mark.slow
def test_cli_database_is_mapped_by_pycolmap(tmp_path):
    """pycolmap's exhaustive matching and incremental mapping register every image of a
    database written by `rectified-colmap extract`."""
    views, images, db = _extract_orbit(tmp_path)
    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = 1  # deterministic
    pycolmap.match_exhaustive(db, matching_options=matching)
    opts = pycolmap.IncrementalPipelineOptions()
    opts.num_threads = 1
    opts.random_seed = 0
    opts.ba_refine_focal_length = False  # exact intrinsics
    recs = pycolmap.incremental_mapping(db, images, tmp_path / "sparse", opts)
    best = max(recs.values(), key=lambda r: r.num_reg_images())
    assert best.num_reg_images() == len(views)
    assert best.num_points3D() > 100
    # the recovered relative poses agree with the ground truth
    ims = {im.name: im for im in best.images.values()}
    gt = to_pair(views[0], views[-1])
    T0, T1 = ims["000.png"].cam_from_world(), ims[f"{len(views) - 1:03d}.png"].cam_from_world()
    R_est = (T1 * T0.inverse()).rotation.matrix()
    err = np.degrees(np.arccos(np.clip((np.trace(R_est.T @ gt.R) - 1) / 2, -1, 1)))
    assert err < 2.0


def test_scene_without_dominant_planes_matches_like_plain_sift():
    """Rubble (hundreds of small, randomly oriented quads): no dominant planes, so rectified
    SIFT must match as plain SIFT does (same successes, correct matches within 15%)."""
    import pycolmap

    from rectified_colmap_research import synth
    from tests.scenes import _view

    totals = {"plain": 0, "rect": 0}
    for seed in range(3):
        rng = np.random.default_rng(seed)
        scene = synth.rubble(rng)
        camera = synth.pinhole_camera(W, H, 0.9 * W)
        p0 = synth.random_view(scene, rng, camera)
        p1 = (
            pycolmap.Rigid3d(
                pycolmap.Rotation3d(np.array([0.0, 0.15, 0.0])), np.array([-0.3, 0.0, 0.0])
            )
            * p0
        )
        views = [_view(scene, camera, p) for p in (p0, p1)]
        feats = {"plain": {}, "rect": {}}
        for name, v in zip("01", views):
            gray = cv2.cvtColor(v["image"], cv2.COLOR_RGB2GRAY)
            feats["plain"][name] = _as_source(detect_sift(gray))
            res = extract_image(v["image"], camera, DepthMap(v["depth"], "metric"))
            feats["rect"][name] = _as_source(res.features)
        recs = evaluate_pair(
            to_pair(*views), {k: FeatureSource(s) for k, s in feats.items()}, EvalConf()
        )
        assert [r["success"] for r in recs] == [True, True]
        for r in recs:
            totals[r["method"]] += r["num_correct"]
    assert abs(totals["rect"] - totals["plain"]) <= 0.15 * totals["plain"], totals
