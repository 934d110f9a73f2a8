"""The scripts' default data folders are the project's ../shared (beside the repository),
wherever the scripts themselves live."""

from pathlib import Path

import pytest

from scripts_util import load_script

SHARED = Path(__file__).resolve().parents[2].parent / "shared"


@pytest.mark.parametrize(
    "script, name, relative",
    [
        ("eval_hloc_sfm", "SACRE_COEUR", "vendor/hloc/datasets/sacre_coeur/mapping"),
        ("eval_sparse_sfm", "DATA", "data"),
        ("build_extreme_pairs", "DATA_ROOT", "data"),
    ],
)
def test_default_data_is_the_shared_folder(script, name, relative):
    assert getattr(load_script(script), name) == SHARED / relative
    if not SHARED.is_dir():
        pytest.skip(f"{SHARED} not present (it holds the shared data)")
    assert (SHARED / relative).is_dir()
