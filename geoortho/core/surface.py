"""Surfaces rays land on: flat ground or a DSM grid; ray–surface intersection."""

from __future__ import annotations

import math
import os
import tempfile
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from affine import Affine
from pyproj import CRS

from geoortho.core.crs import horizontal_of
from geoortho.core.kernels import compiled
from geoortho.errors import InputError

__all__ = ["Surface", "FlatSurface", "GridSurface", "RayHits", "read_surface", "sample_grid"]

_REMAP_COLS = 4096  # cv2.remap wants both map sides below SHRT_MAX


def sample_grid(grid: np.ndarray, cols: np.ndarray, rows: np.ndarray, *, nearest: bool = False) -> np.ndarray:
    """Bilinear samples of a 2-D float32 grid at fractional (col, row) cell-centre coordinates.

    Outside the grid → NaN. Any input shape; cv2.remap does the work.
    """
    shape = np.shape(cols)
    c = np.asarray(cols, dtype=np.float32).ravel()
    r = np.asarray(rows, dtype=np.float32).ravel()
    n = c.size
    if n == 0:
        return np.empty(shape, dtype=np.float32)
    pad = (-n) % _REMAP_COLS if n > _REMAP_COLS else 0
    width = _REMAP_COLS if n > _REMAP_COLS else n
    if pad:
        c = np.concatenate([c, np.full(pad, -1e6, np.float32)])
        r = np.concatenate([r, np.full(pad, -1e6, np.float32)])
    out = cv2.remap(
        grid,
        c.reshape(-1, width),
        r.reshape(-1, width),
        cv2.INTER_NEAREST if nearest else cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=float("nan"),
    )
    return out.ravel()[:n].reshape(shape)


@dataclass(frozen=True, eq=False)
class RayHits:
    """Where rays met the surface. ``hit`` False → ray clipped at max range."""

    points: np.ndarray  # (N, 3)
    hit: np.ndarray  # (N,) bool
    range_m: np.ndarray  # (N,) distance from the origin
    extended: np.ndarray | None = None  # (N,) bool: met the plane beyond the grid, not the grid itself


class Surface:
    """A height field z(x, y) in the world CRS."""

    z_min: float
    z_max: float

    def elevation(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:  # pragma: no cover - abstract
        raise NotImplementedError

    def intersect(
        self, origins: np.ndarray, dirs: np.ndarray, *, max_range_m: float = 1000.0, step_m: float | None = None
    ) -> RayHits:
        """First intersection of each ray with the surface (rays from above it)."""
        raise NotImplementedError


@dataclass(frozen=True, eq=False)
class FlatSurface(Surface):
    """Level ground at one elevation."""

    elevation_m: float

    @property
    def z_min(self) -> float:  # type: ignore[override]
        return self.elevation_m

    @property
    def z_max(self) -> float:  # type: ignore[override]
        return self.elevation_m

    def elevation(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        return np.full(np.broadcast(x, y).shape, self.elevation_m, dtype=float)

    def intersect(
        self, origins: np.ndarray, dirs: np.ndarray, *, max_range_m: float = 1000.0, step_m: float | None = None
    ) -> RayHits:
        o = np.asarray(origins, float).reshape(-1, 3)
        d = np.asarray(dirs, float).reshape(-1, 3)
        o = np.broadcast_to(o, d.shape)
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (self.elevation_m - o[:, 2]) / d[:, 2]
        hit = (d[:, 2] < 0) & (t >= 0) & (t <= max_range_m)
        t = np.where(hit, t, max_range_m)
        return RayHits(o + d * t[:, None], hit, t)


@dataclass(frozen=True, eq=False)
class GridSurface(Surface):
    """A north-up elevation grid (DSM/DTM); NaN where there is no data.

    ``transform`` maps (col, row) of cell corners to world x, y (rasterio's Affine).
    With ``extend``, the ground goes on beyond the grid and through its holes at the
    nearby ground height (:meth:`nearest_elevation`), so that a DSM covering part of a
    flight does not send rays to their range limit.
    """

    grid: np.ndarray
    transform: Affine
    crs: CRS | None = None
    extend: bool = False
    decimated: bool = False  # read coarser than the raster (read_surface's max_cells)
    height_unit: str = "metre"  # what the raster's heights were read as (converted to metres)
    undeclared_fill: tuple[float, int] | None = None  # a fill value read as no data, and its cells

    def __post_init__(self) -> None:
        g = np.ascontiguousarray(self.grid, dtype=np.float32)
        object.__setattr__(self, "grid", g)
        if self.transform.b != 0 or self.transform.d != 0 or self.transform.e >= 0:
            raise ValueError("GridSurface needs a north-up grid")
        # fmin/fmax skip NaN without the copy of the finite cells a mask would make (a DSM's size each)
        z_min = float(np.fmin.reduce(g, axis=None)) if g.size else math.nan
        if math.isnan(z_min):
            raise ValueError("the elevation grid has no data")
        object.__setattr__(self, "_zmin", z_min)
        object.__setattr__(self, "_zmax", float(np.fmax.reduce(g, axis=None)))

    def mapped(self, folder: str | os.PathLike[str]) -> GridSurface:
        """This surface with its grid kept in a file in ``folder`` and mapped into memory.

        Sent to pool or cluster workers it travels as the file's name and its small caches (the
        height range, the ground it is continued by): each worker maps the same pages, which the
        system holds once for all, where each would otherwise unpickle a copy of its own and make
        its ground again from the whole grid. A surface mapped already is returned as it is."""
        if getattr(self, "_file", None) is not None:
            return self
        self.ground_base()
        fd, name = tempfile.mkstemp(prefix="surface_", suffix=".npy", dir=folder)
        with os.fdopen(fd, "wb") as f:
            np.save(f, self.grid)
        return _rebuilt_surface(name, {**self.__dict__, "grid": None})

    def __reduce__(self) -> tuple[Any, ...]:
        state = dict(self.__dict__)
        file = state.pop("_file", None)
        if file is not None:
            state["grid"] = None  # the workers map the file
        return _rebuilt_surface, (file, state)

    @property
    def z_min(self) -> float:  # type: ignore[override]
        return float(self._zmin)  # type: ignore[attr-defined]

    @property
    def z_max(self) -> float:  # type: ignore[override]
        return float(self._zmax)  # type: ignore[attr-defined]

    @property
    def cell_m(self) -> float:
        return float(min(abs(self.transform.a), abs(self.transform.e)))

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        rows, cols = self.grid.shape
        x0, y0 = self.transform.c, self.transform.f
        return x0, y0 + rows * self.transform.e, x0 + cols * self.transform.a, y0

    def colrow(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Fractional (col, row) with integers at cell centres."""
        t = self.transform
        return (np.asarray(x) - t.c) / t.a - 0.5, (np.asarray(y) - t.f) / t.e - 0.5

    def elevation(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        c, r = self.colrow(x, y)
        z = sample_grid(self.grid, c, r).astype(float)
        if self.extend:
            miss = np.isnan(z)
            if miss.any():
                z[miss] = self.nearest_elevation(np.broadcast_to(c, z.shape)[miss], np.broadcast_to(r, z.shape)[miss])
        return z

    def nearest_elevation(self, cols: np.ndarray, rows: np.ndarray) -> np.ndarray:
        """Ground height near fractional (col, row), inside the grid or beyond it.

        Read from a smooth ground-like version of the grid (block minimum to ~1 m, holes filled
        from the nearest data, an opening that removes buildings and trees up to ~15 m across,
        then a mean of the same size), so the plane that continues a DSM past its edge is at the
        ground's height there, not at the roof or tree top that happens to stand on the edge."""
        base, f = self.ground_base()
        nr, nc = self.grid.shape
        ci = np.clip(np.rint(cols), 0, nc - 1).astype(np.intp) // f
        ri = np.clip(np.rint(rows), 0, nr - 1).astype(np.intp) // f
        return np.asarray(base[ri, ci], dtype=float)

    def ground_base(self) -> tuple[np.ndarray, int]:
        """The smooth ground :meth:`nearest_elevation` reads, and its cells' side in grid cells."""
        cached: tuple[np.ndarray, int] | None = getattr(self, "_base", None)
        if cached is not None:
            return cached
        from scipy.ndimage import distance_transform_edt, grey_opening, uniform_filter

        f = max(1, int(round(1.0 / self.cell_m)))
        nr, nc = self.grid.shape
        # the block minimum a band of rows at a time: whole-grid temporaries are a DSM's size each
        band = f * max(1, 4096 // f)
        c = np.empty((-(-nr // f), -(-nc // f)), np.float32)
        for r0 in range(0, nr, band):
            part = self.grid[r0 : r0 + band]
            g = np.pad(
                np.where(np.isnan(part), np.inf, part), ((0, (-len(part)) % f), (0, (-nc) % f)), constant_values=np.inf
            )
            c[r0 // f : r0 // f + g.shape[0] // f] = g.reshape(g.shape[0] // f, f, g.shape[1] // f, f).min(axis=(1, 3))
        missing = ~np.isfinite(c)
        if missing.any():
            idx = distance_transform_edt(missing, return_distances=False, return_indices=True)
            c = c[idx[0], idx[1]]
        k = max(3, int(round(15.0 / (self.cell_m * f))))
        c = uniform_filter(grey_opening(c, size=(k, k)), size=k, mode="nearest")
        out = (c.astype(np.float32), f)
        object.__setattr__(self, "_base", out)
        return out

    def intersect(
        self, origins: np.ndarray, dirs: np.ndarray, *, max_range_m: float = 1000.0, step_m: float | None = None
    ) -> RayHits:
        """March each ray through the height range of the grid, then refine by bisection.

        ``step_m`` (default two cells) bounds how thin a feature can be missed.
        Cells without data let rays pass. Rays that meet nothing within
        ``max_range_m`` end there with ``hit`` False.
        """
        d = np.asarray(dirs, float).reshape(-1, 3)
        o = np.broadcast_to(np.asarray(origins, float).reshape(-1, 3), d.shape)
        n = len(d)
        step = step_m if step_m is not None else 2.0 * self.cell_m
        dz = d[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            t_top = np.where(dz < 0, (self.z_max - o[:, 2]) / dz, np.where(o[:, 2] <= self.z_max, 0.0, np.inf))
            t_bot = np.where(dz < 0, (self.z_min - o[:, 2]) / dz, np.inf)
        t0 = np.clip(t_top, 0.0, None)
        # March a step past the lowest cell: in float32 a ray that ends exactly on the
        # lowest ground could otherwise stop a hair above it and miss.
        t1 = np.minimum(t_bot + step, max_range_m)
        t_end = np.full(n, float(max_range_m))
        hit = np.zeros(n, bool)
        active = np.nonzero(t1 > t0)[0]
        if active.size:
            self._march(o, d, t0, t1, active, step, t_end, hit)
        pts = o + d * t_end[:, None]
        if hit.any():
            # Snap z onto the surface (removes the bisection residue).
            hz = self.elevation(pts[hit, 0], pts[hit, 1])
            pts[hit, 2] = np.where(np.isnan(hz), pts[hit, 2], hz)
        extended = None
        if self.extend:
            extended = ~hit & (dz < 0)
            if extended.any():
                ii = np.nonzero(extended)[0]
                te = self._plane_beyond(o[ii], d[ii])
                ok = (te >= 0) & (te <= max_range_m)
                ii, te = ii[ok], te[ok]
                t_end[ii] = te
                hit[ii] = True
                pts[ii] = o[ii] + d[ii] * te[:, None]
                extended[:] = False
                extended[ii] = True
        return RayHits(pts, hit, t_end, extended)

    def _plane_beyond(self, o: np.ndarray, d: np.ndarray) -> np.ndarray:
        """Range to a level plane at the nearby ground height where the ray lands (a few fixed-point rounds)."""
        z = self.elevation(o[:, 0], o[:, 1])
        t = np.zeros(len(o))
        for _ in range(4):
            t = np.maximum((z - o[:, 2]) / d[:, 2], 0.0)
            z = self.elevation(o[:, 0] + t * d[:, 0], o[:, 1] + t * d[:, 1])
        return np.asarray((z - o[:, 2]) / d[:, 2])

    def _coarse_max(self) -> tuple[np.ndarray, int]:
        """Block maximum of the grid (8×8 cells), dilated by one block; cached."""
        cached: tuple[np.ndarray, int] | None = getattr(self, "_coarse", None)
        if cached is not None:
            return cached
        from scipy.ndimage import maximum_filter

        block = 8
        rows, cols = self.grid.shape
        if min(rows, cols) < 4 * block:
            out: tuple[np.ndarray, int] = (self.grid, 1)
        else:
            pr, pc = (-rows) % block, (-cols) % block
            g = np.pad(np.nan_to_num(self.grid, nan=-np.inf), ((0, pr), (0, pc)), constant_values=-np.inf)
            m = g.reshape(g.shape[0] // block, block, g.shape[1] // block, block).max(axis=(1, 3))
            m = maximum_filter(m, size=3, mode="nearest")
            out = (np.where(np.isinf(m), np.nan, m).astype(np.float32), block)
        object.__setattr__(self, "_coarse", out)
        return out

    def _grid_rays(self, o: np.ndarray, d: np.ndarray, active: np.ndarray) -> _Rays:
        """The ``active`` rays in grid units (column, row, height; their steps a metre), float32."""
        tr = self.transform
        sub_o, sub_d = o[active], d[active]
        return _Rays(
            ((sub_o[:, 0] - tr.c) / tr.a - 0.5).astype(np.float32),
            ((sub_o[:, 1] - tr.f) / tr.e - 0.5).astype(np.float32),
            sub_o[:, 2].astype(np.float32),
            (sub_d[:, 0] / tr.a).astype(np.float32),
            (sub_d[:, 1] / tr.e).astype(np.float32),
            sub_d[:, 2].astype(np.float32),
        )

    def _march(
        self,
        o: np.ndarray,
        d: np.ndarray,
        t0: np.ndarray,
        t1: np.ndarray,
        active: np.ndarray,
        step: float,
        t_end: np.ndarray,
        hit: np.ndarray,
    ) -> None:
        """Fill ``t_end``/``hit`` for the ``active`` rays (those with t0 < t1)."""
        # One piece: the coarse skip, the march and the bisection share a dozen per-ray float32
        # arrays in grid units; split, each step would pass them all (the renderer's hot path).
        # Per-ray state in grid units, float32 and contiguous: each step is then three
        # multiply-adds and one cv2.remap. The rays still marching are kept in packed copies,
        # packed again only when a third of them have finished: a gather of every array at
        # every step cost more than the march's own arithmetic.
        ray = self._grid_rays(o, d, active)
        if active.size >= COMPILED_MIN_RAYS and (kernel := compiled(_march_each)) is not None:
            # a ray at a time: each is sampled only until it lands, where the numpy path below samples
            # every live ray at every step (a photo of 1.7 MP: 1.3 s -> 0.7 s), the same rays bit for bit
            rays = np.ascontiguousarray(np.stack([ray.oc, ray.orr, ray.oz, ray.dc, ray.dr, ray.dz]))
            coarse, block = self._coarse_max()
            out_t, out_hit = np.empty(active.size), np.zeros(active.size, np.bool_)
            kernel(rays, t0[active], t1[active], self.grid, coarse, block, float(step), self.cell_m, out_t, out_hit)
            t_end[active[out_hit]] = out_t[out_hit]
            hit[active] = out_hit
            return
        grid = self.grid

        def f(r: _Rays, t: np.ndarray) -> np.ndarray:
            h = sample_grid(grid, r.oc + t * r.dc, r.orr + t * r.dr)
            return np.asarray(np.where(np.isnan(h), np.float32(1.0), r.oz + t * r.dz - h))  # >0 above

        lo = t0[active].astype(np.float32)
        t_stop = t1[active].astype(np.float32)
        below = f(ray, lo) <= 0  # origin already under the surface
        t_end[active[below]] = lo[below]
        hit[active[below]] = True
        idx = np.nonzero(~below)[0]  # positions into the active arrays
        lo = lo[idx]
        # Coarse pass: skip air in strides of one coarse cell against a dilated
        # block maximum, which bounds the DSM along the whole stride.
        coarse, block = self._coarse_max()
        if block > 1 and idx.size:
            c_step = np.float32(block * self.cell_m)
            skip = np.zeros(idx.size, np.float32)
            pos = np.arange(idx.size)
            cr, clo, cstop, clo0 = ray.take(idx), lo, t_stop[idx], lo
            live = np.ones(idx.size, bool)
            while pos.size:
                t = np.minimum(clo + c_step, cstop)
                hb = sample_grid(
                    coarse,
                    (cr.oc + t * cr.dc) / block - 0.5 + 0.5 / block,
                    (cr.orr + t * cr.dr) / block - 0.5 + 0.5 / block,
                    nearest=True,
                )
                clear = (cr.oz + t * cr.dz > hb) | np.isnan(hb)
                done = live & ~(clear & (t < cstop))
                skip[pos[done]] = np.where(clear[done], t[done], clo[done]) - clo0[done]
                live &= ~done
                clo = t
                if np.count_nonzero(live) < _PACK * pos.size:
                    cr, clo, cstop, clo0, pos = cr.take(live), clo[live], cstop[live], clo0[live], pos[live]
                    live = np.ones(pos.size, bool)
            lo = lo + skip
            keep = lo < t_stop[idx]
            idx, lo = idx[keep], lo[keep]
        span = t_stop[idx] - lo
        n_steps = np.maximum(1, np.ceil(span / step)).astype(np.int32)
        k = 0
        found: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        cr, start = ray.take(idx), lo
        live = np.ones(idx.size, bool)
        while idx.size:
            k += 1
            hi = start + span * np.minimum(np.float32(k) / n_steps, 1)
            crossed = (f(cr, hi) <= 0) & live
            if crossed.any():
                found.append((idx[crossed], lo[crossed], hi[crossed]))
            live &= ~crossed & (k < n_steps)
            lo = hi
            if np.count_nonzero(live) < _PACK * idx.size:
                cr, idx, lo = cr.take(live), idx[live], lo[live]
                start, span, n_steps = start[live], span[live], n_steps[live]
                live = np.ones(idx.size, bool)
        if not found:
            return
        fi = np.concatenate([a for a, _, _ in found])
        a = np.concatenate([b for _, b, _ in found])
        b = np.concatenate([c for _, _, c in found])
        cr = ray.take(fi)
        for _ in range(6):  # bisection to step/64, then one secant step
            m = 0.5 * (a + b)
            above = f(cr, m) > 0
            a = np.where(above, m, a)
            b = np.where(above, b, m)
        fa, fb = f(cr, a), f(cr, b)
        with np.errstate(divide="ignore", invalid="ignore"):
            w = np.where(fa - fb > 0, fa / (fa - fb), 0.5)
        t_end[active[fi]] = a + np.clip(w, 0, 1) * (b - a)
        hit[active[fi]] = True


#: The march packs its rays again when fewer than this share of them are still marching.
_PACK = 0.7

#: Calls with at least this many rays to march take the compiled loop; below, a process that casts
#: only a few rays never loads numba (0.4 s).
COMPILED_MIN_RAYS = 100_000


def _march_each(
    rays: np.ndarray,
    t0: np.ndarray,
    t1: np.ndarray,
    grid: np.ndarray,
    coarse: np.ndarray,
    block: int,
    step: float,
    cell_m: float,
    t_end: np.ndarray,
    hit: np.ndarray,
) -> None:
    """:meth:`GridSurface._march`, one ray at a time (compiled: see :func:`geoortho.core.kernels.compiled`),
    bit for bit: ``rays`` rows (float32, as the numpy path packs them): column, row, height of the
    origin, and their steps per metre of range. The same passes in the same precisions: the origin
    under the surface and the coarse skip in float32; the steps, six bisections and a secant step in
    float64; the grid read as ``sample_grid`` reads it (OpenCV's remap: float32 positions and
    weights, lerps that are fused multiply-adds; nearest rounds half to even)."""
    nr, nc = grid.shape
    nrc, ncc = coarse.shape
    f32 = np.float32
    c_step = f32(block * cell_m)
    half_block = f32(0.5 / block)

    def height(col64: float, row64: float) -> float:
        col, row = f32(col64), f32(row64)
        ic, ir = math.floor(col), math.floor(row)
        if ic < 0 or ic + 1 >= nc or ir < 0 or ir + 1 >= nr:
            return math.nan
        # the weights as float64 differences (exact): written as a float32 difference widened, the
        # compiler narrowed the lerps to float32 products, a rounding off the remap's in 1 ray of 2,000
        wc, wr = float(col) - ic, float(row) - ir
        g00, g01, g10, g11 = grid[ir, ic], grid[ir, ic + 1], grid[ir + 1, ic], grid[ir + 1, ic + 1]
        # each lerp a float32 fused multiply-add (a float32 product is exact in float64)
        top = f32(float(g01 - g00) * wc + float(g00))
        bottom = f32(float(g11 - g10) * wc + float(g10))
        return float(f32(float(bottom - top) * wr + float(top)))

    def above(oc: float, orr: float, oz: float, dc: float, dr: float, dz: float, t: float) -> float:
        # the numpy path's f in float64 (a float32 ray times a float64 range): > 0 above the surface
        h = height(oc + t * dc, orr + t * dr)
        return 1.0 if math.isnan(h) else oz + t * dz - h

    for i in range(rays.shape[1]):
        oc, orr, oz, dc, dr, dz = rays[0, i], rays[1, i], rays[2, i], rays[3, i], rays[4, i], rays[5, i]
        lo, t_stop = f32(t0[i]), f32(t1[i])
        h = height(oc + lo * dc, orr + lo * dr)  # float32 products and sums, as numpy's
        if not math.isnan(h) and float(oz + lo * dz) - h <= 0:
            t_end[i] = lo
            hit[i] = True
            continue
        if block > 1:
            clo = lo
            while True:
                t = min(f32(clo + c_step), t_stop)
                bc = round(float((oc + t * dc) / f32(block) - f32(0.5) + half_block))
                br = round(float((orr + t * dr) / f32(block) - f32(0.5) + half_block))
                hb = coarse[br, bc] if 0 <= bc < ncc and 0 <= br < nrc else math.nan
                clear = math.isnan(hb) or oz + t * dz > hb
                if not (clear and t < t_stop):
                    lo = f32(lo + f32((t if clear else clo) - lo))
                    break
                clo = t
            if not lo < t_stop:
                continue
        start, span = float(lo), float(f32(t_stop - lo))
        n_steps = max(1, int(math.ceil(f32(f32(span) / f32(step)))))
        a = float(lo)
        for k in range(1, n_steps + 1):
            b = start + span * min(float(f32(k)) / n_steps, 1.0)
            if above(oc, orr, oz, dc, dr, dz, b) > 0:
                a = b
                continue
            for _ in range(6):
                m = 0.5 * (a + b)
                if above(oc, orr, oz, dc, dr, dz, m) > 0:
                    a = m
                else:
                    b = m
            fa, fb = above(oc, orr, oz, dc, dr, dz, a), above(oc, orr, oz, dc, dr, dz, b)
            w = fa / (fa - fb) if fa - fb > 0 else 0.5
            t_end[i] = a + min(max(w, 0.0), 1.0) * (b - a)
            hit[i] = True
            break


def warm() -> None:
    """Compile the march into numba's cache (``make`` runs it ahead, so no command pays for it)."""
    kernel = compiled(_march_each)
    if kernel is None:
        return
    grid = np.zeros((8, 8), np.float32)
    rays = np.array([[3.0], [3.0], [10.0], [0.1], [0.1], [-1.0]], np.float32)
    t_end, hit = np.zeros(1), np.zeros(1, np.bool_)
    kernel(rays, np.zeros(1), np.full(1, 20.0), grid, grid, 1, 1.0, 1.0, t_end, hit)


def _rebuilt_surface(file: str | None, state: dict[str, Any]) -> GridSurface:
    """A :class:`GridSurface` from its fields and caches as they were, its grid mapped from ``file``
    when it has one (copy-on-write: a kernel gets a writable array, the file stays as it is)."""
    surface = object.__new__(GridSurface)
    if file is not None:
        state = {**state, "grid": np.asarray(np.load(file, mmap_mode="c")), "_file": file}
    for name, value in state.items():
        object.__setattr__(surface, name, value)
    return surface


@dataclass(frozen=True)
class _Rays:
    """Rays in grid units (column, row, height; their steps per metre of range), float32."""

    oc: np.ndarray
    orr: np.ndarray
    oz: np.ndarray
    dc: np.ndarray
    dr: np.ndarray
    dz: np.ndarray

    def take(self, which: np.ndarray) -> _Rays:
        return _Rays(self.oc[which], self.orr[which], self.oz[which], self.dc[which], self.dr[which], self.dz[which])


def read_surface(
    path: str | os.PathLike[str],
    crs: CRS | None = None,
    *,
    band: int = 1,
    extend: bool = False,
    bounds: tuple[float, float, float, float] | None = None,
    max_cells: int | None = None,
) -> GridSurface:
    """Read a DSM/DTM raster into a north-up :class:`GridSurface`, in ``crs`` if given.

    Heights come back in metres: a raster whose CRS has a vertical axis gives its unit, one whose
    horizontal unit is feet is read as heights in those feet (as US elevation products are), any
    other as metres. A raster in another CRS is warped (bilinear) into ``crs``. An image (RGB,
    RGBA, a palette) is refused: its band 1 is no height. ``bounds`` (xmin, ymin, xmax, ymax in ``crs``): read only the
    window that covers them (a DSM of a whole county for one flight); ``max_cells``: read
    it decimated (nearest) to at most that many cells. Memory then follows the window.

    Raises
    ------
    InputError
        The file cannot be read, has no CRS, or does not reach ``bounds``.
    """
    import rasterio
    from rasterio.enums import Resampling
    from rasterio.errors import RasterioIOError
    from rasterio.vrt import WarpedVRT
    from rasterio.windows import Window, from_bounds

    decimated = False

    def read(ds: Any, masked: bool) -> tuple[np.ndarray, Any]:
        nonlocal decimated
        win = None
        if bounds is not None:
            full = Window(0, 0, ds.width, ds.height)
            try:
                win = from_bounds(*bounds, transform=ds.transform).round_offsets().round_lengths()
                win = win.intersection(full)
            except rasterio.errors.WindowError:
                raise InputError(
                    f"the elevation raster does not reach the area needed ({bounds[0]:.0f}, {bounds[1]:.0f} to "
                    f"{bounds[2]:.0f}, {bounds[3]:.0f} in its CRS): give one that covers it",
                    path=path,
                ) from None
        h, w = (ds.height, ds.width) if win is None else (int(win.height), int(win.width))
        f = math.sqrt(h * w / max_cells) if max_cells and h * w > max_cells else 1.0
        shape = (max(1, int(h / f)), max(1, int(w / f)))
        decimated = shape != (h, w)
        grid = ds.read(band, window=win, out_shape=shape, out_dtype="float32", masked=masked,
                       resampling=Resampling.nearest)  # fmt: skip
        if masked:
            grid = grid.filled(np.nan)
        transform = ds.transform if win is None else ds.window_transform(win)
        return grid, transform @ Affine.scale(w / shape[1], h / shape[0])

    try:
        with rasterio.open(path) as src:
            if src.crs is None:
                raise InputError("the elevation raster has no CRS", path=path)
            refuse_image(src, path)
            src_crs = CRS.from_user_input(src.crs)
            unit_name, to_m = height_unit(src_crs)
            # the map grid alone: a DEM's heights' datum (compound or 3D CRS) is no reason to warp it
            src_crs, crs = horizontal_of(src_crs), (horizontal_of(crs) if crs is not None else None)
            if crs is not None and not src_crs.equals(crs):
                with WarpedVRT(
                    src, crs=crs.to_wkt(), resampling=Resampling.bilinear, src_nodata=src.nodata, nodata=float("nan")
                ) as vrt:
                    grid, transform = read(vrt, False)
                out_crs = crs
            else:
                grid, transform = read(src, True)
                out_crs = src_crs
    except RasterioIOError as e:
        raise InputError(f"cannot read elevation raster: {e}", path=path) from None
    grid, fill = _without_fill(grid)
    if to_m != 1.0:
        grid = grid * np.float32(to_m)
    try:
        return GridSurface(grid, transform, out_crs, extend, decimated, unit_name, fill)
    except ValueError as e:
        raise InputError(str(e), path=path) from None


#: Fill values elevation rasters carry without declaring them as nodata (no height is one).
FILL_VALUES = (-9999.0, -99999.0, -32767.0, -32768.0, -3.4028234663852886e38)


@dataclass(frozen=True)
class Holed:
    """A DSM made whole to cast rays on (:func:`whole_surface`), and what was done to it."""

    surface: GridSurface
    n_interpolated: int  # small nodata gaps inside the data, interpolated
    on_ground: np.ndarray  # bool: wider holes and the grid beyond the data, at the ground near them


def whole_surface(surf: GridSurface, max_gap_m: float = 10.0) -> Holed:
    """``surf`` with no cell empty, for footprints and rays: gaps up to ``max_gap_m`` (at least 4
    cells) interpolated from round them, wider holes and the grid beyond the data at the ground's
    height near them (:meth:`GridSurface.nearest_elevation`): a hole is ground the photos saw.
    The ortho renders on it, and the dem casts the footprints it states areas by on it, so both
    state the same figures."""
    from geoortho.core.gapfill import fill_gaps_by_windows

    grid, n_filled = fill_gaps_by_windows(surf.grid, max_gap_cells=max(4.0, max_gap_m / surf.cell_m))
    rest = ~np.isfinite(grid)
    if rest.any():
        rows, cols = np.nonzero(rest)
        grid = np.array(grid, np.float32, copy=True)
        grid[rows, cols] = surf.nearest_elevation(cols.astype(float), rows.astype(float))
    if n_filled or rest.any():
        surf = GridSurface(grid, surf.transform, surf.crs, extend=True)
    return Holed(surf, n_filled, rest)


def _without_fill(grid: np.ndarray) -> tuple[np.ndarray, tuple[float, int] | None]:
    """The grid with an undeclared fill value (or any height beyond 1e20 m) as NaN, and which."""
    fill = np.isin(grid, np.asarray(FILL_VALUES, np.float32)) | (np.abs(grid) > 1e20)
    if not fill.any():
        return grid, None
    value = float(grid[fill][0])
    return np.where(fill, np.float32(np.nan), grid), (value, int(fill.sum()))


def height_unit(crs: CRS) -> tuple[str, float]:
    """The unit a raster's heights are in, and metres per unit: the vertical axis's when the CRS
    has one, the horizontal unit's when that is feet, else metres."""
    axes = list(crs.axis_info or [])
    vertical = [a for a in axes if a.direction in ("up", "down")]
    unit = vertical[0] if vertical else (axes[0] if axes and crs.is_projected else None)
    factor = float(unit.unit_conversion_factor) if unit is not None and unit.unit_conversion_factor else 1.0
    if unit is None or abs(factor - 1.0) < 1e-9 or not (vertical or abs(factor - 0.3048) < 0.001):
        return "metre", 1.0
    return str(unit.unit_name), factor


def refuse_unless_north_up(transform: Affine, path: Any) -> None:
    """A grid its readers take as rows running south, columns east and cells as wide as they are
    tall: refused otherwise, in one line naming the file."""
    t = transform
    if t.b != 0 or t.d != 0 or t.e >= 0 or not math.isclose(t.a, -t.e, rel_tol=1e-6):
        raise InputError("the DSM is not north up with square cells", path=path)


def refuse_image(ds: Any, path: Any) -> None:
    """An orthophoto or any picture given where heights are wanted: refused, not read as heights."""
    from rasterio.enums import ColorInterp

    colour = {ColorInterp.red, ColorInterp.green, ColorInterp.blue, ColorInterp.alpha, ColorInterp.palette}
    if ds.count >= 3 or any(c in colour for c in ds.colorinterp):
        bands = ", ".join(c.name for c in ds.colorinterp)
        raise InputError(f"an image ({ds.count} bands: {bands}), not an elevation raster: give a DSM", path=path)
    # a product's source codes (dsm_source.tif: 0 no data, 1 measured, ...) are no heights
    described = " ".join(d or "" for d in ds.descriptions).lower()
    if "measured" in described and "interpolated" in described:
        raise InputError("a raster of source codes (measured, interpolated ...), not heights: give the DSM", path=path)
