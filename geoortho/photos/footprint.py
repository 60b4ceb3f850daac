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
"""

from __future__ import annotations

import math
import os
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from pyproj import CRS

from geoortho.core.camera import Intrinsics, Pose, PosedCamera, rotation_from_ypr, undistort_pixels, ypr_from_rotation
from geoortho.core.crs import WGS84, crs_to_text, grid_north, transformer, utm_crs_for
from geoortho.core.gsd import ray_gsd_m
from geoortho.core.outputs import write_cog, write_vector
from geoortho.core.sfm_model import cameras_from_sfm
from geoortho.core.styles import overlap as overlap_style
from geoortho.core.styles import product_styles, write_raster_style
from geoortho.core.surface import FlatSurface, GridSurface, Surface, read_surface
from geoortho.errors import InputError
from geoortho.feedback import Feedback, as_feedback, split, warn_grouped
from geoortho.photos.heights import GpsAltitude, HeightModel, resolve_heights
from geoortho.photos.metadata import Photo, PhotoSet, read_photos

__all__ = [
    "PhotoCamera",
    "FootprintResult",
    "photo_cameras",
    "compute_footprints",
    "footprints",
    "working_crs",
]


@dataclass(frozen=True, eq=False, kw_only=True)
class PhotoCamera(PosedCamera):
    """A photo placed in the world from its metadata (or the SfM): the posed camera, the photo it
    took and how its height was found."""

    photo: Photo
    height_source: str
    # Meridian convergence applied to the yaw (grid azimuth of true north, degrees) and the CRS's
    # point scale (grid metres per ground metre) at the photo: crs.grid_north.
    grid_convergence_deg: float = 0.0
    grid_scale: float = 1.0

    @classmethod
    def of(
        cls, photo: Photo, pose: Pose, height_source: str, convergence_deg: float = 0.0, scale: float = 1.0
    ) -> PhotoCamera:
        return cls(
            photo.intrinsics(),
            pose,
            photo.image,
            photo.path,
            photo=photo,
            height_source=height_source,
            grid_convergence_deg=convergence_deg,
            grid_scale=scale,
        )


#: Cells of the DSM read under a flight (64 MB of float32): footprints need the ground's shape,
#: not every 5 cm cell of it.
DSM_MAX_CELLS = 16_000_000


def _dsm_under(
    dsm: Path,
    photos: Sequence[Photo],
    crs: CRS,
    takeoff_elevation_m: float | None,
    flight_height_m: float | None,
    gps_altitude: GpsAltitude,
    max_range_m: float,
) -> GridSurface:
    """Only the DSM the footprints need (a county's DSM for one flight is not read whole): the
    footprints on a coarse read of the flight's area out to the longest ray say where, then
    that window (and a margin) is read at full resolution, up to DSM_MAX_CELLS."""
    reach = _flight_bounds(photos, crs, max_range_m)
    coarse = read_surface(dsm, crs, extend=True, bounds=reach, max_cells=COARSE_DSM_CELLS)
    cams, heights = photo_cameras(
        photos, crs, coarse, takeoff_elevation_m, flight_height_m=flight_height_m, gps_altitude=gps_altitude
    )
    rings = compute_footprints(cams, heights.surface, per_side=4, max_range_m=max_range_m).rings.reshape(-1, 2)
    ok = np.isfinite(rings).all(axis=1)
    if not ok.any():
        return read_surface(dsm, crs, extend=True, bounds=reach, max_cells=DSM_MAX_CELLS)
    (x0, y0), (x1, y1) = rings[ok].min(axis=0), rings[ok].max(axis=0)
    # the coarse ground is within a coarse cell or two of the fine one: a margin of several
    margin = 0.05 * max(x1 - x0, y1 - y0) + 8 * coarse.cell_m
    bounds = (float(x0 - margin), float(y0 - margin), float(x1 + margin), float(y1 + margin))
    return read_surface(dsm, crs, extend=True, bounds=bounds, max_cells=DSM_MAX_CELLS)


#: Cells of the first, coarse read of the DSM under a flight (it only says where to read).
COARSE_DSM_CELLS = 1_000_000


def _flight_bounds(photos: Sequence[Photo], crs: CRS, reach_m: float) -> tuple[float, float, float, float]:
    """The photos' positions in ``crs`` (metres), widened by the longest ray."""
    from pyproj import Transformer

    t = Transformer.from_crs("EPSG:4326", crs, always_xy=True)
    lonlat = np.array([[p.longitude_deg, p.latitude_deg] for p in photos if p.has_gps])
    x, y = t.transform(lonlat[:, 0], lonlat[:, 1])
    return _box_around(np.asarray(x), np.asarray(y), reach_m)


def _box_around(x: np.ndarray, y: np.ndarray, reach_m: float) -> tuple[float, float, float, float]:
    """The bounding box of the points (x, y), widened by ``reach_m`` on every side."""
    return float(x.min() - reach_m), float(y.min() - reach_m), float(x.max() + reach_m), float(y.max() + reach_m)


def working_crs(photos: Sequence[Photo], crs: CRS | None = None) -> CRS:
    """The CRS to compute in: ``crs`` if projected, else the photos' UTM zone."""
    if crs is not None and crs.is_projected:
        return crs
    lonlat = np.array([[p.longitude_deg, p.latitude_deg] for p in photos if p.has_gps])
    if lonlat.size == 0:
        raise InputError("no photo with a GPS position")
    lon, lat = np.median(lonlat, axis=0)
    return utm_crs_for(float(lon), float(lat))


def photo_cameras(
    photos: Sequence[Photo],
    crs: CRS,
    surface: Surface | None = None,
    takeoff_elevation_m: float | None = None,
    *,
    flight_height_m: float | None = None,
    gps_altitude: GpsAltitude = "auto",
    gnss_takeoff: bool = False,
    ground_label: str = "",
) -> tuple[list[PhotoCamera], HeightModel]:
    """Place every photo in ``crs``: position from GPS, height from :func:`geoortho.photos.heights.resolve_heights`,
    rotation from the attitude. Returns the cameras and the flight's height model (its ``surface``
    is the ground used: ``surface``, or flat ground at the take-off)."""
    lon, lat, xy = _grid_positions(photos, crs)
    heights = resolve_heights(
        photos,
        xy,
        np.c_[lon, lat],
        surface,
        takeoff_elevation_m=takeoff_elevation_m,
        flight_height_m=flight_height_m,
        gps_altitude=gps_altitude,
        gnss_takeoff=gnss_takeoff,
        ground_label=ground_label,
    )
    return _posed(photos, crs, lon, lat, xy, heights.z_m, heights.sources), heights


def _grid_positions(photos: Sequence[Photo], crs: CRS) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The photos' GPS longitudes, latitudes and positions in ``crs`` ((N, 2))."""
    lon = np.array([p.longitude_deg for p in photos], float)
    lat = np.array([p.latitude_deg for p in photos], float)
    x, y = transformer(WGS84, crs).transform(lon, lat)
    return lon, lat, np.c_[x, y]


def _posed(
    photos: Sequence[Photo],
    crs: CRS,
    lon: np.ndarray,
    lat: np.ndarray,
    xy: np.ndarray,
    z_m: np.ndarray,
    sources: Sequence[str],
) -> list[PhotoCamera]:
    """The photos as cameras at ``xy`` and ``z_m``, turned by their recorded attitude."""
    # Yaw is from true north; the CRS's grid north differs by the meridian convergence (1.9° at
    # a UTM zone edge at 40° N, 0.7° between UTM 29N and PT-TM06 in Lisbon).
    convergence, scale = grid_north(crs, lon, lat)
    return [
        PhotoCamera.of(
            p,
            Pose(
                np.array([xy[i, 0], xy[i, 1], z_m[i]]),
                rotation_from_ypr(p.yaw_deg + convergence[i], p.pitch_deg, p.roll_deg),
            ),
            sources[i],
            float(convergence[i]),
            float(scale[i]),
        )
        for i, p in enumerate(photos)
    ]


@dataclass(frozen=True)
class FootprintTable:
    """Footprints as arrays, one row per camera."""

    rings: np.ndarray  # (N, M, 2) border vertices in the world CRS
    clipped: np.ndarray  # (N,) some ray met nothing within max range
    gsd_m: np.ndarray  # (N,) at the image centre: metres inside; centimetres in the layers users read
    gsd_min_m: np.ndarray
    gsd_max_m: np.ndarray
    altitude_m: np.ndarray  # camera above the ground under it
    outside: np.ndarray  # (N,) some ray landed beyond the DSM, on the plane that continues it


def _border_and_centre(intr: Intrinsics, per_side: int) -> np.ndarray:
    return np.vstack([intr.border_pixels(per_side), [[intr.cx_px, intr.cy_px]]])


def compute_footprints(
    cams: Sequence[PosedCamera], surface: Surface, *, per_side: int = 16, max_range_m: float = 500.0
) -> FootprintTable:
    """Cast each camera's border (``per_side`` points per edge) and centre onto ``surface``.

    Vectorised over all cameras: cameras sharing intrinsics share their
    camera-frame ray bundle, rotated into the world by one matrix product.
    """
    n = len(cams)
    m = 4 * per_side
    origins = np.array([c.pose.center for c in cams]).reshape(n, 3)
    rots = np.array([c.pose.rotation for c in cams]).reshape(n, 3, 3)
    dirs = np.empty((n, m + 1, 3))
    cos_theta = np.empty((n, m + 1))
    focal = np.empty(n)
    groups: dict[Intrinsics, list[int]] = {}
    for i, c in enumerate(cams):
        groups.setdefault(c.intrinsics, []).append(i)
    for intr, idx in groups.items():
        xn = undistort_pixels(_border_and_centre(intr, per_side), intr)
        cam_dirs = np.c_[xn, np.ones(len(xn))]
        cam_dirs /= np.linalg.norm(cam_dirs, axis=1, keepdims=True)
        ii = np.asarray(idx)
        dirs[ii] = np.einsum("nij,mj->nmi", rots[ii], cam_dirs)
        cos_theta[ii] = cam_dirs[:, 2]
        focal[ii] = intr.focal_px
    flat_o = np.repeat(origins, m + 1, axis=0)
    flat_d = dirs.reshape(-1, 3)
    hits = surface.intersect(flat_o, flat_d, max_range_m=max_range_m)
    pts = hits.points.reshape(n, m + 1, 3)
    # Rays are cast in ground metres; the CRS's grid is k times larger horizontally (UTM: 0.9996
    # to 1.001), so the footprint's offsets from the camera are scaled into grid units.
    k = np.array([getattr(c, "grid_scale", 1.0) for c in cams], float)
    if np.any(k != 1.0):
        pts[..., :2] = origins[:, None, :2] + k[:, None, None] * (pts[..., :2] - origins[:, None, :2])
    hit = hits.hit.reshape(n, m + 1)
    rng = hits.range_m.reshape(n, m + 1)
    # GSD as the side of the ground area one pixel covers (level ground locally):
    # range · sqrt(cos³θ / cos i) / f, θ off the optical axis, i the incidence angle.
    cos_inc = np.abs(dirs[..., 2])
    with np.errstate(divide="ignore", invalid="ignore"):
        gsd_m = ray_gsd_m(rng, cos_theta, cos_inc, focal[:, None])
    gsd_m = np.where(hit, gsd_m, np.nan)
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN rows: nothing hit
        ground_z = surface.elevation(origins[:, 0], origins[:, 1])
        under = np.nanmedian(np.where(hit, pts[..., 2], np.nan), axis=1)
        ground_z = np.where(np.isnan(ground_z), under, ground_z)
        gmin = np.nanmin(gsd_m, axis=1)
        gmax = np.nanmax(gsd_m, axis=1)
    return FootprintTable(
        rings=pts[:, :m, :2],
        clipped=np.asarray(~hit[:, :m].all(axis=1)),
        gsd_m=gsd_m[:, m],
        gsd_min_m=gmin,
        gsd_max_m=gmax,
        altitude_m=origins[:, 2] - ground_z,
        outside=np.asarray(
            hits.extended.reshape(n, m + 1).any(axis=1) if hits.extended is not None else np.zeros(n, bool)
        ),
    )


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
        surface = _dsm_under(dsm, photos.photos, work, takeoff_elevation_m, flight_height_m, gps_altitude, max_range_m)
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
    fp, cam_layer = _footprint_layers(cams, table, heights, ground, work)
    overlap_path = _write_layers(output, fp, cam_layer, work, crs, overlap, overlap_cell_m)
    s_write.progress(1.0)
    median_gsd = float(np.nanmedian(table.gsd_m * 100))
    fb.info(
        f"{len(cams)} footprints, median GSD {median_gsd:.2f} cm, {int(table.clipped.sum())} clipped; "
        f"{photos.summary()}"
    )
    return FootprintResult(
        Path(output),
        crs_to_text(crs or work),
        len(cams),
        len(photos.skipped),
        median_gsd,
        overlap_path,
        f"{ground}; {heights.method}",
        heights.datum,
        tuple(heights.notes),
        altitude_m=_median(table.altitude_m),
        altitude_metadata_m=_median(table.altitude_m),
    )


def _write_layers(
    output: Path,
    fp: Any,
    cam_layer: Any,
    work: CRS,
    out_crs: CRS | None,
    overlap: Path | None,
    cell_m: float,
    extra: dict[str, Any] | None = None,
) -> Path | None:
    """The overlap raster (in the working CRS), then the layers in the output CRS; the overlap's path."""

    overlap_path = write_overlap(overlap, fp.geometry.values, work, cell_m) if overlap is not None else None
    layers = {"footprints": fp, "cameras": cam_layer, **(extra or {})}
    if out_crs is not None and not out_crs.equals(work):
        layers = {name: layer.to_crs(out_crs) for name, layer in layers.items()}
    write_vector(output, layers, styles=product_styles(*layers))
    return overlap_path


def _median(values: np.ndarray) -> float:
    ok = np.isfinite(values)
    return float(np.median(values[ok])) if ok.any() else math.nan


#: A height given or read that differs from the measured one by more than this share (of the
#: height above ground), or an elevation by more than ELEVATION_TOLERANCE_M, is called wrong.
HEIGHT_TOLERANCE = 0.10
ELEVATION_TOLERANCE_M = 2.0
#: Heights read from the photos alone (a take-off from GNSS heights) err by metres: on a low
#: flight 10 % is within that, so they are called wrong only past this as well.
ASSUMED_ALLOWANCE_M = 5.0


@dataclass(frozen=True)
class Heights:
    """The height options a user gave (None: not given)."""

    flight_height_m: float | None = None
    takeoff_elevation_m: float | None = None
    ground_elevation_m: float | None = None
    gps_altitude: GpsAltitude = "auto"


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
    surface, ground = _ground_under_sfm(dsm, work, centres, max_range_m, tie_points, fb)
    cams = _sfm_photo_cameras(sfm_cams, by_name, work)
    s_read.progress(1.0)
    table = compute_footprints(cams, surface, max_range_m=max_range_m)
    s_cast.progress(1.0)
    altitude_m = _median(table.altitude_m)
    check = check_given_heights([by_name[c.name] for c in sfm_cams], cams, table, work, surface, given, fb)
    datum = "the SfM model's (its GCPs', else its GPS heights')"
    heights = HeightModel(
        np.array([c.pose.center[2] for c in cams]), ("SfM pose",) * len(cams), "SfM poses", datum, math.nan, surface
    )
    fp, cam_layer = _footprint_layers(cams, table, heights, ground, work)
    fp["altitude_metadata_m"] = check.per_photo_m
    left = _left_out([by_name[n] for n in unregistered], sfm, cams, table, fp.geometry.values, work, max_range_m, fb)
    extra = {"left_out": left.layer} if left.layer is not None else {}
    overlap_path = _write_layers(output, fp, cam_layer, work, out_crs, overlap, overlap_cell_m, extra)
    s_write.progress(1.0)
    median_gsd = float(np.nanmedian(table.gsd_m * 100))
    fb.info(
        f"{len(cams)} footprints of the SfM cameras on the {ground}, median GSD {median_gsd:.2f} cm, "
        f"{altitude_m:.1f} m above the ground; {photos.summary()}"
    )
    return FootprintResult(
        Path(output),
        crs_to_text(out_crs or work),
        len(cams),
        len(photos.skipped),
        median_gsd,
        overlap_path,
        f"{ground}; SfM poses (measured)",
        datum,
        check.notes,
        altitude_m=altitude_m,
        altitude_metadata_m=check.altitude_m,
        height_check=check.problem,
        n_left_out=len(unregistered),
        area_left_out_m2=left.area_m2,
        area_seen_m2=left.seen_m2,
    )


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
    height_m = _median(table.altitude_m)
    ground_m = _median(np.array([c.pose.center[2] for c in cams]) - table.altitude_m)
    if not (math.isfinite(height_m) and math.isfinite(ground_m)):
        return _LeftOut(None, 0.0, seen_m2)
    lon, lat, xy = _grid_positions(placeable, work)
    n = len(placeable)
    source = "GPS and attitude of the photo, at the SfM's median height above the ground"
    placed = _posed(placeable, work, lon, lat, xy, np.full(n, ground_m + height_m), [source] * n)
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


@dataclass(frozen=True)
class HeightCheck:
    """The metadata's heights against the measured ones."""

    altitude_m: float  # median height above ground from the metadata (NaN: none to be had)
    per_photo_m: np.ndarray  # the same per photo
    problem: str  # the disagreement, in words ("" when they agree)
    notes: tuple[str, ...]


def _ground_under_sfm(
    dsm: Path | None, work: CRS, centres: np.ndarray, reach_m: float, tie_points: np.ndarray, fb: Feedback
) -> tuple[Surface, str]:
    """The ground the SfM cameras' footprints are cast on, and its name: the DSM (moved onto the
    tie points when it lies in another vertical datum), else the tie points' ground level."""
    from dataclasses import replace

    if dsm is None:
        # no surface given: the tie points' ground level (below roofs and trees)
        z = tie_points[:, 2] if len(tie_points) else np.array([0.0])
        return FlatSurface(float(np.percentile(z, 30))), "the SfM tie points' ground level"
    box = _box_around(centres[:, 0], centres[:, 1], reach_m)
    grid = read_surface(dsm, work, extend=True, bounds=box, max_cells=DSM_MAX_CELLS)
    surface: Surface = grid
    ground = "DSM"
    # A DSM in another vertical datum than the SfM (a lidar DSM, a model on drifting GPS
    # heights): the cameras' height over it would be off by the difference. The tie points
    # measure it; past ELEVATION_TOLERANCE_M the DSM is moved onto the SfM, and that is said.
    if len(tie_points):
        with np.errstate(invalid="ignore"):
            under = np.asarray(surface.elevation(tie_points[:, 0], tie_points[:, 1]), float)
        offset = _median(tie_points[:, 2] - under)
        if math.isfinite(offset) and abs(offset) > ELEVATION_TOLERANCE_M:
            surface = replace(grid, grid=grid.grid + np.float32(offset))
            ground = f"DSM moved {offset:+.1f} m onto the SfM's tie points"
            fb.warning(
                f"the DSM lies {-offset:+.1f} m off the SfM's tie points (another vertical datum?): the heights "
                "above ground are measured on it moved onto the SfM"
            )
    return surface, ground


def _sfm_photo_cameras(sfm_cams: Sequence[Any], by_name: dict[str, Photo], work: CRS) -> list[PhotoCamera]:
    """The SfM's cameras as photo cameras: measured pose and intrinsics, the photo's attitude
    replaced by the pose's (its yaw from grid north to true north)."""
    from dataclasses import replace

    lon = np.array([by_name[c.name].longitude_deg for c in sfm_cams], float)
    lat = np.array([by_name[c.name].latitude_deg for c in sfm_cams], float)
    convergence, _ = grid_north(work, lon, lat)
    cams = []
    for c, conv in zip(sfm_cams, np.nan_to_num(convergence)):
        yaw, pitch, roll = ypr_from_rotation(c.pose.rotation)
        photo = replace(
            by_name[c.name], yaw_deg=yaw - float(conv), pitch_deg=pitch, roll_deg=roll, attitude_source="SfM"
        )
        cams.append(
            PhotoCamera(
                c.intrinsics,
                c.pose,
                c.name,
                c.path,
                photo=photo,
                height_source="SfM pose",
                grid_convergence_deg=float(conv),
            )
        )
    return cams


def check_given_heights(
    photos: Sequence[Photo],
    measured: Sequence[PhotoCamera],
    table: FootprintTable,
    crs: CRS,
    surface: Surface,
    given: Heights,
    fb: Feedback,
) -> HeightCheck:
    """Place the photos as their metadata and ``given`` would, on the measured surface, and
    compare the cameras' heights with the measured ones. A disagreement over HEIGHT_TOLERANCE (or
    ELEVATION_TOLERANCE_M for an elevation given; for heights read from the photos alone, also
    over ASSUMED_ALLOWANCE_M) is warned about, naming the option to fix."""
    n = len(photos)
    nothing = np.full(n, np.nan)
    measured_alt = _median(table.altitude_m)
    with_alt = [i for i, p in enumerate(photos) if p.has_altitude or given.flight_height_m is not None]
    if not with_alt:
        note = f"no altitude in the photos' metadata: heights measured by the SfM ({measured_alt:.1f} m above ground)"
        fb.info(note)
        return HeightCheck(math.nan, nothing, "", (note,))
    try:
        meta, model = photo_cameras(
            [photos[i] for i in with_alt],
            crs,
            surface if given.ground_elevation_m is None else FlatSurface(float(given.ground_elevation_m)),
            given.takeoff_elevation_m,
            flight_height_m=given.flight_height_m,
            gps_altitude=given.gps_altitude,
        )
    except InputError as e:
        note = (
            f"the photos' altitudes give no height above ground ({' '.join(str(e).split())}); "
            f"heights measured by the SfM: {measured_alt:.1f} m above the ground"
        )
        fb.info(note)
        return HeightCheck(math.nan, nothing, "", (note,))
    idx = np.asarray(with_alt)
    z_meta = np.array([c.pose.center[2] for c in meta])
    xy_meta = np.array([c.pose.center[:2] for c in meta])
    with np.errstate(invalid="ignore"):
        ground_meta = np.asarray(surface.elevation(xy_meta[:, 0], xy_meta[:, 1]), float)
    per_photo = nothing.copy()
    per_photo[idx] = z_meta - ground_meta
    z_sfm = np.array([measured[i].pose.center[2] for i in idx])
    offset_m = _median(z_meta - z_sfm)  # + : the metadata puts the cameras higher than measured
    meta_alt = _median(per_photo)
    notes = [
        f"camera heights: metadata {model.method}: {meta_alt:.1f} m above the ground; measured {measured_alt:.1f} m"
    ]
    problem = ""
    share = offset_m / measured_alt if measured_alt > 0 else math.nan
    if given.flight_height_m is not None and abs(share) > HEIGHT_TOLERANCE:
        problem = (
            f"flight_height_m {given.flight_height_m:g} m disagrees with the SfM: the cameras flew "
            f"{measured_alt:.1f} m above the ground, not {meta_alt:.1f} m ({share:+.0%}); the products use the "
            "measured heights: check flight_height_m"
        )
    elif given.takeoff_elevation_m is not None and abs(offset_m) > ELEVATION_TOLERANCE_M:
        problem = (
            f"takeoff_elevation_m {given.takeoff_elevation_m:g} m disagrees with the SfM by {offset_m:+.1f} m "
            f"(the cameras' measured elevations put the take-off at {given.takeoff_elevation_m - offset_m:.1f} m); "
            "the products use the measured heights: check takeoff_elevation_m and its datum"
        )
    elif given.ground_elevation_m is not None:
        off = float(given.ground_elevation_m) - _median(ground_meta)
        if abs(off) > ELEVATION_TOLERANCE_M:
            problem = (
                f"ground_elevation_m {given.ground_elevation_m:g} m disagrees with the measured surface by "
                f"{off:+.1f} m (its median under the cameras: {_median(ground_meta):.1f} m); the products use the "
                "measured surface: check ground_elevation_m and its datum"
            )
    elif abs(share) > HEIGHT_TOLERANCE and abs(offset_m) > ASSUMED_ALLOWANCE_M:
        problem = (
            f"the photos' altitudes ({model.method}) put the cameras {meta_alt:.1f} m above the ground; the SfM "
            f"measured {measured_alt:.1f} m ({share:+.0%}); the products use the measured heights"
        )
    if problem:
        fb.warning(problem)
        notes.append(problem)
    else:
        fb.info(notes[0])
    return HeightCheck(meta_alt, per_photo, problem, tuple(notes))


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


def _with_ground(ground: str, source: str) -> str:
    """A photo's height source naming its ground once: the heights' own sources often end with it."""
    return source if ground in source else f"{ground}; {source}"


def _footprint_layers(
    cams: Sequence[PhotoCamera], table: FootprintTable, heights: HeightModel, ground: str, work: CRS
) -> tuple[Any, Any]:
    """The footprints layer (one polygon and its figures per photo) and the cameras layer."""
    import geopandas as gpd
    import shapely

    polys = shapely.polygons(table.rings)
    bad = ~shapely.is_valid(polys)
    if bad.any():
        polys[bad] = shapely.make_valid(polys[bad])
    records = {
        "image": [c.photo.image for c in cams],
        "gsd_cm": table.gsd_m * 100,
        "gsd_min_cm": table.gsd_min_m * 100,
        "gsd_max_cm": table.gsd_max_m * 100,
        "altitude_m": table.altitude_m,
        "pitch_deg": [c.photo.pitch_deg for c in cams],
        "yaw_deg": [c.photo.yaw_deg for c in cams],
        "roll_deg": [c.photo.roll_deg for c in cams],
        "area_m2": shapely.area(polys),
        "clipped": table.clipped,
        "outside_dsm": table.outside,
        "height_source": [_with_ground(ground, c.height_source) for c in cams],
        "vertical_datum": [heights.datum] * len(cams),
        "attitude_source": [c.photo.attitude_source for c in cams],
        "grid_convergence_deg": [c.grid_convergence_deg for c in cams],
        "camera": [f"{c.photo.make} {c.photo.model}".strip() for c in cams],
        "focal_px": [c.intrinsics.focal_px for c in cams],
        "taken_at": [c.photo.taken_at for c in cams],
        "gps_fix": [c.photo.gps_fix for c in cams],
        "gps_sigma_h_m": [c.photo.gps_sigma_h_m for c in cams],
        "gps_sigma_v_m": [c.photo.gps_sigma_v_m for c in cams],
    }
    fp = gpd.GeoDataFrame(records, geometry=polys, crs=work)
    centers = np.array([c.pose.center for c in cams])
    cam_layer = gpd.GeoDataFrame(
        {
            "image": records["image"],
            "z_m": centers[:, 2],
            "latitude_deg": [c.photo.latitude_deg for c in cams],
            "longitude_deg": [c.photo.longitude_deg for c in cams],
            "relative_altitude_m": [c.photo.relative_altitude_m for c in cams],
            "yaw_deg": records["yaw_deg"],
            "pitch_deg": records["pitch_deg"],
            "roll_deg": records["roll_deg"],
            "gsd_cm": records["gsd_cm"],
            "gps_fix": records["gps_fix"],
            "gps_sigma_h_m": records["gps_sigma_h_m"],
            "gps_sigma_v_m": records["gps_sigma_v_m"],
        },
        geometry=shapely.points(centers[:, :2]),
        crs=work,
    )
    return fp, cam_layer


def write_overlap(path: str | os.PathLike[str], polygons: Sequence[Any], crs: CRS, cell_m: float) -> Path:
    """Raster of how many polygons cover each cell (uint16 COG, 0 = not covered is nodata)."""
    import shapely
    from rasterio.features import MergeAlg, rasterize
    from rasterio.transform import from_origin

    x0, y0, x1, y1 = shapely.total_bounds(np.asarray(polygons))
    x0, y0 = math.floor(x0 / cell_m) * cell_m, math.floor(y0 / cell_m) * cell_m
    cols, rows = int(math.ceil((x1 - x0) / cell_m)), int(math.ceil((y1 - y0) / cell_m))
    if cols * rows > 400_000_000:
        raise InputError(f"overlap raster of {cols}x{rows} cells is too large; raise overlap_cell_m")
    transform = from_origin(x0, y0 + rows * cell_m, cell_m, cell_m)
    # Vertices closer than half a cell change no cell: simplify first (rasterio reads every vertex
    # through __geo_interface__, the slow part for thousands of footprints).
    simple = shapely.simplify(np.asarray(polygons), cell_m / 2)
    count = rasterize(
        ((g, 1) for g in simple),
        out_shape=(rows, cols),
        transform=transform,
        merge_alg=MergeAlg.add,
        dtype="uint16",
        fill=0,
    )
    out = write_cog(path, count, transform=transform, crs=crs, nodata=0)
    write_raster_style(out, overlap_style(out))
    return out
