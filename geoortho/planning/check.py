"""plan-check: an existing plan, or the photos of a flight, against the GCPs and the overlap needed."""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import geopandas as gpd
import numpy as np
import rasterio
import shapely
from pyproj import CRS
from rasterio.features import shapes

from geoortho.core.camera import Intrinsics, rotation_from_ypr
from geoortho.core.crs import crs_to_text
from geoortho.core.outputs import write_json, write_vector
from geoortho.core.surface import FlatSurface, Surface, read_surface
from geoortho.errors import InputError
from geoortho.feedback import Feedback, as_feedback
from geoortho.photos.footprint import photos_with_altitude
from geoortho.photos.footprint_layers import write_overlap
from geoortho.photos.photo_cameras import compute_footprints, photo_cameras, working_crs
from geoortho.planning.control import given_gcps, seen_by


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
    pts, notes = given_gcps(str(gcp_file), gcp_crs, flown.crs, flown.surface, lowest, site=hull)
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
            got = seen_by(centres, rots, intr, np.array([x, y, z]), margin, flown.laid * 8 / 6)
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
