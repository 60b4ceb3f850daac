"""Compiled loops with numba, where it imports: each kernel is a plain Python function that its
module also keeps a numpy path for, compiled here on first use and cached on disk (numba's cache,
beside the module or in its user-wide folder), so a fresh process loads it rather than compiling.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from functools import cache
from typing import Any

#: Set to 0 to keep the numpy paths (a check of the kernels, or a platform numba fails on).
ENV_SWITCH = "GEOORTHO_COMPILED"


def compiled(function: Callable[..., Any]) -> Callable[..., Any] | None:
    """``function`` compiled by numba (no Python objects inside, no GIL held), or None where the
    numpy path is to be taken: numba absent or switched off (ENV_SWITCH), or nowhere to cache."""
    if os.environ.get(ENV_SWITCH, "1") == "0":
        return None
    return _compiled(function)


@cache
def _compiled(function: Callable[..., Any]) -> Callable[..., Any] | None:
    try:
        from numba import njit
    except (ImportError, OSError):  # none in this environment (a QGIS install's own Python), or its
        return None  # LLVM fails to load: the numpy paths
    try:
        return njit(cache=True, nogil=True)(function)
    except RuntimeError:  # no folder to cache in: compiling in every process would cost seconds
        return None
