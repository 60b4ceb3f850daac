"""Contour lines of a DTM as a GeoPackage: the DTM's quality made visible (a noisy DTM draws
noisy contours), at an interval chosen from its vertical accuracy or given.

Lines are traced by scikit-image (``measure.find_contours``, marching squares, with the cells
that have no value masked out) on the DTM brought to at most ``MAX_CELLS`` cells (a block mean:
a contour finer than that is noise at a map's scale); every fifth level is an index contour.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from affine import Affine

from geoortho.core.gapfill import block_means
from geoortho.core.outputs import write_vector
from geoortho.core.styles import product_styles

__all__ = ["ContourResult", "contour_interval_m", "write_contours"]

#: The standard steps of a contour interval, metres.
STEPS_M = tuple(m * 10.0**e for e in range(-2, 4) for m in (1.0, 2.0, 2.5, 5.0))
#: NMAS: 90 % of well-defined points within half an interval, RMSEz x 1.6449 x 2 = 3.29 RMSEz.
ACCURACY_TO_INTERVAL = 3.29
#: Never more levels than this over the DTM's relief (a larger step is taken).
MAX_LEVELS = 200
MAX_CELLS = 500_000
INDEX_EVERY = 5


@dataclass(frozen=True)
class ContourResult:
    path: Path
    interval_m: float
    n_lines: int
    why: str  # how the interval was chosen


def contour_interval_m(vertical_rmse_m: float, relief_m: float) -> float:
    """The smallest standard step of at least 3.29 x ``vertical_rmse_m`` that keeps the levels over
    ``relief_m`` under MAX_LEVELS."""
    need = max(ACCURACY_TO_INTERVAL * max(vertical_rmse_m, 0.0), relief_m / MAX_LEVELS, STEPS_M[0])
    return next((s for s in STEPS_M if s >= need - 1e-12), STEPS_M[-1])


def _block_mean(z: np.ndarray, f: int) -> np.ndarray:
    return z if f <= 1 else block_means(z, np.isfinite(z), f)


def write_contours(
    path: Path, z: np.ndarray, transform: Affine, crs: Any, interval_m: float, why: str = ""
) -> ContourResult:
    """Contours of ``z`` (NaN: none; heights in metres) every ``interval_m``, as a GeoPackage layer
    ``contours`` (``elevation_m``, ``index``: every fifth level)."""
    import geopandas as gpd
    import shapely
    from skimage.measure import find_contours

    f = max(1, int(math.ceil(math.sqrt(z.size / MAX_CELLS))))
    zz = _block_mean(np.asarray(z, np.float64), f)
    t = transform @ Affine.scale(f)
    valid = np.isfinite(zz)
    lines: list[Any] = []
    levels: list[float] = []
    if valid.any() and interval_m > 0:
        lo, hi = float(np.nanmin(zz)), float(np.nanmax(zz))
        filled = np.where(valid, zz, lo)
        for k in range(int(math.ceil(lo / interval_m)), int(math.floor(hi / interval_m)) + 1):
            level = k * interval_m
            for rc in find_contours(filled, level, mask=valid):
                if len(rc) < 2:
                    continue
                x = t.c + (rc[:, 1] + 0.5) * t.a
                y = t.f + (rc[:, 0] + 0.5) * t.e
                lines.append(shapely.LineString(np.c_[x, y]))
                levels.append(round(level, 6))
    index = [round(lv / interval_m) % INDEX_EVERY == 0 for lv in levels]
    frame = gpd.GeoDataFrame({"elevation_m": levels, "index": index}, geometry=lines, crs=crs)
    write_vector(path, {"contours": frame}, styles=product_styles("contours"))
    return ContourResult(Path(path), interval_m, len(lines), why)
