"""research/scripts/bench_cli.py: the rounds' medians and each round's ratio."""

import pytest

from scripts_util import load_script


def row(cpu, wall=1.0, kp=100.0):
    return {"cpu": cpu, "wall": wall, "peak_MB": 10.0, "tree_MB": 10.0, "kp": kp}


def test_summary_takes_medians_and_pairs_each_round_with_its_own_baseline():
    bench = load_script("bench_cli")
    measured = {
        "pycolmap": [row(1.0), row(2.0), row(1.5)],
        "rectified": [row(4.0, kp=200.0), row(5.0, kp=200.0), row(9.0, kp=200.0)],
    }
    rows = bench.summarise(measured)
    assert rows["pycolmap"]["cpu"] == 1.5 and rows["rectified"]["cpu"] == 5.0
    assert rows["rectified"]["kp"] == 200.0
    # round by round: 4 / 1, 5 / 2, 9 / 1.5 (not the medians' ratio 5 / 1.5)
    assert rows["rectified"]["ratios"] == pytest.approx([4.0, 2.5, 6.0])
    assert rows["pycolmap"]["ratios"] == pytest.approx([1.0, 1.0, 1.0])
    assert bench.summarise({"rectified": [row(3.0)]})["rectified"]["ratios"] == []


def test_rounds_must_be_positive():
    bench = load_script("bench_cli")
    assert bench.parse_args(["--synthetic", "1", "--rounds", "3"]).rounds == 3
    with pytest.raises(SystemExit):
        bench.parse_args(["--synthetic", "1", "--rounds", "0"])


def test_table_gives_the_median_of_the_rounds_ratios_and_their_range(capsys):
    bench = load_script("bench_cli")
    measured = {
        "pycolmap": [row(1.0), row(2.0), row(1.5)],
        "rectified": [row(4.0), row(5.0), row(9.0)],
    }
    bench.print_table(bench.summarise(measured), 1)
    line = [x for x in capsys.readouterr().out.splitlines() if x.startswith("| rectified")][0]
    cells = [c.strip() for c in line.strip("|").split("|")]
    assert cells[1] == "5.00" and cells[3] == "4.00x" and cells[4] == "2.50-6.00x"


def test_a_missing_console_script_stops_before_any_run(monkeypatch, tmp_path):
    bench = load_script("bench_cli")
    monkeypatch.setenv("PATH", str(tmp_path))  # nothing on it
    monkeypatch.setattr(bench, "measure", lambda *a: pytest.fail("measured"))
    with pytest.raises(ValueError, match="rectified-colmap is not on PATH"):
        bench.main(["--synthetic", "1", "--methods", "pycolmap", "rectified"])
