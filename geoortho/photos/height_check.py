"""A given flight height or take-off elevation checked against what the SfM measured: the ground under
the SfM's cameras, the heights it implies, and a refusal naming what to give when they disagree.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from pyproj import CRS

from geoortho.core.camera import ypr_from_rotation
from geoortho.core.crs import grid_north
from geoortho.core.surface import FlatSurface, Surface, read_surface
from geoortho.errors import InputError
from geoortho.feedback import Feedback
from geoortho.photos.heights import GpsAltitude
from geoortho.photos.metadata import Photo
from geoortho.photos.photo_cameras import DSM_MAX_CELLS, FootprintTable, PhotoCamera, box_around, photo_cameras


def finite_median(values: np.ndarray) -> float:
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


@dataclass(frozen=True)
class HeightCheck:
    """The metadata's heights against the measured ones."""

    altitude_m: float  # median height above ground from the metadata (NaN: none to be had)
    per_photo_m: np.ndarray  # the same per photo
    problem: str  # the disagreement, in words ("" when they agree)
    notes: tuple[str, ...]


def ground_under_sfm(
    dsm: Path | None, work: CRS, centres: np.ndarray, reach_m: float, tie_points: np.ndarray, fb: Feedback
) -> tuple[Surface, str]:
    """The ground the SfM cameras' footprints are cast on, and its name: the DSM (moved onto the
    tie points when it lies in another vertical datum), else the tie points' ground level."""
    from dataclasses import replace

    if dsm is None:
        # no surface given: the tie points' ground level (below roofs and trees)
        z = tie_points[:, 2] if len(tie_points) else np.array([0.0])
        return FlatSurface(float(np.percentile(z, 30))), "the SfM tie points' ground level"
    box = box_around(centres[:, 0], centres[:, 1], reach_m)
    grid = read_surface(dsm, work, extend=True, bounds=box, max_cells=DSM_MAX_CELLS)
    surface: Surface = grid
    ground = "DSM"
    # A DSM in another vertical datum than the SfM (a lidar DSM, a model on drifting GPS
    # heights): the cameras' height over it would be off by the difference. The tie points
    # measure it; past ELEVATION_TOLERANCE_M the DSM is moved onto the SfM, and that is said.
    if len(tie_points):
        with np.errstate(invalid="ignore"):
            under = np.asarray(surface.elevation(tie_points[:, 0], tie_points[:, 1]), float)
        offset = finite_median(tie_points[:, 2] - under)
        if math.isfinite(offset) and abs(offset) > ELEVATION_TOLERANCE_M:
            surface = replace(grid, grid=grid.grid + np.float32(offset))
            ground = f"DSM moved {offset:+.1f} m onto the SfM's tie points"
            fb.warning(
                f"the DSM lies {-offset:+.1f} m off the SfM's tie points (another vertical datum?): the heights "
                "above ground are measured on it moved onto the SfM"
            )
    return surface, ground


def sfm_photo_cameras(sfm_cams: Sequence[Any], by_name: dict[str, Photo], work: CRS) -> list[PhotoCamera]:
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
    measured_alt = finite_median(table.altitude_m)
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
    offset_m = finite_median(z_meta - z_sfm)  # + : the metadata puts the cameras higher than measured
    meta_alt = finite_median(per_photo)
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
        off = float(given.ground_elevation_m) - finite_median(ground_meta)
        if abs(off) > ELEVATION_TOLERANCE_M:
            problem = (
                f"ground_elevation_m {given.ground_elevation_m:g} m disagrees with the measured surface by "
                f"{off:+.1f} m (its median under the cameras: {finite_median(ground_meta):.1f} m); the products use "
                "the measured surface: check ground_elevation_m and its datum"
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
