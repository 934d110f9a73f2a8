"""The user scripts (scripts/*.py) run from the installed package and hloc alone (no
research/ on the path), and report a missing input in one line (exit code 2, no
traceback)."""

import os
import subprocess
import sys

import pytest
from user_scripts import ROOT, SCRIPTS, hloc_missing

CASES = [
    ("aachen_hloc.py", ["--make_mini_from", "{x}", "--dataset", "{t}/d", "--outputs", "{t}/o"]),
    ("aachen_hloc.py", ["--dataset", "{x}", "--outputs", "{t}/o"]),
    ("hloc_sfm.py", ["--images", "{x}", "--outputs", "{t}/o"]),
]


def _run(script: str, argv: list[str]) -> subprocess.CompletedProcess:
    # the checkout's package only: the research project is not importable
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    return subprocess.run(
        [sys.executable, str(SCRIPTS / script), *argv],
        env=env,
        cwd=ROOT.parent,
        capture_output=True,
        text=True,
        timeout=300,
    )


def test_every_user_script_is_covered():
    assert sorted({c[0] for c in CASES}) == sorted(p.name for p in SCRIPTS.glob("*.py"))


@pytest.mark.parametrize("script", sorted(p.name for p in SCRIPTS.glob("*.py")))
def test_help_runs_without_research_code(script):
    out = _run(script, ["--help"])
    assert out.returncode == 0, out.stderr[-2000:]
    assert "usage:" in out.stdout and "--outputs" in out.stdout


@pytest.mark.parametrize("script, args", CASES)
def test_a_missing_input_is_one_line(tmp_path, script, args):
    missing = hloc_missing()
    if missing:
        pytest.skip(missing)
    absent = tmp_path / "not-here"
    out = _run(script, [a.format(x=absent, t=tmp_path) for a in args])
    assert out.returncode == 2, out.stderr[-2000:]
    assert "Traceback" not in out.stderr
    last = out.stderr.strip().splitlines()[-1]
    assert str(absent) in last and "error" in last, last
    assert not (tmp_path / "o").exists()  # stopped before writing anything
