"""rectified_colmap_research.evaluation.homography_report: per-half and per-class tables."""

from rectified_colmap_research.evaluation.homography_report import (
    label_order,
    paired_markdown,
    pairs_solved,
    sign_test_p,
    solved_pairs,
    split_group_markdown,
    split_names,
    split_summary_markdown,
)


def rec(pair, method, direction, success, num_gt):
    return dict(pair=pair, method=method, direction=direction, success=success, num_gt=num_gt)


# pairs a, b in "choose", c in "check"; m1 solves a (one direction) and c, m2 only b
RECORDS = [
    rec("a", "m1", "0->1", True, 50),
    rec("a", "m1", "1->0", False, 10),
    rec("a", "m2", "0->1", False, 0),
    rec("a", "m2", "1->0", False, 2),
    rec("b", "m1", "0->1", False, 4),
    rec("b", "m1", "1->0", False, 6),
    rec("b", "m2", "0->1", True, 30),
    rec("b", "m2", "1->0", True, 40),
    rec("c", "m1", "0->1", True, 90),
    rec("c", "m1", "1->0", True, 70),
    rec("c", "m2", "0->1", False, 1),
    rec("c", "m2", "1->0", False, 3),
]
SPLITS = {"a": "choose", "b": "choose", "c": "check"}


def row(text, *first):
    """Cells of the table row starting with ``first``."""
    for line in text.splitlines():
        cells = [c.strip() for c in line.strip("|").split("|")]
        if cells[: len(first)] == list(first):
            return cells
    raise AssertionError(f"no row {first} in\n{text}")


def test_label_order_sorts_bins_by_their_numbers():
    labels = ["4-8", "<2", "2-4", ">4x", "2-4x", "<2x", "other", "180", "90", "0", "yes", "no"]
    assert sorted(labels[:3], key=label_order) == ["<2", "2-4", "4-8"]
    assert sorted(labels[3:6], key=label_order) == ["<2x", "2-4x", ">4x"]
    assert sorted(labels[6:10], key=label_order) == ["0", "90", "180", "other"]
    assert sorted(labels[10:], key=label_order) == ["no", "yes"]
    joint = ["yes & <2x", "no & >4x", "no & 2-4x", "yes & 2-4x"]  # part by part
    assert sorted(joint, key=label_order) == ["no & 2-4x", "no & >4x", "yes & <2x", "yes & 2-4x"]


def test_halves_and_solved_pairs():
    assert split_names(RECORDS, SPLITS) == ["choose", "check", "all"]
    assert split_names(RECORDS, None) == ["all"]
    assert solved_pairs([r for r in RECORDS if r["method"] == "m1"]) == (2, 3)
    assert solved_pairs([r for r in RECORDS if r["method"] == "m2"]) == (1, 3)


def test_summary_gives_every_number_per_half_and_the_cost():
    text = split_summary_markdown(RECORDS, SPLITS, {"m1": {"extract": 0.5, "match": 0.25}})
    head = row(text, "method")
    assert head[1:4] == ["pairs solved: choose", "pairs solved: check", "pairs solved: all"]
    m1 = row(text, "m1")
    assert m1[1:5] == ["1 of 2", "1 of 1", "2 of 3", "3 of 6"]
    assert m1[5:8] == ["8", "80", "30"]  # median GT-consistent per case: choose, check, all
    assert m1[8:] == ["0.50", "0.25"]
    m2 = row(text, "m2")
    assert m2[1:5] == ["1 of 2", "0 of 1", "1 of 3", "2 of 6"]
    assert m2[8:] == ["-", "-"]
    # without halves: just "all"
    plain = split_summary_markdown(RECORDS)
    assert "choose" not in plain and row(plain, "m1")[1] == "2 of 3"


def test_group_table_gives_each_class_per_half():
    groups = {"a": "4-8", "b": "<2", "c": "4-8"}
    text = split_group_markdown(RECORDS, "tilt_bin", groups, SPLITS)
    lines = [x for x in text.splitlines() if x.startswith("| <2") or x.startswith("| 4-8")]
    assert [x.split("|")[1].strip() for x in lines] == ["<2", "<2", "4-8", "4-8"]
    assert row(text, "4-8", "m1")[2:5] == ["1 of 1", "1 of 1", "2 of 2"]
    assert row(text, "4-8", "m2")[2:5] == ["0 of 1", "0 of 1", "0 of 2"]
    assert row(text, "<2", "m2")[2:5] == ["1 of 1", "0 of 0", "1 of 1"]
    assert row(text, "<2", "m2")[5:8] == ["35", "-", "35"]


def test_pairs_solved_either_direction_per_method():
    assert pairs_solved(RECORDS, "m1") == {"a": True, "b": False, "c": True}
    assert pairs_solved(RECORDS, "m2") == {"a": False, "b": True, "c": False}
    assert pairs_solved(RECORDS, "none") == {}


def test_sign_test_p_is_the_exact_two_sided_binomial_tail():
    assert sign_test_p(0, 0) == 1.0 and sign_test_p(3, 3) == 1.0
    assert sign_test_p(5, 0) == sign_test_p(0, 5) == 2 / 32  # 0.0625
    assert sign_test_p(4, 1) == 2 * (1 + 5) / 32
    assert sign_test_p(10, 0) < 0.002 and sign_test_p(6, 5) == 1.0


def test_paired_markdown_names_the_gained_and_lost_pairs_per_half():
    base = pairs_solved(RECORDS, "m1")  # a, c
    new = pairs_solved(RECORDS, "m2")  # b
    new["d"] = True  # in one run only: left out
    text = paired_markdown(base, new, SPLITS, ("m1", "m2"))
    assert text.startswith("3 pairs in both runs (1 in one only)")
    assert row(text, "choose") == ["choose", "2", "1", "1", "0", "1", "1", "1", "b", "a"]
    assert row(text, "check") == ["check", "1", "1", "0", "0", "0", "1", "1", "-", "c"]
    assert row(text, "all")[:8] == ["all", "3", "2", "1", "0", "1", "2", "1"]
    assert row(text, "all")[8:] == ["b", "a c"]
    assert row(paired_markdown(base, base), "all")[5:8] == ["0", "0", "1"]  # no split: all
