"""The DSM an orthophoto is rectified on: read, its holes filled, its heights' unit and datum checked
against the SfM points (corrected, refused or kept, as asked).
"""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path
from typing import Any, Literal, get_args

import numpy as np
from pyproj import CRS

from geoortho.core.surface import FlatSurface, GridSurface, read_surface, sample_grid, whole_surface
from geoortho.errors import InputError
from geoortho.feedback import Feedback
from geoortho.orthophoto.coverage import enclosed

DsmOffset = Literal["correct", "refuse", "ignore"]
DSM_OFFSET: tuple[str, ...] = get_args(DsmOffset)


def given_surface(
    dsm: Path | None,
    ground_elevation_m: float | None,
    default_ground: float | None,
    crs: CRS,
    notes: list[str],
    fb: Feedback,
) -> Any:
    """The surface to rectify on: the DSM, else flat ground at the given elevation, else at the
    SfM points' median height; None when nothing gives one (the metadata's heights then do)."""
    if dsm is not None:
        return _read_dsm(Path(dsm), crs, fb, notes)
    if ground_elevation_m is not None:
        return FlatSurface(float(ground_elevation_m))
    if default_ground is not None:
        notes.append(f"no DSM: flat ground at the SfM points' median height {default_ground:.2f} m")
        return FlatSurface(default_ground)
    return None


#: A DSM whose heights spread about the SfM points' by more than this share of the flight height
#: (robust sigma), or this many metres at least, is not the same surface: no offset is applied.
MAX_DSM_SPREAD_SHARE = 0.05
MIN_DSM_SPREAD_M = 2.0
#: No two vertical datums differ by more than this (m): the geoid lies within -106..+85 m of the
#: ellipsoid. A larger offset is another unit, a fill value or another place.
MAX_DATUM_OFFSET_M = 150.0


def check_dsm_against_points(
    surface: GridSurface,
    pts: np.ndarray,
    how: str,
    max_offset_m: float,
    notes: list[str],
    fb: Feedback,
    flown_m: float = math.nan,
) -> tuple[GridSurface, float]:
    """Measure the DSM's vertical offset from the SfM points (median of point − DSM over the points
    inside it; the sparse points lie on the surface, roofs and trees included). Beyond
    ``max_offset_m``: move the DSM onto the points (correct), refuse, or only say it (ignore).

    An offset is a datum's, tens of metres at most: one larger than ``MAX_DATUM_OFFSET_M``, or
    heights that spread about the points more than a DSM of the same surface does (a share of the
    cameras' height over the points, ``flown_m``), say another unit, an undeclared fill or another
    place. Such a DSM is refused
    whatever ``how`` says: moved, it made a 50 m site's orthophoto 6.8 km wide."""
    z = surface.grid
    c, r = surface.colrow(pts[:, 0], pts[:, 1])

    dsm_z = sample_grid(z, c, r).astype(float)
    ok = np.isfinite(dsm_z)
    if ok.sum() < 20:
        notes.append(f"DSM vs SfM points: only {int(ok.sum())} points over the DSM, offset not measured")
        fb.warning(notes[-1])
        return surface, math.nan
    factor, why = _feet_against_points(pts[ok, 2], dsm_z[ok], surface.height_unit)
    if why:
        notes.append(why)
        fb.warning(why)
        surface = replace(surface, grid=surface.grid * np.float32(factor), height_unit="metre")
        dsm_z = dsm_z * factor
    d = pts[ok, 2] - dsm_z[ok]
    offset = float(np.median(d))
    spread = float(1.4826 * np.median(np.abs(d - offset)))
    text = (
        f"DSM vs SfM points: the DSM is {-offset:+.2f} m off the points (median of {int(ok.sum())}, "
        f"spread {spread:.2f} m)"
    )
    if abs(offset) <= max_offset_m:
        notes.append(text)
        fb.info(text)
        return surface, -offset
    limit_m = max(MIN_DSM_SPREAD_M, MAX_DSM_SPREAD_SHARE * flown_m) if math.isfinite(flown_m) else MIN_DSM_SPREAD_M
    if abs(offset) > MAX_DATUM_OFFSET_M or spread > limit_m:
        why = (
            f"more than any two vertical datums differ ({MAX_DATUM_OFFSET_M:.0f} m)"
            if abs(offset) > MAX_DATUM_OFFSET_M
            else f"its heights spread about them beyond {limit_m:.1f} m"
        )
        raise InputError(
            f"{text}: {why}: not the surface the photos saw (another unit, an undeclared fill value or another "
            "place?); give the DSM of this site in metres, or none"
        )
    if how == "refuse":
        raise InputError(f"{text}: another vertical datum? give a DSM in the SfM's datum, or dsm_offset correct")
    if how == "ignore":
        notes.append(text + ": not corrected (dsm_offset ignore)")
        fb.warning(notes[-1])
        return surface, -offset
    notes.append(text + f": corrected (DSM moved {offset:+.2f} m onto the points)")
    fb.warning(notes[-1])
    return replace(surface, grid=surface.grid + np.float32(offset)), -offset


FOOT_M = 0.3048


def _feet_against_points(points_z: np.ndarray, dsm_z: np.ndarray, unit: str) -> tuple[float, str]:
    """A DSM whose heights are in another unit than read (feet under a CRS in metres; metres under a
    CRS in feet): against the SfM points (metres) its heights scale 0.3048 or 3.28, which no datum
    shift does. With relief, the robust slope of the points on the DSM says it; on flat ground, the
    points' median height being the DSM's so converted. The factor to apply (1: none) and why."""
    if len(points_z) < 20:
        return 1.0, ""
    from scipy.stats import siegelslopes

    rng = np.random.default_rng(0)
    pick = rng.choice(len(points_z), min(len(points_z), 1500), replace=False)
    pz, dz = points_z[pick], dsm_z[pick]
    factor = FOOT_M if unit == "metre" else 1.0 / FOOT_M
    what = "feet, not metres" if unit == "metre" else f"metres, not {unit} as its CRS says"
    relief = float(np.subtract(*np.percentile(dz, [90, 10])))
    mid_p, mid_d = float(np.median(pz)), float(np.median(dz))
    if relief > 3.0:
        slope = float(siegelslopes(pz, dz)[0])
        if abs(slope / factor - 1.0) < 0.1:
            return factor, (
                f"the DSM's heights scale {slope:.3f} against the SfM points: they are {what} "
                "(converted; give a DSM in metres, or with its vertical unit in its CRS)"
            )
        return 1.0, ""
    if abs(mid_p - mid_d) > 5.0 and abs(mid_p - factor * mid_d) < 1.0:
        return factor, (
            f"the DSM lies at {mid_d:.1f} where the SfM points are at {mid_p:.1f} m: its heights are {what} "
            "(converted; give a DSM in metres)"
        )
    return 1.0, ""


def _read_dsm(path: Path, crs: CRS, fb: Feedback, notes: list[str]) -> GridSurface:
    """The DSM in the output CRS, its small nodata holes filled (reported)."""

    surf = read_surface(path, crs, extend=True)
    if surf.undeclared_fill is not None:
        notes.append(
            f"DSM: {surf.undeclared_fill[1]:,} cells hold {surf.undeclared_fill[0]:g}, a fill value its nodata does "
            "not declare: read as no data"
        )
        fb.warning(notes[-1])
    if surf.height_unit != "metre":
        notes.append(f"DSM: its CRS gives its heights in {surf.height_unit}: converted to metres")
        fb.info(notes[-1])
    whole = whole_surface(surf)
    if whole.n_interpolated:
        notes.append(f"DSM: {whole.n_interpolated} nodata cells inside the data filled by interpolation")
        fb.warning(notes[-1])
    # Wider holes take the ground plane the DSM is continued by beyond its edge: a hole is ground the
    # photos saw (water, canopy the matcher missed), never a reason to leave the mosaic empty there.
    rest = whole.on_ground
    if rest.any():
        # holes inside the DSM's data apart from the grid's margin beyond it: the dem stage said how
        # much of the ground the photos saw has a value, and a margin is no hole in that
        holes = enclosed(rest)
        wide = max(4.0, 10.0 / surf.cell_m) * surf.cell_m
        said = []
        if holes.any():
            said.append(f"{float(holes.sum()) * surf.cell_m**2:,.0f} m² of holes wider than {wide:.0f} m in it")
        if (rest & ~holes).any():
            said.append(f"{float((rest & ~holes).sum()) * surf.cell_m**2:,.0f} m² of its grid beyond its data")
        notes.append(f"DSM: {' and '.join(said)} rendered on the ground plane near them")
        (fb.warning if holes.any() else fb.info)(notes[-1])
    return whole.surface
