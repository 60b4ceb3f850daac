"""The DSM and DTM of a grid too large to hold whole, made tile by tile in bounded memory.

``dem`` holds its grids whole while they are small (a few million cells). Past that, memory
would follow the grid (64 bytes a cell at the peak: 50 M points at 0.5 m took 3.7 GB), so:

1. one pass over the cloud sorts every kept point into the file of its *home tile* (a square
   of TILE cells; x, y, z, its index in the source, its class), on disk beside the output, and
   grids the SMRF minimum surface of the whole cloud (1 m cells: small), from which the
   provisional ground is made once, as when the grid is held whole;
2. each tile is gridded from the points of its home file and its neighbours' within two cells
   (IDW's reach): the DSM, its points' ground flags against that surface, the DTM — unfilled,
   into temporary float64 GeoTIFFs; block means of them make a coarse copy of each grid;
3. each tile's gaps are filled (and it is smoothed) in a window of the unfilled grid with a halo
   of what a cell's value depends on: twice the widest gap filled, and the median's radius;
4. the tile's own cells go into a tiled GeoTIFF, made a COG at the end by GDAL (which streams it).

Where that halo would pass HALO_MAX_CELLS (fine cells and wide gaps: 0.05 m cells and 25 m gaps
make 1,000 cells), it is cut there, so the work stays within (1 + 2 halo / tile)² of the grid's:
the gap mask is then taken with the data going on past the window's inner edges (and kept where
the coarse grid's own gap mask agrees), and a gap crossing such an edge is held there at the
coarse grid's harmonic fill. A gap wider than the halo is thus filled from the coarse fill at its
crossing and from its own rim everywhere else.

Where the SMRF grid itself is too large to hold (SMRF_WHOLE_MAX_CELLS: 8 km² at 1 m), SMRF runs
per tile on the global SMRF grid's cells, from the points within its window's reach around the
tile (objects wider than that may differ at tile borders).

Elsewhere the tiled grids are the whole grid's up to the gap fill's convergence (the small survey
forced into tiles: identical classes, grids within millimetres). Memory follows a tile and its
halo, not the grid.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from geoortho.core.gapfill import block_sums, fill_harmonic, gap_mask
from geoortho.core.outputs import append_by_tile
from geoortho.core.parallel import imap_ordered
from geoortho.elevation.grid import GROUND, NODATA, Accumulator, Grid, finite_points, with_nodata
from geoortho.elevation.ground import SmrfParams, bilinear, ground_mask, smrf_surface
from geoortho.feedback import Feedback, split

__all__ = [
    "HALO_MAX_CELLS",
    "SMRF_WHOLE_MAX_CELLS",
    "TILE_CELLS",
    "WHOLE_GRID_MAX_CELLS",
    "TiledGrids",
    "make_tiled",
]

#: Cells of a tile's side (without its halo).
TILE_CELLS = 1024
#: Grids of more cells than this are made in tiles.
WHOLE_GRID_MAX_CELLS = 8_000_000
#: The widest halo of the gap fill, cells: past it a gap is held at the coarse grid's fill.
HALO_MAX_CELLS = 256
#: The coarse grids (for gaps wider than the halo) have at most this many cells.
COARSE_MAX_CELLS = 4_000_000
#: SMRF grids of more cells than this run per tile.
SMRF_WHOLE_MAX_CELLS = 8_000_000
READ_POINTS = 1_000_000  # points read from a tile file at a time
SLICE_POINTS = 250_000  # points gridded or classified at a time
_POINT = np.dtype([("x", "f8"), ("y", "f8"), ("z", "f8"), ("i", "i8"), ("c", "u1")])


def _smrf_reach_m(params: SmrfParams) -> float:
    """How far (metres) SMRF's surface at a place depends on points: an opening by its window,
    the objects grown by the margin and refilled."""
    return 2.5 * params.window_m + params.margin_m + 2 * params.cell_m


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


@dataclass(frozen=True)
class _Tiling:
    """The grid cut into tiles of ``t`` cells, ``n_tr`` x ``n_tc`` of them."""

    grid: Any
    t: int
    n_tr: int
    n_tc: int

    def window(self, k: int, halo: int = 0) -> tuple[int, int, int, int]:
        """Rows and columns (r0, r1, c0, c1) of tile ``k`` with ``halo`` cells around it, in the grid."""
        tr, tc = divmod(k, self.n_tc)
        g, t = self.grid, self.t
        return (
            max(0, tr * t - halo),
            min(g.rows, (tr + 1) * t + halo),
            max(0, tc * t - halo),
            min(g.cols, (tc + 1) * t + halo),
        )


def _coarse_factor(grid: Any) -> int:
    """Cells of the grid per coarse cell a side: a power of two, the coarse grid within COARSE_MAX_CELLS."""
    f = 1
    while math.ceil(grid.rows / f) * math.ceil(grid.cols / f) > COARSE_MAX_CELLS:
        f *= 2
    return f


def make_tiled(
    src: Any,
    grid: Any,
    method: str,
    ground_method: str | None,
    params: SmrfParams,
    keep: Any,
    want_dtm: bool,
    max_gap_cells: float,
    finish: Callable[..., np.ndarray],
    smooth_px: int,
    work: Path,
    fb: Feedback,
    progress: Feedback,
) -> TiledGrids:
    """Sort the points into tiles, grid each tile, fill each tile's gaps (see the module's doc)."""
    plan = _plan_tiles(src, grid, ground_method, params, max_gap_cells, smooth_px, fb)
    s_sort, s_tiles, s_fill = split(progress, [1, 1, 1])
    files = [work / f"tile_{k}.bin" for k in range(plan.n_tiles)]
    n_used, surface_npy = _sort_into_tiles(src, plan, keep, params, files, work, fb, s_sort)
    layers = ["dsm", "dtm"] if want_dtm else ["dsm"]
    base = _TileJob(
        k=0,
        files=files,
        tiling=plan.tiling,
        points_halo=plan.points_halo,
        method=method,
        ground_method=ground_method,
        smrf_grid=plan.smrf_grid,
        smrf_surface=surface_npy,
        params=params,
        horizontal_m=src.horizontal_m,
        vertical_m=src.vertical_m,
        want_dtm=want_dtm,
    )
    profile = _tile_profile(src, grid)
    raw = {name: work / f"{name}_unfilled.tif" for name in layers}
    ground_flags = np.zeros(src.count, bool) if ground_method is not None else None
    coarse = {name: _CoarseSums(grid, plan.coarse_factor) for name in layers} if plan.coarse_factor else {}
    n_ground = _grid_tiles(base, plan, layers, raw, profile, coarse, ground_flags, s_tiles)
    for file in files:
        file.unlink(missing_ok=True)
    coarse_npy = {name: c.filled(max_gap_cells, work / f"{name}_coarse") for name, c in coarse.items()}
    filled = {name: work / f"{name}.tif" for name in layers}
    fill_jobs = [
        _FillJob(
            k, name, plan.tiling, plan.halo, raw[name], coarse_npy.get(name), plan.coarse_factor, max_gap_cells,
            smooth_px, finish,
        )
        for name in layers
        for k in range(plan.n_tiles)
    ]  # fmt: skip
    _fill_tiles(fill_jobs, plan.tiling, filled, profile, s_fill)
    for path in raw.values():
        path.unlink(missing_ok=True)
    return TiledGrids(filled["dsm"], filled.get("dtm"), ground_flags, n_used, n_ground, plan.n_tiles)


@dataclass(frozen=True)
class _TilePlan:
    """How the grid is cut: tiles, the halos they read, the coarse grid for wide gaps, SMRF's grid."""

    tiling: _Tiling
    points_halo: float  # a tile reads the points this far beyond its edge (the cloud's units)
    halo: int  # cells of gap-fill halo
    coarse_factor: int  # gaps wider than the halo are held at this coarser grid's fill (0: none)
    smrf_grid: Any  # SMRF's grid, or None
    smrf_whole: bool  # SMRF's provisional surface made once over the whole cloud

    @property
    def n_tiles(self) -> int:
        return self.tiling.n_tr * self.tiling.n_tc


def _plan_tiles(
    src: Any, grid: Any, ground_method: str | None, params: SmrfParams, max_gap_cells: float, smooth_px: int,
    fb: Feedback,
) -> _TilePlan:  # fmt: skip
    hm = src.horizontal_m
    smrf_grid, smrf_whole = None, False
    if ground_method == "smrf":
        xmin, ymin, _, xmax, ymax, _ = src.bounds
        smrf_grid = Grid.covering(xmin, ymin, xmax, ymax, params.cell_m / hm)
        smrf_whole = smrf_grid.rows * smrf_grid.cols <= SMRF_WHOLE_MAX_CELLS
    points_halo = 2 * grid.cell  # IDW: a point feeds the cells within cell·√2 of it
    if smrf_grid is not None and not smrf_whole:
        points_halo = max(points_halo, _smrf_reach_m(params) / hm)
    reach = int(math.ceil(2 * max_gap_cells + 2)) + smooth_px if max_gap_cells > 0 else smooth_px
    halo = min(reach, HALO_MAX_CELLS)
    f = _coarse_factor(grid) if reach > halo else 0
    # a tile at least as wide as the points' halo (a tile's points are in its 3 x 3 neighbourhood),
    # a whole number of coarse cells
    t = max(TILE_CELLS, int(math.ceil(points_halo / grid.cell)), 16)
    t = -(-t // f) * f if f else t
    tiling = _Tiling(grid, t, math.ceil(grid.rows / t), math.ceil(grid.cols / t))
    n_tiles = tiling.n_tr * tiling.n_tc
    fb.info(
        f"grid of {grid.cols:,} x {grid.rows:,} cells made in {n_tiles} tiles of {t} cells (gap fill halo {halo} cells"
        + (f"; gaps wider than it held at a {f}x coarser grid's fill" if f else "")
        + (")" if smrf_grid is None or smrf_whole else "; SMRF per tile: its grid is too large to hold whole)")
    )
    return _TilePlan(tiling, points_halo, halo, f, smrf_grid, smrf_whole)


def _sort_into_tiles(
    src: Any, plan: _TilePlan, keep: Any, params: SmrfParams, files: list[Path], work: Path, fb: Feedback,
    progress: Feedback,
) -> tuple[int, Path | None]:  # fmt: skip
    """Every point into its tile's file; the points used, and SMRF's provisional surface of the
    whole cloud (a file, when it is made once) as when the grid is held whole."""
    grid, t, n_tc = plan.tiling.grid, plan.tiling.t, plan.tiling.n_tc
    whole = plan.smrf_grid is not None and plan.smrf_whole
    zmin = Accumulator(plan.smrf_grid, "min") if whole else None
    n_used = n_bad = 0
    for ch in src.chunks(READ_POINTS):
        fb.check_canceled()
        fin, ok = finite_points(ch, keep)
        n_bad += int((~np.isfinite(ch.x) | ~np.isfinite(ch.y) | ~np.isfinite(ch.z)).sum())
        if not len(fin.x):
            continue
        if zmin is not None:
            zmin.add(fin.x, fin.y, fin.z)
        r, c = grid.index(fin.x, fin.y)
        inside = r >= 0
        rec = np.empty(int(inside.sum()), _POINT)
        rec["x"], rec["y"], rec["z"] = fin.x[inside], fin.y[inside], fin.z[inside]
        rec["i"] = (ch.start + np.flatnonzero(ok))[inside]
        rec["c"] = fin.classification[inside] if fin.classification is not None else 0
        n_used += len(rec)
        append_by_tile(rec, (r[inside] // t) * n_tc + (c[inside] // t), lambda k: files[k])
        progress.progress(min(1.0, (ch.start + len(ch.x)) / max(src.count, 1)))
    if n_bad:
        fb.warning(f"{n_bad} points with non-finite coordinates skipped")
    if zmin is None:
        return n_used, None
    surface = smrf_surface(zmin.result(), plan.smrf_grid.cell, params, src.horizontal_m, src.vertical_m)
    del zmin
    surface_npy = work / "smrf_surface.npy"
    np.save(surface_npy, surface)
    return n_used, surface_npy


def _tile_profile(src: Any, grid: Any) -> dict[str, Any]:
    return dict(
        driver="GTiff",
        width=grid.cols,
        height=grid.rows,
        count=1,
        dtype="float32",
        crs=src.crs_with_heights,
        transform=grid.transform,
        nodata=NODATA,
        tiled=True,
        blockxsize=256,
        blockysize=256,
        BIGTIFF="YES",
    )


def _grid_tiles(
    base: _TileJob, plan: _TilePlan, layers: list[str], raw: dict[str, Path], profile: dict[str, Any],
    coarse: dict[str, _CoarseSums], ground_flags: np.ndarray | None, progress: Feedback,
) -> int:  # fmt: skip
    """Each tile gridded (unfilled, float64) into ``raw``; the coarse sums and the ground flags
    gathered on the way. The ground points counted."""
    import rasterio

    n_ground = 0
    raw_profile = {**profile, "dtype": "float64", "nodata": np.nan}
    with rasterio.Env(GDAL_CACHEMAX=64):
        outs = {name: rasterio.open(raw[name], "w", **raw_profile) for name in layers}
        try:
            # one tile at a time here (memory follows one tile); on the Dask cluster when one is given
            jobs = [replace(base, k=k) for k in range(plan.n_tiles)]
            for k, grids, own_i, own_g in imap_ordered(make_tile, jobs, workers=1, feedback=progress):
                r0, r1, c0, c1 = plan.tiling.window(k)
                win = rasterio.windows.Window(c0, r0, c1 - c0, r1 - r0)
                for name, z in zip(layers, grids):
                    outs[name].write(z, 1, window=win)
                    if name in coarse:
                        coarse[name].add(z, r0, c0)
                if ground_flags is not None:
                    ground_flags[own_i] = own_g
                    n_ground += int(own_g.sum())
        finally:
            for o in outs.values():
                o.close()
    return n_ground


def _fill_tiles(
    fill_jobs: list[_FillJob], tiling: _Tiling, filled: dict[str, Path], profile: dict[str, Any], progress: Feedback
) -> None:
    """Each tile's gaps filled (with its halo) into the ``filled`` COG-ready GeoTIFFs."""
    import rasterio

    with rasterio.Env(GDAL_CACHEMAX=64):
        outs = {name: rasterio.open(path, "w", **profile) for name, path in filled.items()}
        try:
            for job, z in zip(fill_jobs, imap_ordered(fill_tile, fill_jobs, workers=1, feedback=progress)):
                r0, r1, c0, c1 = tiling.window(job.k)
                outs[job.layer].write(z, 1, window=rasterio.windows.Window(c0, r0, c1 - c0, r1 - r0))
        finally:
            for o in outs.values():
                o.close()


@dataclass(frozen=True)
class _TileJob:
    """Everything gridding one tile needs (sent to a worker when the tiles run on a cluster)."""

    k: int
    files: list[Path]
    tiling: _Tiling
    points_halo: float  # cloud units
    method: str
    ground_method: str | None
    smrf_grid: Any
    smrf_surface: Path | None  # the whole cloud's SMRF surface (None: SMRF per tile)
    params: SmrfParams
    horizontal_m: float
    vertical_m: float
    want_dtm: bool


def make_tile(job: _TileJob) -> tuple[int, list[np.ndarray], np.ndarray, np.ndarray]:
    """One tile's unfilled DSM (and DTM) cells (NaN: no point) and its own points' ground flags
    (their source indices and flags)."""

    tiling = job.tiling
    grid, t = tiling.grid, tiling.t
    tr, tc = divmod(job.k, tiling.n_tc)
    r0, r1, c0, c1 = tiling.window(job.k)
    # gridded on the tile and a ring of one cell: the points beyond it feed no cell of the tile
    hr0, hr1, hc0, hc1 = tiling.window(job.k, 1)
    sub = grid.window(hr0, hc0, hr1 - hr0, hc1 - hc0)
    ph = job.points_halo
    x0, x1 = grid.x0 + c0 * grid.cell - ph, grid.x0 + c1 * grid.cell + ph
    y1, y0 = grid.y0 - r0 * grid.cell + ph, grid.y0 - r1 * grid.cell - ph
    pts = _neighbourhood(job.files, tr, tc, tiling.n_tr, tiling.n_tc, (x0, y0, x1, y1))
    inner = np.s_[r0 - hr0 : r1 - hr0, c0 - hc0 : c1 - hc0]
    acc = Accumulator(sub, job.method)
    _add(acc, pts)
    grids = [acc.result()[inner]]
    del acc
    if job.ground_method is None:
        return job.k, grids, np.empty(0, np.int64), np.empty(0, bool)
    g = _ground(pts, job)
    home_r, home_c = grid.index(pts["x"], pts["y"])
    own = (home_r // t == tr) & (home_c // t == tc)
    if job.want_dtm:
        acc = Accumulator(sub, "idw")
        _add(acc, pts[g])
        grids.append(acc.result()[inner])
    return job.k, grids, pts["i"][own], g[own]


class _CoarseSums:
    """Block sums of a grid's known cells, ``f`` x ``f`` cells a block, fed tile by tile."""

    def __init__(self, grid: Any, f: int):
        self.f = f
        shape = (math.ceil(grid.rows / f), math.ceil(grid.cols / f))
        self.sums, self.counts = np.zeros(shape), np.zeros(shape)

    def add(self, z: np.ndarray, r0: int, c0: int) -> None:
        f = self.f
        sums, counts = block_sums(z, np.isfinite(z), f)
        at = np.s_[r0 // f : r0 // f + sums.shape[0], c0 // f : c0 // f + sums.shape[1]]
        self.sums[at] += sums
        self.counts[at] += counts

    def filled(self, max_gap_cells: float, stem: Path) -> tuple[Path, Path]:
        """The coarse grid's harmonic gap fill and its gap-closed outline, saved."""

        known = self.counts > 0
        z = np.where(known, self.sums / np.maximum(self.counts, 1), np.nan)
        gap = gap_mask(known, max_gap_cells / self.f)
        values, closed = stem.with_name(stem.name + "_values.npy"), stem.with_name(stem.name + "_closed.npy")
        np.save(values, fill_harmonic(z, known, gap))
        np.save(closed, known | gap)
        return values, closed


@dataclass(frozen=True)
class _FillJob:
    """One tile's gap fill and smoothing, in a window of the unfilled grid."""

    k: int
    layer: str
    tiling: _Tiling
    halo: int
    raw: Path
    coarse: tuple[Path, Path] | None  # the coarse fill and its gap-closed outline (gaps wider than the halo)
    f: int
    max_gap_cells: float
    smooth_px: int
    finish: Callable[..., np.ndarray]


def fill_tile(job: _FillJob) -> np.ndarray:
    """The tile's final cells (float32, nodata as NODATA)."""
    import rasterio

    grid = job.tiling.grid
    r0, r1, c0, c1 = job.tiling.window(job.k)
    hr0, hr1, hc0, hc1 = job.tiling.window(job.k, job.halo)
    with rasterio.open(job.raw) as src:
        z = src.read(1, window=rasterio.windows.Window(hc0, hr0, hc1 - hc0, hr1 - hr0)).astype(np.float64)
    inner = np.s_[r0 - hr0 : r1 - hr0, c0 - hc0 : c1 - hc0]
    if job.coarse is None or job.max_gap_cells <= 0:
        return with_nodata(job.finish(z, job.max_gap_cells, job.smooth_px)[inner])
    # the halo is cut short of the widest gap: past the window's inner edges the data goes on where
    # the coarse grid's gap-closed outline says so
    f = job.f
    rows, cols = np.arange(hr0 - 1, hr1 + 1) // f, np.arange(hc0 - 1, hc1 + 1) // f
    # the coarse grids around the window, a cell of margin for the interpolation
    crop = np.s_[max(0, rows[0] - 1) : rows[-1] + 2, max(0, cols[0] - 1) : cols[-1] + 2]
    cr0, cc0 = crop[0].start, crop[1].start
    values_npy, closed_npy = job.coarse
    closed = np.asarray(np.load(closed_npy, mmap_mode="r")[crop])
    rows, cols = np.clip(rows - cr0, 0, closed.shape[0] - 1), np.clip(cols - cc0, 0, closed.shape[1] - 1)
    ring = closed[np.ix_(rows, cols)]  # the window and one cell around it
    open_edges = (hr0 > 0, hr1 < grid.rows, hc0 > 0, hc1 < grid.cols)
    beyond = (ring[0, 1:-1], ring[-1, 1:-1], ring[1:-1, 0], ring[1:-1, -1])
    gap = gap_mask(np.isfinite(z), job.max_gap_cells, tuple(b if o else None for o, b in zip(open_edges, beyond)))
    gap &= ring[1:-1, 1:-1]
    edge = np.zeros_like(gap)
    edge[0, :], edge[-1, :] = open_edges[0], open_edges[1]
    edge[:, 0] |= open_edges[2]
    edge[:, -1] |= open_edges[3]
    edge &= gap
    if edge.any():
        # a gap crossing the window's edge is held there at the coarse grid's fill
        values = np.asarray(np.load(values_npy, mmap_mode="r")[crop])
        er, ec = np.nonzero(edge)
        z[er, ec] = bilinear(values, (hc0 + ec + 0.5) / f - 0.5 - cc0, (hr0 + er + 0.5) / f - 0.5 - cr0)
    return with_nodata(job.finish(z, job.max_gap_cells, job.smooth_px, gap)[inner])


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


def _ground(pts: np.ndarray, job: _TileJob) -> np.ndarray:
    """Which of the tile's points are ground: the file's class 2, or SMRF's test against the whole
    cloud's surface (or, where that is too large to hold, one made on the global SMRF grid's cells
    that the points cover)."""

    if job.ground_method == "classification":
        return np.asarray(pts["c"] == GROUND)
    if not len(pts):
        return np.zeros(0, bool)
    g = job.smrf_grid
    r, c = g.index(pts["x"], pts["y"])
    if job.smrf_surface is not None:
        # the surface around the points, two cells of margin: its slope there is the whole one's
        r0, c0 = max(0, int(r.min()) - 2), max(0, int(c.min()) - 2)
        r1, c1 = min(g.rows, int(r.max()) + 3), min(g.cols, int(c.max()) + 3)
        win = g.window(r0, c0, r1 - r0, c1 - c0)
        surface = np.asarray(np.load(job.smrf_surface, mmap_mode="r")[r0:r1, c0:c1])
    else:
        r0, c0 = int(r.min()), int(c.min())
        win = g.window(r0, c0, int(r.max()) + 1 - r0, int(c.max()) + 1 - c0)
        zmin = Accumulator(win, "min")
        _add(zmin, pts)
        surface = smrf_surface(zmin.result(), g.cell, job.params, job.horizontal_m, job.vertical_m)
    x0, y0 = win.left, win.top
    out = np.empty(len(pts), bool)
    for i in range(0, len(pts), SLICE_POINTS):  # its temporaries follow the slice, not the tile
        p = pts[i : i + SLICE_POINTS]
        out[i : i + len(p)] = ground_mask(
            p["x"], p["y"], p["z"], surface, x0, y0, g.cell, job.params, job.horizontal_m, job.vertical_m
        )
    return out


def _add(acc: Any, pts: np.ndarray) -> None:
    """Grid points a slice at a time (IDW's temporaries are ~20 arrays as long as its input)."""
    for i in range(0, len(pts), SLICE_POINTS):
        p = pts[i : i + SLICE_POINTS]
        acc.add(p["x"], p["y"], p["z"])
