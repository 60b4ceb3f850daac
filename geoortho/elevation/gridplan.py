"""What a DEM is made with, decided before any point is gridded: the options checked, the cell, the
whole grid or tiles (by the memory there is), and the ground filter's window for the survey's size.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Literal, get_args

from geoortho.core.pointcloud import PointSource
from geoortho.elevation import tiles as dem_tiles
from geoortho.elevation.extent import auto_resolution_m
from geoortho.elevation.grid import (
    METHODS,
    Grid,
)
from geoortho.elevation.ground import SmrfParams
from geoortho.errors import InputError, ParameterError
from geoortho.feedback import Feedback

GroundMethod = Literal["smrf", "csf", "classification"]
Engine = Literal["native", "pdal"]
GROUND_METHODS: tuple[str, ...] = get_args(GroundMethod)
#: the DSM statistics, and auto: chosen from what the cloud is
DemMethod = Literal["auto", "max", "min", "mean", "idw", "count"]
ENGINES: tuple[str, ...] = get_args(Engine)


def check_options(
    method: str, ground_method: str, resolution_m: float | None, max_gap_m: float, smooth_px: int, engine: str
) -> None:
    if method not in METHODS:
        raise ParameterError("method", f"unknown method {method!r}; use one of {', '.join(METHODS)}")
    if ground_method not in GROUND_METHODS:
        raise ParameterError(
            "ground_method", f"unknown ground method {ground_method!r}; use one of {', '.join(GROUND_METHODS)}"
        )
    # each negative value is named for itself: the parameter the user must change
    for name, value in (("resolution_m", resolution_m or 0.0), ("max_gap_m", max_gap_m), ("smooth_px", smooth_px)):
        if value < 0:
            raise ParameterError(name, f"{name} must not be negative (given {value})")
    if engine not in ENGINES:
        raise ParameterError("engine", f"unknown engine {engine!r}; use one of {', '.join(ENGINES)}")


def check_source(src: PointSource, classified: Path | None, ground_method: str) -> None:
    if src.count == 0:
        raise InputError("the point cloud is empty", path=src.path)
    if classified is not None and (src.path is None or src.path.suffix.lower() not in (".las", ".laz")):
        raise ParameterError("classified", "a classified cloud can be written for LAS/LAZ input only")
    if ground_method == "classification" and not src.has_classification:
        raise InputError("the points have no classification; use ground_method smrf or csf", path=src.path)


#: Bytes per grid cell at the peak of a DSM + DTM run (accumulators, gap fill, ground filter, the
#: written products), rounded up from the measured peak of the 10 M-point benchmark.
BYTES_PER_CELL = 64


def _check_memory(grid: Grid, res_m: float, src: PointSource, width_m: float, height_m: float) -> None:
    """Refuse, before allocating, a grid that cannot fit in half the memory available, saying which
    resolution fits (and, when the cloud is far wider than its points fill, that an outlier is likely)."""
    import psutil

    cells = float(grid.cols) * float(grid.rows)
    budget = 0.5 * psutil.virtual_memory().available
    need = cells * BYTES_PER_CELL
    if need <= budget:
        return
    fits = res_m * math.sqrt(need / budget)
    fits = float(f"{fits:.2g}") if fits < 10 else math.ceil(fits)
    hint = ""
    if src.count / max(width_m * height_m, 1e-9) < 0.01:  # under one point per 100 m²
        hint = "; the points are very sparse over that extent: a far outlier point in the file?"
    raise InputError(
        f"a {res_m:g} m grid over {width_m:,.0f} x {height_m:,.0f} m is {grid.cols:,} x {grid.rows:,} cells "
        f"(~{need / 1e9:.1f} GB), more than this machine has free ({budget / 1e9:.1f} GB for it): "
        f"give --resolution-m {fits:g} or coarser{hint}",
        path=src.path,
    )


#: Finer grids than this many cells per point are interpolation, not measurement.
MAX_CELLS_PER_POINT = 100


@dataclass(frozen=True)
class GridPlan:
    grid: Grid
    resolution_m: float  # cell size on the ground, metres
    cell: float  # the same in the cloud's horizontal units


def whole_grid_max_cells() -> int:
    return dem_tiles.WHOLE_GRID_MAX_CELLS  # read when called: a test (or a user) may lower it


def plan_grid(src: PointSource, resolution_m: float | None, fb: Feedback, tiles_allowed: bool = True) -> GridPlan:
    res_m = resolution_m or auto_resolution_m(src)
    cell = res_m / src.horizontal_m
    xmin, ymin, _, xmax, ymax, _ = src.bounds
    if not all(map(math.isfinite, src.bounds)):
        raise InputError("no point has finite coordinates", path=src.path)
    if xmax - xmin < 2 * cell or ymax - ymin < 2 * cell:
        # a surface needs an area: a line of points (or a header X/Y scale of 0) has none
        raise InputError(
            f"the points span {xmax - xmin:.3g} x {ymax - ymin:.3g} {src.horizontal_unit}: a line or a spot, "
            "not an area (a header scale of 0? the wrong file?)",
            path=src.path,
        )
    grid = Grid.covering(xmin, ymin, xmax, ymax, cell)
    width_m, height_m = (xmax - xmin) * src.horizontal_m, (ymax - ymin) * src.horizontal_m
    cells = float(grid.rows) * float(grid.cols)
    if cells > MAX_CELLS_PER_POINT * src.count:
        # nearly every cell would be interpolated: minutes of gap filling for no detail
        spacing_m = math.sqrt(width_m * height_m / src.count)
        raise ParameterError(
            "resolution_m",
            f"{res_m:g} m makes {cells:,.0f} cells for {src.count:,} points (one point per "
            f"{cells / src.count:,.0f} cells; the points are ~{spacing_m:.2g} m apart): "
            f"give {1.05 * spacing_m / math.sqrt(MAX_CELLS_PER_POINT):.2g} m or coarser",
        )
    if not tiles_allowed or cells <= whole_grid_max_cells():  # larger grids are made in tiles
        _check_memory(grid, res_m, src, width_m, height_m)
    fb.info(
        f"grid {grid.cols} x {grid.rows} cells of {res_m:g} m ({cell:g} {src.horizontal_unit})"
        + ("" if resolution_m else ", from the point density")
    )
    return GridPlan(grid, res_m, cell)


#: Seconds per cell and per squared opening radius of OpenCV's float32 opening with a disc
#: (measured: radius 80 on 1 M cells, 1.8 s); the SMRF estimate sums it over every step.
OPEN_S_PER_CELL_R2 = 3e-10
#: The longest SMRF run allowed, estimated before it starts.
MAX_SMRF_S = 600.0


#: The automatic SMRF window: at least SmrfParams' published 18 m, at most this (a wood or a hall
#: 100 m wide), at most half the survey, and what AUTO_SMRF_S of openings allow.
AUTO_WINDOW_MIN_M = 18.0
AUTO_WINDOW_MAX_M = 50.0
AUTO_SMRF_S = 20.0


def _auto_window_m(width_m: float, height_m: float, cell_m: float) -> float:
    """The SMRF window that follows the largest object the survey can hold: a wood 40 m wide is
    canopy called ground under the published 18 m window (a real survey: the DTM 6-8 m up)."""
    cells = (width_m / cell_m + 1) * (height_m / cell_m + 1)
    budget_m = cell_m * (3.0 * AUTO_SMRF_S / (OPEN_S_PER_CELL_R2 * cells)) ** (1.0 / 3.0)
    result: float = max(AUTO_WINDOW_MIN_M, min(AUTO_WINDOW_MAX_M, 0.5 * max(width_m, height_m), budget_m))
    return result


def check_smrf(src: PointSource, params: SmrfParams, fb: Feedback) -> SmrfParams:
    """SMRF parameters that can finish: a window wider than the cloud is cut to its size (an
    opening that wide removes nothing more), and a cell whose estimated run passes MAX_SMRF_S
    is refused with the finest cell that fits."""

    xmin, ymin, _, xmax, ymax, _ = src.bounds
    width_m, height_m = (xmax - xmin) * src.horizontal_m, (ymax - ymin) * src.horizontal_m
    if params.cell_m <= 0 or params.window_m < 0:
        raise ParameterError("smrf_cell_m", "the SMRF cell must be positive and the window not negative")
    if params.window_m == 0:
        params = replace(params, window_m=_auto_window_m(width_m, height_m, params.cell_m))
        fb.info(
            f"SMRF window {params.window_m:.0f} m: objects up to ~{2 * params.window_m:.0f} m wide are taken out "
            "(the survey's half-width, within a time budget)"
        )
    widest = max(width_m, height_m, params.cell_m)
    if params.window_m > widest:
        fb.info(f"SMRF window {params.window_m:g} m is wider than the cloud: {widest:.0f} m used")
        params = replace(params, window_m=widest)

    def seconds(cell_m: float) -> float:
        cells = (width_m / cell_m + 1) * (height_m / cell_m + 1)
        steps = max(1.0, math.ceil(params.window_m / cell_m))
        return OPEN_S_PER_CELL_R2 * cells * steps**3 / 3.0

    est = seconds(params.cell_m)
    if est > MAX_SMRF_S:
        fits = params.cell_m * (est / MAX_SMRF_S) ** 0.2  # cells ~ 1/c², steps³ ~ 1/c³
        raise ParameterError(
            "smrf_cell_m",
            f"{params.cell_m:g} m cells with a {params.window_m:g} m window over {width_m:,.0f} x {height_m:,.0f} m "
            f"would take ~{est / 3600:,.1f} h: give {float(f'{fits:.2g}'):g} m or coarser (or a smaller smrf_window_m)",
        )
    return params
