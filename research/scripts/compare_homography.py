#!/usr/bin/env python
"""Two runs of `eval_homography.py` on the same pairs, compared pair by pair.

Each run is ``PATH[:METHOD]``: an output folder of eval_homography.py (its records.csv)
or a records.csv, and the method to take from it (default ``rectsift``; two methods of one
run: the same PATH twice). Prints, per half (the records' ``split`` column: the generated
extreme pairs' choose / check) and for all pairs, the pairs each solves, the discordant
pairs (gained: only the second solves it; lost: only the first) by name, and the exact
sign test's p on them (homography_report.paired_markdown).

A variant that gains a few pairs on one half may only have drawn lucky pairs there: at
stop 65 a setting chosen on seed 0's choose half gained 4 pairs and lost 1 on seed 0, then
gained none and lost 5 on seed 2. Compare every set you have, by its discordant pairs.

    python research/scripts/compare_homography.py OUT-default OUT-variant
    python research/scripts/compare_homography.py OUT:rectsift OUT:asift --output cmp.md
"""

from __future__ import annotations

import argparse
from pathlib import Path

from rectified_colmap.errors import run_script
from rectified_colmap_research.evaluation.homography_report import (
    paired_markdown,
    pairs_solved,
    read_records_csv,
)


def read_run(spec: str) -> tuple[dict[str, bool], dict[str, str], str]:
    """``PATH[:METHOD]`` -> (pair -> solved, pair -> half, label). SystemExit (one line)
    when the file is missing or the method has no records there."""
    path, _, method = spec.partition(":")
    method = method or "rectsift"
    csv_path = Path(path) / "records.csv" if Path(path).is_dir() else Path(path)
    if not csv_path.is_file():
        raise SystemExit(f"{csv_path}: no such records file (eval_homography.py writes one)")
    rows = read_records_csv(csv_path)
    solved = pairs_solved(rows, method)
    if not solved:
        have = sorted({r.get("method", "?") for r in rows})
        raise SystemExit(f"{csv_path}: no records of method {method!r} (it has {have})")
    splits = {r["pair"]: r["split"] for r in rows if r.get("split")}
    return solved, splits, f"{Path(path).name}:{method}"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("base", help="PATH[:METHOD], the run compared against")
    p.add_argument("new", help="PATH[:METHOD]")
    p.add_argument("--output", type=Path, help="also write the table here (Markdown)")
    args = p.parse_args(argv)
    base, splits, base_label = read_run(args.base)
    new, new_splits, new_label = read_run(args.new)
    text = paired_markdown(base, new, {**new_splits, **splits}, (base_label, new_label))
    print(text, end="")
    if args.output is not None:
        args.output.write_text(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(run_script(main, "compare_homography"))
