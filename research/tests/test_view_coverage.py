"""research/scripts/view_coverage.py: a pair's residual tilt per view set, crossed with the
pairs a method solved."""

from types import SimpleNamespace

import numpy as np
import pytest
from scripts_util import load_script

from rectified_colmap.eval.homography import HomographyPair

vc = load_script("view_coverage")


def test_rows_and_report_tell_covered_from_solved(tmp_path):
    """An affine pair with tilt 3 over a 640 x 480 image: the plain images leave 3, a depth
    view of image 1 that undoes it 1, ASIFT's views less than sqrt 2; the records make the
    pair lost, and the report lists it among the covered pairs that were lost."""
    pair = HomographyPair("p", "a.jpg", "b.jpg", np.diag([3.0, 1.0, 1.0]), (640, 480), (1920, 480))
    pair.info.update(split="check", tilt_bin="2-4", scale_bin="<2x")
    plain, undo = (np.eye(3), None), (np.diag([1 / 3.0, 1.0, 1.0]), None)
    asift = vc.asift_view_set()
    sets = {
        "plain": ([plain], [plain], ["plain"], ["plain"]),
        "default": ([plain], [plain, undo], ["plain"], ["plain", "depth"]),
        "asift": (asift, asift, ["asift"] * len(asift), ["asift"] * len(asift)),
    }
    row = vc.pair_row(pair, sets, 40.0)
    assert row["points"] == 16 * 12
    assert row["plain_tilt"] == pytest.approx(3.0) and row["default_tilt"] == pytest.approx(1.0)
    assert row["asift_tilt"] < 2**0.5 and row["asift_coverage"] == 1.0
    assert row["default_best"] == "plain+depth" and row["default_views"] == "0+1"
    assert row["default_scale"] == pytest.approx(1.0) and row["plain_coverage"] == 0.0
    records = tmp_path / "records.csv"
    records.write_text("pair,method,direction,success\np,m,0->1,False\np,m,1->0,False\n")
    row.update({m: "p" in names for m, names in vc.solved_pairs([records]).items()})
    md = vc.report([row], ["m"], SimpleNamespace(data=tmp_path, split=None, conf="rectsift"))
    assert "| met | 0 | 1 |" in md and "| not covered | 0 | 0 |" in md and "| p | check |" in md
    assert vc.meeting(row, "plain") == "not covered" and vc.meeting(row, "default") == "met"
    assert vc.meeting({**row, "default_scale": 5.0}, "default") == "beyond 4x"
