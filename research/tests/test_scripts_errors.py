"""Every research script reports a missing input in one line (rectified_colmap.errors.run_script),
exit code 2, no traceback."""

import os
import subprocess
import sys
from pathlib import Path

import pytest

RESEARCH = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize(
    "script, args",
    [
        ("eval_homography.py", ["--data", "{x}", "--output_dir", "{t}/o", "--methods", "sift"]),
        ("build_extreme_pairs.py", ["--output", "{t}/o", "--data_root", "{x}"]),
        ("eval_strecha.py", ["--data", "{x}", "--output_dir", "{t}/o", "--methods", "sift"]),
        ("benchmark.py", ["--image_path", "{x}"]),
        ("bench_sift_backends.py", ["--image_path", "{x}"]),
        ("compare_homography.py", ["{x}", "{x}"]),
    ],
)
def test_scripts_report_a_missing_input_in_one_line(tmp_path, script, args):
    missing = tmp_path / "not-here"
    argv = [a.format(x=missing, t=tmp_path) for a in args]
    out = subprocess.run(
        [sys.executable, str(RESEARCH / "scripts" / script), *argv],
        env=dict(os.environ, PYTHONPATH=str(RESEARCH)),
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert out.returncode == 2, out.stderr[-2000:]
    assert "Traceback" not in out.stderr
    last = out.stderr.strip().splitlines()[-1]
    assert str(missing) in last and "error" in last
