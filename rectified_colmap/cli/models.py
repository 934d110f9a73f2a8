"""`rectified-colmap models list|download NAME|info NAME_OR_PATH`: the depth-model registry.

(Exporting a PyTorch network to a contract ONNX file is research/scripts/export_depth_model.py:
it needs torch, which the extractor never does.)"""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path

logger = logging.getLogger(__name__)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "models",
        help="list, download and inspect depth models",
        description="Depth networks: the embedded default and public ONNX "
        "models (downloaded on demand into the cache).",
    )
    msub = p.add_subparsers(dest="models_command", required=True)
    msub.add_parser("list", help="registered models, licences and cache state")
    d = msub.add_parser("download", help="fetch a registered model into the cache")
    d.add_argument("name")
    d.add_argument("--force", action="store_true", help="download again even if cached")
    d.add_argument("--no_progress", action="store_true")
    i = msub.add_parser("info", help="contract (preprocessing, output) of a model or file")
    i.add_argument("name_or_path")
    p.set_defaults(func=run)


def _list() -> int:
    from ..depth import registry

    print(f"cache: {registry.cache_dir()}")
    for name, e in registry.REGISTRY.items():
        path = registry.model_path(name)
        state = "present" if path.is_file() else ("missing" if e.embedded else "not downloaded")
        size = f"~{e.approx_mb:g} MB" if e.approx_mb else ""
        origin = "embedded" if e.embedded else (e.url or "")
        print(f"{name:26s} {e.licence:14s} {size:9s} {state:15s} {e.description}")
        print(f"{'':26s} {origin}")
    return 0


def _info(name_or_path: str) -> int:
    from ..depth import registry
    from ..depth.contract import ModelSpec, find_sidecar

    path = registry.resolve_model(name_or_path, download_missing=False)
    entry = registry.REGISTRY.get(name_or_path)
    spec = ModelSpec.from_onnx(path, fallback=entry.spec if entry else None)
    print(f"file: {path} ({Path(path).stat().st_size / 1e6:.1f} MB)")
    sidecar = find_sidecar(path)
    if sidecar:
        print(f"sidecar: {sidecar}")
    if entry is not None:
        print(
            f"registry: {entry.name}, licence {entry.licence}, sha256 "
            f"{registry.expected_sha256(entry) or 'not pinned'}"
        )
    print(json.dumps({k: v for k, v in vars(spec).items()}, indent=2))
    return 0


def run(args: argparse.Namespace) -> int:
    from ..depth import registry

    try:
        if args.models_command == "list":
            return _list()
        if args.models_command == "download":
            path = registry.download(args.name, force=args.force, progress=not args.no_progress)
            print(path)
            return 0
        return _info(args.name_or_path)
    except (ValueError, FileNotFoundError, ImportError, registry.ModelDownloadError) as e:
        logger.error("%s", e)
        return 1
