"""Flight and ground-control planning before the flight.

A lawnmower (single or double) grid over an area of interest, sized from the
camera, a target GSD (or altitude) and the overlaps; photos at constant
altitude above the take-off or following a DTM; footprints, GSD and an
overlap raster made by the same code as the ``footprints`` algorithm; proposed
(or given) GCPs with the number of planned photos that will see each, and the
marker size to print so that geoortho's own detector decodes it at the planned
GSD. Exports for pilots: KML 2.2 waypoints and a Litchi mission CSV.

Conventions: the working frame is the projected CRS (the AOI's own, or the UTM
zone of its centre); ``grid_heading_deg`` is clockwise from grid north (the
frame the rest of geoortho poses cameras in) and ``heading_deg`` from true north
(what the drone flies), one per photo. The image's top points along the flight
line, its width across it, as DJI and Litchi mapping missions shoot.
"""

from __future__ import annotations

import difflib
import json
import logging
import math
import os
import time
import warnings
from dataclasses import dataclass, field
from functools import cache
from pathlib import Path
from typing import Any, Literal
from xml.sax.saxutils import escape

import cv2
import geopandas as gpd
import numpy as np
import pyogrio
import rasterio
import shapely
from pyproj import CRS, Proj
from rasterio.features import geometry_mask, shapes
from scipy.special import ndtr

from geoortho.core.camera import Intrinsics, Pose, PosedCamera, rotation_from_ypr
from geoortho.core.crs import WGS84, crs_to_text, grid_north, horizontal_unit_m, transformer, utm_crs_for
from geoortho.core.gsd import focal_length_px, gsd_at_height_m, height_for_gsd_m, marker_gsd_m
from geoortho.core.outputs import atomic_path, write_json, write_text, write_vector
from geoortho.core.surface import FlatSurface, GridSurface, Surface, read_surface, sample_grid
from geoortho.errors import InputError
from geoortho.feedback import Feedback, as_feedback, split
from geoortho.gcp.detect import SearchWindow, detect_in_image
from geoortho.gcp.io import heights_are_placeholders, marker_id_of, read_gcp_file
from geoortho.gcp.markers import Dictionary, get_dictionary, marker_cells
from geoortho.photos.footprint import (
    compute_footprints,
    photo_cameras,
    photos_with_altitude,
    working_crs,
    write_overlap,
)
from geoortho.photos.metadata import read_photo
from geoortho.photos.sensors import CAMERA_SPECS

__all__ = [
    "CAMERAS",
    "CameraSpec",
    "PlanResult",
    "plan",
    "check_plan",
    "PlanCheckResult",
    "resolve_camera",
    "min_module_px",
    "default_gcp_count",
    "line_overlaps",
]

DEFAULT_MAX_ALTITUDE_M = 120.0  # the open-category ceiling in the EU and the US
# How far a flown photo is from the planned one (consumer GNSS and wind; gimbal and aircraft
# attitude): what makes a GCP near a frame edge seen or not.
FLIGHT_POSITION_SIGMA_M = 0.5
FLIGHT_ATTITUDE_SIGMA_DEG = 1.5
DETECTION_SAFETY = 1.5  # printed module size over the smallest one the detector decodes
MIN_MARKER_STEP_M = 0.05  # print sizes are rounded up to 5 cm


@dataclass(frozen=True)
class CameraSpec:
    """A camera as planning needs it."""

    name: str
    sensor_width_mm: float
    focal_mm: float
    width_px: int
    height_px: int
    source: str

    @property
    def focal_px(self) -> float:
        return focal_length_px(self.focal_mm, self.sensor_width_mm, self.width_px)

    def intrinsics(self) -> Intrinsics:
        return Intrinsics(self.width_px, self.height_px, self.focal_px)


CAMERAS: dict[str, CameraSpec] = {}
for _name, _model, _sw, _sh, _f, _w, _h in CAMERA_SPECS:
    for _key in (_name, _model):
        CAMERAS[_key.lower()] = CameraSpec(_name, _sw, _f, _w, _h, f"table: {_name} ({_model})")


def resolve_camera(
    camera: str = "",
    sensor_width_mm: float | None = None,
    focal_mm: float | None = None,
    image_width_px: int | None = None,
    image_height_px: int | None = None,
) -> CameraSpec:
    """The camera from a model name, a sample photo, or explicit values (which override either)."""
    base: CameraSpec | None = None
    try:
        a_photo = bool(camera) and Path(camera).is_file()
    except OSError:  # a name longer than a file name can be is a model name
        a_photo = False
    if a_photo:
        p = read_photo(camera)
        if not (math.isfinite(p.focal_mm) and math.isfinite(p.sensor_width_mm)):
            raise InputError("the photo gives no focal length or sensor width: give --sensor-width-mm", path=camera)
        base = CameraSpec(
            f"{p.make} {p.model}".strip(),
            p.sensor_width_mm,
            p.focal_mm,
            p.width_px,
            p.height_px,
            f"photo {Path(camera).name} ({p.sensor_source})",
        )
    elif camera:
        words = camera.strip().lower().split()
        # make and model as EXIF writes them ("DJI FC6310", "Hasselblad L1D-20c"): the model alone
        # is the table's key, so the make (one word or more) is tried away
        base = next((CAMERAS[k] for k in (" ".join(words[i:]) for i in range(len(words))) if k in CAMERAS), None)
        if base is None:
            names = sorted({c.name for c in CAMERAS.values()} | {m for _, m, *_ in CAMERA_SPECS})
            close = difflib.get_close_matches(camera, names, n=4, cutoff=0.3)
            hint = (
                f"closest: {', '.join(close)}"
                if close
                else f"known: {', '.join(sorted({c.name for c in CAMERAS.values()}))}"
            )
            named = camera if len(camera) <= 60 else f"{camera[:40]}… ({len(camera)} characters)"
            raise InputError(
                f"unknown camera {named!r} ({hint}); or give a sample photo, or --sensor-width-mm, "
                "--focal-mm, --image-width-px and --image-height-px"
            )
    explicit = (sensor_width_mm, focal_mm, image_width_px, image_height_px)
    if base is None:
        if any(v is None for v in explicit):
            raise InputError(
                "no camera: give --camera MODEL|PHOTO, or all of --sensor-width-mm, --focal-mm, "
                "--image-width-px and --image-height-px"
            )
        base = CameraSpec("camera", 1.0, 1.0, 1, 1, "given")
    spec = CameraSpec(
        base.name,
        float(sensor_width_mm if sensor_width_mm is not None else base.sensor_width_mm),
        float(focal_mm if focal_mm is not None else base.focal_mm),
        int(image_width_px if image_width_px is not None else base.width_px),
        int(image_height_px if image_height_px is not None else base.height_px),
        base.source if not any(v is not None for v in explicit) else base.source + " with given values",
    )
    if not (spec.sensor_width_mm > 0 and spec.focal_mm > 0 and spec.width_px >= 16 and spec.height_px >= 16):
        raise InputError(f"camera values out of range: {spec}")
    return spec


# ---------------------------------------------------------------------------------------------
# Marker detectability, measured with geoortho's own detector


@cache
def min_module_px(dictionary: str = "DICT_4X4_50") -> float:
    """The smallest marker module (cell) size in pixels at which geoortho's detector decodes every
    trial: markers rendered area-averaged at 8 rotations and sub-pixel offsets, lens blur
    (sigma 0.6 px) and noise (sigma 3 DN), searched in a predicted window as ``gcp-find`` does.
    Every larger size tried must decode too."""
    sizes = np.round(np.arange(1.0, 8.01, 0.25), 2)
    rng = np.random.default_rng(7)
    ok_at = []
    n_ids = get_dictionary(dictionary).bytesList.shape[0]
    for module in sizes:
        good = True
        for t in range(8):
            mid = int(t * 7 % n_ids)
            cells = marker_cells(dictionary, mid)
            gray = _render_marker(cells, float(module), 22.5 * t / 4 + 3.0, rng)
            h, w = gray.shape
            side = cells.shape[0] * module
            win = SearchWindow("m", mid, (w - 1) / 2, (h - 1) / 2, max(24.0, 1.5 * side), side)
            dets = detect_in_image(gray, [win], dictionary)
            hit = [d for d in dets if d.marker_id == mid and math.hypot(d.x_px - win.x_px, d.y_px - win.y_px) < module]
            if not hit:
                good = False
                break
        ok_at.append(good)
        cv2.setNumThreads(0)
    ok = np.array(ok_at)
    for i in range(len(sizes)):
        if ok[i:].all():
            return float(sizes[i])
    raise RuntimeError(f"{dictionary}: no module size up to 8 px was always decoded")  # pragma: no cover


def _render_marker(cells: np.ndarray, module_px: float, angle_deg: float, rng: np.random.Generator) -> np.ndarray:
    """A marker (with a one-module white quiet zone) on mid-grey ground, rotated, area-averaged."""
    quiet = np.pad(cells, 1, constant_values=True)
    up = 16
    big = np.asarray(np.kron(np.where(quiet, 230.0, 25.0), np.ones((up, up))), np.float32)
    n = quiet.shape[0] * module_px
    size = int(math.ceil(n * 1.6 + 40))
    scale = module_px / up
    c_big = (big.shape[1] - 1) / 2
    off = rng.uniform(-0.5, 0.5, 2)
    m = cv2.getRotationMatrix2D((c_big, c_big), angle_deg, scale)
    m[:, 2] += (size - 1) / 2 + off - c_big
    # Render at 8x the output and area-average down: each pixel integrates the scene as a sensor does.
    k = 8
    m8 = m * np.array([[k], [k]])
    m8[:, 2] = (m[:, 2] + 0.5) * k - 0.5
    hi = cv2.warpAffine(big, m8, (size * k, size * k), flags=cv2.INTER_LINEAR, borderValue=128.0)
    img = cv2.resize(hi, (size, size), interpolation=cv2.INTER_AREA)
    img = cv2.GaussianBlur(img, (0, 0), 0.6)
    img = img + np.asarray(rng.normal(0, 3.0, img.shape), np.float32)
    result: np.ndarray = np.clip(img + 0.5, 0, 255).astype(np.uint8)
    return result


def default_gcp_count(area_ha: float) -> int:
    """5 GCPs up to 5 ha (four near the corners and one inside, the usual minimum), then one more
    for every further 10 ha, at most 40."""
    return int(min(40, 5 + math.ceil(max(0.0, area_ha - 5.0) / 10.0)))


# ---------------------------------------------------------------------------------------------
# The plan


@dataclass(frozen=True)
class PlanResult:
    """What the plan algorithm wrote, and its figures.

    Attributes
    ----------
    output : Path
        The plan folder.
    plan : Path
        plan.gpkg (layers aoi, photos, lines, footprints, gcps).
    photos : str
        Photo positions (layer photos of plan.gpkg, as ``path|layername=photos``).
    lines : str
        Flight lines (layer lines).
    footprints : str
        Predicted footprints (layer footprints).
    gcps : str
        GCPs with the photos that will see each (layer gcps).
    overlap : Path
        Photos covering each ground cell (GeoTIFF).
    kml : Path
        Waypoints, lines, AOI and GCPs (KML 2.2).
    litchi : Path
        Litchi mission CSV.
    summary : Path
        summary.json.
    n_photos : int
        Planned photos.
    n_lines : int
        Flight lines.
    flight_length_m : float
        Length of the photo lines and the turns between them.
    flight_time_min : float
        At the planned speed.
    altitude_m : float
        Altitude above the take-off (constant mode) or above the ground (terrain following).
    median_gsd_cm : float
        Median GSD at the image centres.
    marker_size_m : float
        Side of the black square of the markers to print.
    crs : str
        CRS of the plan.
    warnings : tuple of str
        What the plan could not meet or assumed.
    """

    output: Path
    plan: Path
    photos: str
    lines: str
    footprints: str
    gcps: str
    overlap: Path
    kml: Path
    litchi: Path
    summary: Path
    n_photos: int
    n_lines: int
    flight_length_m: float
    flight_time_min: float
    altitude_m: float
    median_gsd_cm: float
    marker_size_m: float
    crs: str
    warnings: tuple[str, ...] = field(default=())


def plan(
    aoi: Path,
    output: Path,
    camera: str = "",
    gsd_cm: float | None = None,
    altitude_m: float | None = None,
    front_overlap: float = 75.0,
    side_overlap: float = 65.0,
    direction_deg: float | None = None,
    dtm: Path | None = None,
    terrain: Literal["constant", "follow"] = "constant",
    takeoff_ground_m: float | None = None,
    pitch_deg: float = -90.0,
    grid: Literal["single", "double"] = "single",
    speed_m_s: float = 8.0,
    min_interval_s: float = 2.0,
    max_altitude_m: float = DEFAULT_MAX_ALTITUDE_M,
    gcps: str = "",
    gcp_crs: CRS | None = None,
    marker_dictionary: Dictionary = "DICT_4X4_50",
    marker_size_m: float | None = None,
    margin: float = 0.0,
    crs: CRS | None = None,
    sensor_width_mm: float | None = None,
    focal_mm: float | None = None,
    image_width_px: int | None = None,
    image_height_px: int | None = None,
    *,
    feedback: Feedback | None = None,
) -> PlanResult:
    """Plan a mapping flight and its ground control over an area of interest.

    Writes to ``output``: plan.gpkg (layers aoi, photos, lines, footprints,
    gcps), overlap.tif, plan.kml, litchi.csv, summary.json and markers/ (one
    print-ready PDF per GCP, at its real size).

    Parameters
    ----------
    aoi : Path
        Area of interest: polygon(s) in a GeoPackage, GeoJSON, KML or Shapefile, any CRS.
    output : Path
        Folder to write the plan into.
    camera : str
        A camera model (e.g. "DJI Phantom 4 Pro", "FC6310") or a sample photo to read it from.
    gsd_cm : float
        Target ground sample distance at the image centre, cm/pixel (or give altitude_m).
    altitude_m : float
        Flight height above the take-off (constant) or above the ground (follow), metres.
    front_overlap : float
        Overlap between consecutive photos of a line, percent.
    side_overlap : float
        Overlap between neighbouring lines, percent.
    direction_deg : float
        Flight line direction, degrees clockwise from grid north. Default: the one
        giving the fewest lines.
    dtm : Path
        Terrain (DTM or DSM raster) for terrain following and the GSD over the ground.
    terrain : str
        constant (one altitude above the take-off; the GSD spread over the terrain is
        reported) or follow (the altitude above the ground is kept per photo; needs dtm).
    takeoff_ground_m : float
        Ground elevation of the take-off point, in the DTM's datum. Default: the
        median ground of the AOI on the DTM (0 without one).
    pitch_deg : float
        Gimbal pitch: -90 nadir, -45 to -80 oblique (looking along the line).
    grid : str
        single, or double (a second grid across the first, for 3D structures).
    speed_m_s : float
        Cruise speed, lowered when the photo spacing needs it (min_interval_s).
    min_interval_s : float
        Shortest time between two photos the camera can keep up.
    max_altitude_m : float
        Highest allowed flight height above the ground.
    gcps : str
        Number of GCPs to propose, or a GCP file (positions to check), or empty for
        the default number by area.
    gcp_crs : CRS
        CRS of a GCP file without one.
    marker_dictionary : str
        ArUco/AprilTag dictionary of the markers to print.
    marker_size_m : float
        Side of the black square of the markers you have: the GCP sightings are counted
        with it, and it is checked against the size needed. Default: the size needed.
    margin : float
        A GCP counts as seen only this far inside the frame, percent of the image side,
        as gcp-find's margin (the marker must be whole in the photo as well).
    crs : CRS
        Projected CRS to plan in. Default: the AOI's, or its UTM zone.
    sensor_width_mm : float
        Sensor width (overrides the camera's).
    focal_mm : float
        Focal length (overrides the camera's).
    image_width_px : int
        Image width (overrides the camera's).
    image_height_px : int
        Image height (overrides the camera's).
    """
    o = PlanOptions(
        camera, gsd_cm, altitude_m, front_overlap, side_overlap, direction_deg, dtm, terrain, takeoff_ground_m,
        pitch_deg, grid, speed_m_s, min_interval_s, max_altitude_m, gcps, gcp_crs, marker_dictionary, marker_size_m,
        margin, crs, sensor_width_mm, focal_mm, image_width_px, image_height_px,
    )  # fmt: skip
    fb = as_feedback(feedback)
    t0 = time.perf_counter()
    s_setup, s_grid, s_foot, s_gcp, s_write = split(fb, [1, 1, 3, 2, 2])
    warnings_: list[str] = []
    site = _layout(Path(aoi), o, warnings_)
    s_setup.progress(1.0)
    flight = _fly(Path(aoi), site, o, warnings_, s_grid, s_foot)
    control = _gcp_sightings(site, flight, o, warnings_)
    s_gcp.progress(1.0)
    try:
        files = _write(Path(output), site, flight, control, o, warnings_, s_write)
        summary = _summary(site, flight, control, files, o, warnings_, time.perf_counter() - t0)
        summary_path = write_json(Path(output) / "summary.json", summary)
    except BaseException:
        # canceled or failed while writing: no half a plan (a KML without its summary, sheets without
        # the plan) is left to be flown
        _remove_plan(Path(output))
        raise
    s_write.progress(1.0)
    for w in warnings_:
        fb.warning(w)
    fb.info(
        f"plan: {len(flight.shots)} photos on {len(flight.lines)} lines, {flight.length_m / 1000:.2f} km, "
        f"{summary['flight_time_min']:.1f} min at {flight.speed:.1f} m/s; {site.agl:.1f} m "
        f"{summary['altitude_meaning']}, GSD {summary['gsd_cm']['median']:.2f} cm; "
        f"{len(control.rows)} GCPs, markers {control.marker_m * 100:.0f} cm"
    )
    gpkg = str(files.plan)
    return PlanResult(
        output=Path(output),
        plan=files.plan,
        photos=f"{gpkg}|layername=photos",
        lines=f"{gpkg}|layername=lines",
        footprints=f"{gpkg}|layername=footprints",
        gcps=f"{gpkg}|layername=gcps",
        overlap=files.overlap,
        kml=files.kml,
        litchi=files.litchi,
        summary=summary_path,
        n_photos=len(flight.shots),
        n_lines=len(flight.lines),
        flight_length_m=flight.length_m,
        flight_time_min=summary["flight_time_min"],
        altitude_m=site.agl,
        median_gsd_cm=summary["gsd_cm"]["median"],
        marker_size_m=control.marker_m,
        crs=crs_to_text(site.work_crs),
        warnings=tuple(warnings_),
    )


@dataclass(frozen=True)
class PlanOptions:
    """:func:`plan`'s options (all but the AOI and the output folder), as one value."""

    camera: str = ""
    gsd_cm: float | None = None
    altitude_m: float | None = None
    front_overlap: float = 75.0
    side_overlap: float = 65.0
    direction_deg: float | None = None
    dtm: Path | None = None
    terrain: Literal["constant", "follow"] = "constant"
    takeoff_ground_m: float | None = None
    pitch_deg: float = -90.0
    grid: Literal["single", "double"] = "single"
    speed_m_s: float = 8.0
    min_interval_s: float = 2.0
    max_altitude_m: float = DEFAULT_MAX_ALTITUDE_M
    gcps: str = ""
    gcp_crs: CRS | None = None
    marker_dictionary: Dictionary = "DICT_4X4_50"
    marker_size_m: float | None = None
    margin: float = 0.0
    crs: CRS | None = None
    sensor_width_mm: float | None = None
    focal_mm: float | None = None
    image_width_px: int | None = None
    image_height_px: int | None = None


@dataclass(frozen=True)
class _Site:
    """What the flight is laid out on: the camera, the area, the ground and the spacing."""

    cam: CameraSpec
    intr: Intrinsics
    area: Any  # shapely geometry in work_crs
    work_crs: CRS
    surface: Surface
    ground: dict[str, float]
    ground_label: str
    z_takeoff: float
    agl: float  # the flight height asked (above the take-off, or the ground when following it)
    spacing_agl: float  # the height the spacing was worked out at
    along_len: float  # footprint along the line, m
    across_w: float  # footprint across, m
    ahead: float
    along: float  # photo spacing, m
    across: float  # line spacing, m


def _layout(aoi: Path, o: PlanOptions, warnings_: list[str]) -> _Site:
    """The camera, the AOI in its working CRS, the ground under it, the flight height and the
    spacings that give the overlaps asked; refuses a plan that cannot be flown."""
    _check_options(
        o.gsd_cm, o.altitude_m, o.front_overlap, o.side_overlap, o.terrain, o.dtm, o.pitch_deg, o.speed_m_s,
        o.min_interval_s, o.max_altitude_m,
    )  # fmt: skip
    cam = resolve_camera(o.camera, o.sensor_width_mm, o.focal_mm, o.image_width_px, o.image_height_px)
    area_geom, work_crs, aoi_notes = _read_aoi(aoi, o.crs)
    warnings_ += aoi_notes
    surface: Surface
    if o.dtm is not None:
        surface = read_surface(o.dtm, work_crs, extend=True)
        ground = _ground_stats(surface, area_geom, o.dtm)
        if ground.get("covered", 1.0) < 1.0:
            warnings_.append(
                f"the DTM covers {100 * ground['covered']:.0f} % of the AOI: the rest is its edge carried on"
            )
        ground_label = f"DTM {Path(o.dtm).name}"
    else:
        surface = FlatSurface(float(o.takeoff_ground_m or 0.0))
        ground = {"min": surface.elevation_m, "median": surface.elevation_m, "max": surface.elevation_m}
        ground_label = "flat ground at the take-off"
    z_takeoff = float(o.takeoff_ground_m) if o.takeoff_ground_m is not None else float(ground["median"])
    if o.dtm is not None and o.takeoff_ground_m is None:
        warnings_.append(
            f"take-off assumed at the AOI's median ground, {z_takeoff:.1f} m on the DTM: "
            "give --takeoff-ground-m for the real one"
        )
    intr = cam.intrinsics()
    tilt = math.radians(90.0 + o.pitch_deg)  # off nadir
    # Height above the ground for the target GSD at the image centre (slant range r = gsd·f·sqrt(cos i)).
    if o.gsd_cm is not None:
        agl = height_for_gsd_m(o.gsd_cm / 100.0, intr.focal_px, tilt)
    else:
        agl = float(o.altitude_m)  # type: ignore[arg-type]
    if agl > o.max_altitude_m:
        best = gsd_at_height_m(o.max_altitude_m, intr.focal_px, tilt) * 100
        raise InputError(
            f"a GSD of {o.gsd_cm:g} cm needs {agl:.0f} m above the ground with {cam.name}, over the "
            f"{o.max_altitude_m:g} m limit (--max-altitude-m); the best possible is {best:.2f} cm"
        )
    # Spacing from the footprint on level ground: at the highest ground of the AOI for a constant
    # altitude, so that the overlaps asked are met everywhere (they grow over lower ground).
    rise = ground["max"] - z_takeoff if o.dtm is not None else 0.0
    spacing_agl = agl if o.terrain == "follow" else agl - rise
    if o.terrain == "constant" and o.dtm is not None and spacing_agl < 0.3 * agl:
        raise InputError(
            f"the ground rises {ground['max'] - z_takeoff:.0f} m above the take-off: a constant "
            f"{agl:.0f} m would pass within {max(spacing_agl, 0):.0f} m of it; use --terrain follow"
        )
    along_len, across_w, ahead = _footprint_shape(intr, o.pitch_deg, spacing_agl)
    along = along_len * (1 - o.front_overlap / 100.0)
    across = across_w * (1 - o.side_overlap / 100.0)
    _refuse_too_many_photos(area_geom, along, across, 2 if o.grid == "double" else 1, cam.name)
    return _Site(
        cam, intr, area_geom, work_crs, surface, ground, ground_label, z_takeoff, agl, spacing_agl, along_len,
        across_w, ahead, along, across,
    )  # fmt: skip


@dataclass(frozen=True)
class _Flight:
    """The lines and photos of the flight, their footprints on the ground, and how it is flown."""

    directions: list[float]
    shots: list[dict[str, Any]]
    lines: list[dict[str, Any]]
    xy: np.ndarray
    grid_heading: np.ndarray
    z: np.ndarray
    rots: np.ndarray
    centres: np.ndarray
    table: Any  # photos.footprint.FootprintTable
    polys: list[Any]
    agl_photo: np.ndarray
    heading_true: np.ndarray
    lonlat: np.ndarray
    speed: float
    length_m: float


def _fly(aoi: Path, site: _Site, o: PlanOptions, warnings_: list[str], s_grid: Feedback, s_foot: Feedback) -> _Flight:
    """The lines across the AOI, a photo every spacing along them, each photo's pose and its
    footprint on the ground; the speed the camera can keep up."""
    directions = [
        _best_direction(site.area, site.across) if o.direction_deg is None else float(o.direction_deg) % 180.0
    ]
    if o.grid == "double":
        directions.append((directions[0] + 90.0) % 180.0)
    shots: list[dict[str, Any]] = []
    lines: list[dict[str, Any]] = []
    for d in directions:
        s, ln = _lines_and_shots(
            site.area, d, site.along, site.across, site.along_len, site.across_w, site.ahead, len(lines)
        )
        shots += s
        lines += ln
    if not shots:
        raise InputError("the AOI is smaller than one photo spacing: nothing to plan", path=aoi)
    s_grid.progress(1.0)

    xy = np.array([(s["x"], s["y"]) for s in shots])
    grid_heading = np.array([s["grid_heading_deg"] for s in shots])
    if o.terrain == "follow":
        ground_z = _ground_under(site.surface, xy, grid_heading, site.along_len, site.across_w, site.ahead)
        z = ground_z + site.agl
    else:
        z = np.full(len(shots), site.z_takeoff + site.agl)
    rots = rotation_from_ypr(grid_heading, np.full(len(xy), o.pitch_deg), np.zeros(len(xy)))
    centres = np.c_[xy, z]
    cams = [PosedCamera(site.intr, Pose(c, r)) for c, r in zip(centres, rots)]
    table = compute_footprints(cams, site.surface, max_range_m=max(1000.0, 20 * site.agl))
    s_foot.progress(0.6)
    polys = list(shapely.make_valid(shapely.polygons(table.rings)))
    agl_photo = np.asarray(table.altitude_m, float)
    if (agl_photo > o.max_altitude_m * 1.001).any():
        warnings_.append(
            f"{int((agl_photo > o.max_altitude_m).sum())} photos fly higher than {o.max_altitude_m:g} m "
            f"above the ground below them (up to {agl_photo.max():.0f} m): the terrain falls away"
        )
    if (agl_photo < 0.5 * site.agl).any():
        warnings_.append(
            f"{int((agl_photo < 0.5 * site.agl).sum())} photos pass within {agl_photo.min():.0f} m of the "
            "ground: the terrain rises; consider --terrain follow"
        )
    heading_true = _true_headings(xy, grid_heading, site.work_crs)
    lonlat = np.array(transformer(site.work_crs, WGS84).transform(xy[:, 0], xy[:, 1])).T
    interval_m = site.along
    speed = min(o.speed_m_s, interval_m / o.min_interval_s)
    if speed < o.speed_m_s:
        warnings_.append(
            f"speed lowered to {speed:.1f} m/s: one photo every {interval_m:.1f} m needs "
            f"{o.min_interval_s:g} s between photos"
        )
    length_m = _flight_length(shots)
    s_foot.progress(1.0)
    return _Flight(
        directions, shots, lines, xy, grid_heading, z, rots, centres, table, polys, agl_photo, heading_true, lonlat,
        speed, length_m,
    )  # fmt: skip


@dataclass(frozen=True)
class _Control:
    """The GCPs, the markers' print size and how many photos see each."""

    rows: list[dict[str, Any]]
    marker_m: float  # the print size needed
    laid_m: float  # the size the sightings were counted with
    n_cells: int
    module_px: float
    worst_gsd_m: float


def _gcp_sightings(site: _Site, flight: _Flight, o: PlanOptions, warnings_: list[str]) -> _Control:
    """Where the GCPs go (or where given ones are), the marker size the largest GSD at any GCP
    needs, and the photos that see each marker whole (expected, sure, at most)."""
    rows, notes = _gcp_positions(
        o.gcps, o.gcp_crs, site.area, site.work_crs, site.surface, site.across_w, o.marker_dictionary,
        float(flight.z.min()),
    )  # fmt: skip
    warnings_ += notes
    module_px = min_module_px(o.marker_dictionary)
    n_cells = get_dictionary(o.marker_dictionary).markerSize + 2
    # The print size from the largest GSD at any GCP among the photos that see it; then the counts
    # with markers of that size (whole in the frame, its white border included).
    at_gcps = [
        _seen_by(flight.centres, flight.rots, site.intr, np.array([g["x"], g["y"], g["z"]]), o.margin, 0.0)[
            "gsd_max_cm"
        ]
        for g in rows
    ]
    seen = [v for v in at_gcps if math.isfinite(v)]
    worst_gsd_m = max(seen) / 100.0 if seen else float(np.nanmax(flight.table.gsd_max_m))
    marker_m = _round_up(n_cells * module_px * DETECTION_SAFETY * worst_gsd_m, MIN_MARKER_STEP_M)
    laid_m = marker_m if o.marker_size_m is None else float(o.marker_size_m)
    if laid_m < marker_m:
        warnings_.append(
            f"markers of {laid_m * 100:.0f} cm are too small for this plan: {marker_m * 100:.0f} cm "
            f"are needed ({o.marker_dictionary} at up to {worst_gsd_m * 100:.2f} cm GSD)"
        )
    quiet = laid_m * (n_cells + 2) / n_cells
    for g in rows:
        g.update(_seen_by(flight.centres, flight.rots, site.intr, np.array([g["x"], g["y"], g["z"]]), o.margin, quiet))
    for g in rows:
        g["marker_side_px"] = marker_m / (g["gsd_max_cm"] / 100.0) if g["n_photos"] else float("nan")
        g["marker_size_m"] = marker_m
    few = [g["name"] for g in rows if g["n_photos_sure"] < 3]
    if few:
        warnings_.append(f"GCPs not surely seen in 3 planned photos: {', '.join(few)}")
    return _Control(rows, marker_m, laid_m, n_cells, module_px, worst_gsd_m)


#: What ``plan`` writes into its folder (removed together when it is canceled while writing).
PLAN_PRODUCTS = ("plan.gpkg", "overlap.tif", "plan.kml", "litchi.csv", "summary.json", "markers")


def _remove_plan(output: Path) -> None:
    import shutil

    for name in PLAN_PRODUCTS:
        path = output / name
        if path.is_dir() and not path.is_symlink():
            shutil.rmtree(path, ignore_errors=True)
        elif path.exists() or path.is_symlink():
            path.unlink(missing_ok=True)


@dataclass(frozen=True)
class _Files:
    plan: Path
    overlap: Path
    kml: Path
    litchi: Path
    sheets: list[Path]
    coverage: dict[str, Any]
    front_m: float
    side_m: float


def _write(
    output: Path,
    site: _Site,
    flight: _Flight,
    control: _Control,
    o: PlanOptions,
    warnings_: list[str],
    s_write: Feedback,
) -> _Files:
    """The overlap raster, plan.gpkg (aoi, photos, lines, footprints, gcps), plan.kml, litchi.csv
    and the markers' print sheets; the coverage and overlaps measured on the footprints."""
    output.mkdir(parents=True, exist_ok=True)
    overlap_path = output / "overlap.tif"

    write_overlap(overlap_path, flight.polys, site.work_crs, max(0.05, site.across_w / 40.0))
    coverage = _coverage(overlap_path, site.area, o.front_overlap, o.side_overlap, o.grid)
    front_m, side_m = line_overlaps(flight.polys, [s["line"] for s in flight.shots])
    crs, shots, lines, rows = site.work_crs, flight.shots, flight.lines, control.rows
    photos_df = gpd.GeoDataFrame(
        {
            "name": [f"P{i + 1:04d}" for i in range(len(shots))],
            "index": np.arange(len(shots)),
            "line": [s["line"] for s in shots],
            "altitude_m": flight.z - site.z_takeoff,
            "agl_m": flight.agl_photo,
            "z_m": flight.z,
            "heading_deg": flight.heading_true,
            "grid_heading_deg": flight.grid_heading,
            "pitch_deg": np.full(len(shots), o.pitch_deg),
            "gsd_cm": flight.table.gsd_m * 100,
            "longitude_deg": flight.lonlat[:, 0],
            "latitude_deg": flight.lonlat[:, 1],
        },
        geometry=shapely.points(flight.xy),
        crs=crs,
    )
    foot_df = gpd.GeoDataFrame(
        {
            "name": photos_df["name"],
            "line": photos_df["line"],
            "gsd_cm": flight.table.gsd_m * 100,
            "gsd_min_cm": flight.table.gsd_min_m * 100,
            "gsd_max_cm": flight.table.gsd_max_m * 100,
            "area_m2": shapely.area(np.asarray(flight.polys)),
            "clipped": flight.table.clipped,
        },
        geometry=flight.polys,
        crs=crs,
    )
    lines_df = gpd.GeoDataFrame(
        {
            "line": [ln["line"] for ln in lines],
            "grid_heading_deg": [ln["grid_heading_deg"] for ln in lines],
            "length_m": [ln["length_m"] for ln in lines],
            "n_photos": [ln["n_photos"] for ln in lines],
        },
        geometry=[shapely.LineString(ln["ends"]) for ln in lines],
        crs=crs,
    )
    gcp_df = gpd.GeoDataFrame(
        {k: [g[k] for g in rows] for k in _GCP_LAYER_FIELDS},
        geometry=shapely.points([(g["x"], g["y"]) for g in rows]) if rows else [],
        crs=crs,
    )
    aoi_df = gpd.GeoDataFrame({"area_ha": [site.area.area / 1e4]}, geometry=[site.area], crs=crs)
    plan_path = write_vector(
        output / "plan.gpkg",
        {"photos": photos_df, "lines": lines_df, "footprints": foot_df, "gcps": gcp_df, "aoi": aoi_df},
    )
    kml = _write_kml(output / "plan.kml", photos_df, lines_df, gcp_df, site.area, crs, o.terrain)
    litchi, litchi_note = _write_litchi(
        output / "litchi.csv", photos_df, lines_df, crs, flight.speed, site.along, o.terrain
    )
    if litchi_note:
        warnings_.append(litchi_note)
    sheets = _write_marker_sheets(output / "markers", rows, o.marker_dictionary, control.marker_m)
    s_write.progress(0.7)
    return _Files(plan_path, overlap_path, kml, litchi, sheets, coverage, front_m, side_m)


#: What plan says of each GCP: in the gcps layer (with the print size) and in summary.json (with x, y).
_GCP_FIGURES = ("z_m", "n_photos", "n_photos_sure", "n_photos_max", "gsd_max_cm", "marker_side_px")
_GCP_LAYER_FIELDS = ("name", "marker_id", "role", *_GCP_FIGURES, "marker_size_m")
_GCP_SUMMARY_FIELDS = ("name", "marker_id", "role", "x", "y", *_GCP_FIGURES)


def _summary(
    site: _Site,
    flight: _Flight,
    control: _Control,
    files: _Files,
    o: PlanOptions,
    warnings_: list[str],
    seconds: float,
) -> dict[str, Any]:
    """summary.json: the camera, the ground, the flight, the overlaps measured, the GCPs and markers."""
    # One piece: a single literal that reads as the file's schema, top to bottom.
    cam = site.cam
    gsd = np.asarray(flight.table.gsd_m * 100, float)  # summary.json's fields are in cm
    return {
        "camera": {
            "name": cam.name,
            "sensor_width_mm": cam.sensor_width_mm,
            "focal_mm": cam.focal_mm,
            "width_px": cam.width_px,
            "height_px": cam.height_px,
            "focal_px": cam.focal_px,
            "source": cam.source,
        },
        "crs": crs_to_text(site.work_crs),
        "aoi_area_ha": site.area.area / 1e4,
        "ground": {
            "model": site.ground_label,
            "takeoff_ground_m": site.z_takeoff,
            "min_m": site.ground["min"],
            "median_m": site.ground["median"],
            "max_m": site.ground["max"],
        },
        "terrain": o.terrain,
        "altitude_m": site.agl,
        "altitude_meaning": "above the take-off" if o.terrain == "constant" else "above the ground under each photo",
        "target_gsd_cm": o.gsd_cm,
        "gsd_cm": {"min": float(np.nanmin(gsd)), "median": float(np.nanmedian(gsd)), "max": float(np.nanmax(gsd))},
        "pitch_deg": o.pitch_deg,
        "grid": o.grid,
        "directions_grid_deg": flight.directions,
        "front_overlap_pct": o.front_overlap,
        "side_overlap_pct": o.side_overlap,
        "spacing": {
            "along_m": site.along,
            "across_m": site.across,
            "footprint_along_m": site.along_len,
            "footprint_across_m": site.across_w,
            "planned_at_agl_m": site.spacing_agl,
        },
        "overlap_on_footprints_pct": {"front": files.front_m, "side": files.side_m},
        "photos": len(flight.shots),
        "lines": len(flight.lines),
        "flight_length_m": flight.length_m,
        "speed_m_s": flight.speed,
        "flight_time_min": flight.length_m / flight.speed / 60.0,
        "photo_interval_s": site.along / flight.speed,
        "coverage": files.coverage,
        "gcps": [{k: g[k] for k in _GCP_SUMMARY_FIELDS} for g in control.rows],
        "gcp_sightings": f"expected count with the flown pose off the plan by {FLIGHT_POSITION_SIGMA_M} m and "
        f"{FLIGHT_ATTITUDE_SIGMA_DEG} deg (1 sigma); sure: probability >= 0.9; max: >= 0.1",
        "gcp_rule": "given positions"
        if o.gcps and not o.gcps.strip().isdigit()
        else "5 up to 5 ha (corners and centre), one more per further 10 ha, at most 40; "
        "about 60 % on the perimeter, the rest spread inside",
        "marker": {
            "dictionary": o.marker_dictionary,
            "size_m": control.marker_m,
            "laid_size_m": control.laid_m,
            "cells": control.n_cells,
            "min_module_px": control.module_px,
            "safety": DETECTION_SAFETY,
            "rule": "black square = cells x min_module_px x safety x the largest GSD at a GCP, "
            "rounded up to 5 cm; a one-module white border around it",
        },
        "files": {
            "plan": files.plan.name,
            "overlap": files.overlap.name,
            "kml": files.kml.name,
            "litchi": files.litchi.name,
            "markers": [p.name for p in files.sheets],
        },
        "warnings": warnings_,
        "seconds": seconds,
    }


def _check_options(
    gsd_cm: float | None,
    altitude_m: float | None,
    front: float,
    side: float,
    terrain: str,
    dtm: Path | None,
    pitch_deg: float,
    speed: float,
    interval: float,
    max_alt: float,
) -> None:
    if (gsd_cm is None) == (altitude_m is None):
        raise InputError("give one of --gsd-cm or --altitude-m")
    if gsd_cm is not None and not 0.05 <= gsd_cm <= 100:
        raise InputError(f"--gsd-cm {gsd_cm:g} is out of range (0.05 to 100 cm)")
    if altitude_m is not None and not 1 <= altitude_m <= 2000:
        raise InputError(f"--altitude-m {altitude_m:g} is out of range (1 to 2000 m)")
    for name, v in (("--front-overlap", front), ("--side-overlap", side)):
        if not 0 <= v < 100:
            raise InputError(f"{name} {v:g} % is not possible: give 0 to 99 % (photos cannot overlap 100 %)")
    if terrain == "follow" and dtm is None:
        raise InputError("--terrain follow needs a --dtm")
    if not -90 <= pitch_deg <= -30:
        raise InputError(f"--pitch-deg {pitch_deg:g}: give -90 (nadir) to -30 (oblique)")
    if speed <= 0 or interval <= 0 or max_alt <= 0:
        raise InputError("--speed-m-s, --min-interval-s and --max-altitude-m must be positive")


def _read_aoi(path: Path, crs: CRS | None) -> tuple[Any, CRS, list[str]]:
    """The AOI as one valid (multi)polygon in the working CRS, with what was repaired."""
    if not path.exists():
        raise InputError("no such file", path=path)
    try:
        if path.is_file() and not len(pyogrio.list_layers(path)):
            raise InputError("the AOI file holds no layer (an empty file?): give an area", path=path)
        df = gpd.read_file(path, engine="pyogrio")
    except InputError:
        raise
    except Exception as e:  # pyogrio raises its own DataSourceError and friends
        raise InputError(f"cannot read the AOI: {e}", path=path) from None
    notes = []
    polys = [g for g in df.geometry if g is not None and not g.is_empty]
    polys = [g for g in polys if g.geom_type in ("Polygon", "MultiPolygon")]
    if not polys:
        kinds = sorted({g.geom_type for g in df.geometry if g is not None})
        raise InputError(f"the AOI holds no polygon ({', '.join(kinds) or 'no geometry'}): give an area", path=path)
    if df.crs is None:
        raise InputError("the AOI has no CRS", path=path)
    xy = shapely.get_coordinates(polys)
    if not np.isfinite(xy).all():
        raise InputError("the AOI has a coordinate that is not a number (NaN or infinite)", path=path)
    src_crs = CRS.from_user_input(df.crs)
    if src_crs.is_geographic and (np.abs(xy[:, 0]).max() > 180 or np.abs(xy[:, 1]).max() > 90):
        raise InputError(
            f"the AOI's coordinates ({xy[0, 0]:.0f}, {xy[0, 1]:.0f}) are not degrees, though its CRS "
            f"({src_crs.name}) says so: projected numbers? give the file its real CRS",
            path=path,
        )
    if src_crs.is_geographic and np.ptp(xy[:, 0]) > 180.0:
        # across the antimeridian: 179.9 and -179.9 are 0.2 degrees apart, not 359.8 (the centre's UTM
        # zone was otherwise 177 degrees away); longitudes unwrapped past 180, as PROJ takes them
        polys = [shapely.transform(g, lambda c: np.c_[np.where(c[:, 0] < 0, c[:, 0] + 360.0, c[:, 0]), c[:, 1]])
                 for g in polys]  # fmt: skip
        notes.append("the AOI crosses the antimeridian: its longitudes read as one area across 180 degrees")
    geom = shapely.union_all(polys)
    if not geom.is_valid:
        reason = shapely.is_valid_reason(geom)
        geom = shapely.make_valid(geom)
        geom = shapely.union_all([g for g in shapely.get_parts(geom) if g.geom_type in ("Polygon", "MultiPolygon")])
        notes.append(
            f"the AOI was not a valid polygon ({reason}): repaired by GEOS make_valid; check it in plan.gpkg, layer aoi"
        )
    if geom.is_empty or geom.area <= 0.0:
        raise InputError("the AOI's polygon has no area (its points lie on a line): give an area", path=path)
    src = src_crs
    if crs is not None:  # a map grid: the faces that parse it say so
        work = crs
        _refuse_untrue_scale(work, _reproject(geom, src, WGS84).centroid)
    elif src.is_projected:
        work = src
    else:  # the UTM zone of the AOI's centre, also when the AOI crosses a zone edge
        c = _reproject(geom, src, WGS84).centroid
        work = utm_crs_for((float(c.x) + 180.0) % 360.0 - 180.0, float(c.y))
    geom = _reproject(geom, src, work)
    if geom.area < 1.0:
        raise InputError(f"the AOI is {geom.area:.2f} m²: too small to plan", path=path)
    _refuse_parts_apart(geom, path)

    if abs(horizontal_unit_m(work) - 1.0) > 1e-9:
        raise InputError(f"plan in a CRS in metres: {crs_to_text(work)} is not (give --crs)")
    return geom, work, notes


#: Parts of an AOI farther apart than this (m) are separate flights: lines across the gap were
#: flown (two fields 8.7 km apart: 2,440 photos, 93 minutes).
MAX_PART_GAP_M = 1000.0


def _refuse_parts_apart(geom: Any, path: Path) -> None:
    """An AOI of parts that lie apart is refused, naming the gap: plan each part on its own."""
    if len(shapely.get_parts(geom)) < 2:
        return
    # parts within the gap of each other are one site: grown by half of it, they join
    sites = list(shapely.get_parts(shapely.union_all(shapely.buffer(shapely.get_parts(geom), MAX_PART_GAP_M / 2))))
    if len(sites) > 1:
        gap = min(float(a.distance(b)) for i, a in enumerate(sites) for b in sites[i + 1 :]) + MAX_PART_GAP_M
        raise InputError(
            f"the AOI has {len(sites)} sites {gap / 1000:,.1f} km apart or more: one flight would cross the gap "
            f"(over {MAX_PART_GAP_M / 1000:g} km); plan each site on its own",
            path=path,
        )


#: A plan's metres are the ground's: a CRS whose scale at the AOI is further from 1 than this
#: (Web Mercator: 1.28 at 38 deg N) would put the photos too close or too far apart.
MAX_SCALE_ERROR = 0.01


def _refuse_untrue_scale(crs: CRS, centre_lonlat: Any) -> None:

    f = Proj(crs).get_factors(float(centre_lonlat.x), float(centre_lonlat.y))
    k = max(abs(f.meridional_scale - 1.0), abs(f.parallel_scale - 1.0))
    if not math.isfinite(k) or k > MAX_SCALE_ERROR:
        raise InputError(
            f"--crs {crs_to_text(crs)}: a metre of it is {1 / f.parallel_scale:.3f} m on the ground here, so "
            "spacings and GSD planned in it would be off: plan in a CRS true to the ground (the default, "
            "the AOI's UTM zone) and reproject the products if that CRS is needed"
        )


def _reproject(geom: Any, src: CRS, dst: CRS) -> Any:

    if src.equals(dst):
        return geom
    t = transformer(src, dst)
    return shapely.transform(geom, lambda c: np.c_[t.transform(c[:, 0], c[:, 1])])


#: More photos than any one flight plan holds (a big mapping job is a few thousand): refused with
#: the count before anything is built (a county at 2 cm would take tens of GB).
MAX_PLAN_PHOTOS = 50_000


def _refuse_too_many_photos(area: Any, along_m: float, across_m: float, grids: int, camera: str) -> None:
    x0, y0, x1, y1 = area.bounds
    lines = (max(x1 - x0, y1 - y0) / across_m + 1) * grids
    n = grids * area.area / (along_m * across_m) + lines
    if n > MAX_PLAN_PHOTOS:
        count = f"{n / 1e6:.1f} M" if n >= 1e6 else f"{n:,.0f}"
        raise InputError(
            f"the plan would take about {count} photos ({area.area / 1e6:,.2f} km² at {along_m:.2f} x {across_m:.2f} m "
            f"spacing with {camera}), over the {MAX_PLAN_PHOTOS:,} a plan holds: split the AOI, or fly higher "
            "(a larger GSD)"
        )


def _ground_stats(surface: Surface, area: Any, dtm: Any = None) -> dict[str, float]:

    x0, y0, x1, y1 = area.bounds
    n = 60
    xs, ys = np.meshgrid(np.linspace(x0, x1, n), np.linspace(y0, y1, n))
    inside = shapely.contains_xy(area, xs, ys)
    if not inside.any():
        inside = np.ones_like(inside)
    covered = 1.0
    if isinstance(surface, GridSurface):
        # the DTM itself, not the ground carried beyond its edge (read with extend)
        c, r = surface.colrow(xs[inside], ys[inside])
        covered = float(np.isfinite(sample_grid(surface.grid, c, r)).mean())
        if covered < 0.5:
            gx0, gy0 = surface.transform @ (0, 0)
            gx1, gy1 = surface.transform @ (surface.grid.shape[1], surface.grid.shape[0])
            far_m = float(np.hypot((x0 + x1 - gx0 - gx1) / 2, (y0 + y1 - gy0 - gy1) / 2))
            raise InputError(
                f"the DTM covers {100 * covered:.0f} % of the AOI (their centres are {far_m / 1000:,.1f} km apart): "
                "give a DTM of this area",
                path=dtm,
            )
    z = surface.elevation(xs[inside], ys[inside])
    z = z[np.isfinite(z)]
    if z.size == 0:
        raise InputError("the DTM does not cover the AOI", path=dtm)
    return {"min": float(z.min()), "median": float(np.median(z)), "max": float(z.max()), "covered": covered}


def _footprint_shape(intr: Intrinsics, pitch_deg: float, agl: float) -> tuple[float, float, float]:
    """A photo's footprint on level ground ``agl`` below: length along the line (through the image
    centre), width across it (at the centre's ground point) and how far ahead of the drone that
    point is."""
    cam = PosedCamera(intr, Pose(np.array([0.0, 0.0, agl]), rotation_from_ypr(0.0, pitch_deg, 0.0)))
    t = compute_footprints([cam], FlatSurface(0.0), per_side=64, max_range_m=50 * agl)
    if t.clipped[0]:
        raise InputError(f"at pitch {pitch_deg:g}° the photo sees the horizon: plan a steeper pitch")
    ring = t.rings[0]
    ahead = agl * math.tan(math.radians(90.0 + pitch_deg))

    poly = shapely.Polygon(ring)
    big = 100 * agl
    along = shapely.intersection(poly, shapely.LineString([(0, -big), (0, big)])).length
    across = shapely.intersection(poly, shapely.LineString([(-big, ahead), (big, ahead)])).length
    return float(along), float(across), float(ahead)


def _axes(direction_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """Unit vectors along the lines (clockwise from grid north) and across them (to the right)."""
    a = math.radians(direction_deg)
    return np.array([math.sin(a), math.cos(a)]), np.array([math.cos(a), -math.sin(a)])


def _best_direction(area: Any, across: float) -> float:
    """The line direction with the fewest lines; ties go to the shorter total line length."""
    pts = np.array(shapely.get_coordinates(shapely.convex_hull(area)))
    best = (math.inf, math.inf, 0.0)
    for d in np.arange(0.0, 180.0, 1.0):
        u, v = _axes(float(d))
        pv, pu = pts @ v, pts @ u
        n = math.ceil((pv.max() - pv.min()) / across) + 1
        key = (n, (pu.max() - pu.min()) * n, float(d))
        best = min(best, key)
    return best[2]


def _lines_and_shots(
    area: Any,
    direction: float,
    along: float,
    across: float,
    along_len: float,
    across_w: float,
    ahead: float,
    first_line: int,
) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """Boustrophedon lines across the AOI: outermost lines on its edges, each line's photos over the
    AOI within its swath, extended by half a footprint at both ends (full front overlap there)."""
    u, v = _axes(direction)
    pts = np.array(shapely.get_coordinates(area))
    pv = pts @ v
    width = float(pv.max() - pv.min())
    n_lines = max(1, math.ceil(width / across - 1e-9) + 1)
    v_mid = (pv.max() + pv.min()) / 2
    v_lines = v_mid + (np.arange(n_lines) - (n_lines - 1) / 2) * across
    shots: list[dict[str, Any]] = []
    lines: list[dict[str, Any]] = []
    big = 1e7
    for k, vk in enumerate(v_lines):
        half = across_w / 2
        strip = shapely.Polygon(
            [
                u * -big + v * (vk - half),
                u * big + v * (vk - half),
                u * big + v * (vk + half),
                u * -big + v * (vk + half),
            ]
        )
        part = shapely.intersection(area, strip)
        if part.is_empty or part.area <= 0:
            continue
        pu = np.array(shapely.get_coordinates(part)) @ u
        u0, u1 = float(pu.min()) - along_len / 2, float(pu.max()) + along_len / 2
        n = max(2, math.ceil((u1 - u0) / along - 1e-9) + 1)
        u_mid = (u0 + u1) / 2
        us = u_mid + (np.arange(n) - (n - 1) / 2) * along
        forward = len(lines) % 2 == 0
        heading = direction if forward else (direction + 180.0) % 360.0
        if not forward:
            us = us[::-1]
        step = 1.0 if forward else -1.0
        line_no = first_line + len(lines) + 1
        ends = []
        for uu in us:
            # the ground point of the image centre is ``ahead`` of the drone along its heading
            p = u * (uu - step * ahead) + v * vk
            shots.append(
                {
                    "x": float(p[0]),
                    "y": float(p[1]),
                    "grid_heading_deg": float((heading + 180) % 360 - 180),
                    "line": line_no,
                }
            )
            ends.append((float(p[0]), float(p[1])))
        lines.append(
            {
                "line": line_no,
                "grid_heading_deg": heading,
                "length_m": float(abs(us[-1] - us[0])),
                "n_photos": int(n),
                "ends": [ends[0], ends[-1]],
                "k": k,
            }
        )
    return shots, lines


def _ground_under(
    surface: Surface, xy: np.ndarray, heading: np.ndarray, along_len: float, across_w: float, ahead: float
) -> np.ndarray:
    """Mean ground over the central half of each photo's nominal footprint (5 x 5 samples): what
    terrain following keeps the height above."""
    s = np.linspace(-0.25, 0.25, 5)  # the central half: the centre GSD held, small bumps averaged out
    su, sv = (g.ravel() for g in np.meshgrid(s * along_len + ahead, s * across_w))
    a = np.radians(heading)[:, None]
    px = xy[:, :1] + np.sin(a) * su + np.cos(a) * sv  # along = (sin, cos), across = (cos, -sin)
    py = xy[:, 1:] + np.cos(a) * su - np.sin(a) * sv
    z = surface.elevation(px.ravel(), py.ravel()).reshape(px.shape)
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        out: np.ndarray = np.nanmean(z, axis=1)
    if not np.isfinite(out).all():
        raise InputError("the DTM does not cover every planned photo: give a DTM that covers the AOI and a margin")
    return out


def _true_headings(xy: np.ndarray, grid_heading: np.ndarray, crs: CRS) -> np.ndarray:
    """Grid headings as azimuths from true north (the meridian convergence taken off)."""
    lon, lat = transformer(crs, WGS84).transform(xy[:, 0], xy[:, 1])
    convergence, _ = grid_north(crs, lon, lat)
    return np.asarray((np.asarray(grid_heading) - convergence + 180.0) % 360.0 - 180.0)


def _flight_length(shots: list[dict[str, Any]]) -> float:
    xy = np.array([(s["x"], s["y"]) for s in shots])
    return float(np.hypot(*np.diff(xy, axis=0).T).sum()) if len(xy) > 1 else 0.0


def _coverage(path: Path, area: Any, front: float, side: float, grid: str) -> dict[str, Any]:
    """Share of the AOI seen by at least N photos, N = what the overlaps give inside the block."""
    with rasterio.open(path) as src:
        count = src.read(1)
        inside = geometry_mask([area], out_shape=count.shape, transform=src.transform, invert=True, all_touched=False)
    need = max(1, int(math.floor(1 / (1 - front / 100) + 1e-9)) * int(math.floor(1 / (1 - side / 100) + 1e-9)))
    if grid == "double":
        need *= 2
    c = count[inside].astype(int)
    if c.size == 0:
        return {"required_photos": need}
    return {
        "required_photos": need,
        "required_rule": "floor(1/(1-front)) x floor(1/(1-side)) photos (x2 for a double grid)",
        "aoi_share_at_required_pct": float(100 * (c >= need).mean()),
        "aoi_share_seen_by_3_pct": float(100 * (c >= 3).mean()),
        "aoi_share_seen_pct": float(100 * (c >= 1).mean()),
        "median_photos": float(np.median(c)),
    }


def line_overlaps(polys: list[Any], line: list[int], max_pairs: int = 1500) -> tuple[float, float]:
    """Mean front overlap (consecutive photos of a line) and side overlap (each photo and the nearest
    photo of the next line), percent of a footprint's area, as footprints give them."""
    polys_a = np.asarray(polys, dtype=object)
    line_a = np.asarray(line)
    areas = shapely.area(polys_a)
    cent = shapely.get_coordinates(shapely.centroid(polys_a))
    fa, fb, sa, sb = [], [], [], []
    ids = list(dict.fromkeys(line_a.tolist()))
    for k, ln in enumerate(ids):
        idx = np.flatnonzero(line_a == ln)
        fa += idx[:-1].tolist()
        fb += idx[1:].tolist()
        if k + 1 < len(ids):
            nxt = np.flatnonzero(line_a == ids[k + 1])
            near = np.argmin(np.hypot(*(cent[nxt][None, :, :] - cent[idx][:, None, :]).transpose(2, 0, 1)), axis=1)
            sa += idx.tolist()
            sb += nxt[near].tolist()

    def share(a: list[int], b: list[int]) -> np.ndarray:
        ia, ib = np.asarray(a, int), np.asarray(b, int)
        if len(ia) > max_pairs:  # an even sample: the median of a large block needs no more
            keep = np.linspace(0, len(ia) - 1, max_pairs).round().astype(int)
            ia, ib = ia[keep], ib[keep]
        result: np.ndarray = shapely.area(shapely.intersection(polys_a[ia], polys_a[ib])) / areas[ia]
        return result

    front, side = share(fa, fb), share(sa, sb)
    # ends of lines overlap less sideways where the AOI narrows: the median is the block's figure
    return (
        float(100 * np.median(front)) if front.size else float("nan"),
        float(100 * np.median(side)) if side.size else float("nan"),
    )


# ---------------------------------------------------------------------------------------------
# GCPs


#: A GCP farther than this (m) from the area flown is seen by no photo: all of them so far is another
#: site's file or another CRS (refused, with the distance); some, a wrong line (said).
FAR_GCP_M = 2000.0


def _given_gcps(
    path: str, gcp_crs: CRS | None, crs: CRS, surface: Surface, camera_z_min: float, site: Any = None
) -> tuple[list[tuple[str, float, float, float]], list[str]]:
    """A GCP file's points in ``crs``: name, x, y and the height to use, with what was assumed.
    Heights that are placeholders (all equal), missing, or at or above the cameras are taken from
    the ground model instead: a GCP above the photos would be seen by none of them. ``site`` (a
    geometry in ``crs``: the AOI, or the cameras' hull) is where they must be."""
    gs = read_gcp_file(path, gcp_crs)
    t = transformer(gs.crs, crs)
    x, y = (np.asarray(v, float) for v in t.transform([p.x for p in gs.points], [p.y for p in gs.points]))
    notes = []
    if site is not None and len(x):
        far_m = np.where(np.isfinite(x) & np.isfinite(y), shapely.distance(site, shapely.points(np.c_[x, y])), np.inf)
        if far_m.min() > FAR_GCP_M:
            near = float(far_m.min())
            raise InputError(
                f"its GCPs lie {near / 1000:,.1f} km or more from the area flown (in {gs.crs.name}): another site's "
                "file, or another CRS (give --gcp-crs)",
                path=Path(path),
            )
        far = [f"{p.name} ({d / 1000:,.1f} km)" for p, d in zip(gs.points, far_m) if d > FAR_GCP_M]
        if far:
            notes.append(f"GCPs far from the area flown, seen by no photo (a wrong line?): {', '.join(far[:8])}")
    z = np.array([p.z for p in gs.points], float)
    ground = surface.elevation(x, y)
    if heights_are_placeholders(z):
        notes.append(f"all GCP heights are {z[0]:g}: taken as placeholders; heights from the ground model")
        z = ground.copy()
    bad = ~np.isfinite(z) | (z >= camera_z_min - 1.0)
    if bad.any():
        names = ", ".join(p.name for p, b in zip(gs.points, bad) if b)
        notes.append(f"GCP heights missing or not below the photos ({names}): heights from the ground model")
        z = np.where(bad, ground, z)
    return [(p.name, float(a), float(b), float(c)) for p, a, b, c in zip(gs.points, x, y, z)], notes


def _gcp_positions(
    gcps: str,
    gcp_crs: CRS | None,
    area: Any,
    crs: CRS,
    surface: Surface,
    across_w: float,
    dictionary: str,
    camera_z_min: float,
) -> tuple[list[dict[str, Any]], list[str]]:
    """Given positions (a file) or N proposed ones: about 60 % on the AOI's perimeter, inset so that
    each lies inside the flown block, the rest inside, spread by farthest-point sampling."""
    text = gcps.strip()
    if text and not text.isdigit():
        pts, notes = _given_gcps(text, gcp_crs, crs, surface, camera_z_min, site=area)
        rows = []
        for name, x, y, z in pts:
            mid = marker_id_of(name)
            rows.append(
                {
                    "name": name,
                    "marker_id": -1 if mid is None else mid,
                    "role": "given",
                    "x": x,
                    "y": y,
                    "z": z,
                    "z_m": z,
                }
            )
        return rows, notes
    n = int(text) if text else default_gcp_count(area.area / 1e4)
    n_ids = get_dictionary(dictionary).bytesList.shape[0]
    if not 1 <= n <= min(200, n_ids - 1):
        raise InputError(f"--gcps {n}: give 1 to {min(200, n_ids - 1)} (the ids of {dictionary})")
    inset = min(0.25 * across_w, 0.2 * math.sqrt(area.area))
    inner = area.buffer(-inset)
    if inner.is_empty or inner.area < 0.05 * area.area:
        inner = area.buffer(-0.1 * math.sqrt(area.area))
    if inner.is_empty:
        inner = area
    ring = (
        inner.exterior if inner.geom_type == "Polygon" else max(shapely.get_parts(inner), key=lambda g: g.area).exterior
    )
    perim_pts = np.array(
        [ring.interpolate(f, normalized=True).coords[0] for f in np.linspace(0, 1, 400, endpoint=False)]
    )
    x0, y0, x1, y1 = inner.bounds
    gx, gy = np.meshgrid(np.linspace(x0, x1, 40), np.linspace(y0, y1, 40))
    ok = shapely.contains_xy(inner, gx, gy)
    inner_pts = np.c_[gx[ok], gy[ok]]
    n_perim = n if n < 4 else max(4, int(round(0.6 * n)))
    n_perim = min(n_perim, n)
    c = np.array(area.centroid.coords[0])
    chosen = [perim_pts[np.argmax(np.hypot(*(perim_pts - c).T))]]
    chosen = _farthest(perim_pts, chosen, n_perim)
    roles = ["perimeter"] * len(chosen)
    if n - n_perim > 0 and len(inner_pts):
        chosen = _farthest(inner_pts, chosen, n)
        roles += ["interior"] * (len(chosen) - len(roles))
    xy = np.array(chosen)
    ground = surface.elevation(xy[:, 0], xy[:, 1])
    return [
        {
            "name": f"GCP{i + 1:02d}",
            "marker_id": i + 1,
            "role": r,
            "x": float(x),
            "y": float(y),
            "z": float(zz),
            "z_m": float(zz),
        }
        for i, ((x, y), zz, r) in enumerate(zip(xy, ground, roles))
    ], []


def _farthest(candidates: np.ndarray, chosen: list[np.ndarray], n: int) -> list[np.ndarray]:
    chosen = list(chosen)
    d = np.min([np.hypot(*(candidates - p).T) for p in chosen], axis=0)
    while len(chosen) < n:
        i = int(np.argmax(d))
        chosen.append(candidates[i])
        d = np.minimum(d, np.hypot(*(candidates - candidates[i]).T))
    return chosen


def _seen_by(
    centres: np.ndarray, rots: np.ndarray, intr: Intrinsics, xyz: np.ndarray, margin_pct: float, marker_m: float
) -> dict[str, Any]:
    """How many planned photos will see a ground point inside the frame minus the margin, with a
    marker ``marker_m`` across (border included) whole in the frame: the expected count given how
    far a flown pose wanders from the planned one, the count sure (probability >= 0.9) and at most
    (>= 0.1); and the largest GSD there among the photos that see it as planned.
    Vectorised over the photos (planned photos have no distortion)."""
    f, cx, cy, w, h = intr.focal_px, intr.cx_px, intr.cy_px, intr.width_px, intr.height_px
    d = xyz[None, :] - centres
    cam = np.einsum("nji,nj->ni", rots, d)  # camera frame: R^T (X - C)
    depth = cam[:, 2]
    front = depth > 1e-6
    with np.errstate(divide="ignore", invalid="ignore"):
        x = f * cam[:, 0] / depth + cx
        y = f * cam[:, 1] / depth + cy
        above = np.maximum(centres[:, 2] - xyz[2], 1e-6)
        gsd = marker_gsd_m(depth, f, above)
        edge = 0.5 * marker_m / gsd
    mx, my = np.maximum(w * margin_pct / 100, edge), np.maximum(h * margin_pct / 100, edge)
    # signed distance (px) inside the allowed part of the frame; the flown pose wanders from the
    # planned one, which moves the point by sigma_px: each photo sees it with probability Phi(d/sigma)
    inside_px = np.minimum.reduce([x - (mx - 0.5), (w - 0.5 - mx) - x, y - (my - 0.5), (h - 0.5 - my) - y])
    with np.errstate(divide="ignore"):  # photos behind the point (depth <= 0): masked by `front` below
        sigma_px = FLIGHT_POSITION_SIGMA_M / gsd + f * math.tan(math.radians(FLIGHT_ATTITUDE_SIGMA_DEG))

    p = np.where(front & np.isfinite(inside_px), ndtr(np.nan_to_num(inside_px) / sigma_px), 0.0)
    ok = front & (inside_px >= 0)
    n = int(ok.sum())
    return {
        "n_photos": int(round(float(p.sum()))),
        "n_in_frame": n,
        "n_photos_sure": int((p >= 0.9).sum()),
        "n_photos_max": int((p >= 0.1).sum()),
        "gsd_max_cm": float(gsd[ok].max() * 100) if n else float("nan"),
    }


def _round_up(v: float, step: float) -> float:
    return round(math.ceil(v / step - 1e-9) * step, 4)


# ---------------------------------------------------------------------------------------------
# Exports


def _write_kml(path: Path, photos: Any, lines: Any, gcps: Any, area: Any, crs: CRS, terrain: str) -> Path:
    """KML 2.2 (OGC 07-147r2): Document > Folders of Placemarks; coordinates lon,lat,alt. Heights are
    relativeToGround (the height above the ground under each photo): KML has no
    above-take-off mode."""
    t = transformer(crs, WGS84)

    def coords(xy: np.ndarray, alt: np.ndarray | None = None) -> str:
        lon, lat = t.transform(xy[:, 0], xy[:, 1])
        a = np.zeros(len(lon)) if alt is None else alt
        return " ".join(f"{o:.8f},{la:.8f},{h:.2f}" for o, la, h in zip(lon, lat, a))

    def data(items: dict[str, Any]) -> str:
        return (
            "<ExtendedData>"
            + "".join(f'<Data name="{escape(k)}"><value>{escape(str(v))}</value></Data>' for k, v in items.items())
            + "</ExtendedData>"
        )

    flies = "a constant altitude above the take-off" if terrain == "constant" else "a constant height over the terrain"
    parts = [
        '<?xml version="1.0" encoding="UTF-8"?>',
        '<kml xmlns="http://www.opengis.net/kml/2.2">',
        "<Document><name>geoortho flight plan</name>",
        "<description>Waypoint heights are above the ground under each photo (relativeToGround); "
        f"the plan flies at {flies}; "
        "summary.json has every figure.</description>",
        '<Style id="photo"><IconStyle><scale>0.5</scale></IconStyle></Style>',
        '<Style id="line"><LineStyle><color>ff00a5ff</color><width>2</width></LineStyle></Style>',
        '<Style id="gcp"><IconStyle><color>ff0000ff</color></IconStyle></Style>',
        '<Style id="aoi"><LineStyle><color>ff00ff00</color><width>2</width></LineStyle>'
        "<PolyStyle><fill>0</fill></PolyStyle></Style>",
        "<Folder><name>AOI</name>",
    ]
    for g in shapely.get_parts(area):
        ring = np.array(g.exterior.coords)
        parts.append(
            "<Placemark><name>AOI</name><styleUrl>#aoi</styleUrl><Polygon><outerBoundaryIs><LinearRing>"
            f"<coordinates>{coords(ring)}</coordinates></LinearRing></outerBoundaryIs></Polygon></Placemark>"
        )
    parts.append("</Folder><Folder><name>Flight lines</name>")
    agl = photos["agl_m"].to_numpy()
    xy = np.c_[photos.geometry.x, photos.geometry.y]
    for ln in lines.itertuples():
        sel = photos["line"].to_numpy() == ln.line
        parts.append(
            f"<Placemark><name>line {ln.line}</name><styleUrl>#line</styleUrl><LineString>"
            f"<altitudeMode>relativeToGround</altitudeMode><coordinates>{coords(xy[sel], agl[sel])}"
            "</coordinates></LineString></Placemark>"
        )
    parts.append("</Folder><Folder><name>Photos</name>")
    for i, r in enumerate(photos.itertuples()):
        parts.append(
            f"<Placemark><name>{escape(r.name)}</name><styleUrl>#photo</styleUrl>"
            + data(
                {
                    "line": r.line,
                    "altitude_above_takeoff_m": f"{r.altitude_m:.2f}",
                    "height_above_ground_m": f"{r.agl_m:.2f}",
                    "heading_deg": f"{r.heading_deg:.2f}",
                    "gimbal_pitch_deg": f"{r.pitch_deg:.1f}",
                    "gsd_cm": f"{r.gsd_cm:.2f}",
                }
            )
            + "<Point><altitudeMode>relativeToGround</altitudeMode>"
            + f"<coordinates>{coords(xy[i : i + 1], agl[i : i + 1])}</coordinates></Point></Placemark>"
        )
    parts.append("</Folder><Folder><name>GCPs</name>")
    for r in gcps.itertuples():
        p = np.array([[r.geometry.x, r.geometry.y]])
        parts.append(
            f"<Placemark><name>{escape(str(r.name))}</name><styleUrl>#gcp</styleUrl>"
            + data({"marker_id": r.marker_id, "photos": r.n_photos, "marker_size_m": r.marker_size_m})
            + f"<Point><coordinates>{coords(p)}</coordinates></Point></Placemark>"
        )
    parts.append("</Folder></Document></kml>")
    return write_text(path, "\n".join(parts) + "\n")


LITCHI_MAX_WAYPOINTS = 99
LITCHI_HEADER = (
    [
        "latitude",
        "longitude",
        "altitude(m)",
        "heading(deg)",
        "curvesize(m)",
        "rotationdir",
        "gimbalmode",
        "gimbalpitchangle",
    ]
    + [f"action{k}{i}" for i in range(1, 16) for k in ("type", "param")]
    + [
        "altitudemode",
        "speed(m/s)",
        "poi_latitude",
        "poi_longitude",
        "poi_altitude(m)",
        "poi_altitudemode",
        "photo_timeinterval",
        "photo_distinterval",
    ]
)


def _write_litchi(
    path: Path, photos: Any, lines: Any, crs: CRS, speed: float, along: float, terrain: str
) -> tuple[Path, str]:
    """Litchi Mission Hub CSV: one waypoint per photo (action 1 = take photo) when they fit in
    Litchi's 99 waypoints, else the line ends with a photo every ``along`` metres
    (photo_distinterval). Altitude mode 0 = above the take-off, 1 = above the ground."""
    gimbal_mode = 2  # interpolate: the gimbal pitch column is applied
    mode = 1 if terrain == "follow" else 0
    rows = []
    note = ""
    t = transformer(crs, WGS84)

    def row(lon: float, lat: float, alt: float, heading: float, pitch: float, photo: bool, dist: float) -> str:
        actions = ["1", "0"] + ["-1", "0"] * 14 if photo else ["-1", "0"] * 15
        vals = [
            f"{lat:.8f}",
            f"{lon:.8f}",
            f"{alt:.1f}",
            f"{heading % 360:.1f}",
            "0",
            "0",
            str(gimbal_mode),
            f"{pitch:.0f}",
            *actions,
            str(mode),
            f"{speed:.1f}",
            "0",
            "0",
            "0",
            "0",
            "-1",
            f"{dist:.1f}" if dist > 0 else "-1",
        ]
        return ",".join(vals)

    alt_col = photos["agl_m"] if terrain == "follow" else photos["altitude_m"]
    if len(photos) <= LITCHI_MAX_WAYPOINTS:
        for r, alt in zip(photos.itertuples(), alt_col):
            rows.append(row(r.longitude_deg, r.latitude_deg, alt, r.heading_deg, r.pitch_deg, True, 0.0))
    else:
        line_col = photos["line"].to_numpy()
        for ln in lines.itertuples():
            idx = np.flatnonzero(line_col == ln.line)
            for j in (idx[0], idx[-1]):
                r = photos.iloc[j]
                lon, lat = t.transform(r.geometry.x, r.geometry.y)
                rows.append(row(lon, lat, float(alt_col.iloc[j]), r.heading_deg, r.pitch_deg, False, along))
        note = (
            f"litchi.csv: {len(photos)} photos are more than Litchi's {LITCHI_MAX_WAYPOINTS} waypoints: "
            f"line ends with a photo every {along:.1f} m instead"
        )
        if len(rows) > LITCHI_MAX_WAYPOINTS:
            note += f"; still {len(rows)} waypoints: split the mission in Litchi Hub"
    return write_text(path, ",".join(LITCHI_HEADER) + "\n" + "\n".join(rows) + "\n"), note


def _write_marker_sheets(folder: Path, gcps: list[dict[str, Any]], dictionary: str, side_m: float) -> list[Path]:
    """One PDF per GCP at the real size: the marker (black square ``side_m``) with its one-module
    white border, a cross-hair mark at the centre outside the marker, and its name, id and size."""
    # matplotlib only here, for the print sheets: 0.35 s to import (matplotlib and its figure module)
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib import rc_context

    # the PDF core fonts (Helvetica): nothing to embed, a sheet in milliseconds (matplotlib's font
    # manager grumbles that no Helvetica *file* exists: none is needed, a PDF reader has it)
    fm_log = logging.getLogger("matplotlib.font_manager")
    level = fm_log.level
    fm_log.setLevel(logging.ERROR)
    try:
        with rc_context({"pdf.use14corefonts": True, "font.family": "Helvetica"}):
            return _marker_pages(folder, gcps, dictionary, side_m)
    finally:
        fm_log.setLevel(level)


def _marker_pages(folder: Path, gcps: list[dict[str, Any]], dictionary: str, side_m: float) -> list[Path]:
    from matplotlib.figure import Figure
    from matplotlib.patches import PathPatch
    from matplotlib.path import Path as MplPath

    out: list[Path] = []
    inch = 0.0254
    fig = ax = label = None
    patch = None
    for g in gcps:
        mid = int(g["marker_id"])
        if mid < 0:
            continue
        cells = marker_cells(dictionary, mid)
        n = cells.shape[0]
        module = side_m / n
        page_w = side_m + 2 * module + 0.04
        label_h = max(0.03, 0.06 * side_m)
        page_h = page_w + label_h
        off = 0.02 + module
        if fig is None:  # one page layout for every sheet (one size): only the cells and label change
            fig = Figure(figsize=(page_w / inch, page_h / inch))
            ax = fig.add_axes((0, label_h / page_h, 1, page_w / page_h))
            ax.set_xlim(0, page_w)
            ax.set_ylim(0, page_w)
            ax.axis("off")
            c = off + side_m / 2
            r0, r1 = side_m / 2 + module + 0.002, side_m / 2 + module + 0.018
            for sgn in (-1, 1):  # ticks in the margin on the centre lines: where to survey
                ax.plot([c + sgn * r0, c + sgn * r1], [c, c], color="k", lw=0.6)
                ax.plot([c, c], [c + sgn * r0, c + sgn * r1], color="k", lw=0.6)
            label = fig.text(
                0.5,
                0.5 * label_h / page_h,
                "",
                ha="center",
                va="center",
                fontsize=max(4.0, min(14.0, label_h / inch * 72 * 0.35)),
            )
        # black cells as one vector path (exact edges at any print size; a raster would be resampled)
        verts, codes = [], []
        for r, cc in zip(*np.nonzero(~cells)):
            x, y = off + cc * module, off + (n - 1 - r) * module
            verts += [(x, y), (x + module, y), (x + module, y + module), (x, y + module), (x, y)]
            codes += [MplPath.MOVETO, MplPath.LINETO, MplPath.LINETO, MplPath.LINETO, MplPath.CLOSEPOLY]
        assert ax is not None and label is not None
        if patch is not None:
            patch.remove()
        patch = ax.add_patch(PathPatch(MplPath(verts, codes), facecolor="black", edgecolor="none", antialiased=False))
        label.set_text(
            f"{g['name']} · id {mid} · {dictionary} · black square {side_m * 100:.1f} × {side_m * 100:.1f} cm "
            "— print at 100 %, check with a ruler; survey the centre"
        )
        target = folder / f"{g['name']}.pdf"
        with atomic_path(target) as tmp:
            fig.savefig(tmp, format="pdf")
        out.append(target)
    return out


def read_plan_photos(path: str | os.PathLike[str]) -> tuple[Any, dict[str, Any]]:
    """The photos layer of a plan.gpkg and its summary.json (beside it): what ``synth`` flies."""
    path = Path(path)
    gpkg = path / "plan.gpkg" if path.is_dir() else path
    try:
        photos = gpd.read_file(gpkg, layer="photos", engine="pyogrio")
    except Exception as e:
        raise InputError(f"not a geoortho plan (no photos layer): {e}", path=gpkg) from None
    summary_path = gpkg.with_name("summary.json")
    summary = json.loads(summary_path.read_text()) if summary_path.exists() else {}
    return photos, summary


# ---------------------------------------------------------------------------------------------
# Check: an existing plan, or the photos of a flight, against the GCPs and the overlap needed


@dataclass(frozen=True)
class PlanCheckResult:
    """What the plan-check algorithm found.

    Attributes
    ----------
    output : Path
        The check folder.
    check : Path
        check.gpkg (layers gcps, under_overlap).
    gcps : str
        GCPs with the photos that see each (layer gcps).
    under_overlap : str
        Areas seen by fewer photos than required (layer under_overlap).
    overlap : Path
        Photos covering each ground cell (GeoTIFF).
    report : Path
        check.json.
    short_gcps : str
        GCPs seen in fewer than min_photos photos, comma-separated.
    n_short_gcps : int
        How many.
    under_overlap_m2 : float
        Area seen by fewer photos than required, m².
    """

    output: Path
    check: Path
    gcps: str
    under_overlap: str
    overlap: Path
    report: Path
    short_gcps: str
    n_short_gcps: int
    under_overlap_m2: float


def check_plan(
    gcp_file: Path,
    output: Path,
    plan: Path | None = None,
    images: Path | None = None,
    dsm: Path | None = None,
    takeoff_elevation_m: float | None = None,
    gcp_crs: CRS | None = None,
    min_photos: int = 3,
    required_photos: int | None = None,
    marker_size_m: float | None = None,
    margin: float = 0.0,
    *,
    feedback: Feedback | None = None,
) -> PlanCheckResult:
    """Check a plan (or the photos of a flight) against the GCPs: GCPs seen in too few photos, and
    the areas seen by fewer photos than required.

    Parameters
    ----------
    gcp_file : Path
        GCP coordinates (any format gcp-find reads).
    output : Path
        Folder to write check.gpkg, overlap.tif and check.json into.
    plan : Path
        A plan folder (or its plan.gpkg) made by ``plan``.
    images : Path
        Or the photos of a flight (their metadata: positions, heights, attitude).
    dsm : Path
        Ground model for the photos' footprints (default: flat take-off ground).
    takeoff_elevation_m : float
        Ground elevation of the take-off point, in the vertical datum of the ground
        model (the DSM, the ground elevation or the GCPs). Default: worked out from the
        photos (absolute − relative altitude, checked against the
        ground model; else the ground under the flight), and said.
    gcp_crs : CRS
        CRS of a GCP file without one.
    min_photos : int
        A GCP needs at least this many photos.
    required_photos : int
        Photos each ground cell needs. Default: the plan's own figure, or 5 for photos.
    marker_size_m : float
        plan's print size, or 1 m for photos.
    margin : float
        A GCP counts as seen only this far inside the frame, percent of the image side.
    """
    fb = as_feedback(feedback)
    if (plan is None) == (images is None):
        raise InputError("give one of --plan or --images")
    if min_photos < 1:
        raise InputError("--min-photos must be at least 1")
    flown = (
        _planned_cameras(Path(plan), dsm, required_photos, marker_size_m)
        if plan is not None
        else _photo_cameras(Path(images), dsm, takeoff_elevation_m, required_photos, marker_size_m, fb)  # type: ignore[arg-type]
    )
    if flown.need < 1:
        raise InputError("--required-photos must be at least 1")
    lowest = min(float(c[:, 2].min()) for _, c, _ in flown.groups)
    hull = shapely.MultiPoint(np.vstack([c[:, :2] for _, c, _ in flown.groups])).convex_hull
    pts, notes = _given_gcps(str(gcp_file), gcp_crs, flown.crs, flown.surface, lowest, site=hull)
    for note in notes:
        fb.warning(note)
    rows = _gcp_counts(pts, flown, margin, min_photos)
    output = Path(output)
    output.mkdir(parents=True, exist_ok=True)
    gpkg, overlap, report, under_m2, covered_m2 = _write_check(output, flown, rows, plan, min_photos)
    short = [r["name"] for r in rows if r["short"]]
    if short:
        fb.warning(f"GCPs seen in fewer than {min_photos} photos: {', '.join(short)}")
    fb.info(
        f"check of {flown.source}: {len(rows) - len(short)} of {len(rows)} GCPs in >= {min_photos} photos; "
        f"{under_m2:,.0f} m² ({100 * under_m2 / max(covered_m2, 1e-9):.1f} % of the "
        f"{'AOI' if plan is not None else 'covered ground'}) seen by "
        f"fewer than {flown.need} photos"
    )
    return PlanCheckResult(
        output,
        gpkg,
        f"{gpkg}|layername=gcps",
        f"{gpkg}|layername=under_overlap",
        overlap,
        report,
        ",".join(short),
        len(short),
        under_m2,
    )


@dataclass(frozen=True)
class _Flown:
    """The cameras a check counts with (a plan's, or photos'), grouped by intrinsics, their
    footprints and what the check asks of them."""

    groups: list[tuple[Intrinsics, np.ndarray, np.ndarray]]  # intrinsics, centres, rotations
    polys: list[Any]
    crs: CRS
    surface: Surface
    need: int  # photos each ground cell needs
    laid: float  # the markers' size, m
    source: str


def _planned_cameras(plan: Path, dsm: Path | None, required_photos: int | None, marker_size_m: float | None) -> _Flown:

    photos, summary = read_plan_photos(plan)
    if not summary:
        raise InputError("no summary.json beside the plan: check a folder made by plan", path=plan)
    crs = CRS.from_user_input(photos.crs)
    c = summary["camera"]
    intr = Intrinsics(int(c["width_px"]), int(c["height_px"]), float(c["focal_px"]))
    centres = np.c_[photos.geometry.x, photos.geometry.y, photos["z_m"]]
    rots = rotation_from_ypr(
        photos["grid_heading_deg"].to_numpy(), photos["pitch_deg"].to_numpy(), np.zeros(len(photos))
    )
    polys = list(gpd.read_file(plan / "plan.gpkg" if plan.is_dir() else plan, layer="footprints").geometry)
    surface: Surface = FlatSurface(float(summary.get("ground", {}).get("takeoff_elevation_m", 0.0)))
    if dsm is not None:
        surface = read_surface(dsm, crs, extend=True)
    return _Flown(
        [(intr, centres, rots)],
        polys,
        crs,
        surface,
        int(required_photos or summary.get("coverage", {}).get("required_photos", 5)),
        float(marker_size_m or summary.get("marker", {}).get("laid_size_m", 1.0)),
        f"plan {plan.name}",
    )


def _photo_cameras(
    images: Path,
    dsm: Path | None,
    takeoff_elevation_m: float | None,
    required_photos: int | None,
    marker_size_m: float | None,
    fb: Feedback,
) -> _Flown:

    ps = photos_with_altitude(images, None, None, fb, fb)
    crs = working_crs(ps.photos)
    ground = read_surface(dsm, crs, extend=True) if dsm is not None else None
    cams, heights = photo_cameras(ps.photos, crs, ground, takeoff_elevation_m)
    for note in heights.notes:
        fb.warning(note)
    by: dict[Intrinsics, list[Any]] = {}
    for cam in cams:
        by.setdefault(cam.intrinsics, []).append(cam)
    groups = [
        (intr, np.array([c.pose.center for c in cs]), np.array([c.pose.rotation for c in cs]))
        for intr, cs in by.items()
    ]
    table = compute_footprints(cams, heights.surface)
    polys = list(shapely.make_valid(shapely.polygons(table.rings)))
    return _Flown(
        groups,
        polys,
        crs,
        heights.surface,
        int(required_photos or 5),
        float(marker_size_m or 1.0),
        f"{len(cams)} photos in {images.name}",
    )


def _gcp_counts(pts: list[Any], flown: _Flown, margin: float, min_photos: int) -> list[dict[str, Any]]:
    """Per GCP, the photos that frame it and those expected, sure and at most to see its marker."""
    rows: list[dict[str, Any]] = []
    for name, x, y, z in pts:
        n_frame = n_exp = n_sure = n_max = 0
        for intr, centres, rots in flown.groups:
            # the marker with its one-module white border (a 4x4 marker: 8 / 6 of the black square)
            got = _seen_by(centres, rots, intr, np.array([x, y, z]), margin, flown.laid * 8 / 6)
            n_frame += got["n_in_frame"]
            n_exp += got["n_photos"]
            n_sure += got["n_photos_sure"]
            n_max += got["n_photos_max"]
        rows.append(
            {
                "name": name,
                "x": float(x),
                "y": float(y),
                "z_m": float(z),
                "n_photos": n_frame,
                "n_expected": n_exp,
                "n_sure": n_sure,
                "n_max": n_max,
                "short": n_frame < min_photos,
            }
        )
    return rows


def _write_check(
    output: Path, flown: _Flown, rows: list[dict[str, Any]], plan: Path | None, min_photos: int
) -> tuple[Path, Path, Path, float, float]:
    """overlap.tif, check.gpkg (gcps, under_overlap) and check.json; the area under the overlap
    asked and the area checked (m²)."""
    polys, crs, need = flown.polys, flown.crs, flown.need
    overlap = write_overlap(output / "overlap.tif", polys, crs, max(0.05, math.sqrt(shapely.area(polys[0])) / 60))
    under = _under_overlap(overlap, need)
    covered_m2 = float(shapely.union_all(polys).area)
    if plan is not None:  # a plan's AOI is what must be covered: its block edge beyond does not count
        gpkg_in = Path(plan) / "plan.gpkg" if Path(plan).is_dir() else Path(plan)
        area = shapely.union_all(list(gpd.read_file(gpkg_in, layer="aoi").geometry))
        under = [g for g in (shapely.intersection(u, area) for u in under) if not g.is_empty and g.area > 0]
        covered_m2 = float(area.area)
    gcp_df = gpd.GeoDataFrame(
        {k: [r[k] for r in rows] for k in ("name", "z_m", "n_photos", "n_expected", "n_sure", "n_max", "short")},
        geometry=shapely.points([(r["x"], r["y"]) for r in rows]),
        crs=crs,
    )
    under_df = gpd.GeoDataFrame({"photos_needed": [need] * len(under)}, geometry=under, crs=crs)
    gpkg = write_vector(output / "check.gpkg", {"gcps": gcp_df, "under_overlap": under_df})
    under_m2 = float(sum(g.area for g in under))
    report = write_json(
        output / "check.json",
        {
            "source": flown.source,
            "crs": crs_to_text(crs),
            "min_photos": min_photos,
            "required_photos": need,
            "marker_size_m": flown.laid,
            "gcps": rows,
            "short_gcps": [r["name"] for r in rows if r["short"]],
            "under_overlap_m2": under_m2,
            "checked_area_m2": covered_m2,
            "checked_area": "the plan's AOI" if plan is not None else "the ground the photos cover",
            "under_overlap_pct": 100 * under_m2 / max(covered_m2, 1e-9),
        },
    )
    return gpkg, overlap, report, under_m2, covered_m2


def _under_overlap(overlap: Path, need: int) -> list[Any]:
    """Polygons of the covered cells seen by fewer than ``need`` photos (the block's ragged outer
    edge included: it is where a flight is short of photos)."""
    with rasterio.open(overlap) as src:
        count = src.read(1)
        mask = (count > 0) & (count < need)
        polys = [
            shapely.geometry.shape(g)
            for g, v in shapes(mask.astype(np.uint8), mask=mask, transform=src.transform)
            if v == 1
        ]
    return polys
