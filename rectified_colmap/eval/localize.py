"""Offline Aachen-style localization: a reference model triangulated into known poses, then
query images localized against it by 2D-3D matches. No hloc needed.

1. :func:`build_reference`: database images with known poses (cam_from_world) and cameras
   -> a COLMAP database (cameras, rigs, frames, images with the model's ids, keypoints),
   ratio-test matches kept when consistent with the known poses (Sampson error under
   ``verify_max_error`` px, as hloc's triangulation.geometric_verification), written as
   two-view geometries WITH ``config = CALIBRATED`` (pycolmap 4.2 ignores UNDEFINED ones),
   then ``pycolmap.triangulate_points`` into a Reconstruction holding the known poses.
2. :func:`localize_queries`: per query, ratio-test matches to every database image (or the
   ``num_retrieved`` images with the most matches), 2D-3D correspondences through the
   database keypoints that have a 3D point, ``pycolmap.estimate_and_refine_absolute_pose``.
3. :func:`pose_accuracy` / :func:`write_poses`: the fraction of queries within (metres,
   degrees) thresholds, or an hloc/Aachen result file ``name qw qx qy qz tx ty tz``
   (cam_from_world, Hamilton quaternion w first).

Features are abstract (rectified_colmap.eval.matching.FeatureSource: an hloc h5 file or a
mapping), so plain and rectified SIFT go through identical code. Keypoints are COLMAP px.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pycolmap

from .config import LocalizeConf
from ..geometry import rotation_angle_deg
from .matching import FeatureSource, match_ratio
from .relpose import sampson_error, fundamental_from_pose

logger = logging.getLogger(__name__)


def _matrix4(T: pycolmap.Rigid3d) -> np.ndarray:
    return np.vstack([np.asarray(T.matrix()), [0, 0, 0, 1]])


def _fundamental(cam0, T0, cam1, T1) -> np.ndarray:
    """F (pixels) between two posed pinhole-part cameras (distortion ignored)."""
    T = _matrix4(T1) @ np.linalg.inv(_matrix4(T0))
    return fundamental_from_pose(
        np.asarray(cam0.calibration_matrix()),
        np.asarray(cam1.calibration_matrix()),
        T[:3, :3],
        T[:3, 3],
    )


def _undistorted_px(camera: pycolmap.Camera, xy: np.ndarray) -> np.ndarray:
    """Keypoints -> pixels of the camera's undistorted pinhole part."""
    n = np.asarray(camera.cam_from_img(np.ascontiguousarray(xy, np.float64)))
    K = np.asarray(camera.calibration_matrix())
    return n @ K[:2, :2].T + K[:2, 2]


def build_reference(
    names: list[str],
    cameras: Mapping[str, pycolmap.Camera],
    poses: Mapping[str, pycolmap.Rigid3d],
    features: FeatureSource | Path | str,
    work_dir: Path | str,
    pairs: list[tuple[str, str]] | None = None,
    conf: LocalizeConf | None = None,
    image_dir: Path | str | None = None,
) -> pycolmap.Reconstruction:
    """Triangulate the features of ``names`` into their known poses -> Reconstruction.

    ``pairs`` defaults to all pairs of ``names``. ``work_dir`` receives ``reference.db`` and
    the model (``sfm/``). ``image_dir`` is only used by COLMAP for point colours."""
    conf = conf or LocalizeConf()
    features = features if isinstance(features, FeatureSource) else FeatureSource(features)
    work_dir = Path(work_dir)
    work_dir.mkdir(parents=True, exist_ok=True)
    missing = [n for n in names if n not in features]
    if missing:
        raise ValueError(
            f"{features.path or 'features'}: no features for {len(missing)} "
            f"reference image(s), e.g. {missing[:3]}"
        )
    db_path = work_dir / "reference.db"
    db_path.unlink(missing_ok=True)
    feats = {n: features[n] for n in names}
    if pairs is None:
        pairs = [(a, b) for k, a in enumerate(names) for b in names[k + 1 :]]
    with pycolmap.Database.open(db_path) as db:
        rec, ids = _posed_images(db, names, cameras, poses, feats)
        n_verified = sum(
            _verified_matches(db, ids, a, b, cameras, poses, feats, conf) for a, b in pairs
        )
    logger.info(
        "reference: %d images, %d pairs, %d verified matches", len(names), len(pairs), n_verified
    )
    opts = pycolmap.IncrementalPipelineOptions()
    opts.num_threads = 1
    sfm = work_dir / "sfm"
    sfm.mkdir(exist_ok=True)
    if image_dir is None:  # only used for colours: missing images just log warnings
        image_dir = work_dir
    out = pycolmap.triangulate_points(rec, db_path, Path(image_dir), sfm, options=opts)
    logger.info(
        "reference model: %d points, mean track %.2f",
        out.num_points3D(),
        out.compute_mean_track_length() if out.num_points3D() else 0.0,
    )
    return out


def _posed_images(db, names, cameras, poses, feats) -> tuple[pycolmap.Reconstruction, dict]:
    """Every image into the database (camera with a prior focal length, trivial rig and
    frame, keypoints) and into a Reconstruction at its known pose -> (it, name -> id)."""
    rec, ids = pycolmap.Reconstruction(), {}
    for i, name in enumerate(names, 1):
        cam = pycolmap.Camera(
            model=cameras[name].model,
            width=cameras[name].width,
            height=cameras[name].height,
            params=cameras[name].params,
        )
        cam.camera_id = i
        cam.has_prior_focal_length = True
        rec.add_camera_with_trivial_rig(cam)
        db.write_camera(cam, use_camera_id=True)
        db.write_rig(rec.rig(i), use_rig_id=True)
        im = pycolmap.Image(name=name, camera_id=i, image_id=i)
        rec.add_image_with_trivial_frame(im, poses[name])
        db.write_image(pycolmap.Image(name=name, camera_id=i, image_id=i), use_image_id=True)
        frame = pycolmap.Frame()
        frame.frame_id = i
        frame.rig_id = i
        frame.add_data_id(rec.image(i).data_id)
        db.write_frame(frame, use_frame_id=True)
        db.write_keypoints(i, feats[name]["keypoints"].astype(np.float32))
        ids[name] = i
    return rec, ids


def _verified_matches(db, ids, a, b, cameras, poses, feats, conf: LocalizeConf) -> int:
    """Ratio-test matches of images a and b, verified against the epipolar geometry of
    their known poses (Sampson error), into the database; returns the verified count."""
    m = match_ratio(feats[a]["descriptors"], feats[b]["descriptors"], conf.ratio, conf.mutual)
    if len(m) == 0:
        return 0
    ca, cb = cameras[a], cameras[b]
    F = _fundamental(ca, poses[a], cb, poses[b])
    err = sampson_error(
        F,
        _undistorted_px(ca, feats[a]["keypoints"][m[:, 0]]),
        _undistorted_px(cb, feats[b]["keypoints"][m[:, 1]]),
    )
    inl = m[err < conf.verify_max_error].astype(np.uint32)
    db.write_matches(ids[a], ids[b], m.astype(np.uint32))
    geom = pycolmap.TwoViewGeometry()
    geom.config = pycolmap.TwoViewGeometryConfiguration.CALIBRATED
    geom.inlier_matches = inl
    db.write_two_view_geometry(ids[a], ids[b], geom)
    return len(inl)


@dataclass
class QueryResult:
    name: str
    cam_from_world: pycolmap.Rigid3d | None
    num_inliers: int = 0
    num_correspondences: int = 0


def _reference_index(
    reference: pycolmap.Reconstruction,
) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Per database image: (indices of keypoints with a 3D point, their 3D points)."""
    out = {}
    for im in reference.images.values():
        idx, xyz = [], []
        for k, p in enumerate(im.points2D):
            if p.has_point3D():
                idx.append(k)
                xyz.append(reference.points3D[p.point3D_id].xyz)
        out[im.name] = (np.array(idx, np.int64), np.array(xyz, np.float64).reshape(-1, 3))
    return out


def localize_queries(
    reference: pycolmap.Reconstruction,
    queries: Mapping[str, pycolmap.Camera],
    features: FeatureSource | Path | str,
    reference_features: FeatureSource | Path | str | None = None,
    conf: LocalizeConf | None = None,
    progress: bool = False,
) -> dict[str, QueryResult]:
    """Localize each query (name -> camera) against the reference model."""
    from tqdm import tqdm

    conf = conf or LocalizeConf()
    features = features if isinstance(features, FeatureSource) else FeatureSource(features)
    ref_feats = (
        features
        if reference_features is None
        else (
            reference_features
            if isinstance(reference_features, FeatureSource)
            else FeatureSource(reference_features)
        )
    )
    index = _reference_index(reference)
    db = {n: ref_feats[n] for n in index if len(index[n][0])}
    est = pycolmap.AbsolutePoseEstimationOptions()
    est.ransac.max_error = conf.ransac_max_error
    est.ransac.random_seed = 0
    results = {}
    for q, cam in tqdm(queries.items(), desc="localize", disable=not progress):
        if q not in features:
            raise ValueError(f"{features.path or 'features'}: no features for query {q!r}")
        fq = features[q]
        per_db = []
        for n, f in db.items():
            m = match_ratio(fq["descriptors"], f["descriptors"], conf.ratio, conf.mutual)
            idx, xyz = index[n]
            pos = np.searchsorted(idx, m[:, 1])
            ok = (pos < len(idx)) & (idx[np.minimum(pos, len(idx) - 1)] == m[:, 1])
            per_db.append((len(m), fq["keypoints"][m[ok, 0]], xyz[pos[ok]]))
        if conf.num_retrieved > 0:
            per_db = sorted(per_db, key=lambda x: -x[0])[: conf.num_retrieved]
        p2 = np.concatenate([x[1] for x in per_db]) if per_db else np.zeros((0, 2))
        p3 = np.concatenate([x[2] for x in per_db]) if per_db else np.zeros((0, 3))
        res = None
        if len(p2) >= 4:
            res = pycolmap.estimate_and_refine_absolute_pose(
                np.ascontiguousarray(p2, np.float64),
                np.ascontiguousarray(p3, np.float64),
                cam,
                estimation_options=est,
            )
        if res is None:
            results[q] = QueryResult(q, None, 0, len(p2))
        else:
            results[q] = QueryResult(q, res["cam_from_world"], int(res["num_inliers"]), len(p2))
    return results


def pose_error(est: pycolmap.Rigid3d, gt: pycolmap.Rigid3d) -> tuple[float, float]:
    """(camera-centre distance in model units, rotation angle in degrees)."""
    Re, Rg = np.asarray(est.rotation.matrix()), np.asarray(gt.rotation.matrix())
    ce = -Re.T @ np.asarray(est.translation)
    cg = -Rg.T @ np.asarray(gt.translation)
    return float(np.linalg.norm(ce - cg)), rotation_angle_deg(Re.T @ Rg)


def pose_accuracy(
    results: Mapping[str, QueryResult],
    gt: Mapping[str, pycolmap.Rigid3d],
    thresholds=((0.25, 2.0), (0.5, 5.0), (5.0, 10.0)),
) -> list[float]:
    """Fraction of the ground-truth queries within each (distance, degrees) threshold;
    a query without a result counts as a failure."""
    errs = []
    for name, T in gt.items():
        r = results.get(name)
        errs.append(
            (np.inf, np.inf)
            if r is None or r.cam_from_world is None
            else pose_error(r.cam_from_world, T)
        )
    errs = np.array(errs, float).reshape(-1, 2)
    if not len(errs):
        raise ValueError("no ground-truth queries")
    return [float(np.mean((errs[:, 0] < d) & (errs[:, 1] < a))) for d, a in thresholds]


def format_pose(name: str, T: pycolmap.Rigid3d) -> str:
    """``name qw qx qy qz tx ty tz`` (cam_from_world), the hloc/Aachen result line."""
    q = np.asarray(T.rotation.quat)  # pycolmap: x, y, z, w
    q = q[[3, 0, 1, 2]]
    if q[0] < 0:
        q = -q
    t = np.asarray(T.translation)
    return " ".join([name] + [f"{v:.10g}" for v in (*q, *t)])


def write_poses(path: Path | str, results: Mapping[str, QueryResult], basename: bool = True) -> int:
    """Write the localized queries (result-file format of the Aachen benchmark, which keys
    images by their base name, as hloc does); returns the number of lines."""
    lines = []
    for name, r in results.items():
        if r.cam_from_world is None:
            continue
        lines.append(format_pose(name.split("/")[-1] if basename else name, r.cam_from_world))
    Path(path).write_text("".join(line + "\n" for line in lines))
    return len(lines)


def read_poses(path: Path | str) -> dict[str, pycolmap.Rigid3d]:
    """Read ``name qw qx qy qz tx ty tz`` lines."""
    out = {}
    for i, line in enumerate(Path(path).read_text().splitlines(), 1):
        parts = line.split()
        if not parts:
            continue
        if len(parts) != 8:
            raise ValueError(f"{path}:{i}: expected 'name qw qx qy qz tx ty tz'")
        w, x, y, z, *t = (float(v) for v in parts[1:])
        out[parts[0]] = pycolmap.Rigid3d(pycolmap.Rotation3d(np.array([x, y, z, w])), np.array(t))
    return out


# -- a whole run from a posed model ---------------------------------------------------------


def holdout_split(names: list[str], every: int = 3, offset: int = 1) -> tuple[list[str], list[str]]:
    """Sorted names -> (database, queries): every ``every``-th image (from ``offset``) is a
    query."""
    if every < 2:
        raise ValueError(f"holdout every={every}: need at least 2 (some database images)")
    names = sorted(names)
    queries = [n for k, n in enumerate(names) if k % every == offset % every]
    return [n for n in names if n not in set(queries)], queries


def localize_with_model(
    model: pycolmap.Reconstruction,
    features: FeatureSource | Path | str,
    work_dir: Path | str,
    queries: Mapping[str, pycolmap.Camera] | None = None,
    holdout_every: int = 3,
    name_prefix: str = "",
    conf: LocalizeConf | None = None,
    progress: bool = False,
    image_dir: Path | str | None = None,
) -> tuple[dict[str, QueryResult], list[float] | None]:
    """Reference from the posed images of ``model`` (minus held-out queries), then localize.

    With ``queries`` (name -> camera; names as in the feature file) every posed model image
    is a database image and there is no ground truth (accuracy None) unless a query is also
    in the model. Without, every ``holdout_every``-th model image is a query, with its model
    pose as ground truth. ``name_prefix`` maps model names to feature names."""
    conf = conf or LocalizeConf()
    posed = {name_prefix + im.name: im for im in model.images.values() if im.has_pose}
    if queries is None:
        db_names, q_names = holdout_split(list(posed), holdout_every)
        queries = {n: model.cameras[posed[n].camera_id] for n in q_names}
    else:
        db_names = sorted(n for n in posed if n not in queries)
    ref = build_reference(
        db_names,
        {n: model.cameras[posed[n].camera_id] for n in db_names},
        {n: posed[n].cam_from_world() for n in db_names},
        features,
        work_dir,
        conf=conf,
        image_dir=image_dir,
    )
    results = localize_queries(ref, queries, features, conf=conf, progress=progress)
    gt = {n: posed[n].cam_from_world() for n in queries if n in posed}
    acc = pose_accuracy(results, gt, conf.thresholds) if gt else None
    return results, acc


def accuracy_table(
    rows: Mapping[str, list[float]], thresholds, num_queries: Mapping[str, int]
) -> str:
    """Markdown: one row per method, the % of queries within each threshold."""
    head = ["method", "queries"] + [f"({d:g} m, {a:g} deg) %" for d, a in thresholds]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for m, acc in rows.items():
        lines.append(
            "| " + " | ".join([m, str(num_queries[m])] + [f"{100 * v:.1f}" for v in acc]) + " |"
        )
    return "\n".join(lines) + "\n"
