"""Memory of SIFT extraction: a bounded number of live pycolmap extractors, and resident
memory that does not grow with the number of distinct feature budgets or images.

Each pycolmap SIFT extractor keeps VLFeat's scale space of the last image it saw (~288
bytes per pixel at first_octave = -1). Measured through /proc (Linux only)."""

from pathlib import Path

import pytest

from rectified_colmap import features
from rectified_colmap.config import SiftConf
from rectified_colmap.features import detect_sift, live_extractors, release_extractors
from tests.conftest import textured_image

STATUS = Path("/proc/self/status")
pytestmark = pytest.mark.skipif(not STATUS.exists(), reason="needs /proc (Linux)")


def _status_mb(field: str) -> float:
    for line in STATUS.read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1]) / 1024
    raise KeyError(field)


def _reset_peak() -> bool:
    """Reset VmHWM (peak resident memory) of this process; False where not allowed."""
    try:
        Path("/proc/self/clear_refs").write_text("5")
    except OSError:
        return False
    return True


def test_live_extractors_stay_bounded():
    img = textured_image(64, 96, 1)
    for n in range(100, 1100, 100):  # ten distinct budgets
        detect_sift(img, SiftConf(), n)
        detect_sift(img, SiftConf(), n, first_octave=0)
        detect_sift(img, SiftConf(), n, coarse_first=True)
        detect_sift(img, SiftConf(), n, slot="patch")
        detect_sift(img, SiftConf(), n + 1, coarse_first=True, slot="patch")
        for slot, cache in features._EXTRACTORS.items():
            assert 1 <= len(cache) <= features.MAX_LIVE_EXTRACTORS[slot]
    assert live_extractors() <= sum(features.MAX_LIVE_EXTRACTORS.values())
    release_extractors()
    assert live_extractors() == 0


def test_a_repeated_budget_reuses_its_extractor():
    img = textured_image(64, 96, 2)
    detect_sift(img, SiftConf(), 300)
    first = next(iter(features._EXTRACTORS["image"].values()))
    detect_sift(img, SiftConf(), 300)
    assert next(iter(features._EXTRACTORS["image"].values())) is first


def test_patches_do_not_evict_the_whole_image_extractor():
    """The whole image's extractor (and its scale space) survives the patches between two
    same-size images, as COLMAP's extractor does on a folder of photos; patches share one."""
    release_extractors()
    img, patch = textured_image(64, 96, 3), textured_image(48, 40, 4)
    detect_sift(img, SiftConf(), 300)
    (first,) = features._EXTRACTORS["image"].values()
    for n in (50, 70, 90):
        detect_sift(patch, SiftConf(), n, slot="patch")
        assert len(features._EXTRACTORS["patch"]) == 1
    detect_sift(img, SiftConf(), 300)
    (again,) = features._EXTRACTORS["image"].values()
    assert again is first
    release_extractors()


def test_memory_does_not_grow_with_budgets_and_images():
    """16 extractions with distinct budgets on two image sizes: resident memory stays within
    about one scale space of the larger image (a cache per budget held one per budget:
    ~16 x 35 MB here)."""
    h, w = 320, 400
    scale_space_mb = 288 * h * w / 2**20  # ~35 MB
    big, small = textured_image(h, w, 3), textured_image(h // 2, w // 2, 4)
    release_extractors()
    detect_sift(big, SiftConf(), 99)  # first use: code, allocator arenas
    release_extractors()
    before = _status_mb("VmRSS")
    peak_ok = _reset_peak()
    for i in range(8):
        detect_sift(big, SiftConf(), 100 + 37 * i)
        detect_sift(small, SiftConf(), 2000 + 37 * i, coarse_first=True)
    grown = _status_mb("VmRSS") - before
    assert grown < 1.5 * scale_space_mb, f"RSS grew by {grown:.0f} MB"
    if peak_ok:
        peak = _status_mb("VmHWM") - before
        assert peak < 2.0 * scale_space_mb, f"peak {peak:.0f} MB above the start"
    release_extractors()
    assert _status_mb("VmRSS") - before < 0.5 * scale_space_mb


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
        "from rectified_colmap.features import detect_sift, retain_freed_memory\n"
        "from tests.conftest import textured_image\n"
        "if not retain_freed_memory():\n"
        "    print('unsupported'); sys.exit(0)\n"
        "img = textured_image(320, 400, 7)\n"
        "detect_sift(img, SiftConf(), 100)\n"
        "detect_sift(img[:200, :300].copy(), SiftConf(), 101)\n"
        "def rss():\n"
        "    for line in open('/proc/self/status'):\n"
        "        if line.startswith('VmRSS'):\n"
        "            return int(line.split()[1]) / 1024\n"
        "before, f0 = rss(), resource.getrusage(resource.RUSAGE_SELF).ru_minflt\n"
        "for i in range(4):\n"
        "    detect_sift(img, SiftConf(), 200 + i)\n"
        "    detect_sift(np.ascontiguousarray(img[:150 + 20 * i, :250]), SiftConf(), 300 + i)\n"
        "faults = resource.getrusage(resource.RUSAGE_SELF).ru_minflt - f0\n"
        "print(faults, rss() - before)\n"
    )
    root = Path(__file__).resolve().parents[1]
    # tests.conftest's textured plane is research code (rectified_colmap_research.synth)
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
