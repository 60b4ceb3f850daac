"""Where each photo was and how it looked, from the photo metadata (direct georeferencing); an
``sfm`` output is read by :mod:`geoortho.reconstruction.model`."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from pyproj import CRS

from geoortho.core.camera import PosedCamera
from geoortho.photos.footprint import photo_cameras
from geoortho.photos.heights import GpsAltitude

__all__ = ["cameras_from_metadata"]


def cameras_from_metadata(
    photos: Sequence[Any],
    crs: CRS,
    surface: Any = None,
    takeoff_elevation_m: float | None = None,
    *,
    flight_height_m: float | None = None,
    gps_altitude: GpsAltitude = "auto",
) -> tuple[list[PosedCamera], Any]:
    """Direct georeferencing: poses from GPS, altitude and gimbal attitude (see :mod:`geoortho.photos.footprint`).
    Returns the cameras and the flight's :class:`~geoortho.photos.heights.HeightModel`."""
    pcs, heights = photo_cameras(
        photos, crs, surface, takeoff_elevation_m, flight_height_m=flight_height_m, gps_altitude=gps_altitude
    )
    return list(pcs), heights
