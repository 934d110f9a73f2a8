"""Image pairs with ground truth: the SuperGlue pair format, and dataset readers.

SuperGlue format, one pair per line (whitespace separated)::

    name0 name1 rot0 rot1 K0(9 values, row-major) K1(9) T_0to1(16, row-major 4x4)

``T_0to1`` maps points from camera 0 to camera 1 (X1 = R X0 + t). ``rot0``/``rot1`` are
EXIF-style rotations (multiples of 90 degrees) that SuperGlue applies to the images; this
package evaluates images as stored, so non-zero rotations are rejected with a clear error.
K is in COLMAP's pixel convention here (the pair files of /work/shared/data/strecha-dev are
written from COLMAP models); the relative-pose metrics of rectified_colmap.eval.relpose do
not depend on a 0.5 px shift beyond the RANSAC noise anyway.

Lines with only ``name0 name1`` are pairs without ground truth (hloc pair lists).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..geometry import rotation_angle_deg  # noqa: F401 (also importable from here)

logger = logging.getLogger(__name__)


@dataclass
class Pair:
    name0: str
    name1: str
    K0: np.ndarray
    """(3, 3) intrinsics of image 0, COLMAP pixel convention."""
    K1: np.ndarray
    T_0to1: np.ndarray
    """(4, 4) rigid transform from camera 0 to camera 1."""
    category: str | None = None
    """Optional dataset category (e.g. a Strong Viewpoint Changes difficulty bin)."""

    @property
    def R(self) -> np.ndarray:
        return self.T_0to1[:3, :3]

    @property
    def t(self) -> np.ndarray:
        return self.T_0to1[:3, 3]

    @property
    def rotation_deg(self) -> float:
        """Angle of the ground-truth relative rotation (degrees)."""
        return rotation_angle_deg(self.R)


def parse_pair_line(line: str, where: str = "") -> Pair:
    """One SuperGlue-format line -> Pair (raises ValueError naming ``where``)."""
    parts = line.split()
    if len(parts) != 38:
        raise ValueError(
            f"{where}: expected 38 fields (name0 name1 rot0 rot1 K0[9] K1[9] "
            f"T_0to1[16]), got {len(parts)}"
        )
    try:
        rot0, rot1 = int(parts[2]), int(parts[3])
        vals = np.array([float(v) for v in parts[4:]], dtype=np.float64)
    except ValueError as e:
        raise ValueError(f"{where}: non-numeric field ({e})") from None
    if rot0 or rot1:
        raise ValueError(
            f"{where}: EXIF rotations ({rot0}, {rot1}) are not supported: "
            "rotate the images and their intrinsics beforehand"
        )
    K0, K1, T = vals[:9].reshape(3, 3), vals[9:18].reshape(3, 3), vals[18:].reshape(4, 4)
    if not np.all(np.isfinite(vals)):
        raise ValueError(f"{where}: non-finite values")
    R = T[:3, :3]
    if np.abs(R @ R.T - np.eye(3)).max() > 1e-3 or np.linalg.det(R) < 0:
        raise ValueError(f"{where}: T_0to1 does not hold a rotation")
    return Pair(parts[0], parts[1], K0, K1, T)


def read_pairs_with_gt(path: Path | str) -> list[Pair]:
    """Read a SuperGlue-format pair file (comments with '#' and blank lines skipped)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: pair file not found")
    pairs = []
    for i, line in enumerate(path.read_text().splitlines(), 1):
        line = line.split("#", 1)[0].strip()
        if line:
            pairs.append(parse_pair_line(line, f"{path}:{i}"))
    if not pairs:
        raise ValueError(f"{path}: no pairs")
    return pairs


def format_pair_line(pair: Pair) -> str:
    vals = np.concatenate([pair.K0.ravel(), pair.K1.ravel(), pair.T_0to1.ravel()])
    return " ".join([pair.name0, pair.name1, "0", "0"] + [f"{v:.10g}" for v in vals])


def write_pairs_with_gt(path: Path | str, pairs: list[Pair]) -> None:
    Path(path).write_text("".join(format_pair_line(p) + "\n" for p in pairs))


def read_pair_list(path: Path | str) -> list[tuple[str, str]]:
    """An hloc pair list (``name0 name1`` per line; extra fields ignored)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: pair list not found")
    out = []
    for i, line in enumerate(path.read_text().splitlines(), 1):
        parts = line.split("#", 1)[0].split()
        if not parts:
            continue
        if len(parts) < 2:
            raise ValueError(f"{path}:{i}: expected 'name0 name1'")
        out.append((parts[0], parts[1]))
    return out


def write_pair_list(path: Path | str, pairs: list[tuple[str, str]]) -> None:
    """Write an hloc pair list; names must not contain whitespace (hloc splits on it)."""
    for a, b in pairs:
        if len(a.split()) != 1 or len(b.split()) != 1:
            raise ValueError(
                f"{path}: image names with whitespace cannot go in a pair list: {a!r} {b!r}"
            )
    Path(path).write_text("".join(f"{a} {b}\n" for a, b in pairs))


def pairs_from_model(
    reconstruction, names: list[str] | None = None, prefix: str = ""
) -> list[Pair]:
    """All pairs (i < j) of registered images of a pycolmap.Reconstruction, with GT.

    Only pinhole cameras (SIMPLE_PINHOLE, PINHOLE) are allowed: K must be the whole model.
    ``prefix`` is prepended to the image names (e.g. "images/").
    """
    images = sorted(
        (im for im in reconstruction.images.values() if im.has_pose), key=lambda im: im.name
    )
    if names is not None:
        keep = set(names)
        images = [im for im in images if im.name in keep]
    out = []
    for i, a in enumerate(images):
        for b in images[i + 1 :]:
            ca, cb = reconstruction.cameras[a.camera_id], reconstruction.cameras[b.camera_id]
            for c in (ca, cb):
                if c.model.name not in ("SIMPLE_PINHOLE", "PINHOLE"):
                    raise ValueError(
                        f"camera {c.camera_id} is {c.model.name}: pair ground "
                        "truth needs pinhole cameras"
                    )
            T = (b.cam_from_world() * a.cam_from_world().inverse()).matrix()
            T = np.vstack([T, [0, 0, 0, 1]])
            out.append(
                Pair(
                    prefix + a.name,
                    prefix + b.name,
                    np.asarray(ca.calibration_matrix()),
                    np.asarray(cb.calibration_matrix()),
                    T,
                )
            )
    return out


# -- Strong Viewpoint Changes (Toft et al. ECCV 2020), best effort -------------------------


def _scene_pairs(scene: Path) -> tuple[list[Pair], dict[tuple[str, str], str]] | None:
    """One scene folder's pairs and their categories from pairs.txt ({} without it), or None
    when the folder has neither pairs_with_gt.txt nor a COLMAP model."""
    import pycolmap

    if (scene / "pairs_with_gt.txt").is_file():
        return read_pairs_with_gt(scene / "pairs_with_gt.txt"), {}
    model = next(
        (
            scene / d
            for d in ("sparse", "model")
            if (scene / d / "images.bin").is_file() or (scene / d / "images.txt").is_file()
        ),
        None,
    )
    if model is None:
        return None
    pairs = pairs_from_model(pycolmap.Reconstruction(str(model)))
    cats: dict[tuple[str, str], str] = {}
    if (scene / "pairs.txt").is_file():
        for line in (scene / "pairs.txt").read_text().splitlines():
            parts = line.split()
            if len(parts) >= 2:
                cats[(parts[0], parts[1])] = parts[2] if len(parts) > 2 else ""
        pairs = [p for p in pairs if (p.name0, p.name1) in cats]
    return pairs, cats


def read_strong_viewpoint_changes(root: Path | str) -> list[Pair]:
    """Best-effort reader of the Strong Viewpoint Changes dataset (Toft et al., ECCV 2020).

    Published description: 8 scenes; image pairs in 18 difficulty categories (10-degree bins
    of the relative rotation, 0-180 degrees); intrinsics and poses per image. The exact file
    layout of the release could not be checked here, so this reader accepts, per scene
    folder ``root/<scene>/``, either

    1. ``pairs_with_gt.txt`` (SuperGlue format, names relative to the scene folder), or
    2. ``sparse/`` (or ``model/``): a COLMAP model with pinhole cameras and poses, plus an
       optional ``pairs.txt`` (``name0 name1 [category]``) selecting the pairs; without
       ``pairs.txt`` every pair of the model is used.

    Names are returned as ``<scene>/<name>``; the category is the one given in pairs.txt,
    else the 10-degree bin of the ground-truth rotation (``"20-30"``), which is how the
    paper defines the 18 difficulty categories.
    """
    root = Path(root)
    if not root.is_dir():
        raise FileNotFoundError(f"{root}: dataset folder not found")
    out: list[Pair] = []
    for scene in sorted(p for p in root.iterdir() if p.is_dir()):
        found = _scene_pairs(scene)
        if found is None:
            logger.warning("%s: neither pairs_with_gt.txt nor a COLMAP model; skipped", scene)
            continue
        pairs, cats = found
        for p in pairs:
            cat = cats.get((p.name0, p.name1)) or None
            if cat is None:
                lo = min(int(p.rotation_deg // 10) * 10, 170)
                cat = f"{lo}-{lo + 10}"
            out.append(
                Pair(
                    f"{scene.name}/{p.name0}", f"{scene.name}/{p.name1}", p.K0, p.K1, p.T_0to1, cat
                )
            )
    if not out:
        raise ValueError(
            f"{root}: no scene with pairs found (see "
            "read_strong_viewpoint_changes for the accepted layouts)"
        )
    return out
