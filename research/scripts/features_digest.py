#!/usr/bin/env python
"""Digests of the features the CLI writes, to show that a refactor changes no output.

For every image folder given (e.g. each strecha-dev scene's images/ and evd-dev's images/)
and every named configuration, runs ``rectified-colmap extract --hloc_features`` (the whole
path: cameras, depth network, pipeline, writer) into ``--output_dir`` and writes
``digest.json``: conf -> folder -> image -> sha256 of the keypoints, descriptors, scales and
orientations as stored, and their count. ``--compare OLD.json`` lists every image whose
features differ (exit 1 when any does).

    python research/scripts/features_digest.py --images ../shared/data/strecha-dev/*/images \\
        ../shared/data/evd-dev/images --confs rectsift rectsift-fast sift \\
        --output_dir outputs/digest-before
    python research/scripts/features_digest.py ... --output_dir outputs/digest-after \\
        --compare outputs/digest-before/digest.json
"""

from __future__ import annotations

import argparse
import hashlib
import json
import logging
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np

from rectified_colmap.errors import run_script

logger = logging.getLogger("features_digest")
DATASETS = ("keypoints", "descriptors", "scales", "oris")


def h5_digest(path: Path) -> dict[str, dict]:
    """image name -> {"n": keypoints, "sha256": hash of the stored arrays}."""
    out = {}
    with h5py.File(path, "r") as f:

        def visit(name, obj):
            if isinstance(obj, h5py.Group) and "keypoints" in obj:
                h = hashlib.sha256()
                for key in DATASETS:
                    if key in obj:
                        h.update(key.encode() + np.ascontiguousarray(obj[key][()]).tobytes())
                out[name] = {"n": int(obj["keypoints"].shape[0]), "sha256": h.hexdigest()}

        f.visititems(visit)
    return out


def differences(old: dict, new: dict) -> list[str]:
    """'conf folder image: why' for every image whose digest differs or is missing."""
    lines = []
    for conf in sorted(set(old) | set(new)):
        for folder in sorted(set(old.get(conf, {})) | set(new.get(conf, {}))):
            a, b = old.get(conf, {}).get(folder, {}), new.get(conf, {}).get(folder, {})
            for image in sorted(set(a) | set(b)):
                if a.get(image) != b.get(image):
                    lines.append(f"{conf} {folder} {image}: {a.get(image)} -> {b.get(image)}")
    return lines


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--images", type=Path, nargs="+", required=True, help="image folders")
    p.add_argument("--confs", nargs="+", default=["rectsift", "rectsift-fast", "sift"])
    p.add_argument("--output_dir", type=Path, required=True)
    p.add_argument("--compare", type=Path, help="an earlier digest.json")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="[%(asctime)s %(name)s] %(message)s")
    digest: dict[str, dict] = {}
    for conf in args.confs:
        for folder in args.images:
            label = f"{folder.parent.name}/{folder.name}"
            h5 = args.output_dir / conf / f"{folder.parent.name}-{folder.name}.h5"
            h5.parent.mkdir(parents=True, exist_ok=True)
            cmd = [sys.executable, "-m", "rectified_colmap.cli", "extract"]
            cmd += ["--image_path", str(folder), "--hloc_features", str(h5)]
            cmd += ["--conf", conf, "--no_progress", "--log_level", "WARNING"]
            rc = subprocess.run(cmd).returncode  # the console script, as a user runs it
            if rc != 0:
                logger.error("%s %s: extract exited with %d", conf, label, rc)
                return rc
            digest.setdefault(conf, {})[label] = h5_digest(h5)
    out = args.output_dir / "digest.json"
    out.write_text(json.dumps(digest, indent=1, sort_keys=True))
    n = sum(len(v) for c in digest.values() for v in c.values())
    print(f"{n} image digests in {out}")
    if args.compare is not None:
        diff = differences(json.loads(args.compare.read_text()), digest)
        print("\n".join(diff) if diff else f"identical to {args.compare}")
        return 1 if diff else 0
    return 0


if __name__ == "__main__":
    sys.exit(run_script(main, "features_digest"))
