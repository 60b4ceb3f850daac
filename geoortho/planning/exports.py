"""A plan's files: plan.gpkg (photos, lines, footprints, GCPs, area), the KML, the Litchi mission, the
marker sheets and summary.json, written whole or not at all."""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any
from xml.sax.saxutils import escape

import geopandas as gpd
import numpy as np
import shapely
from pyproj import CRS

from geoortho.core.crs import WGS84, crs_to_text, transformer
from geoortho.core.outputs import atomic_path, write_text, write_vector
from geoortho.feedback import Feedback
from geoortho.gcp.markers import marker_cells
from geoortho.photos.footprint_layers import write_overlap
from geoortho.planning.control import DETECTION_SAFETY, FLIGHT_ATTITUDE_SIGMA_DEG, FLIGHT_POSITION_SIGMA_M, Control
from geoortho.planning.flight import Flight, line_overlaps, photo_coverage
from geoortho.planning.site import PlanOptions, Site

#: What ``plan`` writes into its folder (removed together when it is canceled while writing).
PLAN_PRODUCTS = ("plan.gpkg", "overlap.tif", "plan.kml", "litchi.csv", "summary.json", "markers")


def remove_plan(output: Path) -> None:
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


def write_plan(
    output: Path,
    site: Site,
    flight: Flight,
    control: Control,
    o: PlanOptions,
    warnings_: list[str],
    s_write: Feedback,
) -> _Files:
    """The overlap raster, plan.gpkg (aoi, photos, lines, footprints, gcps), plan.kml, litchi.csv
    and the markers' print sheets; the coverage and overlaps measured on the footprints."""
    output.mkdir(parents=True, exist_ok=True)
    overlap_path = output / "overlap.tif"

    write_overlap(overlap_path, flight.polys, site.work_crs, max(0.05, site.across_w / 40.0))
    coverage = photo_coverage(overlap_path, site.area, o.front_overlap, o.side_overlap, o.grid)
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


def plan_summary(
    site: Site,
    flight: Flight,
    control: Control,
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
