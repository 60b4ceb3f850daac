"""One exception hierarchy for geoortho.

Only the faces (CLI, QGIS provider) translate these: the CLI exits 2 with one
stderr line for an :class:`InputError`, and 1 for anything else.
"""

from __future__ import annotations

from os import PathLike

__all__ = [
    "GeoorthoError",
    "InputError",
    "ParameterError",
    "CanceledError",
    "DependencyError",
    "ClusterError",
    "WorkerError",
    "GeoorthoWarning",
    "interrupted",
    "shortened",
]


class GeoorthoError(Exception):
    """Root of every error geoortho raises on purpose."""


class InputError(GeoorthoError, ValueError):
    """Bad input: a file, a line of it, or a parameter value.

    The message names where the problem is, ``path:line: reason``, so a user
    can go straight to it.

    Parameters
    ----------
    message
        What is wrong and, where it helps, what was expected.
    path
        The offending file, if any.
    line
        1-based line number in ``path``, if the input is a text file.
    """

    def __init__(self, message: str, *, path: str | PathLike[str] | None = None, line: int | None = None) -> None:
        self.reason = message
        self.path = None if path is None else str(path)
        self.line = line
        where = ""
        if self.path is not None:
            where = self.path if line is None else f"{self.path}:{line}"
            where += ": "
        super().__init__(where + message)


class ParameterError(InputError):
    """A parameter value that does not fit its spec (type, range, choices)."""

    def __init__(self, name: str, message: str) -> None:
        self.name = name
        super().__init__(f"{name}: {message}")


class CanceledError(GeoorthoError):
    """The user asked to stop; raised from the feedback's progress callback."""


class DependencyError(GeoorthoError, ImportError):
    """An optional dependency (pdal, dask.distributed) is missing."""


class ClusterError(GeoorthoError, RuntimeError):
    """The Dask cluster a run was given went away mid-run (its scheduler died or was unreachable)."""


class WorkerError(GeoorthoError, RuntimeError):
    """A worker process of the local pool ended abruptly (killed, out of memory, or dead at start-up)."""


class GeoorthoWarning(UserWarning):
    """Root of geoortho's warning classes."""


def interrupted(exc: BaseException) -> bool:
    """True when a Ctrl-C is what ``exc`` stands for, however a library wrapped it.

    A KeyboardInterrupt that lands while a C extension initialises comes back as that
    library's own error: pybind11 turns it into ``ImportError("initialization failed")``
    and pycolmap that into ``RuntimeError("Cannot import the C++ backend")``."""
    seen: set[int] = set()
    cur: BaseException | None = exc
    while cur is not None and id(cur) not in seen:
        if isinstance(cur, (KeyboardInterrupt, CanceledError)):
            return True
        seen.add(id(cur))
        cur = cur.__cause__ or cur.__context__
    return False


def shortened(text: str, limit: int = 40) -> str:
    """``text`` as a one-line message shows it: past ``limit`` characters (a number of hundreds of
    digits, a pasted page, a 300-character name), its head and tail with its length."""
    if len(text) <= limit:
        return text
    return f"{text[: limit // 2]}…{text[-8:]} ({len(text)} characters)"
