#!/usr/bin/env python
"""Do the views reach the plane? The residual transition tilt of planar pairs, per pair,
for the default's views beside ASIFT's and plain SIFT's (issue 41, item 3: "the true
orientation always within the tilt tolerance of SIFT on some view").

For the pairs of ``--data`` (pairs.json and images/, e.g. build_extreme_pairs.py's generated
pairs, ``--split`` for one half), each image is extracted as eval_homography.py's
``rectsift`` does (extreme_pairs.guessed_camera, the embedded network, ``--conf``). On a grid
of the overlap (image-0 points that image 1 sees on the plane), every point gets its
residual tilt (rectified_colmap_research.evaluation.view_meeting.best_view_pairs): the
smallest transition tilt between a view of image 0 and a view of image 1 that both hold it. The
views: the image itself and the default's rectified views (``default``), OpenCV's ASIFT
views (``asift``: whole-image affine tilts, no mask), the images alone (``plain``: the
pair's own transition tilt). A pair is *covered* where the median point's residual tilt is
at most TAU_MAX (2); the scale change is the one at which the views meet, nearest 1.

With ``--records`` (eval_homography.py's records.csv, repeatable), each method there adds
whether it solved the pair (either direction), and the report crosses how the views reach
the plane (``met``: covered within SCALE_MAX scale change; covered only beyond it; not
covered) with solved: a pair the default loses although its views meet the plane lost its
matches after the orientation (resolution, budget, detector, matching); one they do not
cover lost it before.

Writes coverage.csv (one row per pair) and coverage.md.

    python research/scripts/view_coverage.py --data OUT/seed3 --output_dir OUT/cov_s3 \\
        --records OUT/ev_s3/records.csv
"""

from __future__ import annotations

import argparse
import csv
import logging
import pickle
from collections import Counter
from pathlib import Path

import numpy as np

from rectified_colmap.config import DEFAULT_DEPTH_MODEL, ExtractConf, confs
from rectified_colmap.errors import run_script
from rectified_colmap.eval.config import HomographyConf
from rectified_colmap_research.evaluation.extreme_pairs import extract_guessed, read_half
from rectified_colmap_research.evaluation.view_meeting import (
    asift_view_set,
    best_view_pairs,
    overlap_points,
    view_kinds,
    view_set,
)

logger = logging.getLogger("view_coverage")
CLASSES = ("tilt_bin", "scale_bin", "rotation", "both_oblique", "portrait")
VIEW_SETS = ("plain", "default", "asift")
TAU_MAX = 2.0
"""The transition tilt SIFT absorbs (ASIFT's analysis): a pair is covered where its median
overlap point has two views that meet within it."""
SCALE_MAX = 4.0
"""A reporting threshold, not a setting: a covered pair whose views meet within this scale
change (at the median point) is *met*; SIFT's octaves span more, but the detail of the
finer view beyond the coarser one's has nothing to match."""


def default_views(res, camera) -> tuple[list, list[str]]:
    """The view set of ``res`` (pipeline.ImageResult: the image itself and its rectified
    views, view_meeting.view_set) and each view's kind (``plain``, view_kinds)."""
    kinds = view_kinds(res.planes.patches) if res.planes is not None else []
    return view_set(camera, res.rectifications), ["plain"] + [
        kinds[r.patch_index] for r in res.rectifications
    ]


def solved_pairs(paths: list[Path]) -> dict[str, set[str]]:
    """method -> names of the pairs it solved in either direction, from records.csv files."""
    out: dict[str, set[str]] = {}
    for path in paths:
        with open(path, newline="") as f:
            for row in csv.DictReader(f):
                out.setdefault(row["method"], set())
                if row["success"] == "True":
                    out[row["method"]].add(row["pair"])
    return out


def pair_row(pair, sets: dict[str, tuple], step: float) -> dict:
    """One pair's residual tilts under each view set (``sets``: name -> (views of image 0,
    views of image 1, kinds of image 0's, kinds of image 1's)): the median over the overlap
    grid (``step`` px) and the share within TAU_MAX; the median scale change at which the
    views meet (view_meeting.best_view_pairs); the kinds of the two views that meet most
    often at the smallest tilt."""
    xy = overlap_points(pair, step)
    row = {"pair": pair.name, "split": pair.info.get("split", ""), "points": len(xy)}
    row.update({c: pair.info.get(c, "") for c in CLASSES})
    for name, (v0, v1, k0, k1) in sets.items():
        tilts, which, scale = best_view_pairs(pair, v0, v1, xy, TAU_MAX)
        empty = float("nan")
        row[f"{name}_tilt"] = float(np.median(tilts)) if len(xy) else empty
        row[f"{name}_coverage"] = float(np.mean(tilts <= TAU_MAX)) if len(xy) else empty
        row[f"{name}_scale"] = float(np.median(scale)) if len(xy) else empty
        if name == "default":
            met = which[tilts <= TAU_MAX]
            kinds = Counter(f"{k0[a]}+{k1[b]}" for a, b in met)
            row["default_views"] = f"{len(v0) - 1}+{len(v1) - 1}"
            row["default_best"] = kinds.most_common(1)[0][0] if kinds else ""
    return row


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--data", type=Path, required=True, help="folder with pairs.json, images/")
    p.add_argument("--split", help="the half (choose / check) of a generated pair file")
    p.add_argument("--conf", default="rectsift", choices=sorted(confs))
    p.add_argument("--output_dir", type=Path, required=True)
    p.add_argument("--records", type=Path, action="append", default=[], help="records.csv")
    p.add_argument("--grid_step", type=float, default=2 * HomographyConf().grid_step)
    p.add_argument("--max_pairs", type=int)
    p.add_argument(
        "--cache",
        type=Path,
        help="folder of each image's views (pickled): reused if there (clear it when the "
        "code or the data change)",
    )
    args = p.parse_args(argv)
    from rectified_colmap.depth.registry import load_depth_source

    pairs = read_half(args.data, args.split, args.max_pairs)
    conf = ExtractConf.from_dict(confs[args.conf])
    source = load_depth_source(DEFAULT_DEPTH_MODEL, num_threads=1)
    solved = solved_pairs(args.records)
    asift = asift_view_set()
    asift_kinds = ["asift"] * len(asift)

    def views(name: str) -> tuple[list, list[str]]:
        cached = args.cache / args.conf / f"{name}.pkl" if args.cache else None
        if cached is not None and cached.exists():
            return pickle.loads(cached.read_bytes())
        out = default_views(*extract_guessed(args.data, name, source, conf))
        if cached is not None:
            cached.parent.mkdir(parents=True, exist_ok=True)
            cached.write_bytes(pickle.dumps(out))
        return out

    rows = []
    for i, pair in enumerate(pairs):
        (v0, k0), (v1, k1) = views(pair.im0), views(pair.im1)
        sets = {
            "plain": (v0[:1], v1[:1], k0, k1),
            "default": (v0, v1, k0, k1),
            "asift": (asift, asift, asift_kinds, asift_kinds),
        }
        row = pair_row(pair, sets, args.grid_step)
        row.update({m: pair.name in names for m, names in solved.items()})
        rows.append(row)
        logger.info("%d/%d %s: %s", i + 1, len(pairs), pair.name, row)
    args.output_dir.mkdir(parents=True, exist_ok=True)
    with open(args.output_dir / "coverage.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    (args.output_dir / "coverage.md").write_text(report(rows, sorted(solved), args))
    logger.info("wrote %s", args.output_dir / "coverage.md")
    return 0


def covered(row: dict, name: str) -> bool:
    """Whether the view set ``name`` covers the pair: its median residual tilt at most
    TAU_MAX."""
    return float(row[f"{name}_tilt"]) <= TAU_MAX


def meeting(row: dict, name: str) -> str:
    """How the view set ``name`` reaches the pair's plane: ``met`` (covered, within
    SCALE_MAX), ``beyond 4x`` (covered only at a larger scale change) or ``not covered``."""
    if not covered(row, name):
        return "not covered"
    return "met" if float(row[f"{name}_scale"]) <= SCALE_MAX else f"beyond {SCALE_MAX:g}x"


def report(rows: list[dict], methods: list[str], args) -> str:
    """coverage.md: pairs covered per view set, half and class; covered x solved."""
    lines = [f"# View coverage: {args.data} {args.split or ''} ({args.conf})", ""]
    lines += [f"A pair is covered where its median residual tilt is <= {TAU_MAX}.", ""]
    halves = sorted({r["split"] for r in rows})
    lines += ["| view set | " + " | ".join(f"covered: {h or 'all'}" for h in halves)]
    lines[-1] += f" | median residual tilt | met within {SCALE_MAX:g}x scale, all |"
    lines += ["|---" * (len(halves) + 3) + "|"]
    for name in VIEW_SETS:
        cells = []
        for h in halves:
            sub = [r for r in rows if r["split"] == h]
            cells.append(f"{sum(covered(r, name) for r in sub)} of {len(sub)}")
        med = np.median([r[f"{name}_tilt"] for r in rows])
        met = sum(meeting(r, name) == "met" for r in rows)
        lines += [f"| {name} | " + " | ".join(cells) + f" | {med:.2f} | {met} |"]
    for cls in CLASSES:
        lines += ["", f"| {cls} | pairs | " + " | ".join(f"{n} covered" for n in VIEW_SETS)]
        lines[-1] += " |"
        lines += ["|---" * (len(VIEW_SETS) + 2) + "|"]
        for value in sorted({r[cls] for r in rows}):
            sub = [r for r in rows if r[cls] == value]
            cells = [str(sum(covered(r, n) for r in sub)) for n in VIEW_SETS]
            lines += [f"| {value} | {len(sub)} | " + " | ".join(cells) + " |"]
    for m in methods:
        views = "asift" if m == "asift" else "default"  # ASIFT's pairs by its own views
        lines += ["", f"## {m}: solved by how the {views} views reach the plane", ""]
        lines += ["| | solved | lost |", "|---|---|---|"]
        for how in ("met", f"beyond {SCALE_MAX:g}x", "not covered"):
            sub = [r for r in rows if meeting(r, views) == how]
            n = sum(r[m] for r in sub)
            lines += [f"| {how} | {n} | {len(sub) - n} |"]
        lost = [r for r in rows if not r[m]]
        if lost:
            lines += ["", "| lost pair | half | default / asift / plain tilt | best views |"]
            lines[-1] += " scale change, default / asift |"
            lines += ["|---" * 5 + "|"]
            for r in lost:
                t = " / ".join(f"{r[f'{n}_tilt']:.2f}" for n in ("default", "asift", "plain"))
                lines += [f"| {r['pair']} | {r['split']} | {t} | {r['default_best']} |"]
                lines[-1] += f" {r['default_scale']:.1f} / {r['asift_scale']:.1f} |"
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    raise SystemExit(run_script(main, "view_coverage"))
