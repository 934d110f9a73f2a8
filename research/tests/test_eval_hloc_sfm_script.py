"""scripts/eval_hloc_sfm.py: the table of its runs (the runs themselves go through the real
hloc in research/tests/test_hloc_integration.py)."""

from scripts_util import load_script


def test_eval_hloc_sfm_table_pairs_seeds():
    """The table's statistics: per-method mean and std, the mean per-seed difference from the
    baseline and on how many seeds it is higher / lower (no hloc needed)."""
    script = load_script("eval_hloc_sfm")
    rows = [
        {"method": "sift", "seed": s, "registered": 10, "points": p}
        for s, p in [(0, 100), (1, 110), (2, 90)]
    ]
    rows += [
        {"method": "x", "seed": s, "registered": r, "points": p}
        for s, r, p in [(0, 9, 104), (1, 10, 107), (2, 10, 102)]
    ]
    table = script.markdown(rows)
    assert "| sift | 10-10 | 100 110 90 | 100.0 | 10.0 | - | - |" in table
    # x - sift per seed: +4, -3, +12 -> mean +4.33 (+4.3 %), higher on 2, lower on 1
    assert "| x | 9-10 | 104 107 102 | 104.3 | 2.5 | +4.3 (+4.3%) | 2 / 1 |" in table
