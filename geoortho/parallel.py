"""Per-item work on a process pool, in order, with progress and cancellation.

One place for the pattern every per-photo stage uses (rendering, detection):
``spawn`` workers (a caller may have started OpenCV's thread pool, which fork
does not survive), results in input order, progress per finished item, and
Cancel or an error stopping what has not started.
"""

from __future__ import annotations

import collections
import concurrent.futures as cf
import itertools
import multiprocessing
import os
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from typing import Any, TypeVar

from .feedback import Feedback, as_feedback

__all__ = ["imap_ordered", "map_ordered", "process_pool"]

T = TypeVar("T")
R = TypeVar("R")


def map_ordered(
    fn: Callable[[T], R],
    items: Sequence[T],
    *,
    workers: int = 0,
    initializer: Callable[..., Any] | None = None,
    initargs: tuple[Any, ...] = (),
    feedback: Feedback | None = None,
    min_items_for_pool: int = 2,
    executor: cf.Executor | None = None,
) -> list[R]:
    """``[fn(x) for x in items]`` on ``workers`` processes (0 = every core).

    In-process when one worker is asked for or there are fewer than
    ``min_items_for_pool`` items; on ``executor`` when one is given (e.g. a
    Dask ``Client.get_executor()``; ``initializer`` is then not run).
    Every item is submitted at once: the caller wants the whole list anyway.
    """
    return list(
        imap_ordered(
            fn,
            items,
            workers=workers,
            initializer=initializer,
            initargs=initargs,
            feedback=feedback,
            min_items_for_pool=min_items_for_pool,
            executor=executor,
            in_flight=max(1, len(items)),
        )
    )


def imap_ordered(
    fn: Callable[[T], R],
    items: Sequence[T],
    *,
    workers: int = 0,
    initializer: Callable[..., Any] | None = None,
    initargs: tuple[Any, ...] = (),
    feedback: Feedback | None = None,
    min_items_for_pool: int = 2,
    executor: cf.Executor | None = None,
    in_flight: int | None = None,
) -> Iterator[R]:
    """Like :func:`map_ordered`, but yields each result as soon as it and those before it are done,
    with at most ``in_flight`` items submitted and not yet yielded (default two per worker): memory
    stays bounded by that window, not by the number of items (tiles of a mosaic)."""
    fb = as_feedback(feedback)
    window = in_flight or 2 * (workers or os.cpu_count() or 1)
    if executor is not None:
        yield from _imap_on(executor, fn, items, fb, window)
        return
    with process_pool(
        workers, len(items), initializer=initializer, initargs=initargs, min_items_for_pool=min_items_for_pool
    ) as pool:
        if pool is not None:
            yield from _imap_on(pool, fn, items, fb, window)
            return
        for i, item in enumerate(items):
            fb.check_canceled()
            yield fn(item)
            fb.progress((i + 1) / len(items))


def _imap_on(
    executor: cf.Executor, fn: Callable[[T], R], items: Sequence[T], fb: Feedback, in_flight: int
) -> Iterator[R]:
    """Results in order with at most ``in_flight`` futures pending; Cancel or an error (or the
    consumer stopping) cancels what has not started."""
    pending: collections.deque[cf.Future[R]] = collections.deque()
    it = iter(items)
    try:
        for item in itertools.islice(it, in_flight):
            pending.append(executor.submit(fn, item))
        done = 0
        while pending:
            fb.check_canceled()
            result = pending.popleft().result()
            for nxt in itertools.islice(it, 1):
                pending.append(executor.submit(fn, nxt))
            done += 1
            fb.progress(done / len(items))
            yield result
    finally:
        for f_ in pending:
            f_.cancel()


@contextmanager
def process_pool(
    workers: int,
    n_items: int,
    *,
    initializer: Callable[..., Any] | None = None,
    initargs: tuple[Any, ...] = (),
    min_items_for_pool: int = 2,
) -> Iterator[cf.Executor | None]:
    """A spawn pool to share between several ``map_ordered`` calls (one start-up), or None
    (after running ``initializer`` here) when in-process is the better choice."""
    n_workers = workers or os.cpu_count() or 1
    if n_workers <= 1 or n_items < min_items_for_pool:
        if initializer is not None:
            initializer(*initargs)
        yield None
        return
    ctx = multiprocessing.get_context("spawn")
    n_procs = min(n_workers, n_items)
    pool = cf.ProcessPoolExecutor(
        n_procs, mp_context=ctx, initializer=_worker_start, initargs=(os.getpid(), initializer, initargs)
    )
    for _ in range(n_procs):
        pool.submit(os.getpid)  # start the workers now: they import while the caller prepares
    try:
        yield pool
    finally:
        pool.shutdown(cancel_futures=True)


def _die_with_parent() -> None:
    """Linux: ask the kernel to send SIGKILL to this worker when its parent dies (a SIGKILLed run
    must not leave workers computing for minutes); elsewhere nothing."""
    import ctypes
    import signal
    import sys

    if not sys.platform.startswith("linux"):
        return
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        pr_set_pdeathsig = 1
        libc.prctl(pr_set_pdeathsig, signal.SIGKILL, 0, 0, 0)
    except (OSError, AttributeError):
        pass


def _worker_start(parent_pid: int, initializer: Callable[..., Any] | None, initargs: tuple[Any, ...]) -> None:
    """Every pool worker's first act: die with the parent, then the caller's initializer."""
    _die_with_parent()
    if os.getppid() != parent_pid:  # the parent died before the request took effect
        os._exit(1)
    if initializer is not None:
        initializer(*initargs)
