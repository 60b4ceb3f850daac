"""The DSM and DTM of a grid too large to hold whole, made tile by tile in bounded memory.

``dem`` holds its grids whole while they are small (a few million cells). Past that, memory
would follow the grid (64 bytes a cell at the peak: 50 M points at 0.5 m took 3.7 GB), so:

1. one pass over the cloud sorts every kept point into the file of its *home tile* (a square
   of TILE cells; x, y, z, its index in the source, its class), on disk beside the output;
2. each tile is then made on its own, from the points of its home file and of its eight
   neighbours' that fall within a halo around it: the DSM (and the ground filter's minimum
   grid, on the global SMRF grid's cells), SMRF, the ground points, the DTM, the gap fill —
   the same functions as the whole grid, on the tile plus its halo;
3. the tile's own cells are written into a tiled GeoTIFF, made a COG at the end by GDAL
   (which streams it).

The halo covers what a cell's value depends on: the widest gap filled (``max_gap_m``), the SMRF
window (an object's opening and refill reach about twice it) and a cell for IDW. Where a gap or
an object is wider than that, a tile border may show. Elsewhere the tiled grids are the whole
grid's up to the gap fill's convergence (the small survey forced into tiles: identical; 50 M
points: DSM identical, DTM within 1 mm). Memory then follows the tile and its halo, not the grid.
"""

from __future__ import annotations

import math
import tempfile
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from .feedback import Feedback, split
from .ground import SmrfParams, ground_mask, smrf_surface
from .parallel import imap_ordered

__all__ = [
    "TILE_CELLS",
    "WHOLE_GRID_MAX_CELLS",
    "TiledGrids",
    "append_by_tile",
    "make_tiled",
    "tile_halo_m",
    "work_folder",
]

#: Cells of a tile's side (without its halo): with the halo of a 25 m gap at 0.1 m cells, 4 M cells.
TILE_CELLS = 1024
#: Grids of more cells than this are made in tiles.
WHOLE_GRID_MAX_CELLS = 8_000_000
READ_POINTS = 1_000_000  # points read from a tile file at a time
SLICE_POINTS = 250_000  # points gridded or classified at a time
_POINT = np.dtype([("x", "f8"), ("y", "f8"), ("z", "f8"), ("i", "i8"), ("c", "u1")])


def tile_halo_m(max_gap_m: float, params: SmrfParams | None, cell_m: float) -> tuple[float, float]:
    """How far (metres) around a tile its cells' values can depend on points: through the gap fill
    (a closing by the widest gap looks twice its radius out) and through SMRF (an opening by its
    window, the objects grown by the margin and refilled)."""
    smrf = 2.5 * params.window_m + params.margin_m + 2 * params.cell_m if params is not None else 0.0
    return 2 * max_gap_m + 2 * cell_m, smrf


@dataclass(frozen=True)
class TiledGrids:
    """What the tiled run hands back to ``dem``: the grids written (temporary GeoTIFFs), the
    ground flags of every source point (for the classified cloud), and the counts."""

    dsm_tif: Path
    dtm_tif: Path | None
    ground: np.ndarray | None  # bool per source point (None: no ground asked)
    n_used: int
    n_ground: int
    n_tiles: int


def make_tiled(
    src: Any,
    grid: Any,
    resolution_m: float,
    method: str,
    ground_method: str | None,
    params: SmrfParams,
    keep: Any,
    want_dtm: bool,
    max_gap_cells: float,
    finish: Callable[[np.ndarray, float, int], np.ndarray],
    smooth_px: int,
    work: Path,
    fb: Feedback,
    progress: Feedback,
) -> TiledGrids:
    """Sort the points into tiles, then make and write each tile (see the module's doc)."""
    import rasterio

    from .elevation import NODATA, Grid, _finite

    smrf = params if ground_method == "smrf" else None
    gap_halo_m, smrf_halo_m = tile_halo_m(max_gap_cells * resolution_m, smrf, resolution_m)
    hm = src.horizontal_m
    halo_cells = int(math.ceil(gap_halo_m / resolution_m))
    points_halo = max(gap_halo_m, smrf_halo_m) / hm  # cloud units
    # a tile at least as wide as the halo: a tile's points are in its 3 x 3 neighbourhood
    t = max(TILE_CELLS, int(math.ceil(points_halo / grid.cell)), halo_cells, 16)
    n_tr, n_tc = math.ceil(grid.rows / t), math.ceil(grid.cols / t)
    n_tiles = n_tr * n_tc
    fb.info(
        f"grid of {grid.cols:,} x {grid.rows:,} cells made in {n_tiles} tiles of {t} cells "
        f"(halo {halo_cells} cells; points within {points_halo * hm:.0f} m)"
    )
    # Cells made, halos included, against the grid's: the halo is metres (gap fill, SMRF), the
    # tile cells, so fine cells and a wide gap fill make every tile mostly halo (0.07 m cells,
    # 25 m gaps: 12x the grid's work, 1,450 s for 25 M points where 5.5 M cells whole took 21 s).
    overhead = sum(
        (min(grid.rows, (tr + 1) * t + halo_cells) - max(0, tr * t - halo_cells))
        * (min(grid.cols, (tc + 1) * t + halo_cells) - max(0, tc * t - halo_cells))
        for tr in range(n_tr)
        for tc in range(n_tc)
    ) / max(1, grid.rows * grid.cols)
    if overhead > 3.0:
        fb.warning(
            f"the tiles' halos make {overhead:.0f}x the grid's cells to compute (halo {halo_cells} cells around "
            f"tiles of {t}): slow; a coarser --resolution-m or a smaller --max-gap-m cuts it"
        )
    s_sort, s_tiles = split(progress, [1, 1])
    files = [work / f"tile_{k}.bin" for k in range(n_tiles)]
    n_used = 0
    n_bad = 0
    for ch in src.chunks(READ_POINTS):
        fb.check_canceled()
        fin, ok = _finite(ch, keep)
        n_bad += int((~np.isfinite(ch.x) | ~np.isfinite(ch.y) | ~np.isfinite(ch.z)).sum())
        if not len(fin.x):
            continue
        r, c = grid.index(fin.x, fin.y)
        inside = r >= 0
        rec = np.empty(int(inside.sum()), _POINT)
        rec["x"], rec["y"], rec["z"] = fin.x[inside], fin.y[inside], fin.z[inside]
        rec["i"] = (ch.start + np.flatnonzero(ok))[inside]
        rec["c"] = fin.classification[inside] if fin.classification is not None else 0
        n_used += len(rec)
        append_by_tile(rec, (r[inside] // t) * n_tc + (c[inside] // t), lambda k: files[k])
        s_sort.progress(min(1.0, (ch.start + len(ch.x)) / max(src.count, 1)))
    if n_bad:
        fb.warning(f"{n_bad} points with non-finite coordinates skipped")
    ground_flags = np.zeros(src.count, bool) if ground_method is not None else None
    smrf_grid = None
    if ground_method == "smrf":
        xmin, ymin, _, xmax, ymax, _ = src.bounds
        smrf_grid = Grid.covering(xmin, ymin, xmax, ymax, params.cell_m / hm)
    profile = dict(
        driver="GTiff",
        width=grid.cols,
        height=grid.rows,
        count=1,
        dtype="float32",
        crs=src.crs,
        transform=grid.transform,
        nodata=NODATA,
        tiled=True,
        blockxsize=256,
        blockysize=256,
        BIGTIFF="YES",
    )
    dsm_tif, dtm_tif = work / "dsm.tif", (work / "dtm.tif" if want_dtm else None)
    n_ground = 0
    base = _TileJob(
        k=0,
        files=files,
        grid=grid,
        t=t,
        n_tr=n_tr,
        n_tc=n_tc,
        halo_cells=halo_cells,
        points_halo=points_halo,
        method=method,
        ground_method=ground_method,
        smrf_grid=smrf_grid,
        params=params,
        horizontal_m=src.horizontal_m,
        vertical_m=src.vertical_m,
        want_dtm=want_dtm,
        max_gap_cells=max_gap_cells,
        finish=finish,
        smooth_px=smooth_px,
    )
    jobs = [replace(base, k=k) for k in range(n_tiles)]
    with rasterio.Env(GDAL_CACHEMAX=64), rasterio.open(dsm_tif, "w", **profile) as dsm_out:
        dtm_out = rasterio.open(dtm_tif, "w", **profile) if dtm_tif is not None else None
        try:
            # one tile at a time here (memory follows one tile); on the Dask cluster when one is given
            for _k, win, dsm_z, dtm_z, own_i, own_g in imap_ordered(make_tile, jobs, workers=1, feedback=s_tiles):
                dsm_out.write(dsm_z, 1, window=win)
                if dtm_out is not None and dtm_z is not None:
                    dtm_out.write(dtm_z, 1, window=win)
                if ground_flags is not None:
                    ground_flags[own_i] = own_g
                    n_ground += int(own_g.sum())
        finally:
            if dtm_out is not None:
                dtm_out.close()
    for f in files:
        f.unlink(missing_ok=True)
    return TiledGrids(dsm_tif, dtm_tif, ground_flags, n_used, n_ground, n_tiles)


@dataclass(frozen=True)
class _TileJob:
    """Everything one tile needs (sent to a worker when the tiles run on a cluster)."""

    k: int
    files: list[Path]
    grid: Any
    t: int  # tile side, cells
    n_tr: int
    n_tc: int
    halo_cells: int
    points_halo: float  # cloud units
    method: str
    ground_method: str | None
    smrf_grid: Any
    params: SmrfParams
    horizontal_m: float
    vertical_m: float
    want_dtm: bool
    max_gap_cells: float
    finish: Callable[[np.ndarray, float, int], np.ndarray]
    smooth_px: int


def make_tile(job: _TileJob) -> tuple[int, Any, np.ndarray, np.ndarray | None, np.ndarray, np.ndarray]:
    """One tile: its DSM (and DTM) cells, and its own points' ground flags (source indices)."""
    import rasterio

    from .elevation import Grid, _Accumulator, _nodata

    grid, t, halo = job.grid, job.t, job.halo_cells
    tr, tc = divmod(job.k, job.n_tc)
    r0, c0 = tr * t, tc * t
    r1, c1 = min(grid.rows, r0 + t), min(grid.cols, c0 + t)
    # the tile with its halo, as a grid of its own on the same cells
    hr0, hc0 = max(0, r0 - halo), max(0, c0 - halo)
    hr1, hc1 = min(grid.rows, r1 + halo), min(grid.cols, c1 + halo)
    sub = Grid(grid.x0 + hc0 * grid.cell, grid.y0 - hr0 * grid.cell, grid.cell, hr1 - hr0, hc1 - hc0)
    ph = job.points_halo
    x0, x1 = grid.x0 + c0 * grid.cell - ph, grid.x0 + c1 * grid.cell + ph
    y1, y0 = grid.y0 - r0 * grid.cell + ph, grid.y0 - r1 * grid.cell - ph
    pts = _neighbourhood(job.files, tr, tc, job.n_tr, job.n_tc, (x0, y0, x1, y1))
    inner = np.s_[r0 - hr0 : r1 - hr0, c0 - hc0 : c1 - hc0]
    win = rasterio.windows.Window(c0, r0, c1 - c0, r1 - r0)
    acc = _Accumulator(sub, job.method)
    _add(acc, pts)
    dsm_z = _nodata(job.finish(acc.result(), job.max_gap_cells, job.smooth_px)[inner])
    del acc
    if job.ground_method is None:
        return job.k, win, dsm_z, None, np.empty(0, np.int64), np.empty(0, bool)
    g = _ground(pts, job.ground_method, job.smrf_grid, job.params, job.horizontal_m, job.vertical_m)
    home_r, home_c = grid.index(pts["x"], pts["y"])
    own = (home_r // t == tr) & (home_c // t == tc)
    dtm_z = None
    if job.want_dtm:
        acc = _Accumulator(sub, "idw")
        _add(acc, pts[g])
        dtm_z = _nodata(job.finish(acc.result(), job.max_gap_cells, job.smooth_px)[inner])
    return job.k, win, dsm_z, dtm_z, pts["i"][own], g[own]


def _neighbourhood(
    files: list[Path], tr: int, tc: int, n_tr: int, n_tc: int, box: tuple[float, float, float, float]
) -> np.ndarray:
    """The points of a tile's home file and its eight neighbours' inside ``box`` (x0, y0, x1, y1),
    read a slice at a time: only the points kept stay in memory."""
    x0, y0, x1, y1 = box
    parts = []
    for r in range(max(0, tr - 1), min(n_tr, tr + 2)):
        for c in range(max(0, tc - 1), min(n_tc, tc + 2)):
            f = files[r * n_tc + c]
            n = f.stat().st_size // _POINT.itemsize if f.exists() else 0
            for start in range(0, n, READ_POINTS):
                m = np.fromfile(f, _POINT, count=min(READ_POINTS, n - start), offset=start * _POINT.itemsize)
                parts.append(m[(m["x"] >= x0) & (m["x"] < x1) & (m["y"] > y0) & (m["y"] <= y1)])
    return np.concatenate(parts) if parts else np.empty(0, _POINT)


def _ground(
    pts: np.ndarray, ground_method: str, smrf_grid: Any, params: SmrfParams, horizontal_m: float, vertical_m: float
) -> np.ndarray:
    """Which of the tile's points are ground: the file's class 2, or SMRF on the global SMRF grid's
    cells that the points cover."""
    from .elevation import GROUND, Grid, _Accumulator

    if ground_method == "classification":
        return np.asarray(pts["c"] == GROUND)
    if not len(pts):
        return np.zeros(0, bool)
    r, c = smrf_grid.index(pts["x"], pts["y"])
    r0, r1, c0, c1 = int(r.min()), int(r.max()) + 1, int(c.min()), int(c.max()) + 1
    g = smrf_grid
    sub = Grid(g.x0 + c0 * g.cell, g.y0 - r0 * g.cell, g.cell, r1 - r0, c1 - c0)
    zmin = _Accumulator(sub, "min")
    _add(zmin, pts)
    surface = smrf_surface(zmin.result(), g.cell, params, horizontal_m, vertical_m)
    out = np.empty(len(pts), bool)
    for i in range(0, len(pts), SLICE_POINTS):  # its temporaries follow the slice, not the tile
        p = pts[i : i + SLICE_POINTS]
        out[i : i + len(p)] = ground_mask(
            p["x"], p["y"], p["z"], surface, sub.x0, sub.y0, g.cell, params, horizontal_m, vertical_m
        )
    return out


def _add(acc: Any, pts: np.ndarray) -> None:
    """Grid points a slice at a time (IDW's temporaries are ~20 arrays as long as its input)."""
    for i in range(0, len(pts), SLICE_POINTS):
        p = pts[i : i + SLICE_POINTS]
        acc.add(p["x"], p["y"], p["z"])


def append_by_tile(rows: np.ndarray, tile: np.ndarray, file_of: Callable[[int], Path]) -> None:
    """Append each row to the file of its tile (``tile``: an integer per row), one write a tile."""
    order = np.argsort(tile, kind="stable")
    tile, rows = tile[order], rows[order]
    cuts = np.flatnonzero(np.diff(tile)) + 1
    for part, k in zip(np.split(rows, cuts), tile[np.r_[0, cuts]] if len(tile) else []):
        with open(file_of(int(k)), "ab") as fh:
            part.tofile(fh)


def work_folder(near: Path) -> tempfile.TemporaryDirectory[str]:
    """A temporary folder for the tile files beside the output (the same disk as the products),
    named as every geoortho temporary is, so that a killed run's is removed by the next run."""
    from .outputs import temp_prefix

    return tempfile.TemporaryDirectory(prefix=temp_prefix(Path(near).name), dir=Path(near).absolute().parent)
