"""research/scripts/compare_homography.py: two eval_homography.py runs, pair by pair."""

import csv

import pytest

from scripts_util import load_script


def write_records(path, method, solved):
    """records.csv of eval_homography.py: two directions per pair, ``solved`` pair ->
    (success 0->1, success 1->0), pairs 0000-0001 in choose, the rest in check."""
    path.mkdir(parents=True, exist_ok=True)
    with open(path / "records.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=["pair", "method", "direction", "success", "split"])
        w.writeheader()
        for pair, ok in solved.items():
            split = "choose" if pair in ("0000", "0001") else "check"
            for d, s in zip(("0->1", "1->0"), ok):
                w.writerow(
                    dict(pair=pair, method=method, direction=d, success=bool(s), split=split)
                )


def test_compare_two_runs_pair_by_pair(tmp_path, capsys):
    write_records(
        tmp_path / "a", "rectsift", {"0000": (1, 0), "0001": (0, 0), "0002": (1, 1), "0003": (1, 1)}
    )
    write_records(
        tmp_path / "b", "variant", {"0000": (0, 0), "0001": (0, 1), "0002": (1, 1), "0003": (0, 0)}
    )
    cmp = load_script("compare_homography")
    out = tmp_path / "cmp.md"
    assert cmp.main([str(tmp_path / "a"), f"{tmp_path / 'b'}:variant", "--output", str(out)]) == 0
    text = capsys.readouterr().out
    assert text == out.read_text()
    lines = {line.split("|")[1].strip(): line for line in text.splitlines() if line.startswith("|")}
    cells = [c.strip() for c in lines["all"].strip("|").split("|")]
    assert cells == ["all", "4", "3", "2", "1", "1", "2", "1", "0001", "0000 0003"]
    cells = [c.strip() for c in lines["check"].strip("|").split("|")]
    assert cells[5:] == ["0", "1", "1", "-", "0003"]
    with pytest.raises(SystemExit, match="no records of method 'rectsift'"):
        cmp.main([str(tmp_path / "b"), str(tmp_path / "a")])
