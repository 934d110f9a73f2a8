"""research/scripts/build_extreme_pairs.py and its evaluation by eval_homography.py, end to
end on synthetic textures (no shared data needed)."""

import csv
import json

import cv2
import numpy as np
import pytest
from scripts_util import load_script

from rectified_colmap.conventions import from_opencv_points
from rectified_colmap.eval.homography import (
    apply_homography,
    points_in_region,
    read_homography_pairs,
)
from rectified_colmap_research.synth.planar import textured_image


@pytest.fixture(scope="module")
def sources(tmp_path_factory):
    """Two synthetic 'photos' (blob texture plus dark window frames) in two groups."""
    root = tmp_path_factory.mktemp("data")
    (root / "tex").mkdir()
    for k in range(2):
        g = textured_image(500, 760, seed=k)
        img = cv2.merge([g, np.roll(g, 7, 1), 255 - g])
        for x in range(40, 740, 120):
            for y in range(40, 480, 150):
                cv2.rectangle(img, (x, y), (x + 70, y + 100), (20, 30, 40), 4)
        cv2.imwrite(str(root / "tex" / f"photo{k}.png"), img)
    lines = [
        "# a test list",
        "tex/photo0.png test/a no",  # split: check
        "tex/photo1.png test/b texture 0,0,700,480",  # split: choose
    ]
    (root / "sources.txt").write_text("\n".join(lines) + "\n")
    return root


def build(root, out, n, seed=5):
    mod = load_script("build_extreme_pairs")
    argv = ["--output", str(out), "--num_pairs", str(n), "--seed", str(seed)]
    assert mod.main(argv + ["--data_root", str(root), "--sources", str(root / "sources.txt")]) == 0
    return json.loads((out / "pairs.json").read_text())


def test_build_is_deterministic_and_its_files_are_exact(sources, tmp_path):
    a = build(sources, tmp_path / "a", 3)
    b = build(sources, tmp_path / "b", 3)
    c = build(sources, tmp_path / "c", 2)
    assert a == b and a[:2] == c  # pair i depends on the seed and i only
    for r in a:
        for key in ("im0", "im1"):
            assert (tmp_path / "a" / r[key]).read_bytes() == (tmp_path / "b" / r[key]).read_bytes()
    assert build(sources, tmp_path / "d", 2, seed=6) != c
    assert "| split |" in (tmp_path / "a" / "README.md").read_text()

    pairs = read_homography_pairs(tmp_path / "a" / "pairs.json", tmp_path / "a")
    for r, p in zip(a, pairs):
        assert {r["source"], r["group"]} in (
            {"tex/photo0.png", "test/a"},
            {"tex/photo1.png", "test/b"},
        )
        assert r["split"] in ("choose", "check") and r["texture_size"][0] in (760, 700)
        for k, im in enumerate((p.im0, p.im1)):
            img = cv2.imread(str(tmp_path / "a" / im))
            assert (img.shape[1], img.shape[0]) == tuple(r[f"size{k}"])
        # the file's conventions: the anchor's two images, and H between them
        a0, a1 = (from_opencv_points(np.array(r[f"anchor{k}"])) for k in (0, 1))
        np.testing.assert_allclose(apply_homography(p.H, a0[None])[0], a1, atol=0.02)
        # ... with its sign: the anchor, seen by both cameras, maps to w > 0, as read
        raw = np.array(r["H"]) @ np.r_[r["anchor0"], 1.0]
        assert raw[2] > 0 and np.sign(abs(r["H"][2][2]) * p.H[2, 2]) == np.sign(r["H"][2][2])
        K0, K1 = (np.array(r[f"K{k}"]) for k in (0, 1))
        for K, size in ((K0, p.size0), (K1, p.size1)):
            np.testing.assert_allclose(from_opencv_points(K[:2, 2]), np.array(size) / 2)
        K0[:2, 2], K1[:2, 2] = np.array(p.size0) / 2, np.array(p.size1) / 2
        # the true normals are a solution of the decomposition of H with the true K (not
        # always the one plane_normals_from_homography picks: two solutions can put every
        # point in front of both cameras)
        Hn = np.linalg.inv(K1) @ p.H @ K0
        _, Rs, _, ns = cv2.decomposeHomographyMat(Hn / np.cbrt(np.linalg.det(Hn)), np.eye(3))
        n0s = [-n.ravel() / np.linalg.norm(n) for n in ns]
        k = int(np.argmin([np.linalg.norm(n - r["normal0"]) for n in n0s]))
        np.testing.assert_allclose(n0s[k], r["normal0"], atol=1e-4)
        np.testing.assert_allclose(Rs[k] @ n0s[k], r["normal1"], atol=1e-4)
        # the regions are the texture: grey fill outside, texture inside
        for region, im in ((p.region0, p.im0), (p.region1, p.im1)):
            img = cv2.imread(str(tmp_path / "a" / im), cv2.IMREAD_GRAYSCALE).astype(float)
            xy = np.stack(np.meshgrid(np.arange(img.shape[1]), np.arange(img.shape[0])), -1)
            inside = points_in_region(from_opencv_points(xy.reshape(-1, 2)), region)
            inside = inside.reshape(img.shape)
            far = cv2.erode((~inside).astype(np.uint8), np.ones((7, 7))).astype(bool)
            if far.any():
                assert abs(np.median(img[far]) - 128) <= 3 and img[far].std() < 6
            assert img[inside].std() > 15
        for key in ("tilt_bin", "scale_bin", "rotation", "both_oblique", "portrait"):
            assert isinstance(r[key], str)
        assert max(r["overlap01"], r["overlap10"]) >= 0.3


def test_evaluation_reports_both_halves_classes_and_cost(sources, tmp_path):
    data = tmp_path / "set"
    recs = build(sources, data, 2, seed=1)
    ev = load_script("eval_homography")
    out = tmp_path / "eval"
    argv = ["--data", str(data), "--output_dir", str(out), "--methods", "sift", "asift"]
    argv += ["oracle_true", "--cameras", "true", "--group_by", "tilt_bin", "both_oblique"]
    argv += ["tilt_bin+both_oblique"]
    assert ev.main(argv) == 0
    text = (out / "summary.md").read_text()
    halves = sorted({r["split"] for r in recs})
    for h in halves + ["all"]:
        assert f"pairs solved: {h}" in text
    assert "| tilt_bin | method |" in text and "| both_oblique | method |" in text
    assert "extract CPU s / image" in text
    rows = list(csv.DictReader(open(out / "records.csv")))
    assert len(rows) == 2 * 2 * 3
    assert {r["split"] for r in rows} == set(halves)
    for r in rows:  # the joint class joins its parts' values
        assert r["tilt_bin+both_oblique"] == f"{r['tilt_bin']} & {r['both_oblique']}"
    assert "| tilt_bin+both_oblique | method |" in text
    for m in ("sift", "asift", "oracle_true"):
        cpu = json.loads((out / "features" / f"{m}.cpu.json").read_text())
        assert len(cpu) == 4 and all(v > 0 for v in cpu.values())
        line = next(x for x in text.splitlines() if x.startswith(f"| {m} |"))
        assert line.split("|")[-3].strip() != "-"  # extraction CPU given
    # the true cameras and normals are required for them
    bad = json.loads((data / "pairs.json").read_text())
    for r in bad:
        del r["normal1"]
    (data / "pairs.json").write_text(json.dumps(bad))
    with pytest.raises(ValueError, match="normal1"):
        ev.main(
            ["--data", str(data), "--output_dir", str(tmp_path / "e2"), "--methods", "oracle_true"]
        )
