"""Compiled kernels for the target fits, with numba when it imports (numpy paths otherwise).

A degraded survey's coded fits render their model some 40,000 times; in numpy each render is a
dozen small array operations, most of its time spent starting them. Compiled, the render is one
loop, with the same arithmetic in the same order, so its result is the same to the bit.

numba is imported once a process has rendered :data:`WARM_RENDERS` models the numpy way, not with
the package: importing it and loading the cached code takes 0.4 s a process, which a clean
survey's few fits would never pay back (a compiled render saves about 90 us). The compiled code is
cached on disk (numba's own cache, beside this file or in its user-wide folder), so a fresh process
loads it rather than compiling.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from functools import cache

import numpy as np

#: Set to 0 to keep the numpy paths (a check of the kernels, or a platform numba fails on).
ENV_SWITCH = "GEOORTHO_COMPILED"


#: numpy renders before the compiled one is loaded: a degraded small survey's worker renders some
#: 19,000 models, a clean survey's none; 3,000 is a handful of fits, and loading the kernel then
#: costs what 4,500 compiled renders save.
WARM_RENDERS = 3000
_numpy_renders = 0


def coded_render_kernel() -> Callable[..., tuple[np.ndarray, np.ndarray]] | None:
    """The compiled coded-marker render, or None: the numpy path is to be taken (numba absent or
    switched off, or the process has not rendered enough to pay for loading it)."""
    global _numpy_renders
    if _numpy_renders < WARM_RENDERS:
        _numpy_renders += 1
        return None
    return _compiled_coded_render()


@cache
def _compiled_coded_render() -> Callable[..., tuple[np.ndarray, np.ndarray]] | None:
    if os.environ.get(ENV_SWITCH, "1") == "0":
        return None
    try:
        from numba import njit
    except ImportError:  # an environment without it (a QGIS install's own Python): numpy paths
        return None
    return njit(cache=True, nogil=True)(_coded_render)


def _coded_render(
    px: np.ndarray,
    py: np.ndarray,
    sdx: np.ndarray,
    sdy: np.ndarray,
    inv: tuple[float, float, float, float],
    table: np.ndarray,
    n: int,
    origin: float,
    on: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Mean reflectance and share on the board of each pixel of a coded marker's model.

    ``px, py``: pixel offsets from the centre; ``sdx, sdy``: sample offsets (pixel area, motion
    path, defocus); ``inv``: pixel offsets → marker sides (row-major 2 × 2); ``table``: the board's
    cells with a ring around them, flat, each white + ``on`` × on the board; ``origin``: a cell
    index's offset. :meth:`.targets._Renderer.render`'s numpy path step for step (its test holds
    the two equal)."""
    i00, i01, i10, i11 = inv
    samples = sdx.shape[0]
    su = np.empty(samples)
    sv = np.empty(samples)
    for j in range(samples):
        su[j] = (i00 * sdx[j] + i01 * sdy[j]) * n
        sv[j] = -(i10 * sdx[j] + i11 * sdy[j]) * n
    top = n + 3.0
    width = n + 4
    value = np.empty(px.shape[0])
    cover = np.empty(px.shape[0])
    for i in range(px.shape[0]):
        a = (i00 * px[i] + i01 * py[i]) * n + origin
        b = -(i10 * px[i] + i11 * py[i]) * n + origin
        packed = 0.0
        for j in range(samples):
            col = a + su[j]
            row = b + sv[j]
            # clipped to the ring; truncation is the floor (a NaN reads the corner, not memory)
            if not col >= 0.0:
                col = 0.0
            elif col > top:
                col = top
            if not row >= 0.0:
                row = 0.0
            elif row > top:
                row = top
            packed += table[int(row) * width + int(col)]
        count = np.floor(packed / on)
        value[i] = (packed - on * count) / max(count, 1.0)
        cover[i] = count / samples
    return value, cover
