"""hloc with this package's features under the pycolmap 4.2 pin (docs/hloc.md, "Pitfalls").

Importing this module does not import hloc; the functions that drive hloc import it on use.

- :func:`import_hloc`: hloc and the modules the scripts use, or :class:`HlocError` with the
  reason (not installed, a dependency such as torch missing, an API generation this code
  does not know) and how to install it;
- hloc's two API generations (both say version 1.5): since upstream commit 374799c
  (2025-09-22) ``hloc.triangulation.import_features`` / ``import_matches`` /
  ``geometric_verification`` take an open ``pycolmap.Database`` (parameter ``db``), before
  that a path (``database_path``). :func:`hloc_generation` tells them apart by signature;
  :func:`call_with` passes each function the arguments it names;
- the pycolmap 4.2 fix: hloc's triangulation writes two-view geometries with config
  UNDEFINED, which pycolmap 4.2.1's DatabaseCache skips ("written by an outdated
  producer"), so 0 points get triangulated. :func:`set_two_view_config` rewrites them as
  ``CALIBRATED`` (the poses are known); :func:`triangulate_with_hloc` runs hloc's
  triangulation steps with it. :func:`two_view_counts` tells what a database holds
  (hloc's ``reconstruction.main`` verifies matches itself and is not hit);
- localize_sfm's silent fallback (a query it cannot localize gets the pose of its first
  retrieved image): :func:`localize_sfm_fallbacks` reads them back from hloc's log.
"""

from __future__ import annotations

import importlib
import inspect
import logging
import pickle
from pathlib import Path

import numpy as np
import pycolmap

logger = logging.getLogger(__name__)


class HlocError(RuntimeError):
    """hloc is missing, cannot be imported, or has an API this code does not know."""


HLOC_INSTALL = (
    "hloc is not on PyPI: clone its GitHub repository "
    "(cvg/Hierarchical-Localization) and `pip install --no-deps -e .` in it (in this "
    "project's development checkout: a copy of ../shared/vendor/hloc, pip builds in the "
    "source tree); it needs torch, kornia, scipy, matplotlib and plotly (docs/hloc.md)"
)

HLOC_MODULES = (
    "extract_features",
    "match_features",
    "pairs_from_exhaustive",
    "pairs_from_covisibility",
    "reconstruction",
    "triangulation",
    "localize_sfm",
)
"""The hloc modules scripts/aachen_hloc.py and scripts/hloc_sfm.py use."""


def import_hloc(modules: tuple[str, ...] = HLOC_MODULES):
    """Import hloc and ``modules`` of it; :class:`HlocError` says why not."""
    try:
        import hloc

        for name in modules:
            importlib.import_module(f"hloc.{name}")
    except ImportError as e:
        missing = getattr(e, "name", None) or str(e)
        if missing == "hloc" or missing.startswith("hloc"):
            raise HlocError(f"hloc is not installed. {HLOC_INSTALL}") from None
        raise HlocError(
            f"hloc is installed but cannot be imported: {e} "
            f"(missing dependency {missing!r}). {HLOC_INSTALL}"
        ) from None
    from hloc import triangulation

    hloc_generation(triangulation)  # raises HlocError when unknown
    return hloc


def hloc_generation(triangulation) -> str:
    """'db' (hloc after 2025-09-22: an open pycolmap.Database) or 'path' (before: a database
    path), from the signature of ``triangulation.import_features``; both say version 1.5."""
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


# -- two-view geometries: the pycolmap 4.2 fix ----------------------------------------------


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


def two_view_counts(database: Path | str) -> dict[str, int]:
    """What the mapper can use in a database: ``verified_pairs`` (a configuration of
    CALIBRATED or above, with inliers) and their ``verified_inliers``, and
    ``undefined_pairs``: geometries with inliers but config UNDEFINED, which pycolmap 4.2
    skips (pitfall 1 of docs/hloc.md)."""
    database = Path(database)
    if not database.is_file():
        raise FileNotFoundError(f"{database}: database not found")
    conf = pycolmap.TwoViewGeometryConfiguration
    out = {"verified_pairs": 0, "verified_inliers": 0, "undefined_pairs": 0}
    with pycolmap.Database.open(database) as db:
        for g in db.read_two_view_geometries()[1]:
            n = len(g.inlier_matches)
            if n == 0:
                continue
            c = conf(g.config)
            if c == conf.UNDEFINED:
                out["undefined_pairs"] += 1
            elif int(c) >= int(conf.CALIBRATED):
                out["verified_pairs"] += 1
                out["verified_inliers"] += n
    return out


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
    import_hloc(("triangulation",))
    from hloc import triangulation

    generation = hloc_generation(triangulation)
    sfm_dir, features, pairs, matches = map(Path, (sfm_dir, features, pairs, matches))
    sfm_dir.mkdir(parents=True, exist_ok=True)
    database = sfm_dir / "database.db"
    reference = reference_model
    if not isinstance(reference, pycolmap.Reconstruction):
        reference = pycolmap.Reconstruction(str(reference))
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
    steps = (
        triangulation.import_features,
        triangulation.import_matches,
        triangulation.geometric_verification,
    )
    if generation == "db":
        with pycolmap.Database.open(database) as db:
            for step in steps:
                call_with(step, db=db, **args)
    else:
        for step in steps:
            call_with(step, database_path=database, **args)
    set_two_view_config(database, "CALIBRATED")  # the pycolmap 4.2 fix (it logs how many)
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
