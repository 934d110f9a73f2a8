"""scripts/eval_vp.py: which configuration each table row runs with."""

from scripts_util import load_script


def test_network_row_is_the_default_and_rows_without_vp_run_without_it():
    from rectified_colmap.config import ExtractConf

    ev = load_script("eval_vp")
    assert list(ev.network_rows(["rectsift-lite0"], without_vp=False)) == [
        "rect network (rectsift-lite0)"
    ]
    rows = ev.network_rows(["rectsift-lite0"], without_vp=True)
    cfs = ev.confs(1024, rows, {"rectify": {"max_viewing_angle_deg": 86.0}})
    assert not cfs["rect GT depth"].vp.enabled
    assert not cfs["rect corrupted"].vp.enabled
    assert cfs["rect corrupted + VP"].vp.enabled
    # the network row is what `rectified-colmap extract` runs: the default conf, VP on
    shipped = ExtractConf.from_dict({"rectify": {"max_viewing_angle_deg": 86.0}})
    shipped.sift.max_num_features = 1024
    assert cfs["rect network (rectsift-lite0)"] == shipped and shipped.vp.enabled
    assert not cfs["rect network (rectsift-lite0), no VP"].vp.enabled
    # a conf that turns VP off keeps it off in the network row
    off = ev.confs(1024, rows, {"vp": {"enabled": False}})
    assert not off["rect network (rectsift-lite0)"].vp.enabled
    for conf in cfs.values():  # the budget and the overrides reach every row
        assert conf.sift.max_num_features == 1024
        assert conf.rectify.max_viewing_angle_deg == 86.0
    assert ev.LINE_ROWS["VP only"].regions == "lines" and ev.LINE_ROWS[ev.WHOLE].regions == "whole"


def test_combine_bins_by_viewpoint_change(tmp_path):
    import pytest

    from rectified_colmap.eval import report

    ev = load_script("eval_vp")
    recs = []
    for i, (rot, view) in enumerate([(5.0, 45.0), (5.0, 45.0), (15.0, None)]):
        for method, correct in (("sift", 100), ("rectsift", 120)):
            recs.append(
                dict(name0=f"a{i}", name1=f"b{i}", method=method, gt_rot=rot, viewpoint=view)
                | dict(category=None, num_kp0=1, num_kp1=1, num_matches=correct)
                | dict(num_inliers=correct, num_correct=correct, num_inliers_correct=correct)
                | dict(R_err=1.0, t_err=1.0, pose_err=1.0, success=True, epipolar_success=True)
            )
    report.write_csv(tmp_path / "r.csv", recs)
    specs = [f"a={tmp_path / 'r.csv'}:sift", f"b={tmp_path / 'r.csv'}:rectsift"]
    text = ev.combine(specs, 10.0, "a", "viewpoint")
    assert "| viewpoint change (deg) | pairs |" in text and "| 40-50 | 2 |" in text
    assert "| b | all | 2 | 0 | 0 | 1.000 | 2 | 0 |" in text  # the unknown pair left out
    assert "| b | all | 3 |" in ev.combine(specs, 10.0, "a")  # by GT rotation: all three
    report.write_csv(tmp_path / "old.csv", [dict(r, viewpoint=None) for r in recs])
    with pytest.raises(SystemExit, match="no records with a known 'viewpoint'"):
        ev.combine([f"a={tmp_path / 'old.csv'}:sift"], 10.0, None, "viewpoint")
