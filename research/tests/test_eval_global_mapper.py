"""scripts/eval_global_mapper.py and evaluation/pycolmap_sfm: subset databases, the table,
and one small run on a rendered street (COLMAP 4's extractor, our default, both mappers)."""

import json
import sqlite3

import cv2
import pycolmap
import pytest

from rectified_colmap_research.evaluation import pycolmap_sfm
from scripts_util import load_script

from rectified_colmap.io.colmap_db import image_ids_to_pair_id
from tests.scenes import street_orbit

script = load_script("eval_global_mapper")


@pytest.fixture(scope="module")
def street(tmp_path_factory):
    """A rendered walk of 6 views written as a Strecha-style scene (images/, sparse/)."""
    views = street_orbit(1, num=6, width=480, height=360)
    root = tmp_path_factory.mktemp("data")
    scene = root / "street"
    (scene / "images").mkdir(parents=True)
    (scene / "sparse").mkdir()
    rec = pycolmap.Reconstruction()
    camera = views[0]["camera"]
    camera.camera_id = 1
    rec.add_camera_with_trivial_rig(camera)
    for i, v in enumerate(views):
        name = f"{i:02d}.png"
        cv2.imwrite(str(scene / "images" / name), v["image"][..., ::-1])
        image = pycolmap.Image(name=name, camera_id=1, image_id=i + 1)
        rec.add_image_with_trivial_frame(image, v["pose"])
    rec.write_text(str(scene / "sparse"))
    return root


def test_subset_database_keeps_the_subset_and_its_pairs_only(street, tmp_path):
    """COLMAP 4's extractor writes rig/frame rows: the subset keeps those of its images and
    the pairs among them; pycolmap loads it."""
    db = tmp_path / "all.db"
    pycolmap_sfm.plain_features(db, street / "street" / "images", "SIMPLE_RADIAL", None, 500)
    pycolmap_sfm.match(db)
    out = tmp_path / "sub.db"
    pycolmap_sfm.subset_database(db, ["00.png", "02.png", "04.png"], out)
    with sqlite3.connect(out) as con:
        ids = dict(con.execute("SELECT name, image_id FROM images"))
        pairs = {r[0] for r in con.execute("SELECT pair_id FROM matches")}
        frames = con.execute("SELECT data_id FROM frame_data").fetchall()
        cams = con.execute("SELECT COUNT(*) FROM cameras").fetchone()[0]
    assert sorted(ids) == ["00.png", "02.png", "04.png"]
    a, b, c = (ids[n] for n in sorted(ids))
    assert pairs == {image_ids_to_pair_id(*p) for p in ((a, b), (a, c), (b, c))}
    assert sorted(f[0] for f in frames) == sorted(ids.values()) and cams == 3
    with pycolmap.Database.open(out) as pdb:
        cache = pycolmap.DatabaseCache.create(pdb, pycolmap.DatabaseCacheOptions())
        assert cache.num_images() == 3 and cache.num_frames() == 3


def test_table_totals_and_where_global_registered_fewer():
    def row(mapper, subset, registered):
        return {
            "scene": "s",
            "cameras": "gt",
            "subset": subset,
            "method": "sift",
            "mapper": mapper,
            "images": 4,
            "registered": registered,
            "points": 10,
            "map_s": 1.0,
            "rot_err_med_deg": 0.1,
        }

    rows = [row("incremental", "all", 4), row("global", "all", 4)]
    rows += [row("incremental", "0::2", 4), row("global", "0::2", 3), row("global", "0::2", 4)]
    summary = script.summarize(rows)
    assert [s["registered"] for s in summary] == [4, 4, 4, 3.5]
    assert script.fewer_than_incremental(summary) == ["s gt 0::2 sift global: 3.5 < 4"]
    table = script.markdown(summary)
    assert "| 3.5 (3-4)/4 |" in table and "| gt | sift | global | 7.5/8 |" in table


def test_rendered_street_end_to_end(street, tmp_path):
    """Plain COLMAP 4 SIFT and our default, the ground-truth camera, both mappers and the
    calibrated global one: every image registered with rotations near the truth; a second
    run reuses everything."""
    out = tmp_path / "out"
    args = ["--output_dir", str(out), "--strecha", str(street), "--cameras", "gt"]
    args += ["--subsets", "0::1", "0::2", "--seeds", "0"]
    assert script.main(args) == 0
    rows = json.loads((out / "global_mapper.json").read_text())
    keys = [(r["method"], r["subset"], r["mapper"]) for r in rows]
    assert keys == [
        (m, s, mapper)
        for m in ("sift", "rectsift")
        for s in ("all", "0::2")
        for mapper in pycolmap_sfm.MAPPERS
    ]
    for r in rows:
        assert r["registered"] == r["images"] and r["prior_focal_share"] == 1.0, r
        assert r["rot_err_med_deg"] < 1.0 and r["points"] > 30, r
    table = (out / "global_mapper.md").read_text()
    assert "| street | gt | all | sift | incremental | 6/6 |" in table
    assert "global registered fewer images than incremental: nowhere" in table
    assert script.main(args) == 0
    assert json.loads((out / "global_mapper.json").read_text()) == rows
