"""The README's "Use on your images" commands run as written (COLMAP 3.8 CLI, no GPU)."""

import re
import shutil
import sqlite3
import subprocess
from pathlib import Path

import pytest

README = Path(__file__).resolve().parent.parent / "README.md"
needs_tools = pytest.mark.skipif(
    shutil.which("colmap") is None or shutil.which("rectified-colmap") is None,
    reason="needs the colmap command line (apt-get install colmap) and the installed "
    "rectified-colmap console script",
)


def readme_commands() -> list[str]:
    """The shell commands of the README's first bash block after "## Use on your images"."""
    text = README.read_text()
    section = text[text.index("## Use on your images") :]
    block = re.search(r"```bash\n(.*?)```", section, re.S).group(1)
    return [ln.strip() for ln in block.splitlines() if ln.strip() and not ln.startswith("#")]


def test_readme_block_has_the_documented_steps():
    cmds = readme_commands()
    tools = [c.split()[0] + " " + c.split()[1] for c in cmds]
    assert tools == [
        "rectified-colmap extract",
        "colmap exhaustive_matcher",
        "mkdir -p",
        "colmap mapper",
        "rectified-colmap extract",
    ]


@needs_tools
@pytest.mark.slow
def test_readme_commands_run_as_written(tmp_path):
    from rectified_colmap.demo import render_walk

    render_walk(tmp_path / "images", num_images=6, width=640, height=480)
    db = tmp_path / "db.db"
    snapshot = None
    for cmd in readme_commands():
        if cmd.startswith("rectified-colmap") and "--hloc_features" in cmd:
            snapshot = _db_rows(db)  # the second extract must not touch the database
        out = subprocess.run(
            cmd + (" --no_progress" if cmd.startswith("rectified") else ""),
            shell=True,
            cwd=tmp_path,
            capture_output=True,
            text=True,
            timeout=600,
        )
        assert out.returncode == 0, f"{cmd}\n{out.stdout[-2000:]}\n{out.stderr[-2000:]}"
    assert snapshot is not None and _db_rows(db) == snapshot
    assert snapshot["verified"] >= 5
    import pycolmap

    rec = pycolmap.Reconstruction(tmp_path / "sparse" / "0")
    # COLMAP 3.8's mapper (multi-threaded, not deterministic) with guessed focal lengths
    # (PNGs have no EXIF) on a small synthetic walk: every image registers, but the point
    # count varies from run to run (9-45 seen), so only its presence is asserted
    assert rec.num_reg_images() >= 5 and rec.num_points3D() > 0
    from rectified_colmap.io import hloc_h5

    assert len(hloc_h5.list_names(tmp_path / "feats-rectsift.h5")) == 6


def _db_rows(db: Path) -> dict:
    con = sqlite3.connect(db)
    try:
        return {
            "keypoints": con.execute("SELECT image_id, data FROM keypoints").fetchall(),
            "matches": con.execute("SELECT pair_id, data FROM matches").fetchall(),
            "verified": con.execute(
                "SELECT COUNT(*) FROM two_view_geometries WHERE config >= 2"
            ).fetchone()[0],
        }
    finally:
        con.close()


REFERENCE_PAGES = [
    README,
    *(
        README.parent / "docs" / f"{n}.md"
        for n in ("usage", "formats", "hloc", "depth-models", "evaluation")
    ),
    README.parent / "research" / "notes" / "results.md",
]


def paragraphs(text: str) -> list[str]:
    """Runs of non-empty lines outside fenced code, tables and headings; each list item
    ("- ", "* ", "1. ") starts a run of its own."""
    text = re.sub(r"```.*?```", "\n\n", text, flags=re.S)
    out, cur = [], []
    for line in text.splitlines() + [""]:
        item = re.match(r"\s*([-*]|\d+\.) ", line) is not None
        if not line.strip() or line.lstrip().startswith(("|", "#")) or item:
            if cur:
                out.append(" ".join(cur))
            cur = [line.strip()] if item else []
        else:
            cur.append(line.strip())
    return out


def test_paragraph_splitter():
    text = "a b\nc\n\n| t | t |\n|---|\nd e f\n```\ng h i j\n```\n# k l\nm\n- n o\n  p\n- q"
    assert [len(p.split()) for p in paragraphs(text)] == [3, 3, 1, 4, 2]


@pytest.mark.parametrize("page", REFERENCE_PAGES, ids=lambda p: p.name)
def test_reference_pages_have_no_paragraph_over_150_words(page):
    long = [p[:60] for p in paragraphs(page.read_text()) if len(p.split()) > 150]
    assert not long, f"{page.name}: paragraphs over 150 words: {long}"


def test_conf_chooser_lists_every_named_conf_and_the_python_block_imports():
    from rectified_colmap.config import confs

    text = README.read_text()
    rows = re.findall(r"^\| `([\w-]+)`", text, flags=re.M)
    for name in confs:
        assert name in rows, f"README's conf table lacks {name}"
    block = re.search(r"```python\n(.*?)```", text, re.S).group(1)
    imports = "\n".join(ln for ln in block.splitlines() if ln.startswith(("from ", "import ")))
    exec(compile(imports, "README.md", "exec"), {})


MARKDOWN_PAGES = sorted(
    [README, README.parent / "research" / "README.md"]
    + list((README.parent / "docs").glob("*.md"))
    + list((README.parent / "research" / "notes").glob("*.md"))
)


def relative_links(text: str) -> list[str]:
    """Targets of the Markdown links ``[text](target)`` outside fenced code that are paths
    (no scheme, no bare anchor), without their ``#anchor``."""
    text = re.sub(r"```.*?```", "", text, flags=re.S)
    out = []
    for target in re.findall(r"\]\(([^)\s]+)\)", text):
        if re.match(r"[a-z]+:", target) or target.startswith("#"):
            continue
        out.append(target.split("#")[0])
    return out


def test_relative_links_splitter():
    text = "[a](x.md) [b](https://e.org) [c](#top) [d](../y/z.md#s)\n```\n[e](no.md)\n```"
    assert relative_links(text) == ["x.md", "../y/z.md"]


@pytest.mark.parametrize(
    "page", MARKDOWN_PAGES, ids=lambda p: p.relative_to(README.parent).as_posix()
)
def test_markdown_links_point_at_existing_files(page):
    broken = [t for t in relative_links(page.read_text()) if not (page.parent / t).exists()]
    assert not broken, f"{page.relative_to(README.parent)}: links to missing files {broken}"
