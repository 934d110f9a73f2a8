"""`rectified-colmap models list|download NAME|info NAME_OR_PATH|export`: the depth-model
registry, and the exporter of a PyTorch network to a contract ONNX file."""

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
    e = msub.add_parser(
        "export",
        help="export a PyTorch depth network to ONNX with the contract (needs torch)",
        description="Export a PyTorch depth network to an ONNX file with the rectified_colmap "
        "contract metadata (opset 17, dynamic size unless --fixed), checked against PyTorch "
        "with onnxruntime. Needs PyTorch: pip install 'rectified-colmap[export]'. The contract "
        "keys are in docs/depth-models.md.",
    )
    e.add_argument(
        "--factory", required=True, help="'package.module:callable' building the nn.Module"
    )
    e.add_argument("--factory_kwargs", default="{}", help="JSON kwargs for the factory")
    e.add_argument("--weights", type=Path, help="state_dict (.pt) to load")
    e.add_argument("--spec", type=Path, help="JSON of contract keys (without prefix)")
    e.add_argument("--output", type=Path, required=True, help="the .onnx file to write")
    e.add_argument("--height", type=int, default=256, help="example input height")
    e.add_argument("--width", type=int, default=320, help="example input width")
    e.add_argument("--fixed", action="store_true", help="fixed input size (default: dynamic)")
    e.add_argument("--fp16", action="store_true", help="fp16 weights, float32 inputs/outputs")
    e.add_argument(
        "--fp16_storage",
        action="store_true",
        help="fp16 weights in the file, float32 arithmetic (half the size)",
    )
    e.add_argument("--no_verify", action="store_true", help="skip the onnxruntime check")
    e.add_argument("--overwrite", action="store_true", help="replace --output if it exists already")
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


def _export(args: argparse.Namespace) -> int:
    from ..depth.export import export_from_factory

    if args.output.exists() and not args.overwrite:
        logger.error("%s: exists already (pass --overwrite to replace it)", args.output)
        return 1
    try:
        kwargs = json.loads(args.factory_kwargs)
    except json.JSONDecodeError as e:
        logger.error("--factory_kwargs: not JSON (%s)", e)
        return 1
    export_from_factory(
        args.factory,
        args.output,
        factory_kwargs=kwargs,
        weights=args.weights,
        spec=args.spec,
        height=args.height,
        width=args.width,
        dynamic=not args.fixed,
        fp16=args.fp16,
        fp16_storage=args.fp16_storage,
        verify=not args.no_verify,
    )
    return 0


def run(args: argparse.Namespace) -> int:
    from ..depth import registry

    try:
        if args.models_command == "export":
            return _export(args)
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
