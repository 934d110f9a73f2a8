"""Memory of SIFT extraction: a bounded number of live pycolmap extractors, and resident
memory that does not grow with the number of distinct feature budgets or images.

Each pycolmap SIFT extractor keeps VLFeat's scale space of the last image it saw (~288
bytes per pixel at first_octave = -1). Measured through /proc (Linux only)."""

from pathlib import Path

import numpy as np
import pytest

from rectified_colmap.config import SiftConf
from rectified_colmap.sift import MAX_LIVE_EXTRACTORS, Sift, detect_sift
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
    img, sift = textured_image(64, 96, 1), Sift()
    for n in range(100, 1100, 100):  # ten distinct budgets
        detect_sift(img, SiftConf(), n, sift=sift)
        detect_sift(img, SiftConf(), n, first_octave=0, sift=sift)
        detect_sift(img, SiftConf(), n, coarse_first=True, sift=sift)
        detect_sift(img, SiftConf(), n, slot="patch", sift=sift)
        detect_sift(img, SiftConf(), n + 1, coarse_first=True, slot="patch", sift=sift)
        for slot, most in MAX_LIVE_EXTRACTORS.items():
            assert 1 <= len(sift.extractors(slot)) <= most
    assert sift.live() <= sum(MAX_LIVE_EXTRACTORS.values())
    sift.release()
    assert sift.live() == 0


def test_a_repeated_budget_reuses_its_extractor():
    img, sift = textured_image(64, 96, 2), Sift()
    detect_sift(img, SiftConf(), 300, sift=sift)
    (first,) = sift.extractors("image")
    detect_sift(img, SiftConf(), 300, sift=sift)
    assert sift.extractors("image") == [first]
    other = Sift()  # extractors belong to their Sift: nothing is shared between them
    detect_sift(img, SiftConf(), 300, sift=other)
    assert other.extractors("image")[0] is not first and sift.live() == 1


def test_patches_do_not_evict_the_whole_image_extractor():
    """The whole image's extractor (and its scale space) survives the patches between two
    same-size images, as COLMAP's extractor does on a folder of photos; patches share one."""
    img, patch, sift = textured_image(64, 96, 3), textured_image(48, 40, 4), Sift()
    detect_sift(img, SiftConf(), 300, sift=sift)
    (first,) = sift.extractors("image")
    for n in (50, 70, 90):
        detect_sift(patch, SiftConf(), n, slot="patch", sift=sift)
        assert len(sift.extractors("patch")) == 1
    detect_sift(img, SiftConf(), 300, sift=sift)
    assert sift.extractors("image") == [first]


def test_detect_sift_without_a_sift_gives_the_same_features():
    """Without a Sift a call makes (and drops) its own extractors: the same features as
    warm ones give; nothing shared to reset between callers."""
    img, sift = textured_image(64, 96, 5), Sift()
    for _ in range(2):  # the second call reuses the warm extractor
        kept = detect_sift(img, SiftConf(), 300, sift=sift)
        alone = detect_sift(img, SiftConf(), 300)
        assert len(kept) > 50
        np.testing.assert_array_equal(alone.keypoints, kept.keypoints)
        np.testing.assert_array_equal(alone.descriptors, kept.descriptors)


def test_memory_does_not_grow_with_budgets_and_images():
    """16 extractions with distinct budgets on two image sizes: resident memory stays within
    about one scale space of the larger image (a cache per budget held one per budget:
    ~16 x 35 MB here)."""
    h, w = 320, 400
    scale_space_mb = 288 * h * w / 2**20  # ~35 MB
    big, small = textured_image(h, w, 3), textured_image(h // 2, w // 2, 4)
    sift = Sift()
    detect_sift(big, SiftConf(), 99, sift=sift)  # first use: code, allocator arenas
    sift.release()
    before = _status_mb("VmRSS")
    peak_ok = _reset_peak()
    for i in range(8):
        detect_sift(big, SiftConf(), 100 + 37 * i, sift=sift)
        detect_sift(small, SiftConf(), 2000 + 37 * i, coarse_first=True, sift=sift)
    grown = _status_mb("VmRSS") - before
    assert grown < 1.5 * scale_space_mb, f"RSS grew by {grown:.0f} MB"
    if peak_ok:
        peak = _status_mb("VmHWM") - before
        assert peak < 2.0 * scale_space_mb, f"peak {peak:.0f} MB above the start"
    sift.release()
    assert _status_mb("VmRSS") - before < 0.5 * scale_space_mb
