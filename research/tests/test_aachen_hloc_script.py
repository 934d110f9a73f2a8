"""research/scripts/aachen_hloc.py: its checks of the hloc installation."""

import sys

import pytest
from scripts_util import load_script

from rectified_colmap.eval.aachen import HlocError, call_with, import_hloc


def test_script_hloc_checks(monkeypatch):
    mod = load_script("aachen_hloc")
    monkeypatch.setitem(sys.modules, "hloc", None)  # import hloc -> ImportError
    with pytest.raises(SystemExit, match="hloc is not installed.*not on PyPI"):
        mod.require_hloc()
    with pytest.raises(HlocError, match="not installed"):
        import_hloc()

    def new_style(image_ids, reference, database_path, max_error=4.0):
        return (image_ids, reference, database_path, max_error)

    def old_style(database_path, pairs_path, verbose=False):
        return (database_path, pairs_path)

    avail = {
        "image_ids": 1,
        "reference": 2,
        "database_path": 3,
        "pairs_path": 4,
        "features_path": 5,
    }
    assert call_with(new_style, **avail) == (1, 2, 3, 4.0)
    assert call_with(old_style, **avail) == (3, 4)
    with pytest.raises(HlocError, match="needs"):
        call_with(lambda other: 0, **avail)
