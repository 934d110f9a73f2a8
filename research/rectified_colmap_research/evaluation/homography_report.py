"""Summaries of a homography-pair evaluation per split and per class, with each method's
CPU cost (research/scripts/eval_homography.py; issue 41: "every number you report gives
both halves", "a class that fails shows as a class").

Records are those of :func:`rectified_colmap.eval.homography.evaluate_homography_pairs`
(one per pair, direction and method: ``pair``, ``method``, ``success``, ``num_gt``, ...).
``splits`` maps a pair name to its half (e.g. "choose" / "check" of the generated extreme
pairs); every table then gives each half and all pairs. A pair is solved when either
direction is (as in :func:`rectified_colmap.eval.homography.homography_markdown`).
"""

from __future__ import annotations

import csv
import math
import re
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from rectified_colmap.eval.config import HomographyConf

ALL = "all"


def write_records_csv(path: Path | str, records: list[dict]) -> None:
    """Records (dicts with the same keys, in the first one's order) as a CSV file."""
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(records[0]))
        w.writeheader()
        w.writerows(records)


def read_records_csv(path: Path | str) -> list[dict]:
    """Records written by :func:`write_records_csv`, as strings but ``success`` a bool."""
    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))
    for r in rows:
        r["success"] = r.get("success") == "True"
    return rows


JOINT = " & "
"""Separator of the parts of a joint label ("2-4 & yes": eval_homography.py's ``A+B``)."""


def label_order(label: str) -> tuple:
    """Sort key of bin labels: by their first number ("<2" before "2-4" before "4-8",
    "0" before "90" before "180"; a leading "<" just below it, ">" just above), then
    labels without a number alphabetically ("no" before "other" before "yes"); a joint
    label part by part."""
    if JOINT in label:
        return tuple(label_order(part) for part in label.split(JOINT))
    m = re.search(r"\d+(\.\d+)?", label)
    if m is None:
        return (1, 0.0, label)
    v = float(m.group())
    if label.startswith("<"):
        v -= 0.5
    elif label.startswith(">"):
        v += 0.5
    return (0, v, label)


def split_names(records: list[dict], splits: Mapping[str, str] | None) -> list[str]:
    """The halves present ("choose", "check" first, then others sorted), then "all"; just
    ["all"] without ``splits``."""
    if not splits:
        return [ALL]
    have = {splits.get(r["pair"], "-") for r in records}
    first = [s for s in ("choose", "check") if s in have]
    return first + sorted(have - set(first)) + [ALL]


def _subset(records, splits, split):
    if split == ALL:
        return records
    return [r for r in records if splits.get(r["pair"], "-") == split]


def solved_pairs(records: list[dict]) -> tuple[int, int]:
    """(pairs solved in either direction, pairs) of the records."""
    pairs = {r["pair"] for r in records}
    return len({r["pair"] for r in records if r["success"]}), len(pairs)


def _median_gt(records) -> str:
    return f"{np.median([r['num_gt'] for r in records]):.0f}" if records else "-"


def split_summary_markdown(
    records: list[dict],
    splits: Mapping[str, str] | None = None,
    cpu: Mapping[str, Mapping[str, float]] | None = None,
    conf: HomographyConf = HomographyConf(),
) -> str:
    """Per method: pairs solved per half and in all, cases solved (all), median
    GT-consistent matches per case per half, and CPU seconds (``cpu``: method ->
    {"extract": s per image, "match": s per case}; missing: "-")."""
    methods = list(dict.fromkeys(r["method"] for r in records))
    names = split_names(records, splits)
    head = " | ".join(f"pairs solved: {s}" for s in names)
    gt = " | ".join(f"median GT-consistent: {s}" for s in names)
    lines = [
        f"| method | {head} | cases solved (visible err < {conf.success_px:g} px) | {gt} | "
        "extract CPU s / image | match CPU s / case |",
        "|---|" + "---|" * (2 * len(names) + 3),
    ]
    cpu = cpu or {}
    for m in methods:
        rs = [r for r in records if r["method"] == m]
        cells = ["{} of {}".format(*solved_pairs(_subset(rs, splits, s))) for s in names]
        gts = [_median_gt(_subset(rs, splits, s)) for s in names]
        c = cpu.get(m, {})
        ext, mat = (f"{c[k]:.2f}" if c.get(k) is not None else "-" for k in ("extract", "match"))
        lines.append(
            f"| {m} | {' | '.join(cells)} | {sum(r['success'] for r in rs)} of {len(rs)} | "
            f"{' | '.join(gts)} | {ext} | {mat} |"
        )
    return "\n".join(lines) + "\n"


def split_group_markdown(
    records: list[dict],
    key: str,
    groups: Mapping[str, str],
    splits: Mapping[str, str] | None = None,
    conf: HomographyConf = HomographyConf(),
) -> str:
    """Per value of ``key`` (``groups``: pair name -> value; pairs without one are "-")
    and method: pairs solved per half and in all, and the median GT-consistent matches per
    case per half. Values in :func:`label_order`."""
    methods = list(dict.fromkeys(r["method"] for r in records))
    values = sorted({groups.get(r["pair"], "-") for r in records}, key=label_order)
    names = split_names(records, splits)
    head = " | ".join(f"solved: {s}" for s in names)
    gt = " | ".join(f"median GT: {s}" for s in names)
    lines = [
        f"| {key} | method | {head} | {gt} |",
        "|---|---|" + "---|" * (2 * len(names)),
    ]
    for v in values:
        for m in methods:
            rs = [r for r in records if r["method"] == m and groups.get(r["pair"], "-") == v]
            cells = ["{} of {}".format(*solved_pairs(_subset(rs, splits, s))) for s in names]
            gts = [_median_gt(_subset(rs, splits, s)) for s in names]
            lines.append(f"| {v} | {m} | {' | '.join(cells)} | {' | '.join(gts)} |")
    return "\n".join(lines) + "\n"


def pairs_solved(records: list[dict], method: str) -> dict[str, bool]:
    """Pair name -> solved in either direction, for ``method``'s records."""
    out: dict[str, bool] = {}
    for r in records:
        if r["method"] == method:
            out[r["pair"]] = out.get(r["pair"], False) or bool(r["success"])
    return out


def sign_test_p(gained: int, lost: int) -> float:
    """Two-sided exact sign test of the discordant pairs (a pair one method solves and the
    other not): the probability, were each equally likely to fall either way, of a split at
    least this uneven (1 for a tie or none)."""
    n, k = gained + lost, min(gained, lost)
    if n == 0:
        return 1.0
    tail = sum(math.comb(n, i) for i in range(k + 1)) / 2.0**n
    return min(1.0, 2.0 * tail)


def paired_markdown(
    base: dict[str, bool],
    new: dict[str, bool],
    splits: Mapping[str, str] | None = None,
    labels: tuple[str, str] = ("base", "new"),
) -> str:
    """Solved pairs of two runs on the same pairs (``pairs_solved``), pair by pair, per
    half and in all: solved by each, by both, the discordant pairs (gained: only ``new``;
    lost: only ``base``) with their names and the sign test's p (``sign_test_p``). A
    difference of a few pairs in one half is often no more than the luck of which pairs
    fell there: this says how uneven the discordant pairs are. Pairs in only one run are
    left out (counted in the header line)."""
    common = sorted(set(base) & set(new))
    splits = splits or {}
    records = [{"pair": p} for p in common]
    lines = [
        f"{len(common)} pairs in both runs ({len(set(base) ^ set(new))} in one only)",
        "",
        f"| half | pairs | {labels[0]} | {labels[1]} | both | gained | lost | sign test p "
        "| gained pairs | lost pairs |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for s in split_names(records, splits if splits else None):
        ps = [r["pair"] for r in _subset(records, splits, s)]
        gained = [p for p in ps if new[p] and not base[p]]
        lost = [p for p in ps if base[p] and not new[p]]
        both = sum(base[p] and new[p] for p in ps)
        lines.append(
            f"| {s} | {len(ps)} | {sum(base[p] for p in ps)} | {sum(new[p] for p in ps)} | "
            f"{both} | {len(gained)} | {len(lost)} | {sign_test_p(len(gained), len(lost)):.3g} "
            f"| {' '.join(gained) or '-'} | {' '.join(lost) or '-'} |"
        )
    return "\n".join(lines) + "\n"
