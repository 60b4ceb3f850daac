"""Photo metadata: EXIF and XMP → :class:`Photo`, without decoding pixels.

Pillow reads the JPEG/TIFF headers only (``Image.open`` is lazy), so the
decoded pixel size is known without decoding — EXIF size tags lie on resized
photos. XMP is read with a tolerant regular expression that accepts both the
attribute form (``drone-dji:GimbalYawDegree="+12.3"``) and the element form
(``<drone-dji:GimbalYawDegree>12.3</...>``) that editors rewrite it into.

Attitude is returned in the drone makers' convention (camera.py): yaw
clockwise from north, pitch −90 = nadir, roll right side down positive.
"""

from __future__ import annotations

import concurrent.futures as cf
import functools
import math
import os
import re
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any
from warnings import catch_warnings, simplefilter

import numpy as np

from geoortho.core.camera import Intrinsics
from geoortho.core.gsd import focal_length_px
from geoortho.core.parallel import map_ordered
from geoortho.errors import InputError
from geoortho.feedback import Feedback, as_feedback, warn_grouped
from geoortho.photos.sensors import SENSOR_WIDTHS_MM, sensor_width_from_table

__all__ = [
    "Photo",
    "PhotoSet",
    "SENSOR_WIDTHS_MM",
    "IMAGE_EXTENSIONS",
    "read_photo",
    "read_photos",
    "list_images",
    "parse_xmp",
    "photo_seconds",
    "sensor_width_from_table",
]

IMAGE_EXTENSIONS = (".jpg", ".jpeg", ".tif", ".tiff")
#: Photos read per task: a pool (or the cluster) pays off from 4 chunks (256 photos) on
PHOTOS_PER_CHUNK = 64

_XMP_ATTR = re.compile(rb"([A-Za-z][\w.-]*):([A-Za-z]\w*)\s*=\s*([\"'])(.*?)\3", re.S)
_XMP_ELEM = re.compile(rb"<([A-Za-z][\w.-]*):([A-Za-z]\w*)>([^<]*)</\1:\2>")
# A struct: an element whose fields are its attributes or its child elements (Skydio's
# CameraOrientationNED, in either form); its fields are keyed ``prefix:Struct:Field``.
_XMP_STRUCT = re.compile(rb"<(?!rdf:|x:)([A-Za-z][\w.-]*):([A-Za-z]\w*)\b([^>]*?)(?:/>|>(.*?)</\1:\2>)", re.S)


@dataclass(frozen=True)
class _Family:
    """One maker's attitude tags: the camera's (gimbal) and the aircraft's, and how to turn them
    into our convention (yaw clockwise from true north, pitch −90 = nadir, roll right side down)."""

    source: str  # stated per photo (Photo.attitude_source)
    camera: tuple[str, str, str]  # yaw, pitch, roll tag names
    aircraft: tuple[str, str, str] | None = None
    pitch_offset_deg: float = 0.0  # added to the tag's pitch
    roll_sign: float = 1.0  # -1: the maker writes roll the other way round
    makes: tuple[str, ...] = ()  # only for these EXIF makes (lower case); () = any


def _ypr(pattern: str) -> tuple[str, str, str]:
    """Yaw, pitch and roll tag names from one pattern: ``"drone-dji:Gimbal{}Degree"``."""
    return pattern.format("Yaw"), pattern.format("Pitch"), pattern.format("Roll")


# First family with any of its tags wins. Documents followed: DJI's XMP drone-dji
# tags (DJI Mobile SDK / Thermal SDK tag list); Autel's newer firmware, which writes DJI's names
# under the prefix ``drone:`` (as observed in EVO II photos; Autel publishes no list); Parrot's
# "Embedded photo metadata" (developer.parrot.com/docs/pdraw/photo-metadata.html: CameraPitchDegree
# is NED, −90 = nadir, and the same photo's Camera:Pitch is 90° more); Skydio's "camera and
# metadata overview" (support.skydio.com 4417425974683: CameraOrientationNED Yaw/Pitch/Roll,
# a struct); Pix4D's "Specifications of xmp.camera tags" (support.pix4d.com 360016450032,
# angles per article 202558969: pitch 0 = nadir), written by MicaSense, Sentera, Parrot
# Sequoia, senseFly (its own namespace URI, same names), WingtraHub and older Autel firmware.
_FAMILIES: tuple[_Family, ...] = (
    _Family("gimbal", _ypr("drone-dji:Gimbal{}Degree"), _ypr("drone-dji:Flight{}Degree")),
    _Family("gimbal (Autel)", _ypr("drone:Gimbal{}Degree"), _ypr("drone:Flight{}Degree")),
    _Family("gimbal (Parrot)", _ypr("drone-parrot:Camera{}Degree"), _ypr("drone-parrot:Drone{}Degree")),
    _Family(
        "gimbal (Skydio)", _ypr("drone-skydio:CameraOrientationNED:{}"), _ypr("drone-skydio:FlightOrientationNED:{}")
    ),
    _Family("camera", _ypr("Camera:{}"), pitch_offset_deg=-90.0, roll_sign=-1.0, makes=("sensefly",)),
    _Family("camera", _ypr("Camera:{}"), pitch_offset_deg=-90.0),
)
_NO_ATTITUDE = "no attitude in the metadata: assumed nadir, image top to the north"
# Position and altitudes where EXIF GPS is missing, and the relative/absolute altitudes, by maker.
_LATITUDE = ("drone-dji:GpsLatitude", "drone-dji:Latitude", "drone:GpsLatitude", "drone-skydio:Latitude")
_LONGITUDE = (
    "drone-dji:GpsLongitude",
    "drone-dji:GpsLongtitude",  # sic: some DJI and Autel firmware
    "drone-dji:Longitude",
    "drone:GpsLongitude",
    "drone:GpsLongtitude",
    "drone-skydio:Longitude",
)
_RELATIVE = (
    "drone-dji:RelativeAltitude",
    "drone:RelativeAltitude",
    "drone-skydio:RelativeAltitude",
    "Camera:AboveGroundAltitude",
)
_ABSOLUTE = ("drone-dji:AbsoluteAltitude", "drone:AbsoluteAltitude", "drone-skydio:AbsoluteAltitude")

# Position accuracy. DJI's RTK aircraft (Phantom 4 RTK, Matrice 300/350 RTK, Mavic 3 Enterprise
# RTK) write the receiver's solution as drone-dji:RtkFlag, with the codes of DJI's SDK enum
# RTKPositioningSolution (0 none, 16 single point, 34 float, 50 fixed point), and its standard
# deviations in metres as RtkStdLon, RtkStdLat and RtkStdHgt (the SDK's LocationStandardDeviation:
# "standard deviation of location accuracy in meters"). Pix4D's XMP camera tags (written by
# MicaSense, Sentera, WingtraHub and others) give Camera:GPSXYAccuracy and Camera:GPSZAccuracy in
# metres; OpenDroneMap reads both families the same way, as standard deviations.
RTK_FLAGS: dict[int, str] = {0: "consumer", 16: "single", 34: "float", 50: "fixed"}
#: 1-sigma horizontal and vertical accuracy (m) taken for a fix state stated without deviations:
#: typical receiver figures (fixed 1-2 cm + 1 ppm, float decimetres, single point metres).
DEFAULT_SIGMA_M: dict[str, tuple[float, float]] = {
    "fixed": (0.02, 0.03),
    "float": (0.3, 0.5),
    "single": (1.5, 3.0),
}
#: A fixed solution stated worse than this (m, horizontal) contradicts itself.
MAX_FIXED_SIGMA_M = 0.5


def factory_calibration(
    tags: dict[str, str], width_px: int, height_px: int
) -> tuple[float, float, float, tuple[float, ...], bool, str]:
    """DJI's factory calibration from the XMP: focal length and optical centre (px, corner origin,
    for the photo's own size), the distortion (k1, k2, p1, p2, k3) from DewarpData
    (``date;fx,fy,cx,cy,k1,k2,p1,p2,k3``), whether the JPEG is already undistorted (DewarpFlag 1),
    and a warning. Values that cannot belong to this photo (a focal length under a third or over
    five times its size, a centre off it) are dropped with the warning."""
    f = _xmp_float(tags, "drone-dji:CalibratedFocalLength")
    cx = _xmp_float(tags, "drone-dji:CalibratedOpticalCenterX")
    cy = _xmp_float(tags, "drone-dji:CalibratedOpticalCenterY")
    dewarped = _xmp_float(tags, "drone-dji:DewarpFlag") == 1.0
    distortion: tuple[float, ...] = ()
    raw = tags.get("drone-dji:DewarpData", "")
    distortion_warning = ""
    if raw:
        try:
            values = [float(v) for v in raw.split(";")[-1].split(",")]
            if len(values) >= 9:
                distortion = tuple(values[4:9])
        except ValueError:
            distortion = ()
    if distortion and math.isfinite(f) and not _plausible_distortion(distortion, f, width_px, height_px):
        # NaN stopped COLMAP with an assertion; an absurd one was blamed on overlap or texture
        distortion_warning = (
            f"DewarpData distortion ({', '.join(f'{v:.4g}' for v in distortion)}) is no lens's: ignored, the "
            "distortion is estimated"
        )
        distortion = ()
    if not math.isfinite(f):
        return math.nan, math.nan, math.nan, (), dewarped, ""
    size = max(width_px, height_px)
    centre_given = math.isfinite(cx) and math.isfinite(cy)
    off_photo = centre_given and not (0 < cx < width_px and 0 < cy < height_px)
    if not size / 3.0 <= f <= 5.0 * size or off_photo:  # (a calibration of the full size, on a resized copy)
        warning = (
            f"CalibratedFocalLength {f:g} px (optical centre {cx:g}, {cy:g}) cannot be this "
            f"{width_px}x{height_px} photo's: ignored"
        )
        return math.nan, math.nan, math.nan, (), dewarped, warning
    if not centre_given:
        cx, cy = width_px / 2.0, height_px / 2.0
    return f, cx, cy, (() if dewarped else distortion), dewarped, distortion_warning


#: A lens's radial distortion moves the frame's corner by at most this share of its radius (a
#: drone's rectilinear lens: a few percent; a fisheye is not calibrated this way).
MAX_CORNER_DISTORTION = 0.3
MAX_TANGENTIAL = 0.05


def _plausible_distortion(k: tuple[float, ...], f_px: float, width_px: int, height_px: int) -> bool:
    """Finite Brown coefficients (k1, k2, p1, p2, k3) that move the frame's corner by less than
    ``MAX_CORNER_DISTORTION`` of its radius, monotonic out to it, with small tangential terms."""
    if not all(math.isfinite(v) for v in k) or len(k) < 5:
        return False
    k1, k2, p1, p2, k3 = k[:5]
    r_corner = math.hypot(width_px, height_px) / 2.0 / f_px
    radii = [r_corner * t for t in (0.25, 0.5, 0.75, 1.0)]
    scaled = [r * (1 + k1 * r**2 + k2 * r**4 + k3 * r**6) for r in radii]
    monotonic = all(b > a for a, b in zip([0.0, *scaled], scaled))
    corner = abs(scaled[-1] / r_corner - 1.0)
    return monotonic and corner <= MAX_CORNER_DISTORTION and max(abs(p1), abs(p2)) <= MAX_TANGENTIAL


def position_accuracy(tags: dict[str, str]) -> tuple[float, float, str, str]:
    """The position's 1-sigma horizontal and vertical accuracy (m), its class, and a warning
    (empty when none) from the XMP tags; NaN and "consumer" when nothing is stated.

    The horizontal sigma is the larger of the two axes' (a per-axis figure, as the priors use
    it). A fix state without deviations takes ``DEFAULT_SIGMA_M``; deviations beyond what the
    state allows are kept (the deviations are measured, the state is a label) and flagged."""
    flag = _xmp_float(tags, "drone-dji:RtkFlag", "drone:RtkFlag")
    lon_m = _xmp_float(tags, "drone-dji:RtkStdLon", "drone:RtkStdLon")
    lat_m = _xmp_float(tags, "drone-dji:RtkStdLat", "drone:RtkStdLat")
    hgt_m = _xmp_float(tags, "drone-dji:RtkStdHgt", "drone:RtkStdHgt")
    if math.isfinite(flag):
        fix = RTK_FLAGS.get(int(flag), "single" if 0 < flag < 50 else "consumer")
        if fix == "consumer":
            return math.nan, math.nan, fix, ""
        h = max((v for v in (lon_m, lat_m) if math.isfinite(v) and v > 0), default=math.nan)
        v = hgt_m if math.isfinite(hgt_m) and hgt_m > 0 else math.nan
        dh, dv = DEFAULT_SIGMA_M[fix]
        warning = ""
        if fix == "fixed" and math.isfinite(h) and h > MAX_FIXED_SIGMA_M:
            warning = (
                f"RtkFlag {int(flag)} (fixed) with RtkStdLon/Lat {h:g} m: a fixed solution is centimetres; "
                "the stated deviation is used"
            )
        return floor_sigma(h if math.isfinite(h) else dh), floor_sigma(v if math.isfinite(v) else dv), fix, warning
    xy = _xmp_float(tags, "Camera:GPSXYAccuracy")
    z = _xmp_float(tags, "Camera:GPSZAccuracy")
    if math.isfinite(xy) and xy > 0:
        return floor_sigma(xy), floor_sigma(z if math.isfinite(z) and z > 0 else 2.0 * xy), "stated", ""
    return math.nan, math.nan, "consumer", ""


#: No GNSS position is known better than this (m, 1 sigma): a deviation stated tighter (a micrometre)
#: made the priors rigid, and sfm then blamed the GPS for the block's own noise.
MIN_SIGMA_M = 0.005


def floor_sigma(sigma_m: float) -> float:
    """A stated deviation, at least ``MIN_SIGMA_M`` (NaN stays NaN: not stated)."""
    return max(sigma_m, MIN_SIGMA_M) if math.isfinite(sigma_m) else sigma_m


@dataclass(frozen=True)
class Photo:
    """What a photo's metadata says: where it was taken, where it looked, with what camera.

    NaN marks a value the photo does not carry. ``sensor_width_mm`` spans the
    image's longer side; ``focal_px`` follows from it and the decoded size.
    """

    path: Path
    width_px: int
    height_px: int
    make: str = ""
    model: str = ""
    latitude_deg: float = math.nan
    longitude_deg: float = math.nan
    gps_altitude_m: float = math.nan  # EXIF GPSAltitude: roughly above sea level
    relative_altitude_m: float = math.nan  # DJI RelativeAltitude: above the take-off point
    absolute_altitude_m: float = math.nan  # DJI AbsoluteAltitude
    yaw_deg: float = 0.0
    pitch_deg: float = -90.0
    roll_deg: float = 0.0
    attitude_source: str = "assumed nadir"
    flight_yaw_deg: float = math.nan
    flight_pitch_deg: float = math.nan
    flight_roll_deg: float = math.nan
    focal_mm: float = math.nan
    focal_35mm: float = math.nan
    sensor_width_mm: float = math.nan
    sensor_source: str = ""
    taken_at: str = ""  # ISO 8601, camera clock
    exposure_time_s: float = math.nan
    f_number: float = math.nan
    iso: float = math.nan
    has_xmp: bool = False
    # The position's stated accuracy (1 sigma, metres; NaN: consumer GPS, none stated) and its
    # class: fixed, float, single (an RTK receiver's solution), stated (a camera's own accuracy
    # tags, no fix state), consumer (nothing said). See position_accuracy.
    gps_sigma_h_m: float = math.nan
    gps_sigma_v_m: float = math.nan
    gps_fix: str = "consumer"
    # The maker's factory calibration (DJI: CalibratedFocalLength, CalibratedOpticalCenterX/Y in
    # pixels, corner origin; DewarpData's k1 k2 p1 p2 k3), NaN/() when not written; ``dewarped``:
    # the JPEG was already undistorted in the camera (DewarpFlag 1), its distortion is none.
    factory_focal_px: float = math.nan
    factory_cx_px: float = math.nan
    factory_cy_px: float = math.nan
    factory_distortion: tuple[float, ...] = ()
    dewarped: bool = False
    warnings: tuple[str, ...] = field(default=(), compare=False)

    @property
    def image(self) -> str:
        return self.path.name

    @property
    def has_gps(self) -> bool:
        return math.isfinite(self.latitude_deg) and math.isfinite(self.longitude_deg)

    @property
    def has_altitude(self) -> bool:
        """Any of RelativeAltitude, AbsoluteAltitude or GPSAltitude."""
        return any(math.isfinite(v) for v in (self.relative_altitude_m, self.absolute_altitude_m, self.gps_altitude_m))

    @property
    def yaw_unknown(self) -> bool:
        """No yaw in the metadata (0 was assumed) and none taken from the course yet."""
        src = self.attitude_source
        return (src == "assumed nadir" or "yaw assumed" in src) and "course" not in src

    @property
    def exposure_value(self) -> float:
        """Relative exposure, ISO · t / N² (NaN when the EXIF lacks any of them): photos of the same
        scene come out brighter in proportion."""
        return self.iso * self.exposure_time_s / self.f_number**2

    @property
    def focal_px(self) -> float:
        """The factory calibration's focal length where the photo carries one, else EXIF's."""
        if math.isfinite(self.factory_focal_px):
            return self.factory_focal_px
        return self.exif_focal_px

    @property
    def exif_focal_px(self) -> float:
        return focal_length_px(self.focal_mm, self.sensor_width_mm, max(self.width_px, self.height_px))

    def intrinsics(self) -> Intrinsics:
        """Pinhole intrinsics, principal point at the image centre."""
        if not math.isfinite(self.focal_px):
            raise InputError("no focal length or sensor size: give sensor_width_mm", path=self.path)
        return Intrinsics(self.width_px, self.height_px, self.focal_px)

    def as_record(self) -> dict[str, Any]:
        """Flat dict for tables (path as text, warnings joined)."""
        d = {k: getattr(self, k) for k in self.__dataclass_fields__}
        d["path"] = str(self.path)
        d["warnings"] = "; ".join(self.warnings)
        d["factory_distortion"] = " ".join(f"{v:g}" for v in self.factory_distortion)
        d["image"] = self.image
        d["focal_px"] = self.focal_px
        return d


@dataclass
class PhotoSet:
    """Photos read from a folder, and those skipped with the reason."""

    photos: list[Photo]
    skipped: list[tuple[str, str]] = field(default_factory=list)

    def to_geodataframe(self, crs: Any = None) -> Any:
        """Camera positions as points (WGS84, or ``crs``), one row per photo with every field."""
        import geopandas as gpd
        import shapely

        records = [p.as_record() for p in self.photos]
        xy = positions_lonlat(self.photos)
        gdf = gpd.GeoDataFrame(records, geometry=shapely.points(xy), crs="EPSG:4326")
        return gdf.to_crs(crs) if crs is not None else gdf

    def summary(self) -> str:
        text = f"{len(self.photos)} photos read"
        if self.skipped:
            text += f", {len(self.skipped)} skipped: " + "; ".join(f"{n} ({r})" for n, r in self.skipped)
        return text


def parse_xmp(xmp: bytes | str | None) -> dict[str, str]:
    """``prefix:Name`` → value text, attribute and element forms alike (first occurrence wins)."""
    if not xmp:
        return {}
    data = xmp.encode("utf-8", "replace") if isinstance(xmp, str) else bytes(xmp)
    out: dict[str, str] = {}
    for rx in (_XMP_ATTR, _XMP_ELEM):
        for m in rx.finditer(data):
            prefix, name = m.group(1).decode(), m.group(2).decode()
            if prefix in ("xmlns", "xml"):
                continue
            value = (m.group(4) if rx is _XMP_ATTR else m.group(3)).decode("utf-8", "replace").strip()
            out.setdefault(f"{prefix}:{name}", value)
    for m in _XMP_STRUCT.finditer(data):
        prefix, name = m.group(1).decode(), m.group(2).decode()
        inner = (m.group(3) or b"") + b" " + (m.group(4) or b"")
        for rx in (_XMP_ATTR, _XMP_ELEM):
            for f in rx.finditer(inner):
                if f.group(1) in (b"xmlns", b"xml", b"rdf"):
                    continue
                value = (f.group(4) if rx is _XMP_ATTR else f.group(3)).decode("utf-8", "replace").strip()
                out.setdefault(f"{prefix}:{name}:{f.group(2).decode()}", value)
    return out


def _float(value: Any) -> float:
    """EXIF rational / number / text → float; NaN when absent or malformed."""
    if value is None:
        return math.nan
    try:
        if isinstance(value, tuple) and len(value) == 2:  # raw (num, den)
            return float(value[0]) / float(value[1]) if value[1] else math.nan
        return float(value)
    except (TypeError, ValueError, ZeroDivisionError):
        return math.nan


def _first(value: Any) -> Any:
    """ISO is a number in some EXIF writers, a tuple of numbers in others."""
    return value[0] if isinstance(value, (tuple, list)) and value else value


def _xmp_float(tags: dict[str, str], *names: str) -> float:
    for n in names:
        v = _float(tags.get(n))
        if math.isfinite(v):
            return v
    return math.nan


def _text(value: Any) -> str:
    if value is None:
        return ""
    if isinstance(value, bytes):
        value = value.decode("utf-8", "replace")
    return str(value).replace("\x00", "").strip()


def _dms_deg(value: Any, ref: Any, negative: str) -> float:
    try:
        d, m, s = (_float(v) for v in value)
    except (TypeError, ValueError):
        return math.nan
    deg = d + m / 60.0 + s / 3600.0
    if _text(ref).upper().startswith(negative):
        deg = -deg
    return deg


def _sensor_width(
    make: str,
    model: str,
    focal_mm: float,
    focal_35mm: float,
    exif_ifd: dict[int, Any],
    size_px: tuple[int, int],
    user_mm: float | None,
) -> tuple[float, str]:
    """Sensor width: user option, then the camera tables, 35 mm equivalent, focal-plane resolution."""
    if user_mm:
        return float(user_mm), "user"
    width = sensor_width_from_table(make, model)
    if math.isfinite(width):
        return width, "database"
    if math.isfinite(focal_35mm) and focal_35mm > 0 and math.isfinite(focal_mm):
        return _width_from_35mm(focal_mm, focal_35mm, size_px)
    xres = _float(exif_ifd.get(0xA20E))
    if not (math.isfinite(xres) and xres > 0):
        return math.nan, ""
    unit_code = _float(exif_ifd.get(0xA210))  # FocalPlaneResolutionUnit, inches when absent
    unit = {2: 25.4, 3: 10.0, 4: 1.0, 5: 0.001}.get(int(unit_code) if math.isfinite(unit_code) else 2, 25.4)
    # The resolution refers to the image size the camera wrote in EXIF (not a later downscale).
    sizes = [_float(exif_ifd.get(t)) for t in (0xA002, 0xA003)]
    exif_w = max((v for v in sizes if math.isfinite(v)), default=0.0) or max(size_px)
    return exif_w / xres * unit, "focal plane resolution"


FULL_FRAME_DIAGONAL_MM = math.hypot(36.0, 24.0)  # 43.27 mm


def _width_from_35mm(focal_mm: float, focal_35mm: float, size_px: tuple[int, int]) -> tuple[float, str]:
    """The sensor width (longer side) from the 35 mm equivalent focal length, by the diagonal as
    makers define it (CIPA DC-008: same angle of view across the diagonal as on a 36 × 24 mm frame).

    The diagonal is the full sensor's: a 16:9 (or wider) photo is taken as a crop of a 4:3 sensor of
    the same width, as drone cameras make it, their 35 mm figure staying that of the whole sensor."""
    diag_mm = focal_mm * FULL_FRAME_DIAGONAL_MM / focal_35mm
    long_px, short_px = max(size_px), min(size_px)
    aspect = long_px / short_px if short_px else 4 / 3
    note = "35mm equivalent (diagonal)"
    if aspect > 1.6:  # 16:9 and wider: a crop of a 4:3 sensor
        aspect, note = 4 / 3, "35mm equivalent (diagonal; a 16:9 crop of a 4:3 sensor assumed)"
    return diag_mm * aspect / math.hypot(aspect, 1.0), note


def read_photo(path: str | os.PathLike[str], sensor_width_mm: float | None = None) -> Photo:
    """Read one photo's metadata (headers only; pixels are not decoded).

    Raises
    ------
    InputError
        The file cannot be opened as an image, or is truncated before its pixels.
    """
    path = Path(path)
    warnings: list[str] = []
    try:
        path.name.encode("utf-8")
    except UnicodeEncodeError:
        # the name could not be written in any product (GeoPackage, JSON, the report)
        raise InputError(f"the file name {shown_name(path.name)} is not UTF-8: rename the photo") from None
    width, height, exif, gps, exif_ifd, xmp_raw = _headers(path)
    tags = parse_xmp(xmp_raw)
    make = _text(exif.get(271)) or tags.get("tiff:Make", "")
    model = _text(exif.get(272)) or tags.get("tiff:Model", "")
    lat, lon, gps_alt = _gps_position(gps, tags, path)
    rel = _xmp_float(tags, *_RELATIVE)
    absolute = _xmp_float(tags, *_ABSOLUTE)
    direction = _float(gps.get(17)) if gps else math.nan  # GPSImgDirection
    if math.isfinite(direction) and _text(gps.get(16)).upper().startswith("M"):
        warnings.append("GPSImgDirection is magnetic: read as true north (declination not applied)")
    yaw, pitch, roll, source, body = _attitude(tags, make, direction, warnings)
    focal_mm, focal_35, sw, sw_source = _lens(make, model, exif_ifd, (width, height), sensor_width_mm, warnings)
    sigma_h, sigma_v, fix, accuracy_warning = position_accuracy(tags)
    if accuracy_warning:
        warnings.append(accuracy_warning)
    cal_f, cal_cx, cal_cy, cal_dist, dewarped, cal_warning = factory_calibration(tags, int(width), int(height))
    if cal_warning:
        warnings.append(cal_warning)
    return Photo(
        path=path,
        width_px=int(width),
        height_px=int(height),
        make=make,
        model=model,
        latitude_deg=lat,
        longitude_deg=lon,
        gps_altitude_m=gps_alt,
        relative_altitude_m=rel,
        absolute_altitude_m=absolute,
        yaw_deg=yaw,
        pitch_deg=pitch,
        roll_deg=roll,
        attitude_source=source,
        flight_yaw_deg=body[0],
        flight_pitch_deg=body[1],
        flight_roll_deg=body[2],
        focal_mm=focal_mm,
        focal_35mm=focal_35,
        sensor_width_mm=sw,
        sensor_source=sw_source,
        taken_at=_taken_at(exif, exif_ifd),
        has_xmp=bool(tags),
        exposure_time_s=_float(exif_ifd.get(0x829A)),
        f_number=_float(exif_ifd.get(0x829D)),
        iso=_float(_first(exif_ifd.get(0x8827))),
        gps_sigma_h_m=sigma_h,
        gps_sigma_v_m=sigma_v,
        gps_fix=fix,
        factory_focal_px=cal_f,
        factory_cx_px=cal_cx,
        factory_cy_px=cal_cy,
        factory_distortion=cal_dist,
        dewarped=dewarped,
        warnings=tuple(warnings),
    )


def _headers(path: Path) -> tuple[int, int, Any, Any, Any, Any]:
    """The image's size, EXIF, its GPS and Exif IFDs and the raw XMP (headers only); a JPEG checked
    whole, and its size against its data."""
    from PIL import Image, UnidentifiedImageError

    try:
        with catch_warnings():
            # a header claiming 90-180 M pixels is checked against its data below, not warned of
            simplefilter("ignore", Image.DecompressionBombWarning)
            with Image.open(path) as im:
                width, height = im.size
                exif = im.getexif()
                xmp_raw = im.info.get("xmp")
                if xmp_raw is None and hasattr(im, "tag_v2"):
                    xmp_raw = im.tag_v2.get(700)  # TIFF XMP tag
                gps = exif.get_ifd(0x8825)
                exif_ifd = exif.get_ifd(0x8769)
                if im.format == "JPEG":
                    _check_jpeg_complete(path)
                    _check_jpeg_size(path, im, exif_ifd)
    except Image.DecompressionBombError:
        raise InputError(
            f"the header claims more than {2 * (Image.MAX_IMAGE_PIXELS or 0) / 1e6:.0f} M pixels: not a drone photo",
            path=path,
        ) from None
    except (UnidentifiedImageError, OSError, SyntaxError, ValueError) as e:
        raise InputError(f"not a readable image ({e})", path=path) from None
    return int(width), int(height), exif, gps, exif_ifd, xmp_raw


def _gps_position(gps: Any, tags: dict[str, str], path: Path) -> tuple[float, float, float]:
    """Latitude, longitude (EXIF GPS, else XMP; NaN without a fix) and the GPS altitude (m)."""
    lat = _dms_deg(gps.get(2), gps.get(1), "S") if gps else math.nan
    lon = _dms_deg(gps.get(4), gps.get(3), "W") if gps else math.nan
    if not (math.isfinite(lat) and math.isfinite(lon)):
        lat, lon = _xmp_float(tags, *_LATITUDE), _xmp_float(tags, *_LONGITUDE)
    if math.isfinite(lat) and math.isfinite(lon) and lat == 0.0 and lon == 0.0:
        lat = lon = math.nan  # a GPS without a fix writes 0, 0
    if (math.isfinite(lat) and abs(lat) > 90) or (math.isfinite(lon) and abs(lon) > 180):
        raise InputError(f"GPS position out of range (latitude {lat:g}, longitude {lon:g})", path=path)
    gps_alt = _float(gps.get(6)) if gps else math.nan
    if gps and math.isfinite(gps_alt) and gps.get(5) in (1, b"\x01"):
        gps_alt = -gps_alt
    return lat, lon, gps_alt


def _lens(
    make: str,
    model: str,
    exif_ifd: Any,
    size: tuple[int, int],
    sensor_width_mm: float | None,
    warnings: list[str],
) -> tuple[float, float, float, str]:
    """Focal length (mm), its 35 mm equivalent, the sensor's width (mm) and where that came from."""
    focal_mm = _float(exif_ifd.get(0x920A))
    focal_35 = _float(exif_ifd.get(0xA405))
    # No camera has a lens under 1.5 mm (35 mm equivalent under 8 mm): 0 and 1 are placeholders.
    if math.isfinite(focal_mm) and focal_mm < 1.5:
        warnings.append(f"FocalLength {focal_mm:g} mm is not a lens: ignored")
        focal_mm = math.nan
    if math.isfinite(focal_35) and focal_35 < 8:
        warnings.append(f"FocalLengthIn35mmFilm {focal_35:g} mm is not a lens: ignored")
        focal_35 = math.nan
    sw, sw_source = _sensor_width(make, model, focal_mm, focal_35, exif_ifd, size, sensor_width_mm)
    if not math.isfinite(focal_mm) and math.isfinite(focal_35):
        # No true focal length: the 35 mm equivalent on a 36 mm-wide virtual sensor.
        focal_mm = focal_35
        sw, sw_source = _width_from_35mm(focal_35, focal_35, size)
    return focal_mm, focal_35, sw, sw_source


def _taken_at(exif: Any, exif_ifd: Any) -> str:
    """DateTimeOriginal (else DateTime) as ISO 8601, with SubSecTimeOriginal's fraction."""
    taken = _text(exif_ifd.get(0x9003)) or _text(exif.get(306))
    if re.fullmatch(r"\d{4}:\d\d:\d\d \d\d:\d\d:\d\d.*", taken):
        taken = taken[:10].replace(":", "-") + "T" + taken[11:19]
        # SubSecTimeOriginal: the fraction of a second (a PPK position is matched to the exposure by it)
        subsec = re.sub(r"\D", "", _text(exif_ifd.get(0x9291)))[:6]
        if subsec:
            taken += "." + subsec
    return taken


def _check_jpeg_complete(path: Path) -> None:
    """A JPEG ends with its EOI marker; a truncated copy does not. Phones append trailers
    after it (Samsung's SEFT), so look in the last 64 KiB; FF D9 cannot occur inside
    entropy-coded data, where every FF byte is stuffed."""
    with open(path, "rb") as f:
        f.seek(0, os.SEEK_END)
        size = f.tell()
        f.seek(max(0, size - 65536))
        tail = f.read()
    if b"\xff\xd9" not in tail:
        raise OSError("truncated JPEG (no end-of-image marker)")


#: Fewer compressed bytes a pixel than any photo holds (a black lens-cap frame: about 0.02): the
#: header's size is then checked against what the data decodes to.
_MIN_JPEG_BYTES_PER_PX = 0.01


def _check_jpeg_size(path: Path, im: Any, exif_ifd: Any) -> None:
    """A JPEG whose frame header (SOF) claims far more pixels than its data holds decodes to a
    picture that stops near its top: every figure from the claimed size would be silently wrong
    (a GSD 13 times too fine). Checked only when the file is too small for its claimed size."""
    width, height = im.size
    if path.stat().st_size >= _MIN_JPEG_BYTES_PER_PX * width * height:
        return
    im.draft("L", (max(1, width // 8), max(1, height // 8)))
    rows = np.asarray(im.convert("L"), dtype=np.float32)
    flat = float(np.mean(rows.std(axis=1) < 0.5))
    if flat > 0.5:
        exif_size = (exif_ifd.get(0xA002), exif_ifd.get(0xA003))
        said = f" (its EXIF says {exif_size[0]}x{exif_size[1]})" if all(exif_size) else ""
        raise OSError(
            f"the JPEG header claims {width}x{height} px{said}, but its data fills only {100 * (1 - flat):.0f} % "
            "of that: a damaged header"
        )


def _attitude(
    tags: dict[str, str], make: str, direction_deg: float, warnings: list[str]
) -> tuple[float, float, float, str, tuple[float, float, float]]:
    """Camera yaw/pitch/roll in our convention, where they came from, and the aircraft's attitude
    (NaN where not written): the camera's (gimbal) tags first, the aircraft's for what they lack,
    then EXIF GPSImgDirection for the yaw, nadir otherwise."""
    nan3 = (math.nan, math.nan, math.nan)
    for fam in _FAMILIES:
        if fam.makes and make.lower() not in fam.makes:
            continue
        g = [_xmp_float(tags, n) for n in fam.camera]
        f = [_xmp_float(tags, n) for n in fam.aircraft] if fam.aircraft else list(nan3)
        if not any(math.isfinite(v) for v in g + f):
            continue
        body = (f[0], f[1], f[2])
        source, notes = fam.source, []
        pitch = g[1] + fam.pitch_offset_deg if math.isfinite(g[1]) else math.nan
        roll = fam.roll_sign * g[2] if math.isfinite(g[2]) else 0.0
        yaw = g[0]
        if not math.isfinite(yaw):
            if math.isfinite(f[0]):
                yaw, source = f[0], source + "+flight"
                notes.append("yaw from the aircraft")
            elif math.isfinite(direction_deg):
                yaw, source = direction_deg, source + "+direction"
                notes.append("yaw from GPSImgDirection")
            else:
                yaw, source = 0.0, source + ", yaw assumed"
                notes.append("yaw assumed 0")
        if not math.isfinite(pitch):
            pitch, source = -90.0, source + ", pitch assumed"
            notes.append("pitch assumed nadir")
        if notes:
            warnings.append("incomplete gimbal attitude: " + ", ".join(notes))
        return _wrap(yaw), pitch, roll, source, body
    if math.isfinite(direction_deg):
        # Plain EXIF (fixed-wing and camera geotaggers): where the camera's top pointed.
        warnings.append("attitude from EXIF GPSImgDirection: pitch assumed nadir, roll 0")
        return _wrap(direction_deg), -90.0, 0.0, "exif direction", nan3
    warnings.append(_NO_ATTITUDE)
    return 0.0, -90.0, 0.0, "assumed nadir", nan3


def _wrap(a: float) -> float:
    return float((a + 180.0) % 360.0 - 180.0)


def list_images(folder: str | os.PathLike[str]) -> list[Path]:
    """Image files of a folder (not recursive), sorted by name; an error if there are none."""
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError("not a folder", path=folder)
    files = sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_EXTENSIONS and p.is_file())
    if not files:
        raise InputError(f"no images ({', '.join(IMAGE_EXTENSIONS)}) in the folder", path=folder)
    return files


def shown_name(name: str) -> str:
    """A file name as it can be printed and written anywhere: bytes that are not UTF-8 as \\xNN."""
    return name.encode("utf-8", "surrogateescape").decode("utf-8", "backslashreplace")


def _read_chunk(paths: Sequence[str], sensor_width_mm: float | None) -> list[Photo | tuple[str, str]]:
    out: list[Photo | tuple[str, str]] = []
    for p in paths:
        try:
            out.append(read_photo(p, sensor_width_mm))
        except InputError as e:
            out.append((shown_name(Path(p).name), e.reason))
    return out


def read_photos(
    images: str | os.PathLike[str] | Iterable[str | os.PathLike[str]],
    sensor_width_mm: float | None = None,
    *,
    require_gps: bool = True,
    require_camera: bool = True,
    executor: cf.Executor | None = None,
    feedback: Feedback | None = None,
) -> PhotoSet:
    """Read every photo of a folder (or a list of files); report and skip the bad ones.

    Photos are read in chunks on ``executor`` (default: a process pool when
    there are many, in-process otherwise). A photo that cannot be read, has no
    GPS position (when ``require_gps``) or no usable camera model (when
    ``require_camera``) is skipped with the reason; the run goes on.
    """
    fb = as_feedback(feedback)
    paths = list_images(images) if isinstance(images, (str, os.PathLike)) else [Path(p) for p in images]
    chunk = PHOTOS_PER_CHUNK
    chunks = [[str(p) for p in paths[i : i + chunk]] for i in range(0, len(paths), chunk)]
    per_chunk = map_ordered(
        functools.partial(_read_chunk, sensor_width_mm=sensor_width_mm),
        chunks,
        executor=executor,
        min_items_for_pool=4,
        feedback=fb,
    )
    results = [r for c in per_chunk for r in c]
    photos: list[Photo] = []
    skipped: list[tuple[str, str]] = []
    for r in results:
        if isinstance(r, tuple):
            skipped.append(r)
        elif require_gps and not r.has_gps:
            skipped.append((r.image, "no GPS position in EXIF or XMP"))
        elif require_camera and not math.isfinite(r.focal_px):
            skipped.append(
                (r.image, f"unknown camera {r.make} {r.model!r}: no focal length or sensor size; give sensor_width_mm")
            )
        else:
            photos.append(r)
    photos, far = _drop_far_away(photos)
    skipped += far
    photos = yaw_from_course(photos)
    # One line per kind of problem, with a count and the first few photos (hundreds of photos
    # share the same few problems).
    by_kind: dict[str, list[str]] = {}
    for name, reason in skipped:
        by_kind.setdefault(f"skipped: {reason}", []).append(name)
    for p in photos:
        for w in p.warnings:
            by_kind.setdefault(w, []).append(p.image)
    for kind, names in by_kind.items():
        warn_grouped(fb, kind, names)
    return PhotoSet(photos, skipped)


def _drop_far_away(photos: list[Photo]) -> tuple[list[Photo], list[tuple[str, str]]]:
    """Photos whose GPS puts them far from the rest (a corrupt fix, a photo from another job):
    farther from the median position than 20 x the photos' median distance to it, and 100 km (a
    corridor's far end is about 2 x that median)."""
    located = [p for p in photos if p.has_gps]
    if len(located) < 3:
        return photos, []
    lat0 = float(np.median([p.latitude_deg for p in located]))
    lon0 = float(np.median([p.longitude_deg for p in located]))
    from pyproj import Geod

    geod = Geod(ellps="WGS84")
    _, _, d = geod.inv(
        np.full(len(located), lon0),
        np.full(len(located), lat0),
        [p.longitude_deg for p in located],
        [p.latitude_deg for p in located],
    )
    d = np.asarray(d)
    limit = max(100_000.0, 20.0 * float(np.median(d)))
    far = {p.image: float(km) for p, km in zip(located, d / 1000) if km * 1000 > limit}
    if not far:
        return photos, []
    kept = [p for p in photos if p.image not in far]
    return kept, [(name, f"{km:,.0f} km from the other photos (a wrong GPS fix?)") for name, km in far.items()]


def yaw_from_course(photos: Sequence[Photo], max_gap_s: float = 30.0, min_move_m: float = 1.0) -> list[Photo]:
    """Photos without a yaw get the course over ground between their neighbours in time.

    Mapping drones fly with the camera's top towards the direction of travel
    unless told otherwise; the course is a far better guess than north. Photos
    with a known yaw, or no neighbour within ``max_gap_s``, are left alone.
    """
    if not any(p.yaw_unknown for p in photos):
        return list(photos)
    timed = sorted((tt, i) for i, p in enumerate(photos) if math.isfinite(tt := photo_seconds(p)) and p.has_gps)
    # Segment k joins timed photo k to k+1: its course, or None (gap in time, no movement).
    courses: list[float | None] = []
    for (ta, ia), (tb, ib) in zip(timed, timed[1:]):
        a, b = photos[ia], photos[ib]
        # local east/north metres (equirectangular; neighbours are metres apart)
        de = (b.longitude_deg - a.longitude_deg) * 111_320.0 * math.cos(math.radians(a.latitude_deg))
        dn = (b.latitude_deg - a.latitude_deg) * 110_540.0
        ok = tb - ta <= max_gap_s and math.hypot(de, dn) >= min_move_m
        courses.append(math.degrees(math.atan2(de, dn)) if ok else None)

    def agree(a: float | None, b: float | None) -> bool:
        return a is not None and b is not None and abs(_wrap(a - b)) < 30.0

    out = list(photos)
    for k, (_, i) in enumerate(timed):
        p = photos[i]
        if not p.yaw_unknown:
            continue
        c_in = courses[k - 1] if k > 0 else None
        c_out = courses[k] if k < len(courses) else None
        if agree(c_in, c_out):
            yaw = c_in + _wrap(c_out - c_in) / 2  # type: ignore[operator]
        elif c_in is not None and (c_out is None or agree(c_in, courses[k - 2] if k > 1 else None)):
            yaw = c_in  # last photo of a line: the way in continues the line
        elif c_out is not None:
            yaw = c_out  # first photo of a line
        else:
            continue
        yaw = _wrap(yaw)
        # The course replaces the "top to the north" guess: say that, not both.
        kept = tuple(w for w in p.warnings if not w.startswith(_NO_ATTITUDE))
        what = (
            "no attitude in the metadata: yaw taken from the flight course, pitch assumed nadir"
            if len(kept) < len(p.warnings)
            else "incomplete gimbal attitude: yaw taken from the flight course"
        )
        out[i] = replace(
            p, yaw_deg=yaw, attitude_source=p.attitude_source + ", yaw from course", warnings=(*kept, what)
        )
    return out


def photo_seconds(p: Photo) -> float:
    """The photo's camera-clock time in seconds (NaN when it has none)."""
    import datetime as dt

    try:
        t = dt.datetime.fromisoformat(p.taken_at)
    except ValueError:
        return math.nan
    # a camera clock has no time zone: read as UTC, so no daylight-saving change falls inside a flight
    return (t if t.tzinfo else t.replace(tzinfo=dt.timezone.utc)).timestamp()


def with_sensor_width(photo: Photo, sensor_width_mm: float) -> Photo:
    return replace(photo, sensor_width_mm=float(sensor_width_mm), sensor_source="user")


def positions_lonlat(photos: Sequence[Photo]) -> np.ndarray:
    """(N, 2) longitude, latitude in degrees."""
    return np.array([[p.longitude_deg, p.latitude_deg] for p in photos], dtype=float).reshape(-1, 2)


def decode_photo(path: str | os.PathLike[str], reduction: int = 1, *, grey: bool = False) -> np.ndarray | None:
    """A JPEG's pixels (BGR, or grey), at 1/``reduction`` of its size straight from the DCT,
    refusing (OSError) entropy-coded data libjpeg finds corrupt: under OpenCV (and Pillow, for a
    bad Huffman code) it only prints "Corrupt JPEG data" and returns a grey-smeared image.
    None when the file is not a JPEG (the caller decodes it its own way)."""
    import simplejpeg

    data = Path(path).read_bytes()
    if data[:2] != b"\xff\xd8":
        return None
    try:
        h, w, _, _ = simplejpeg.decode_jpeg_header(data)
        img = simplejpeg.decode_jpeg(
            data,
            "GRAY" if grey else "BGR",
            min_height=math.ceil(h / reduction),
            min_width=math.ceil(w / reduction),
            strict=True,
        )
    except ValueError as e:
        raise OSError(f"its pixel data is corrupt ({e}): the image cannot be trusted") from None
    return np.asarray(img[:, :, 0] if grey and img.ndim == 3 else img)
