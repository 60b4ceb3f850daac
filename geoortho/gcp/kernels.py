"""Compiled kernels for the target fits, with numba when it imports (numpy paths otherwise).

A degraded survey's coded fits render their model some 40,000 times, and solve its levels as
often; in numpy each is a dozen small array operations, most of their time spent starting them.
Compiled, each is one loop, with the same arithmetic in the same order, so a fit ends where the
numpy paths end it, to the last bit (tests/test_gcp_targets.py holds them so).

numba is imported once a process has asked for a kernel :data:`WARM_CALLS` times (and taken the
numpy path), not with the package: importing it and loading the cached code takes 0.4 s and
130 MiB a process, which a clean survey's few fits would never pay back (a compiled render saves
about 90 us). The compiled code is cached on disk (numba's own cache, beside this file or in its
user-wide folder), so a fresh process loads it rather than compiling. Compiling takes 6 s
(:func:`geoortho.gcp.targets.warm`, which ``make`` runs ahead).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager
from functools import cache
from typing import Any

import numpy as np

from geoortho.core import kernels as kernel_loader

#: Set to 0 to keep the numpy paths (a check of the kernels, or a platform numba fails on).
ENV_SWITCH = kernel_loader.ENV_SWITCH


#: Calls for a kernel answered "the numpy way" before the compiled kernels are loaded: a degraded
#: small survey's worker renders some 19,000 models, a clean survey's none; 3,000 is a handful of
#: fits, and loading the kernels then costs what 4,500 compiled renders save.
WARM_CALLS = 3000
_numpy_calls = 0


def compiled(name: str, calls: int = 1) -> Callable[..., Any] | None:
    """The compiled kernel ``name`` (a function of this module), or None: the numpy path is to be
    taken (numba absent or switched off, or the process has not done enough to pay for loading
    it). ``calls``: how many the asker makes at once (a kernel's rows)."""
    global _numpy_calls
    if _numpy_calls < WARM_CALLS:
        _numpy_calls += calls
        return None
    return _compiled(name)


@cache
def _compiled(name: str) -> Callable[..., Any] | None:
    return kernel_loader.compiled(globals()[name])


@contextmanager
def compiled_now() -> Iterator[None]:
    """Inside, every kernel asked for is the compiled one at once (for warming numba's cache:
    :func:`geoortho.gcp.targets.warm`)."""
    global _numpy_calls
    calls, _numpy_calls = _numpy_calls, WARM_CALLS
    try:
        yield
    finally:
        _numpy_calls = calls


def _coded_render(
    xs: np.ndarray,
    ys: np.ndarray,
    cxs: np.ndarray,
    cys: np.ndarray,
    sdx: np.ndarray,
    sdy: np.ndarray,
    inv: np.ndarray,
    table: np.ndarray,
    n: int,
    origin: float,
    on: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Mean reflectance and share on the board of each pixel of a coded marker's model, for each
    of a few places of it (rows): a fit's Jacobian asks a dozen at once.

    ``xs, ys``: the pixels; per row, ``cxs, cys``: the centre, ``sdx, sdy``: the sample offsets
    (pixel area, motion path, defocus), ``inv``: pixel offsets → marker sides (row-major 2 × 2);
    ``table``: the board's cells with a ring around them, flat, each white + ``on`` × on the board;
    ``origin``: a cell index's offset. :meth:`.look.Renderer.render`'s numpy path step for step
    (its test holds the two equal)."""
    rows, pixels, samples = cxs.shape[0], xs.shape[0], sdx.shape[1]
    value = np.empty((rows, pixels))
    cover = np.empty((rows, pixels))
    su = np.empty(samples)
    sv = np.empty(samples)
    cell = np.empty(samples, np.int64)
    top = n + 3.0
    width = n + 4
    for k in range(rows):
        i00, i01, i10, i11 = inv[k, 0], inv[k, 1], inv[k, 2], inv[k, 3]
        for j in range(samples):
            su[j] = (i00 * sdx[k, j] + i01 * sdy[k, j]) * n
            sv[j] = -(i10 * sdx[k, j] + i11 * sdy[k, j]) * n
        if np.isnan(su).any() or np.isnan(sv).any():
            raise ValueError("the model's blur or shape is not a number")
        for i in range(pixels):
            px, py = xs[i] - cxs[k], ys[i] - cys[k]
            a = (i00 * px + i01 * py) * n + origin
            b = -(i10 * px + i11 * py) * n + origin
            if np.isnan(a) or np.isnan(b):  # (a NaN would index anywhere)
                raise ValueError("the model's place is not a number")
            # each sample's cell first, clipped to the ring (truncation is the floor), then their
            # sum: two loops without a branch, which the compiler vectorises (2x the one loop with ifs)
            for j in range(samples):
                cell[j] = int(min(max(b + sv[j], 0.0), top)) * width + int(min(max(a + su[j], 0.0), top))
            packed = 0.0
            for j in range(samples):
                packed += table[cell[j]]
            count = np.floor(packed / on)
            value[k, i] = (packed - on * count) / max(count, 1.0)
            cover[k, i] = count / samples
    return value, cover


def _glare_exponent(
    x: np.ndarray, y: np.ndarray, gx: float, gy: float, vx: float, vy: float, path: np.ndarray, var: float
) -> np.ndarray:
    """The exponent of a Gaussian glare spot centred at (``gx``, ``gy``) of variance ``var`` (px²)
    at each sample of each pixel (pixels × samples), the samples along the motion path ``path``
    (−½…½) of the blur vector (``vx``, ``vy``). numpy takes the exponential and the mean: its own
    exp is not the compiled one to the last bit, and a fit's path follows the last bit."""
    out = np.empty((x.shape[0], path.shape[0]))
    for i in range(x.shape[0]):
        for j in range(path.shape[0]):
            dx = x[i] - gx + vx * path[j]
            dy = y[i] - gy - vy * path[j]
            out[i, j] = -(dx * dx + dy * dy) / (2 * var)
    return out


def _level_residuals(
    t: np.ndarray,
    cover: np.ndarray,
    spot: np.ndarray,
    rim: bool,
    seen: np.ndarray,
    solved: np.ndarray,
    censor: np.ndarray,
) -> np.ndarray:
    """A fit's residuals (grey levels / 8) once its levels are solved in closed form, for each of a
    few models (rows of ``t``, ``cover`` and ``spot``): gain, the board's and the ground's offsets
    (``rim``: the model covers ``cover`` of a pixel, the ground the rest) and the glare's amplitude
    (``spot``, no columns for none), by least squares on the ``solved`` pixels; a ``censor``-ed
    (clipped) pixel counts only where the model is brighter."""
    glare = spot.shape[1] > 0
    k = (3 if rim else 2) + (1 if glare else 0)
    pixels = t.shape[1]
    out = np.empty(t.shape)
    d = np.empty((pixels, k))
    rows = np.flatnonzero(solved)
    rcond = np.finfo(np.float64).eps * max(rows.shape[0], k)
    for m in range(t.shape[0]):
        for i in range(pixels):
            if rim:
                d[i, 0] = t[m, i] * cover[m, i]
                d[i, 1] = 1.0 - cover[m, i]
                d[i, 2] = 1.0
            else:
                d[i, 0] = t[m, i]
                d[i, 1] = 1.0
            if glare:
                d[i, k - 1] = spot[m, i]
        coef = np.linalg.lstsq(d[rows], seen[rows], rcond=rcond)[0]
        r = d @ coef - seen
        for i in range(pixels):
            if censor[i] and r[i] > 0.0:
                r[i] = 0.0
        out[m] = r / 8.0
    return out
