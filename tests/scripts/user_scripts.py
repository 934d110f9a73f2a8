"""The top-level scripts/*.py (what users run) as modules, and the data their end-to-end
tests need: the shared folder beside the checkout (``../shared``), or the folder in
``RECTIFIED_COLMAP_SHARED``."""

from __future__ import annotations

import importlib.util
import os
from pathlib import Path
from types import ModuleType

import pytest

ROOT = Path(__file__).resolve().parents[2]
SCRIPTS = ROOT / "scripts"
SHARED = Path(os.environ.get("RECTIFIED_COLMAP_SHARED", ROOT.parent / "shared"))
SACRE_COEUR = SHARED / "vendor" / "hloc" / "datasets" / "sacre_coeur" / "mapping"
FOUNTAIN = SHARED / "data" / "strecha-dev" / "fountain-P11"


def load_user_script(name: str) -> ModuleType:
    """scripts/<name>.py imported as a module named ``name`` (not registered in
    sys.modules)."""
    spec = importlib.util.spec_from_file_location(name, SCRIPTS / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def hloc_missing() -> str | None:
    """Why hloc cannot be used here (docs/hloc.md), or None."""
    from rectified_colmap.eval.hloc_compat import HlocError, import_hloc

    try:
        import_hloc()
    except HlocError as e:
        return str(e)
    return None


def needs(path: Path) -> None:
    """Skip, with the reason, without the shared data."""
    if not path.is_dir():
        pytest.skip(
            f"{path} not found (shared data beside the checkout, or set RECTIFIED_COLMAP_SHARED)"
        )
