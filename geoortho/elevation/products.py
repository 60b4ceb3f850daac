"""What dem hands back and writes beside its rasters: the result, the COGs, their QGIS styles, the
contours and the hillshade.
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from geoortho.core.outputs import atomic_path, cog_options
from geoortho.core.styles import terrain, write_raster_style
from geoortho.elevation.bareearth import ground_noise_m
from geoortho.elevation.contours import contour_interval_m as auto_interval
from geoortho.elevation.contours import write_contours
from geoortho.elevation.coverage import (
    source_style,
)
from geoortho.errors import InputError
from geoortho.feedback import Feedback


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
    resolution_crs_units : float
        Cell size in the CRS's horizontal units (feet in a CRS in feet): the rasters' own.
    crs : str
        CRS of the rasters.
    units : str
        Horizontal and vertical units.
    resolution_m : float
        Cell size in metres.
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
    resolution_crs_units: float
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
    resolution_m: float = field(init=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "resolution_m", self.resolution_crs_units * _unit_m(self, "horizontal"))

    @property
    def resolution(self) -> float:
        """The cell size in CRS units, by its former name (:attr:`resolution_crs_units`)."""
        return self.resolution_crs_units


def with_styles(result: DemResult) -> DemResult:
    """Each raster's QGIS style beside it as its default (``.qml``): the DEMs coloured by
    height, the source rasters paletted with their codes' meanings."""
    for path in (result.dsm, result.dtm):
        if path is not None:
            write_raster_style(path, terrain(path))
    for path in (result.dsm_source, result.dtm_source):
        if path is not None:
            write_raster_style(path, source_style())
    return result


def with_contours(
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
    acc = json_or_empty(Path(sfm) / "report.json").get("checkpoint_accuracy") or {}
    try:
        return float(acc["rmse_z_m"])
    except (KeyError, TypeError, ValueError):
        return math.nan


def json_or_empty(path: Path) -> dict[str, Any]:
    try:
        got = json.loads(path.read_text())
    except (OSError, ValueError):
        return {}
    return got if isinstance(got, dict) else {}


def cog_of(tif: Path, target: Path, name: str, units: str) -> None:
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


def hillshade_of(tif: Path, target: Path, z_per_xy: float) -> None:
    import rasterio
    from rasterio.enums import Resampling

    with rasterio.open(tif) as ds:
        f = max(1.0, max(ds.width, ds.height) / MAX_HILLSHADE_PX)
        shape = (max(1, round(ds.height / f)), max(1, round(ds.width / f)))
        z = ds.read(1, out_shape=shape, resampling=Resampling.nearest, masked=True).astype(np.float64).filled(np.nan)
        cell = ds.transform.a * ds.width / shape[1]
    write_hillshade(target, z, cell, z_per_xy)


def vertical_unit_tag(name: str) -> str:
    return {"metre": "m", "foot": "ft", "US survey foot": "US survey foot"}.get(name, name)


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
