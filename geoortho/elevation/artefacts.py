"""What a surveyor sees in a DTM's hillshade, as numbers the quality check can grade.

* :func:`roughness_m`: the surface less its own 1 m median, RMS, on open ground. Bare ground is
  smooth at that scale (a synthetic survey's true ground: 0.03 cm); a photogrammetric DTM's
  speckle shows here first.
* :func:`footprint_step_m`: the step a surface makes where a photo's footprint ends. A depth map
  that sits a few centimetres off its neighbours leaves a patch with straight edges, one per
  photo: the step across each edge, less what the slope there explains, averaged along the edge
  (noise averages out along it, a patch's step does not), then the RMS over the edges.

Both take the cells to measure on (``open_ground``): the caller's judgement of where the ground
shows (no object, measured).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np
from affine import Affine
from scipy import ndimage

from geoortho.elevation.ground import bilinear

__all__ = ["footprint_step_m", "roughness_m"]

#: Cells the roughness is measured on (evenly spread over the open ground).
SAMPLES = 40_000
#: Samples an edge needs for its mean step to count (noise / sqrt(20) is a fifth of a sample's).
MIN_EDGE_SAMPLES = 20


def roughness_m(
    z: np.ndarray, open_ground: np.ndarray, cell_m: float, window_m: float = 1.0, max_samples: int = SAMPLES
) -> float:
    """RMS of ``z`` less its median over ``window_m`` (odd cells, at least 3) on ``open_ground``
    (at most ``max_samples`` cells, evenly spread: a median filter over a whole 6 M-cell DTM took
    30 s); NaN with fewer than 50 cells."""
    size = max(3, int(round(window_m / cell_m)) | 1)
    half = size // 2
    valid = np.isfinite(z)
    # only cells whose whole window has values: a window reaching past the surface's edge measures
    # what the edge was filled with
    whole = ndimage.minimum_filter(valid.astype(np.uint8), size=size, mode="constant", cval=0) > 0
    rows, cols = np.nonzero(np.asarray(open_ground, bool) & whole)
    if len(rows) < 50:
        return math.nan
    step = max(1, len(rows) // max_samples)
    rows, cols = rows[::step], cols[::step]
    padded = np.pad(np.where(valid, z, 0.0), half)
    view = np.lib.stride_tricks.sliding_window_view(padded, (size, size))
    # the windows are copied out a few thousand at a time: all 40,000 at once at a 5 cm cell were
    # 140 MB, the dem's peak
    med = np.concatenate(
        [np.median(view[rows[i : i + 4096], cols[i : i + 4096]], axis=(1, 2)) for i in range(0, len(rows), 4096)]
    )
    return float(np.sqrt(np.mean((z[rows, cols] - med) ** 2)))


def footprint_step_m(
    z: np.ndarray, transform: Affine, polygons: Sequence[Any], open_ground: np.ndarray
) -> tuple[float, int]:
    """The RMS over footprint edges of each edge's mean step (metres), and the edges measured."""
    cell = transform.a
    inv = ~transform
    ok_grid = np.asarray(open_ground, bool) & np.isfinite(z)
    zz = np.where(np.isfinite(z), z, 0.0)
    steps: list[float] = []
    for poly in polygons:
        for ring in _rings(poly):
            xy = np.asarray(ring.coords, float)
            for (x0, y0), (x1, y1) in zip(xy[:-1], xy[1:]):
                step = _edge_step(zz, ok_grid, inv, cell, x0, y0, x1, y1)
                if step is not None:
                    steps.append(step)
    if not steps:
        return math.nan, 0
    return float(np.sqrt(np.mean(np.square(steps)))), len(steps)


def _rings(poly: Any) -> list[Any]:
    geoms = getattr(poly, "geoms", [poly])
    return [g.exterior for g in geoms if getattr(g, "exterior", None) is not None and not g.is_empty]


def _edge_step(
    z: np.ndarray, ok: np.ndarray, inv: Affine, cell: float, x0: float, y0: float, x1: float, y1: float
) -> float | None:
    length = math.hypot(x1 - x0, y1 - y0)
    n_samples = int(length / cell)
    if n_samples < MIN_EDGE_SAMPLES:
        return None
    # the edge's middle 80 %: a corner's two edges meet there
    t = np.linspace(0.1, 0.9, n_samples)
    px, py = x0 + t * (x1 - x0), y0 + t * (y1 - y0)
    nx, ny = -(y1 - y0) / length, (x1 - x0) / length
    vals = []
    good = np.ones(n_samples, bool)
    for d in (-4.5, -1.5, 1.5, 4.5):
        sx, sy = px + d * cell * nx, py + d * cell * ny
        col, row = inv * (sx, sy)  # type: ignore[operator]
        col, row = np.asarray(col) - 0.5, np.asarray(row) - 0.5
        inside = (col >= 0) & (row >= 0) & (col <= z.shape[1] - 1) & (row <= z.shape[0] - 1)
        # every cell the bilinear sample weighs: one beyond the surface's edge (its nodata read as 0)
        # made a 3.5 m step of a clean edge of the small survey, the quality check's red
        c0 = np.clip(np.floor(col).astype(np.int64), 0, z.shape[1] - 1)
        r0 = np.clip(np.floor(row).astype(np.int64), 0, z.shape[0] - 1)
        c1, r1 = np.minimum(c0 + 1, z.shape[1] - 1), np.minimum(r0 + 1, z.shape[0] - 1)
        good &= inside & ok[r0, c0] & ok[r0, c1] & ok[r1, c0] & ok[r1, c1]
        vals.append(bilinear(z, col, row))
    if int(good.sum()) < MIN_EDGE_SAMPLES:
        return None
    far_minus, near_minus, near_plus, far_plus = vals
    # a slope gives near = far / 3; a step of height s gives near = far = s: 1.5 x (near - far / 3) = s
    step = 1.5 * ((near_plus - near_minus) - (far_plus - far_minus) / 3.0)
    return float(np.mean(step[good]))
