"""Helpers for Aachen Day-Night with hloc that do not need hloc (scripts/aachen_hloc.py).

- query lists with intrinsics (``name MODEL W H params...``, what localize_sfm parses);
- hloc pair lists restricted to the images of a reference model (hloc raises KeyError on
  any other name);
- the pycolmap 4.2 fix: hloc's triangulation writes two-view geometries with config
  UNDEFINED, which pycolmap 4.2.1's DatabaseCache skips ("written by an outdated
  producer"), so 0 points get triangulated. :func:`set_two_view_config` rewrites them with
  ``CALIBRATED`` (the poses are known) before ``triangulate_points``;
- result files (``basename qw qx qy qz tx ty tz``, cam_from_world), validated against the
  query list (the benchmark server keys queries by base name).

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
            cam = pycolmap.Camera(model=model, width=int(w), height=int(h),
                                  params=[float(p) for p in params])
        except Exception as e:
            raise ValueError(f"{path}:{i}: invalid camera ({e})") from None
        if not cam.verify_params():
            raise ValueError(f"{path}:{i}: {len(params)} params do not fit model {model}")
        out[name] = cam
    return out


def filter_pairs(pairs: list[tuple[str, str]], names: set[str] | list[str],
                 both: bool = True) -> list[tuple[str, str]]:
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


def set_two_view_config(database: Path | str, config: str = "CALIBRATED",
                        only_undefined: bool = True) -> int:
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


def group_by_camera(cameras: Mapping[str, pycolmap.Camera]
                    ) -> list[tuple[str, tuple[float, ...], list[str]]]:
    """Queries grouped by identical (model, size, params): one extraction call per group.

    Returns [(model name, params, names)], names sorted, groups in first-seen order."""
    groups: dict[tuple, list[str]] = {}
    for name, cam in cameras.items():
        key = (cam.model.name, cam.width, cam.height, tuple(float(p) for p in cam.params))
        groups.setdefault(key, []).append(name)
    return [(k[0], k[3], sorted(v)) for k, v in groups.items()]
