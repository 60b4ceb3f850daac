"""The tags a drone photo's metadata carries, as the makers write them: XMP parsed in either form, the
attitude families, position and altitude tags, the receiver's accuracy, the lens calibration, and the
values read (numbers, rationals, degrees-minutes-seconds).
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from typing import Any

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
NO_ATTITUDE = "no attitude in the metadata: assumed nadir, image top to the north"
# Position and altitudes where EXIF GPS is missing, and the relative/absolute altitudes, by maker.
LATITUDE_TAGS = ("drone-dji:GpsLatitude", "drone-dji:Latitude", "drone:GpsLatitude", "drone-skydio:Latitude")
LONGITUDE_TAGS = (
    "drone-dji:GpsLongitude",
    "drone-dji:GpsLongtitude",  # sic: some DJI and Autel firmware
    "drone-dji:Longitude",
    "drone:GpsLongitude",
    "drone:GpsLongtitude",
    "drone-skydio:Longitude",
)
RELATIVE_ALTITUDE_TAGS = (
    "drone-dji:RelativeAltitude",
    "drone:RelativeAltitude",
    "drone-skydio:RelativeAltitude",
    "Camera:AboveGroundAltitude",
)
ABSOLUTE_ALTITUDE_TAGS = ("drone-dji:AbsoluteAltitude", "drone:AbsoluteAltitude", "drone-skydio:AbsoluteAltitude")

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
    f = xmp_float(tags, "drone-dji:CalibratedFocalLength")
    cx = xmp_float(tags, "drone-dji:CalibratedOpticalCenterX")
    cy = xmp_float(tags, "drone-dji:CalibratedOpticalCenterY")
    dewarped = xmp_float(tags, "drone-dji:DewarpFlag") == 1.0
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
    flag = xmp_float(tags, "drone-dji:RtkFlag", "drone:RtkFlag")
    lon_m = xmp_float(tags, "drone-dji:RtkStdLon", "drone:RtkStdLon")
    lat_m = xmp_float(tags, "drone-dji:RtkStdLat", "drone:RtkStdLat")
    hgt_m = xmp_float(tags, "drone-dji:RtkStdHgt", "drone:RtkStdHgt")
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
    xy = xmp_float(tags, "Camera:GPSXYAccuracy")
    z = xmp_float(tags, "Camera:GPSZAccuracy")
    if math.isfinite(xy) and xy > 0:
        return floor_sigma(xy), floor_sigma(z if math.isfinite(z) and z > 0 else 2.0 * xy), "stated", ""
    return math.nan, math.nan, "consumer", ""


#: No GNSS position is known better than this (m, 1 sigma): a deviation stated tighter (a micrometre)
#: made the priors rigid, and sfm then blamed the GPS for the block's own noise.
MIN_SIGMA_M = 0.005


def floor_sigma(sigma_m: float) -> float:
    """A stated deviation, at least ``MIN_SIGMA_M`` (NaN stays NaN: not stated)."""
    return max(sigma_m, MIN_SIGMA_M) if math.isfinite(sigma_m) else sigma_m


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


def tag_float(value: Any) -> float:
    """EXIF rational / number / text → float; NaN when absent or malformed."""
    if value is None:
        return math.nan
    try:
        if isinstance(value, tuple) and len(value) == 2:  # raw (num, den)
            return float(value[0]) / float(value[1]) if value[1] else math.nan
        return float(value)
    except (TypeError, ValueError, ZeroDivisionError):
        return math.nan


def first_value(value: Any) -> Any:
    """ISO is a number in some EXIF writers, a tuple of numbers in others."""
    return value[0] if isinstance(value, (tuple, list)) and value else value


def xmp_float(tags: dict[str, str], *names: str) -> float:
    for n in names:
        v = tag_float(tags.get(n))
        if math.isfinite(v):
            return v
    return math.nan


def tag_text(value: Any) -> str:
    if value is None:
        return ""
    if isinstance(value, bytes):
        value = value.decode("utf-8", "replace")
    return str(value).replace("\x00", "").strip()


def dms_deg(value: Any, ref: Any, negative: str) -> float:
    try:
        d, m, s = (tag_float(v) for v in value)
    except (TypeError, ValueError):
        return math.nan
    deg = d + m / 60.0 + s / 3600.0
    if tag_text(ref).upper().startswith(negative):
        deg = -deg
    return deg


def attitude_from_tags(
    tags: dict[str, str], make: str, direction_deg: float, warnings: list[str]
) -> tuple[float, float, float, str, tuple[float, float, float]]:
    """Camera yaw/pitch/roll in our convention, where they came from, and the aircraft's attitude
    (NaN where not written): the camera's (gimbal) tags first, the aircraft's for what they lack,
    then EXIF GPSImgDirection for the yaw, nadir otherwise."""
    nan3 = (math.nan, math.nan, math.nan)
    for fam in _FAMILIES:
        if fam.makes and make.lower() not in fam.makes:
            continue
        g = [xmp_float(tags, n) for n in fam.camera]
        f = [xmp_float(tags, n) for n in fam.aircraft] if fam.aircraft else list(nan3)
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
        return wrap_deg(yaw), pitch, roll, source, body
    if math.isfinite(direction_deg):
        # Plain EXIF (fixed-wing and camera geotaggers): where the camera's top pointed.
        warnings.append("attitude from EXIF GPSImgDirection: pitch assumed nadir, roll 0")
        return wrap_deg(direction_deg), -90.0, 0.0, "exif direction", nan3
    warnings.append(NO_ATTITUDE)
    return 0.0, -90.0, 0.0, "assumed nadir", nan3


def wrap_deg(a: float) -> float:
    return float((a + 180.0) % 360.0 - 180.0)
