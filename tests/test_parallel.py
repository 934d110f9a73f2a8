"""Worker processes (rectified_colmap.parallel): never forked from a parent whose thread
pools have run, usable however the caller's main module was started (a script with or
without a main guard, standard input, ``python -c``), same outputs as one process, no
C-level stack dump when a pool stops its workers.

Each run that could hang runs in a subprocess with a time limit: a hang fails the test
instead of hanging the suite."""

import logging
import multiprocessing as mp
import os
import signal
import sqlite3
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import cv2
import h5py
import numpy as np
import pytest

from rectified_colmap import parallel
from rectified_colmap.extraction import extract
from rectified_colmap.io import hloc_h5
from rectified_colmap_research.synth.planar import look_at, plane_view, textured_image

ROOT = Path(__file__).resolve().parent.parent
K = np.array([[300.0, 0, 160], [0, 300, 120], [0, 0, 1]])
PARAMS = "300,300,160,120"
NUM_IMAGES = 4
STRESS_REPEATS = 4
STRESS_LIMIT_S = 300


@pytest.fixture(scope="module")
def views(tmp_path_factory):
    """NUM_IMAGES oblique JPEG views of a textured plane (the network finds planes)."""
    root = tmp_path_factory.mktemp("views") / "images"
    root.mkdir()
    tex = textured_image(500, 500, 3)
    for i in range(NUM_IMAGES):
        R, t = look_at([2.0 - i, -3.5, 1.5 + 0.3 * i], [0, 0, 0])
        img, _ = plane_view(tex, 0.01, K, R, t, (320, 240))
        cv2.imwrite(str(root / f"v{i}.jpg"), img)
    return root


def _run_python(
    args: list[str], timeout: float, cwd: Path, stdin: str | None = None
) -> tuple[subprocess.CompletedProcess, float]:
    """``python *args`` (fed ``stdin``) in its own process group; on timeout the whole
    group (workers included) is killed and the test fails. research/ is on its path as
    pytest's pythonpath puts it here (the stress script's textured plane is research code)."""
    paths = [str(ROOT / "research"), os.environ.get("PYTHONPATH", "")]
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(p for p in paths if p))
    t0 = time.perf_counter()
    proc = subprocess.Popen(
        [sys.executable, *args],
        stdin=subprocess.PIPE if stdin is not None else subprocess.DEVNULL,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=cwd,
        start_new_session=True,
        env=env,
    )
    try:
        out, err = proc.communicate(stdin, timeout=timeout)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        out, err = proc.communicate()
        pytest.fail(f"hung: no result after {timeout} s\n{out}\n{err[-3000:]}")
    done = subprocess.CompletedProcess(proc.args, proc.returncode, out, err)
    return done, time.perf_counter() - t0


STRESS = """
import sys, time
from pathlib import Path

import cv2
import numpy as np


def use_thread_pools(rng):
    \"\"\"Leave OpenCV's, onnxruntime's and (when installed) torch's thread pools live.\"\"\"
    cv2.setNumThreads(4)
    big = rng.integers(0, 255, (1500, 1500, 3), np.uint8)
    for _ in range(3):
        cv2.GaussianBlur(big, (21, 21), 3)
        cv2.resize(big, (700, 700), interpolation=cv2.INTER_AREA)
    from rectified_colmap.depth.registry import load_depth_source
    from rectified_colmap_research.synth.planar import textured_image

    net = load_depth_source("rectsift-lite0", num_threads=4)
    import pycolmap

    cam = pycolmap.Camera(model="PINHOLE", width=320, height=240, params=[300, 300, 160, 120])
    net(np.dstack([textured_image(240, 320, 1)] * 3), cam, "x.jpg")
    try:
        import torch
    except ImportError:
        return "cv2 onnxruntime"
    torch.set_num_threads(4)
    a = torch.randn(600, 600)
    for _ in range(5):
        a = torch.tanh(a @ a)
    return "cv2 onnxruntime torch"


if __name__ == "__main__":
    from rectified_colmap.extraction import extract

    images, out = Path(sys.argv[1]), Path(sys.argv[2])
    repeats, params = int(sys.argv[3]), sys.argv[4]
    rng = np.random.default_rng(0)
    for i in range(repeats):
        used = use_thread_pools(rng)
        t0 = time.perf_counter()
        s = extract(images, database=out / f"{i}.db", hloc_features=out / f"{i}.h5",
                    reader={"camera_model": "PINHOLE", "camera_params": params},
                    run={"num_workers": 2, "progress": False})
        assert s.ok and len(s.done) == len(list(images.glob("*.jpg"))), s.report()
        print(f"run {i}: {time.perf_counter() - t0:.1f} s after {used}", flush=True)
"""


def test_pool_started_after_live_thread_pools_never_hangs(views, tmp_path):
    """The parent has run OpenCV, onnxruntime and torch on several threads before each
    pool starts (the mini-Aachen hang: a forked worker stuck in OpenCV's
    setNumThreads); STRESS_REPEATS pools in a row from a script, each within the limit."""
    script = tmp_path / "stress.py"
    script.write_text(STRESS)
    out = tmp_path / "out"
    out.mkdir()
    proc, seconds = _run_python(
        [str(script), str(views), str(out), str(STRESS_REPEATS), PARAMS], STRESS_LIMIT_S, tmp_path
    )
    assert proc.returncode == 0, proc.stderr
    runs = [ln for ln in proc.stdout.splitlines() if ln.startswith("run ")]
    assert len(runs) == STRESS_REPEATS, proc.stdout
    print(f"stress: {STRESS_REPEATS} pools in {seconds:.1f} s:", "; ".join(runs))


def _dump(out: Path) -> tuple[dict, dict]:
    """Per image name: database camera and feature bytes; hloc datasets and attributes."""
    with sqlite3.connect(out / "db.db") as con:
        db = {
            r[0]: r[1:]
            for r in con.execute(
                "SELECT i.name, c.model, c.params, k.data, d.data FROM images i "
                "JOIN cameras c USING (camera_id) JOIN keypoints k USING (image_id) "
                "JOIN descriptors d USING (image_id)"
            )
        }
    h5 = {}
    with h5py.File(out / "f.h5", "r") as f:
        for name in hloc_h5.list_names(out / "f.h5"):
            h5[name] = ({k: f[name][k][()].tobytes() for k in f[name]}, dict(f[name].attrs))
    return db, h5


def test_cli_workers_from_python_c_equal_one_worker(views, tmp_path):
    """`rectified-colmap extract --num_workers 2` from ``python -c`` (no main script)
    writes exactly what one process writes; worker log records reach the caller's
    handlers (the depth network's line, once per worker)."""
    one = tmp_path / "one"
    s = extract(
        views,
        database=one / "db.db",
        hloc_features=one / "f.h5",
        reader={"camera_model": "PINHOLE", "camera_params": PARAMS},
        run={"progress": False},
    )
    assert s.ok and len(s.done) == NUM_IMAGES and len(s.plain) < NUM_IMAGES
    two = tmp_path / "two"
    argv = ["extract", "--database_path", str(two / "db.db"), "--image_path", str(views)]
    argv += ["--hloc_features", str(two / "f.h5"), "--camera_model", "PINHOLE"]
    argv += ["--camera_params", PARAMS, "--num_workers", "2", "--no_progress"]
    code = f"import sys; from rectified_colmap.cli import main; sys.exit(main({argv!r}))"
    proc, _ = _run_python(["-c", code], 240, tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert _dump(one) == _dump(two)
    # the parent's line and one per worker, formatted by the parent's handler
    loaded = [ln for ln in proc.stderr.splitlines() if "depth model rectsift" in ln]
    assert len(loaded) == 3 and all(ln.startswith("[") for ln in loaded), proc.stderr


STACK_DUMP = "stack trace:"
"""What glog's failure handler (installed by pycolmap) prints before its C-level frames."""


def _extraction_code(views: Path, db: Path, guard: bool) -> str:
    """A main module calling extract(num_workers=2) that prints one line per run of its
    top level (a worker importing it would print again)."""
    body = textwrap.dedent(
        f"""
        from rectified_colmap.extraction import extract
        s = extract({str(views)!r}, database={str(db)!r},
                    reader={{"camera_model": "PINHOLE", "camera_params": "{PARAMS}"}},
                    run={{"num_workers": 2, "progress": False}})
        assert s.ok and len(s.done) == {NUM_IMAGES}, s.report()
        """
    )
    top = 'print("top level ran", flush=True)\n'
    if not guard:
        return top + body
    return top + "if __name__ == '__main__':\n" + textwrap.indent(body, "    ")


def _check_written(proc: subprocess.CompletedProcess, db: Path) -> None:
    """Exit 0, every image's features in ``db``, the caller's top level run once, and no
    stack dump."""
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert STACK_DUMP not in proc.stderr and "Traceback" not in proc.stderr, proc.stderr
    assert proc.stdout.count("top level ran") == 1, proc.stdout
    with sqlite3.connect(db) as con:
        assert con.execute("SELECT COUNT(*) FROM keypoints WHERE rows > 0").fetchone()[0] == (
            NUM_IMAGES
        )


def test_extraction_from_standard_input_with_workers(views, tmp_path):
    """`python - <<EOF ... extract(num_workers=2) ... EOF`: the workers do not look for a
    file `<stdin>` (which broke the pool, with a C-level stack dump)."""
    db = tmp_path / "stdin.db"
    proc, _ = _run_python(["-"], 240, tmp_path, stdin=_extraction_code(views, db, guard=False))
    _check_written(proc, db)


def test_extraction_from_python_c_with_workers(views, tmp_path):
    db = tmp_path / "c.db"
    proc, _ = _run_python(["-c", _extraction_code(views, db, guard=False)], 240, tmp_path)
    _check_written(proc, db)


@pytest.mark.parametrize("guard", [True, False], ids=["guarded", "unguarded"])
def test_script_with_or_without_main_guard_runs_its_top_level_once(views, tmp_path, guard):
    """Workers never import the caller's script: one without `if __name__ ==
    "__main__":` works (it stopped with a one-line error), and no line of either runs
    again in a worker."""
    db = tmp_path / "script.db"
    script = tmp_path / "script.py"
    script.write_text(_extraction_code(views, db, guard))
    proc, _ = _run_python([str(script)], 240, tmp_path)
    _check_written(proc, db)


MAIN_POOL = """
import sys
from rectified_colmap import parallel


def square(x):
    return x * x


if __name__ == "__main__":
    with parallel.context().Pool(2) as pool:
        print(sum(pool.map(square, range(10))))
"""


def test_pools_that_run_main_functions_still_import_the_main_script(tmp_path):
    """context()'s default (import_main=True) keeps multiprocessing's rule for pools whose
    functions live in the caller's script (research/scripts/build_real_pool.py)."""
    script = tmp_path / "main_pool.py"
    script.write_text(MAIN_POOL)
    proc, _ = _run_python([str(script)], 120, tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.split() == ["285"]


SIGTERM_SELF = """
import multiprocessing as mp
import signal
import sys

from rectified_colmap import parallel

if __name__ == "__main__":
    ours = sys.argv[1] == "ours"
    ctx = parallel.context(["pycolmap"]) if ours else mp.get_context("forkserver")
    if not ours:
        ctx.set_forkserver_preload(["pycolmap"])
    p = ctx.Process(target=signal.raise_signal, args=(signal.SIGTERM,))
    p.start()
    p.join(60)
    print(p.exitcode)
"""


@pytest.mark.skipif(parallel.start_method() != "forkserver", reason="needs the forkserver")
def test_a_worker_stopped_by_sigterm_ends_without_a_stack_dump(tmp_path):
    """pycolmap (imported in the workers) installs glog's failure handler, which prints a
    C-level stack dump on SIGTERM, as a pool sends its workers when another one died; our
    workers end quietly."""
    script = tmp_path / "sigterm.py"
    script.write_text(SIGTERM_SELF)
    plain, _ = _run_python([str(script), "plain"], 120, tmp_path)
    if STACK_DUMP not in plain.stderr:
        pytest.skip("this pycolmap prints no stack dump on SIGTERM: nothing to keep away")
    proc, _ = _run_python([str(script), "ours"], 120, tmp_path)
    assert proc.returncode == 0 and proc.stdout.split() == [str(-signal.SIGTERM)], proc.stderr
    assert STACK_DUMP not in proc.stderr, proc.stderr


def test_bootstrapping_check_names_the_guard(monkeypatch):
    """A worker of a pool that imports the main script (import_main=True, e.g. the
    caller's own) stops at once when that script starts an extraction unguarded."""
    monkeypatch.setattr(mp.current_process(), "_inheriting", True, raising=False)
    with pytest.raises(RuntimeError, match="if __name__ == '__main__':"):
        parallel.check_not_bootstrapping()


def test_main_module_attributes_are_restored_after_a_start(tmp_path):
    """The main module's __file__ / __spec__ are hidden only while a worker starts."""
    main = sys.modules["__main__"]
    before = {k: v for k, v in vars(main).items() if k in ("__file__", "__spec__")}
    ctx = parallel.context(import_main=False)
    p = ctx.Process(target=time.sleep, args=(0,))
    p.start()
    p.join(60)
    assert p.exitcode == 0
    assert {k: v for k, v in vars(main).items() if k in ("__file__", "__spec__")} == before


def test_worker_logs_are_replayed_in_the_parent(caplog):
    """Records captured in a worker process (formatted, picklable) go through the
    parent's loggers at the parent's levels."""
    import pickle

    old = logging.getLogger().handlers[:]
    try:
        q = parallel.capture_logs(logging.INFO)
        logging.getLogger("rectified_colmap.x").info("kept %d", 1)
        logging.getLogger("rectified_colmap.x").debug("dropped")
        try:
            raise ValueError("boom")
        except ValueError:
            logging.getLogger("rectified_colmap.y").exception("failed")
        records = pickle.loads(pickle.dumps(parallel.drain(q)))
    finally:
        root = logging.getLogger()
        root.handlers[:] = old
        logging.getLogger("rectified_colmap").setLevel(logging.NOTSET)
    assert [r.getMessage().splitlines()[0] for r in records] == ["kept 1", "failed"]
    assert "ValueError: boom" in records[1].getMessage()
    assert parallel.drain(q) == [] and parallel.drain(None) == []
    caplog.set_level(logging.WARNING)
    parallel.replay(records)
    assert [r.getMessage().splitlines()[0] for r in caplog.records] == ["failed"]


def test_start_method_is_never_fork():
    assert parallel.start_method() in ("forkserver", "spawn")
    for import_main in (True, False):
        ctx = parallel.context(["rectified_colmap.extraction.run"], import_main=import_main)
        assert ctx.get_start_method() == parallel.start_method()
        assert ctx.Process.import_main is import_main
        assert issubclass(ctx.Process, mp.process.BaseProcess)
