"""scripts/eval_vp.py: which configuration each table row runs with."""

import importlib.util
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def load_script():
    spec = importlib.util.spec_from_file_location("eval_vp", ROOT / "scripts" / "eval_vp.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_rows_without_vp_run_without_it_although_the_default_has_it():
    ev = load_script()
    rows = ev.network_rows(["rectsift-lite0"], with_vp=True)
    cfs = ev.confs(1024, rows, {"rectify": {"max_viewing_angle_deg": 86.0}})
    assert not cfs["rect GT depth"].vp.enabled
    assert not cfs["rect corrupted"].vp.enabled
    assert cfs["rect corrupted + VP"].vp.enabled
    assert not cfs["rect network (rectsift-lite0)"].vp.enabled
    assert cfs["rect network (rectsift-lite0) + VP"].vp.enabled
    for conf in cfs.values():  # the budget and the overrides reach every row
        assert conf.sift.max_num_features == 1024
        assert conf.rectify.max_viewing_angle_deg == 86.0
    assert cfs["VP only"].vp.depth_free and cfs[ev.WHOLE].vp.depth_free_regions == "whole"
