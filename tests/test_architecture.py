"""The layout follows the data flow (docs/architecture.md, issue 14): no lower stage imports a
higher one, the CLI stays a thin layer nobody imports, scripts run from the installed package,
and every module is in the module map.

The import graph is read with ``ast`` from the sources (module-level AND in-function imports,
relative ones resolved), so nothing is imported to check it.
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PKG = ROOT / "rectified_colmap"

# Stage of each module (dotted name under rectified_colmap; a package covers its modules
# unless a longer name is listed). A module may import its own stage and lower ones.
LEVELS = {
    "": 13,  # rectified_colmap/__init__.py: the public API, re-exported from the stages
    "config": 0,
    "errors": 0,  # one-line messages of the CLI and the scripts
    "conventions": 0,
    "geometry": 0,
    "camera": 0,
    "io": 0,
    "io.images": 0,
    "io.lock": 0,
    "parallel": 0,  # worker processes: start method (never fork), log records sent back
    "progress": 0,  # progress bars that log lines do not break
    "depth": 1,  # DepthMap, sources (files, ONNX, registry, contract): raw maps
    "normals": 2,
    "planes": 3,
    "disparity": 4,  # disparity -> depth: choosing the shift fits normals and planes
    "vp": 4,  # vanishing points: refine / replace the plane directions
    "vp.segments": 4,  # LSD segments on the Gaussian sphere
    "vp.manhattan": 4,  # Manhattan frame, a-contrario trust test
    "vp.fusion": 4,  # fusion with the depth directions, the entry point
    "rectify": 5,  # one patch -> its virtual camera, warp, map back
    "views": 5,  # the views of an image: which patches, tilt neighbours, pixel budget
    "features": 6,  # the Features container
    "sift": 6,  # COLMAP SIFT on the image and in its views
    "budget": 6,  # the feature budget: cap, views' budgets, the cut
    "dedup": 7,
    "io.colmap_db": 8,
    "io.hloc_h5": 8,
    "io.merge": 8,  # writers of Features
    "pipeline": 9,
    "viz": 9,
    "extraction": 10,
    "eval": 11,
    "training": 11,
    "demo": 11,
    "cli": 12,
}

# Known violations, (module, import); remove an entry when its import goes (a stale entry
# fails below).
ALLOWED: set[tuple[str, str]] = set()

# Scripts still putting the repository on sys.path (issue 14, item 6; none left); they
# should run from the installed package like the others.
SYS_PATH_ALLOWED: set[str] = set()


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(PKG).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


MODULES = {_module_name(p): p for p in sorted(PKG.rglob("*.py"))}


def _imports(path: Path, package: str) -> set[str]:
    """Package modules (names relative to rectified_colmap) that ``path`` imports anywhere in
    its body; ``package`` is the dotted package the file is in ("" at the top)."""
    out = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".") if package else []
                base = base[: len(base) - (node.level - 1)]
                target = ".".join(base + ([node.module] if node.module else []))
            elif node.module and (
                node.module == "rectified_colmap" or node.module.startswith("rectified_colmap.")
            ):
                target = (
                    node.module[len("rectified_colmap.") :]
                    if node.module != "rectified_colmap"
                    else ""
                )
            else:
                continue
            for alias in node.names:
                sub = f"{target}.{alias.name}" if target else alias.name
                out.add(sub if sub in MODULES else target)
        elif isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name.startswith("rectified_colmap."):
                    out.add(alias.name[len("rectified_colmap.") :])
    return out


def _graph() -> dict[str, set[str]]:
    graph = {}
    for name, path in MODULES.items():
        package = name if path.name == "__init__.py" else name.rpartition(".")[0]
        graph[name] = _imports(path, package) - {name}
    return graph


def _level(name: str) -> int | None:
    """The stage of a module: its own entry or its package's (the top package's entry, the
    public API of __init__.py, covers no module)."""
    if name == "":
        return LEVELS[""]
    while name:
        if name in LEVELS:
            return LEVELS[name]
        name = name.rpartition(".")[0]
    return None


def test_every_module_has_a_stage():
    missing = [m for m in MODULES if _level(m) is None]
    assert not missing, (
        f"place {missing} in LEVELS of tests/test_architecture.py (and in "
        "the module map of docs/architecture.md)"
    )


def test_graph_reader_sees_relative_and_in_function_imports():
    g = _graph()
    assert {"camera", "geometry", "planes", "conventions"} <= g["rectify"]
    assert {"depth", "normals", "planes"} <= g["disparity"]
    assert "io.hloc_h5" in g["eval.matching"]  # ..io.hloc_h5
    assert "depth" in g["depth.files"]  # "from . import DepthMap" in depth/
    assert "eval.matching" in g["cli"]  # cli/__init__.py, in a function


def test_no_lower_stage_imports_a_higher_one():
    bad = sorted(
        (m, t)
        for m, targets in _graph().items()
        for t in targets
        if _level(t) > _level(m) and (m, t) not in ALLOWED
    )
    assert not bad, "lower stage imports a higher one (module -> import): " + ", ".join(
        f"{m} ({_level(m)}) -> {t} ({_level(t)})" for m, t in bad
    )


def test_allowed_violations_still_exist():
    g = _graph()
    stale = sorted((m, t) for m, t in ALLOWED if t not in g.get(m, set()))
    assert not stale, f"remove {stale} from ALLOWED in tests/test_architecture.py"


def test_cli_is_a_thin_layer_nobody_imports():
    g = _graph()
    users = sorted(
        m
        for m, targets in g.items()
        if not m.startswith("cli") and any(t == "cli" or t.startswith("cli.") for t in targets)
    )
    assert not users, f"package modules importing the CLI: {users}"
    cross = sorted(
        (m, t)
        for m, targets in g.items()
        if m.startswith("cli.")
        for t in targets
        if t.startswith("cli.") and t != m
    )
    assert not cross, f"CLI modules importing each other (shared code belongs below): {cross}"


SCRIPTS = sorted(
    p.relative_to(ROOT).as_posix()
    for folder in ("scripts", "research/scripts")
    for p in (ROOT / folder).glob("*.py")
)


@pytest.mark.parametrize("script", SCRIPTS)
def test_scripts_use_the_installed_package(script):
    """Scripts import the package's API, never its CLI, nor edit sys.path; the user scripts
    (scripts/) import no research code (the research project is not installed)."""
    text = (ROOT / script).read_text()
    tree = ast.parse(text)
    modules = {n.module for n in ast.walk(tree) if isinstance(n, ast.ImportFrom) and n.module}
    modules |= {a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names}
    assert not any(
        m == "rectified_colmap.cli" or m.startswith("rectified_colmap.cli.") for m in modules
    ), f"{script} imports the CLI; use the API (eval/, ...)"
    if script.startswith("scripts/"):
        research = sorted(m for m in modules if m.startswith("rectified_colmap_research"))
        assert not research, f"{script} imports research code {research}"
    if script not in SYS_PATH_ALLOWED:
        assert not re.search(r"sys\.path\.(insert|append)|sys\.path\[", text), (
            f"{script} edits sys.path; import rectified_colmap from the installed package"
        )


def test_module_map_lists_every_module():
    doc = (ROOT / "docs" / "architecture.md").read_text()
    listed = set(re.findall(r"^\| `([^`]+)`", doc, flags=re.M))
    missing = []
    for path in MODULES.values():
        rel = path.relative_to(PKG).as_posix()
        parents = [p.as_posix() + "/" for p in path.relative_to(PKG).parents if p.as_posix() != "."]
        if rel not in listed and not any(p in listed for p in parents):
            missing.append(rel)
    assert not missing, f"docs/architecture.md's module map lacks {missing}"
    gone = sorted(e for e in listed if not (PKG / e.rstrip("/")).exists())
    assert not gone, f"docs/architecture.md's module map lists missing files {gone}"


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan, iterative)."""
    index, low, on, stack, out = {}, {}, set(), [], []
    for root in graph:
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = len(index)
        stack.append(root)
        on.add(root)
        while work:
            node, it = work[-1]
            for nxt in it:
                if nxt not in graph:
                    continue
                if nxt not in index:
                    index[nxt] = low[nxt] = len(index)
                    stack.append(nxt)
                    on.add(nxt)
                    work.append((nxt, iter(sorted(graph[nxt]))))
                    break
                if nxt in on:
                    low[node] = min(low[node], index[nxt])
            else:
                work.pop()
                if work:
                    low[work[-1][0]] = min(low[work[-1][0]], low[node])
                if low[node] == index[node]:
                    comp = []
                    while True:
                        m = stack.pop()
                        on.discard(m)
                        comp.append(m)
                        if m == node:
                            break
                    if len(comp) > 1:
                        out.append(sorted(comp))
    return out


def test_cycle_finder_finds_a_cycle():
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert _cycles({"a": {"b"}, "b": set()}) == []


def test_no_import_cycle_among_the_modules():
    cycles = _cycles(_graph())
    assert not cycles, f"modules importing each other (directly or around a loop): {cycles}"


def test_runtime_loads_no_file_by_path_and_imports_no_research_code():
    """The wheel stands alone: no module loads code by file path (scripts are not
    installed), and nothing imports the research folder (not installed either)."""
    bad = []
    for name, path in MODULES.items():
        text = path.read_text()
        if "spec_from_file_location" in text or "run_path(" in text:
            bad.append(f"{name}: loads code by file path")
        tree = ast.parse(text)
        for node in ast.walk(tree):
            mods = (
                [node.module or ""]
                if isinstance(node, ast.ImportFrom)
                else [a.name for a in node.names]
                if isinstance(node, ast.Import)
                else []
            )
            bad += [
                f"{name}: imports {m}" for m in mods if m.startswith("rectified_colmap_research")
            ]
    assert not bad, bad


def test_the_wheel_holds_the_runtime_only():
    """pyproject.toml packages rectified_colmap* only: research/ (training, scripts, their
    data) is its own project."""
    text = (ROOT / "pyproject.toml").read_text()
    assert 'include = ["rectified_colmap*"]' in text
    assert not (PKG / "training").exists()
    assert (ROOT / "research" / "pyproject.toml").is_file()


# -- size limits (issue 42): what a newcomer has to read --------------------------------------

MAX_MODULE_LINES = 500
MAX_FUNCTION_LINES = 60  # from `def` to its last line, docstring included
MAX_CONF_FIELDS, MAX_SECTION_FIELDS = 60, 20
MAX_EXTRACT_PARAMS = 8


def _functions():
    for name, path in MODULES.items():
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                yield name, node


def test_no_module_or_function_is_too_long():
    long_modules = {
        n: len(p.read_text().splitlines())
        for n, p in MODULES.items()
        if len(p.read_text().splitlines()) > MAX_MODULE_LINES
    }
    assert not long_modules, f"modules over {MAX_MODULE_LINES} lines: {long_modules}"
    long_functions = {
        f"{m}.{f.name}": f.end_lineno - f.lineno + 1
        for m, f in _functions()
        if f.end_lineno - f.lineno + 1 > MAX_FUNCTION_LINES
    }
    assert not long_functions, f"functions over {MAX_FUNCTION_LINES} lines: {long_functions}"
    (extract_image,) = [f for m, f in _functions() if m == "pipeline" and f.name == "extract_image"]
    assert extract_image.end_lineno - extract_image.lineno + 1 <= 50  # one assembly path


def test_the_configuration_stays_small():
    import dataclasses

    from rectified_colmap.config import ExtractConf

    conf = ExtractConf()
    sizes = {
        f.name: len(dataclasses.fields(getattr(conf, f.name))) for f in dataclasses.fields(conf)
    }
    assert sum(sizes.values()) <= MAX_CONF_FIELDS, sizes
    assert max(sizes.values()) <= MAX_SECTION_FIELDS, sizes


def test_extract_takes_few_parameters():
    import inspect

    from rectified_colmap import extract

    params = inspect.signature(extract).parameters
    assert len(params) <= MAX_EXTRACT_PARAMS, list(params)


def test_the_wheel_never_imports_torch():
    """Not at module level nor in a function: torch is research's (training, export)."""
    bad = []
    for name, path in MODULES.items():
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            mods = (
                [node.module or ""]
                if isinstance(node, ast.ImportFrom)
                else [a.name for a in node.names]
                if isinstance(node, ast.Import)
                else []
            )
            bad += [f"{name}: {m}" for m in mods if m == "torch" or m.startswith("torch.")]
    assert not bad, bad
