"""Point clouds in bounded memory: LAS/LAZ (laspy + lazrs), PLY (plyfile), NumPy arrays.

A :class:`PointSource` knows its CRS, units, bounds and count from the header
and yields the points in chunks as often as asked (the DEM makes two passes),
so memory follows the chunk size, not the cloud.

Units: coordinates stay in the file's units. LAS files from the United States
often carry feet, and sometimes say so only half-way — an EPSG code in metres
next to a GeoTIFF ``ProjLinearUnits`` key in US survey feet (PDAL's
``mvk-thin.las``). The key wins when the coordinates fall in the CRS's area of
use only in its units; the reason is reported.
"""

from __future__ import annotations

import copy
import math
import os
import struct
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
from pyproj import CRS

from geoortho.core.crs import (
    heights_label,
    heights_of,
    horizontal_of,
    horizontal_unit_m,
    transformer,
    with_heights,
)
from geoortho.core.outputs import atomic_path
from geoortho.errors import InputError

__all__ = ["Chunk", "PointSource", "open_points", "write_las", "UNIT_CODES"]

#: GeoTIFF linear unit codes (ProjLinearUnitsGeoKey / VerticalUnitsGeoKey) → (name, metres per unit)
UNIT_CODES = {9001: ("metre", 1.0), 9002: ("foot", 0.3048), 9003: ("US survey foot", 1200 / 3937)}
POINT_EXTENSIONS = (".las", ".laz", ".ply")
CHUNK_POINTS = 2_000_000


@dataclass
class Chunk:
    x: np.ndarray  # float64, CRS units
    y: np.ndarray
    z: np.ndarray  # vertical units
    classification: np.ndarray | None  # uint8 ASPRS classes, when the source has them
    start: int  # index of the first point in the source


@dataclass
class PointSource:
    """Where the points come from and what they are, without reading them."""

    path: Path | None
    crs: CRS
    count: int
    bounds: tuple[float, float, float, float, float, float]  # xmin ymin zmin xmax ymax zmax
    horizontal_unit: str
    horizontal_m: float  # metres per horizontal unit
    vertical_unit: str
    vertical_m: float
    has_classification: bool
    notes: list[str] = field(default_factory=list)  # how the CRS and units were decided
    _array: np.ndarray | None = None
    _classes: np.ndarray | None = None
    _reproject_from: CRS | None = None  # the file's CRS when the points are read into ``crs``
    heights: CRS | str | None = None  # the heights' datum (``crs`` is horizontal), None: not stated

    @property
    def crs_with_heights(self) -> CRS:
        """``crs`` with the heights' datum, for a product of heights (a DEM) to carry."""
        return with_heights(self.crs, self.heights)

    @property
    def file_crs(self) -> CRS:
        """The CRS the file's coordinates are in (``crs`` unless reprojected)."""
        return self._reproject_from or self.crs

    def chunks(self, size: int = CHUNK_POINTS) -> Iterator[Chunk]:
        """The points, ``size`` at a time (NaN coordinates are the caller's to judge)."""
        if self._reproject_from is None:
            yield from self._file_chunks(size)
            return
        t = transformer(self._reproject_from, self.crs)
        for ch in self._file_chunks(size):
            x, y = t.transform(ch.x, ch.y)
            yield Chunk(np.asarray(x, float), np.asarray(y, float), ch.z, ch.classification, ch.start)

    def _file_chunks(self, size: int) -> Iterator[Chunk]:
        if self._array is not None:
            for i in range(0, self.count, size):
                a = self._array[i : i + size]
                cls = self._classes[i : i + size] if self._classes is not None else None
                yield Chunk(a[:, 0], a[:, 1], a[:, 2], cls, i)
            return
        assert self.path is not None
        import laspy

        start = 0
        try:
            with laspy.open(str(self.path)) as reader:
                for pts in reader.chunk_iterator(size):
                    n = len(pts)
                    yield Chunk(
                        np.asarray(pts.x, float),
                        np.asarray(pts.y, float),
                        np.asarray(pts.z, float),
                        np.asarray(pts.classification, np.uint8),
                        start,
                    )
                    start += n
        except (laspy.errors.LaspyException, ValueError, OSError, RuntimeError, struct.error, IndexError) as e:
            # RuntimeError: lazrs's LazrsError, a LAZ stream that ends before the header's count
            raise InputError(
                f"cannot read points after {start:,} of the {self.count:,} the header states "
                f"(truncated or corrupt file?): {e}",
                path=self.path,
            ) from e
        except BaseException as e:
            # lazrs panics on some corrupt streams: pyo3's PanicException derives from BaseException
            if type(e).__name__ != "PanicException":
                raise
            raise InputError(
                f"cannot read points after {start:,}: the LAZ stream is corrupt ({e})", path=self.path
            ) from None

    def describe_units(self) -> str:
        return f"horizontal {self.horizontal_unit}, vertical {self.vertical_unit}"


def open_points(
    source: str | os.PathLike[str] | np.ndarray,
    crs: CRS | None = None,
    *,
    classification: np.ndarray | None = None,
    default_crs: CRS | None = None,
) -> PointSource:
    """Open a LAS/LAZ/PLY file or wrap an (N, 3) array (x, y, z in ``crs``).

    ``crs`` overrides the file's CRS; ``default_crs`` is taken only when the file has none
    (one of them is required then).
    """
    if isinstance(source, np.ndarray):
        return _from_array(source, crs or default_crs, classification, None, [])
    path = Path(source)
    if not path.is_file():
        raise InputError("no such file", path=path)
    ext = path.suffix.lower()
    if ext in (".las", ".laz"):
        return _open_las(path, crs, default_crs)
    if ext == ".ply":
        return _open_ply(path, crs or default_crs)
    raise InputError(f"unknown point cloud format {ext!r} (use {', '.join(POINT_EXTENSIONS)})", path=path)


def reprojected(src: PointSource, crs: CRS) -> PointSource:
    """The same points in another projected CRS (x, y transformed by pyproj as they are read;
    heights unchanged). The source itself if it already is in ``crs``.

    Refused when the points lie outside their own CRS's area: that CRS is then wrong (the old
    meaning of dem's --crs was to override it; --points-crs does that now), and reprojecting
    from it would write garbage."""
    target = horizontal_of(crs)  # heights are not moved between datums: the points' stays
    if target == src.crs:
        return src
    xmin, ymin, zmin, xmax, ymax, zmax = src.bounds
    if _inside_area(src.crs, (xmin + xmax) / 2, (ymin + ymax) / 2) is False:
        raise InputError(
            f"the points lie outside the area of their CRS ({src.crs.name}), so they cannot be reprojected "
            "to --crs: give the CRS they are really in with --points-crs",
            path=src.path,
        )
    t = transformer(src.crs, target)
    if all(map(math.isfinite, (xmin, ymin, xmax, ymax))):
        bx0, by0, bx1, by1 = t.transform_bounds(xmin, ymin, xmax, ymax, densify_pts=21)
    else:
        bx0 = by0 = bx1 = by1 = math.nan
    h_name, h_m = _units_of(target)
    note = (
        f"reprojected from {src.crs.name} to {target.name} (x, y by pyproj; heights unchanged, "
        f"in {src.vertical_unit} of the points' vertical datum)"
    )
    return replace(
        src,
        crs=target,
        bounds=(bx0, by0, zmin, bx1, by1, zmax),
        horizontal_unit=h_name,
        horizontal_m=h_m,
        notes=[*src.notes, note],
        _reproject_from=src.crs,
    )


def write_las(
    path: str | os.PathLike[str],
    xyz: np.ndarray,
    crs: CRS | None,
    *,
    rgb: np.ndarray | None = None,
    classification: np.ndarray | None = None,
    offset: np.ndarray | None = None,
    chunk_points: int = 1_000_000,
) -> Path:
    """Write points (N, 3) as LAS/LAZ 1.4 (by extension), millimetre scale, the CRS in the header
    (none for a cloud in a local frame: ``crs`` None).

    ``xyz`` may be relative to ``offset`` (e.g. float32 near a survey's middle); ``rgb`` is (N, 3)
    in 0..1. Written atomically, ``chunk_points`` at a time: memory holds one chunk, not a copy of
    the cloud.
    """
    xyz = np.asarray(xyz).reshape(-1, 3)
    parts = (
        (
            xyz[start : start + chunk_points],
            None if rgb is None else rgb[start : start + chunk_points],
            None if classification is None else classification[start : start + chunk_points],
        )
        for start in range(0, len(xyz), chunk_points)
    )
    lowest = xyz.min(axis=0).astype(float) if len(xyz) else np.zeros(3)
    return write_las_parts(path, parts, crs, lowest=lowest, offset=offset)


def write_las_parts(
    path: str | os.PathLike[str],
    parts: Iterable[tuple[np.ndarray, np.ndarray | None, np.ndarray | None]],
    crs: CRS | None,
    *,
    lowest: np.ndarray,
    offset: np.ndarray | None = None,
) -> Path:
    """:func:`write_las` for a cloud that comes a part at a time — (xyz, rgb or None, class or
    None), each as there — and is never held whole. ``lowest``: the cloud's smallest x, y, z (in
    ``xyz``'s frame), known before the first part, for the header's offsets. Atomic."""
    import laspy

    base = np.zeros(3) if offset is None else np.asarray(offset, float).reshape(3)
    header = laspy.LasHeader(point_format=3, version="1.4")
    header.offsets = np.floor(np.asarray(lowest, float) + base)
    header.scales = [0.001, 0.001, 0.001]
    if crs is not None:
        # GeoTIFF keys (read by every LAS reader) for a CRS with one EPSG code; a compound or 3D
        # CRS (the heights' datum) has none, and goes as the LAS 1.4 WKT record
        header.add_crs(crs, keep_compatibility=crs.to_epsg() is not None)
    with atomic_path(path) as tmp:
        with laspy.open(str(tmp), mode="w", header=header) as writer:
            for xyz, rgb, classification in parts:
                pts = np.asarray(xyz).reshape(-1, 3).astype(np.float64) + base
                rec = laspy.ScaleAwarePointRecord.zeros(len(pts), header=header)
                rec.x, rec.y, rec.z = pts[:, 0], pts[:, 1], pts[:, 2]
                if classification is not None:
                    rec.classification = np.asarray(classification, np.uint8)
                if rgb is not None:
                    col16 = np.clip(np.asarray(rgb, float) * 65535.0 + 0.5, 0, 65535).astype(np.uint16)
                    rec.red, rec.green, rec.blue = col16[:, 0], col16[:, 1], col16[:, 2]
                writer.write_points(rec)
    return Path(path)


def _units_of(crs: CRS) -> tuple[str, float]:
    m = horizontal_unit_m(crs)
    return (crs.axis_info[0].unit_name if m != 1.0 else "metre"), m


def _vertical_of(crs: CRS) -> tuple[str, float] | None:
    for sub in crs.sub_crs_list or []:
        if sub.is_vertical and sub.axis_info:
            return sub.axis_info[0].unit_name, float(sub.axis_info[0].unit_conversion_factor)
    return None


def with_linear_unit(crs: CRS, name: str, metres: float) -> CRS:
    """The same projected CRS with its axes in another linear unit."""
    d = copy.deepcopy(crs.to_json_dict())
    target = d.get("components", [d])[0] if d.get("type") == "CompoundCRS" else d
    for axis in target["coordinate_system"]["axis"]:
        axis["unit"] = {"type": "LinearUnit", "name": name, "conversion_factor": metres}
    target.pop("id", None)
    target["name"] = f"{target['name']} ({name})"
    d.pop("id", None)
    return CRS.from_json_dict(d)


def _inside_area(crs: CRS, x: float, y: float) -> bool | None:
    aou = crs.area_of_use
    if aou is None:
        return None
    lon, lat = transformer(crs, CRS.from_epsg(4326)).transform(x, y)
    w, s, e, n = aou.bounds
    pad = 1.0
    return bool(w - pad <= lon <= e + pad and s - pad <= lat <= n + pad)


def _geokeys(header: Any) -> dict[int, int]:
    for v in header.vlrs:
        if type(v).__name__ == "GeoKeyDirectoryVlr":
            return {k.id: k.value_offset for k in v.geo_keys if k.tiff_tag_location == 0}
    return {}


#: Bytes per point of each LAS point format (0-10), the least a record can hold.
_LAS_RECORD_MIN = (20, 28, 26, 34, 57, 63, 30, 36, 38, 59, 67)
#: No LAZ file compresses its points better than this (typical: 5-10 x).
_LAZ_MAX_RATIO = 100


def check_las_header(path: Path) -> None:
    """Refuse a LAS/LAZ header whose counts cannot be true before laspy or lazrs trusts them:
    a mutated VLR count makes laspy read for minutes, a point count of billions makes lazrs
    allocate tens of GB and abort the process (not an exception: the run dies)."""
    size = path.stat().st_size
    with open(path, "rb") as f:
        h = f.read(375)
    if len(h) < 227 or h[:4] != b"LASF":
        raise InputError("not a LAS/LAZ file (no LASF signature)", path=path)
    minor = h[25]
    header_size, to_points, n_vlrs = struct.unpack_from("<HII", h, 94)
    fmt_byte, record_len, legacy_count = struct.unpack_from("<BHI", h, 104)
    fmt, compressed = fmt_byte & 0x3F, bool(fmt_byte & 0xC0)
    count = legacy_count
    if minor >= 4 and len(h) >= 255:
        count = max(count, struct.unpack_from("<Q", h, 247)[0])

    def bad(why: str) -> InputError:
        return InputError(f"corrupt LAS header: {why}", path=path)

    if not 227 <= header_size <= to_points <= size:
        raise bad(f"header size {header_size} and point offset {to_points} do not fit a file of {size:,} bytes")
    if n_vlrs * 54 > to_points - header_size:
        raise bad(f"{n_vlrs:,} VLRs cannot fit in the {to_points - header_size:,} bytes before the points")
    if fmt >= len(_LAS_RECORD_MIN) or record_len < _LAS_RECORD_MIN[fmt]:
        raise bad(f"point format {fmt} with {record_len}-byte records")
    with open(path, "rb") as f:  # the VLRs: the laszip one states the chunk lazrs allocates whole
        f.seek(header_size)
        vlrs = f.read(to_points - header_size)
    at = 0
    for _ in range(n_vlrs):
        if at + 54 > len(vlrs):
            raise bad(f"{n_vlrs} VLRs announced, the header region ends after fewer")
        user_id = vlrs[at + 2 : at + 18].rstrip(b"\0")
        record_id, length = struct.unpack_from("<HH", vlrs, at + 18)
        data = vlrs[at + 54 : at + 54 + length]
        if user_id == b"laszip encoded" and record_id == 22204 and len(data) >= 16:
            chunk = struct.unpack_from("<I", data, 12)[0]
            if chunk != 0xFFFFFFFF and chunk * record_len > 2**31:  # 0xFFFFFFFF: variable-size chunks
                raise bad(f"a LAZ chunk of {chunk:,} points")
            _check_chunk_table(path, to_points, size, bad)
        at += 54 + length
    room = size - to_points
    if count * record_len > (_LAZ_MAX_RATIO if compressed or path.suffix.lower() == ".laz" else 1) * room:
        raise bad(f"{count:,} points of {record_len} bytes cannot be in {room:,} bytes of point data")


def _check_chunk_table(path: Path, to_points: int, size: int, bad: Any) -> None:
    """LAZ: the points start with the chunk table's offset; the table starts with its chunk count,
    which lazrs allocates before reading a chunk. No chunk is smaller than a byte."""
    with open(path, "rb") as f:
        f.seek(to_points)
        raw = f.read(8)
        if len(raw) < 8:
            raise bad("no LAZ chunk table offset")
        offset = struct.unpack("<q", raw)[0]
        if offset == -1:  # not written (a streamed file): lazrs reads the chunks in order
            return
        if not to_points < offset <= size - 8:
            raise bad(f"the LAZ chunk table offset {offset:,} is outside the file")
        f.seek(offset + 4)
        n_chunks = struct.unpack("<I", f.read(4))[0]
    if n_chunks > size:
        raise bad(f"{n_chunks:,} LAZ chunks in a file of {size:,} bytes")


def _open_las(path: Path, override: CRS | None, default: CRS | None = None) -> PointSource:
    import laspy

    check_las_header(path)
    try:
        with laspy.open(str(path)) as reader:
            h = reader.header
            count = int(h.point_count)
            mins, maxs = np.asarray(h.mins, float), np.asarray(h.maxs, float)
            try:
                file_crs = h.parse_crs()
            except Exception as e:  # a broken CRS record is reported, not fatal when --crs is given
                file_crs = None
                if override is None and default is None:
                    raise InputError(
                        f"unreadable CRS in the LAS header ({e}); give the points' CRS (--points-crs)", path=path
                    ) from e
            keys = _geokeys(h)
    except InputError:
        raise
    except BaseException as e:  # laspy meets a broken header with struct, value and index errors of all kinds
        if not isinstance(e, Exception) and type(e).__name__ != "PanicException":  # lazrs panics are Base
            raise
        raise InputError(f"not a readable LAS/LAZ file: {type(e).__name__}: {e}", path=path) from None
    notes: list[str] = []
    if override is not None:
        crs = override
        notes.append(f"CRS given: {crs.name}")
    elif file_crs is None and default is not None:
        crs = override = default  # as if given: the header's unit keys are not read either
        notes.append(f"no CRS in the LAS header: taken to be the output CRS, {crs.name}")
    elif file_crs is None:
        raise InputError("no CRS in the LAS header; give the points' CRS (--points-crs)", path=path)
    else:
        crs = file_crs
        notes.append(f"CRS from the LAS header: {crs.name}" + (f" (EPSG:{crs.to_epsg()})" if crs.to_epsg() else ""))
        h_unit = UNIT_CODES.get(keys.get(3076, 0))
        unit_name, unit_m = _units_of(crs)
        if crs.is_projected and h_unit is not None and abs(h_unit[1] - unit_m) > 1e-9:
            # The EPSG code and the unit key disagree: believe whichever puts the points in the CRS's area.
            cx, cy = (mins[0] + maxs[0]) / 2, (mins[1] + maxs[1]) / 2
            alt = with_linear_unit(crs, *h_unit)
            if _inside_area(crs, cx, cy) is not True and _inside_area(alt, cx, cy) is not False:
                notes.append(
                    f"units: {h_unit[0]} from the GeoTIFF ProjLinearUnits key, not the {unit_name} of "
                    f"the CRS code: only in {h_unit[0]} do the points fall in the CRS's area"
                )
                crs = alt
            else:
                notes.append(
                    f"units: {unit_name} of the CRS code kept over the ProjLinearUnits key "
                    f"({h_unit[0]}): the points fall in the CRS's area in {unit_name}"
                )
    if crs.is_geographic:
        raise InputError(
            "geographic coordinates (degrees): reproject the cloud to a projected CRS or give "
            "the projected CRS it is in (--points-crs)",
            path=path,
        )
    h_name, h_m = _units_of(crs)
    v_name, v_m = h_name, h_m
    v_key = UNIT_CODES.get(keys.get(4099, 0)) if override is None else None
    v_crs = _vertical_of(crs)
    if v_crs is not None:
        v_name, v_m = v_crs
        notes.append(f"heights in {v_name} (vertical CRS)")
    elif v_key is not None:
        v_name, v_m = v_key
        notes.append(f"heights in {v_name} (GeoTIFF VerticalUnits key)")
    else:
        notes.append(f"heights in {v_name}, as the horizontal units (no vertical unit stated)")
    heights = heights_of(crs)
    notes.append(f"heights' datum: {heights_label(heights)}" + ("" if heights else " in the LAS header's CRS"))
    return PointSource(
        path, horizontal_of(crs), count, (*mins, *maxs), h_name, h_m, v_name, v_m, True, notes, heights=heights
    )


def _open_ply(path: Path, override: CRS | None) -> PointSource:
    from plyfile import PlyData, PlyHeaderParseError

    try:
        ply = PlyData.read(str(path))
        v = ply["vertex"]
        xyz = np.c_[np.asarray(v["x"], float), np.asarray(v["y"], float), np.asarray(v["z"], float)]
    except (PlyHeaderParseError, KeyError, ValueError, OSError) as e:
        raise InputError(f"not a readable PLY point cloud with x, y, z vertices: {e}", path=path) from e
    names = v.data.dtype.names or ()
    cls = np.asarray(v["classification"], np.uint8) if "classification" in names else None
    if override is None:
        raise InputError("PLY files carry no CRS; give the points' CRS (--points-crs)", path=path)
    return _from_array(xyz, override, cls, path, [f"CRS given: {override.name}"])


def _from_array(
    a: np.ndarray, crs: CRS | None, classification: np.ndarray | None, path: Path | None, notes: list[str]
) -> PointSource:
    a = np.asarray(a, float)
    if a.ndim != 2 or a.shape[1] < 3:
        raise InputError(f"points must be an (N, 3) array of x, y, z, not {a.shape}", path=path)
    if crs is None:
        raise InputError("the points have no CRS; give one (crs=...)", path=path)
    if crs.is_geographic:
        raise InputError("geographic coordinates (degrees): give points in a projected CRS", path=path)
    if classification is not None and len(classification) != len(a):
        raise InputError(f"{len(classification)} classes for {len(a)} points", path=path)
    finite = np.isfinite(a[:, :3]).all(axis=1)
    if len(a) and finite.any():
        mins, maxs = a[finite, :3].min(axis=0), a[finite, :3].max(axis=0)
    else:
        mins = maxs = np.full(3, np.nan)
    h_name, h_m = _units_of(crs)
    v = _vertical_of(crs)
    v_name, v_m = v if v is not None else (h_name, h_m)
    return PointSource(
        path,
        horizontal_of(crs),
        len(a),
        (*mins, *maxs),
        h_name,
        h_m,
        v_name,
        v_m,
        classification is not None,
        notes or [f"CRS given: {crs.name}"],
        _array=a[:, :3],
        _classes=None if classification is None else np.asarray(classification, np.uint8),
        heights=heights_of(crs),
    )
