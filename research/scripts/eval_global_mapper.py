#!/usr/bin/env python
"""COLMAP 4's global mapper beside its incremental one, on plain COLMAP SIFT and on ours.

For each Strecha-style scene (``<scene>/images``, ``<scene>/sparse``: the ground-truth
COLMAP text model) and each camera setting (``--cameras``):

- ``gt``: the ground-truth intrinsics as one PINHOLE camera (a prior focal length);
- ``guessed``: COLMAP's default cameras (SIMPLE_RADIAL; without EXIF, as on the Strecha
  photos, the focal length guessed as 1.2 x the larger side and no prior),

the features of every image are extracted once per method:

- ``sift``: COLMAP 4's own extractor (pycolmap.extract_features, CPU, one thread); its
  database's cameras are those of every method;
- ``rectsift``: ``rectified_colmap.extract`` with the default configuration and the
  embedded depth network (another named configuration by its name), into a featureless
  copy of the ``sift`` database (so both have the same cameras);

then matched once (pycolmap.match_exhaustive, one thread). Each subset (``--subsets``,
``START::STEP`` of the name-ordered images; default all, every second, every third) is
mapped from the matched database without the other images, by each mapper of
``--mappers`` (rectified_colmap_research.evaluation.pycolmap_sfm: ``incremental``,
``global``, ``global+calibration``), once per ``--seeds`` value, each with one thread.
Per run: registered images, 3D points, the median relative-rotation error of all pairs of
registered images against the ground truth, and the mapping seconds.

    OMP_NUM_THREADS=1 python research/scripts/eval_global_mapper.py --output_dir OUT

Writes ``OUT/global_mapper.json`` (one row per mapper run) and ``OUT/global_mapper.md``
(the table, means over the seeds; also printed). Features, matches and finished runs are
reused when the command is run again; delete them to redo.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from pathlib import Path

import numpy as np
import pycolmap

from rectified_colmap.errors import run_script
from rectified_colmap_research.evaluation import pycolmap_sfm
from rectified_colmap_research.evaluation.colmap_sfm import (
    copy_database,
    subset_label,
    subset_names,
)

ROOT = Path(__file__).resolve().parents[2]  # the repository
DATA = ROOT.parent / "shared" / "data"
CAMERAS = ("gt", "guessed")


class InputError(ValueError):
    """A missing or bad input (run_script reports it in one line, exit code 2)."""


def find_scenes(root: Path, only: list[str] | None) -> list[Path]:
    if not root.is_dir():
        raise InputError(f"--strecha {root}: no such folder")
    scenes = [
        d for d in sorted(root.iterdir()) if (d / "images").is_dir() and (d / "sparse").is_dir()
    ]
    if only:
        unknown = set(only) - {d.name for d in scenes}
        if unknown:
            raise InputError(f"--sets: no such scene {', '.join(sorted(unknown))}")
        scenes = [d for d in scenes if d.name in only]
    if not scenes:
        raise InputError(f"{root}: no scenes (images/ with sparse/)")
    return scenes


def load_gt(scene: Path) -> pycolmap.Reconstruction:
    gt = pycolmap.Reconstruction()
    gt.read_text(scene / "sparse")
    return gt


def extract(scene: Path, cameras: str, method: str, gt, args, out: Path) -> tuple[Path, float]:
    """The matched database of every image of ``scene`` for ``method`` with ``cameras``
    (made once) and its extraction seconds."""
    work = out / scene.name / cameras / method
    done = work / "matched.json"
    if done.exists():
        return work / "matched.db", json.loads(done.read_text())["extract_s"]
    work.mkdir(parents=True, exist_ok=True)
    features = work / "features.db"
    features.unlink(missing_ok=True)
    if method == "sift":
        cam = next(iter(gt.cameras.values()))
        params = list(cam.params) if cameras == "gt" else None
        model = "PINHOLE" if cameras == "gt" else "SIMPLE_RADIAL"
        seconds = pycolmap_sfm.plain_features(
            features, scene / "images", model, params, args.max_num_features
        )
    else:
        from rectified_colmap import extract as rectified_extract
        from rectified_colmap.config import ExtractConf, confs

        sift_db, _ = extract(scene, cameras, "sift", gt, args, out)
        copy_database(sift_db.parent / "features.db", features)
        pycolmap_sfm.strip_features(features)
        conf = ExtractConf.from_dict(confs[method])
        conf.sift.max_num_features = args.max_num_features
        t0 = time.perf_counter()
        summary = rectified_extract(
            scene / "images",
            database=features,
            conf=conf,
            run={"num_workers": args.num_workers, "progress": False},
        )
        if not summary.ok:
            raise RuntimeError(f"{scene.name} {method}: extraction failed\n{summary.report()}")
        seconds = time.perf_counter() - t0
    matched = work / "matched.db"
    matched.unlink(missing_ok=True)
    copy_database(features, matched)
    match_s = pycolmap_sfm.match(matched)
    done.write_text(json.dumps({"extract_s": seconds, "match_s": match_s}))
    return matched, seconds


def evaluate(scene: Path, cameras: str, spec: str, method: str, gt, args, out: Path) -> list[dict]:
    """Every mapper and seed on one subset with one method's features; rows reused from
    ``rows.json`` for runs already done."""
    matched, extract_s = extract(scene, cameras, method, gt, args, out)
    names = subset_names([p.name for p in (scene / "images").iterdir() if p.is_file()], spec)
    work = out / scene.name / cameras / subset_label(spec).replace(":", "_") / method
    work.mkdir(parents=True, exist_ok=True)
    cache = work / "rows.json"
    done = (
        {(r["mapper"], r["seed"]): r for r in json.loads(cache.read_text())}
        if cache.exists()
        else {}
    )
    db = work / "subset.db"
    if not db.exists():
        pycolmap_sfm.subset_database(matched, names, db)
    rows = []
    for mapper in args.mappers:
        for seed in args.seeds:
            if (mapper, seed) not in done:
                rec, seconds = pycolmap_sfm.map_database(
                    mapper, db, scene / "images", work / f"{mapper}-{seed}", seed
                )
                done[(mapper, seed)] = {
                    "scene": scene.name,
                    "cameras": cameras,
                    "subset": subset_label(spec),
                    "images": len(names),
                    "method": method,
                    "mapper": mapper,
                    "seed": seed,
                    "prior_focal_share": pycolmap_sfm.prior_focal_share(db),
                    "extract_s": extract_s,
                    "map_s": seconds,
                    **pycolmap_sfm.model_row(rec, gt),
                }
                cache.write_text(json.dumps(list(done.values()), indent=1))
            rows.append(done[(mapper, seed)])
    return rows


# -- the table ----------------------------------------------------------------------------


def summarize(rows: list[dict]) -> list[dict]:
    """One row per scene, cameras, subset, method and mapper (in the order met): means over
    the seeds, registered images also as min-max."""
    groups: dict[tuple, list[dict]] = {}
    for r in rows:
        groups.setdefault(
            (r["scene"], r["cameras"], r["subset"], r["method"], r["mapper"]), []
        ).append(r)
    out = []
    for key, rs in groups.items():
        s = dict(zip(("scene", "cameras", "subset", "method", "mapper"), key))
        reg = [r["registered"] for r in rs]
        s.update(images=rs[0]["images"], runs=len(rs), registered=float(np.mean(reg)))
        s.update(registered_min=min(reg), registered_max=max(reg))
        for k in ("points", "map_s", "rot_err_med_deg"):
            v = [r[k] for r in rs if not np.isnan(r[k])]
            s[k] = float(np.mean(v)) if v else float("nan")
        out.append(s)
    return out


def _registered(s: dict) -> str:
    reg = f"{s['registered']:.3g}"
    if s["registered_min"] != s["registered_max"]:
        reg += f" ({s['registered_min']}-{s['registered_max']})"
    return f"{reg}/{s['images']}"


def markdown(summary: list[dict]) -> str:
    """The table of :func:`summarize`'s rows, then per camera setting, method and mapper
    the totals, and the (scene, subset) where a global mapper registered fewer images than
    the incremental one with the same features (mean over the seeds)."""
    cols = ["scene", "cameras", "subset", "features", "mapper", "registered", "3D points"]
    cols += ["rot. err. med (deg)", "mapping (s)"]
    lines = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    last = None
    for s in summary:
        head = (s["scene"], s["cameras"], s["subset"])
        cells = list(head) if head != last else ["", "", ""]
        last = head
        rot = "-" if np.isnan(s["rot_err_med_deg"]) else f"{s['rot_err_med_deg']:.2f}"
        cells += [s["method"], s["mapper"], _registered(s), f"{s['points']:.0f}", rot]
        cells.append(f"{s['map_s']:.1f}")
        lines.append("| " + " | ".join(cells) + " |")
    lines.append("")
    totals: dict[tuple, list[dict]] = {}
    for s in summary:
        totals.setdefault((s["cameras"], s["method"], s["mapper"]), []).append(s)
    lines.append(
        "| cameras | features | mapper | registered (sum) | 3D points (sum) | mapping (s, sum) |"
    )
    lines.append("|---|---|---|---|---|---|")
    for (cameras, method, mapper), ss in totals.items():
        reg = sum(s["registered"] for s in ss)
        total = sum(s["images"] for s in ss)
        pts = sum(s["points"] for s in ss)
        secs = sum(s["map_s"] for s in ss)
        lines.append(
            f"| {cameras} | {method} | {mapper} | {reg:.4g}/{total} | {pts:.0f} | {secs:.1f} |"
        )
    fewer = fewer_than_incremental(summary)
    lines.append("")
    lines.append(
        "global registered fewer images than incremental: "
        + ("; ".join(fewer) if fewer else "nowhere")
    )
    return "\n".join(lines) + "\n"


def fewer_than_incremental(summary: list[dict]) -> list[str]:
    """'scene cameras subset method mapper: a < b' wherever a global mapper registered fewer
    images (mean over the seeds) than the incremental mapper on the same database."""
    inc = {
        (s["scene"], s["cameras"], s["subset"], s["method"]): s["registered"]
        for s in summary
        if s["mapper"] == "incremental"
    }
    out = []
    for s in summary:
        key = (s["scene"], s["cameras"], s["subset"], s["method"])
        if s["mapper"] != "incremental" and key in inc and s["registered"] < inc[key]:
            out.append(f"{' '.join(key)} {s['mapper']}: {s['registered']:.3g} < {inc[key]:g}")
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--output_dir", "--output_path", type=Path, required=True)
    p.add_argument("--strecha", type=Path, default=DATA / "strecha-dev", help="folder of scenes")
    p.add_argument("--sets", nargs="+", help="only these scenes (folder names)")
    p.add_argument("--subsets", nargs="+", default=["0::1", "0::2", "0::3"])
    p.add_argument("--cameras", nargs="+", choices=CAMERAS, default=list(CAMERAS))
    p.add_argument("--methods", nargs="+", default=["sift", "rectsift"])
    p.add_argument(
        "--mappers", nargs="+", choices=pycolmap_sfm.MAPPERS, default=list(pycolmap_sfm.MAPPERS)
    )
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    p.add_argument("--max_num_features", type=int, default=8192)
    p.add_argument("--num_workers", type=int, default=1, help="rectified-colmap workers")
    args = p.parse_args(argv)
    from rectified_colmap.config import confs
    from rectified_colmap_research.evaluation.colmap_sfm import parse_subset

    for m in args.methods:
        if m != "sift" and m not in confs:
            p.error(f"--methods {m}: expected sift or a named configuration ({', '.join(confs)})")
    for spec in args.subsets:
        try:
            parse_subset(spec)
        except ValueError as e:
            p.error(str(e))
    scenes = find_scenes(args.strecha, args.sets)
    logging.basicConfig(level=logging.WARNING)
    pycolmap.logging.minloglevel = 2  # COLMAP's INFO and WARNING lines (one per step)
    args.output_dir.mkdir(parents=True, exist_ok=True)
    rows = []
    for scene in scenes:
        gt = load_gt(scene)
        for cameras in args.cameras:
            for method in args.methods:
                for spec in args.subsets:
                    rs = evaluate(scene, cameras, spec, method, gt, args, args.output_dir)
                    rows += rs
                    for r in rs[:: len(args.seeds)]:
                        print(
                            f"{scene.name} {cameras} {r['subset']} {method} {r['mapper']}: "
                            f"{r['registered']}/{r['images']} images, {r['points']} points, "
                            f"{r['map_s']:.1f} s",
                            file=sys.stderr,
                            flush=True,
                        )
                    (args.output_dir / "global_mapper.json").write_text(json.dumps(rows, indent=1))
    table = markdown(summarize(rows))
    (args.output_dir / "global_mapper.md").write_text(table)
    print(table)
    return 0


if __name__ == "__main__":
    sys.exit(run_script(main, "eval_global_mapper"))
