"""Merge the outputs of sharded runs into one COLMAP database and one hloc feature file.

``merge_databases(target, inputs)`` and ``merge_feature_files(target, inputs)`` (CLI:
``rectified-colmap merge``) add every image with features from the inputs to the target,
in the order of their names, so that the merged database is the one a single run over all
images writes (same names, cameras, keypoints and descriptors bit for bit; with a single
sequential run, also the same image and camera ids).

Rules:
- Conflicts are refused before anything is written: the same image name with different
  features in two inputs, or in an input and the target (identical copies are taken once;
  an image already in the target with the same features is left as it is).
- Empty inputs (a shard that got no image: a database and a feature file with no image)
  are accepted and add nothing; a target with no image to add is still created, valid.
- Inputs must not hold matches yet (their pair ids would be meaningless in the target):
  merge shards first, then match.
- Cameras are renumbered; each input camera row stays one camera in the target. Shards of
  a ``--single_camera`` run each made their own camera: merge them with
  ``single_camera=True`` (CLI ``--single_camera``), which unifies identical cameras
  (model, size, parameters, prior), to get the single camera of a single run.
- Inputs are opened through the same locks as the writers: a shard still running is waited
  for. The target is written image by image through the crash-safe writers: an interrupted
  merge leaves valid files and a rerun completes it.
"""

from __future__ import annotations

import contextlib
import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .colmap_db import EXTRACTOR_NAME, ColmapDatabase
from .hloc_h5 import HlocFeatureWriter, _open_read, list_names

logger = logging.getLogger(__name__)


@dataclass
class MergeSummary:
    added: list[str] = field(default_factory=list)
    already: list[str] = field(default_factory=list)
    """Images the target already had, with the same features."""
    without_features: list[str] = field(default_factory=list)
    """Image rows of the inputs that have no features (skipped)."""

    def report(self, target: Path) -> str:
        return (
            f"{target}: {len(self.added)} image(s) added, {len(self.already)} already "
            f"there, {len(self.without_features)} input image(s) without features "
            "skipped"
        )


def _conflict_error(conflicts: dict[str, list[str]]) -> ValueError:
    names = sorted(conflicts)
    shown = "; ".join(f"{n!r} in {' and '.join(conflicts[n])}" for n in names[:3])
    return ValueError(
        f"{len(names)} image(s) have different features under the same name "
        f"({shown}{'; ...' if len(names) > 3 else ''}); nothing was merged"
    )


def merge_databases(
    target: Path | str, inputs: list[Path | str], single_camera: bool = False
) -> MergeSummary:
    """Add the images of the input databases to ``target`` (created when missing)."""
    target = Path(target)
    summary = MergeSummary()
    with contextlib.ExitStack() as stack:
        for path in inputs:
            if not Path(path).is_file():
                raise FileNotFoundError(f"{path}: input database does not exist")
        srcs = [stack.enter_context(ColmapDatabase(p)) for p in inputs]
        for src in srcs:
            n_matches, n_geoms = src.count_matches(src.image_names())
            if n_matches or n_geoms:
                raise ValueError(
                    f"{src.path}: holds {n_matches} match and {n_geoms} two-view "
                    "geometry rows; merge shard outputs before matching them"
                )
        entries = _database_entries(srcs, summary)  # conflicts raise before target exists
        out = stack.enter_context(ColmapDatabase(target))
        conflicts: dict[str, list[str]] = {}
        for name, (src, image_id, _) in entries.items():
            found = out.find_image(name)
            if found is not None and out.has_features(found[0]):
                if _same_db_features(src, image_id, out, found[0]):
                    summary.already.append(name)
                else:
                    conflicts.setdefault(name, [str(src.path)]).append(str(out.path))
        if conflicts:
            raise _conflict_error(conflicts)
        already = set(summary.already)
        todo = {n: e for n, e in entries.items() if n not in already}
        summary.added += _copy_images(out, todo, single_camera)
    return summary


def _database_entries(srcs: list[ColmapDatabase], summary: MergeSummary) -> dict:
    """name -> (input, image_id, camera_id) of the images with features (the first input
    holding a name; images without features listed in ``summary``); the same name with
    different features in two inputs raises."""
    entries: dict[str, tuple[ColmapDatabase, int, int]] = {}
    conflicts: dict[str, list[str]] = {}
    for src in srcs:
        with_features = src.image_ids_with_features()
        for image_id, name in sorted(src.image_names().items()):
            if image_id not in with_features:
                summary.without_features.append(name)
                continue
            if name in entries:
                other, other_id, _ = entries[name]
                if not _same_db_features(src, image_id, other, other_id):
                    conflicts.setdefault(name, [str(other.path)]).append(str(src.path))
                continue
            entries[name] = (src, image_id, src.find_image(name)[1])
    if conflicts:
        raise _conflict_error(conflicts)
    return entries


def _copy_images(out: ColmapDatabase, entries: dict, single_camera: bool) -> list[str]:
    """The images of ``entries`` (as _database_entries) into ``out``, in name order, with
    their cameras (one per input camera; with ``single_camera`` identical cameras shared);
    returns their names."""
    by_source: dict[tuple[int, int], int] = {}  # (input, camera_id) -> target camera
    by_value: dict[tuple, int] = {}  # identical cameras -> target camera (single_camera)
    added = []
    for name in sorted(entries):
        src, image_id, cam_id = entries[name]
        camera = src.get_camera(cam_id)
        value = (
            int(camera.model.value),
            camera.width,
            camera.height,
            np.asarray(camera.params, np.float64).tobytes(),
            camera.has_prior_focal_length,
        )
        target_cam = by_source.get((id(src), cam_id))
        if target_cam is None and single_camera:
            target_cam = by_value.get(value)
        extractor = EXTRACTOR_NAME if image_id in src.ours() else None
        _, target_cam, _ = out.write_image(
            name,
            src.read_features(image_id),
            camera,
            camera.has_prior_focal_length,
            target_cam,
            extractor=extractor,
        )
        by_source[(id(src), cam_id)] = target_cam
        if single_camera:
            by_value.setdefault(value, target_cam)
        added.append(name)
    return added


def _same_db_features(a: ColmapDatabase, ia: int, b: ColmapDatabase, ib: int) -> bool:
    return np.array_equal(a.read_keypoints(ia), b.read_keypoints(ib)) and np.array_equal(
        a.read_descriptors(ia), b.read_descriptors(ib)
    )


def merge_feature_files(target: Path | str, inputs: list[Path | str]) -> MergeSummary:
    """Add the images of the input hloc feature files to ``target``, groups copied bit for
    bit (datasets and attributes)."""
    target = Path(target)
    summary = MergeSummary()
    for path in inputs:
        if not Path(path).exists() and not (Path(str(path) + ".partial")).is_dir():
            raise FileNotFoundError(f"{path}: input feature file does not exist")
        # Completes a killed shard's staged work, under that file's lock (waits for a
        # shard still writing it).
        HlocFeatureWriter(path).close()
    with HlocFeatureWriter(target) as out:
        sources: dict[str, Path] = {}
        conflicts: dict[str, list[str]] = {}
        for path in map(Path, inputs):
            for name in list_names(path):
                if name in sources:
                    if not _same_h5_group(sources[name], path, name):
                        conflicts.setdefault(name, [str(sources[name])]).append(str(path))
                    continue
                sources[name] = path
        for name, path in sources.items():
            if out.has(name):
                if _same_h5_group(path, target, name):
                    summary.already.append(name)
                else:
                    conflicts.setdefault(name, [str(path)]).append(str(target))
        if conflicts:
            raise _conflict_error(conflicts)
        out.create_if_missing()  # also when the inputs hold no image (empty shards)
        already = set(summary.already)
        for name in sorted(sources):
            if name not in already:
                out.copy_from(sources[name], name)
                summary.added.append(name)
    return summary


def _same_h5_group(a: Path, b: Path, name: str) -> bool:
    with _open_read(a) as fa, _open_read(b) as fb:
        ga, gb = fa[name], fb[name]
        if set(ga.keys()) != set(gb.keys()):
            return False
        return all(np.array_equal(ga[k][()], gb[k][()]) for k in ga.keys())
