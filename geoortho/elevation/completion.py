"""A DEM completed to the ground the photos saw: the cells of the SfM's footprints the cloud left empty,
and a DTM under the DSM's support.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
from affine import Affine

from geoortho.core.crs import horizontal_of
from geoortho.core.outputs import write_cog
from geoortho.core.pointcloud import PointSource
from geoortho.core.sfm_model import cameras_from_sfm
from geoortho.core.surface import GridSurface, whole_surface
from geoortho.elevation.artefacts import footprint_step_m, roughness_m
from geoortho.elevation.bareearth import bare_earth
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
)
from geoortho.elevation.grid import (
    NODATA,
    Box,
    finite_points,
    with_nodata,
)
from geoortho.elevation.products import DemResult, vertical_unit_tag, write_hillshade
from geoortho.elevation.walls import fill_beside_objects
from geoortho.errors import InputError
from geoortho.feedback import Feedback


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
    unit = vertical_unit_tag(src.vertical_unit)

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
    else:
        # the objects are the DTM's: without one the gaps beside them stay interpolated across (the
        # demo's cloud against its true DSM: RMSE 0.299 m without a DTM, 0.274 m with one)
        notes.append(
            "DSM: no DTM was asked for, so the gaps beside and under objects are interpolated across, "
            "not filled from their own side: give a DTM too for the better DSM"
        )
        fb.warning(f"dem: {notes[-1]}")
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
