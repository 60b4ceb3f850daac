"""CRS parsing at the edges, UTM zone choice and cached pyproj transformers.

``always_xy=True`` everywhere: easting/longitude first.
"""

from __future__ import annotations

import re
from functools import lru_cache
from typing import Any

import numpy as np
from pyproj import CRS, Transformer
from pyproj.exceptions import CRSError

from geoortho.errors import DependencyError

__all__ = [
    "WGS84",
    "parse_crs",
    "utm_crs_for",
    "transformer",
    "crs_to_text",
    "horizontal_of",
    "heights_of",
    "with_heights",
    "heights_label",
    "heights_to_text",
    "heights_from_text",
    "ELLIPSOIDAL",
    "horizontal_unit_m",
    "geoid_undulation_m",
    "grid_north",
]

WGS84 = CRS.from_epsg(4326)
WGS84_3D = CRS.from_epsg(4979)

_UTM_WORDS = re.compile(r"^\s*WGS\s*-?\s*84\s+UTM\s+(?:zone\s+)?(\d{1,2})\s*([NS])\s*$", re.I)


def parse_crs(value: Any) -> CRS:
    """A pyproj CRS from what users write.

    Accepts anything ``CRS.from_user_input`` does (``EPSG:32629``, ``32629``,
    a PROJ string, WKT) plus ODM's legacy ``WGS84 UTM 29N``.

    Raises
    ------
    ValueError
        The text is not a CRS pyproj knows.

    >>> parse_crs("WGS84 UTM 29N").to_epsg()
    32629
    """
    if isinstance(value, CRS):
        return value
    text = str(value).strip()
    m = _UTM_WORDS.match(text)
    if m:
        zone, hemi = int(m.group(1)), m.group(2).upper()
        if not 1 <= zone <= 60:
            raise ValueError(f"UTM zone {zone} out of range 1..60")
        return CRS.from_epsg((32600 if hemi == "N" else 32700) + zone)
    try:
        return CRS.from_user_input(text)
    except CRSError:
        shown = text if len(text) <= 80 else text[:77] + "..."
        raise ValueError(f"unknown CRS {shown!r} (expected e.g. EPSG:32629, a PROJ string or WKT)") from None


def utm_crs_for(lon_deg: float, lat_deg: float) -> CRS:
    """The WGS84 UTM zone containing a point (Norway/Svalbard exceptions ignored).

    >>> utm_crs_for(-9.14, 38.72).to_epsg()
    32629
    """
    zone = int((lon_deg + 180.0) // 6.0) % 60 + 1
    return CRS.from_epsg((32600 if lat_deg >= 0 else 32700) + zone)


@lru_cache(maxsize=64)
def _transformer(src_wkt: str, dst_wkt: str) -> Transformer:
    return Transformer.from_crs(CRS.from_wkt(src_wkt), CRS.from_wkt(dst_wkt), always_xy=True)


def transformer(src: CRS, dst: CRS) -> Transformer:
    """A cached ``Transformer`` with ``always_xy=True``."""
    return _transformer(src.to_wkt(), dst.to_wkt())


def crs_to_text(crs: CRS) -> str:
    """``EPSG:xxxx`` when the CRS has a code (``EPSG:h+v`` for a compound one whose parts have
    codes), else a PROJ string (ODM's gcp_list header)."""
    code = crs.to_epsg()
    if code is not None:
        return f"EPSG:{code}"
    if crs.is_compound and len(crs.sub_crs_list) == 2:
        codes = [c.to_epsg() for c in crs.sub_crs_list]
        if None not in codes:
            return f"EPSG:{codes[0]}+{codes[1]}"
    import warnings

    with warnings.catch_warnings():  # PROJ strings drop datum details; ODM reads nothing else
        warnings.simplefilter("ignore", UserWarning)
        return crs.to_proj4()


#: The heights' datum of a CRS whose heights are above the ellipsoid (a 3D CRS: EPSG has no
#: vertical CRS for them).
ELLIPSOIDAL = "ellipsoidal"


def horizontal_of(crs: CRS) -> CRS:
    """The horizontal CRS of a compound or 3D one (the CRS itself when it is 2D): every map-grid
    computation runs in it; the heights' datum rides beside it (:func:`heights_of`)."""
    if crs.is_compound:
        return crs.sub_crs_list[0]
    if len(crs.axis_info) == 3:
        return crs.to_2d()
    return crs


def heights_of(crs: CRS | None) -> CRS | str | None:
    """The datum of a CRS's heights: its vertical CRS (compound), :data:`ELLIPSOIDAL` (3D), or None
    when the CRS does not say."""
    if crs is None:
        return None
    if crs.is_compound:
        return next((c for c in crs.sub_crs_list if c.is_vertical), None)
    if len(crs.axis_info) == 3 and "ellipsoidal" in (crs.axis_info[2].name or "").lower():
        return ELLIPSOIDAL
    return None


def with_heights(crs: CRS, heights: CRS | str | None) -> CRS:
    """``crs`` (horizontal) with its heights' datum: compound with a vertical CRS, 3D for
    :data:`ELLIPSOIDAL`, as is for None. A GeoTIFF or LAS header written with it carries the
    heights' datum, which QGIS and PDAL read.

    >>> crs_to_text(with_heights(CRS.from_epsg(32629), CRS.from_epsg(5773)))
    'EPSG:32629+5773'
    """
    crs = horizontal_of(crs)
    if heights is None:
        return crs
    if isinstance(heights, str):
        if heights == ELLIPSOIDAL:
            return crs.to_3d()
        heights = parse_crs(heights)
    if not heights.is_vertical:
        raise ValueError(f"{heights.name} is not a vertical CRS")
    parts = [crs.to_json_dict(), heights.to_json_dict()]
    return CRS.from_json_dict({"type": "CompoundCRS", "name": f"{crs.name} + {heights.name}", "components": parts})


def heights_label(heights: CRS | str | None) -> str:
    """The heights' datum in words: ``EGM96 height (EPSG:5773)``, ``ellipsoidal height``, or
    ``not stated``."""
    if heights is None:
        return "not stated"
    if isinstance(heights, str):
        return "ellipsoidal height" if heights == ELLIPSOIDAL else heights
    code = heights.to_epsg()
    return f"{heights.name}" + (f" (EPSG:{code})" if code else "")


def heights_to_text(heights: CRS | str | None) -> str | None:
    """The heights' datum for a JSON report: ``EPSG:5773``, ``ellipsoidal``, a WKT, or None."""
    if heights is None or isinstance(heights, str):
        return heights
    code = heights.to_epsg()
    return f"EPSG:{code}" if code else heights.to_wkt()


def heights_from_text(text: str | None) -> CRS | str | None:
    """The inverse of :func:`heights_to_text`."""
    if not text:
        return None
    return ELLIPSOIDAL if text == ELLIPSOIDAL else parse_crs(text)


def horizontal_unit_m(crs: CRS) -> float:
    """Metres per horizontal unit of a projected CRS (1.0 for metres, 0.3048 for feet)."""
    axis = crs.axis_info[0] if crs.axis_info else None
    if axis is None or axis.unit_conversion_factor in (None, 0):
        return 1.0
    return float(axis.unit_conversion_factor)


def grid_north(crs: CRS, lon_deg: Any, lat_deg: Any, step_m: float = 10.0) -> tuple[np.ndarray, np.ndarray]:
    """Meridian convergence and point scale of a projected CRS at WGS84 points.

    Returns the grid azimuth of true north (degrees clockwise from grid north: a true azimuth
    ψ is ψ + this on the grid; about Δλ·sin φ in Transverse Mercator, 1.9° at a UTM zone edge
    at 40° N) and the grid metres per ground metre on the ellipsoid (UTM: 0.9996 on the central
    meridian, 1.001 at a zone edge). Measured by a ``step_m`` step due north and one due east."""
    from pyproj import Geod

    lon = np.atleast_1d(np.asarray(lon_deg, float))
    lat = np.atleast_1d(np.asarray(lat_deg, float))
    geod = Geod(ellps="WGS84")
    lon_n, lat_n, _ = geod.fwd(lon, lat, np.zeros_like(lon), np.full_like(lon, step_m))
    lon_e, lat_e, _ = geod.fwd(lon, lat, np.full_like(lon, 90.0), np.full_like(lon, step_m))
    t = transformer(WGS84, crs)
    x0, y0 = t.transform(lon, lat)
    xn, yn = t.transform(lon_n, lat_n)
    xe, ye = t.transform(lon_e, lat_e)
    unit = horizontal_unit_m(crs)
    convergence = np.degrees(np.arctan2(xn - x0, yn - y0))
    # the mean of the two directions' scales (equal in a conformal projection)
    scale = (np.hypot(xn - x0, yn - y0) + np.hypot(xe - x0, ye - y0)) / (2 * step_m) * unit
    return convergence, scale


# EGM96 on a 15' grid: PROJ's current name and the legacy one Debian's proj-data ships.
_GEOID_GRIDS = ("us_nga_egm96_15.tif", "egm96_15.gtx")
_SYSTEM_PROJ_DIRS = ("/usr/share/proj", "/usr/local/share/proj")


@lru_cache(maxsize=1)
def _geoid_transformer() -> Transformer:
    import os

    import pyproj.datadir

    dirs = [
        pyproj.datadir.get_data_dir(),
        *(os.environ.get(v, "") for v in ("PROJ_DATA", "PROJ_LIB")),
        *_SYSTEM_PROJ_DIRS,
    ]
    found = next((d for d in dirs for g in _GEOID_GRIDS if d and os.path.isfile(os.path.join(d, g))), None)
    if found is None:
        raise DependencyError(
            "no EGM96 geoid grid (egm96_15.gtx): install Debian's proj-data "
            "(apt-get install proj-data) or put us_nga_egm96_15.tif in PROJ's data folder"
        )
    if found not in pyproj.datadir.get_data_dir().split(os.pathsep):
        # pyproj's wheel carries no grids; PROJ then finds the system grid by its legacy name.
        pyproj.datadir.append_data_dir(found)
    return Transformer.from_crs(WGS84_3D, CRS("EPSG:4326+5773"), always_xy=True, only_best=True)


def geoid_undulation_m(lon_deg: Any, lat_deg: Any) -> Any:
    """EGM96 geoid height N above the WGS84 ellipsoid (ellipsoidal h = orthometric H + N), metres.

    Uses PROJ's EGM96 grid through pyproj; raises DependencyError when the grid is not installed.

    >>> round(float(geoid_undulation_m(-9.1887, 38.7476)), 1)  # Lisbon
    53.7
    """
    import numpy as np

    lon = np.asarray(lon_deg, float)
    lat = np.asarray(lat_deg, float)
    _, _, h_orth = _geoid_transformer().transform(lon, lat, np.zeros_like(lon), errcheck=True)
    return -np.asarray(h_orth) if np.ndim(h_orth) else -float(h_orth)
