"""Log lines never break a progress bar's line (rectified_colmap.progress); a truncated
JPEG prints the project's warning only, not libjpeg's."""

import logging
import subprocess
import sys

import cv2
import numpy as np
import pytest
from tqdm import tqdm

from rectified_colmap.progress import AboveTheBar, progress_bar

WARNING = "truncated JPEG (no end-of-image marker)"


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    """A good JPEG and a truncated one (its name sorts second: the bar is live then)."""
    root = tmp_path_factory.mktemp("progress") / "images"
    root.mkdir()
    rng = np.random.default_rng(0)
    for name in ("a.jpg", "b.jpg"):
        _, buf = cv2.imencode(".jpg", rng.integers(0, 255, (240, 320, 3), np.uint8))
        data = buf.tobytes()
        (root / name).write_bytes(data if name == "a.jpg" else data[: len(data) * 6 // 10])
    return root


@pytest.mark.parametrize("workers", [1, 2])
def test_cli_warning_on_its_own_line_and_no_libjpeg_message(folder, tmp_path, workers):
    """`rectified-colmap extract` as a user runs it (its logging.basicConfig, a live bar
    on stderr): the truncated image's warning is a line of its own, not glued to the bar,
    and libjpeg's 'Premature end of JPEG file' is not printed (by this process or a
    worker)."""
    argv = ["extract", "--database_path", str(tmp_path / "db.db"), "--image_path", str(folder)]
    argv += ["--camera_model", "PINHOLE", "--camera_params", "300,300,160,120"]
    argv += ["--depth_model", "none", "--num_workers", str(workers)]
    code = f"import sys; from rectified_colmap.cli import main; sys.exit(main({argv!r}))"
    proc = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=240, cwd=tmp_path
    )
    err = proc.stderr
    assert proc.returncode == 0, err
    assert "rectified SIFT:" in err  # the bar was drawn
    assert "Premature end of JPEG file" not in err
    # what a terminal shows of each line: the text after its last carriage return
    shown = [line.rsplit("\r", 1)[-1] for line in err.split("\n")]
    warned = [line for line in shown if WARNING in line and "WARNING]" in line]
    assert len(warned) == 1, err
    glued = [line for line in err.split("\n") if "rectified SIFT:" in line and "WARNING]" in line]
    assert warned[0].startswith("[") and not glued, err


def test_handlers_restored_and_levels_kept(capsys):
    """Console handlers write above the bar only while it is open, with their own level
    and format; other handlers are untouched; all restored after an exception too."""
    root = logging.getLogger()
    console = logging.StreamHandler(sys.stderr)
    console.setLevel(logging.WARNING)
    console.setFormatter(logging.Formatter("<%(levelname)s> %(message)s"))
    other = logging.NullHandler()
    before = root.handlers[:]
    root.addHandler(console)
    root.addHandler(other)
    log = logging.getLogger("rectified_colmap.test_progress")
    log.setLevel(logging.INFO)
    try:
        with pytest.raises(KeyError):
            with progress_bar(total=2, desc="bar") as bar:
                assert isinstance(bar, tqdm)
                wrapped = [h for h in root.handlers if isinstance(h, AboveTheBar)]
                assert [h.handler for h in wrapped] == [console] and other in root.handlers
                log.info("not shown")
                log.warning("shown")
                bar.update()
                raise KeyError("boom")
        assert console in root.handlers and not any(
            isinstance(h, AboveTheBar) for h in root.handlers
        )
    finally:
        root.handlers[:] = before
        log.setLevel(logging.NOTSET)
    err = capsys.readouterr().err
    assert "<WARNING> shown\n" in err and "not shown" not in err
    assert "bar:" in err.split("<WARNING> shown\n")[1]  # redrawn below the message
