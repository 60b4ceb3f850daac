"""What ground the photos saw, and a surface carried to the edge of it with its source per cell.

A product is measured against the photos' footprints, not against itself: :func:`seen_count`
counts, per cell of a grid, the registered photos whose frame covers it (their borders cast on a
surface), and :func:`complete_grid` carries a DSM or DTM over every cell that enough photos saw,
saying per cell how its value was obtained (:data:`SOURCE_NAMES`): measured (points in the cell),
interpolated (a harmonic fill from the measured cells and the SfM tie points: no overshoot), or a
fallback plane where nothing was measured at all (a survey of water or snow).
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from affine import Affine

from geoortho.core.gapfill import block_sums, distance_cells, fill_gaps_by_windows, fill_harmonic
from geoortho.core.styles import paletted
from geoortho.photos.footprint import compute_footprints

__all__ = [
    "FALLBACK",
    "INTERPOLATED",
    "MEASURED",
    "SOURCE_NAMES",
    "UNDER_OBJECT",
    "Completed",
    "complete_grid",
    "extended_grid",
    "footprint_polygons",
    "seen_area_m2",
    "source_style",
    "seen_count",
    "source_path",
]

MEASURED, INTERPOLATED, FALLBACK, UNDER_OBJECT = 1, 2, 3, 4
SOURCE_NAMES = {
    0: "none",
    MEASURED: "measured",
    INTERPOLATED: "interpolated",
    FALLBACK: "fallback plane",
    UNDER_OBJECT: "under an object, no ground seen",
}
#: The codes' colours in QGIS (the source rasters' default style).
SOURCE_COLOURS = {MEASURED: "#1a9641", INTERPOLATED: "#fdae61", FALLBACK: "#d7191c", UNDER_OBJECT: "#7b3294"}


def source_style() -> Any:
    """A source raster's QGIS style: its codes paletted, each with its meaning as its legend."""
    return paletted(1, SOURCE_COLOURS, SOURCE_NAMES)


#: The band raster's description, as QGIS shows it (4: the DTM only, under a wide object).
SOURCE_DESCRIPTION = "0 no data, 1 measured, 2 interpolated, 3 fallback plane, 4 under an object, no ground seen"
#: The harmonic fill is solved on a grid of at most this many cells (~120 bytes a cell), then
#: carried to the fine grid; cells near measured data are solved again on the fine grid.
MAX_SOLVE_CELLS = 2_000_000


def source_path(surface_path: str | os.PathLike[str]) -> Path:
    """Where the source raster of a DSM or DTM lies: beside it, ``<name>_source.tif``."""
    p = Path(surface_path)
    return p.with_name(p.stem + "_source.tif")


def footprint_polygons(cams: Sequence[Any], surface: Any, max_range_m: float | None = None) -> list[Any]:
    """Each camera's frame border cast on ``surface`` as a shapely polygon (in the surface's CRS).

    Rays that meet nothing end at ``max_range_m`` (default: 3 x the median camera height over the
    surface), so an oblique photo's polygon stops short of the horizon."""
    import shapely

    if not cams:
        return []
    centres = np.array([c.pose.center for c in cams], float)
    ground = surface.elevation(centres[:, 0], centres[:, 1])
    lowest = np.nanmin(ground) if np.isfinite(ground).any() else 0.0
    heights = centres[:, 2] - np.where(np.isfinite(ground), ground, lowest)
    if max_range_m is None:
        up = heights[heights > 0]
        max_range_m = 3.0 * float(np.median(up)) if len(up) else 1000.0
    table = compute_footprints(cams, surface, max_range_m=max_range_m)
    out = []
    for ring in table.rings:
        poly = shapely.make_valid(shapely.Polygon(ring))
        out.append(poly)
    return out


def seen_area_m2(polygons: Sequence[Any], at_least: int = 2) -> float:
    """The area (square CRS units) of the ground inside ``at_least`` (1 or 2) of the footprints,
    from the polygons themselves: one figure, whatever grid a product is on (the dem and the
    ortho state it, and must state the same)."""
    import shapely

    polys = np.asarray([p for p in polygons if not p.is_empty], dtype=object)
    if not len(polys):
        return 0.0
    if at_least == 1:
        return float(shapely.union_all(polys).area)
    if at_least != 2:
        raise ValueError(f"at_least must be 1 or 2, not {at_least}")
    a, b = shapely.STRtree(polys).query(polys, predicate="intersects")
    pair = a < b
    return float(shapely.union_all(shapely.intersection(polys[a[pair]], polys[b[pair]])).area)


def seen_count(polygons: Sequence[Any], transform: Affine, shape: tuple[int, int]) -> np.ndarray:
    """Photos whose footprint covers each cell's centre (uint16, the grid ``transform`` x ``shape``)."""
    import shapely
    from rasterio.features import MergeAlg, rasterize

    if not len(polygons):
        return np.zeros(shape, np.uint16)
    simple = shapely.simplify(np.asarray(polygons, dtype=object), abs(transform.a) / 2)
    return np.asarray(
        rasterize(
            ((g, 1) for g in simple if not g.is_empty),
            out_shape=shape,
            transform=transform,
            merge_alg=MergeAlg.add,
            dtype="uint16",
            fill=0,
        )
    )


def extended_grid(
    transform: Affine, shape: tuple[int, int], bounds: tuple[float, float, float, float]
) -> tuple[Affine, tuple[int, int], tuple[int, int]]:
    """The grid of ``transform`` x ``shape`` grown (on the same cell lattice) to also cover ``bounds``.

    Returns the new transform, shape and where the old grid's (0, 0) lies in it (row, col)."""
    cell = transform.a
    x0, y1 = transform.c, transform.f
    rows, cols = shape
    left = max(0, int(math.ceil((x0 - bounds[0]) / cell)))
    top = max(0, int(math.ceil((bounds[3] - y1) / cell)))
    right = max(0, int(math.ceil((bounds[2] - (x0 + cols * cell)) / cell)))
    bottom = max(0, int(math.ceil(((y1 - rows * cell) - bounds[1]) / cell)))
    new = Affine(cell, 0.0, x0 - left * cell, 0.0, transform.e, y1 + top * cell)
    return new, (rows + top + bottom, cols + left + right), (top, left)


@dataclass(frozen=True)
class Completed:
    """A grid carried over its target cells, with each cell's source (see :data:`SOURCE_NAMES`)."""

    z: np.ndarray  # float32, NaN where no value
    source: np.ndarray  # uint8
    fallback_plane: tuple[float, float, float] | None  # z = a + b x + c y, when used

    def share(self, code: int, within: np.ndarray | None = None) -> float:
        """The share of the cells (with a value; or of ``within``) whose source is ``code``."""
        cells = self.source > 0 if within is None else within
        n = int(cells.sum())
        return float((self.source[cells] == code).sum()) / n if n else 0.0


def complete_grid(
    z: np.ndarray,
    measured: np.ndarray,
    target: np.ndarray,
    transform: Affine,
    support: np.ndarray | None = None,
    *,
    max_solve_cells: int = MAX_SOLVE_CELLS,
) -> Completed:
    """``z`` carried over every ``target`` cell it has no value in.

    Cells with a value keep it: ``measured`` ones are :data:`MEASURED`, the rest (an earlier gap
    fill) :data:`INTERPOLATED`. Target cells without one are solved from Laplace's equation with
    the valued cells and the ``support`` points (x, y, z: SfM tie points, one median per solve
    cell where no value is) fixed: :data:`INTERPOLATED`. With no value and no support point in the
    grid, they take the least-squares plane through the support points: :data:`FALLBACK`; with no
    support point at all, they stay empty.
    """
    z = np.asarray(z, np.float32)
    known = np.isfinite(z)
    source = np.where(known, np.where(measured, MEASURED, INTERPOLATED), 0).astype(np.uint8)
    need = np.asarray(target, bool) & ~known
    out = z.copy()
    if not need.any():
        return Completed(out, source, None)
    h, w = z.shape
    f = max(1, int(math.ceil(math.sqrt(h * w / max_solve_cells))))
    hp, wp = -(-h // f) * f, -(-w // f) * f
    csum, ccount = block_sums(z, known, f)
    ck = ccount > 0
    cz = np.where(ck, csum / np.maximum(ccount, 1), np.nan)
    pts = _support_cells(support, transform, f, cz.shape, ck)
    if pts is not None:
        r, c, v = pts
        cz[r, c] = v
        ck[r, c] = True
    plane = None
    if not ck.any():
        plane = _plane(support)
        if plane is None:
            return Completed(out, source, None)
        rows, cols = np.nonzero(need)
        x = transform.c + (cols + 0.5) * transform.a  # north-up grids: no rotation terms
        y = transform.f + (rows + 0.5) * transform.e
        out[rows, cols] = plane[0] + plane[1] * x + plane[2] * y
        source[rows, cols] = FALLBACK
        return Completed(out, source, plane)
    coarse = fill_harmonic(cz, ck)
    if f == 1:
        out[need] = coarse[need]
        source[need] = INTERPOLATED
        return Completed(out, source, None)
    import cv2

    # the coarse answer at the fine cells' centres (block centres at (f - 1) / 2)
    up = cv2.resize(coarse.astype(np.float32), (wp, hp), interpolation=cv2.INTER_LINEAR)[:h, :w]

    near = distance_cells(~known) <= 2 * f + 1
    far = need & ~near
    work = out.copy()
    work[far] = up[far]
    # the band between the data and the coarse answer: enclosed by both, solved on the fine grid
    filled, _ = fill_gaps_by_windows(work, max_gap_cells=2 * f + 2)
    band = need & near
    got = np.where(np.isfinite(filled), filled, up)
    out[need] = np.where(band, got, up)[need]
    source[need] = INTERPOLATED
    return Completed(out, source, None)


def _support_cells(
    support: np.ndarray | None, transform: Affine, f: int, shape: tuple[int, int], known: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """The median support height of each solve cell that has no value (row, col, z)."""
    s = _finite_rows(support)
    if s is None:
        return None
    lo, hi = np.percentile(s[:, 2], [0.5, 99.5])  # a tie point far above or below all is a mismatch
    s = s[(s[:, 2] >= lo) & (s[:, 2] <= hi)]
    col = np.floor((s[:, 0] - transform.c) / transform.a / f).astype(np.int64)
    row = np.floor((s[:, 1] - transform.f) / transform.e / f).astype(np.int64)
    ok = (row >= 0) & (row < shape[0]) & (col >= 0) & (col < shape[1])
    row, col, zz = row[ok], col[ok], s[ok, 2]
    free = ~known[row, col]
    row, col, zz = row[free], col[free], zz[free]
    if not len(zz):
        return None
    key = row * shape[1] + col
    order = np.lexsort((zz, key))
    key, zz = key[order], zz[order]
    starts = np.flatnonzero(np.r_[True, key[1:] != key[:-1]])
    ends = np.r_[starts[1:], len(key)]
    med = zz[(starts + ends - 1) // 2]
    k = key[starts]
    return k // shape[1], k % shape[1], med


def _finite_rows(support: np.ndarray | None) -> np.ndarray | None:
    """The support points (x, y, z) with every coordinate finite; None when there are none."""
    if support is None or not len(support):
        return None
    s = np.asarray(support, float)
    s = s[np.isfinite(s).all(axis=1)]
    return s if len(s) else None


def _plane(support: np.ndarray | None) -> tuple[float, float, float] | None:
    """A least-squares plane through the support points (level at their median when fewer than 3)."""
    s = _finite_rows(support)
    if s is None:
        return None
    if len(s) < 3:
        return float(np.median(s[:, 2])), 0.0, 0.0
    mx, my = s[:, 0].mean(), s[:, 1].mean()
    a = np.c_[np.ones(len(s)), s[:, 0] - mx, s[:, 1] - my]
    coef, *_ = np.linalg.lstsq(a, s[:, 2], rcond=None)
    return float(coef[0] - coef[1] * mx - coef[2] * my), float(coef[1]), float(coef[2])
