"""Per-item work on a process pool, in order, with progress and cancellation.

One place for the pattern every per-photo stage uses (rendering, detection):
``spawn`` workers (a caller may have started OpenCV's thread pool, which fork
does not survive), results in input order, progress per finished item, and
Cancel or an error stopping what has not started.
"""

from __future__ import annotations

import concurrent.futures as cf
import multiprocessing
import os
from collections.abc import Callable, Sequence
from typing import Any, TypeVar

from .feedback import Feedback, as_feedback

__all__ = ["map_ordered"]

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
    fb = as_feedback(feedback)
    n = len(items)
    n_workers = workers or os.cpu_count() or 1
    results: list[R] = []
    if executor is None and (n_workers <= 1 or n < min_items_for_pool):
        if initializer is not None:
            initializer(*initargs)
        for i, item in enumerate(items):
            fb.check_canceled()
            results.append(fn(item))
            fb.progress((i + 1) / n)
        return results
    own = None
    if executor is None:
        ctx = multiprocessing.get_context("spawn")
        own = executor = cf.ProcessPoolExecutor(min(n_workers, n), mp_context=ctx, initializer=initializer,
                                                initargs=initargs)
    futures = [executor.submit(fn, item) for item in items]
    try:
        for i, fut in enumerate(futures):
            fb.check_canceled()
            results.append(fut.result())
            fb.progress((i + 1) / n)
    except BaseException:
        for f_ in futures:
            f_.cancel()
        raise
    finally:
        if own is not None:
            own.shutdown(cancel_futures=True)
    return results
