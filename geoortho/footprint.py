"""Photo footprints and GSD: each photo's image border cast onto flat ground or a DSM.

Every border ray is intersected with the surface (not only the point under the
drone), so footprints follow the terrain and oblique photos come out as the
trapezoids they are. Rays at or above the horizon, or longer than
``max_range_m``, are clipped at that range and the footprint is flagged.

Heights: the camera's elevation is the take-off elevation plus DJI's
RelativeAltitude (barometric, good to decimetres), in the datum of the ground
model. The take-off elevation is the user's ``takeoff_elevation_m`` when given;
otherwise the median of AbsoluteAltitude − RelativeAltitude over the flight
(consumer GNSS heights can be metres off: a known take-off is better); photos
without RelativeAltitude use their absolute altitude as is. Without any ground
model the ground is flat at the take-off elevation.
"""

from __future__ import annotations

import math
import os
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import numpy as np
from pyproj import CRS

from .camera import Intrinsics, Pose, project_points, rotation_from_ypr, undistort_pixels
from .crs import WGS84, crs_to_text, parse_crs, transformer, utm_crs_for
from .errors import InputError
from .feedback import Feedback, as_feedback, split
from .photos import Photo, read_photos
from .surface import FlatSurface, Surface, read_surface

__all__ = [
    "PhotoCamera",
    "FootprintResult",
    "photo_cameras",
    "compute_footprints",
    "footprints",
    "working_crs",
]


@dataclass(frozen=True, eq=False)
class PhotoCamera:
    """A photo placed in the world: intrinsics, pose (world CRS) and how its height was found."""

    photo: Photo
    intrinsics: Intrinsics
    pose: Pose
    height_source: str

    def project(self, points_xyz: np.ndarray) -> np.ndarray:
        """World points (N, 3) → pixel coordinates (N, 2), NaN behind the camera.

        Pixel (0, 0) is the centre of the top-left pixel (OpenDroneMap's gcp_list.txt).
        """
        px, _ = project_points(points_xyz, self.intrinsics, self.pose)
        return px


def working_crs(photos: Sequence[Photo], crs: CRS | str | None = None) -> CRS:
    """The CRS to compute in: ``crs`` if projected, else the photos' UTM zone."""
    if crs is not None:
        c = parse_crs(crs)
        if c.is_projected:
            return c
    lonlat = np.array([[p.longitude_deg, p.latitude_deg] for p in photos if p.has_gps])
    if lonlat.size == 0:
        raise InputError("no photo with a GPS position")
    lon, lat = np.median(lonlat, axis=0)
    return utm_crs_for(float(lon), float(lat))


def _absolute(p: Photo) -> float:
    return p.absolute_altitude_m if math.isfinite(p.absolute_altitude_m) else p.gps_altitude_m


def takeoff_elevation(photos: Sequence[Photo]) -> float:
    """Median of absolute − relative altitude: the take-off point in the GNSS height datum (NaN if none)."""
    d = [_absolute(p) - p.relative_altitude_m for p in photos
         if math.isfinite(_absolute(p)) and math.isfinite(p.relative_altitude_m)]
    return float(np.median(d)) if d else math.nan


def photo_cameras(
    photos: Sequence[Photo],
    crs: CRS,
    surface: Surface | None = None,
    takeoff_elevation_m: float | None = None,
) -> tuple[list[PhotoCamera], Surface, str]:
    """Place every photo in ``crs``: position from GPS, height per the module notes, rotation from
    the attitude. Returns the cameras, the ground surface used, and a note on the heights."""
    to_xy = transformer(WGS84, crs)
    lon = np.array([p.longitude_deg for p in photos], float)
    lat = np.array([p.latitude_deg for p in photos], float)
    x, y = to_xy.transform(lon, lat)
    # The flight's absolute−relative offset: the take-off in the GNSS height datum. It also turns
    # an absolute altitude into a relative one for photos that lack RelativeAltitude (XMP
    # stripped by an editor).
    offset = takeoff_elevation(photos)
    if takeoff_elevation_m is not None and math.isfinite(takeoff_elevation_m):
        takeoff, how = float(takeoff_elevation_m), "take-off elevation given"
    elif surface is None:
        takeoff, how = 0.0, "flat ground at the take-off point"
    else:
        takeoff, how = offset, "take-off from absolute−relative altitude"
        if not math.isfinite(takeoff):
            takeoff = float(surface.elevation(np.array([x[0]]), np.array([y[0]]))[0])
            how = "take-off assumed at the ground under the first photo"
    if surface is None:
        surface = FlatSurface(takeoff)
    cams = []
    for i, p in enumerate(photos):
        if math.isfinite(p.relative_altitude_m):
            z, src = takeoff + p.relative_altitude_m, f"relative altitude; {how}"
        elif math.isfinite(_absolute(p)) and math.isfinite(offset):
            z, src = takeoff + _absolute(p) - offset, f"absolute altitude less the flight's offset; {how}"
        elif math.isfinite(_absolute(p)):
            if isinstance(surface, FlatSurface) and takeoff_elevation_m is None and how.startswith("flat"):
                # No relative altitude and no ground: the absolute altitude is all there is, taken
                # as height above the take-off (flagged: wrong if it is a true sea-level height).
                z, src = takeoff + _absolute(p), "absolute altitude taken as height above take-off"
            else:
                z, src = _absolute(p), "absolute altitude"
        else:
            raise InputError("no altitude in the metadata", path=p.path)
        rot = rotation_from_ypr(p.yaw_deg, p.pitch_deg, p.roll_deg)
        cams.append(PhotoCamera(p, p.intrinsics(), Pose(np.array([x[i], y[i], z]), rot), src))
    return cams, surface, how


@dataclass(frozen=True)
class FootprintTable:
    """Footprints as arrays, one row per camera."""

    rings: np.ndarray  # (N, M, 2) border vertices in the world CRS
    clipped: np.ndarray  # (N,) some ray met nothing within max range
    gsd_cm: np.ndarray
    gsd_min_cm: np.ndarray
    gsd_max_cm: np.ndarray
    altitude_m: np.ndarray  # camera above the ground under it


class Posed(Protocol):
    """What a footprint needs of a camera: a :class:`PhotoCamera`, or the ortho stage's SfM cameras."""

    @property
    def intrinsics(self) -> Intrinsics: ...

    @property
    def pose(self) -> Pose: ...


def _border_and_centre(intr: Intrinsics, per_side: int) -> np.ndarray:
    return np.vstack([intr.border_pixels(per_side), [[intr.cx_px, intr.cy_px]]])


def compute_footprints(cams: Sequence[Posed], surface: Surface, *, per_side: int = 16,
                       max_range_m: float = 500.0) -> FootprintTable:
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
    hit = hits.hit.reshape(n, m + 1)
    rng = hits.range_m.reshape(n, m + 1)
    # GSD as the side of the ground area one pixel covers (level ground locally):
    # range · sqrt(cos³θ / cos i) / f, θ off the optical axis, i the incidence angle.
    cos_inc = np.abs(dirs[..., 2])
    with np.errstate(divide="ignore", invalid="ignore"):
        gsd_m = rng * np.sqrt(cos_theta ** 3 / cos_inc) / focal[:, None]
    gsd_m = np.where(hit, gsd_m, np.nan)
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN rows: nothing hit
        ground_z = surface.elevation(origins[:, 0], origins[:, 1])
        under = np.nanmedian(np.where(hit, pts[..., 2], np.nan), axis=1)
        ground_z = np.where(np.isnan(ground_z), under, ground_z)
        gmin = np.nanmin(gsd_m, axis=1)
        gmax = np.nanmax(gsd_m, axis=1)
    return FootprintTable(
        rings=pts[:, :m, :2], clipped=~hit[:, :m].all(axis=1), gsd_cm=gsd_m[:, m] * 100,
        gsd_min_cm=gmin * 100, gsd_max_cm=gmax * 100, altitude_m=origins[:, 2] - ground_z,
    )


@dataclass(frozen=True)
class FootprintResult:
    """What the footprints algorithm wrote, and the survey's figures."""

    output: Path
    crs: str
    n_photos: int
    n_skipped: int
    median_gsd_cm: float
    overlap: Path | None
    height_source: str


def footprints(
    images: Path,
    output: Path,
    dsm: Path | None = None,
    ground_elevation_m: float | None = None,
    takeoff_elevation_m: float | None = None,
    crs: str | None = None,
    sensor_width_mm: float | None = None,
    max_range_m: float = 500.0,
    overlap: Path | None = None,
    overlap_cell_m: float = 1.0,
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
        Ground elevation of the take-off point, in the datum of the DSM or
        ground elevation. Default: estimated from the photos' absolute and
        relative altitudes.
    crs : str
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
    """
    import geopandas as gpd
    import shapely

    from .outputs import write_vector

    fb = as_feedback(feedback)
    s_read, s_cast, s_write = split(fb, [3, 2, 1])
    if dsm is not None and ground_elevation_m is not None:
        raise InputError("give either a DSM or a ground elevation, not both")
    out_crs = parse_crs(crs) if crs else None
    photos = read_photos(images, sensor_width_mm, feedback=s_read)
    if not photos.photos:
        raise InputError(f"no usable photo ({photos.summary()})", path=images)
    usable = [p for p in photos.photos if p.has_altitude]
    for p in photos.photos:
        if not p.has_altitude:
            photos.skipped.append((p.image, "no altitude (RelativeAltitude, AbsoluteAltitude or GPSAltitude)"))
            fb.warning(f"skipped {p.image}: no altitude in the metadata")
    photos.photos = usable
    if not usable:
        raise InputError(f"no usable photo ({photos.summary()})", path=images)
    work = working_crs(photos.photos, out_crs)
    surface: Surface | None = None
    if dsm is not None:
        surface = read_surface(dsm, work)
    elif ground_elevation_m is not None:
        surface = FlatSurface(float(ground_elevation_m))
    cams, surface, how = photo_cameras(photos.photos, work, surface, takeoff_elevation_m)
    ground = "DSM" if dsm is not None else ("ground elevation" if ground_elevation_m is not None else
                                             "flat take-off ground")
    fb.info(f"heights: {ground}; {how}")
    s_read.progress(1.0)
    table = compute_footprints(cams, surface, max_range_m=max_range_m)
    s_cast.progress(1.0)

    polys = shapely.polygons(table.rings)
    bad = ~shapely.is_valid(polys)
    if bad.any():
        polys[bad] = shapely.make_valid(polys[bad])
    records = {
        "image": [c.photo.image for c in cams],
        "gsd_cm": table.gsd_cm, "gsd_min_cm": table.gsd_min_cm, "gsd_max_cm": table.gsd_max_cm,
        "altitude_m": table.altitude_m,
        "pitch_deg": [c.photo.pitch_deg for c in cams], "yaw_deg": [c.photo.yaw_deg for c in cams],
        "roll_deg": [c.photo.roll_deg for c in cams], "area_m2": shapely.area(polys),
        "clipped": table.clipped, "height_source": [f"{ground}; {c.height_source}" for c in cams],
        "attitude_source": [c.photo.attitude_source for c in cams],
        "camera": [f"{c.photo.make} {c.photo.model}".strip() for c in cams],
        "focal_px": [c.intrinsics.focal_px for c in cams],
        "taken_at": [c.photo.taken_at for c in cams],
    }
    fp = gpd.GeoDataFrame(records, geometry=polys, crs=work)
    centers = np.array([c.pose.center for c in cams])
    cam_layer = gpd.GeoDataFrame(
        {"image": records["image"], "z_m": centers[:, 2], "latitude_deg": [c.photo.latitude_deg for c in cams],
         "longitude_deg": [c.photo.longitude_deg for c in cams],
         "relative_altitude_m": [c.photo.relative_altitude_m for c in cams],
         "yaw_deg": records["yaw_deg"], "pitch_deg": records["pitch_deg"], "roll_deg": records["roll_deg"],
         "gsd_cm": table.gsd_cm},
        geometry=shapely.points(centers[:, :2]), crs=work,
    )
    overlap_path = None
    if overlap is not None:
        overlap_path = write_overlap(overlap, fp.geometry.values, work, overlap_cell_m)
    if out_crs is not None and not out_crs.equals(work):
        fp, cam_layer = fp.to_crs(out_crs), cam_layer.to_crs(out_crs)
    write_vector(output, {"footprints": fp, "cameras": cam_layer})
    s_write.progress(1.0)
    median_gsd = float(np.nanmedian(table.gsd_cm))
    fb.info(f"{len(cams)} footprints, median GSD {median_gsd:.2f} cm, {int(table.clipped.sum())} clipped; "
            f"{photos.summary()}")
    return FootprintResult(Path(output), crs_to_text(out_crs or work), len(cams), len(photos.skipped),
                           median_gsd, overlap_path, how)


def write_overlap(path: str | os.PathLike[str], polygons: Sequence, crs: CRS, cell_m: float) -> Path:
    """Raster of how many polygons cover each cell (uint16 COG, 0 = not covered is nodata)."""
    import shapely
    from rasterio.features import MergeAlg, rasterize
    from rasterio.transform import from_origin

    from .outputs import write_cog

    x0, y0, x1, y1 = shapely.total_bounds(np.asarray(polygons))
    x0, y0 = math.floor(x0 / cell_m) * cell_m, math.floor(y0 / cell_m) * cell_m
    cols, rows = int(math.ceil((x1 - x0) / cell_m)), int(math.ceil((y1 - y0) / cell_m))
    if cols * rows > 400_000_000:
        raise InputError(f"overlap raster of {cols}x{rows} cells is too large; raise overlap_cell_m")
    transform = from_origin(x0, y0 + rows * cell_m, cell_m, cell_m)
    count = rasterize(((g, 1) for g in polygons), out_shape=(rows, cols), transform=transform,
                      merge_alg=MergeAlg.add, dtype="uint16", fill=0)
    return write_cog(path, count, transform=transform, crs=crs, nodata=0)
