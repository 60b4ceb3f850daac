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
    """
    if executor is not None:
        return _map_on(executor, fn, items, as_feedback(feedback))
    with process_pool(workers, len(items), initializer=initializer, initargs=initargs,
                      min_items_for_pool=min_items_for_pool) as pool:
        if pool is not None:
            return _map_on(pool, fn, items, as_feedback(feedback))
        return _map_here(fn, items, as_feedback(feedback))


def imap_ordered(
    fn: Callable[[T], R],
    items: Sequence[T],
    *,
    workers: int = 0,
    initializer: Callable[..., Any] | None = None,
    initargs: tuple[Any, ...] = (),
    feedback: Feedback | None = None,
    executor: cf.Executor | None = None,
) -> Iterator[R]:
    """Like :func:`map_ordered`, but yields each result as soon as it and those before it are done,
    with at most a few items per worker in flight: memory stays bounded by the window, not by
    the number of items (tiles of a mosaic)."""
    fb = as_feedback(feedback)
    if executor is not None:
        yield from _imap_on(executor, fn, items, fb, 4 * (workers or os.cpu_count() or 1))
        return
    with process_pool(workers, len(items), initializer=initializer, initargs=initargs) as pool:
        if pool is None:
            for i, item in enumerate(items):
                fb.check_canceled()
                yield fn(item)
                fb.progress((i + 1) / len(items))
            return
        yield from _imap_on(pool, fn, items, fb, 2 * (workers or os.cpu_count() or 1))


def _imap_on(executor: cf.Executor, fn: Callable[[T], R], items: Sequence[T], fb: Feedback,
             in_flight: int) -> Iterator[R]:
    pending: collections.deque[cf.Future[R]] = collections.deque()
    it = iter(items)
    try:
        for item in itertools.islice(it, in_flight):
            pending.append(executor.submit(fn, item))
        done = 0
        while pending:
            fb.check_canceled()
            result = pending.popleft().result()
            nxt = next(it, _END)
            if nxt is not _END:
                pending.append(executor.submit(fn, nxt))  # type: ignore[arg-type]
            done += 1
            fb.progress(done / len(items))
            yield result
    finally:
        for f_ in pending:
            f_.cancel()


_END = object()


@contextmanager
def process_pool(
    workers: int, n_items: int, *, initializer: Callable[..., Any] | None = None,
    initargs: tuple[Any, ...] = (), min_items_for_pool: int = 2,
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
    pool = cf.ProcessPoolExecutor(n_procs, mp_context=ctx, initializer=initializer, initargs=initargs)
    for _ in range(n_procs):
        pool.submit(os.getpid)  # start the workers now: they import while the caller prepares
    try:
        yield pool
    finally:
        pool.shutdown(cancel_futures=True)


def _map_here(fn: Callable[[T], R], items: Sequence[T], fb: Feedback) -> list[R]:
    results: list[R] = []
    for i, item in enumerate(items):
        fb.check_canceled()
        results.append(fn(item))
        fb.progress((i + 1) / len(items))
    return results


def _map_on(executor: cf.Executor, fn: Callable[[T], R], items: Sequence[T], fb: Feedback) -> list[R]:
    futures = [executor.submit(fn, item) for item in items]
    results: list[R] = []
    try:
        for i, fut in enumerate(futures):
            fb.check_canceled()
            results.append(fut.result())
            fb.progress((i + 1) / len(items))
    except BaseException:
        for f_ in futures:
            f_.cancel()
        raise
    return results
