"""Photo footprints and GSD: each photo's image border cast onto flat ground or a DSM.

Every border ray is intersected with the surface (not only the point under the
drone), so footprints follow the terrain and oblique photos come out as the
trapezoids they are. Rays at or above the horizon, or longer than
``max_range_m``, are clipped at that range and the footprint is flagged.

Heights come from :mod:`geoortho.photos.heights` (one height model per flight: which
altitude, read how, in which vertical datum, checked against the photo spacing
and over time; refused with what to give when no height above ground can be
trusted). Without any ground model the ground is flat at the take-off elevation.
A DSM that does not cover every photo is extended by a plane at the nearby ground
height (flagged per footprint in ``outside_dsm``), not left to the range limit.

Here: :func:`footprints` and its result, from metadata or from an SfM. Beside it:
:mod:`.photo_cameras` (the photos as posed cameras, their footprints cast), :mod:`.height_check`
(given heights against the SfM's) and :mod:`.footprint_layers` (what is written).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from pyproj import CRS

from geoortho.core.crs import crs_to_text
from geoortho.core.sfm_model import cameras_from_sfm
from geoortho.core.surface import FlatSurface, Surface
from geoortho.errors import InputError
from geoortho.feedback import Feedback, as_feedback, split, warn_grouped
from geoortho.photos.footprint_layers import layers_of_footprints, write_layers
from geoortho.photos.height_check import (
    Heights,
    check_given_heights,
    finite_median,
    ground_under_sfm,
    sfm_photo_cameras,
)
from geoortho.photos.heights import GpsAltitude, HeightModel
from geoortho.photos.metadata import Photo, PhotoSet, read_photos
from geoortho.photos.photo_cameras import (
    DSM_MAX_CELLS,
    FootprintTable,
    PhotoCamera,
    compute_footprints,
    dsm_under,
    grid_positions,
    photo_cameras,
    posed_cameras,
    working_crs,
)

__all__ = [
    "PhotoCamera",
    "FootprintResult",
    "photo_cameras",
    "compute_footprints",
    "footprints",
    "working_crs",
]


@dataclass(frozen=True)
class FootprintResult:
    """What the footprints algorithm wrote, and the survey's figures.

    Attributes
    ----------
    output : Path
        Footprints (layer footprints) and camera positions (layer cameras).
    crs : str
        CRS of the output.
    n_photos : int
        Photos with a footprint.
    n_skipped : int
        Photos skipped.
    median_gsd_cm : float
        Median GSD at the image centres, cm.
    overlap : Path
        Photos seeing each ground cell (None when not asked for).
    height_source : str
        How camera heights were found.
    vertical_datum : str
        Vertical datum of the heights.
    notes : tuple of str
        What was assumed or checked, in words.
    altitude_m : float
        Median height of the cameras above the ground under them, m (measured, with ``sfm``).
    altitude_metadata_m : float
        The same from the photos' metadata and the heights given (NaN when they give none).
    height_check : str
        With ``sfm``: the heights given or assumed that disagree with the measured ones (over
        10 %, or 2 m for an elevation), in words; empty when they agree.
    n_left_out : int
        With ``sfm``: photos the SfM did not register (a failed submodel, a lost strip), whose
        footprints from their own GPS and attitude are the layer ``left_out``.
    area_left_out_m2 : float
        The ground only those photos saw (no registered photo's footprint covers it), m²: the
        products cannot show it.
    area_seen_m2 : float
        The ground every photo saw together, m² (registered and left out).
    """

    output: Path
    crs: str
    n_photos: int
    n_skipped: int
    median_gsd_cm: float
    overlap: Path | None
    height_source: str
    vertical_datum: str = ""
    notes: tuple[str, ...] = ()
    altitude_m: float = math.nan
    altitude_metadata_m: float = math.nan
    height_check: str = ""
    n_left_out: int = 0
    area_left_out_m2: float = 0.0
    area_seen_m2: float = math.nan


def footprints(
    images: Path,
    output: Path,
    dsm: Path | None = None,
    ground_elevation_m: float | None = None,
    takeoff_elevation_m: float | None = None,
    crs: CRS | None = None,
    sensor_width_mm: float | None = None,
    max_range_m: float = 500.0,
    overlap: Path | None = None,
    overlap_cell_m: float = 1.0,
    flight_height_m: float | None = None,
    gps_altitude: GpsAltitude = "auto",
    sfm: Path | None = None,
    *,
    feedback: Feedback | None = None,
) -> FootprintResult:
    """Footprint polygon, GSD and attitude of every photo, on flat ground or a DSM.

    Writes one polygon per photo (layer ``footprints``: image, gsd_cm at the
    image centre, gsd_min_cm, gsd_max_cm, altitude_m above ground, pitch_deg,
    yaw_deg, roll_deg, area_m2, clipped, height_source) and the camera
    positions (layer ``cameras``). Photos without GPS, unreadable files and
    unknown cameras are reported and skipped.

    Parameters
    ----------
    images : Path
        Folder of photos (JPEG/TIFF with EXIF GPS; DJI XMP used when present).
    output : Path
        Vector file to write (GeoPackage, or any OGR format by extension).
    dsm : Path
        DSM or DTM raster: every border ray is intersected with it.
    ground_elevation_m : float
        Level ground at this elevation (same datum as the photos' altitudes),
        when there is no DSM.
    takeoff_elevation_m : float
        Ground elevation of the take-off point, in the vertical datum of the ground
        model (the DSM, the ground elevation or the GCPs). Default: worked out from the
        photos (absolute − relative altitude, checked against the
        ground model; else the ground under the flight), and said.
    crs : CRS
        CRS of the output (EPSG code, WKT, PROJ string). Default: the photos'
        UTM zone.
    sensor_width_mm : float
        Sensor width for cameras missing from the database and the EXIF.
    max_range_m : float
        Rays at or above the horizon, or longer than this, are clipped here.
    overlap : Path
        Also write a raster of how many photos see each ground cell.
    overlap_cell_m : float
        Cell size of the overlap raster, metres.
    flight_height_m : float
        Flight height above the take-off ground: use it instead of the photos'
        altitudes (for cameras that write only a sea-level GPS altitude).
    gps_altitude : str
        What GPSAltitude holds when the photos have no RelativeAltitude: auto
        (decided from the photo spacing and the ground, and said), above-takeoff,
        orthometric or ellipsoidal.
    sfm : Path
        Output folder of the sfm algorithm: the registered photos' measured poses and
        calibrated cameras are cast (on the DSM, else on the tie points' ground), and the
        heights the metadata and the options give are checked against them.
    """
    fb = as_feedback(feedback)
    if dsm is not None and ground_elevation_m is not None and sfm is None:
        raise InputError("give either a DSM or a ground elevation, not both")
    if sfm is not None:
        given = Heights(flight_height_m, takeoff_elevation_m, ground_elevation_m, gps_altitude)
        return _footprints_from_sfm(
            images, output, Path(sfm), dsm, given, crs, sensor_width_mm, max_range_m, overlap, overlap_cell_m, fb
        )

    s_read, s_cast, s_write = split(fb, [3, 2, 1])
    photos = photos_with_altitude(images, sensor_width_mm, flight_height_m, s_read, fb)
    work = working_crs(photos.photos, crs)
    surface: Surface | None = None
    if dsm is not None:
        surface = dsm_under(dsm, photos.photos, work, takeoff_elevation_m, flight_height_m, gps_altitude, max_range_m)
        if surface.decimated:
            fb.info(f"DSM read at {surface.cell_m:.2g} m cells (at most {DSM_MAX_CELLS:,} under the flight)")
    elif ground_elevation_m is not None:
        surface = FlatSurface(float(ground_elevation_m))
    cams, heights = photo_cameras(
        photos.photos, work, surface, takeoff_elevation_m, flight_height_m=flight_height_m, gps_altitude=gps_altitude
    )
    ground = (
        "DSM" if dsm is not None else ("ground elevation" if ground_elevation_m is not None else "flat take-off ground")
    )
    fb.info(f"heights: {ground}; {heights.method}; vertical datum: {heights.datum}")
    for note in heights.notes:
        fb.warning(note)
    s_read.progress(1.0)
    table = compute_footprints(cams, heights.surface, max_range_m=max_range_m)
    s_cast.progress(1.0)
    if table.outside.any():
        fb.warning(
            f"{int(table.outside.sum())} footprint(s) reach beyond the DSM: there the ground is a plane at "
            "the nearby ground height of the DSM (column outside_dsm)"
        )
    fp, cam_layer = layers_of_footprints(cams, table, heights, ground, work)
    overlap_path = write_layers(output, fp, cam_layer, work, crs, overlap, overlap_cell_m)
    s_write.progress(1.0)
    return _written(
        output, crs or work, cams, photos, table, overlap_path, fb,
        f"{int(table.clipped.sum())} clipped",
        height_source=f"{ground}; {heights.method}",
        vertical_datum=heights.datum,
        notes=tuple(heights.notes),
        altitude_m=finite_median(table.altitude_m),
        altitude_metadata_m=finite_median(table.altitude_m),
    )  # fmt: skip


def _written(
    output: Path,
    crs: CRS,
    cams: Sequence[PhotoCamera],
    photos: PhotoSet,
    table: FootprintTable,
    overlap: Path | None,
    fb: Feedback,
    said: str,
    **figures: Any,
) -> FootprintResult:
    """The result of footprints written, said in one line (``said``: what this way adds)."""
    median_gsd_cm = float(np.nanmedian(table.gsd_m * 100))
    fb.info(f"{len(cams)} footprints, median GSD {median_gsd_cm:.2f} cm, {said}; {photos.summary()}")
    return FootprintResult(
        Path(output), crs_to_text(crs), len(cams), len(photos.skipped), median_gsd_cm, overlap, **figures
    )


def _footprints_from_sfm(
    images: Path,
    output: Path,
    sfm: Path,
    dsm: Path | None,
    given: Heights,
    out_crs: CRS | None,
    sensor_width_mm: float | None,
    max_range_m: float,
    overlap: Path | None,
    overlap_cell_m: float,
    fb: Feedback,
) -> FootprintResult:
    """Footprints of the SfM's registered cameras (measured poses, calibrated intrinsics) on the
    DSM, and the metadata's heights checked against them."""

    s_read, s_cast, s_write = split(fb, [3, 2, 1])
    photos = read_photos(images, sensor_width_mm, feedback=s_read)
    sfm_cams, work, tie_points, _ = cameras_from_sfm(sfm, images)
    by_name = {p.image: p for p in photos.photos}
    sfm_cams = [c for c in sfm_cams if c.name in by_name]
    if not sfm_cams:
        raise InputError("no photo of this folder is registered in the SfM model", path=sfm)
    registered = {c.name for c in sfm_cams}
    unregistered = [p.image for p in photos.photos if p.image not in registered]
    photos.skipped.extend((name, "not registered by the SfM") for name in unregistered)
    warn_grouped(fb, "no footprint: not registered by the SfM", unregistered)
    centres = np.array([c.pose.center for c in sfm_cams])
    surface, ground = ground_under_sfm(dsm, work, centres, max_range_m, tie_points, fb)
    cams = sfm_photo_cameras(sfm_cams, by_name, work)
    s_read.progress(1.0)
    table = compute_footprints(cams, surface, max_range_m=max_range_m)
    s_cast.progress(1.0)
    altitude_m = finite_median(table.altitude_m)
    check = check_given_heights([by_name[c.name] for c in sfm_cams], cams, table, work, surface, given, fb)
    datum = "the SfM model's (its GCPs', else its GPS heights')"
    heights = HeightModel(
        np.array([c.pose.center[2] for c in cams]), ("SfM pose",) * len(cams), "SfM poses", datum, math.nan, surface
    )
    fp, cam_layer = layers_of_footprints(cams, table, heights, ground, work)
    fp["altitude_metadata_m"] = check.per_photo_m
    left = _left_out([by_name[n] for n in unregistered], sfm, cams, table, fp.geometry.values, work, max_range_m, fb)
    extra = {"left_out": left.layer} if left.layer is not None else {}
    overlap_path = write_layers(output, fp, cam_layer, work, out_crs, overlap, overlap_cell_m, extra)
    s_write.progress(1.0)
    return _written(
        output, out_crs or work, cams, photos, table, overlap_path, fb,
        f"the SfM cameras' on the {ground}, {altitude_m:.1f} m above it",
        height_source=f"{ground}; SfM poses (measured)",
        vertical_datum=datum,
        notes=check.notes,
        altitude_m=altitude_m,
        altitude_metadata_m=check.altitude_m,
        height_check=check.problem,
        n_left_out=len(unregistered),
        area_left_out_m2=left.area_m2,
        area_seen_m2=left.seen_m2,
    )  # fmt: skip


@dataclass(frozen=True)
class _LeftOut:
    layer: Any  # GeoDataFrame of the left-out photos' footprints (None: none left out)
    area_m2: float  # ground only they saw
    seen_m2: float  # ground all the photos saw


def _left_out(
    photos: Sequence[Photo],
    sfm: Path,
    cams: Sequence[PhotoCamera],
    table: FootprintTable,
    polygons: Any,
    work: CRS,
    max_range_m: float,
    fb: Feedback,
) -> _LeftOut:
    """Where the photos the SfM left out looked, from their own GPS and attitude at the measured
    flight's height above the measured ground (the median of the registered cameras': their own
    heights may be in another datum), and the ground that only they saw: never a silent hole."""
    import json

    import geopandas as gpd
    import shapely

    registered = shapely.union_all(polygons)  # the registered photos' footprints (``table``'s rings)
    seen_m2 = float(registered.area)
    placeable = [p for p in photos if math.isfinite(p.latitude_deg) and math.isfinite(p.longitude_deg)]
    if not placeable:
        return _LeftOut(None, 0.0, seen_m2)
    height_m = finite_median(table.altitude_m)
    ground_m = finite_median(np.array([c.pose.center[2] for c in cams]) - table.altitude_m)
    if not (math.isfinite(height_m) and math.isfinite(ground_m)):
        return _LeftOut(None, 0.0, seen_m2)
    lon, lat, xy = grid_positions(placeable, work)
    n = len(placeable)
    source = "GPS and attitude of the photo, at the SfM's median height above the ground"
    placed = posed_cameras(placeable, work, lon, lat, xy, np.full(n, ground_m + height_m), [source] * n)
    theirs = compute_footprints(placed, FlatSurface(ground_m), max_range_m=max_range_m)
    polys = shapely.make_valid(shapely.polygons(theirs.rings))
    only_theirs = shapely.difference(polys, registered)
    try:
        why = json.loads((Path(sfm) / "report.json").read_text()).get("unregistered") or {}
    except (OSError, ValueError):
        why = {}
    layer = gpd.GeoDataFrame(
        {
            "image": [p.image for p in placeable],
            "why": [
                str(why.get(p.image, "not registered by the SfM")) if isinstance(why, dict) else "" for p in placeable
            ],
            "area_m2": shapely.area(polys),
            "area_only_here_m2": shapely.area(only_theirs),
            "placed_by": [c.height_source for c in placed],
        },
        geometry=polys,
        crs=work,
    )
    union = shapely.union_all(polys)
    area_m2 = float(shapely.difference(union, registered).area)
    seen_m2 = float(shapely.union(union, registered).area)
    if area_m2 > 0.0:
        fb.warning(
            f"{len(placeable)} photos left out by the SfM saw {area_m2:,.0f} m² that no registered photo saw "
            f"({100 * area_m2 / seen_m2:.1f} % of the ground seen): the products do not show it (footprints "
            "layer left_out)"
        )
    return _LeftOut(layer, area_m2, seen_m2)


def photos_with_altitude(
    images: Path, sensor_width_mm: float | None, flight_height_m: float | None, progress: Feedback, fb: Feedback
) -> PhotoSet:
    """The readable photos with an altitude (any photo when the flight height is given); the rest skipped."""
    photos = read_photos(images, sensor_width_mm, feedback=progress)
    if not photos.photos:
        raise InputError(f"no usable photo ({photos.summary()})", path=images)
    usable = [p for p in photos.photos if p.has_altitude or flight_height_m is not None]
    lacking = [p.image for p in photos.photos if p not in usable]
    for name in lacking:
        photos.skipped.append((name, "no altitude (RelativeAltitude, AbsoluteAltitude or GPSAltitude)"))
    warn_grouped(fb, "skipped: no altitude in the metadata", lacking)
    photos.photos = usable
    if not usable:
        raise InputError(f"no usable photo ({photos.summary()}); give flight_height_m", path=images)
    return photos
