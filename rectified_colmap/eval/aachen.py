"""Helpers for Aachen Day-Night with hloc (scripts/aachen_hloc.py, docs/hloc.md).

Importing this module does not import hloc; the functions that drive hloc import it on use
(:func:`import_hloc` raises :class:`HlocError` with the reason when it is missing or of an
API generation this code does not know).

- query lists with intrinsics (``name MODEL W H params...``, what localize_sfm parses);
- hloc pair lists restricted to the images of a reference model (hloc raises KeyError on
  any other name);
- the pycolmap 4.2 fix: hloc's triangulation writes two-view geometries with config
  UNDEFINED, which pycolmap 4.2.1's DatabaseCache skips ("written by an outdated
  producer"), so 0 points get triangulated. :func:`set_two_view_config` rewrites them with
  ``CALIBRATED`` (the poses are known) before ``triangulate_points``;
- result files (``basename qw qx qy qz tx ty tz``, cam_from_world), validated against the
  query list (the benchmark server keys queries by base name);
- hloc's two API generations (both say version 1.5): since upstream commit 374799c
  (2025-09-22) ``hloc.triangulation.import_features``/``import_matches``/
  ``geometric_verification`` take an open ``pycolmap.Database`` (parameter ``db``), before
  that a path (``database_path``). :func:`hloc_generation` tells them apart by signature;
  :func:`triangulate_with_hloc` runs hloc's steps for either, with the fix;
- localize_sfm's silent fallback (a query it cannot localize gets the pose of its first
  retrieved image): :func:`localize_sfm_fallbacks` reads them back from hloc's log;
- database images with the reference model's intrinsics: :func:`write_camera_database`
  (rectified_colmap.extraction reads the cameras of an existing database);
- a mini Aachen from a posed scene (:func:`make_mini_aachen`, e.g. Strecha fountain-P11)
  with held-out queries and their ground truth, and :func:`localization_errors`;
- keypoint orientations for LightGlue's SIFT mode (radians, :func:`oris_for_lightglue`).

Names are paths relative to the image root (``images_upright``), '/' separated.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from pathlib import Path

import numpy as np
import pycolmap

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


def filter_pairs(
    pairs: list[tuple[str, str]], names: set[str] | list[str], both: bool = True
) -> list[tuple[str, str]]:
    """Pairs whose images are in ``names`` (both, or the second one when ``both=False``,
    for query-to-database pairs), without duplicates (i, j) / (j, i)."""
    names = set(names)
    seen, out = set(), []
    for a, b in pairs:
        if b not in names or (both and a not in names):
            continue
        key = (a, b) if a <= b else (b, a)
        if key in seen or a == b:
            continue
        seen.add(key)
        out.append((a, b))
    return out


def set_two_view_config(
    database: Path | str, config: str = "CALIBRATED", only_undefined: bool = True
) -> int:
    """Give every (UNDEFINED) two-view geometry of a database a configuration.

    Returns the number of geometries rewritten. Needed after hloc's triangulation steps with
    pycolmap >= 4.2 (see the module docstring)."""
    database = Path(database)
    if not database.is_file():
        raise FileNotFoundError(f"{database}: database not found")
    target = getattr(pycolmap.TwoViewGeometryConfiguration, config)
    undefined = pycolmap.TwoViewGeometryConfiguration.UNDEFINED
    n = 0
    with pycolmap.Database.open(database) as db:
        pair_ids, geoms = db.read_two_view_geometries()
        for pid, g in zip(pair_ids, geoms):
            if only_undefined and pycolmap.TwoViewGeometryConfiguration(g.config) != undefined:
                continue
            if len(g.inlier_matches) == 0:
                continue
            i, j = pycolmap.pair_id_to_image_pair(pid)
            new = pycolmap.TwoViewGeometry()
            new.config = target
            new.inlier_matches = np.asarray(g.inlier_matches, np.uint32)
            db.update_two_view_geometry(i, j, new)
            n += 1
    logger.info("%s: %d two-view geometries set to %s", database, n, config)
    return n


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


def group_by_camera(
    cameras: Mapping[str, pycolmap.Camera],
) -> list[tuple[str, tuple[float, ...], list[str]]]:
    """Queries grouped by identical (model, size, params): one extraction call per group.

    Returns [(model name, params, names)], names sorted, groups in first-seen order."""
    groups: dict[tuple, list[str]] = {}
    for name, cam in cameras.items():
        key = (cam.model.name, cam.width, cam.height, tuple(float(p) for p in cam.params))
        groups.setdefault(key, []).append(name)
    return [(k[0], k[3], sorted(v)) for k, v in groups.items()]


# -- hloc: import, API generation, triangulation with the pycolmap 4.2 fix ------------------


class HlocError(RuntimeError):
    """hloc is missing, cannot be imported, or has an API this code does not know."""


HLOC_INSTALL = (
    "hloc is not on PyPI: clone its GitHub repository "
    "(cvg/Hierarchical-Localization) and `pip install -e .` in it, or install the "
    "vendored copy with `pip install --no-deps ../shared/vendor/hloc`; it needs "
    "torch, kornia, scipy, matplotlib and plotly (docs/hloc.md)"
)


def import_hloc():
    """Import hloc and the modules the Aachen path uses; :class:`HlocError` says why not."""
    try:
        import hloc
        from hloc import localize_sfm, match_features, triangulation  # noqa: F401
    except ImportError as e:
        missing = getattr(e, "name", None) or str(e)
        if missing == "hloc" or missing.startswith("hloc"):
            raise HlocError(f"hloc is not installed. {HLOC_INSTALL}") from None
        raise HlocError(
            f"hloc is installed but cannot be imported: {e} "
            f"(missing dependency {missing!r}). {HLOC_INSTALL}"
        ) from None
    hloc_generation(triangulation)  # raises HlocError when unknown
    return hloc


def hloc_generation(triangulation) -> str:
    """'db' (hloc after 2025-09-22: an open pycolmap.Database) or 'path' (before: a database
    path), from the signature of ``triangulation.import_features``; both say version 1.5."""
    import inspect

    fns = (
        "create_db_from_model",
        "import_features",
        "import_matches",
        "geometric_verification",
        "run_triangulation",
    )
    missing = [f for f in fns if not callable(getattr(triangulation, f, None))]
    if missing:
        raise HlocError(f"hloc.triangulation has no {missing}: unsupported hloc version")
    params = inspect.signature(triangulation.import_features).parameters
    if "db" in params:
        return "db"
    if "database_path" in params:
        return "path"
    raise HlocError(
        "hloc.triangulation.import_features takes neither `db` nor "
        f"`database_path` ({list(params)}): unsupported hloc version"
    )


def call_with(fn, **available):
    """Call an hloc function with the arguments its signature names (hloc versions differ
    in which of them they take); :class:`HlocError` when it needs one we do not have."""
    import inspect

    params = inspect.signature(fn).parameters
    kwargs = {k: v for k, v in available.items() if k in params}
    missing = [
        k
        for k, p in params.items()
        if p.default is p.empty
        and k not in kwargs
        and p.kind not in (p.VAR_POSITIONAL, p.VAR_KEYWORD)
    ]
    if missing:
        raise HlocError(
            f"hloc {fn.__module__}.{fn.__name__} needs {missing}: unsupported hloc version"
        )
    return fn(**kwargs)


def triangulate_with_hloc(
    reference_model: Path | str | pycolmap.Reconstruction,
    sfm_dir: Path | str,
    image_dir: Path | str,
    pairs: Path | str,
    features: Path | str,
    matches: Path | str,
    max_error: float = 4.0,
) -> pycolmap.Reconstruction:
    """hloc.triangulation.main's steps (known poses, matches verified against them), with
    every UNDEFINED two-view geometry set to CALIBRATED before ``triangulate_points``:
    stock ``main`` triangulates 0 points under pycolmap 4.2. Works with both hloc API
    generations. Raises RuntimeError when nothing gets triangulated."""
    import_hloc()
    from hloc import triangulation

    generation = hloc_generation(triangulation)
    sfm_dir, features, pairs, matches = map(Path, (sfm_dir, features, pairs, matches))
    sfm_dir.mkdir(parents=True, exist_ok=True)
    database = sfm_dir / "database.db"
    reference = (
        reference_model
        if isinstance(reference_model, pycolmap.Reconstruction)
        else pycolmap.Reconstruction(str(reference_model))
    )
    image_ids = triangulation.create_db_from_model(reference, database)
    args = {
        "image_ids": image_ids,
        "reference": reference,
        "features_path": features,
        "pairs_path": pairs,
        "matches_path": matches,
        "min_match_score": None,
        "skip_geometric_verification": False,
        "max_error": max_error,
    }
    if generation == "db":
        with pycolmap.Database.open(database) as db:
            call_with(triangulation.import_features, db=db, **args)
            call_with(triangulation.import_matches, db=db, **args)
            call_with(triangulation.geometric_verification, db=db, **args)
    else:
        call_with(triangulation.import_features, database_path=database, **args)
        call_with(triangulation.import_matches, database_path=database, **args)
        call_with(triangulation.geometric_verification, database_path=database, **args)
    n = set_two_view_config(database, "CALIBRATED")
    logger.info("pycolmap 4.2 fix: %d verified two-view geometries given config CALIBRATED", n)
    rec = call_with(
        triangulation.run_triangulation,
        model_path=sfm_dir,
        database_path=database,
        image_dir=Path(image_dir),
        reference_model=reference,
    )
    logger.info("reference model: %d images, %d points", rec.num_reg_images(), rec.num_points3D())
    if rec.num_points3D() == 0:
        raise RuntimeError(
            f"{sfm_dir}: 0 points triangulated: check the pairs, features and matches"
        )
    return rec


def localize_sfm_fallbacks(results: Path | str) -> list[str]:
    """Queries that hloc's localize_sfm did NOT localize (it writes the pose of the first
    retrieved database image for them, silently), read from its ``<results>_logs.pkl``."""
    import pickle

    logs_path = Path(f"{results}_logs.pkl")
    with open(logs_path, "rb") as f:
        logs = pickle.load(f)
    out = []
    for name, log in logs["loc"].items():
        if log.get("covisibility_clustering"):
            failed = log.get("best_cluster") is None
        else:
            failed = log.get("PnP_ret") is None
        if failed:
            out.append(name)
    return sorted(out)


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
    import cv2

    from .localize import format_pose, holdout_split

    scene, out = Path(scene), Path(out)
    for what, path in (("scene folder", scene), ("posed model", scene / "sparse")):
        if not path.is_dir():
            raise FileNotFoundError(f"{path}: {what} not found (a scene needs images/ and sparse/)")
    try:
        model = pycolmap.Reconstruction(str(scene / "sparse"))
    except ValueError as e:
        raise ValueError(f"{scene / 'sparse'}: not a COLMAP model ({e})") from None
    by_name = {im.name: im for im in model.images.values()}
    db_names, q_names = holdout_split(sorted(by_name), holdout_every, holdout_offset)
    if num_queries is not None:
        q_names = q_names[:num_queries]
    root = out / "images" / "images_upright"
    ref = pycolmap.Reconstruction()
    queries, gt_lines, new_names = {}, [], {}
    for k, name in enumerate(sorted(db_names + q_names), 1):
        im = by_name[name]
        cam = model.cameras[im.camera_id]
        img = cv2.imread(str(scene / "images" / name), cv2.IMREAD_COLOR)
        if img is None:
            raise FileNotFoundError(f"{scene / 'images' / name}: cannot read the image")
        h, w = img.shape[:2]
        if (w, h) != (cam.width, cam.height):
            raise ValueError(f"{name}: image {w}x{h}, camera {cam.width}x{cam.height}")
        cam = pycolmap.Camera(model=cam.model.name, width=w, height=h, params=cam.params)
        s = 1.0 if not max_size else min(1.0, max_size / max(w, h))
        if s < 1:
            nw, nh = round(w * s), round(h * s)
            img = cv2.resize(img, (nw, nh), interpolation=cv2.INTER_AREA)
            cam.rescale(nw, nh)
        is_query = name in q_names
        new = f"{'query/day' if is_query else 'db'}/{Path(name).name}"
        new_names[name] = new
        (root / new).parent.mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(root / new), img, [cv2.IMWRITE_JPEG_QUALITY, 95])
        if is_query:
            queries[new] = cam
            gt_lines.append(format_pose(new, im.cam_from_world()))
        else:
            cam.camera_id = k
            ref.add_camera_with_trivial_rig(cam)
            ref.add_image_with_trivial_frame(
                pycolmap.Image(name=new, camera_id=k, image_id=k), im.cam_from_world()
            )
    paths = {
        "dataset": out,
        "images": root,
        "queries": out / "queries" / "day_time_queries_with_intrinsics.txt",
        "reference_sfm": out / "3D-models" / "reference",
        "loc_pairs": out / "pairs-query-exhaustive.txt",
        "ground_truth": out / "ground_truth.txt",
    }
    paths["queries"].parent.mkdir(parents=True, exist_ok=True)
    write_query_list(paths["queries"], queries)
    paths["reference_sfm"].mkdir(parents=True, exist_ok=True)
    ref.write(str(paths["reference_sfm"]))
    db = sorted(new_names[n] for n in db_names)
    paths["loc_pairs"].write_text("".join(f"{q} {d}\n" for q in sorted(queries) for d in db))
    paths["ground_truth"].write_text("".join(line + "\n" for line in sorted(gt_lines)))
    logger.info("mini Aachen in %s: %d database images, %d queries", out, len(db), len(queries))
    return paths


def localization_errors(
    results: Path | str, ground_truth: Path | str
) -> dict[str, tuple[float, float]]:
    """Per ground-truth query: (camera-centre error in model units, rotation error in
    degrees) of a result file; (inf, inf) when it has no line. Both files key queries by
    base name (the benchmark format)."""
    from .localize import pose_error, read_poses

    est = {n.split("/")[-1]: T for n, T in read_poses(results).items()}
    out = {}
    for name, T in read_poses(ground_truth).items():
        base = name.split("/")[-1]
        out[base] = pose_error(est[base], T) if base in est else (np.inf, np.inf)
    return out


def recall(
    errors: Mapping[str, tuple[float, float]],
    thresholds=((0.25, 2.0), (0.5, 5.0), (5.0, 10.0)),
    failed: list[str] | tuple = (),
) -> list[float]:
    """Fraction of queries within each (distance, degrees) threshold; queries in ``failed``
    (e.g. localize_sfm fallbacks) count as failures."""
    if not errors:
        raise ValueError("no queries")
    failed = {n.split("/")[-1] for n in failed}
    e = np.array([(np.inf, np.inf) if n in failed else v for n, v in errors.items()], float)
    return [float(np.mean((e[:, 0] < d) & (e[:, 1] < a))) for d, a in thresholds]


# -- keypoint orientations for LightGlue ------------------------------------------------------


def oris_for_lightglue(oris_deg: np.ndarray) -> np.ndarray:
    """Our (and hloc DoG's) ``oris`` are COLMAP orientations (atan2(a21, a11), image axes)
    in DEGREES; LightGlue's SIFT extractor hands its matcher the same angle in RADIANS (its
    pycolmap backend passes COLMAP's keypoint angle through, its OpenCV backend
    ``deg2rad(KeyPoint.angle)``). Returns float32 radians."""
    return np.deg2rad(np.asarray(oris_deg, np.float64)).astype(np.float32)


def convert_oris_for_lightglue(src: Path | str, dst: Path | str) -> int:
    """Copy an hloc feature file with every ``oris`` dataset in radians (attribute
    ``oris_unit = 'rad'``), for LightGlue's SIFT weights; returns the number of images."""
    import h5py

    src, dst = Path(src), Path(dst)
    if src.resolve() == dst.resolve():
        raise ValueError("convert into a new file: hloc's own readers expect degrees")
    n = 0
    with h5py.File(src, "r") as fi, h5py.File(dst, "w") as fo:

        def visit(name, obj):
            nonlocal n
            if isinstance(obj, h5py.Group) and "keypoints" in obj:
                g = fo.require_group(name)
                for k, d in obj.items():
                    if k == "oris":
                        if d.attrs.get("oris_unit") == "rad":
                            raise ValueError(f"{src}: {name}/oris already in radians")
                        g.create_dataset(k, data=oris_for_lightglue(d[()]))
                        g[k].attrs["oris_unit"] = "rad"
                    else:
                        fi.copy(d, g, name=k)
                n += 1

        fi.visititems(visit)
    return n
