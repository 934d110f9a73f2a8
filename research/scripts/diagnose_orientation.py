#!/usr/bin/env python
"""How far off are the plane orientations the pipeline gets from the network and from the
lines? Per image of a homography pair file with true normals (the generated extreme pairs of
build_extreme_pairs.py; ``--split`` keeps one half), by the view's in-plane rotation (roll)
and tilt (issue 41, item 3: the orientation error the estimators actually make).

For each image, with its true camera (``--cameras true``: the error of the estimators alone,
not of a guessed focal length; ``guessed`` compares normals in the guessed camera's frame
with the true ones, so the focal length's error is in the number), the smallest angle
between the true plane normal and the normal of a patch that lies on the plane (at least
``MIN_INSIDE`` of its work cells in the pair's region):

- ``network``: the depth network's plane patches (rectified_colmap.planes);
- ``lines``: every patch after the vanishing points (the network's patches oriented by
  them, plus the plane hypotheses from pairs of vanishing points): what the views use;
- ``hypotheses``: the plane hypotheses alone;
- ``upright``: the network's patches when the network sees the image turned by the multiple
  of 90 degrees nearest its roll, so that its content is upright (the network was trained
  on upright photos), the depth turned back.

Writes ``orientation.md`` (median error and the share under 10 degrees, per roll class and
tilt bin) and ``orientation.csv``.

    python research/scripts/diagnose_orientation.py --data ../outputs/extreme-pairs \\
        --split choose --output_dir outputs/orientation
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

import cv2
import numpy as np

from rectified_colmap.config import DEFAULT_DEPTH_MODEL, ExtractConf
from rectified_colmap.conventions import pixel_centers
from rectified_colmap.depth import DepthMap
from rectified_colmap.errors import run_script
from rectified_colmap.eval.homography import points_in_region
from rectified_colmap.geometry import line_angle_deg
from rectified_colmap.io.images import read_image
from rectified_colmap.planes import HYPOTHESIS_AXIS, Patch
from rectified_colmap.pipeline import image_planes, with_vanishing_points
from rectified_colmap_research.evaluation.homography_report import write_records_csv
from rectified_colmap_research.evaluation.extreme_pairs import (
    pinhole_camera,
    read_half,
    rotation_class,
)

logger = logging.getLogger("diagnose_orientation")
MIN_INSIDE = 0.2
"""A patch is on the plane when at least this share of its work cells lies in the region."""
SOURCES = ("network", "lines", "hypotheses", "upright")
TILT_BINS = ((0.0, 45.0, "<45"), (45.0, 70.0, "45-70"), (70.0, 90.0, ">=70"))


def region_mask(region: list[np.ndarray], image_size: tuple[int, int], shape: tuple[int, int]):
    """(h, w) bool work-grid cells whose centre lies in ``region`` (polygons of COLMAP
    pixels of an image of ``image_size`` (W, H))."""
    h, w = shape
    centres = pixel_centers(w, h, *image_size).reshape(-1, 2)
    return points_in_region(centres, region).reshape(h, w)


def best_patch_error(patches: list[Patch], on_plane: np.ndarray, normal: np.ndarray) -> float:
    """Smallest angle (degrees, sign-free) between ``normal`` (3,) and the normal of a patch
    with at least MIN_INSIDE of its cells in ``on_plane`` (h, w) bool; NaN if none is."""
    n = np.asarray(normal, float) / np.linalg.norm(normal)
    errors = [
        float(line_angle_deg(p.normal / np.linalg.norm(p.normal), n))
        for p in patches
        if p.mask.any() and (p.mask & on_plane).sum() >= MIN_INSIDE * p.mask.sum()
    ]
    return float(min(errors)) if errors else float("nan")


def upright_turns(roll_deg: float) -> int:
    """k for np.rot90(image, k) (k quarter turns counter-clockwise on the screen) that turns
    a view rolled by ``roll_deg`` back upright, to the nearest multiple of 90 degrees. The
    camera's roll is from x towards y (extreme_pairs.roll_matrix), so the view's content is
    turned counter-clockwise by it on the screen (the pair files' H from a view rolled by 90
    degrees to one rolled by 0 turns by +90, clockwise), and k = -round(roll / 90)."""
    return (-int(round(roll_deg / 90.0))) % 4


def image_errors(rgb, camera, normal, region, roll_deg, network, conf) -> dict[str, float]:
    """The four errors of the module docstring for one image, and two counts that need no
    ground truth (``num_hypotheses``, ``num_turned_by_lines``: whether the lines gave the
    image any orientation of their own)."""
    gray = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
    rng = np.random.default_rng(0)
    depth = network(rgb, camera)
    planes, _ = image_planes(camera, depth, conf, rng, {})
    on_plane = region_mask(region, (camera.width, camera.height), planes.labels.shape)
    out = {"network": best_patch_error(planes.patches, on_plane, normal)}
    lined = with_vanishing_points(gray, camera, planes, conf, rng, {})
    out["lines"] = best_patch_error(lined.patches, on_plane, normal)
    hyps = [p for p in lined.patches if p.axis == HYPOTHESIS_AXIS]
    out["hypotheses"] = best_patch_error(hyps, on_plane, normal)
    # what the image itself shows, without the true plane: how many plane hypotheses the
    # lines gave, how many of the network's patches they turned by more than a degree
    out["num_hypotheses"] = len(hyps)
    turned = [
        line_angle_deg(a.normal, b.normal) > 1.0 for a, b in zip(planes.patches, lined.patches)
    ]
    out["num_turned_by_lines"] = int(sum(turned))
    k = upright_turns(roll_deg)
    if k == 0:
        out["upright"] = out["network"]
    else:
        turned = network(np.ascontiguousarray(np.rot90(rgb, k)), None)
        back = np.ascontiguousarray(np.rot90(turned.values, -k))
        h, w = depth.values.shape
        back = cv2.resize(back, (w, h), interpolation=cv2.INTER_LINEAR)
        up, _ = image_planes(camera, DepthMap(back, turned.kind), conf, rng, {})
        out["upright"] = best_patch_error(up.patches, on_plane, normal)
    return out


def summary_markdown(rows: list[dict]) -> str:
    """Median error and share under 10 degrees per source, by roll class and tilt bin."""
    groups = [("all", rows)]
    for c in ("0", "90", "180", "other"):
        groups.append((f"roll {c}", [r for r in rows if r["roll_class"] == c]))
    for lo, hi, name in TILT_BINS:
        groups.append((f"tilt {name} deg", [r for r in rows if lo <= r["tilt_deg"] < hi]))
    head = " | ".join(f"{s}: median / < 10 deg" for s in SOURCES)
    lines = [f"| images | n | {head} |", "|---|---|" + "---|" * len(SOURCES)]
    for name, sel in groups:
        if not sel:
            continue
        cells = []
        for s in SOURCES:
            v = np.array([r[s] for r in sel], float)
            v = v[np.isfinite(v)]
            cells.append(f"{np.median(v):.1f} / {100 * np.mean(v < 10):.0f} %" if len(v) else "-")
        lines.append(f"| {name} | {len(sel)} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--data", type=Path, required=True, help="folder with pairs.json, images/")
    p.add_argument("--output_dir", type=Path, required=True)
    p.add_argument("--split", default=None, help="only the pairs of this half (e.g. choose)")
    p.add_argument("--cameras", choices=("true", "guessed"), default="true")
    p.add_argument("--depth_model", default=DEFAULT_DEPTH_MODEL)
    p.add_argument("--max_pairs", type=int, default=None)
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="[%(asctime)s %(name)s] %(message)s")
    cv2.setNumThreads(1)
    pairs = read_half(args.data, args.split, args.max_pairs)
    from rectified_colmap.depth.registry import load_depth_source

    network = load_depth_source(args.depth_model, num_threads=1)
    conf = ExtractConf()
    rows = []
    for q in pairs:
        for k, name in enumerate((q.im0, q.im1)):
            rgb = read_image(args.data / name)
            size = (rgb.shape[1], rgb.shape[0])
            focal = 1.2 * max(size) if args.cameras == "guessed" else float(q.info[f"focal{k}"])
            roll = float(q.info[f"rotation{k}_deg"])
            errors = image_errors(
                rgb,
                pinhole_camera(focal, size),
                np.asarray(q.info[f"normal{k}"], float),
                q.region0 if k == 0 else q.region1,
                roll,
                network,
                conf,
            )
            rows.append(
                {
                    "pair": q.name,
                    "image": k,
                    "roll_class": rotation_class(roll),
                    "tilt_deg": float(q.info[f"tilt{k}_deg"]),
                    **errors,
                }
            )
            logger.info("%s %d: %s", q.name, k, {s: round(v, 1) for s, v in errors.items()})
    args.output_dir.mkdir(parents=True, exist_ok=True)
    write_records_csv(args.output_dir / "orientation.csv", rows)
    head = (
        f"cameras {args.cameras}, {len(pairs)} pairs{f' ({args.split})' if args.split else ''}; "
        "best patch on the plane, degrees from the true normal\n\n"
    )
    table = head + summary_markdown(rows)
    (args.output_dir / "orientation.md").write_text(table)
    print(table)
    return 0


if __name__ == "__main__":
    sys.exit(run_script(main, "diagnose_orientation"))
