"""Photo metadata: EXIF and XMP → :class:`Photo`, without decoding pixels.

Pillow reads the JPEG/TIFF headers only (``Image.open`` is lazy), so the
decoded pixel size is known without decoding — EXIF size tags lie on resized
photos. XMP is read with a tolerant regular expression that accepts both the
attribute form (``drone-dji:GimbalYawDegree="+12.3"``) and the element form
(``<drone-dji:GimbalYawDegree>12.3</...>``) that editors rewrite it into.

Attitude is returned in the drone makers' convention (camera.py): yaw
clockwise from north, pitch −90 = nadir, roll right side down positive.

Here: reading photos (one, or a folder in parallel), their checks and decoding. Beside it:
:mod:`.tags` (the makers' tags and their values), :mod:`.photo` (:class:`Photo`) and
:mod:`.flight_photos` (a flight's photos taken together).
"""

from __future__ import annotations

import concurrent.futures as cf
import functools
import math
import os
import re
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any
from warnings import catch_warnings, simplefilter

import numpy as np

from geoortho.core.folders import IMAGE_EXTENSIONS
from geoortho.core.parallel import map_ordered
from geoortho.errors import InputError
from geoortho.feedback import Feedback, as_feedback, warn_grouped
from geoortho.photos.flight_photos import drop_far_away, photo_seconds, yaw_from_course
from geoortho.photos.photo import Photo, PhotoSet
from geoortho.photos.sensors import SENSOR_WIDTHS_MM, sensor_width_from_table
from geoortho.photos.tags import (
    ABSOLUTE_ALTITUDE_TAGS,
    LATITUDE_TAGS,
    LONGITUDE_TAGS,
    RELATIVE_ALTITUDE_TAGS,
    attitude_from_tags,
    dms_deg,
    factory_calibration,
    first_value,
    parse_xmp,
    position_accuracy,
    tag_float,
    tag_text,
    xmp_float,
)

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

#: Photos read per task: a pool (or the cluster) pays off from 4 chunks (256 photos) on
PHOTOS_PER_CHUNK = 64


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
    xres = tag_float(exif_ifd.get(0xA20E))
    if not (math.isfinite(xres) and xres > 0):
        return math.nan, ""
    unit_code = tag_float(exif_ifd.get(0xA210))  # FocalPlaneResolutionUnit, inches when absent
    unit = {2: 25.4, 3: 10.0, 4: 1.0, 5: 0.001}.get(int(unit_code) if math.isfinite(unit_code) else 2, 25.4)
    # The resolution refers to the image size the camera wrote in EXIF (not a later downscale).
    sizes = [tag_float(exif_ifd.get(t)) for t in (0xA002, 0xA003)]
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
    make = tag_text(exif.get(271)) or tags.get("tiff:Make", "")
    model = tag_text(exif.get(272)) or tags.get("tiff:Model", "")
    lat, lon, gps_alt = _gps_position(gps, tags, path)
    rel = xmp_float(tags, *RELATIVE_ALTITUDE_TAGS)
    absolute = xmp_float(tags, *ABSOLUTE_ALTITUDE_TAGS)
    direction = tag_float(gps.get(17)) if gps else math.nan  # GPSImgDirection
    if math.isfinite(direction) and tag_text(gps.get(16)).upper().startswith("M"):
        warnings.append("GPSImgDirection is magnetic: read as true north (declination not applied)")
    yaw, pitch, roll, source, body = attitude_from_tags(tags, make, direction, warnings)
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
        exposure_time_s=tag_float(exif_ifd.get(0x829A)),
        f_number=tag_float(exif_ifd.get(0x829D)),
        iso=tag_float(first_value(exif_ifd.get(0x8827))),
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
    lat = dms_deg(gps.get(2), gps.get(1), "S") if gps else math.nan
    lon = dms_deg(gps.get(4), gps.get(3), "W") if gps else math.nan
    if not (math.isfinite(lat) and math.isfinite(lon)):
        lat, lon = xmp_float(tags, *LATITUDE_TAGS), xmp_float(tags, *LONGITUDE_TAGS)
    if math.isfinite(lat) and math.isfinite(lon) and lat == 0.0 and lon == 0.0:
        lat = lon = math.nan  # a GPS without a fix writes 0, 0
    if (math.isfinite(lat) and abs(lat) > 90) or (math.isfinite(lon) and abs(lon) > 180):
        raise InputError(f"GPS position out of range (latitude {lat:g}, longitude {lon:g})", path=path)
    gps_alt = tag_float(gps.get(6)) if gps else math.nan
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
    focal_mm = tag_float(exif_ifd.get(0x920A))
    focal_35 = tag_float(exif_ifd.get(0xA405))
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
    taken = tag_text(exif_ifd.get(0x9003)) or tag_text(exif.get(306))
    if re.fullmatch(r"\d{4}:\d\d:\d\d \d\d:\d\d:\d\d.*", taken):
        taken = taken[:10].replace(":", "-") + "T" + taken[11:19]
        # SubSecTimeOriginal: the fraction of a second (a PPK position is matched to the exposure by it)
        subsec = re.sub(r"\D", "", tag_text(exif_ifd.get(0x9291)))[:6]
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
    photos, far = drop_far_away(photos)
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
