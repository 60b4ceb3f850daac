"""DSM and DTM from a point cloud: grid, classify ground, fill gaps, write COGs.

Two passes over the points in chunks (memory follows the grid, not the
cloud): the first grids the DSM and the minimum surface the ground filter
needs; the second classifies each point against the provisional ground and
grids the ground points into the DTM (and writes the classified cloud when
asked). Gaps are filled harmonically (:mod:`geoortho.core.gapfill`) — no ringing —
up to ``max_gap_m`` from data on both sides; beyond that cells stay nodata.

Grids stay in the cloud's CRS and units (feet stay feet, and the result says
so); every distance parameter is in metres and converted.
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Literal, get_args

import numpy as np
from affine import Affine
from pyproj import CRS

from geoortho.core.crs import crs_to_text, heights_to_text, horizontal_of
from geoortho.core.gapfill import fill_harmonic, gap_mask
from geoortho.core.outputs import atomic_path, atomic_paths, cog_options, work_folder, write_cog
from geoortho.core.pointcloud import CHUNK_POINTS, Chunk, PointSource, open_points, reprojected
from geoortho.core.sfm_model import cameras_from_sfm
from geoortho.core.styles import terrain, write_raster_style
from geoortho.core.surface import GridSurface, whole_surface
from geoortho.elevation import tiles as dem_tiles
from geoortho.elevation.artefacts import footprint_step_m, roughness_m
from geoortho.elevation.bareearth import bare_earth, ground_noise_m
from geoortho.elevation.contours import contour_interval_m as auto_interval
from geoortho.elevation.contours import write_contours
from geoortho.elevation.coverage import (
    FALLBACK,
    INTERPOLATED,
    MEASURED,
    SOURCE_DESCRIPTION,
    UNDER_OBJECT,
    complete_grid,
    extended_grid,
    footprint_polygons,
    seen_area_m2,
    seen_count,
    source_path,
    source_style,
)
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
from geoortho.elevation.ground import SmrfParams, ground_mask, smrf_surface
from geoortho.elevation.tiles import make_tiled
from geoortho.elevation.walls import fill_beside_objects
from geoortho.errors import DependencyError, InputError, ParameterError
from geoortho.feedback import Feedback, as_feedback, split

__all__ = ["DemResult", "dem", "grid_points", "Grid", "METHODS", "NODATA"]

GroundMethod = Literal["smrf", "csf", "classification"]
Engine = Literal["native", "pdal"]
GROUND_METHODS: tuple[str, ...] = get_args(GroundMethod)
#: the DSM statistics, and auto: chosen from what the cloud is
DemMethod = Literal["auto", "max", "min", "mean", "idw", "count"]
ENGINES: tuple[str, ...] = get_args(Engine)


@dataclass(frozen=True)
class DemResult:
    """The rasters dem wrote and what it measured.

    Attributes
    ----------
    dsm : Path
        DSM (COG, float32, nodata -9999).
    dtm : Path
        DTM from ground points (None when not asked for).
    classified : Path
        The cloud with ground as class 2 (None when not asked for).
    hillshade : Path
        Hillshade preview (None when not asked for).
    resolution : float
        Cell size in the CRS units (feet in a CRS in feet).
    crs : str
        CRS of the rasters.
    units : str
        Horizontal and vertical units.
    n_points : int
        Points used.
    n_ground : int
        Ground points.
    notes : tuple of str
        What was assumed or checked, in words.
    dsm_source : Path
        With ``sfm``: which cells of the DSM are measured (1), interpolated (2) or a fallback
        plane (3); uint8 COG, 0 = no data.
    dtm_source : Path
        The same for the DTM (measured: the ground filter's surface where the DSM's measured
        cells are ground).
    seen_m2 : float
        With ``sfm``: ground seen by at least two registered photos, m² (measured only for a cloud in
        metres).
    dsm_m2 : float
        Area of the DSM with a value.
    measured_share : float
        Share of the DSM's valued cells measured from points.
    interpolated_share : float
        Share interpolated (gap fill, and carried to the photos' edge).
    fallback_share : float
        Share on the fallback plane.
    dtm_measured_share : float
        With ``sfm``: share of the DTM's cells that are measured ground (rims, objects and stray
        ground islands taken out).
    dtm_under_object_share : float
        With ``sfm``: share of the DTM over the ground >= 2 photos saw that lies under an object
        farther from any ground seen than a fill can bridge there (2-10 m, judged on the ground's
        own relief around it; source code 4: a guess).
    dtm_roughness_m : float
        With ``sfm``: the DTM less its 1 m median, RMS, on open ground (metres).
    footprint_step_m : float
        With ``sfm``: the DTM's step across the photos' footprint edges, RMS over the edges (a
        depth map's offset shows as a patch with straight edges), metres.
    ground_noise_m : float
        With ``sfm``: the speckle of the measured ground (robust sigma less its 0.5 m smoothing)
        that the DTM was cleaned of, metres.
    contours : Path
        Contour lines of the DTM (GeoPackage), when asked for.
    contour_interval_m : float
        Their interval.
    vertical_crs : str
        The heights' datum the DEMs carry (``EPSG:5773``, ``ellipsoidal``), None when the points
        did not state it.
    """

    dsm: Path
    dtm: Path | None
    classified: Path | None
    hillshade: Path | None
    resolution: float  # cell size in the CRS units
    crs: str
    units: str
    n_points: int
    n_ground: int
    notes: tuple[str, ...] = field(default_factory=tuple)
    dsm_source: Path | None = None
    dtm_source: Path | None = None
    seen_m2: float = 0.0
    dsm_m2: float = 0.0
    measured_share: float = 1.0
    interpolated_share: float = 0.0
    fallback_share: float = 0.0
    dtm_measured_share: float = math.nan
    dtm_under_object_share: float = math.nan
    dtm_roughness_m: float = math.nan
    footprint_step_m: float = math.nan
    ground_noise_m: float = math.nan
    contours: Path | None = None
    contour_interval_m: float = math.nan
    vertical_crs: str | None = None


def _auto_resolution_m(src: PointSource) -> float:
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


def _scan_extent(src: PointSource, fb: Feedback) -> _Scan:
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
        Also write the cloud with ground as class 2 (LAS/LAZ input only).
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
    _check_options(chosen, ground_method, resolution_m, max_gap_m, smooth_px, engine)
    if contours is not None and dtm is None:  # refused before any work
        raise ParameterError("contours", "contours are drawn from the DTM: give --dtm too")
    src = _open_source(points, points_crs, crs, engine, classified, ground_method, why_method, fb)
    want_ground = dtm is not None or classified is not None
    s_scan, s_pass1, s_pass2, s_write = split(fb, [1, 4, 4 if want_ground else 0, 2])
    scan = _scan_extent(src, s_scan)
    src = scan.src
    src.notes.extend(scan.notes)
    tiles_allowed = not (want_ground and ground_method == "csf")  # CSF needs every point at once
    plan = _plan_grid(src, resolution_m, fb, tiles_allowed=tiles_allowed)
    params = SmrfParams(smrf_cell_m, smrf_slope, smrf_window_m, smrf_threshold_m, smrf_scalar, smrf_margin_m)
    if want_ground and ground_method == "smrf":
        params = _check_smrf(src, params, fb)
    if engine == "pdal":
        return _with_styles(_run_pdal(src, plan.grid, output, dtm, chosen, ground_method, max_gap_m, params, fb))

    if tiles_allowed and float(plan.grid.rows) * plan.grid.cols > _whole_grid_max_cells():
        tiled = _dem_tiled(
            src, plan, chosen, ground_method, params, scan.keep, output, dtm, classified, hillshade,
            max_gap_m, smooth_px, s_pass1, s_write, fb,
        )  # fmt: skip
        tiled = tiled if sfm is None else complete_to_photos(tiled, src, scan.keep, Path(sfm), fb)
        return _with_styles(_with_contours(tiled, contours, contour_interval_m, sfm, fb))
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
    result = _with_styles(_with_contours(result, contours, contour_interval_m, sfm, fb))
    s_write.progress(1.0)
    return result


def _with_styles(result: DemResult) -> DemResult:
    """Each raster's QGIS style beside it as its default (``.qml``): the DEMs coloured by
    height, the source rasters paletted with their codes' meanings."""
    for path in (result.dsm, result.dtm):
        if path is not None:
            write_raster_style(path, terrain(path))
    for path in (result.dsm_source, result.dtm_source):
        if path is not None:
            write_raster_style(path, source_style())
    return result


def _with_contours(
    result: DemResult, contours: Path | None, interval_m: float, sfm: Path | None, fb: Feedback
) -> DemResult:
    """``result`` with the DTM's contour lines written to ``contours`` (when asked for)."""
    if contours is None:
        return result
    assert result.dtm is not None  # dem refuses contours without a DTM before any work
    import rasterio

    with rasterio.open(result.dtm) as ds:
        z = ds.read(1, masked=True).filled(np.nan).astype(np.float64)
        transform, crs = ds.transform, ds.crs
    z *= _unit_m(result, "vertical")
    why = f"given: {interval_m:g} m"
    if interval_m <= 0:
        noise = result.ground_noise_m
        if not math.isfinite(noise):
            noise = ground_noise_m(z, np.isfinite(z), abs(transform.a) * _unit_m(result, "horizontal"))
        checkpoints = _checkpoint_rmse_z_m(sfm)
        rmse = math.hypot(noise, checkpoints if math.isfinite(checkpoints) else 0.0)
        relief = float(np.nanmax(z) - np.nanmin(z)) if np.isfinite(z).any() else 0.0
        interval_m = auto_interval(rmse, relief)
        why = (
            f"from a vertical RMSE of {100 * rmse:.1f} cm (ground noise {100 * noise:.1f} cm"
            + (f", checkpoints {100 * checkpoints:.1f} cm" if math.isfinite(checkpoints) else "")
            + f"): {interval_m:g} m"
        )
    drawn = write_contours(contours, z, transform, crs, interval_m, why)
    note = f"contours every {drawn.interval_m:g} m ({drawn.why}): {drawn.n_lines:,} lines in {Path(contours).name}"
    fb.info(note)
    return replace(result, contours=Path(contours), contour_interval_m=drawn.interval_m, notes=(*result.notes, note))


#: Metres per unit, by the names the point sources give their units.
_UNIT_M = {"metre": 1.0, "foot": 0.3048, "US survey foot": 1200.0 / 3937.0}


def _unit_m(result: DemResult, axis: str) -> float:
    """Metres per ``axis`` (horizontal, vertical) unit of the result's rasters."""
    for part in result.units.split(", "):
        if part.startswith(axis + " "):
            return _UNIT_M.get(part[len(axis) + 1 :], 1.0)
    return 1.0


def _checkpoint_rmse_z_m(sfm: Path | None) -> float:
    """The SfM's checkpoints' vertical RMSE (NaN when it has none)."""
    if sfm is None:
        return math.nan
    acc = _json_or_empty(Path(sfm) / "report.json").get("checkpoint_accuracy") or {}
    try:
        return float(acc["rmse_z_m"])
    except (KeyError, TypeError, ValueError):
        return math.nan


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
    _check_source(src, classified, ground_method)
    for n in src.notes:
        fb.info(n)
    return src


def _json_or_empty(path: Path) -> dict[str, Any]:
    try:
        got = json.loads(path.read_text())
    except (OSError, ValueError):
        return {}
    return got if isinstance(got, dict) else {}


def _auto_method(method: str, points: Any, sfm: Path | None) -> tuple[str, str]:
    """The DSM statistic ``auto`` stands for, and the note that says why ("" when chosen).

    A cloud from the photos is one noisy surface: a cell's highest point stood 4 cm (1.1 GSD)
    above the true ground on the free-heading survey, the distance-weighted mean 1.3 cm (RMSE
    8.5 -> 4.1 cm, roofs 3.7 -> 2.0 cm). A lidar cloud keeps its first returns (max)."""
    if method != "auto":
        return method, ""
    from_dense = False
    if isinstance(points, (str, os.PathLike)):  # dense writes its report beside its cloud
        from_dense = "depth_maps" in _json_or_empty(Path(points).with_name(Path(points).stem + "_report.json"))
    if sfm is not None or from_dense:
        return "idw", "method auto: idw (a cloud from photos: a cell's highest point would stand above the surface)"
    return "max", "method auto: max (a lidar or other cloud: each cell's first return)"


def _dem_tiled(
    src: PointSource,
    plan: _GridPlan,
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
    unit_tag = _unit_tag(src.vertical_unit) if method != "count" else ""
    with work_folder(Path(output)) as work:
        tiles = make_tiled(
            src, grid, method, ground_method if want_ground else None, params, keep,
            dtm is not None, max_gap_cells, _finish, smooth_px, Path(work), fb, progress,
        )  # fmt: skip
        with atomic_paths(output, dtm, hillshade, commit_check=fb.check_canceled) as (t_dsm, t_dtm, t_shade):
            assert t_dsm is not None
            _cog_of(tiles.dsm_tif, t_dsm, "dsm", unit_tag)
            if t_dtm is not None and tiles.dtm_tif is not None:
                _cog_of(tiles.dtm_tif, t_dtm, "dtm", _unit_tag(src.vertical_unit))
            if t_shade is not None:
                _hillshade_of(tiles.dtm_tif or tiles.dsm_tif, t_shade, src.vertical_m / src.horizontal_m)
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


def _cog_of(tif: Path, target: Path, name: str, units: str) -> None:
    """A tiled GeoTIFF made a COG by GDAL, block by block (as write_cog makes one from an array)."""
    import rasterio
    from rasterio.shutil import copy as rio_copy

    with rasterio.open(tif, "r+") as ds:
        ds.set_band_description(1, name)
        if units:
            ds.set_band_unit(1, units)
    with rasterio.Env(GDAL_CACHEMAX=128):
        rio_copy(tif, target, driver="COG", **cog_options("DEFLATE", is_float=True))


#: The hillshade of a tiled grid is a preview: at most this many pixels a side.
MAX_HILLSHADE_PX = 4096
HILLSHADE_STRIP_ROWS = 256


def _hillshade_of(tif: Path, target: Path, z_per_xy: float) -> None:
    import rasterio
    from rasterio.enums import Resampling

    with rasterio.open(tif) as ds:
        f = max(1.0, max(ds.width, ds.height) / MAX_HILLSHADE_PX)
        shape = (max(1, round(ds.height / f)), max(1, round(ds.width / f)))
        z = ds.read(1, out_shape=shape, resampling=Resampling.nearest, masked=True).astype(np.float64).filled(np.nan)
        cell = ds.transform.a * ds.width / shape[1]
    write_hillshade(target, z, cell, z_per_xy)


def _check_options(
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


def _check_source(src: PointSource, classified: Path | None, ground_method: str) -> None:
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
class _GridPlan:
    grid: Grid
    resolution_m: float  # cell size on the ground, metres
    cell: float  # the same in the cloud's horizontal units


def _whole_grid_max_cells() -> int:
    return dem_tiles.WHOLE_GRID_MAX_CELLS  # read when called: a test (or a user) may lower it


def _plan_grid(src: PointSource, resolution_m: float | None, fb: Feedback, tiles_allowed: bool = True) -> _GridPlan:
    res_m = resolution_m or _auto_resolution_m(src)
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
    if not tiles_allowed or cells <= _whole_grid_max_cells():  # larger grids are made in tiles
        _check_memory(grid, res_m, src, width_m, height_m)
    fb.info(
        f"grid {grid.cols} x {grid.rows} cells of {res_m:g} m ({cell:g} {src.horizontal_unit})"
        + ("" if resolution_m else ", from the point density")
    )
    return _GridPlan(grid, res_m, cell)


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


def _check_smrf(src: PointSource, params: SmrfParams, fb: Feedback) -> SmrfParams:
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


class _GroundFilter:
    """A ground method as the two passes see it: it watches the points of pass 1,
    prepares between the passes, then says which points of pass 2 are ground."""

    #: The ground is known chunk by chunk in pass 1 already (the file's own classes).
    known_in_first_pass = False

    def __init__(self, src: PointSource, params: SmrfParams):
        self.src, self.params = src, params

    def observe(self, ch: Chunk) -> None:
        """Pass 1: one chunk of finite points."""

    def prepare(self) -> None:
        """Between the passes."""

    def ground(self, ch: Chunk) -> np.ndarray:
        """Pass 2 (pass 1 too when ``known_in_first_pass``): ground mask of a chunk of finite points."""
        raise NotImplementedError


class _SmrfGround(_GroundFilter):
    """Pingel's SMRF on a minimum-elevation grid of its own cell size."""

    def __init__(self, src: PointSource, params: SmrfParams):
        super().__init__(src, params)
        xmin, ymin, _, xmax, ymax, _ = src.bounds
        self.grid = Grid.covering(xmin, ymin, xmax, ymax, params.cell_m / src.horizontal_m)
        self.zmin = Accumulator(self.grid, "min")
        self.surface: np.ndarray | None = None

    def observe(self, ch: Chunk) -> None:
        self.zmin.add(ch.x, ch.y, ch.z)

    def prepare(self) -> None:
        self.surface = smrf_surface(
            self.zmin.result(), self.grid.cell, self.params, self.src.horizontal_m, self.src.vertical_m
        )

    def ground(self, ch: Chunk) -> np.ndarray:
        assert self.surface is not None
        g = self.grid
        return ground_mask(
            ch.x, ch.y, ch.z, self.surface, g.x0, g.y0, g.cell, self.params, self.src.horizontal_m, self.src.vertical_m
        )


class _CsfGround(_GroundFilter):
    """The cloth simulation filter: it needs every point at once, so pass 1 keeps them."""

    def __init__(self, src: PointSource, params: SmrfParams):
        super().__init__(src, params)
        self.xyz: list[np.ndarray] = []
        self.mask: np.ndarray | None = None
        self.offset = 0

    def observe(self, ch: Chunk) -> None:
        self.xyz.append(np.c_[ch.x, ch.y, ch.z])

    def prepare(self) -> None:
        self.mask = _csf(np.concatenate(self.xyz), self.src, self.params)
        self.xyz.clear()

    def ground(self, ch: Chunk) -> np.ndarray:
        assert self.mask is not None
        g = self.mask[self.offset : self.offset + len(ch.x)]
        self.offset += len(ch.x)
        return g


class _ClassificationGround(_GroundFilter):
    """The file's own class 2."""

    known_in_first_pass = True

    def ground(self, ch: Chunk) -> np.ndarray:
        assert ch.classification is not None
        return np.asarray(ch.classification == GROUND)


#: ground_method -> its filter (a new method is a new entry, not a new branch in the passes).
GROUND_FILTERS: dict[str, type[_GroundFilter]] = {
    "smrf": _SmrfGround,
    "csf": _CsfGround,
    "classification": _ClassificationGround,
}
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
    ground: _GroundFilter | None,
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
    ground: _GroundFilter | None,
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
    plan: _GridPlan,
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
    unit_tag = _unit_tag(src.vertical_unit) if method != "count" else ""

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
        dtm_path = write(dtm, dtm_grid, "dtm", _unit_tag(src.vertical_unit))
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


def _on_grid(points: np.ndarray | None, transform: Any) -> np.ndarray | None:
    """World points (x, y, z) as (row, col, z) of a grid (fractional cells)."""
    if points is None or not len(points):
        return None
    p = np.asarray(points, np.float64)
    col, row = ~transform * (p[:, 0], p[:, 1])
    result: np.ndarray | None = np.c_[row, col, p[:, 2]]
    return result


def complete_to_photos(result: DemResult, src: PointSource, keep: Box | None, sfm: Path, fb: Feedback) -> DemResult:
    """The DSM and DTM just written, carried over the ground at least two of the SfM's registered
    photos saw, with a source raster beside each (see :mod:`geoortho.elevation.coverage`)."""
    import rasterio

    if src.horizontal_m != 1.0 or src.vertical_m != 1.0:
        note = "not carried to the photos' edge: the cloud is not in metres"
        fb.warning(f"dem: {note}")
        return replace(result, notes=(*result.notes, note))
    cams, _, tie_points, _ = cameras_from_sfm(sfm, None, src.crs, local_frame_ok=src.crs is None)
    with rasterio.open(result.dsm) as ds:
        dsm = ds.read(1, masked=True).filled(np.nan).astype(np.float32)
        transform = ds.transform
    if not np.isfinite(dsm).any():
        raise InputError("the DSM has no value to carry to the photos' edge", path=result.dsm)
    polys = footprint_polygons(cams, GridSurface(dsm, transform, extend=True))
    import shapely

    bounds = tuple(shapely.total_bounds(np.asarray(polys, dtype=object))) if polys else None
    if bounds is None or not np.isfinite(bounds).all():
        return result
    z, target, new_t = _over_the_footprints(dsm, transform, polys, bounds)
    measured = _point_cells(src, keep, new_t, z.shape)
    done = complete_grid(z, measured, target, new_t, tie_points)
    cell_m2 = abs(new_t.a * new_t.e)
    have = done.source > 0
    shares = {code: done.share(code) for code in (MEASURED, INTERPOLATED, FALLBACK)}
    covered = float((have & target).sum()) / max(int(target.sum()), 1)
    crs = src.crs
    unit = _unit_tag(src.vertical_unit)

    dsm_source = write_cog(
        source_path(result.dsm), done.source, transform=new_t, crs=crs, nodata=0, band_names=(SOURCE_DESCRIPTION,)
    )
    notes = []
    if done.fallback_plane is not None:
        notes.append("nothing was measured under the photos: the DSM is a plane through the SfM tie points")
    dtm_source = dtm_grid = None
    dtm_fields: dict[str, Any] = {}
    if result.dtm is not None:
        dtm_source, dtm_grid, objects, note, dtm_fields = _complete_dtm(
            result.dtm, done, z, measured, target, new_t, src.crs_with_heights, unit, polys
        )
        notes.append(note)
        # the DSM's gaps beside and under the objects the DTM found, each filled from its own side
        dsm_z, n_walls = fill_beside_objects(done.z, measured, objects, new_t.a, _on_grid(tie_points, new_t))
        done = replace(done, z=dsm_z)
        notes.append(f"DSM: {n_walls:,} filled cells beside and under objects filled again from their own side")
        warning = dtm_fields.pop("notes_extra", "")
        if warning:
            notes.append(warning)
            fb.warning(f"dem: {warning}")
    write_cog(
        result.dsm, with_nodata(done.z), transform=new_t, crs=src.crs_with_heights, nodata=NODATA,
        band_names=("dsm",), units=unit,
    )  # fmt: skip
    # the area itself from the footprints cast on the DSM written (the ortho on it states the same
    # figure), not a count of this grid's cells
    seen_m2 = seen_area_m2(footprint_polygons(cams, whole_surface(GridSurface(done.z, new_t, extend=True)).surface))
    notes.insert(
        0,
        f"DSM carried over the {seen_m2:,.0f} m² seen by >= 2 of {len(cams)} registered photos "
        f"({covered:.1%} of it has a value): measured {shares[MEASURED]:.1%}, interpolated "
        f"{shares[INTERPOLATED]:.1%}, fallback plane {shares[FALLBACK]:.1%} of its cells ({dsm_source.name})",
    )
    if result.hillshade is not None:
        write_hillshade(result.hillshade, dtm_grid if dtm_grid is not None else done.z, new_t.a, 1.0)
    for n in notes:
        fb.info(n)
    if covered < 0.98 or shares[MEASURED] < 0.5:
        warn = (
            f"the DSM is measured on {shares[MEASURED]:.0%} of its cells and covers {covered:.0%} of the ground "
            ">= 2 photos saw: the rest is interpolated (see the source raster)"
        )
        notes.append(warn)
        fb.warning(f"dem: {warn}")
    return replace(
        result,
        dsm_source=dsm_source,
        dtm_source=dtm_source,
        seen_m2=seen_m2,
        dsm_m2=float(have.sum()) * cell_m2,
        measured_share=shares[MEASURED],
        interpolated_share=shares[INTERPOLATED],
        fallback_share=shares[FALLBACK],
        notes=(*result.notes, *notes),
        **dtm_fields,
    )


def _over_the_footprints(
    dsm: np.ndarray, transform: Affine, polys: list[Any], bounds: tuple[float, ...]
) -> tuple[np.ndarray, np.ndarray, Affine]:
    """The DSM on a grid grown to the footprints' bounds and cropped to what has a value or must
    have one; the cells seen by >= 2 photos, and the grid's transform."""
    new_t, shape, (r0, c0) = extended_grid(transform, dsm.shape, bounds)  # type: ignore[arg-type]
    target = seen_count(polys, new_t, shape) >= 2
    z = np.full(shape, np.nan, np.float32)
    z[r0 : r0 + dsm.shape[0], c0 : c0 + dsm.shape[1]] = dsm
    # crop to what has a value or must: the polygons' bounding box holds the single-photo fringe too
    rows = np.flatnonzero((target | np.isfinite(z)).any(axis=1))
    cols = np.flatnonzero((target | np.isfinite(z)).any(axis=0))
    sl = np.s_[rows[0] : rows[-1] + 1, cols[0] : cols[-1] + 1]
    new_t = new_t @ Affine.translation(int(cols[0]), int(rows[0]))
    return z[sl], target[sl], new_t


def _complete_dtm(
    path: Path, done: Any, z: np.ndarray, measured: np.ndarray, target: np.ndarray, new_t: Affine, crs: Any,
    unit: str, polys: list[Any],
) -> tuple[Path, np.ndarray, np.ndarray, str, dict[str, Any]]:  # fmt: skip
    """The DTM just written, made bare earth (:mod:`geoortho.elevation.bareearth`) and carried over
    the same cells as the DSM (``done``): its source raster, its grid, the objects found on the
    DSM, the note of its shares and the DemResult fields it measured (its artefacts,
    :mod:`geoortho.elevation.artefacts`)."""
    import rasterio

    with rasterio.open(path) as ds:
        d = ds.read(1, masked=True).filled(np.nan).astype(np.float32)
        dt = ds.transform
    grid = np.full(z.shape, np.nan, np.float32)
    rr = int(round((new_t.f - dt.f) / new_t.a))
    cc = int(round((dt.c - new_t.c) / new_t.a))
    grid[rr : rr + d.shape[0], cc : cc + d.shape[1]] = d
    # ground measured where the DSM was measured and is the ground (no object on it)
    with np.errstate(invalid="ignore"):
        ground_seen = measured & (np.abs(z - grid) <= max(2.0 * new_t.a, 0.1))
    plane = _dtm_support(done, grid, new_t)
    dtm_done = complete_grid(grid, ground_seen, target, new_t, plane)
    clean = bare_earth(done.z, dtm_done.z, ground_seen, new_t.a)
    source = dtm_done.source.copy()
    source[(source == MEASURED) & ~clean.ground] = INTERPOLATED
    source[clean.no_ground & (source > 0)] = UNDER_OBJECT
    dtm_done = replace(dtm_done, z=clean.z, source=source)
    write_cog(path, with_nodata(clean.z), transform=new_t, crs=crs, nodata=NODATA, band_names=("dtm",), units=unit)
    dtm_source = write_cog(  # codes, not heights: the map grid alone
        source_path(path), source, transform=new_t, crs=horizontal_of(crs), nodata=0, band_names=(SOURCE_DESCRIPTION,)
    )
    # open ground: ground kept, off every object, the DSM on it
    with np.errstate(invalid="ignore"):
        open_ground = clean.ground & ~clean.objects & (np.abs(done.z - clean.z) <= max(2.0 * new_t.a, 0.1))
    rough = roughness_m(clean.z, open_ground, new_t.a)
    step, n_edges = footprint_step_m(clean.z, new_t, polys, open_ground)
    in_target = target & (source > 0)
    fields: dict[str, Any] = {
        "dtm_measured_share": dtm_done.share(MEASURED),
        "dtm_under_object_share": dtm_done.share(UNDER_OBJECT, within=in_target) if in_target.any() else 0.0,
        "dtm_roughness_m": rough,
        "footprint_step_m": step,
        "ground_noise_m": clean.noise_m,
    }
    if not clean.ground.any() and clean.no_ground.any():
        fields["notes_extra"] = (
            f"no ground seen: what the ground filter kept is {100 * clean.noise_m:.0f} cm rough (canopy, not ground); "
            "the DTM is a plane through the lowest points, every cell under an object"
        )
    note = (
        f"DTM: ground measured {dtm_done.share(MEASURED):.1%}, interpolated {dtm_done.share(INTERPOLATED):.1%}, "
        f"under an object with no ground seen {dtm_done.share(UNDER_OBJECT):.1%} (bridged up to "
        f"{clean.bridge_m:g} m from the ground, the median over the objects, as the ground's relief allows), "
        f"fallback plane {dtm_done.share(FALLBACK):.1%} of its cells; {clean.n_rim:,} cells of rims and "
        f"objects and {clean.n_islands:,} of stray ground islands taken out; open-ground roughness "
        f"{100 * rough:.1f} cm RMS (less its 1 m median), step at {n_edges} photo footprint edges "
        f"{100 * step:.1f} cm RMS"
    )
    return dtm_source, clean.z, clean.objects, note, fields


def _dtm_support(dsm: Any, dtm: np.ndarray, transform: Any) -> np.ndarray | None:
    """Where the DTM has nothing at all (water only): the DSM's cells as the plane's support."""
    if np.isfinite(dtm).any():
        return None
    rows, cols = np.nonzero(np.isfinite(dsm.z))
    if not len(rows):
        return None
    step = max(1, len(rows) // 20000)
    rows, cols = rows[::step], cols[::step]
    x, y = transform * (cols + 0.5, rows + 0.5)
    result: np.ndarray | None = np.c_[x, y, dsm.z[rows, cols]]
    return result


def _point_cells(src: PointSource, keep: Box | None, transform: Any, shape: tuple[int, int]) -> np.ndarray:
    """Cells of the grid within one cell of a point of the cloud: measured at the points' spacing
    (the automatic cell holds about two points, so a measured surface leaves single cells empty)."""
    out = np.zeros(shape[0] * shape[1], bool)
    for ch in src.chunks():
        fin, _ = finite_points(ch, keep)
        c = np.floor((fin.x - transform.c) / transform.a).astype(np.int64)
        r = np.floor((fin.y - transform.f) / transform.e).astype(np.int64)
        ok = (c >= 0) & (c < shape[1]) & (r >= 0) & (r < shape[0])
        out[r[ok] * shape[1] + c[ok]] = True
    from scipy import ndimage

    return np.asarray(ndimage.binary_dilation(out.reshape(shape), structure=np.ones((3, 3), bool)))


def _unit_tag(name: str) -> str:
    return {"metre": "m", "foot": "ft", "US survey foot": "US survey foot"}.get(name, name)


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


def write_hillshade(
    path: str | os.PathLike[str],
    z: np.ndarray,
    cell: float,
    z_per_xy: float = 1.0,
    azimuth_deg: float = 315.0,
    altitude_deg: float = 45.0,
) -> Path:
    """A greyscale hillshade PNG (sun from the north-west, 45° up); nodata transparent."""
    import cv2

    valid = np.isfinite(z)
    fill = np.nanmean(z) if valid.any() else 0.0
    az, alt = math.radians(azimuth_deg), math.radians(altitude_deg)
    grey = np.empty(z.shape, np.uint8)
    # in strips of rows (a row of margin each side, so the slopes are the whole grid's): a 4096 px
    # preview's dozen temporaries held whole took 900 MB
    for r0 in range(0, z.shape[0], HILLSHADE_STRIP_ROWS):
        r1 = min(z.shape[0], r0 + HILLSHADE_STRIP_ROWS)
        a, b = max(0, r0 - 1), min(z.shape[0], r1 + 1)
        zz = np.where(valid[a:b], z[a:b], fill) * z_per_xy
        gy, gx = np.gradient(zz, cell)
        slope = np.arctan(np.hypot(gx, gy))
        aspect = np.arctan2(-gx, gy)  # downhill direction, clockwise from north (rows go south)
        shade = np.sin(alt) * np.cos(slope) + np.cos(alt) * np.sin(slope) * np.cos(az - aspect)
        grey[r0:r1] = np.clip(shade[r0 - a : r1 - a] * 255, 0, 255).astype(np.uint8)
    rgba = np.dstack([grey, grey, grey, np.where(valid, 255, 0).astype(np.uint8)])
    with atomic_path(path) as tmp:
        if not cv2.imwrite(str(tmp), rgba):
            raise InputError("cannot write an image there (use .png)", path=Path(path))
    return Path(path)


class _ClassifiedWriter:
    """The source LAS/LAZ again, chunk by chunk, with ground set to class 2 (and former
    ground that is not ground any more set to 1), written atomically."""

    def __init__(self, src: PointSource, target: Path):
        import contextlib

        import laspy

        assert src.path is not None
        self._stack = contextlib.ExitStack()
        tmp = self._stack.enter_context(atomic_path(target))
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

    def abort(self) -> None:
        if not self._done:
            self._done = True
            err = RuntimeError("aborted")
            self._stack.__exit__(type(err), err, None)  # the temporary file is removed


def _csf(xyz: np.ndarray, src: PointSource, params: SmrfParams) -> np.ndarray:
    """Cloth simulation filter (Zhang et al. 2016; the ``cloth-simulation-filter`` package)."""
    try:
        import CSF
    except ImportError as e:
        raise DependencyError(
            "ground_method csf needs the cloth-simulation-filter package (pip install cloth-simulation-filter)"
        ) from e
    import contextlib
    import io

    c = CSF.CSF()
    c.params.bSloopSmooth = True
    c.params.cloth_resolution = params.cell_m / src.horizontal_m
    c.params.class_threshold = params.threshold_m / src.vertical_m
    c.params.rigidness = 2
    c.setPointCloud(xyz - xyz.min(axis=0))  # CSF works in float; keep the numbers small
    ground, other = CSF.VecInt(), CSF.VecInt()
    with contextlib.redirect_stdout(io.StringIO()):  # it prints its progress
        c.do_filtering(ground, other, exportCloth=False)
    mask = np.zeros(len(xyz), bool)
    mask[np.asarray(list(ground), np.int64)] = True
    return mask


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
                    units=_unit_tag(src.vertical_unit),
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
