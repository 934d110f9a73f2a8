"""pycolmap 4.2.1's wheel exports zlib symbols of its own; a process that loads Python's
zlib after pycolmap can abort on the next PNG save ("free(): invalid pointer", seen with
hloc). The package loads zlib before any pycolmap import (rectified_colmap/__init__.py), and
our plots run in a fresh process that also has pycolmap and hloc-style imports."""

import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]

ORDER = textwrap.dedent("""
    import sys
    sys.path[:0] = {path!r}
    order = ["zlib (at start-up)"] if "zlib" in sys.modules else []
    class Recorder:
        def find_spec(self, name, path=None, target=None):
            if name in ("zlib", "pycolmap") and name not in order:
                order.append(name)
    sys.meta_path.insert(0, Recorder())
    import {module}
    print(",".join(order))
""")


@pytest.mark.parametrize(
    "module",
    ["rectified_colmap.eval.aachen", "rectified_colmap.eval.hloc_compat", "rectified_colmap.viz"],
)
def test_zlib_loaded_before_pycolmap(module):
    # -S: no site hooks, which may load zlib at start-up and hide the order
    code = ORDER.format(module=module, path=[str(ROOT)] + [p for p in sys.path if p])
    out = subprocess.run(
        [sys.executable, "-S", "-c", code], capture_output=True, text=True, timeout=120, check=False
    )
    assert out.returncode == 0, out.stderr[-2000:]
    order = out.stdout.strip().split(",")
    assert order == ["zlib", "pycolmap"], order


PLOTS = textwrap.dedent("""
    import numpy as np
    from rectified_colmap.eval.report import plot_success
    import pycolmap
    records = [dict(method=m, gt_rot=float(a), success=bool(a < 60),
                    epipolar_success=True, category=None)
               for m in ("sift", "rectsift") for a in range(0, 120, 7)]
    plot_success({out!r} + "/success.png", records)
    from PIL import Image
    Image.fromarray(np.random.default_rng(0).integers(0, 255, (400, 400, 3), np.uint8)
                    ).save({out!r} + "/noise.png")
    print("saved")
""")


def test_plots_after_pycolmap_do_not_abort(tmp_path):
    pytest.importorskip("matplotlib", reason="plots need matplotlib")
    out = subprocess.run(
        [sys.executable, "-c", PLOTS.format(out=str(tmp_path))],
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )
    assert out.returncode == 0, (out.returncode, out.stderr[-2000:])
    from PIL import Image

    for name in ("success.png", "noise.png"):
        with Image.open(tmp_path / name) as im:
            im.load()
            assert im.size[0] > 100
