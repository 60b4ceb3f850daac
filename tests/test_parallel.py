"""The process-pool helper: order, the in-flight window, cancellation."""

from __future__ import annotations

import concurrent.futures as cf
import threading

import pytest

from geoortho.errors import CanceledError
from geoortho.feedback import Feedback
from geoortho.parallel import imap_ordered, map_ordered


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
