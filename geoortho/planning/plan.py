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

The algorithm is here; its steps are the modules beside it, each importing only those before it:
:mod:`.site` (the camera, the options, the area and the ground), :mod:`.flight` (lines, shots,
overlaps), :mod:`.control` (GCPs, their sightings, the marker size), :mod:`.exports` (the plan's
files) and :mod:`.check` (``plan-check``, whose function this module also holds out).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from pyproj import CRS

from geoortho.core.crs import crs_to_text
from geoortho.core.outputs import write_json
from geoortho.feedback import Feedback, as_feedback, split
from geoortho.gcp.markers import Dictionary
from geoortho.planning.check import PlanCheckResult, check_plan, read_plan_photos
from geoortho.planning.control import default_gcp_count, gcp_sightings, min_module_px
from geoortho.planning.exports import plan_summary, remove_plan, write_plan
from geoortho.planning.flight import fly_site, line_overlaps
from geoortho.planning.site import CAMERAS, DEFAULT_MAX_ALTITUDE_M, CameraSpec, PlanOptions, resolve_camera, site_layout

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
    "read_plan_photos",
]


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
    site = site_layout(Path(aoi), o, warnings_)
    s_setup.progress(1.0)
    flight = fly_site(Path(aoi), site, o, warnings_, s_grid, s_foot)
    control = gcp_sightings(site, flight, o, warnings_)
    s_gcp.progress(1.0)
    try:
        files = write_plan(Path(output), site, flight, control, o, warnings_, s_write)
        summary = plan_summary(site, flight, control, files, o, warnings_, time.perf_counter() - t0)
        summary_path = write_json(Path(output) / "summary.json", summary)
    except BaseException:
        # canceled or failed while writing: no half a plan (a KML without its summary, sheets without
        # the plan) is left to be flown
        remove_plan(Path(output))
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
