"""GCP coordinate files as surveyors hand them over, and OpenDroneMap's gcp_list.txt.

Formats read (detected from the content, not the extension):

* text ``name x y z`` (or ``name lat lon h`` in a geographic CRS) with a CRS
  line first: ``EPSG:32629``, a PROJ string, or ODM's legacy ``WGS84 UTM 29N``;
  spaces, tabs, commas or semicolons between fields; ``#`` comments;
* CSV with named columns (name/id/label, lat/lon/alt, x/y/z,
  easting/northing/elevation, ...), comma, semicolon or tab separated;
* an OpenDroneMap ``gcp_list.txt`` (its coordinates, one per GCP name);
* OpenSfM's ``ground_control_points.json``.

In a geographic CRS, text files give latitude first (the surveyors' habit);
the obvious swap (a "latitude" beyond ±90 with a longitude within it) is an
error that says so. Heights are as in the file: say which datum they are in.
"""

from __future__ import annotations

import csv
import io
import json
import math
import os
import re
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from pyproj import CRS

from geoortho.core.crs import WGS84_3D, crs_to_text, parse_crs
from geoortho.errors import InputError

__all__ = ["GroundControlPoint", "ImagePoint", "GcpSet", "read_gcp_file", "marker_id_of"]

_NAME_COLS = ("name", "id", "label", "gcp", "gcp_name", "point", "point_id", "pointid")
_COLS = {
    "lat": ("lat", "latitude", "lat_deg", "latitude_deg"),
    "lon": ("lon", "long", "lng", "longitude", "lon_deg", "longitude_deg"),
    "alt": ("alt", "altitude", "h", "height", "ellipsoidal_height", "elev", "elevation", "z", "alt_m"),
    "x": ("x", "easting", "east", "e"),
    "y": ("y", "northing", "north", "n"),
    "z": ("z", "elevation", "elev", "height", "h", "alt", "altitude", "z_m"),
}


@dataclass(frozen=True)
class GroundControlPoint:
    """One surveyed point: coordinates in the file's CRS (x = easting or longitude)."""

    name: str
    x: float
    y: float
    z: float
    line: int = 0


@dataclass(frozen=True)
class ImagePoint:
    """Where a GCP is seen in a photo (a gcp_list.txt row); pixel (0, 0) is the top-left pixel's centre."""

    gcp: str
    image: str
    x_px: float
    y_px: float
    line: int = 0


@dataclass(frozen=True)
class GcpSet:
    """The points of a GCP file and its CRS (and, for a gcp_list.txt, where photos see them)."""

    points: tuple[GroundControlPoint, ...]
    crs: CRS
    path: Path
    observations: tuple[ImagePoint, ...] = ()

    def by_name(self) -> dict[str, GroundControlPoint]:
        return {p.name: p for p in self.points}


def heights_are_placeholders(z: Sequence[float] | np.ndarray) -> bool:
    """All GCP heights equal (two GCPs or more): a file with horizontal control and a filler height
    (toledo's gcp_list: every height 400), not surveyed heights."""
    zs = np.asarray(z, float)
    return len(zs) >= 2 and bool(np.ptp(zs) < 1e-6)


def marker_id_of(name: str) -> int | None:
    """The coded-marker id a GCP name stands for: its trailing integer (``GCP07`` → 7, ``12`` → 12)."""
    m = re.search(r"(\d+)\s*$", name)
    return int(m.group(1)) if m else None


def _num(text: str, path: Path, line: int, what: str) -> float:
    try:
        v = float(text.replace(",", ".") if text.count(",") == 1 and "." not in text else text)
    except ValueError:
        raise InputError(f"{what} is not a number: {text!r}", path=path, line=line) from None
    if not math.isfinite(v):
        raise InputError(f"{what} is not finite: {text!r}", path=path, line=line)
    return v


def _crs_line(text: str, path: Path, line: int) -> CRS | None:
    t = text.strip()
    if not t:
        return None
    if re.match(r"^(EPSG:\d+|\+proj=|\+init=|WGS\s*-?84\s+UTM|PROJCS\[|GEOGCS\[|PROJCRS\[|GEOGCRS\[)", t, re.I):
        try:
            return parse_crs(t)
        except ValueError as e:  # InputError is a ValueError too
            raise InputError(str(getattr(e, "reason", e)), path=path, line=line) from None
    return None


def _check_geographic(name: str, lat: float, lon: float, path: Path, line: int) -> None:
    if abs(lat) > 90 and abs(lon) <= 90:
        raise InputError(
            f"{name}: latitude {lat} is beyond ±90 while longitude {lon} is not: "
            "the columns look swapped (latitude comes first)",
            path=path,
            line=line,
        )
    if abs(lat) > 90 or abs(lon) > 180:
        raise InputError(f"{name}: latitude {lat} / longitude {lon} out of range", path=path, line=line)


#: A GCP this far from the others' middle is not of the same site (one survey spans kilometres).
STRAY_KM = 100.0


def _refuse_strays(points: list[GroundControlPoint], path: Path) -> None:
    """A row far from all the others under a projected CRS: most often latitude and longitude among
    eastings and northings (38.75, -9.19 read as metres lies near the grid's origin). It would be
    predicted in no photo and dropped silently: refused, naming its line."""
    xy = np.array([(p.x, p.y) for p in points])
    mid = np.median(xy, axis=0)
    far = np.hypot(*(xy - mid).T) / 1000.0
    if len(points) < 3 or far.max() <= STRAY_KM:
        return
    k = int(np.argmax(far))
    p = points[k]
    degrees = abs(p.x) <= 180 and abs(p.y) <= 180
    raise InputError(
        f"GCP {p.name} ({p.x:g}, {p.y:g}) lies {far[k]:,.0f} km from the others"
        + (": latitude and longitude among projected coordinates?" if degrees else ": is it of this site?"),
        path=path,
        line=p.line,
    )


def _finish(
    points: list[GroundControlPoint], crs: CRS, path: Path, observations: tuple[ImagePoint, ...] = ()
) -> GcpSet:
    if not points:
        raise InputError("no GCP in the file", path=path)
    if crs.is_geocentric:
        raise InputError(
            f"the CRS {crs_to_text(crs)} is geocentric (X, Y, Z from the Earth's centre): "
            "give the GCPs in a projected or geographic CRS",
            path=path,
        )
    if crs.is_vertical and not (crs.is_projected or crs.is_geographic):
        raise InputError(
            f"the CRS {crs_to_text(crs)} is vertical only: give the horizontal CRS (e.g. EPSG:32629, "
            "or a compound one such as EPSG:32629+5773)",
            path=path,
        )
    if crs.is_projected:
        _refuse_strays(points, path)
    seen: dict[str, GroundControlPoint] = {}
    unique = []
    for p in points:
        q = seen.get(p.name)
        if q is None:
            seen[p.name] = p
            unique.append(p)
        elif max(abs(p.x - q.x), abs(p.y - q.y), abs(p.z - q.z)) > 1e-6:
            raise InputError(
                f"GCP {p.name!r} appears again with other coordinates (first on line {q.line})", path=path, line=p.line
            )
    return GcpSet(tuple(unique), crs, path, observations)


def read_gcp_file(path: str | os.PathLike[str], crs: CRS | str | None = None) -> GcpSet:
    """Read a GCP coordinate file in any supported format.

    ``crs`` is used when the file has no CRS of its own (and overrides none).

    Raises
    ------
    InputError
        Naming the file, the line and what was expected.
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as e:
        raise InputError(f"cannot read GCP file: {e}", path=path) from None
    given = parse_crs(crs) if crs is not None else None
    if text.lstrip().startswith(("{", "[")):
        return _read_opensfm_json(text, path)
    lines = text.splitlines()
    first = next((i for i, ln in enumerate(lines) if ln.strip() and not ln.lstrip().startswith("#")), None)
    if first is None:
        raise InputError("empty GCP file", path=path)
    file_crs = _crs_line(lines[first], path, first + 1)
    if file_crs is not None:
        return _read_text_rows(lines, first + 1, file_crs, path)
    header = re.split(r"[,;\t]", lines[first].strip().lower())
    header = [h.strip().strip('"') for h in header]
    if any(h in _NAME_COLS for h in header) and not any(_is_number(h) for h in header):
        return _read_named_csv(lines, first, given, path)
    if given is None:
        raise InputError(
            "no CRS: the first line should be EPSG:xxxx, a PROJ string or 'WGS84 UTM 29N' (or give the CRS)",
            path=path,
            line=first + 1,
        )
    return _read_text_rows(lines, first, given, path)


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def _read_text_rows(lines: list[str], start: int, crs: CRS, path: Path) -> GcpSet:
    points = []
    observations = []
    unnamed: set[int] = set()
    geographic = crs.is_geographic
    for i in range(start, len(lines)):
        raw = lines[i].split("#", 1)[0].strip()
        if not raw:
            continue
        if ";" in raw:  # semicolon-separated: commas inside a field are decimal commas (483601,6247)
            f = [t.strip().replace(",", ".") for t in raw.split(";") if t.strip()]
        elif "\t" in raw:  # tab-separated: a field may hold spaces (an image name)
            f = [t.strip() for t in raw.split("\t") if t.strip()]
        else:
            f = [t for t in re.split(r"[\s,]+", raw) if t]
        n = i + 1
        if len(f) >= 6 and _is_number(f[0]) and _is_number(f[3]) and _is_number(f[4]):
            # an ODM gcp_list.txt row: geo_x geo_y geo_z im_x im_y image [name]
            f = f[:5] + _image_then_rest(f[5:])
            x, y, z = (_num(v, path, n, w) for v, w in zip(f[:3], ("x", "y", "z")))
            name = f[6] if len(f) >= 7 else f"{x:.3f}_{y:.3f}"
            if len(f) < 7:
                unnamed.add(n)
            if geographic:
                _check_geographic(name, y, x, path, n)
            points.append(GroundControlPoint(name, x, y, z, n))
            px, py = _num(f[3], path, n, "pixel x"), _num(f[4], path, n, "pixel y")
            observations.append(ImagePoint(name, f[5], px, py, n))
            continue
        if len(f) < 3:
            raise InputError(f"expected 'name x y z' (or 'name lat lon h'), got {len(f)} fields", path=path, line=n)
        name = f[0]
        a = _num(f[1], path, n, "latitude" if geographic else "x")
        b = _num(f[2], path, n, "longitude" if geographic else "y")
        z = _num(f[3], path, n, "height") if len(f) >= 4 else 0.0
        if geographic:
            _check_geographic(name, a, b, path, n)
            points.append(GroundControlPoint(name, b, a, z, n))
        else:
            points.append(GroundControlPoint(name, a, b, z, n))
    if unnamed:
        # A row without a name belongs to the named GCP at the same coordinates, if there is one.
        named = {(p.x, p.y, p.z): p.name for p in points if p.line not in unnamed}
        points = [replace(p, name=named.get((p.x, p.y, p.z), p.name)) for p in points]
        new_name = {p.line: p.name for p in points}
        observations = [replace(o, gcp=new_name.get(o.line, o.gcp)) for o in observations]
    return _finish(points, crs, path, tuple(observations))


_IMAGE_SUFFIX = re.compile(r".*\.(jpe?g|tiff?|png|dng)$", re.IGNORECASE)


def _image_then_rest(fields: list[str]) -> list[str]:
    """An image name split at its spaces (``DJI 0001.JPG``) joined again: the shortest run of
    fields that ends in an image suffix, when the first field does not."""
    if _IMAGE_SUFFIX.match(fields[0]):
        return fields
    for k in range(2, len(fields) + 1):
        if _IMAGE_SUFFIX.match(fields[k - 1]):
            return [" ".join(fields[:k]), *fields[k:]]
    return fields


def _read_named_csv(lines: list[str], first: int, crs: CRS | None, path: Path) -> GcpSet:
    body = "\n".join(lines[first:])
    try:
        dialect = csv.Sniffer().sniff(lines[first], delimiters=",;\t")
    except csv.Error:
        dialect = csv.excel
    reader = csv.reader(io.StringIO(body), dialect)
    header = [h.strip().lower() for h in next(reader)]

    def col(names: tuple[str, ...]) -> int | None:
        return next((header.index(n) for n in names if n in header), None)

    i_name = col(_NAME_COLS)
    i_lat, i_lon = col(_COLS["lat"]), col(_COLS["lon"])
    i_a: int | None
    i_b: int | None
    if i_lat is not None and i_lon is not None:
        i_a, i_b, i_z, geographic = i_lon, i_lat, col(_COLS["alt"]), True
        crs = crs or WGS84_3D
    else:
        i_a, i_b, i_z, geographic = col(_COLS["x"]), col(_COLS["y"]), col(_COLS["z"]), False
        if i_a is None or i_b is None:
            raise InputError(
                f"no coordinate columns in header {header}: expected lat/lon(/alt) or "
                "x/y/z or easting/northing/elevation",
                path=path,
                line=first + 1,
            )
        if crs is None:
            raise InputError("projected coordinates but no CRS: give the CRS", path=path, line=first + 1)
    points = []
    for k, row in enumerate(reader):
        n = first + 2 + k
        if not row or not "".join(row).strip() or row[0].lstrip().startswith("#"):
            continue
        need = max(i for i in (i_name, i_a, i_b, i_z) if i is not None)
        if len(row) <= need:
            raise InputError(f"expected {need + 1} columns, got {len(row)}", path=path, line=n)
        name = row[i_name].strip() if i_name is not None else str(k + 1)
        a = _num(row[i_a].strip(), path, n, header[i_a])
        b = _num(row[i_b].strip(), path, n, header[i_b])
        z = _num(row[i_z].strip(), path, n, header[i_z]) if i_z is not None else 0.0
        if geographic:
            _check_geographic(name, b, a, path, n)
        points.append(GroundControlPoint(name, a, b, z, n))
    return _finish(points, crs, path)


def _read_opensfm_json(text: str, path: Path) -> GcpSet:
    try:
        doc = json.loads(text)
    except json.JSONDecodeError as e:
        raise InputError(f"not valid JSON: {e.msg}", path=path, line=e.lineno) from None
    items = doc.get("points") if isinstance(doc, dict) else None
    if not isinstance(items, list):
        raise InputError(
            'expected OpenSfM\'s ground_control_points.json: {"points": [{"id": ..., "position": '
            '{"latitude": ..., "longitude": ..., "altitude": ...}}, ...]}',
            path=path,
        )
    points = []
    for k, p in enumerate(items):
        if not isinstance(p, dict):
            raise InputError(f"point {k + 1}: expected an object with id and position, got {p!r:.40}", path=path)
        name = str(p.get("id", k + 1))
        if "position" in p:
            pos = p["position"]
            try:
                lat, lon = float(pos["latitude"]), float(pos["longitude"])
                alt = float(pos.get("altitude", 0.0))
            except (KeyError, TypeError, ValueError, AttributeError):
                raise InputError(f"point {name!r}: position needs latitude, longitude (altitude)", path=path) from None
            if not all(map(math.isfinite, (lat, lon, alt))):
                raise InputError(f"point {name!r}: latitude, longitude and altitude must be numbers", path=path)
            _check_geographic(name, lat, lon, path, 0)
            points.append(GroundControlPoint(name, lon, lat, alt, 0))
    if not points:
        raise InputError("no point with a 'position' in ground_control_points.json", path=path)
    return _finish(points, WGS84_3D, path)
