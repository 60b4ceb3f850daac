"""The flight over the site: the lines' direction and spacing, the shots along them, the heights over
the ground, true headings, and the overlaps the footprints give."""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import rasterio
import shapely
from pyproj import CRS
from rasterio.features import geometry_mask

from geoortho.core.camera import Pose, PosedCamera, rotation_from_ypr
from geoortho.core.crs import WGS84, grid_north, transformer
from geoortho.core.surface import Surface
from geoortho.errors import InputError
from geoortho.feedback import Feedback
from geoortho.photos.footprint import (
    compute_footprints,
)
from geoortho.planning.site import PlanOptions, Site


@dataclass(frozen=True)
class Flight:
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


def fly_site(aoi: Path, site: Site, o: PlanOptions, warnings_: list[str], s_grid: Feedback, s_foot: Feedback) -> Flight:
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
    return Flight(
        directions, shots, lines, xy, grid_heading, z, rots, centres, table, polys, agl_photo, heading_true, lonlat,
        speed, length_m,
    )  # fmt: skip


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


def photo_coverage(path: Path, area: Any, front: float, side: float, grid: str) -> dict[str, Any]:
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
