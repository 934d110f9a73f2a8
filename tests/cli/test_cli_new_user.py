"""What a new user meets first (issue 30): COLMAP habits, mistakes and what the CLI says.

Each test runs the real CLI (``rectified_colmap.cli.main``) on small rendered plane views
without depth (plain SIFT: fast), and checks the exit code, the message and that nothing was
written where the run stopped on a bad argument.
"""

import argparse
import os
import re
import shutil
import sqlite3
import subprocess
import sys
from pathlib import Path

import cv2
import h5py
import numpy as np
import pycolmap
import pytest

from rectified_colmap.cli import main, normalize_bool_flags
from rectified_colmap.config import ExtractConf, SiftConf
from rectified_colmap.extraction import extract
from rectified_colmap.sift import detect_sift
from tests.conftest import look_at, plane_view, textured_image

K = np.array([[400.0, 0, 200], [0, 400, 150], [0, 0, 1]])
ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def images(tmp_path_factory):
    """Three 400x300 PNG views (no EXIF: COLMAP guesses f = 1.2 x 400) in two folders."""
    root = tmp_path_factory.mktemp("images")
    (root / "a").mkdir()
    (root / "b").mkdir()
    tex = textured_image(600, 600, 3)
    for i, (eye, folder) in enumerate(
        [([2.5, -4.0, 2.0], "a"), ([-2.0, -4.0, 1.5], "a"), ([0.5, -3.5, 3.5], "b")]
    ):
        R, t = look_at(eye, [0, 0, 0])
        img, _ = plane_view(tex, 0.01, K, R, t, (400, 300))
        cv2.imwrite(str(root / folder / f"{i}.png"), img)
    return root


def _cameras(db: Path) -> dict[str, tuple[int, np.ndarray]]:
    """image name -> (camera id, params) of a database."""
    with pycolmap.Database.open(str(db)) as d:
        cams = {c.camera_id: c for c in d.read_all_cameras()}
        return {
            im.name: (im.camera_id, np.asarray(cams[im.camera_id].params))
            for im in d.read_all_images()
        }


def _extract(images, db, *extra):
    return main(
        ["extract", "--database_path", str(db), "--image_path", str(images)]
        + ["--depth_model", "none", "--no_progress", *extra]
    )


@pytest.mark.parametrize(
    "model, expect",
    [
        ("PINHOLE", [480, 480, 200, 150]),
        ("SIMPLE_PINHOLE", [480, 200, 150]),
        ("OPENCV", [480, 480, 200, 150, 0, 0, 0, 0]),
    ],
)
def test_camera_model_without_params_gets_colmaps_initial_params(images, tmp_path, model, expect):
    """--camera_model alone (COLMAP's --ImageReader.camera_model habit): the guessed focal
    length (1.2 x the larger side), the image centre and the model's defaults, as
    `colmap feature_extractor` makes them (it crashed every image with IndexError)."""
    db = tmp_path / "db.db"
    assert _extract(images, db, "--ImageReader.camera_model", model) == 0
    cams = _cameras(db)
    assert sorted(cams) == ["a/0.png", "a/1.png", "b/2.png"]
    for _, params in cams.values():
        np.testing.assert_allclose(params, expect)
    with pycolmap.Database.open(str(db)) as d:
        assert {c.model.name for c in d.read_all_cameras()} == {model}


def test_colmap_sift_and_image_reader_options(images, tmp_path, caplog):
    """COLMAP's SiftExtraction / ImageReader spellings are taken: mapped (max_num_features,
    num_threads -> workers, focal factor, one camera per folder) or said not to apply."""
    db = tmp_path / "db.db"
    caplog.set_level("INFO")
    rc = _extract(
        images,
        db,
        "--SiftExtraction.use_gpu",
        "0",
        "--SiftExtraction.num_threads",
        "2",
        "--SiftExtraction.max_num_features",
        "300",
        "--SiftExtraction.peak_threshold",
        "0.01",
        "--ImageReader.single_camera_per_folder",
        "1",
        "--ImageReader.default_focal_length_factor",
        "2.0",
    )
    assert rc == 0
    assert "--SiftExtraction.use_gpu 0: not applied" in caplog.text
    cams = _cameras(db)
    assert cams["a/0.png"][0] == cams["a/1.png"][0] != cams["b/2.png"][0]  # per folder
    np.testing.assert_allclose(cams["b/2.png"][1][0], 800.0)  # 2.0 x 400
    # the SIFT options reached COLMAP's SIFT: exactly plain SIFT with them
    sift = SiftConf(max_num_features=300, peak_threshold=0.01)
    with sqlite3.connect(db) as con:
        rows = dict(
            con.execute(
                "SELECT i.name, k.rows FROM keypoints k JOIN images i USING (image_id)"
            ).fetchall()
        )
    for name, n in rows.items():
        gray = cv2.imread(str(images / name), cv2.IMREAD_GRAYSCALE)
        assert n == len(detect_sift(gray, sift, 300)) < len(detect_sift(gray, SiftConf(), 300))


def test_empty_or_wrong_image_folder_is_an_error_and_writes_nothing(tmp_path, caplog):
    empty = tmp_path / "empty"
    (empty / "sub").mkdir(parents=True)
    (empty / "notes.txt").write_text("no image here")
    db = tmp_path / "db.db"
    assert _extract(empty, db) == 2
    assert "no images found" in caplog.text and str(empty) in caplog.text
    assert not db.exists()
    assert _extract(tmp_path / "missing", db) == 2
    assert not db.exists()


def test_usage_errors_exit_2_in_one_line_with_the_subcommand_and_a_suggestion(
    images, tmp_path, capsys
):
    # no output given: exit 2 and the subcommand's name (was exit 1, unprefixed)
    assert main(["extract", "--image_path", str(images)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("rectified-colmap extract: error: give --database")
    assert len(err.strip().splitlines()) == 1
    # a misspelled flag: the subcommand's message with the closest option, one line
    assert main(["extract", "--image_path", str(images), "--max_features", "10"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("rectified-colmap extract: error: unrecognized arguments")
    assert "did you mean --max_num_features?" in err and len(err.splitlines()) == 1
    assert not (tmp_path / "db.db").exists()
    # a bad --conf: exit 2 before anything is written
    db = tmp_path / "c.db"
    assert _extract(images, db, "--conf", "nonexistent-conf") == 2
    assert "--conf 'nonexistent-conf'" in capsys.readouterr().err and not db.exists()


def test_log_level_after_the_subcommand_and_help_texts(images, tmp_path, capsys, caplog):
    db = tmp_path / "db.db"
    assert _extract(images, db, "--log_level", "WARNING") == 0
    help_text = subprocess.run(
        [sys.executable, "-m", "rectified_colmap.cli", "extract", "--help"],
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    for flag in ("--log_level", "--no_progress", "--SiftExtraction.use_gpu"):
        i = help_text.index(flag)
        assert len(help_text[i : i + 200].split()) > 3, f"{flag} has no help"


@pytest.mark.parametrize(
    "argv, expect",
    [
        (
            ["merge", "--single_camera", "a.db", "b.db"],
            ["merge", "--single_camera=1", "a.db", "b.db"],
        ),
        (["extract", "--single_camera", "0", "x"], ["extract", "--single_camera=0", "x"]),
        (["--ImageReader.single_camera", "1"], ["--ImageReader.single_camera=1"]),
        (["--single_camera"], ["--single_camera=1"]),
    ],
)
def test_optional_flag_values_never_swallow_a_path(argv, expect):
    assert normalize_bool_flags(argv) == expect


def test_merge_single_camera_before_the_inputs(images, tmp_path):
    """`merge --single_camera a.db b.db` (argparse took a.db as the flag's value)."""
    names = ["a/0.png", "a/1.png", "b/2.png"]
    for i, name in enumerate(names):
        lst = tmp_path / f"l{i}.txt"
        lst.write_text(name + "\n")
        args = ["--image_list_path", str(lst), "--single_camera", "--camera_model", "PINHOLE"]
        assert _extract(images, tmp_path / f"s{i}.db", *args) == 0
    merged = tmp_path / "merged.db"
    rc = main(
        ["merge", "--single_camera", *[str(tmp_path / f"s{i}.db") for i in range(3)]]
        + ["--database_path", str(merged)]
    )
    assert rc == 0
    assert len({cam for cam, _ in _cameras(merged).values()}) == 1


def test_summary_of_a_run_that_only_copied_or_skipped(images, tmp_path, caplog):
    """After copying features between outputs, the summary says nothing was extracted
    (it said `keypoints: 0 (0 per image)`, `0.00 images/s`)."""
    db, h5 = tmp_path / "db.db", tmp_path / "f.h5"
    assert _extract(images, db) == 0
    caplog.clear()
    caplog.set_level("INFO")
    assert _extract(images, db, "--hloc_features", str(h5)) == 0
    text = caplog.text
    assert "3 copied between outputs" in text and "nothing extracted in this run" in text
    assert "images/s" not in text and "0 per image" not in text


def test_demo_result_keys_are_explained():
    from rectified_colmap.demo import RESULT_KEYS

    assert "max_rotation_error_deg" in RESULT_KEYS and "reused_images" in RESULT_KEYS
    source = (ROOT / "rectified_colmap" / "demo" / "__init__.py").read_text()
    for key in RESULT_KEYS:  # every key of the result is explained, and only those
        assert f'"{key}"' in source.split("RESULT_KEYS")[0]


def test_mask_path_drops_keypoints_where_the_mask_is_black(images, tmp_path, caplog):
    """COLMAP's --ImageReader.mask_path: masks/<name>.png, no features where black; an
    image without a mask file is not masked; a mask of the wrong size fails its image."""
    masks = tmp_path / "masks"
    (masks / "a").mkdir(parents=True)
    m = np.full((300, 400), 255, np.uint8)
    m[:, :200] = 0  # the left half is masked
    cv2.imwrite(str(masks / "a" / "0.png.png"), m)
    cv2.imwrite(str(masks / "a" / "1.png.png"), m[:100])  # wrong size
    h5_masked, h5_plain = tmp_path / "m.h5", tmp_path / "p.h5"
    args = ["--ImageReader.mask_path", str(masks), "--hloc_features"]
    assert _extract(images, tmp_path / "m.db", *args, str(h5_masked)) == 1
    assert _extract(images, tmp_path / "p.db", "--hloc_features", str(h5_plain)) == 0
    from rectified_colmap.io import hloc_h5

    assert hloc_h5.list_names(h5_masked) == ["a/0.png", "b/2.png"]  # a/1.png failed
    assert "a/1.png: mask" in caplog.text and "400x100 but the image is 400x300" in caplog.text
    masked, plain = hloc_h5.read(h5_masked, "a/0.png"), hloc_h5.read(h5_plain, "a/0.png")
    keep = np.floor(plain["keypoints"][:, 0]) >= 200  # read() gives COLMAP pixels
    np.testing.assert_array_equal(masked["keypoints"], plain["keypoints"][keep])
    assert 0 < keep.sum() < len(keep)
    np.testing.assert_array_equal(
        hloc_h5.read(h5_masked, "b/2.png")["keypoints"],
        hloc_h5.read(h5_plain, "b/2.png")["keypoints"],
    )


def test_retired_conf_names_warn_and_run_the_default(caplog):
    """--conf rectsift-wide / rectsift-plus (earlier confs for extreme viewpoints): a WARNING
    that says why, then exactly the default configuration."""
    from rectified_colmap.cli.extract import _load_conf
    from rectified_colmap.config import RETIRED_CONFS, ExtractConf

    for name in ("rectsift-wide", "rectsift-plus"):
        assert name in RETIRED_CONFS
        caplog.clear()
        with caplog.at_level("WARNING"):
            conf = _load_conf(name, None)
        assert conf == ExtractConf()
        assert any(f"--conf {name} is retired" in r.getMessage() for r in caplog.records)


def test_images_without_features_fail_by_name_and_are_retried(images, tmp_path, caplog):
    """An image that yields no features (1x1, blank) is a named failure (exit 1), not
    recorded as done: nothing written for it, and the next run tries it again (it was
    written with 0 keypoints and skipped as "already had features" from then on)."""
    root = tmp_path / "images"
    shutil.copytree(images / "a", root)
    cv2.imwrite(str(root / "dot.png"), np.full((1, 1), 128, np.uint8))
    cv2.imwrite(str(root / "blank.png"), np.full((300, 400), 128, np.uint8))
    db, h5 = tmp_path / "db.db", tmp_path / "f.h5"
    for _ in range(2):  # the second run retries the two, and skips the others
        caplog.clear()
        assert _extract(root, db, "--hloc_features", str(h5)) == 1
        text = caplog.text
        assert "FAILED dot.png: no features: the image is 1x1" in text
        assert "FAILED blank.png: no features: SIFT found none" in text
        assert sorted(_cameras(db)) == ["0.png", "1.png"]
        with h5py.File(h5, "r") as f:
            assert sorted(f) == ["0.png", "1.png"]
    assert "2 skipped" in text and "2 failed" in text


def test_zero_feature_budget_is_an_argument_error(images, tmp_path, capsys):
    db = tmp_path / "db.db"
    for flag in ("--max_num_features", "--SiftExtraction.max_num_features"):
        assert _extract(images, db, flag, "0") == 2
        err = capsys.readouterr().err
        assert "must be at least 1, got 0" in err and err.count("\n") == 1
    assert not db.exists()
    with pytest.raises(ValueError, match="sift.max_num_features must be at least 1"):
        ExtractConf.from_dict({"sift": {"max_num_features": 0}})
    conf = ExtractConf()
    conf.sift.max_num_features = 0  # set after construction: extract() checks again
    with pytest.raises(ValueError, match="at least 1"):
        extract(images, database=db, conf=conf, depth={"model": "none"}, run={"progress": False})
    assert not db.exists()


@pytest.mark.skipif(not Path("/proc/self").is_dir(), reason="needs Linux's /proc")
def test_an_unwritable_output_folder_is_named_as_such(images, caplog):
    """/proc accepts no new file even for root (whom permission bits do not stop): the
    message names the database and its folder, not the lock file beside it."""
    assert _extract(images, Path("/proc/db.db")) == 2
    errors = [r.getMessage() for r in caplog.records if r.levelname == "ERROR"]
    assert errors == [
        "/proc/db.db: cannot write the database: folder /proc does not accept new files "
        "(No such file or directory)"
    ]


def test_summary_counts_plain_sift_images_as_images(images, tmp_path, caplog):
    caplog.set_level("INFO")
    assert _extract(images, tmp_path / "db.db") == 0
    assert "plain SIFT only: 3 of the 3 extracted image(s)" in caplog.text
    assert "of them with plain SIFT" not in caplog.text


# -- COLMAP 4.x spellings (issue 43) ------------------------------------------------------


def _keypoints(db: Path) -> dict[str, bytes]:
    with sqlite3.connect(db) as con:
        rows = con.execute("SELECT i.name, k.data FROM keypoints k JOIN images i USING (image_id)")
        return dict(rows.fetchall())


def test_colmap4_spellings_give_the_keypoints_of_the_colmap3_ones(images, tmp_path, caplog):
    """`--FeatureExtraction.*` (COLMAP 4.x) sets what `--SiftExtraction.*` (3.x) sets: the
    same keypoints, with the default depth network; max_image_size did apply (other
    keypoints than without it); the GPU flags are said not to apply."""
    caplog.set_level("INFO")
    runs = {
        "colmap4": ["--FeatureExtraction.type", "SIFT", "--FeatureExtraction.max_image_size"]
        + ["300", "--FeatureExtraction.num_threads", "1", "--FeatureExtraction.use_gpu", "0"],
        "colmap3": ["--SiftExtraction.max_image_size", "300", "--SiftExtraction.num_threads"]
        + ["1", "--SiftExtraction.use_gpu", "0"],
        "full size": [],
    }
    kps = {}
    for name, flags in runs.items():
        db = tmp_path / f"{name}.db"
        argv = ["extract", "--database_path", str(db), "--image_path", str(images)]
        assert main([*argv, "--no_progress", *flags]) == 0
        kps[name] = _keypoints(db)
    assert len(kps["colmap4"]) == 3 and kps["colmap4"] == kps["colmap3"]
    assert all(kps["colmap4"][n] != kps["full size"][n] for n in kps["colmap4"])
    assert "--FeatureExtraction.use_gpu 0: not applied" in caplog.text


def test_feature_types_other_than_sift_stop_in_one_line(images, tmp_path, capsys):
    db = tmp_path / "db.db"
    assert _extract(images, db, "--FeatureExtraction.type", "ALIKED_N16ROT") == 2
    err = capsys.readouterr().err.strip()
    assert "--FeatureExtraction.type" in err and "SIFT only" in err and len(err.splitlines()) == 1
    assert not db.exists()
    assert _extract(images, db, "--FeatureExtraction.type", "sift") == 0


def _extract_parser():
    from rectified_colmap.cli import build_parser

    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    return sub.choices["extract"]


def _installed_extraction_options() -> list[str]:
    """`--Group.name` of every field of the installed pycolmap's FeatureExtractionOptions:
    its own fields as FeatureExtraction.*, a nested group's (``sift``, ...) as
    SiftExtraction.* and so on, as COLMAP 4's feature_extractor spells them."""

    def fields(cls) -> list[str]:
        return [n for n in dir(cls) if isinstance(getattr(cls, n), property)]

    out = []
    top = pycolmap.FeatureExtractionOptions()
    for name in fields(type(top)):
        value = getattr(top, name)
        if hasattr(value, "todict"):  # a nested group of options
            group = f"{name[0].upper()}{name[1:]}Extraction"
            out += [f"--{group}.{n}" for n in fields(type(value))]
        else:
            out.append(f"--FeatureExtraction.{name}")
    return out


def test_every_feature_extraction_option_of_the_installed_pycolmap_maps_or_says_why_not():
    """A COLMAP release that adds or renames an extraction option fails here, not in a
    user's run: each option of the installed pycolmap is accepted, and --help says what it
    sets or why it is not applied."""
    options = _installed_extraction_options()
    assert "--FeatureExtraction.max_image_size" in options
    assert "--SiftExtraction.peak_threshold" in options
    parser = _extract_parser()
    by_flag = {s: a for a in parser._actions for s in a.option_strings}
    help_text = " ".join(parser.format_help().split())
    missing = [o for o in options if o not in by_flag]
    assert not missing, f"COLMAP options unknown to `rectified-colmap extract`: {missing}"
    for option in options:
        action = by_flag[option]
        assert option in help_text and action.help and action.help != argparse.SUPPRESS
        if action.help.startswith("not applied"):
            why = action.help.removeprefix("not applied:").split()
            assert len(why) >= 3, f"{option}: not applied, but not why"
        else:  # a setting: its help says what it sets
            assert "not applied" not in action.help and len(action.help.split()) >= 3, option


@pytest.mark.parametrize(
    "option, value, field, expect",
    [
        ("--FeatureExtraction.max_image_size", "640", "max_image_size", 640),
        ("--SiftExtraction.max_image_size", "640", "max_image_size", 640),
        ("--FeatureExtraction.max_image_size", "-1", "max_image_size", 3200),
        ("--SiftExtraction.first_octave", "0", "first_octave", 0),
        ("--SiftExtraction.peak_threshold", "0.02", "peak_threshold", 0.02),
        ("--SiftExtraction.edge_threshold", "5", "edge_threshold", 5.0),
        ("--SiftExtraction.max_num_orientations", "1", "max_num_orientations", 1),
        ("--SiftExtraction.upright", "1", "upright", True),
        ("--SiftExtraction.max_num_features", "100", "max_num_features", 100),
    ],
)
def test_colmap_sift_options_set_the_configuration(option, value, field, expect):
    from rectified_colmap.cli.extract import _load_conf, apply_colmap_options

    args = _extract_parser().parse_args(["--image_path", "x", option, value])
    conf = _load_conf(args.conf, args.max_num_features)  # sets max_num_features
    if field != "max_num_features":
        setattr(conf.sift, field, (not expect) if isinstance(expect, bool) else expect + 1)
    apply_colmap_options(args, conf)
    assert getattr(conf.sift, field) == expect


@pytest.mark.parametrize(
    "option", ["--FeatureExtraction.num_threads", "--SiftExtraction.num_threads"]
)
def test_num_threads_is_num_workers_in_both_spellings(option):
    from rectified_colmap.cli.extract import apply_colmap_options

    for value, workers in (("3", 3), ("-1", os.cpu_count() or 1)):
        args = _extract_parser().parse_args(["--image_path", "x", option, value])
        apply_colmap_options(args, None)
        assert args.num_workers == workers


@pytest.mark.skipif(shutil.which("colmap") is None, reason="colmap command line not installed")
def test_every_extraction_option_of_the_installed_colmap_is_accepted():
    """The installed `colmap feature_extractor`'s ImageReader / SiftExtraction /
    FeatureExtraction options (3.8 here) are all accepted. (Its general options, --log_level
    0-2, --random_seed, --project_path, --camera_mode, are not feature-extraction ones.)"""
    out = subprocess.run(
        [shutil.which("colmap"), "feature_extractor", "-h"], capture_output=True, text=True
    ).stdout
    flags = set(re.findall(r"--((?:ImageReader|SiftExtraction|FeatureExtraction)\.\w+)", out))
    assert "SiftExtraction.max_image_size" in flags or "FeatureExtraction.max_image_size" in flags
    accepted = {s for a in _extract_parser()._actions for s in a.option_strings}
    assert not {f"--{f}" for f in flags} - accepted
