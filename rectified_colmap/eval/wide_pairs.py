"""Wide-baseline image pairs from a reconstruction: co-visibility and viewpoint change.

MegaDepth and the Image Matching Challenge build their pairs this way: poses come from the
full reconstruction of a photo collection, and a pair is kept when the two images observe
enough common 3D points. What makes a pair hard for local features is how differently
the two cameras see the surface, not the rotation between them (two cameras side by side
looking at the same facade differ little in rotation but see it from different angles).
So each pair is also described by its *viewpoint change*: the median, over the 3D points
both images observe, of the angle between the two viewing rays (camera centre to point);
for a point on a surface this is the change of the viewing direction on it.

Conventions: camera centres and points (N, 3) in world coordinates of the reconstruction;
angles in degrees. The pycolmap adapters read a ``pycolmap.Reconstruction``: registered
images only, tracks from ``points3D``.
"""

from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..geometry import rotation_angle_deg


def viewing_angles_deg(center0: np.ndarray, center1: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(N,) angle between the rays from ``center0`` and from ``center1`` (3,) to each of
    ``points`` (N, 3): 0 when both see the point from the same direction, 180 from opposite
    sides. A point at a camera centre gives NaN."""
    a = np.asarray(points, float).reshape(-1, 3) - np.asarray(center0, float)
    b = np.asarray(points, float).reshape(-1, 3) - np.asarray(center1, float)
    sin = np.linalg.norm(np.cross(a, b), axis=1)  # atan2: accurate near 0 and 180 too
    out = np.degrees(np.arctan2(sin, np.einsum("ij,ij->i", a, b)))
    out[(np.abs(a).sum(1) == 0) | (np.abs(b).sum(1) == 0)] = np.nan
    return out


def incidence(tracks: list[np.ndarray], num_images: int) -> np.ndarray:
    """(num_images, P) bool: image i observes point p. ``tracks[p]``: the indices (into
    0..num_images-1) of the images observing point p, repeats allowed."""
    out = np.zeros((num_images, len(tracks)), bool)
    if tracks:
        lengths = np.fromiter((len(t) for t in tracks), int, len(tracks))
        cols = np.repeat(np.arange(len(tracks)), lengths)
        rows = np.concatenate([np.asarray(t, int) for t in tracks]) if lengths.sum() else []
        out[rows, cols] = True
    return out


@dataclass
class WidePair:
    """Two images of one reconstruction (name0 < name1) and how they relate."""

    name0: str
    name1: str
    num_covisible: int
    """3D points observed by both images."""
    viewpoint_deg: float
    """Median angle between the two viewing rays of the co-visible points."""
    rotation_deg: float
    """Angle of the relative rotation of the two cameras."""


def select_pairs(
    names: list[str],
    centers: np.ndarray,
    rotations: np.ndarray,
    points: np.ndarray,
    seen: np.ndarray,
    min_covisible: int = 30,
    min_viewpoint_deg: float = 0.0,
    max_viewpoint_deg: float = 180.0,
) -> list[WidePair]:
    """Every pair of images (i < j in the order of ``names``) with at least
    ``min_covisible`` common points and a viewpoint change in [min, max].

    names: (n,) image names; centers: (n, 3) camera centres; rotations: (n, 3, 3)
    cam_from_world rotations; points: (P, 3); seen: (n, P) bool incidence.
    Sorted by viewpoint change, then names."""
    seen = np.asarray(seen, bool)
    counts = seen.astype(np.int32) @ seen.T.astype(np.int32)
    out = []
    for i, j in zip(*np.nonzero(np.triu(counts >= max(min_covisible, 1), 1))):
        common = seen[i] & seen[j]
        angle = float(np.nanmedian(viewing_angles_deg(centers[i], centers[j], points[common])))
        if not min_viewpoint_deg <= angle <= max_viewpoint_deg:
            continue
        r = rotation_angle_deg(rotations[j] @ rotations[i].T)
        a, b = (i, j) if names[i] <= names[j] else (j, i)
        out.append(WidePair(names[a], names[b], int(counts[i, j]), angle, float(r)))
    out.sort(key=lambda p: (p.viewpoint_deg, p.name0, p.name1))
    return out


def reconstruction_arrays(rec) -> tuple[list[str], np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(names, centers (n, 3), rotations (n, 3, 3), points (P, 3), seen (n, P)) of a
    pycolmap.Reconstruction's registered images, sorted by name."""
    images = sorted((im for im in rec.images.values() if im.has_pose), key=lambda im: im.name)
    index = {im.image_id: k for k, im in enumerate(images)}
    centers = np.array([im.projection_center() for im in images], float).reshape(-1, 3)
    rotations = np.array([im.cam_from_world().rotation.matrix() for im in images], float).reshape(
        -1, 3, 3
    )
    pts = list(rec.points3D.values())
    points = np.array([p.xyz for p in pts], float).reshape(-1, 3)
    tracks = [
        np.array([index[e.image_id] for e in p.track.elements if e.image_id in index], int)
        for p in pts
    ]
    return [im.name for im in images], centers, rotations, points, incidence(tracks, len(images))


def wide_pairs(rec, **kw) -> list[WidePair]:
    """select_pairs on a pycolmap.Reconstruction (keyword arguments: its thresholds)."""
    return select_pairs(*reconstruction_arrays(rec), **kw)


CSV_FIELDS = ("name0", "name1", "num_covisible", "viewpoint_deg", "rotation_deg")


def write_pairs_csv(path: Path | str, pairs: list[WidePair], prefix: str = "") -> None:
    """One row per pair (CSV_FIELDS); ``prefix`` before the names (e.g. "images/")."""
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(CSV_FIELDS)
        for p in pairs:
            w.writerow(
                [
                    prefix + p.name0,
                    prefix + p.name1,
                    p.num_covisible,
                    f"{p.viewpoint_deg:.2f}",
                    f"{p.rotation_deg:.2f}",
                ]
            )


def read_viewpoints(path: Path | str) -> dict[tuple[str, str], float]:
    """(name0, name1) -> viewpoint change (degrees) from a file of write_pairs_csv."""
    with open(path, newline="") as f:
        return {(r["name0"], r["name1"]): float(r["viewpoint_deg"]) for r in csv.DictReader(f)}
