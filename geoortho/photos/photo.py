"""A photo as geoortho knows it from its metadata (:class:`Photo`), and a batch of them with the ones
that could not be read (:class:`PhotoSet`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from geoortho.core.camera import Intrinsics
from geoortho.core.gsd import focal_length_px
from geoortho.errors import InputError


@dataclass(frozen=True)
class Photo:
    """What a photo's metadata says: where it was taken, where it looked, with what camera.

    NaN marks a value the photo does not carry. ``sensor_width_mm`` spans the
    image's longer side; ``focal_px`` follows from it and the decoded size.
    """

    path: Path
    width_px: int
    height_px: int
    make: str = ""
    model: str = ""
    latitude_deg: float = math.nan
    longitude_deg: float = math.nan
    gps_altitude_m: float = math.nan  # EXIF GPSAltitude: roughly above sea level
    relative_altitude_m: float = math.nan  # DJI RelativeAltitude: above the take-off point
    absolute_altitude_m: float = math.nan  # DJI AbsoluteAltitude
    yaw_deg: float = 0.0
    pitch_deg: float = -90.0
    roll_deg: float = 0.0
    attitude_source: str = "assumed nadir"
    flight_yaw_deg: float = math.nan
    flight_pitch_deg: float = math.nan
    flight_roll_deg: float = math.nan
    focal_mm: float = math.nan
    focal_35mm: float = math.nan
    sensor_width_mm: float = math.nan
    sensor_source: str = ""
    taken_at: str = ""  # ISO 8601, camera clock
    exposure_time_s: float = math.nan
    f_number: float = math.nan
    iso: float = math.nan
    has_xmp: bool = False
    # The position's stated accuracy (1 sigma, metres; NaN: consumer GPS, none stated) and its
    # class: fixed, float, single (an RTK receiver's solution), stated (a camera's own accuracy
    # tags, no fix state), consumer (nothing said). See position_accuracy.
    gps_sigma_h_m: float = math.nan
    gps_sigma_v_m: float = math.nan
    gps_fix: str = "consumer"
    # The maker's factory calibration (DJI: CalibratedFocalLength, CalibratedOpticalCenterX/Y in
    # pixels, corner origin; DewarpData's k1 k2 p1 p2 k3), NaN/() when not written; ``dewarped``:
    # the JPEG was already undistorted in the camera (DewarpFlag 1), its distortion is none.
    factory_focal_px: float = math.nan
    factory_cx_px: float = math.nan
    factory_cy_px: float = math.nan
    factory_distortion: tuple[float, ...] = ()
    dewarped: bool = False
    warnings: tuple[str, ...] = field(default=(), compare=False)

    @property
    def image(self) -> str:
        return self.path.name

    @property
    def has_gps(self) -> bool:
        return math.isfinite(self.latitude_deg) and math.isfinite(self.longitude_deg)

    @property
    def has_altitude(self) -> bool:
        """Any of RelativeAltitude, AbsoluteAltitude or GPSAltitude."""
        return any(math.isfinite(v) for v in (self.relative_altitude_m, self.absolute_altitude_m, self.gps_altitude_m))

    @property
    def yaw_unknown(self) -> bool:
        """No yaw in the metadata (0 was assumed) and none taken from the course yet."""
        src = self.attitude_source
        return (src == "assumed nadir" or "yaw assumed" in src) and "course" not in src

    @property
    def exposure_value(self) -> float:
        """Relative exposure, ISO · t / N² (NaN when the EXIF lacks any of them): photos of the same
        scene come out brighter in proportion."""
        return self.iso * self.exposure_time_s / self.f_number**2

    @property
    def focal_px(self) -> float:
        """The factory calibration's focal length where the photo carries one, else EXIF's."""
        if math.isfinite(self.factory_focal_px):
            return self.factory_focal_px
        return self.exif_focal_px

    @property
    def exif_focal_px(self) -> float:
        return focal_length_px(self.focal_mm, self.sensor_width_mm, max(self.width_px, self.height_px))

    def intrinsics(self) -> Intrinsics:
        """Pinhole intrinsics, principal point at the image centre."""
        if not math.isfinite(self.focal_px):
            raise InputError("no focal length or sensor size: give sensor_width_mm", path=self.path)
        return Intrinsics(self.width_px, self.height_px, self.focal_px)

    def as_record(self) -> dict[str, Any]:
        """Flat dict for tables (path as text, warnings joined)."""
        d = {k: getattr(self, k) for k in self.__dataclass_fields__}
        d["path"] = str(self.path)
        d["warnings"] = "; ".join(self.warnings)
        d["factory_distortion"] = " ".join(f"{v:g}" for v in self.factory_distortion)
        d["image"] = self.image
        d["focal_px"] = self.focal_px
        return d


@dataclass
class PhotoSet:
    """Photos read from a folder, and those skipped with the reason."""

    photos: list[Photo]
    skipped: list[tuple[str, str]] = field(default_factory=list)

    def to_geodataframe(self, crs: Any = None) -> Any:
        """Camera positions as points (WGS84, or ``crs``), one row per photo with every field."""
        import geopandas as gpd
        import shapely

        records = [p.as_record() for p in self.photos]
        xy = positions_lonlat(self.photos)
        gdf = gpd.GeoDataFrame(records, geometry=shapely.points(xy), crs="EPSG:4326")
        return gdf.to_crs(crs) if crs is not None else gdf

    def summary(self) -> str:
        text = f"{len(self.photos)} photos read"
        if self.skipped:
            text += f", {len(self.skipped)} skipped: " + "; ".join(f"{n} ({r})" for n, r in self.skipped)
        return text


def with_sensor_width(photo: Photo, sensor_width_mm: float) -> Photo:
    return replace(photo, sensor_width_mm=float(sensor_width_mm), sensor_source="user")


def positions_lonlat(photos: Sequence[Photo]) -> np.ndarray:
    """(N, 2) longitude, latitude in degrees."""
    return np.array([[p.longitude_deg, p.latitude_deg] for p in photos], dtype=float).reshape(-1, 2)
