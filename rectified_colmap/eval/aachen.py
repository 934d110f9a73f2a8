"""Aachen Day-Night files and a mini Aachen, for scripts/aachen_hloc.py (docs/hloc.md).

No hloc here (hloc itself: rectified_colmap.eval.hloc_compat).

- query lists with intrinsics (``name MODEL W H params...``, what localize_sfm parses);
- result files (``basename qw qx qy qz tx ty tz``, cam_from_world), validated against the
  query list (the benchmark server keys queries by base name);
- database images with the reference model's intrinsics: :func:`write_camera_database`
  (rectified_colmap.extraction reads the cameras of an existing database);
- a mini Aachen from a posed scene (:func:`make_mini_aachen`, e.g. Strecha fountain-P11)
  with held-out queries and their ground truth, :func:`localization_errors` and
  :func:`recall`.

Names are paths relative to the image root (``images_upright``), '/' separated.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from pathlib import Path

import numpy as np
import pycolmap

from .localize import format_pose, holdout_split, pose_error, read_poses

logger = logging.getLogger(__name__)


def format_query_line(name: str, camera: pycolmap.Camera) -> str:
    if any(c.isspace() for c in name):
        raise ValueError(f"query name {name!r} contains whitespace")
    params = " ".join(f"{p:.10g}" for p in camera.params)
    return f"{name} {camera.model.name} {camera.width} {camera.height} {params}"


def write_query_list(path: Path | str, queries: Mapping[str, pycolmap.Camera]) -> None:
    """``name MODEL W H p1 p2 ...`` per query (COLMAP pixel convention params)."""
    Path(path).write_text("".join(format_query_line(n, c) + "\n" for n, c in queries.items()))


def read_query_list(path: Path | str) -> dict[str, pycolmap.Camera]:
    """Parse a query list with intrinsics into pycolmap cameras (clear error per line)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: query list not found")
    out = {}
    for i, line in enumerate(path.read_text().splitlines(), 1):
        parts = line.split()
        if not parts:
            continue
        if len(parts) < 5:
            raise ValueError(f"{path}:{i}: expected 'name MODEL W H params...'")
        name, model, w, h, *params = parts
        try:
            cam = pycolmap.Camera(
                model=model, width=int(w), height=int(h), params=[float(p) for p in params]
            )
        except (RuntimeError, TypeError, ValueError) as e:
            raise ValueError(f"{path}:{i}: invalid camera ({e})") from None
        if not cam.verify_params():
            raise ValueError(f"{path}:{i}: {len(params)} params do not fit model {model}")
        out[name] = cam
    return out


def check_results(path: Path | str, query_names: list[str]) -> tuple[int, list[str]]:
    """Validate a result file against the queries: returns (lines, missing base names).

    Raises ValueError on malformed lines, duplicates, unknown names or non-unit quaternions."""
    path = Path(path)
    expected = {n.split("/")[-1] for n in query_names}
    seen = set()
    for i, line in enumerate(path.read_text().splitlines(), 1):
        parts = line.split()
        if not parts:
            continue
        if len(parts) != 8:
            raise ValueError(f"{path}:{i}: expected 'name qw qx qy qz tx ty tz'")
        name = parts[0]
        if name not in expected:
            raise ValueError(f"{path}:{i}: {name!r} is not a query")
        if name in seen:
            raise ValueError(f"{path}:{i}: duplicate {name!r}")
        q = np.array([float(v) for v in parts[1:5]])
        if abs(np.linalg.norm(q) - 1) > 1e-4:
            raise ValueError(f"{path}:{i}: quaternion is not unit")
        seen.add(name)
    return len(seen), sorted(expected - seen)


# -- database images with the reference model's intrinsics ----------------------------------


def write_camera_database(path: Path | str, cameras: Mapping[str, pycolmap.Camera]) -> int:
    """A COLMAP database with one camera per image (identical cameras shared) and no
    features: ``rectified_colmap.extraction.extract(database=path)`` then uses these cameras
    instead of EXIF or a guess. Returns the number of cameras written."""
    path = Path(path)
    if path.exists():
        path.unlink()
    ids: dict[tuple, int] = {}
    with pycolmap.Database.open(path) as db:
        for name, cam in cameras.items():
            key = (cam.model.name, cam.width, cam.height, tuple(float(p) for p in cam.params))
            if key not in ids:
                c = pycolmap.Camera(
                    model=cam.model.name, width=cam.width, height=cam.height, params=list(key[3])
                )
                c.has_prior_focal_length = True
                ids[key] = db.write_camera(c)
            db.write_image(pycolmap.Image(name=name, camera_id=ids[key]))
    return len(ids)


def model_cameras(model: pycolmap.Reconstruction) -> dict[str, pycolmap.Camera]:
    """Image name -> its camera in a COLMAP model."""
    return {im.name: model.cameras[im.camera_id] for im in model.images.values()}


# -- a mini Aachen from a posed scene, and localization errors ------------------------------


def _posed_scene(scene: Path) -> pycolmap.Reconstruction:
    """The posed model of a scene folder (``images/`` and ``sparse/``), or a clear error."""
    for what, path in (("scene folder", scene), ("posed model", scene / "sparse")):
        if not path.is_dir():
            raise FileNotFoundError(f"{path}: {what} not found (a scene needs images/ and sparse/)")
    try:
        return pycolmap.Reconstruction(str(scene / "sparse"))
    except ValueError as e:
        raise ValueError(f"{scene / 'sparse'}: not a COLMAP model ({e})") from None


def _copy_image(
    src: Path, dst: Path, camera: pycolmap.Camera, max_size: int | None
) -> pycolmap.Camera:
    """``src`` written to ``dst`` (JPEG), downscaled (INTER_AREA) to at most ``max_size``
    pixels on its larger side; returns its camera, rescaled with it."""
    import cv2

    img = cv2.imread(str(src), cv2.IMREAD_COLOR)
    if img is None:
        raise FileNotFoundError(f"{src}: cannot read the image")
    h, w = img.shape[:2]
    if (w, h) != (camera.width, camera.height):
        raise ValueError(f"{src.name}: image {w}x{h}, camera {camera.width}x{camera.height}")
    cam = pycolmap.Camera(model=camera.model.name, width=w, height=h, params=camera.params)
    s = 1.0 if not max_size else min(1.0, max_size / max(w, h))
    if s < 1:
        nw, nh = round(w * s), round(h * s)
        img = cv2.resize(img, (nw, nh), interpolation=cv2.INTER_AREA)
        cam.rescale(nw, nh)
    dst.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(dst), img, [cv2.IMWRITE_JPEG_QUALITY, 95])
    return cam


def _mini_paths(out: Path) -> dict[str, Path]:
    return {
        "dataset": out,
        "images": out / "images" / "images_upright",
        "queries": out / "queries" / "day_time_queries_with_intrinsics.txt",
        "reference_sfm": out / "3D-models" / "reference",
        "loc_pairs": out / "pairs-query-exhaustive.txt",
        "ground_truth": out / "ground_truth.txt",
    }


def make_mini_aachen(
    scene: Path | str,
    out: Path | str,
    max_size: int | None = None,
    holdout_every: int = 3,
    holdout_offset: int = 1,
    num_queries: int | None = None,
) -> dict[str, Path]:
    """An Aachen-layout dataset from a scene with ``images/`` and a posed ``sparse/`` model
    (e.g. Strecha): every ``holdout_every``-th image (from ``holdout_offset``) becomes a
    held-out query (the first ``num_queries`` of them when given; the others are left out),
    the rest the database.

    Writes ``images/images_upright/{db,query/day}/<name>``, ``queries/day_time_queries_with_
    intrinsics.txt``, ``3D-models/reference`` (database images, poses, no points),
    ``pairs-query-exhaustive.txt`` (every query with every database image) and
    ``ground_truth.txt`` (query poses, result-file format). Images larger than ``max_size``
    are downscaled (INTER_AREA) with their cameras. Returns the paths by role."""
    scene, paths = Path(scene), _mini_paths(Path(out))
    model = _posed_scene(scene)
    by_name = {im.name: im for im in model.images.values()}
    db_names, q_names = holdout_split(sorted(by_name), holdout_every, holdout_offset)
    q_names = q_names[:num_queries] if num_queries is not None else q_names
    ref = pycolmap.Reconstruction()
    queries, gt_lines, db = {}, [], []
    for k, name in enumerate(sorted(db_names + q_names), 1):
        im = by_name[name]
        new = f"{'query/day' if name in q_names else 'db'}/{Path(name).name}"
        cam = _copy_image(
            scene / "images" / name, paths["images"] / new, model.cameras[im.camera_id], max_size
        )
        if name in q_names:
            queries[new] = cam
            gt_lines.append(format_pose(new, im.cam_from_world()))
            continue
        db.append(new)
        cam.camera_id = k
        ref.add_camera_with_trivial_rig(cam)
        ref.add_image_with_trivial_frame(
            pycolmap.Image(name=new, camera_id=k, image_id=k), im.cam_from_world()
        )
    paths["queries"].parent.mkdir(parents=True, exist_ok=True)
    write_query_list(paths["queries"], queries)
    paths["reference_sfm"].mkdir(parents=True, exist_ok=True)
    ref.write(str(paths["reference_sfm"]))
    pairs = "".join(f"{q} {d}\n" for q in sorted(queries) for d in sorted(db))
    paths["loc_pairs"].write_text(pairs)
    paths["ground_truth"].write_text("".join(line + "\n" for line in sorted(gt_lines)))
    logger.info("mini Aachen in %s: %d database images, %d queries", out, len(db), len(queries))
    return paths


def localization_errors(
    results: Path | str, ground_truth: Path | str
) -> dict[str, tuple[float, float]]:
    """Per ground-truth query: (camera-centre error in model units, rotation error in
    degrees) of a result file; (inf, inf) when it has no line. Both files key queries by
    base name (the benchmark format)."""
    est = {n.split("/")[-1]: T for n, T in read_poses(results).items()}
    out = {}
    for name, T in read_poses(ground_truth).items():
        base = name.split("/")[-1]
        out[base] = pose_error(est[base], T) if base in est else (np.inf, np.inf)
    return out


RECALL_THRESHOLDS = ((0.25, 2.0), (0.5, 5.0), (5.0, 10.0))
"""Aachen Day-Night's (metres, degrees) thresholds."""


def recall(
    errors: Mapping[str, tuple[float, float]],
    thresholds=RECALL_THRESHOLDS,
    failed: list[str] | tuple = (),
) -> list[float]:
    """Fraction of queries within each (distance, degrees) threshold; queries in ``failed``
    (e.g. localize_sfm fallbacks) count as failures."""
    if not errors:
        raise ValueError("no queries")
    failed = {n.split("/")[-1] for n in failed}
    e = np.array([(np.inf, np.inf) if n in failed else v for n, v in errors.items()], float)
    return [float(np.mean((e[:, 0] < d) & (e[:, 1] < a))) for d, a in thresholds]
