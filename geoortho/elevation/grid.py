"""The grid a cloud is gridded on, and what gridding a chunk of points needs: one statistic per
cell (max, min, mean, distance-weighted mean, count), the points kept, the nodata value written.

Shared by the whole-grid path (:mod:`geoortho.elevation.gridding`) and the tiled one
(:mod:`geoortho.elevation.tiles`), which both build on it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any, Literal, get_args

import numpy as np

from geoortho.core.kernels import compiled
from geoortho.core.pointcloud import Chunk
from geoortho.errors import ParameterError

__all__ = ["Accumulator", "Box", "GROUND", "Grid", "METHODS", "Method", "NODATA", "finite_points", "grid_points"]

Method = Literal["max", "min", "mean", "idw", "count"]
METHODS: tuple[str, ...] = get_args(Method)
#: The value of a cell with no height, in every raster written.
NODATA = -9999.0
#: ASPRS class of ground points.
GROUND = 2


@dataclass(frozen=True)
class Grid:
    """A north-up grid: top-left corner, cell size and shape, in the cloud's units.

    A window of a larger grid keeps that grid's corner and says where it starts (``row0``,
    ``col0``): its cells are then the larger grid's, computed the same way to the last bit (a
    point on a cell's edge — a millimetre lattice at 5 cm cells — falls in the same cell)."""

    x0: float
    y0: float  # top edge
    cell: float
    rows: int
    cols: int
    row0: int = 0
    col0: int = 0

    @classmethod
    def covering(cls, xmin: float, ymin: float, xmax: float, ymax: float, cell: float) -> Grid:
        x0 = math.floor(xmin / cell) * cell
        y0 = math.ceil(ymax / cell) * cell
        if y0 == ymax:  # a point on the top edge belongs to the row below it
            y0 += cell
        cols = int(math.floor((xmax - x0) / cell)) + 1
        rows = int(math.floor((y0 - ymin) / cell)) + 1
        return cls(x0, y0, cell, rows, cols)

    def window(self, row0: int, col0: int, rows: int, cols: int) -> Grid:
        """The cells ``row0 .. row0 + rows``, ``col0 .. col0 + cols`` of this grid, as a grid."""
        return replace(self, rows=rows, cols=cols, row0=self.row0 + row0, col0=self.col0 + col0)

    def index(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Cell (row, col) of each point; -1 outside."""
        c = np.floor((x - self.x0) / self.cell).astype(np.int64) - self.col0
        r = np.floor((self.y0 - y) / self.cell).astype(np.int64) - self.row0
        out = (c < 0) | (c >= self.cols) | (r < 0) | (r >= self.rows)
        c[out] = -1
        r[out] = -1
        return r, c

    @property
    def left(self) -> float:
        return self.x0 + self.col0 * self.cell

    @property
    def top(self) -> float:
        return self.y0 - self.row0 * self.cell

    @property
    def transform(self) -> Any:
        from rasterio.transform import from_origin

        return from_origin(self.left, self.top, self.cell, self.cell)


class Accumulator:
    """One statistic per cell, fed chunk by chunk."""

    def __init__(self, grid: Grid, method: str):
        if method not in METHODS:
            raise ParameterError("method", f"unknown gridding method {method!r}; use one of {', '.join(METHODS)}")
        self.grid, self.method = grid, method
        n = grid.rows * grid.cols
        if method == "max":
            self.a = np.full(n, -np.inf)
        elif method == "min":
            self.a = np.full(n, np.inf)
        else:
            self.a = np.zeros(n)
        self.w = np.zeros(n) if method in ("mean", "idw") else None
        self.count = np.zeros(n, np.int64) if method == "count" else None

    def add(self, x: np.ndarray, y: np.ndarray, z: np.ndarray) -> None:
        g = self.grid
        r, c = g.index(x, y)
        ok = r >= 0
        r, c, x, y, z = r[ok], c[ok], x[ok], y[ok], z[ok]
        idx = r * g.cols + c
        if self.method == "max":
            np.maximum.at(self.a, idx, z)
        elif self.method == "min":
            np.minimum.at(self.a, idx, z)
        elif self.method == "count":
            assert self.count is not None
            _add_counts(self.count, idx)
        elif self.method == "mean":
            assert self.w is not None
            _add_counts(self.a, idx, z)
            _add_counts(self.w, idx)
        else:  # idw: each point feeds the cells whose centre lies within cell·√2 (PDAL's default radius)
            assert self.w is not None
            kernel = compiled(_idw_sums) if len(idx) >= COMPILED_MIN_POINTS else None
            if kernel is not None:
                kernel(self.a, self.w, x, y, z, r, c, g.x0, g.y0, g.cell, g.row0, g.col0, g.rows, g.cols)
                return
            # the point's place in its cell (cells), and its squared distance to each of the nine
            # centres about it: the sums over each offset cost less than centres in metres did
            fx = (x - g.x0) / g.cell - (c + g.col0) - 0.5
            fy = (g.y0 - y) / g.cell - (r + g.row0) - 0.5
            offsets = [(dr, dc) for dr in (-1, 0, 1) for dc in (-1, 0, 1)]
            uses = []
            for dr, dc in offsets:
                use = (fx - dc) ** 2 + (fy - dr) ** 2 <= 2.0  # within cell·√2
                if dr:
                    use &= (r + dr >= 0) & (r + dr < g.rows)
                if dc:
                    use &= (c + dc >= 0) & (c + dc < g.cols)
                uses.append(use)
            # one sum a chunk over the cells it touches (nine over the whole grid took 10 of the
            # demo's 66 s), into arrays of the exact size: lists of the nine pieces and their
            # concatenation held twice as much, the dem's peak (demo: 300 MB a chunk)
            counts = [int(u.sum()) for u in uses]
            m = sum(counts)
            k, wgt, wz = np.empty(m, np.int64), np.empty(m), np.empty(m)
            floor = 1e-6  # (1e-3 of a cell)², as PDAL's weight keeps a point on a centre finite
            at = 0
            for (dr, dc), use, n in zip(offsets, uses, counts):
                part = slice(at, at + n)
                d2 = (fx[use] - dc) ** 2 + (fy[use] - dr) ** 2
                wgt[part] = 1.0 / (np.maximum(d2, floor) * g.cell * g.cell)
                k[part] = idx[use] + (dr * g.cols + dc)
                np.multiply(wgt[part], z[use], out=wz[part])
                at += n
            del uses
            _add_counts(self.a, k, wz)
            _add_counts(self.w, k, wgt)

    def result(self) -> np.ndarray:
        """The grid (rows, cols), NaN where no point fell."""
        if self.method == "count":
            assert self.count is not None
            out = self.count.astype(np.float64)
            out[self.count == 0] = np.nan
        elif self.method in ("max", "min"):
            out = np.where(np.isfinite(self.a), self.a, np.nan)
        else:
            assert self.w is not None
            with np.errstate(invalid="ignore", divide="ignore"):
                out = np.where(self.w > 0, self.a / self.w, np.nan)
        return out.reshape(self.grid.rows, self.grid.cols)


#: Chunks of at least this many points are gridded by the compiled loop (a point's nine cells in
#: one visit; the numpy path makes nine masks and sums): the demo survey's dem 17 s -> 3 s in its
#: distance-weighted sums (the loop 1.3 s). Fewer stay in numpy: a process that grids little never
#: loads numba.
COMPILED_MIN_POINTS = 100_000


def _idw_sums(
    a: np.ndarray,
    w: np.ndarray,
    x: np.ndarray,
    y: np.ndarray,
    z: np.ndarray,
    r: np.ndarray,
    c: np.ndarray,
    x0: float,
    y0: float,
    cell: float,
    row0: int,
    col0: int,
    rows: int,
    cols: int,
) -> None:
    """The numpy path's weighted sums, point by point, into ``a`` (weight x height) and ``w``
    (weights), with the same arithmetic (compiled: see :func:`geoortho.core.kernels.compiled`)."""
    floor = 1e-6
    for k in range(x.size):
        fx = (x[k] - x0) / cell - (c[k] + col0) - 0.5
        fy = (y0 - y[k]) / cell - (r[k] + row0) - 0.5
        for dr in range(-1, 2):
            rr = r[k] + dr
            if rr < 0 or rr >= rows:
                continue
            for dc in range(-1, 2):
                cc = c[k] + dc
                if cc < 0 or cc >= cols:
                    continue
                d2 = (fx - dc) ** 2 + (fy - dr) ** 2
                if d2 <= 2.0:
                    wgt = 1.0 / (max(d2, floor) * cell * cell)
                    a[rr * cols + cc] += wgt * z[k]
                    w[rr * cols + cc] += wgt


def _add_counts(total: np.ndarray, idx: np.ndarray, weights: np.ndarray | None = None) -> None:
    """``total[idx] += weights`` (1 each when None), summed over the span of cells ``idx`` touches."""
    if not len(idx):
        return
    lo, hi = int(idx.min()), int(idx.max()) + 1
    total[lo:hi] += np.bincount(idx - lo, weights, minlength=hi - lo)


def grid_points(x: np.ndarray, y: np.ndarray, z: np.ndarray, grid: Grid, method: Method = "max") -> np.ndarray:
    """One statistic of the points per cell (NaN where none fell)."""
    acc = Accumulator(grid, method)
    acc.add(np.asarray(x, float), np.asarray(y, float), np.asarray(z, float))
    return acc.result()


Box = tuple[float, float, float, float, float, float]  # xmin ymin zmin xmax ymax zmax


def finite_points(ch: Chunk, keep: Box | None = None) -> tuple[Chunk, np.ndarray]:
    """The chunk's points with finite coordinates (inside ``keep`` when given: the far outliers
    are out), and which of its points those are."""
    ok = np.isfinite(ch.x) & np.isfinite(ch.y) & np.isfinite(ch.z)
    if keep is not None:
        ok &= (ch.x >= keep[0]) & (ch.x <= keep[3]) & (ch.y >= keep[1]) & (ch.y <= keep[4])
        ok &= (ch.z >= keep[2]) & (ch.z <= keep[5])
    if ok.all():
        return ch, ok
    cls = ch.classification[ok] if ch.classification is not None else None
    return Chunk(ch.x[ok], ch.y[ok], ch.z[ok], cls, ch.start), ok


def with_nodata(grid: np.ndarray) -> np.ndarray:
    """NaN cells as NODATA, float32: a raster as written."""
    return np.where(np.isfinite(grid), grid, NODATA).astype(np.float32)


def warm() -> None:
    """Compile the gridding loop into numba's cache (``make`` runs it ahead)."""
    rng = np.random.default_rng(0)
    x, y = rng.uniform(0.0, 10.0, (2, COMPILED_MIN_POINTS))
    grid_points(x, y, np.ones_like(x), Grid.covering(0.0, 0.0, 10.0, 10.0, 0.5), "idw")
