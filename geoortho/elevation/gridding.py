"""DSM and DTM from a point cloud: grid, classify ground, fill gaps, write COGs.

Two passes over the points in chunks (memory follows the grid, not the
cloud): the first grids the DSM and the minimum surface the ground filter
needs; the second classifies each point against the provisional ground and
grids the ground points into the DTM (and writes the classified cloud when
asked). Gaps are filled harmonically (:mod:`geoortho.core.gapfill`) — no ringing —
up to ``max_gap_m`` from data on both sides; beyond that cells stay nodata.

Grids stay in the cloud's CRS and units (feet stay feet, and the result says
so); every distance parameter is in metres and converted. Beside it: :mod:`.extent` (where the points
are), :mod:`.gridplan` (the options, the cell, whole grid or tiles), :mod:`.products` (the result and
what is written beside the rasters), :mod:`.ground_filters` and :mod:`.completion` (the cells the
photos saw and the cloud left empty).
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
from pyproj import CRS

from geoortho.core.copc import is_copc_path, write_copc
from geoortho.core.crs import crs_to_text, heights_to_text, horizontal_of
from geoortho.core.gapfill import fill_harmonic, gap_mask
from geoortho.core.outputs import atomic_path, atomic_paths, work_folder, write_cog
from geoortho.core.pointcloud import CHUNK_POINTS, PointSource, open_points, reprojected
from geoortho.elevation.completion import complete_to_photos
from geoortho.elevation.extent import scan_extent
from geoortho.elevation.grid import (
    GROUND,
    METHODS,
    NODATA,
    Accumulator,
    Box,
    Grid,
    finite_points,
    grid_points,
    with_nodata,
)
from geoortho.elevation.gridplan import (
    GROUND_METHODS,
    DemMethod,
    Engine,
    GridPlan,
    GroundMethod,
    check_options,
    check_smrf,
    check_source,
    plan_grid,
    whole_grid_max_cells,
)
from geoortho.elevation.ground import SmrfParams
from geoortho.elevation.ground_filters import GROUND_FILTERS, GroundFilter
from geoortho.elevation.products import (
    DemResult,
    cog_of,
    hillshade_of,
    json_or_empty,
    vertical_unit_tag,
    with_contours,
    with_styles,
    write_hillshade,
)
from geoortho.elevation.tiles import make_tiled
from geoortho.errors import DependencyError, InputError, ParameterError
from geoortho.feedback import Feedback, as_feedback, split

__all__ = ["DemResult", "dem", "grid_points", "Grid", "METHODS", "NODATA"]


def dem(
    points: Path,
    output: Path,
    dtm: Path | None = None,
    resolution_m: float | None = None,
    method: DemMethod = "auto",
    ground_method: GroundMethod = "smrf",
    crs: CRS | None = None,
    max_gap_m: float = 25.0,
    smooth_px: int = 0,
    classified: Path | None = None,
    hillshade: Path | None = None,
    smrf_cell_m: float = SmrfParams.cell_m,
    smrf_slope: float = SmrfParams.slope,
    smrf_window_m: float = SmrfParams.window_m,
    smrf_threshold_m: float = SmrfParams.threshold_m,
    smrf_scalar: float = SmrfParams.scalar,
    smrf_margin_m: float = SmrfParams.margin_m,
    engine: Engine = "native",
    points_crs: CRS | None = None,
    sfm: Path | None = None,
    contours: Path | None = None,
    contour_interval_m: float = 0.0,
    *,
    feedback: Feedback | None = None,
) -> DemResult:
    """Make a DSM (and a DTM) from a point cloud as Cloud-Optimized GeoTIFFs.

    Reads LAS/LAZ/PLY in chunks, grids the DSM, classifies ground with SMRF
    (or CSF, or the file's class 2), grids the DTM from ground points, and
    fills gaps harmonically (no ringing) up to ``max_gap_m`` from data.
    Values stay in the cloud's units (feet stay feet; the result says which).

    Parameters
    ----------
    points : Path
        LAS/LAZ (CRS from the header) or PLY point cloud.
    output : Path
        DSM GeoTIFF to write.
    dtm : Path
        Also write a DTM (ground only) here.
    resolution_m : float
        Cell size in metres on the ground (in a CRS in feet, converted: the result's
        ``resolution`` states it in feet); default (or 0): from the point density, about
        two points per cell.
    method : str
        DSM statistic per cell: max, min, mean, idw or count; auto (default): idw for a cloud
        made from photos (``sfm`` given, or the dense report beside the points), max otherwise.
    ground_method : str
        Ground points for the DTM: smrf (filter), csf (cloth simulation) or classification (the file's class 2).
    crs : CRS
        Output CRS (projected): the points are reprojected into it (x, y; heights unchanged)
        before gridding. Default: the points' CRS. For points without a CRS (PLY, arrays),
        it is also taken as theirs.
    max_gap_m : float
        Fill gaps up to this far from data (on both sides); farther cells stay nodata.
    smooth_px : int
        Median filter radius in cells after filling (0 = none).
    classified : Path
        Also write the cloud with ground as class 2 (LAS/LAZ input only); a name ending in .copc.laz
        writes it as COPC, which QGIS opens as a layer.
    hillshade : Path
        Also write a hillshade PNG preview (of the DTM when made, else the DSM).
    smrf_cell_m : float
        SMRF grid cell, metres.
    smrf_slope : float
        SMRF slope threshold (rise over run).
    smrf_window_m : float
        SMRF largest opening window, metres (the widest object it removes is about twice this);
        0 (default): half the survey's width, at least 18 m (PDAL's) and at most 50 m, within a
        time budget.
    smrf_threshold_m : float
        SMRF elevation threshold, metres.
    smrf_scalar : float
        SMRF elevation scalar (threshold grows by scalar × local slope).
    smrf_margin_m : float
        Objects found by SMRF are grown by this before the ground is refilled (0 = as published).
    engine : str
        native, or pdal (PDAL's pipeline, when the pdal module is installed).
    points_crs : CRS
        CRS of the points, when the file has none or states a wrong one (overrides it).
    sfm : Path
        Output folder of the sfm run the photos' cloud came from: the DSM and DTM are then
        carried over all the ground at least two registered photos saw (their frames cast on
        the surface), interpolated from the measured cells and the SfM tie points across holes
        (water, canopy, cars) and out to that edge, a plane only where nothing was measured;
        ``<name>_source.tif`` beside each says per cell which (1 measured, 2 interpolated,
        3 fallback plane, 4 under an object with no ground seen: the DTM only). The DTM is made
        bare earth: objects found on the DSM whatever their size, their rims taken in, stray
        ground dropped, filled smoothly, its speckle smoothed where the ground is smooth.
    contours : Path
        Also write the DTM's contour lines here (GeoPackage; needs ``dtm``).
    contour_interval_m : float
        Their interval, metres; 0 (default): from the DTM's vertical accuracy (3.29 x its RMSE,
        as NMAS asks: the SfM's checkpoints' when given, and the ground's own noise), a standard
        step of 1, 2, 2.5 or 5.
    """
    fb = as_feedback(feedback)
    chosen, why_method = _auto_method(method, points, sfm)
    check_options(chosen, ground_method, resolution_m, max_gap_m, smooth_px, engine)
    if contours is not None and dtm is None:  # refused before any work
        raise ParameterError("contours", "contours are drawn from the DTM: give --dtm too")
    src = _open_source(points, points_crs, crs, engine, classified, ground_method, why_method, fb)
    want_ground = dtm is not None or classified is not None
    s_scan, s_pass1, s_pass2, s_write = split(fb, [1, 4, 4 if want_ground else 0, 2])
    scan = scan_extent(src, s_scan)
    src = scan.src
    src.notes.extend(scan.notes)
    tiles_allowed = not (want_ground and ground_method == "csf")  # CSF needs every point at once
    plan = plan_grid(src, resolution_m, fb, tiles_allowed=tiles_allowed)
    params = SmrfParams(smrf_cell_m, smrf_slope, smrf_window_m, smrf_threshold_m, smrf_scalar, smrf_margin_m)
    if want_ground and ground_method == "smrf":
        params = check_smrf(src, params, fb)
    if engine == "pdal":
        return with_styles(_run_pdal(src, plan.grid, output, dtm, chosen, ground_method, max_gap_m, params, fb))

    if tiles_allowed and float(plan.grid.rows) * plan.grid.cols > whole_grid_max_cells():
        tiled = _dem_tiled(
            src, plan, chosen, ground_method, params, scan.keep, output, dtm, classified, hillshade,
            max_gap_m, smooth_px, s_pass1, s_write, fb,
        )  # fmt: skip
        tiled = tiled if sfm is None else complete_to_photos(tiled, src, scan.keep, Path(sfm), fb)
        return with_styles(with_contours(tiled, contours, contour_interval_m, sfm, fb))
    ground = GROUND_FILTERS[ground_method](src, params) if want_ground else None
    dtm_acc = Accumulator(plan.grid, "idw") if dtm is not None else None
    first = _first_pass(src, plan.grid, chosen, ground, dtm_acc, scan.keep, s_pass1, fb)
    n_ground = first.n_ground
    if ground is not None:
        ground.prepare()
    if classified is not None or (ground is not None and not ground.known_in_first_pass):
        n_ground += _second_pass(src, ground, dtm_acc, classified, scan.keep, s_pass2, fb)
    # the products appear together or not at all: a SIGTERM while they are written leaves none
    with atomic_paths(output, dtm, hillshade, commit_check=fb.check_canceled) as (t_dsm, t_dtm, t_shade):
        assert t_dsm is not None
        result = _write_products(
            src, plan, chosen, first, dtm_acc, t_dsm, t_dtm, t_shade, max_gap_m, smooth_px, classified, n_ground
        )
    result = replace(
        result,
        dsm=Path(output),
        dtm=None if dtm is None else Path(dtm),
        hillshade=None if hillshade is None else Path(hillshade),
    )
    if dtm is not None:
        fb.info(f"ground: {n_ground} of {first.n_used} points ({ground_method})")
    # the accumulators and the ground filter are written out: freed before the photos' grids are
    # made (demo: 200 MB, the dem's peak)
    del first, dtm_acc, ground
    if sfm is not None:
        result = complete_to_photos(result, src, scan.keep, Path(sfm), fb)
    result = with_styles(with_contours(result, contours, contour_interval_m, sfm, fb))
    s_write.progress(1.0)
    return result


def _open_source(
    points: Any, points_crs: CRS | None, crs: CRS | None, engine: str, classified: Path | None,
    ground_method: str, why_method: str, fb: Feedback,
) -> PointSource:  # fmt: skip
    """The points as gridding reads them: reprojected into ``crs`` when it is another, checked,
    and what was assumed said."""
    src = open_points(points, points_crs, default_crs=crs)
    if why_method:
        src.notes.append(why_method)
    if crs is not None and horizontal_of(crs) != src.crs:
        if engine == "pdal":
            raise ParameterError("engine", "reprojection (--crs) runs on the native engine only")
        src = reprojected(src, crs)
        if classified is not None:
            src.notes.append(f"the classified cloud keeps the points' CRS ({src.file_crs.name})")
    check_source(src, classified, ground_method)
    for n in src.notes:
        fb.info(n)
    return src


def _auto_method(method: str, points: Any, sfm: Path | None) -> tuple[str, str]:
    """The DSM statistic ``auto`` stands for, and the note that says why ("" when chosen).

    A cloud from the photos is one noisy surface: a cell's highest point stood 4 cm (1.1 GSD)
    above the true ground on the free-heading survey, the distance-weighted mean 1.3 cm (RMSE
    8.5 -> 4.1 cm, roofs 3.7 -> 2.0 cm). A lidar cloud keeps its first returns (max)."""
    if method != "auto":
        return method, ""
    from_dense = False
    if isinstance(points, (str, os.PathLike)):  # dense writes its report beside its cloud
        from_dense = "depth_maps" in json_or_empty(Path(points).with_name(Path(points).stem + "_report.json"))
    if sfm is not None or from_dense:
        return "idw", "method auto: idw (a cloud from photos: a cell's highest point would stand above the surface)"
    return "max", "method auto: max (a lidar or other cloud: each cell's first return)"


def _dem_tiled(
    src: PointSource,
    plan: GridPlan,
    method: str,
    ground_method: str,
    params: SmrfParams,
    keep: Box | None,
    output: Path,
    dtm: Path | None,
    classified: Path | None,
    hillshade: Path | None,
    max_gap_m: float,
    smooth_px: int,
    progress: Feedback,
    s_write: Feedback,
    fb: Feedback,
) -> DemResult:
    """:func:`dem` for a grid too large to hold whole: tile by tile (:mod:`geoortho.elevation.tiles`)."""

    grid = plan.grid
    want_ground = dtm is not None or classified is not None
    max_gap_cells = min(max_gap_m / plan.resolution_m, math.hypot(grid.rows, grid.cols))
    unit_tag = vertical_unit_tag(src.vertical_unit) if method != "count" else ""
    with work_folder(Path(output)) as work:
        tiles = make_tiled(
            src, grid, method, ground_method if want_ground else None, params, keep,
            dtm is not None, max_gap_cells, _finish, smooth_px, Path(work), fb, progress,
        )  # fmt: skip
        with atomic_paths(output, dtm, hillshade, commit_check=fb.check_canceled) as (t_dsm, t_dtm, t_shade):
            assert t_dsm is not None
            cog_of(tiles.dsm_tif, t_dsm, "dsm", unit_tag)
            if t_dtm is not None and tiles.dtm_tif is not None:
                cog_of(tiles.dtm_tif, t_dtm, "dtm", vertical_unit_tag(src.vertical_unit))
            if t_shade is not None:
                hillshade_of(tiles.dtm_tif or tiles.dsm_tif, t_shade, src.vertical_m / src.horizontal_m)
    if classified is not None:
        assert tiles.ground is not None
        writer = _ClassifiedWriter(src, classified)
        try:
            for i in range(0, src.count, CHUNK_POINTS):
                fb.check_canceled()
                writer.write(tiles.ground[i : i + CHUNK_POINTS])
            writer.close()
        finally:
            writer.abort()
    if dtm is not None:
        fb.info(f"ground: {tiles.n_ground} of {tiles.n_used} points ({ground_method})")
    s_write.progress(1.0)
    notes = [
        *src.notes,
        f"values in {src.vertical_unit}" if method != "count" else "values: points per cell",
        f"made in {tiles.n_tiles} tiles (the grid is too large to hold whole)",
    ]
    return DemResult(
        Path(output),
        None if dtm is None else Path(dtm),
        None if classified is None else Path(classified),
        None if hillshade is None else Path(hillshade),
        plan.cell,
        crs_to_text(src.crs),
        src.describe_units(),
        tiles.n_used,
        tiles.n_ground,
        tuple(notes),
        vertical_crs=heights_to_text(src.heights),
    )


assert set(GROUND_FILTERS) == set(GROUND_METHODS)


@dataclass(frozen=True)
class _FirstPass:
    dsm: Accumulator
    n_used: int
    n_ground: int  # counted here only when the ground is known in pass 1


def _first_pass(
    src: PointSource,
    grid: Grid,
    method: str,
    ground: GroundFilter | None,
    dtm_acc: Accumulator | None,
    keep: Box | None,
    progress: Feedback,
    fb: Feedback,
) -> _FirstPass:
    """Grid the DSM; let the ground filter see the points (or grid the ground it already knows)."""
    dsm_acc = Accumulator(grid, method)
    n_bad, first_bad, n_used, n_ground = 0, -1, 0, 0
    for ch in src.chunks():
        fb.check_canceled()
        ch, ok = finite_points(ch)
        if not ok.all():
            first_bad = first_bad if n_bad else ch.start + int(np.argmin(ok))
            n_bad += int((~ok).sum())
        if keep is not None:
            ch, _ = finite_points(ch, keep)
        n_used += len(ch.x)
        dsm_acc.add(ch.x, ch.y, ch.z)
        if ground is not None:
            ground.observe(ch)
            if ground.known_in_first_pass:
                g = ground.ground(ch)
                n_ground += int(g.sum())
                if dtm_acc is not None:
                    dtm_acc.add(ch.x[g], ch.y[g], ch.z[g])
        progress.progress(min(1.0, (ch.start + CHUNK_POINTS) / src.count))
    if n_bad:
        fb.warning(f"{n_bad} points with non-finite coordinates skipped (first at index {first_bad})")
    if n_used < 3:
        raise InputError(f"{n_used} point(s) with finite coordinates: too few to make a surface", path=src.path)
    return _FirstPass(dsm_acc, n_used, n_ground)


def _second_pass(
    src: PointSource,
    ground: GroundFilter | None,
    dtm_acc: Accumulator | None,
    classified: Path | None,
    keep: Box | None,
    progress: Feedback,
    fb: Feedback,
) -> int:
    """Classify every point against the prepared ground, grid the DTM, write the classified cloud.

    Returns the ground points counted here (those of pass 1 are not counted again)."""
    count_here = ground is not None and not ground.known_in_first_pass
    writer = _ClassifiedWriter(src, classified) if classified is not None else None
    n_ground = 0
    try:
        for ch in src.chunks():
            fb.check_canceled()
            fin, used = finite_points(ch, keep)
            g = np.zeros(len(ch.x), bool)
            if ground is not None:
                g[used] = ground.ground(fin)
            if count_here:
                n_ground += int(g.sum())
                if dtm_acc is not None:
                    dtm_acc.add(ch.x[g], ch.y[g], ch.z[g])
            if writer is not None:
                writer.write(g)
            progress.progress(min(1.0, (ch.start + CHUNK_POINTS) / src.count))
        if writer is not None:
            writer.close()
    finally:
        if writer is not None:
            writer.abort()
    return n_ground


def _write_products(
    src: PointSource,
    plan: GridPlan,
    method: str,
    first: _FirstPass,
    dtm_acc: Accumulator | None,
    output: Path,
    dtm: Path | None,
    hillshade: Path | None,
    max_gap_m: float,
    smooth_px: int,
    classified: Path | None,
    n_ground: int,
) -> DemResult:
    """Fill, smooth and write the DSM, the DTM and the hillshade."""

    grid = plan.grid
    # no gap is wider than the grid: a larger max gap means "every gap" (and must not pad the grid by it)
    max_gap_cells = min(max_gap_m / plan.resolution_m, math.hypot(grid.rows, grid.cols))
    dsm_grid = _finish(first.dsm.result(), max_gap_cells, smooth_px)
    notes = [*src.notes, f"values in {src.vertical_unit}" if method != "count" else "values: points per cell"]
    unit_tag = vertical_unit_tag(src.vertical_unit) if method != "count" else ""

    def write(path: Path, z: np.ndarray, name: str, units: str) -> Path:
        return write_cog(
            path, with_nodata(z), transform=grid.transform, crs=src.crs_with_heights, nodata=NODATA,
            band_names=(name,), units=units,
        )  # fmt: skip

    dsm_path = write(output, dsm_grid, "dsm", unit_tag)
    dtm_path = None
    dtm_grid = None
    if dtm is not None:
        assert dtm_acc is not None
        dtm_grid = _finish(dtm_acc.result(), max_gap_cells, smooth_px)
        dtm_path = write(dtm, dtm_grid, "dtm", vertical_unit_tag(src.vertical_unit))
    shade_path = None
    if hillshade is not None:
        shade_path = write_hillshade(
            hillshade, dtm_grid if dtm_grid is not None else dsm_grid, plan.cell, src.vertical_m / src.horizontal_m
        )
    return DemResult(
        dsm_path,
        dtm_path,
        Path(classified) if classified is not None else None,
        shade_path,
        plan.cell,
        crs_to_text(src.crs),
        src.describe_units(),
        first.n_used,
        n_ground,
        tuple(notes),
        vertical_crs=heights_to_text(src.heights),
    )


def _finish(grid: np.ndarray, max_gap_cells: float, smooth_px: int, gap: np.ndarray | None = None) -> np.ndarray:
    """Gaps filled (``gap``: the cells to fill; default, the gaps up to ``max_gap_cells``), then smoothed."""
    known = np.isfinite(grid)
    if gap is None and max_gap_cells > 0:
        gap = gap_mask(known, max_gap_cells)
    out = fill_harmonic(grid, known, gap) if gap is not None else grid
    if smooth_px > 0:
        from scipy import ndimage

        valid = np.isfinite(out)
        med = ndimage.median_filter(np.where(valid, out, np.nanmedian(out)), size=2 * smooth_px + 1)
        out = np.where(valid, med, np.nan)
    return out


class _ClassifiedWriter:
    """The source LAS/LAZ again, chunk by chunk, with ground set to class 2 (and former
    ground that is not ground any more set to 1), written atomically."""

    def __init__(self, src: PointSource, target: Path):
        import contextlib

        import laspy

        assert src.path is not None
        self._stack = contextlib.ExitStack()
        # a COPC target (``.copc.laz``) is written as LAZ first, then made COPC from it at close
        self._copc = Path(target) if is_copc_path(target) else None
        self._laz = Path(target).with_name(f".{Path(target).name}.laz") if self._copc else Path(target)
        tmp = self._stack.enter_context(atomic_path(self._laz))
        self._reader = self._stack.enter_context(laspy.open(str(src.path)))
        self._chunks = self._reader.chunk_iterator(CHUNK_POINTS)
        self._writer = self._stack.enter_context(
            laspy.open(
                str(tmp), mode="w", header=self._reader.header, do_compress=Path(target).suffix.lower() == ".laz"
            )
        )
        self._done = False

    def write(self, ground: np.ndarray) -> None:
        pts = next(self._chunks)
        cls = np.asarray(pts.classification).copy()
        cls[(cls == GROUND) & ~ground] = 1
        cls[ground] = GROUND
        pts.classification = cls
        self._writer.write_points(pts)

    def close(self) -> None:
        self._done = True
        self._stack.close()  # writer, reader, then the rename
        if self._copc is not None:
            try:
                write_copc(self._laz, self._copc)
            finally:
                self._laz.unlink(missing_ok=True)

    def abort(self) -> None:
        if not self._done:
            self._done = True
            err = RuntimeError("aborted")
            self._stack.__exit__(type(err), err, None)  # the temporary file is removed


def _run_pdal(
    src: PointSource,
    grid: Grid,
    output: Path,
    dtm: Path | None,
    method: str,
    ground_method: str,
    max_gap_m: float,
    params: SmrfParams,
    fb: Feedback,
) -> DemResult:
    """The same products through PDAL (readers.las, filters.smrf, writers.gdal), then our gap fill."""
    try:
        import pdal
    except ImportError as e:
        raise DependencyError(
            "engine pdal needs the pdal Python package and PDAL itself "
            "(not installable on Debian 12; conda-forge has both)"
        ) from e
    import json
    import tempfile

    import rasterio

    if src.path is None:
        raise ParameterError("engine", "engine pdal reads files only")
    out_type = {"max": "max", "min": "min", "mean": "mean", "idw": "idw", "count": "count"}[method]
    with tempfile.TemporaryDirectory() as d:
        raw_dsm, raw_dtm = Path(d) / "dsm.tif", Path(d) / "dtm.tif"
        bounds = f"([{grid.x0}, {grid.x0 + grid.cols * grid.cell}], [{grid.y0 - grid.rows * grid.cell}, {grid.y0}])"
        writer = {
            "type": "writers.gdal",
            "resolution": grid.cell,
            "output_type": out_type,
            "bounds": bounds,
            "data_type": "float32",
            "nodata": NODATA,
        }
        pdal.Pipeline(json.dumps([str(src.path), {**writer, "filename": str(raw_dsm)}])).execute()
        stages: list[Any] = [str(src.path), *_pdal_ground_filter(ground_method, params, src)]
        n_ground = 0
        if dtm is not None:
            stages += [
                {"type": "filters.range", "limits": "Classification[2:2]"},
                {**writer, "output_type": "idw", "filename": str(raw_dtm)},
            ]
            p = pdal.Pipeline(json.dumps(stages))
            n_ground = int(p.execute())
        outs = []
        for raw, target, name in ((raw_dsm, output, "dsm"), (raw_dtm, dtm, "dtm")):
            if target is None:
                continue
            with rasterio.open(raw) as ds:
                z = ds.read(1).astype(np.float64)
            z[z == NODATA] = np.nan
            z = _finish(z, max_gap_m / (grid.cell * src.horizontal_m), 0)
            outs.append(
                write_cog(
                    target,
                    with_nodata(z),
                    transform=grid.transform,
                    crs=src.crs_with_heights,
                    nodata=NODATA,
                    band_names=(name,),
                    units=vertical_unit_tag(src.vertical_unit),
                )
            )
    fb.info("engine: PDAL")
    return DemResult(
        outs[0], outs[1] if dtm is not None else None, None, None, grid.cell, crs_to_text(src.crs),
        src.describe_units(), src.count, n_ground, tuple(src.notes), vertical_crs=heights_to_text(src.heights),
    )  # fmt: skip


def _pdal_ground_filter(ground_method: str, params: SmrfParams, src: PointSource) -> list[dict[str, Any]]:
    """PDAL's stage that classifies the ground as ours would (its parameters in the cloud's units)."""
    if ground_method == "smrf":
        return [
            {
                "type": "filters.smrf",
                "cell": params.cell_m / src.horizontal_m,
                "slope": params.slope,
                "window": params.window_m / src.horizontal_m,
                "threshold": params.threshold_m / src.vertical_m,
                "scalar": params.scalar,
            }
        ]
    return [{"type": "filters.csf"}] if ground_method == "csf" else []
