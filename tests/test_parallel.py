"""The process-pool helper: order, the in-flight window, cancellation."""

from __future__ import annotations

import concurrent.futures as cf
import os
import threading

import pytest

from geoortho.core.parallel import imap_ordered, map_ordered
from geoortho.errors import CanceledError
from geoortho.feedback import Feedback


def _square(x: int) -> int:
    return x * x


def test_map_ordered_keeps_order_in_process_and_on_a_pool():
    assert map_ordered(_square, list(range(7)), workers=1) == [x * x for x in range(7)]
    assert map_ordered(_square, list(range(7)), workers=2) == [x * x for x in range(7)]
    assert map_ordered(_square, [], workers=2) == []


def test_imap_ordered_submits_no_more_than_the_window():
    submitted = []
    lock = threading.Lock()

    class Counting(cf.ThreadPoolExecutor):
        def submit(self, fn, *args, **kwargs):
            with lock:
                submitted.append(args[0])
            return super().submit(fn, *args, **kwargs)

    with Counting(2) as ex:
        it = imap_ordered(_square, list(range(20)), executor=ex, in_flight=3)
        assert next(it) == 0
        assert len(submitted) == 4  # the first window, and one more once the first result is taken
        assert list(it) == [x * x for x in range(1, 20)]
    assert submitted == list(range(20))


def test_imap_ordered_stops_on_cancel():
    fb = Feedback()
    seen = []
    with pytest.raises(CanceledError):
        for y in imap_ordered(_square, list(range(10)), workers=1, feedback=fb):
            seen.append(y)
            if len(seen) == 3:
                fb.cancel()
    assert seen == [0, 1, 4]


def test_workers_die_with_a_sigkilled_parent(tmp_path):
    """Issue 23 (8): after SIGKILL, pool workers went on rendering for over 10 minutes."""
    import signal
    import subprocess
    import sys
    import time

    import psutil

    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "geoortho",
            "synth",
            "--output",
            str(tmp_path / "s"),
            "--preset",
            "small",
            "--workers",
            "2",
            "--quiet",
        ],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    parent = psutil.Process(proc.pid)
    deadline = time.monotonic() + 60
    while len(parent.children()) < 2:
        assert proc.poll() is None and time.monotonic() < deadline
        time.sleep(0.1)
    workers = parent.children(recursive=True)
    time.sleep(1.0)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    gone, alive = psutil.wait_procs(workers, timeout=10)
    assert not alive, f"{len(alive)} workers outlived their parent"


def test_a_script_without_the_main_guard_runs(tmp_path):
    """A first script calls geoortho at its top level, no ``if __name__ == "__main__":``: the
    spawned workers must not run it again (they did, and the pool waited for ever)."""
    import subprocess
    import sys

    script = tmp_path / "survey.py"
    script.write_text(
        "import geoortho\n"
        f"s = geoortho.synth({str(tmp_path / 'survey')!r}, preset='tiny', seed=1, workers=2)\n"
        "print('photos', len(list(s.images.iterdir())))\n"
    )
    done = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.split() == ["photos", "9"]
    # the same from stdin (``python - <<EOF``): there is no script for a worker to find again
    code = "from geoortho.core.parallel import map_ordered\nprint(map_ordered(abs, [-1, -2, -3, -4], workers=2))\n"
    done = subprocess.run([sys.executable, "-"], input=code, capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.strip() == "[1, 2, 3, 4]"


def test_workers_dead_at_start_up_raise():
    import os

    from geoortho.errors import WorkerError

    with pytest.raises(WorkerError, match="workers=1"):
        map_ordered(abs, [1, -2, 3, -4], workers=2, initializer=os._exit, initargs=(3,))


def test_every_worker_starts_with_the_pool(monkeypatch):
    """All workers start inside the pool's start-up block (where the user's main script is kept
    from them). A slow caller (here: every submit takes a second; large initargs or a busy machine
    did it) let the first worker finish its start-up task before the second was asked for, and
    the second then started later, outside the block, and ran the user's unguarded script."""
    import concurrent.futures as cf
    import time

    from geoortho.core.parallel import process_pool

    submit = cf.ProcessPoolExecutor.submit

    def slow_submit(self, *args, **kwargs):
        future = submit(self, *args, **kwargs)
        time.sleep(1.0)
        return future

    monkeypatch.setattr(cf.ProcessPoolExecutor, "submit", slow_submit)
    with process_pool(2, 8) as pool:
        assert pool is not None
        assert len(pool._processes) == 2  # started, not left for a later submit


def _thread_vars(_: int) -> tuple[str | None, ...]:
    import os

    return tuple(os.environ.get(k) for k in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"))


def test_workers_share_the_cores_between_their_blas_threads(monkeypatch):
    """Two workers' BLAS each started a thread per core: gcp-find on a degraded survey took 1.2 x
    the time of one thread each. A worker gets its share of the cores; a value the user set is
    kept; the caller's own environment is as it was."""
    import os

    from geoortho.core.parallel import process_pool

    for k in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        monkeypatch.delenv(k, raising=False)
    monkeypatch.setenv("MKL_NUM_THREADS", "3")
    monkeypatch.setattr(os, "cpu_count", lambda: 4)
    with process_pool(2, 4) as pool:
        seen = set(map_ordered(_thread_vars, [0, 1, 2, 3], workers=2, executor=pool))
    assert seen == {("2", "2", "3")}
    assert os.environ.get("OPENBLAS_NUM_THREADS") is None and os.environ["MKL_NUM_THREADS"] == "3"
    monkeypatch.setattr(os, "cpu_count", lambda: 2)
    with process_pool(3, 4) as pool:  # more workers than cores: one thread each, never none
        assert set(map_ordered(_thread_vars, [0, 1, 2], workers=3, executor=pool)) == {("1", "1", "3")}


# Ctrl-C taken by another thread while a worker starts: the caller's handler then ran in the
# middle of writing the worker's start-up data (after the process was made, before the write).
_CTRL_C_AS_A_WORKER_STARTS = r"""
import multiprocessing.util, os, signal, sys, threading
from geoortho.core.parallel import map_ordered

threading.Thread(target=threading.Event().wait, daemon=True).start()  # takes the signal: unblocked
spawn = multiprocessing.util.spawnv_passfds
def spawn_then_ctrl_c(path, args, passfds):
    pid = spawn(path, args, passfds)
    if any("spawn_main" in os.fsdecode(a) for a in args):  # a worker, not the resource tracker
        multiprocessing.util.spawnv_passfds = spawn
        os.kill(os.getpid(), signal.SIGINT)
    return pid
multiprocessing.util.spawnv_passfds = spawn_then_ctrl_c
try:
    map_ordered(abs, [-1, -2, -3, -4], workers=2)
except KeyboardInterrupt:
    print("interrupted")
"""


def test_a_ctrl_c_while_a_worker_starts_waits_for_the_start():
    """A worker whose start-up data was cut short by the caller's KeyboardInterrupt was never
    killed (the pool did not know it yet) and printed an EOFError traceback after "canceled"
    (twice in 180 signals sent to dense at random moments)."""
    import signal
    import subprocess
    import sys

    # a suite started in the background by a shell without job control inherits SIGINT ignored,
    # and Python keeps it so: the Ctrl-C this test sends would be lost (nothing printed)
    done = subprocess.run([sys.executable, "-c", _CTRL_C_AS_A_WORKER_STARTS], capture_output=True, text=True,
                          timeout=60, preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))  # fmt: skip
    assert done.stdout.strip() == "interrupted" and "Traceback" not in done.stderr, done.stderr[-2000:]


def _one_opencv_thread() -> None:
    import cv2

    cv2.setNumThreads(1)


def test_a_worker_initializer_run_here_leaves_opencv_its_threads():
    """A batch too small for a pool runs here, after the workers' initializer: its OpenCV thread
    count of one stayed this process's for every later stage of a run."""
    import cv2

    before = cv2.getNumThreads()
    assert before > 1 or (os.cpu_count() or 1) == 1
    got = map_ordered(lambda x: cv2.getNumThreads(), [0], workers=2, initializer=_one_opencv_thread)
    assert got == [1]  # the task saw the initializer's setting
    assert cv2.getNumThreads() == before


def test_exact_distances_are_the_same_on_one_opencv_thread_or_many():
    """OpenCV's serial and parallel exact distance transforms differ in the last float32 place,
    enough to move a DSM's gap fill (a roof edge cell by 6 m); the distances are whole roots."""
    import cv2
    import numpy as np

    from geoortho.core.gapfill import distance_cells

    rng = np.random.default_rng(0)
    inside = np.ones((700, 900), bool)
    for r, c in rng.integers(0, (700, 900), (120, 2)):
        inside[max(0, r - 9) : r + 9, max(0, c - 14) : c + 14] = False
    before = cv2.getNumThreads()
    try:
        cv2.setNumThreads(1)
        one = distance_cells(inside)
        raw_one = cv2.distanceTransform(inside.astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
        cv2.setNumThreads(max(2, before))
        many = distance_cells(inside)
        raw_many = cv2.distanceTransform(inside.astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    finally:
        cv2.setNumThreads(before)
    assert not np.array_equal(raw_one, raw_many)  # the pitfall is still there to guard against
    assert np.array_equal(one, many)
    squared = one.astype(np.float64) ** 2
    assert np.abs(squared - np.rint(squared)).max() < 1e-3 and one.max() > 30


def test_a_pool_is_wholly_ended_when_its_block_ends():
    """The pool's own thread was still closing its wake-up pipe after the block, and a short
    command's exit hook wrote to it as it closed: a traceback on stderr after gcp-find."""
    from geoortho.core.parallel import process_pool

    for _ in range(3):
        with process_pool(2, 4) as pool:
            assert isinstance(pool, cf.ProcessPoolExecutor)
            assert map_ordered(abs, [-1, -2, -3, -4], executor=pool) == [1, 2, 3, 4]
            manager = pool._executor_manager_thread  # type: ignore[attr-defined]
        assert manager is not None and not manager.is_alive()
