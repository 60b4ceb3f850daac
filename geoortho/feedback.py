"""Progress, messages and cancellation, injected into every core function.

Core functions take ``feedback: Feedback | None``; they report progress as a
fraction 0..1, and the callback raises :class:`~geoortho.errors.CanceledError`
when the user asked to stop, so a cancel needs no check beyond reporting
progress.
"""

from __future__ import annotations

import json
import logging
import os
import sys
import threading
import time
from collections.abc import Iterable, Iterator, Sequence
from typing import IO, Any, TypeVar

from geoortho.errors import CanceledError

__all__ = [
    "Feedback",
    "NullFeedback",
    "TerminalFeedback",
    "JsonLinesFeedback",
    "as_feedback",
    "split",
    "track",
    "warn_grouped",
]

log = logging.getLogger(__name__)
T = TypeVar("T")


class Feedback:
    """Base feedback: logs messages, ignores progress, can be canceled.

    Subclasses override :meth:`set_progress` and the message methods; callers
    use :meth:`progress`, which also raises when canceled.
    """

    def __init__(self) -> None:
        self._cancel = threading.Event()

    # --- what core code calls -------------------------------------------------
    def progress(self, fraction: float) -> None:
        """Report progress (0..1); raise CanceledError if a cancel was asked."""
        self.check_canceled()
        self.set_progress(min(1.0, max(0.0, float(fraction))))

    def info(self, message: str) -> None:
        log.info(message)

    def warning(self, message: str) -> None:
        log.warning(message)

    def is_canceled(self) -> bool:
        return self._cancel.is_set()

    def stage(self, name: str, index: int, count: int, start: float, width: float) -> None:
        """A run of several stages (``run``) enters stage ``index`` of ``count``, which spans
        [start, start + width] of this feedback's progress; faces that can show it do."""

    def check_canceled(self) -> None:
        if self.is_canceled():
            raise CanceledError("canceled by the user")

    # --- what faces call ------------------------------------------------------
    def cancel(self) -> None:
        self._cancel.set()

    def set_progress(self, fraction: float) -> None:
        """Show progress; the base class shows nothing."""

    def close(self) -> None:
        """Finish any display (progress bar)."""


class NullFeedback(Feedback):
    """Feedback that shows nothing and logs nothing."""

    def info(self, message: str) -> None:
        pass

    def warning(self, message: str) -> None:
        pass


def as_feedback(feedback: Feedback | None) -> Feedback:
    """The given feedback, or a :class:`NullFeedback` for None."""
    return NullFeedback() if feedback is None else feedback


class _SubFeedback(Feedback):
    """Maps 0..1 of a sub-step onto [start, start+width] of its parent."""

    def __init__(self, parent: Feedback, start: float, width: float) -> None:
        super().__init__()
        self._parent = parent
        self._start = start
        self._width = width

    def set_progress(self, fraction: float) -> None:
        self._parent.progress(self._start + self._width * fraction)

    def info(self, message: str) -> None:
        self._parent.info(message)

    def warning(self, message: str) -> None:
        self._parent.warning(message)

    def stage(self, name: str, index: int, count: int, start: float, width: float) -> None:
        self._parent.stage(name, index, count, self._start + self._width * start, self._width * width)

    def is_canceled(self) -> bool:
        return self._parent.is_canceled() or super().is_canceled()

    def cancel(self) -> None:
        self._parent.cancel()


def split(feedback: Feedback | None, weights: Sequence[float]) -> list[Feedback]:
    """Split one run into sub-steps with relative weights.

    >>> steps = split(None, [1, 3])
    >>> len(steps)
    2
    """
    parent = as_feedback(feedback)
    total = float(sum(weights))
    if total <= 0:
        raise ValueError("weights must sum to a positive number")
    out: list[Feedback] = []
    start = 0.0
    for w in weights:
        out.append(_SubFeedback(parent, start / total, w / total))
        start += w
    return out


def track(items: Iterable[T], feedback: Feedback | None, total: int | None = None) -> Iterator[T]:
    """Yield items, reporting progress after each (and checking for cancel)."""
    fb = as_feedback(feedback)
    if total is None:
        try:
            total = len(items)  # type: ignore[arg-type]
        except TypeError:
            total = None
    fb.progress(0.0)
    for i, item in enumerate(items, 1):
        yield item
        if total:
            fb.progress(i / total)


class TerminalFeedback(Feedback):
    """A tqdm progress bar on stderr and messages through logging.

    In a run of stages, two bars: the whole run (with the stage's name and number, and the ETA)
    and the current stage.
    """

    _FORMAT = "{desc} {percentage:3.0f}%|{bar}| {elapsed}<{remaining}"

    def __init__(self, description: str = "", *, quiet: bool = False, stream: IO[str] | None = None) -> None:
        super().__init__()
        self._quiet = quiet
        self._stream = stream if stream is not None else sys.stderr
        self._bar: Any = None
        self._stage_bar: Any = None
        self._description = description
        self._stage: tuple[str, float, float] | None = None
        self._stage_started = self._heartbeat = 0.0

    def _shown(self) -> bool:
        if self._quiet or not getattr(self._stream, "isatty", lambda: False)():
            return False
        # a terminal with no width (a CI log, `script`) draws no bar: it gets the heartbeat lines
        try:
            return os.get_terminal_size(self._stream.fileno()).columns > 0
        except (OSError, ValueError, AttributeError):  # a terminal whose size cannot be asked
            return True

    def _new_bar(self, description: str, position: int) -> Any:
        from tqdm import tqdm

        return tqdm(
            total=1000, desc=description, file=self._stream, leave=False, position=position, bar_format=self._FORMAT
        )

    #: Without a terminal (stderr to a file or a pipe) a long stage says how far it is this often.
    HEARTBEAT_S = 60.0

    def stage(self, name: str, index: int, count: int, start: float, width: float) -> None:
        self._stage = (name, start, width)
        if not self._shown():
            # no bar to watch: a line per stage, and a heartbeat (set_progress), so that a log
            # shows a 30-minute SfM alive
            if not self._quiet:
                self._stage_started = self._heartbeat = time.monotonic()
                self._write(f"{self._description} [{index}/{count}] {name}: started {time.strftime('%H:%M:%S')}")
            return
        if self._bar is None:
            self._bar = self._new_bar(self._description, 0)
        self._bar.set_description_str(f"{self._description} [{index}/{count}] {name}", refresh=False)
        if self._stage_bar is None:
            self._stage_bar = self._new_bar(f"  {name}", 1)
        else:
            self._stage_bar.reset(total=1000)
            self._stage_bar.set_description_str(f"  {name}", refresh=False)

    def set_progress(self, fraction: float) -> None:
        if not self._shown():
            if not self._quiet and self._stage is not None:
                now = time.monotonic()
                if now - self._heartbeat >= self.HEARTBEAT_S:
                    self._heartbeat = now
                    name, start, width = self._stage
                    within = min(1.0, max(0.0, (fraction - start) / width)) if width > 0 else 1.0
                    self._write(f"  {name}: {within:.0%} after {(now - self._stage_started) / 60:.1f} min")
            return
        if self._bar is None:
            self._bar = self._new_bar(self._description, 0)
        self._bar.n = int(round(fraction * 1000))
        self._bar.refresh()
        if self._stage is not None and self._stage_bar is not None:
            _, start, width = self._stage
            within = (fraction - start) / width if width > 0 else 1.0
            self._stage_bar.n = int(round(min(1.0, max(0.0, within)) * 1000))
            self._stage_bar.refresh()

    def _write(self, message: str) -> None:
        if self._bar is not None:
            self._bar.write(message, file=self._stream)
        else:
            print(message, file=self._stream)

    def info(self, message: str) -> None:
        log.info(message)
        if not self._quiet:
            self._write(message)

    def warning(self, message: str) -> None:
        log.warning(message)
        if not self._quiet:  # --quiet: errors only (warnings stay in the log and the products' reports)
            self._write(f"warning: {message}")

    def close(self) -> None:
        for bar in (self._stage_bar, self._bar):
            if bar is not None:
                bar.close()
        self._bar = self._stage_bar = None


class JsonLinesFeedback(Feedback):
    """Machine-readable feedback: one JSON object a line (for the QGIS provider).

    ``{"progress": 0.42}``, ``{"info": "..."}``, ``{"warning": "..."}``.
    Progress lines are written only when the value moved by 0.1 % or more.
    """

    def __init__(self, stream: IO[str] | None = None) -> None:
        super().__init__()
        self._stream = stream if stream is not None else sys.stderr
        self._last = -1.0

    def _emit(self, obj: dict[str, object]) -> None:
        # plain values only (a progress, a message, a stage's name and numbers): the standard
        # library's JSON, strict as the reader is
        self._stream.write(json.dumps(obj, allow_nan=False) + "\n")
        self._stream.flush()

    def set_progress(self, fraction: float) -> None:
        if abs(fraction - self._last) >= 0.001 or fraction == 1.0:
            self._last = fraction
            self._emit({"progress": round(fraction, 4)})

    def info(self, message: str) -> None:
        self._emit({"info": message})

    def warning(self, message: str) -> None:
        self._emit({"warning": message})

    def stage(self, name: str, index: int, count: int, start: float, width: float) -> None:
        self._emit({"stage": name, "index": index, "count": count})


def warn_grouped(feedback: Feedback | None, kind: str, items: Sequence[str], *, show: int = 3) -> None:
    """One warning for many photos with the same problem: the kind, the count and the first few.

    >>> warn_grouped(None, "no attitude: assumed nadir", ["a.jpg", "b.jpg"])
    """
    if not items:
        return
    first = ", ".join(items[:show]) + (", …" if len(items) > show else "")
    as_feedback(feedback).warning(f"{kind}: {len(items)} photo{'s' if len(items) != 1 else ''} ({first})")


def reclaim_signal_handlers() -> None:
    """Put Python's own SIGTERM handler back after a library replaced it at the C level.

    COLMAP's glog installs a failure handler on SIGTERM when pycolmap is imported: a
    terminated run (QGIS's Cancel) then dies with a 30-line C++ dump and leaves its work
    folder. Python still knows its handler (the CLI's: cancel the feedback); set it again."""
    import signal

    if threading.current_thread() is not threading.main_thread():
        return
    handler = signal.getsignal(signal.SIGTERM)
    if handler is not None:
        signal.signal(signal.SIGTERM, handler)
