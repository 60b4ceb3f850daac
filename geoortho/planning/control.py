"""The ground control of a plan: where the GCPs go (proposed, or a GCP file checked), which photos
see each, and the marker size the detector needs at the flight's GSD."""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cache
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import shapely
from pyproj import CRS
from scipy.special import ndtr

from geoortho.core.camera import Intrinsics
from geoortho.core.crs import transformer
from geoortho.core.gsd import marker_gsd_m
from geoortho.core.surface import Surface
from geoortho.errors import InputError
from geoortho.gcp.detect import SearchWindow, detect_in_image
from geoortho.gcp.io import heights_are_placeholders, marker_id_of, read_gcp_file
from geoortho.gcp.markers import get_dictionary, marker_cells
from geoortho.planning.flight import Flight
from geoortho.planning.site import PlanOptions, Site

# How far a flown photo is from the planned one (consumer GNSS and wind; gimbal and aircraft
# attitude): what makes a GCP near a frame edge seen or not.
FLIGHT_POSITION_SIGMA_M = 0.5


FLIGHT_ATTITUDE_SIGMA_DEG = 1.5


DETECTION_SAFETY = 1.5  # printed module size over the smallest one the detector decodes


MIN_MARKER_STEP_M = 0.05  # print sizes are rounded up to 5 cm


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


@dataclass(frozen=True)
class Control:
    """The GCPs, the markers' print size and how many photos see each."""

    rows: list[dict[str, Any]]
    marker_m: float  # the print size needed
    laid_m: float  # the size the sightings were counted with
    n_cells: int
    module_px: float
    worst_gsd_m: float


def gcp_sightings(site: Site, flight: Flight, o: PlanOptions, warnings_: list[str]) -> Control:
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
        seen_by(flight.centres, flight.rots, site.intr, np.array([g["x"], g["y"], g["z"]]), o.margin, 0.0)["gsd_max_cm"]
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
        g.update(seen_by(flight.centres, flight.rots, site.intr, np.array([g["x"], g["y"], g["z"]]), o.margin, quiet))
    for g in rows:
        g["marker_side_px"] = marker_m / (g["gsd_max_cm"] / 100.0) if g["n_photos"] else float("nan")
        g["marker_size_m"] = marker_m
    few = [g["name"] for g in rows if g["n_photos_sure"] < 3]
    if few:
        warnings_.append(f"GCPs not surely seen in 3 planned photos: {', '.join(few)}")
    return Control(rows, marker_m, laid_m, n_cells, module_px, worst_gsd_m)


#: A GCP farther than this (m) from the area flown is seen by no photo: all of them so far is another
#: site's file or another CRS (refused, with the distance); some, a wrong line (said).
FAR_GCP_M = 2000.0


def given_gcps(
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
        pts, notes = given_gcps(text, gcp_crs, crs, surface, camera_z_min, site=area)
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


def seen_by(
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
