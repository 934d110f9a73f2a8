"""research/: retain_freed_memory (benchmarks): freed scale-space pages are reused."""

from pathlib import Path

import pytest

STATUS = Path("/proc/self/status")
pytestmark = pytest.mark.skipif(not STATUS.exists(), reason="needs /proc (Linux)")


def test_retained_memory_is_reused(tmp_path):
    """With retain_freed_memory (glibc), new extractors and new image sizes reuse freed pages:
    no page faults after the first image, and resident memory does not grow. In a child
    process: the setting is process-wide."""
    import os
    import subprocess
    import sys

    script = tmp_path / "child.py"
    script.write_text(
        "import resource, sys\n"
        "import numpy as np\n"
        "from rectified_colmap.config import SiftConf\n"
        "from rectified_colmap.sift import Sift, detect_sift\n"
        "from rectified_colmap_research.memory import retain_freed_memory\n"
        "from tests.conftest import textured_image\n"
        "if not retain_freed_memory():\n"
        "    print('unsupported'); sys.exit(0)\n"
        "img = textured_image(320, 400, 7)\n"
        "sift = Sift()\n"
        "detect_sift(img, SiftConf(), 100, sift=sift)\n"
        "detect_sift(img[:200, :300].copy(), SiftConf(), 101, sift=sift)\n"
        "def rss():\n"
        "    for line in open('/proc/self/status'):\n"
        "        if line.startswith('VmRSS'):\n"
        "            return int(line.split()[1]) / 1024\n"
        "before, f0 = rss(), resource.getrusage(resource.RUSAGE_SELF).ru_minflt\n"
        "for i in range(4):\n"
        "    detect_sift(img, SiftConf(), 200 + i, sift=sift)\n"
        "    sub = np.ascontiguousarray(img[:150 + 20 * i, :250])\n"
        "    detect_sift(sub, SiftConf(), 300 + i, sift=sift)\n"
        "faults = resource.getrusage(resource.RUSAGE_SELF).ru_minflt - f0\n"
        "print(faults, rss() - before)\n"
    )
    root = Path(__file__).resolve().parents[2]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(root), str(root / "research")])}
    out = subprocess.run(
        [sys.executable, str(script)], cwd=root, capture_output=True, text=True, check=True, env=env
    ).stdout.split()
    if out == ["unsupported"]:
        pytest.skip("not glibc")
    faults, grown = int(out[0]), float(out[1])
    scale_space_pages = 288 * 320 * 400 / 4096  # ~9000 pages per new extractor without it
    assert faults < 0.5 * scale_space_pages, faults  # 8 new extractors, none faulted in
    # RSS grows by a constant 4 MiB here (1024 pages), by 5 MiB now and then under load;
    # one scale space not reused would add ~36 MiB
    assert grown < 0.25 * scale_space_pages * 4096 / 2**20, grown
