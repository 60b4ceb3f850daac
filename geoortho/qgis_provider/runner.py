"""Run ``python -m geoortho <id>`` in a subprocess, feeding a QGIS-like feedback.

No qgis import here. The feedback is anything with QgsProcessingFeedback's
methods ``setProgress(percent)``, ``pushInfo``, ``pushWarning``,
``pushConsoleInfo`` and ``isCanceled()``.

The CLI's ``--progress-json`` writes one JSON object a line on stderr
(``{"progress": 0.42}``, ``{"info": ...}``, ``{"warning": ...}``); its
``--json`` prints the outputs on stdout at the end. Exit codes: 0 done, 2 bad
input (one line on stderr), 130 canceled, anything else a failure.
"""

from __future__ import annotations

import json
import os
import queue
import signal
import subprocess
import threading
import time
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any, Protocol

from .interpreter import NEUTRAL_CWD, clean_environment

__all__ = ["RunCanceled", "RunFailed", "run_geoortho", "remove_partial_outputs"]


class ProcessingFeedbackLike(Protocol):
    def setProgress(self, progress: float) -> None: ...  # noqa: N802 (QGIS's name)
    def pushInfo(self, info: str) -> None: ...  # noqa: N802
    def pushWarning(self, warning: str) -> None: ...  # noqa: N802
    def pushConsoleInfo(self, info: str) -> None: ...  # noqa: N802
    def setProgressText(self, text: str) -> None: ...  # noqa: N802
    def isCanceled(self) -> bool: ...  # noqa: N802


class RunFailed(RuntimeError):
    """geoortho exited with an error; the message is geoortho's own last line."""

    def __init__(self, message: str, returncode: int) -> None:
        super().__init__(message)
        self.returncode = returncode


class RunCanceled(RuntimeError):
    """The run was canceled and the process has ended."""


#: Seconds a canceled geoortho gets to stop at its next progress report (and
#: remove its temporary files) before its whole process group is killed.
CANCEL_GRACE_S = 10.0


def _reader(stream: Any, sink: queue.Queue[str | None]) -> None:
    for line in iter(stream.readline, ""):
        sink.put(line.rstrip("\n"))
    sink.put(None)


def _popen_kwargs() -> dict[str, Any]:
    # Its own process group, so a kill reaches the worker processes too.
    if os.name == "posix":
        return {"start_new_session": True}
    return {"creationflags": getattr(subprocess, "CREATE_NEW_PROCESS_GROUP", 0)}


def _kill_group(proc: subprocess.Popen[str]) -> None:
    """SIGKILL the run's process group: geoortho and any worker still alive."""
    if os.name == "posix":
        try:
            os.killpg(proc.pid, signal.SIGKILL)
        except (ProcessLookupError, PermissionError):
            pass  # the group has ended
    elif proc.poll() is None:
        proc.kill()


def _handle_line(line: str, feedback: ProcessingFeedbackLike, plain: list[str]) -> None:
    message: Any = None
    if line.startswith("{"):
        try:
            message = json.loads(line)
        except ValueError:
            message = None
    if not isinstance(message, dict):
        if line.strip():
            plain.append(line)
            feedback.pushConsoleInfo(line)
        return
    if message.get("type") in ("error", "canceled"):  # geoortho's last word, as one JSON object
        plain.append(str(message.get("message", "")))
        return
    if "progress" in message:
        feedback.setProgress(100.0 * float(message["progress"]))
    if "info" in message:
        feedback.pushInfo(str(message["info"]))
    if "warning" in message:
        feedback.pushWarning(str(message["warning"]))
    if "stage" in message:  # a run of stages: the stage's name over the progress bar
        feedback.setProgressText(f"[{message.get('index', '?')}/{message.get('count', '?')}] {message['stage']}")


def remove_partial_outputs(destinations: Iterable[str | os.PathLike[str]]) -> list[Path]:
    """Remove the temporary files geoortho writes beside each destination.

    geoortho writes ``<dir>/.<stem>.tmp-<random><suffix>`` and renames it when
    complete (``geoortho.core.outputs.atomic_path``); a killed run leaves that
    temporary, never a half-written destination.
    """
    removed = []
    for destination in destinations:
        target = Path(destination)
        if not target.parent.is_dir():
            continue
        for tmp in target.parent.glob(f".{target.stem}.tmp-*"):
            try:
                tmp.unlink()
                removed.append(tmp)
            except OSError:
                pass
    return removed


def _start(cmd: list[str]) -> subprocess.Popen[str]:
    """The CLI started in a clean environment and a neutral folder, its streams piped."""
    try:
        return subprocess.Popen(
            cmd,
            stdin=subprocess.DEVNULL,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            encoding="utf-8",
            errors="replace",
            env=clean_environment(),
            cwd=NEUTRAL_CWD,
            **_popen_kwargs(),
        )
    except OSError as e:
        raise RunFailed(f"could not start {cmd[0]}: {e}", -1) from None


def run_geoortho(
    interpreter: str,
    algorithm_id: str,
    arguments: Sequence[str],
    feedback: ProcessingFeedbackLike,
    *,
    destinations: Sequence[str | os.PathLike[str]] = (),
    poll_s: float = 0.1,
    grace_s: float = CANCEL_GRACE_S,
) -> dict[str, Any]:
    """Run one algorithm through the CLI and return its outputs dict.

    Raises :class:`RunFailed` (with geoortho's message) or :class:`RunCanceled`.
    On Cancel the process gets SIGTERM, which geoortho turns into a cancel at
    its next progress report; after ``grace_s`` the process group is killed and
    the temporary files beside ``destinations`` are removed.
    """
    cmd = [interpreter, "-m", "geoortho", algorithm_id, *arguments, "--json", "--progress-json"]
    feedback.pushConsoleInfo(" ".join(_quote(c) for c in cmd))
    proc = _start(cmd)

    lines: queue.Queue[str | None] = queue.Queue()
    stdout_chunks: list[str] = []
    threads = [
        threading.Thread(target=_reader, args=(proc.stderr, lines), daemon=True),
        threading.Thread(target=lambda: stdout_chunks.append(proc.stdout.read()), daemon=True),  # type: ignore[union-attr]
    ]
    for t in threads:
        t.start()

    plain: list[str] = []
    canceled_at: float | None = None
    stderr_open = True
    exited_at: float | None = None
    while stderr_open:
        if proc.poll() is not None:
            exited_at = exited_at or time.monotonic()
            if time.monotonic() - exited_at > 2 * grace_s:
                break  # a leftover child holds stderr open; geoortho itself is done
        elif canceled_at is None and feedback.isCanceled():
            canceled_at = time.monotonic()
            feedback.pushInfo("canceling geoortho ...")
            proc.terminate()
        if canceled_at is not None and time.monotonic() - canceled_at > grace_s:
            _kill_group(proc)
        try:
            line = lines.get(timeout=poll_s)
        except queue.Empty:
            continue
        if line is None:
            stderr_open = False
        else:
            _handle_line(line, feedback, plain)
    returncode = proc.wait()
    for t in threads:
        t.join(timeout=5)
    for stream in (proc.stdout, proc.stderr):
        if stream is not None:
            stream.close()
    if canceled_at is not None:
        _kill_group(proc)  # workers a grace kill orphaned
        if returncode != 0:  # (a run that finished before the cancel landed is simply done)
            remove_partial_outputs(destinations)
            raise RunCanceled(f"geoortho {algorithm_id}: canceled")
    if returncode != 0:
        message = plain[-1] if plain else f"geoortho {algorithm_id} exited with code {returncode}"
        if returncode == 130:
            raise RunCanceled(message)
        raise RunFailed(message, returncode)
    stdout = "".join(stdout_chunks)
    try:
        outputs = json.loads(stdout)
    except ValueError:
        raise RunFailed(f"geoortho {algorithm_id} printed no JSON outputs: {stdout[-300:]!r}", returncode) from None
    return outputs if isinstance(outputs, dict) else {}


def _quote(word: str) -> str:
    return word if word and all(c.isalnum() or c in "-_./:=,+@%" for c in word) else repr(word)
