"""The photos as posed cameras from their metadata (the working CRS, the DSM read under the flight, each
photo's position, height and attitude made a :class:`PhotoCamera`), and their footprints cast on the
surface (:func:`compute_footprints`).
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from pyproj import CRS

from geoortho.core.camera import Intrinsics, Pose, PosedCamera, rotation_from_ypr, undistort_pixels
from geoortho.core.crs import WGS84, grid_north, transformer, utm_crs_for
from geoortho.core.gsd import ray_gsd_m
from geoortho.core.surface import GridSurface, Surface, read_surface
from geoortho.errors import InputError
from geoortho.photos.heights import GpsAltitude, HeightModel, resolve_heights
from geoortho.photos.metadata import Photo


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


def dsm_under(
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
    return box_around(np.asarray(x), np.asarray(y), reach_m)


def box_around(x: np.ndarray, y: np.ndarray, reach_m: float) -> tuple[float, float, float, float]:
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
    lon, lat, xy = grid_positions(photos, crs)
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
    return posed_cameras(photos, crs, lon, lat, xy, heights.z_m, heights.sources), heights


def grid_positions(photos: Sequence[Photo], crs: CRS) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The photos' GPS longitudes, latitudes and positions in ``crs`` ((N, 2))."""
    lon = np.array([p.longitude_deg for p in photos], float)
    lat = np.array([p.latitude_deg for p in photos], float)
    x, y = transformer(WGS84, crs).transform(lon, lat)
    return lon, lat, np.c_[x, y]


def posed_cameras(
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
