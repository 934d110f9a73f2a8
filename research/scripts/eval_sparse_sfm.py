#!/usr/bin/env python
"""Sparse-view structure from motion with COLMAP 3.8: plain COLMAP SIFT beside rectified SIFT.

The benchmark runs on two kinds of set:

- each Strecha-style scene (``<scene>/images``, ``<scene>/sparse``: the ground-truth
  COLMAP text model). It runs on all images and on sparser subsets of the name-ordered
  images (``--subsets``; default ``0::1 0::2 1::2 0::3``: all, every second image from the
  first and from the second, every third);
- each real-pool set with a ``colmap_sparse`` model (a pycolmap SfM result, *not* ground
  truth: the reference poses). It runs on all images, and with ``--real_subsets`` (default
  every second image) for sets of at least ``--real_subset_min_images`` images.

For each set and method the features are extracted once, for all the set's images:

- ``sift``: ``colmap feature_extractor`` (CPU). Its database's cameras are those of every
  method: Strecha gets the ground-truth intrinsics as one PINHOLE camera; a real-pool set
  gets COLMAP's defaults (one SIMPLE_RADIAL camera per image, focal length from EXIF or
  1.2 x the larger side), or what ``--ImageReader.*`` flags ask for (e.g.
  ``--ImageReader.single_camera 1``). A rectified method's database is a copy of it without the
  features, so ``rectified-colmap extract`` keeps those cameras (the same for both);
- ``rectsift``: ``rectified-colmap extract`` with the default configuration; any other
  named configuration by its name, and ``--variant NAME=JSON|CONF``.

Each subset's database is the set's database with only the subset's images. Then
``colmap exhaustive_matcher`` and ``colmap mapper`` (CPU, one mapper thread,
``--Mapper.min_model_size 3`` unless given, other ``--Mapper.*`` flags passed on; once per
``--seeds`` value, passed as ``--random_seed``: COLMAP's mapper still varies between runs,
and the matcher, run once per subset, too). Per subset, method and mapper run, of the
mapper's largest model: registered images, 3D points, verified matches and pairs, the median
relative-rotation error of all pairs of registered images (no alignment), and the rotation
and position errors of the registered cameras after a similarity alignment to the
reference (:func:`pose_errors`; positions relative to the spread of the subset's reference
camera centres).

    python scripts/eval_sparse_sfm.py --output_dir OUT --num_workers 1

Writes ``OUT/sparse_sfm.json`` and ``OUT/sparse_sfm.csv`` (one row per mapper run) and
``OUT/sparse_sfm.md`` (the table, means over the runs; also printed). Extracted features
(``OUT/<set>/<method>/features.db``) and finished subsets (``rows.json``) are reused when
the command is run again; delete them to redo.
"""

from __future__ import annotations

import argparse
import csv
import json
import shutil
import sys
from pathlib import Path
from typing import NamedTuple

import numpy as np

from rectified_colmap_research.evaluation.methods import add_variant_argument
from rectified_colmap_research.evaluation.colmap_sfm import (
    best_model,
    conf_args,
    connect,
    copy_database,
    match_and_map,
    model_stats,
    parse_methods,
    parse_subset,
    pinhole_camera_args,
    rectified_command,
    rotation_errors,
    run,
    sift_command,
    subset_label,
    subset_names,
    verified_matches,
)

from rectified_colmap.errors import run_script

ROOT = Path(__file__).resolve().parents[2]  # the repository
DATA = ROOT.parent / "shared" / "data"


class InputError(ValueError):
    """A missing or bad input (run_script reports it in one line, exit code 2)."""


class SceneSet(NamedTuple):
    """One set of the benchmark: its images, reference model and how cameras are made."""

    name: str
    images: Path
    reference: Path
    ground_truth: bool  # False: an SfM result used as the reference
    subsets: list[str]
    camera: tuple[str, ...] = ()  # --ImageReader flags of both methods


# -- pose errors --------------------------------------------------------------------------


def rotation_angles_deg(R: np.ndarray) -> np.ndarray:
    """Angles (degrees) of rotation matrices (..., 3, 3)."""
    c = (np.trace(R, axis1=-2, axis2=-1) - 1.0) / 2.0
    return np.degrees(np.arccos(np.clip(c, -1.0, 1.0)))


def align(
    R_est: np.ndarray, c_est: np.ndarray, R_ref: np.ndarray, c_ref: np.ndarray
) -> tuple[float, np.ndarray, np.ndarray]:
    """The similarity ``x_ref = s R x_est + t`` from the estimated to the reference world:
    R the chordal mean of the per-camera world rotations ``R_ref_i^T R_est_i``, s and t the
    least-squares fit of the camera centres given R (s is NaN for a single camera).

    Rotations from the orientations, not Umeyama on the centres: defined for two cameras and
    for centres on a line (a walk down a street), and a frame that the centres tilt does not
    turn into a rotation error of every camera (British Museum: every camera 2.3-2.8 degrees
    off after Umeyama, 0.02-0.9 so, with relative rotations within 0.3 degrees)."""
    U, _, Vt = np.linalg.svd(np.einsum("nji,njk->ik", R_ref, R_est))
    R = U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))]) @ Vt
    mu_s, mu_d = c_est.mean(0), c_ref.mean(0)
    x, y = (c_est - mu_s) @ R.T, c_ref - mu_d
    den = (x**2).sum()
    s = float((x * y).sum() / den) if den > 0 else float("nan")
    return s, R, mu_d - s * R @ mu_s


def pose_errors(
    R_est: np.ndarray, c_est: np.ndarray, R_ref: np.ndarray, c_ref: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Per camera, after :func:`align`: the rotation error (degrees) and the position error
    (in the reference's units) of estimated cam_from_world rotations ``R_est`` (n, 3, 3) and
    centres ``c_est`` (n, 3) against the reference's."""
    s, R, t = align(R_est, c_est, R_ref, c_ref)
    rot = rotation_angles_deg(R_est @ R.T @ np.transpose(R_ref, (0, 2, 1)))
    pos = np.linalg.norm(s * c_est @ R.T + t - c_ref, axis=1)
    return rot, pos


def centre_spread(c: np.ndarray) -> float:
    """RMS distance of camera centres (n, 3) from their centroid."""
    return float(np.sqrt(((c - c.mean(0)) ** 2).sum(1).mean()))


def camera_poses(rec, names: list[str]) -> tuple[np.ndarray, np.ndarray]:
    """cam_from_world rotations (n, 3, 3) and centres (n, 3) of the images ``names`` of a
    pycolmap Reconstruction."""
    by_name = {im.name: im for im in rec.images.values()}
    ims = [by_name[n] for n in names]
    R = np.array([im.cam_from_world().rotation.matrix() for im in ims]).reshape(-1, 3, 3)
    c = np.array([im.projection_center() for im in ims]).reshape(-1, 3)
    return R, c


def nearest_neighbour_deg(R: np.ndarray) -> float:
    """Median over cameras of the rotation angle to the nearest other camera."""
    if len(R) < 2:
        return float("nan")
    ang = rotation_angles_deg(np.einsum("aij,bkj->abik", R, R))
    np.fill_diagonal(ang, np.inf)
    return float(np.median(ang.min(1)))


# -- databases ----------------------------------------------------------------------------


def keep_images(db: Path, names: list[str]) -> None:
    """Delete from a COLMAP database every image not in ``names`` with its features and
    matches, and the cameras no image uses any more."""
    with connect(db) as con:
        ids = dict(con.execute("SELECT name, image_id FROM images"))
        keep = set(names)
        drop = [(i,) for n, i in ids.items() if n not in keep]
        tables = {r[0] for r in con.execute("SELECT name FROM sqlite_master WHERE type='table'")}
        for table in ("images", "keypoints", "descriptors", "rectified_colmap_features"):
            if table in tables:
                con.executemany(f"DELETE FROM {table} WHERE image_id = ?", drop)
        con.execute("DELETE FROM matches")
        con.execute("DELETE FROM two_view_geometries")
        con.execute("DELETE FROM cameras WHERE camera_id NOT IN (SELECT camera_id FROM images)")


def strip_features(db: Path) -> None:
    """Delete every image's features and matches (keeps cameras and images)."""
    with connect(db) as con:
        for table in ("keypoints", "descriptors", "matches", "two_view_geometries"):
            con.execute(f"DELETE FROM {table}")


def extract_set(scene: SceneSet, method: str, spec, args, out: Path) -> Path:
    """The features of every image of ``scene`` for ``method``, once (reused when done):
    ``out/<set>/<method>/features.db``. Rectified methods start from a featureless copy of
    the ``sift`` database, so that every method has the same cameras. Features made with
    other camera flags are made again."""
    work = out / scene.name / method
    db, done = work / "features.db", work / "features.done"
    if done.exists() and json.loads(done.read_text()).get("camera", []) == list(scene.camera):
        return db
    if work.exists():
        shutil.rmtree(work)
    work.mkdir(parents=True)
    log = work / "log.txt"
    if method == "sift":
        t = run(sift_command(db, scene.images, args.max_num_features, scene.camera), log)
    else:
        copy_database(extract_set(scene, "sift", None, args, out), db)
        strip_features(db)
        cmd = rectified_command(
            db, scene.images, args.max_num_features, args.num_workers, conf_args(spec, work)
        )
        t = run(cmd, log)
    done.write_text(json.dumps({"extract_s": t, "camera": list(scene.camera)}))
    return db


# -- one subset ---------------------------------------------------------------------------


def evaluate_subset(
    scene: SceneSet, spec: str, method: str, features_db: Path, ref, args, out: Path
) -> list[dict]:
    """Match and map one subset with one method's features, once per seed; a row per run.
    Reuses what ``rows.json`` says was done with the same camera flags: the matched
    database (only the mapper runs again when the seeds or --Mapper flags differ), or also
    the models (same seeds and flags), which are scored again without running COLMAP."""
    names = subset_names([p.name for p in scene.images.iterdir() if p.is_file()], spec)
    work = out / scene.name / subset_label(spec).replace(":", "_") / method
    db, log, cached = work / "database.db", work / "log.txt", work / "rows.json"
    done = json.loads(cached.read_text()) if cached.exists() else []
    flags, camera = " ".join(args.mapper), " ".join(scene.camera)
    # rows from before camera_flags was recorded had the default cameras
    matched = bool(done) and all(r.get("camera_flags", camera) == camera for r in done)
    runs = [(r["seed"], r.get("mapper_flags", "")) for r in done]
    mapped = matched and runs == [(seed, flags) for seed in args.seeds]
    match_s = done[0]["match_s"] if matched else None
    if not matched:
        if work.exists():
            shutil.rmtree(work)
        work.mkdir(parents=True)
        copy_database(features_db, db)
        keep_images(db, names)
    elif not mapped:
        cached.unlink()
        for d in work.glob("sparse-*"):
            shutil.rmtree(d)
    ref_names = [n for n in names if n in {im.name for im in ref.images.values()}]
    R_ref_all, c_ref_all = camera_poses(ref, ref_names)
    base = {
        "set": scene.name,
        "subset": subset_label(spec),
        "reference": "GT" if scene.ground_truth else "SfM",
        "method": method,
        "images": len(names),
        "ref_images": len(ref_names),
        "neighbour_deg": nearest_neighbour_deg(R_ref_all),
        "extract_s": json.loads((features_db.parent / "features.done").read_text())["extract_s"],
    }
    rows = []
    for i, seed in enumerate(args.seeds):
        sparse = work / f"sparse-{i}"
        if mapped:
            times = {k: done[i][k] for k in ("match_s", "map_s")}
        else:
            mapper = ["--random_seed", str(seed), *mapper_command_flags(args.mapper)]
            match = match_s is None
            t_match, t_map = match_and_map(db, scene.images, sparse, log, mapper, match=match)
            match_s = t_match if match else match_s
            times = {"match_s": match_s, "map_s": t_map}
        matches, pairs = verified_matches(db)
        rec = best_model(sparse)
        row = {**base, "run": i, "seed": seed, "mapper_flags": flags, "camera_flags": camera}
        row.update(times)
        row.update(verified_matches=matches, verified_pairs=pairs, **model_stats(rec))
        row["models"] = sum(d.is_dir() for d in sparse.iterdir())
        row.update(registered_errors(rec, ref, ref_names, centre_spread(c_ref_all)))
        rows.append(row)
    cached.write_text(json.dumps(rows, indent=1))
    return rows


def registered_errors(rec, ref, ref_names: list[str], spread: float) -> dict:
    """Error statistics of the registered cameras of ``rec`` that the reference has:
    median relative-rotation error, median / max rotation error and median / max position
    error (relative to ``spread``; the median also in the reference's units)."""
    nan = float("nan")
    out = {
        "rel_rot_err_med_deg": nan,
        "rot_err_med_deg": nan,
        "rot_err_max_deg": nan,
        "pos_err_med": nan,
        "pos_err_max": nan,
        "pos_err_med_ref_units": nan,
    }
    if rec is None:
        return out
    reg = {im.name for im in rec.images.values() if im.has_pose}
    common = [n for n in ref_names if n in reg]
    if len(common) < 2:
        return out
    rel = rotation_errors(rec, ref)
    rot, pos = pose_errors(*camera_poses(rec, common), *camera_poses(ref, common))
    out.update(
        rel_rot_err_med_deg=float(np.median(rel)),
        rot_err_med_deg=float(np.median(rot)),
        rot_err_max_deg=float(rot.max()),
        pos_err_med=float(np.median(pos) / spread),
        pos_err_max=float(pos.max() / spread),
        pos_err_med_ref_units=float(np.median(pos)),
    )
    return out


# -- the table ----------------------------------------------------------------------------


def summarize(rows: list[dict]) -> list[dict]:
    """One row per set, subset and method: the means over its mapper runs (registered
    images also as min-max); sets, subsets and methods in the order met, methods within
    each subset."""
    groups: dict[tuple, list[dict]] = {}
    for r in rows:
        groups.setdefault((r["set"], r["subset"], r["method"]), []).append(r)
    order = {}
    for i in range(3):
        order[i] = {v: j for j, v in enumerate(dict.fromkeys(key[i] for key in groups))}
    out = []
    for key in sorted(groups, key=lambda key: tuple(order[i][v] for i, v in enumerate(key))):
        rs = groups[key]
        s = {k: rs[0][k] for k in ("set", "subset", "reference", "method", "images")}
        s.update(neighbour_deg=rs[0]["neighbour_deg"], runs=len(rs))
        s["verified_matches"] = rs[0]["verified_matches"]
        s["verified_pairs"] = rs[0]["verified_pairs"]
        reg = [r["registered"] for r in rs]
        s.update(registered=float(np.mean(reg)), registered_min=min(reg), registered_max=max(reg))
        for k in (
            "points",
            "models",
            "rel_rot_err_med_deg",
            "rot_err_med_deg",
            "rot_err_max_deg",
            "pos_err_med",
            "pos_err_max",
        ):
            v = [r[k] for r in rs if not np.isnan(r[k])]
            s[k] = float(np.mean(v)) if v else float("nan")
        out.append(s)
    return out


def _num(v: float, fmt: str) -> str:
    return "-" if np.isnan(v) else format(v, fmt)


def _registered(s: dict) -> str:
    reg = f"{s['registered']:g}"
    if s["registered_min"] != s["registered_max"]:
        reg += f" ({s['registered_min']}-{s['registered_max']})"
    return f"{reg}/{s['images']}"


def _vs(v: float, base: float | None) -> str:
    return "" if not base else f" ({(v - base) / base:+.1%})"


def markdown(summary: list[dict]) -> str:
    """The table of :func:`summarize`'s rows: per set and subset the first method's row,
    then the others with their 3D points and verified matches relative to it; a total row
    per method (registered images and 3D points summed)."""
    cols = [
        "set (reference)",
        "subset",
        "nearest view (deg)",
        "method",
        "registered",
        "models",
        "3D points",
        "verified matches",
        "verified pairs",
        "rel. rotation err. med (deg)",
        "rotation err. med / max (deg)",
        "position err. med / max (% of spread)",
    ]
    lines = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    first: dict[tuple, dict] = {}
    for s in summary:
        key = (s["set"], s["subset"])
        base = first.setdefault(key, s)
        own = base is s
        cells = [
            f"{s['set']} ({s['reference']})" if own else "",
            s["subset"] if own else "",
            _num(s["neighbour_deg"], ".1f") if own else "",
            s["method"],
            _registered(s),
            f"{s['models']:g}",
            f"{s['points']:.0f}" + ("" if own else _vs(s["points"], base["points"])),
            f"{s['verified_matches']}"
            + ("" if own else _vs(s["verified_matches"], base["verified_matches"])),
            str(s["verified_pairs"]),
            _num(s["rel_rot_err_med_deg"], ".2f"),
            f"{_num(s['rot_err_med_deg'], '.2f')} / {_num(s['rot_err_max_deg'], '.2f')}",
            f"{_num(100 * s['pos_err_med'], '.2f')} / {_num(100 * s['pos_err_max'], '.2f')}",
        ]
        lines.append("| " + " | ".join(cells) + " |")
    for m in dict.fromkeys(s["method"] for s in summary):
        ss = [s for s in summary if s["method"] == m]
        reg = sum(s["registered"] for s in ss)
        total = sum(s["images"] for s in ss)
        pts = sum(s["points"] for s in ss)
        cells = ["**total**", f"{len(ss)} subsets", "", m, f"{reg:g}/{total}", "", f"{pts:.0f}"]
        lines.append("| " + " | ".join(cells + [""] * (len(cols) - len(cells))) + " |")
    return "\n".join(lines) + "\n"


def write_csv(rows: list[dict], path: Path) -> None:
    keys = list(dict.fromkeys(k for r in rows for k in r))
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, keys)
        w.writeheader()
        w.writerows(rows)


# -- the sets -----------------------------------------------------------------------------


def _folder(path: Path, what: str) -> Path:
    if not path.is_dir():
        raise InputError(f"{what} {path}: no such folder")
    return path


def find_sets(args) -> list[SceneSet]:
    """The Strecha scenes and real-pool sets of the command line, with their subsets."""
    import pycolmap

    sets = []
    if args.strecha != "none":
        root = _folder(Path(args.strecha), "--strecha")
        for d in sorted(root.iterdir()):
            if (d / "images").is_dir() and (d / "sparse").is_dir():
                gt = pycolmap.Reconstruction()
                gt.read_text(d / "sparse")
                camera = pinhole_camera_args(gt)
                sets.append(
                    SceneSet(d.name, d / "images", d / "sparse", True, args.subsets, camera)
                )
    if args.real_pool != "none":
        root = _folder(Path(args.real_pool), "--real_pool")
        for d in sorted(root.iterdir()):
            if (d / "images").is_dir() and (d / "colmap_sparse").is_dir():
                n = sum(p.is_file() for p in (d / "images").iterdir())
                subsets = ["0::1"] + (args.real_subsets if n >= args.real_subset_min_images else [])
                sets.append(
                    SceneSet(d.name, d / "images", d / "colmap_sparse", False, subsets, args.reader)
                )
    if args.sets:
        unknown = set(args.sets) - {s.name for s in sets}
        if unknown:
            raise InputError(f"--sets: no such set {', '.join(sorted(unknown))}")
        sets = [s for s in sets if s.name in args.sets]
    if not sets:
        raise InputError("no sets found (images/ with sparse/ or colmap_sparse/)")
    return sets


def load_reference(scene: SceneSet):
    import pycolmap

    rec = pycolmap.Reconstruction()
    rec.read_text(scene.reference)
    return rec


def mapper_command_flags(flags: list[str]) -> list[str]:
    """``colmap mapper`` flags: ``--Mapper.min_model_size 3`` unless ``flags`` set it, then
    ``flags``."""
    default = [] if "--Mapper.min_model_size" in flags else ["--Mapper.min_model_size", "3"]
    return default + flags


def colmap_flags(extra: list[str], groups=("Mapper", "ImageReader")) -> dict[str, list[str]]:
    """The command line's other words as COLMAP flags per group: ``--GROUP.NAME VALUE``
    pairs (or ``--GROUP.NAME=VALUE``), e.g. ``--Mapper.ba_refine_focal_length 0``.
    Raises ValueError for anything else."""
    out, i = {g: [] for g in groups}, 0
    while i < len(extra):
        flag, sep, value = extra[i].partition("=")
        group = flag[2:].partition(".")[0] if flag.startswith("--") else ""
        if group not in out or "." not in flag:
            raise ValueError(f"unrecognized argument {extra[i]!r}")
        if not sep:
            if i + 1 >= len(extra) or extra[i + 1].startswith("--"):
                raise ValueError(f"{flag}: expected a value")
            value, i = extra[i + 1], i + 1
        out[group] += [flag, value]
        i += 1
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(
        description=__doc__.split("\n")[0],
        epilog="COLMAP options pass through: --Mapper.NAME VALUE to colmap mapper, "
        "--ImageReader.NAME VALUE to the cameras of the real-pool sets (e.g. "
        "--ImageReader.single_camera 1; Strecha always has its ground-truth camera). "
        "--Mapper.min_model_size is 3 unless given.",
    )
    p.add_argument("--output_dir", "--output_path", type=Path, required=True)
    p.add_argument(
        "--strecha", default=str(DATA / "strecha-dev"), help="folder of Strecha scenes, or none"
    )
    p.add_argument("--real_pool", default=str(DATA / "real-pool"), help="real-pool folder, or none")
    p.add_argument("--sets", nargs="+", help="only these sets (folder names)")
    p.add_argument("--subsets", nargs="+", default=["0::1", "0::2", "1::2", "0::3"])
    p.add_argument("--real_subsets", nargs="+", default=["0::2"])
    p.add_argument("--real_subset_min_images", type=int, default=11)
    p.add_argument(
        "--methods",
        nargs="+",
        default=["sift", "rectsift"],
        help="sift (colmap feature_extractor), rectsift (the default configuration) or "
        "another named configuration of rectified-colmap",
    )
    add_variant_argument(p)
    p.add_argument(
        "--max_num_features", "--SiftExtraction.max_num_features", type=int, default=8192
    )
    p.add_argument(
        "--seeds", type=int, nargs="+", default=[0], help="one mapper run per value (repeats ok)"
    )
    p.add_argument("--num_workers", type=int, default=1, help="rectified-colmap workers")
    args, extra = p.parse_known_args(argv)
    try:
        flags = colmap_flags(extra)
        args.mapper, args.reader = flags["Mapper"], flags["ImageReader"]
        for spec in args.subsets + args.real_subsets:
            parse_subset(spec)
        methods = parse_methods(args.methods, args.variant)
    except ValueError as e:
        p.error(str(e))
    sets = find_sets(args)
    if shutil.which("colmap") is None:
        raise InputError("the colmap executable is needed (e.g. apt-get install colmap)")
    args.output_dir.mkdir(parents=True, exist_ok=True)
    rows = []
    for scene in sets:
        ref = load_reference(scene)
        for method, spec in methods.items():
            features = extract_set(scene, method, spec, args, args.output_dir)
            for subset in scene.subsets:
                rs = evaluate_subset(scene, subset, method, features, ref, args, args.output_dir)
                rows += rs
                r = rs[-1]
                print(
                    f"{scene.name} {r['subset']} {method}: {r['registered']}/{r['images']} "
                    f"images, {r['points']} points, {r['verified_matches']} verified matches",
                    file=sys.stderr,
                    flush=True,
                )
            (args.output_dir / "sparse_sfm.json").write_text(json.dumps(rows, indent=1))
    write_csv(rows, args.output_dir / "sparse_sfm.csv")
    table = markdown(summarize(rows))
    (args.output_dir / "sparse_sfm.md").write_text(table)
    print(table)
    return 0


if __name__ == "__main__":
    sys.exit(run_script(main, "eval_sparse_sfm"))
