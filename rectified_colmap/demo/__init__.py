"""`rectified-colmap demo`: the whole job on a rendered street, with no data to download.

Renders a short walk along a synthetic street (the renderer's poses and intrinsics are
exact), extracts rectified SIFT with the embedded depth network into a COLMAP database and
an hloc feature file, matches and maps with pycolmap, and compares the recovered camera
rotations with the ground truth.

The demo wing: this job (:func:`run_demo`, :func:`render_walk`) and the renderer it runs,
procedural street scenes of textured planar quads with exact depth, normals and poses:
``scene`` (the quad scene, its builder), ``street`` (the demo's street: facade rows,
clutter, trees), ``textures`` (procedural and photo textures), ``render`` (ray casting:
image, depth, normals, plane ids), ``views`` (pinhole cameras, look-at poses, the walk along
a street). World frame: metres, z up, ground z = 0; cameras are pycolmap PINHOLE /
SIMPLE_PINHOLE (COLMAP pixel convention); poses ``cam_from_world`` pycolmap.Rigid3d (camera
x right, y down, z forward). What only training, tests and benchmarks use (random views,
view pairs and their ground truth, the corner, square and rubble scenes, random training
samples, line drawings, one textured plane) is research code:
``rectified_colmap_research.synth`` (research/, not installed).
"""

from __future__ import annotations

import logging
import shutil
from pathlib import Path

import cv2
import numpy as np
import pycolmap

from ..config import DEFAULT_DEPTH_MODEL
from ..extraction import extract
from ..geometry import rotation_angle_deg
from .render import render
from .street import street
from .views import pinhole_camera, pitched, view_orbit

logger = logging.getLogger(__name__)


def render_walk(
    out_dir: Path, num_images: int = 8, width: int = 640, height: int = 480, seed: int = 0
) -> tuple[list[str], pycolmap.Camera, dict[str, pycolmap.Rigid3d]]:
    """Write a walk along a street to out_dir; returns (names, camera, cam_from_world)."""
    rng = np.random.default_rng(seed)
    scene = street(rng)
    camera = pinhole_camera(width, height, 0.7 * width)
    out_dir.mkdir(parents=True, exist_ok=True)
    names, poses = [], {}
    for i, pose in enumerate(view_orbit(scene, num_images, rng, camera=camera)):
        pose = pitched(pose, 12.0)  # ground and facades: no single-plane degeneracy
        name = f"street_{i:03d}.png"
        cv2.imwrite(str(out_dir / name), render(scene, camera, pose).image[..., ::-1])
        names.append(name)
        poses[name] = pose
    return names, camera, poses


def run_demo(
    output: Path,
    num_images: int = 8,
    depth_model: str = DEFAULT_DEPTH_MODEL,
    overwrite: bool = False,
    num_workers: int = 1,
) -> dict:
    output = Path(output)
    if overwrite and output.exists():
        shutil.rmtree(output)
    images = output / "images"
    logger.info("rendering %d street images into %s", num_images, images)
    names, camera, gt = render_walk(images, num_images)
    params = ",".join(f"{p:.6f}" for p in camera.params)
    db, h5 = output / "database.db", output / "features.h5"
    summary = extract(
        images,
        database=db,
        hloc_features=h5,
        reader={"camera_model": "PINHOLE", "camera_params": params, "single_camera": True},
        depth={"model": depth_model},
        run={"num_workers": num_workers, "visualize": output / "viz"},
    )
    logger.info("extraction\n%s", summary.report())
    pycolmap.match_exhaustive(db)
    opts = pycolmap.IncrementalPipelineOptions()
    opts.random_seed = 0
    opts.ba_refine_focal_length = False  # the renderer's intrinsics are exact
    opts.ba_refine_extra_params = False
    recs = pycolmap.incremental_mapping(db, images, output / "sparse", opts)
    extracted = len(summary.done)
    result = {
        "images": len(names),
        "extracted_images": extracted,
        "reused_images": len(summary.skipped) + len(summary.copied),
        "rectified_images": extracted - len(summary.plain) if extracted else None,
        "extraction_ok": summary.ok,
        "registered": 0,
        "points3D": 0,
        "max_rotation_error_deg": None,
    }
    if recs:
        best = max(recs.values(), key=lambda r: r.num_reg_images())
        result["registered"] = best.num_reg_images()
        result["points3D"] = best.num_points3D()
        ims = {im.name: im for im in best.images.values()}
        ref = names[0] if names[0] in ims else next(iter(ims))
        errs = []
        for n, im in ims.items():  # relative rotations to the reference image vs GT
            R_est = (im.cam_from_world() * ims[ref].cam_from_world().inverse()).rotation.matrix()
            R_gt = (gt[n] * gt[ref].inverse()).rotation.matrix()
            errs.append(rotation_angle_deg(R_est.T @ R_gt))
        result["max_rotation_error_deg"] = float(max(errs))
    return result


RESULT_KEYS = {
    "images": "rendered street views",
    "extracted_images": "images extracted in this run",
    "reused_images": "images whose features an earlier run wrote (kept; --overwrite redoes them)",
    "rectified_images": "extracted images with at least one rectified patch (null: none "
    "extracted in this run)",
    "extraction_ok": "no image failed",
    "registered": "images in the largest model pycolmap's mapper built",
    "points3D": "3D points of that model",
    "max_rotation_error_deg": "largest error of the recovered camera rotations relative to "
    "one image, against the renderer's exact poses (degrees; under 1 is a good model)",
}
"""What each key of :func:`run_demo`'s result means (printed by the CLI under the JSON)."""
