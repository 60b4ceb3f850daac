"""Where a cloud's points are: a scan of a sample that finds the core of the survey, with far outliers
(a stray point kilometres off) left out of the grid and counted.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from geoortho.core.pointcloud import PointSource
from geoortho.elevation.grid import (
    Box,
    finite_points,
)
from geoortho.errors import InputError
from geoortho.feedback import Feedback


def auto_resolution_m(src: PointSource) -> float:
    """About two points per cell on average, rounded to a 1-2-2.5-5 step."""
    xmin, ymin, _, xmax, ymax, _ = src.bounds
    area_m2 = max((xmax - xmin) * (ymax - ymin), 1e-9) * src.horizontal_m**2
    raw = math.sqrt(2.0 * area_m2 / max(src.count, 1))
    steps = [m * 10.0**e for e in range(-2, 3) for m in (1.0, 2.0, 2.5, 5.0)]
    return min(steps, key=lambda s: abs(math.log(s / raw)))


#: Points sampled by the extent scan; far outliers are judged against the sample's core.
SCAN_SAMPLE = 200_000
#: The core holds all but this share of the sampled points on each side of each axis.
CORE_TAIL = 0.001
#: A far outlier lies beyond the core by more than the core's size and more than this
#: (metres; heights: at least FAR_Z_M, as no structure is taller).
FAR_XY_M = 100.0
FAR_Z_M = 1000.0
#: Points beyond the core by that much are outliers only while they are this rare; more are data.
MAX_OUTLIER_SHARE = 0.001


@dataclass(frozen=True)
class _Scan:
    src: PointSource  # with the bounds of the points kept
    keep: Box | None  # the box far outliers fall out of (None: every finite point is kept)
    notes: tuple[str, ...]


def _bounds_of(src: PointSource, keep: Box | None, fb: Feedback) -> tuple[int, Box, list[np.ndarray]]:
    """One read of the points: how many are finite (and inside ``keep``), their exact bounds,
    and a systematic sample of about SCAN_SAMPLE of them."""
    step = max(1, src.count // SCAN_SAMPLE)
    lo = np.full(3, np.inf)
    hi = np.full(3, -np.inf)
    n = 0
    sample: list[np.ndarray] = []
    for ch in src.chunks():
        fb.check_canceled()
        ch, _ = finite_points(ch, keep)
        if not len(ch.x):
            continue
        n += len(ch.x)
        xyz = (ch.x, ch.y, ch.z)
        lo = np.minimum(lo, [a.min() for a in xyz])
        hi = np.maximum(hi, [a.max() for a in xyz])
        first = (-ch.start) % step
        sample.append(np.c_[ch.x[first::step], ch.y[first::step], ch.z[first::step]])
    return n, (*lo, *hi), sample


def scan_extent(src: PointSource, fb: Feedback) -> _Scan:
    """The extent the grid must cover, read from the points (headers' bounds and counts can lie),
    without the far outliers: a point tens of km off would otherwise make the grid huge
    (or, with the automatic resolution, its cells coarse)."""
    n, bounds, sample = _bounds_of(src, None, fb)
    if n < 3:
        raise InputError(f"{n} point(s) with finite coordinates: too few to make a surface", path=src.path)
    notes: list[str] = []
    if n != src.count:
        notes.append(f"{n:,} of {src.count:,} points have finite coordinates")
    pts = np.concatenate(sample)
    core_lo = np.quantile(pts, CORE_TAIL, axis=0)
    core_hi = np.quantile(pts, 1.0 - CORE_TAIL, axis=0)
    size = core_hi - core_lo
    far_xy = max(float(size[0]), float(size[1]), FAR_XY_M / src.horizontal_m)
    far_z = max(float(size[2]), FAR_Z_M / src.vertical_m)
    keep: Box = (
        core_lo[0] - far_xy,
        core_lo[1] - far_xy,
        core_lo[2] - far_z,
        core_hi[0] + far_xy,
        core_hi[1] + far_xy,
        core_hi[2] + far_z,
    )
    inside = all(keep[i] <= bounds[i] and bounds[i + 3] <= keep[i + 3] for i in range(3))
    if inside:
        return _Scan(_with_bounds(src, bounds), None, tuple(notes))
    n_kept, kept_bounds, _ = _bounds_of(src, keep, fb)
    n_out = n - n_kept
    if n_out > MAX_OUTLIER_SHARE * n:
        # that many points are not strays: keep them all (the memory check speaks if it cannot fit)
        notes.append(f"{n_out:,} points ({100 * n_out / n:.2f} %) lie far outside the bulk of the cloud; kept as data")
        return _Scan(_with_bounds(src, bounds), None, tuple(notes))
    centre = (core_lo + core_hi) / 2
    units = (src.horizontal_m, src.horizontal_m, src.vertical_m)
    reach = max(max(abs(bounds[i] - centre[i]), abs(bounds[i + 3] - centre[i])) * units[i] for i in range(3))
    notes.append(
        f"{n_out:,} far outlier point(s) dropped (up to {reach / 1000:,.1f} km from the rest; "
        f"the other {n_kept:,} span {(kept_bounds[3] - kept_bounds[0]) * src.horizontal_m:,.0f} x "
        f"{(kept_bounds[4] - kept_bounds[1]) * src.horizontal_m:,.0f} m)"
    )
    fb.warning(notes[-1])
    return _Scan(_with_bounds(src, kept_bounds), keep, tuple(notes))


def _with_bounds(src: PointSource, bounds: Box) -> PointSource:
    return replace(src, bounds=bounds, notes=list(src.notes))
