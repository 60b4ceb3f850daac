"""Camera heights you can trust: which altitude a photo carries, what it is relative to, and whether it holds.

Drones write three different heights and consumer cameras mix them up:

* DJI ``RelativeAltitude`` (XMP): barometric, above the take-off point, good to decimetres.
* EXIF ``GPSAltitude``: orthometric (above the geoid, "sea level") by the EXIF standard, but many
  makers write ellipsoidal heights there, and old DJI firmware wrote the height above take-off.
* DJI ``AbsoluteAltitude``: GNSS height, metres off on consumer receivers.

Height above the ground is what footprints, GSD and the quick orthophoto need. This module
turns the metadata into one explicit :class:`HeightModel` per flight — camera elevations in
the ground model's datum, the source of each, the vertical datum, and notes on what was checked —
or refuses with one line naming what to give (``flight_height_m``, ``takeoff_elevation_m`` or a
DSM). It never takes a sea-level height for a height above ground silently.

How a photo without RelativeAltitude is read (``gps_altitude="auto"``): each reading of its
altitude — above take-off, the ground model's datum as is, orthometric↔ellipsoidal by the EGM96
geoid (:func:`geoortho.core.crs.geoid_undulation_m`) — gives a height above the ground; it must be
positive and fit the spacing of consecutive photos (a mapping flight's front overlap is
50–85 %, so the spacing bounds the height to a factor of about three, give or take 15 % for
GNSS error). The reading that fits is taken and said; none fits → refused; an altitude that
drifts or jumps over the flight is not trusted either.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Literal, get_args

import numpy as np

from geoortho.core.crs import geoid_undulation_m
from geoortho.core.surface import FlatSurface, GridSurface, Surface
from geoortho.errors import DependencyError, InputError
from geoortho.photos.metadata import Photo, photo_seconds

__all__ = [
    "GPS_ALTITUDE",
    "GpsAltitude",
    "AltitudeCheck",
    "HeightModel",
    "check_altitudes",
    "flight_height_range_m",
    "resolve_heights",
]

# What EXIF GPSAltitude / AbsoluteAltitude hold, when the photos carry no RelativeAltitude.
#: What GPSAltitude holds when there is no RelativeAltitude.
GpsAltitude = Literal["auto", "above-takeoff", "orthometric", "ellipsoidal"]
GPS_ALTITUDE: tuple[str, ...] = get_args(GpsAltitude)
# A mapping flight's front overlap: the spacing of consecutive photos bounds the flight height.
FRONT_OVERLAP_RANGE = (0.5, 0.85)
# An altitude series that moves more than this over a constant-height flight is not trusted.
MAX_DRIFT_M = 8.0
MAX_STEP_M = 5.0


def absolute_altitude(p: Photo) -> float:
    """DJI AbsoluteAltitude when present, else EXIF GPSAltitude (NaN if neither)."""
    return p.absolute_altitude_m if math.isfinite(p.absolute_altitude_m) else p.gps_altitude_m


@dataclass(frozen=True)
class AltitudeCheck:
    """How one altitude series behaves over the flight (a constant-height flight should be flat)."""

    label: str
    n: int
    drift_m: float  # fitted linear change from the first photo to the last
    duration_s: float
    spread_m: float  # robust standard deviation about the trend
    steps: tuple[str, ...] = ()  # photos where the series jumps and stays
    outliers: tuple[str, ...] = ()  # photos far off the trend

    @property
    def trusted(self) -> bool:
        return abs(self.drift_m) <= MAX_DRIFT_M and not self.steps

    def describe(self) -> str:
        parts = [
            f"{self.label}: drift {self.drift_m:+.1f} m over {self.duration_s / 60:.1f} min, "
            f"spread {self.spread_m:.1f} m"
        ]
        if self.steps:
            parts.append(f"{len(self.steps)} jump(s) (first at {self.steps[0]})")
        if self.outliers:
            parts.append(f"{len(self.outliers)} outlier(s) ({', '.join(self.outliers[:3])})")
        return ", ".join(parts)


def _theil_sen_slope(t: np.ndarray, z: np.ndarray, max_points: int = 2000) -> float:
    """Median of the slopes between every two points at different times (Theil–Sen), on at most
    ``max_points`` evenly spaced points. Written out rather than scipy.stats.theilslopes, whose
    import costs about 2.5 s in each command that checks altitudes (gcp-find on 35 photos: 5 s)."""
    if len(t) > max_points:
        keep = np.linspace(0, len(t) - 1, max_points).round().astype(int)
        t, z = t[keep], z[keep]
    i, j = np.triu_indices(len(t), k=1)
    dt = t[j] - t[i]
    ok = dt != 0
    return float(np.median((z[j] - z[i])[ok] / dt[ok])) if ok.any() else 0.0


def check_altitudes(
    photos: Sequence[Photo], values_m: Sequence[float] | np.ndarray, label: str
) -> AltitudeCheck | None:
    """Trend, jumps and outliers of an altitude series against time (None: too few timed values).

    A jump is a change between consecutive photos larger than ``MAX_STEP_M`` and six robust
    sigmas of those changes, with the level held before and after it; the drift is a robust line
    (Theil–Sen) through the series less its jumps; an outlier is off that line by as much.
    """
    t = np.array([photo_seconds(p) for p in photos])
    z = np.asarray(values_m, float)
    ok = np.isfinite(t) & np.isfinite(z)
    if ok.sum() < 5:
        return None
    order = np.argsort(t[ok], kind="stable")
    t, z = t[ok][order], z[ok][order]
    names = [p.image for p, k in zip(photos, ok) if k]
    names = [names[i] for i in order]
    duration = float(t[-1] - t[0])
    # Noise from consecutive differences (blind to drift and to a few jumps), then the jumps,
    # then the drift of what is left (Theil–Sen), then outliers about that trend.
    dz = np.diff(z)
    step_sigma = 1.4826 * float(np.median(np.abs(dz - np.median(dz)))) / math.sqrt(2.0) + 0.05
    limit = max(MAX_STEP_M, 6.0 * step_sigma)
    jump = np.abs(dz - np.median(dz)) > limit
    is_step = np.zeros(len(dz), bool)
    for k in np.nonzero(jump)[0]:
        after, before = z[k + 1 : k + 4], z[max(0, k - 2) : k + 1]
        # a level held before and after → a jump; one photo off and back → an outlier
        is_step[k] = (
            len(after) > 1
            and bool(np.all(np.abs(after - z[k + 1]) < limit))
            and bool(np.all(np.abs(before - z[k]) < limit))
        )
    steps = [names[k + 1] for k in np.nonzero(is_step)[0]]
    flat = z - np.concatenate([[0.0], np.cumsum(np.where(is_step, dz, 0.0))])
    slope = _theil_sen_slope(t, flat) if duration > 0 else 0.0
    resid = flat - slope * t
    resid = resid - np.median(resid)
    sigma = 1.4826 * float(np.median(np.abs(resid))) + 0.05
    far = np.abs(resid) > max(MAX_STEP_M, 6.0 * sigma)
    outliers = [names[i] for i in np.nonzero(far)[0]]
    return AltitudeCheck(
        label, int(ok.sum()), float(slope * duration), duration, sigma, tuple(steps), tuple(outliers[:20])
    )


def flight_height_range_m(photos: Sequence[Photo], xy: np.ndarray) -> tuple[float, float] | None:
    """Bounds on the height above ground from the spacing of consecutive photos and the camera.

    Consecutive photos of a mapping line overlap by ``FRONT_OVERLAP_RANGE``; the footprint's
    along-track side is the image side pointing along the course (the short side when the
    yaw is unknown or follows the course, else whichever the yaw says). None when there are
    too few timed, moving photos.
    """
    t = np.array([photo_seconds(p) for p in photos])
    order = [i for i in np.argsort(t, kind="stable") if np.isfinite(t[i])]
    ratios = []  # along-track spacing / (along-track sensor side / focal): a height per unit of (1 - overlap)
    for a, b in zip(order, order[1:]):
        d = float(np.hypot(*(xy[b] - xy[a])))
        if not (0.5 < d and t[b] - t[a] <= 20.0):
            continue
        p = photos[a]
        if not (math.isfinite(p.focal_px) and p.focal_px > 0):
            continue
        course = math.degrees(math.atan2(xy[b, 0] - xy[a, 0], xy[b, 1] - xy[a, 1]))
        rel = abs(((p.yaw_deg - course) + 90.0) % 180.0 - 90.0)  # 0: image top along the course
        known_yaw = not p.yaw_unknown and "course" not in p.attitude_source
        side_px = p.height_px if (not known_yaw or rel < 45.0) else p.width_px
        ratios.append(d * p.focal_px / side_px)
    if len(ratios) < 3:
        return None
    r = float(np.median(ratios))
    lo, hi = FRONT_OVERLAP_RANGE
    return r / (1.0 - lo), r / (1.0 - hi)


@dataclass(frozen=True)
class HeightModel:
    """Camera elevations of a flight in the ground model's datum, and how they were found."""

    z_m: np.ndarray  # (N,) camera elevation per photo
    sources: tuple[str, ...]  # per photo: which altitude, read how
    method: str  # one line for the whole flight
    datum: str  # vertical datum of z_m (that of the ground model)
    takeoff_elevation_m: float
    surface: Surface
    notes: tuple[str, ...] = ()
    checks: tuple[AltitudeCheck, ...] = field(default=(), compare=False)
    vertical_gps_trusted: bool = True


def _ground_level(ground: np.ndarray) -> float:
    """The ground under the flight as a take-off level: its 30th percentile (below roofs and trees)."""
    return float(np.nanpercentile(ground, 30))


def _ground_under(surface: Surface | None, xy: np.ndarray) -> np.ndarray:
    if surface is None:
        return np.full(len(xy), np.nan)
    return np.asarray(surface.elevation(xy[:, 0], xy[:, 1]), float)


def _undulation(lonlat: np.ndarray) -> float:

    return float(np.median(geoid_undulation_m(lonlat[:, 0], lonlat[:, 1])))


def resolve_heights(
    photos: Sequence[Photo],
    xy: np.ndarray,
    lonlat: np.ndarray,
    surface: Surface | None = None,
    *,
    takeoff_elevation_m: float | None = None,
    flight_height_m: float | None = None,
    gps_altitude: GpsAltitude = "auto",
    ground_label: str = "",
    gnss_takeoff: bool = False,
) -> HeightModel:
    """Camera elevations for ``photos`` at ``xy`` (world CRS), in the datum of ``surface``.

    Parameters
    ----------
    photos, xy, lonlat
        The photos, their projected positions (N, 2) and longitude/latitude (N, 2).
    surface
        Ground model (DSM or flat ground); None: flat ground at the take-off point.
    takeoff_elevation_m
        Ground elevation at the take-off point, in the ground model's datum.
    flight_height_m
        Flight height above the take-off ground, when the photos' altitudes are not to be used.
    gps_altitude
        What GPSAltitude holds when there is no RelativeAltitude: auto (decided and said),
        above-takeoff, orthometric or ellipsoidal.
    gnss_takeoff
        Without a ground model or a given take-off, put RelativeAltitude flights on the take-off
        the GNSS heights give (absolute − relative altitude) rather than at 0: camera elevations
        in the GNSS datum, as SfM's pose priors want them.

    Raises
    ------
    InputError
        No trustworthy height above ground can be found: the message names what to give.
    """
    if gps_altitude not in GPS_ALTITUDE:
        raise InputError(f"gps_altitude {gps_altitude!r} is not one of {', '.join(GPS_ALTITUDE)}")
    n = len(photos)
    rel = np.array([p.relative_altitude_m for p in photos], float)
    gnss = np.array([absolute_altitude(p) for p in photos], float)
    ground = _ground_under(surface, xy)
    label = ground_label or (
        "DSM"
        if isinstance(surface, GridSurface)
        else "ground elevation"
        if surface is not None
        else "flat take-off ground"
    )
    datum = (
        "the DSM's datum"
        if isinstance(surface, GridSurface)
        else "the ground elevation's datum"
        if surface is not None
        else "height above take-off"
    )
    notes: list[str] = []
    checks: list[AltitudeCheck] = []
    has_takeoff = takeoff_elevation_m is not None and math.isfinite(takeoff_elevation_m)
    if surface is None and has_takeoff:
        datum = "the take-off elevation's datum"

    if flight_height_m is not None and math.isfinite(flight_height_m):
        if has_takeoff:
            base, how = float(takeoff_elevation_m), "take-off elevation given"  # type: ignore[arg-type]
        elif np.isfinite(ground).any():
            base, how = _ground_level(ground), f"take-off at the {label} under the flight"
        else:
            base, how = 0.0, "flat take-off ground"
        z = np.full(n, base + float(flight_height_m))
        src = f"flight height given ({flight_height_m:g} m above take-off); {how}"
        surf = surface if surface is not None else FlatSurface(base)
        return HeightModel(z, (src,) * n, src, datum, base, surf, tuple(notes), tuple(checks), False)

    has_rel = np.isfinite(rel)
    if has_rel.sum() >= max(1, n // 2):
        return _from_relative(
            photos, xy, lonlat, rel, gnss, ground, surface, takeoff_elevation_m, label, datum, gnss_takeoff
        )
    return _from_gnss(photos, xy, lonlat, gnss, ground, surface, takeoff_elevation_m, gps_altitude, label, datum)


def _from_relative(
    photos: Sequence[Photo],
    xy: np.ndarray,
    lonlat: np.ndarray,
    rel: np.ndarray,
    gnss: np.ndarray,
    ground: np.ndarray,
    surface: Surface | None,
    takeoff_elevation_m: float | None,
    label: str,
    datum: str,
    gnss_takeoff: bool = False,
) -> HeightModel:
    """RelativeAltitude + take-off elevation (given, from the GNSS heights, or from the DSM)."""
    notes: list[str] = []
    checks = [c for c in (check_altitudes(photos, rel, "relative altitude"),) if c is not None]
    offsets = gnss - rel  # the take-off in the GNSS datum, once per photo: constant if the GNSS height holds
    gnss_check = check_altitudes(photos, offsets, "GNSS altitude − relative altitude")
    gnss_ok = True
    if gnss_check is not None:
        checks.append(gnss_check)
        gnss_ok = gnss_check.trusted
        if not gnss_ok:
            notes.append("GNSS altitude not trusted (" + gnss_check.describe() + ")")
    offset = float(np.nanmedian(offsets)) if np.isfinite(offsets).any() else math.nan
    if takeoff_elevation_m is not None and math.isfinite(takeoff_elevation_m):
        takeoff, how = float(takeoff_elevation_m), "take-off elevation given"
    elif surface is None and gnss_takeoff and math.isfinite(offset):
        takeoff, how = offset, "take-off from absolute − relative altitude (GNSS heights)"
        datum = "the GNSS heights' datum"
    elif surface is None:
        takeoff, how = 0.0, "flat ground at the take-off point"
    elif isinstance(surface, FlatSurface) or not math.isfinite(offset) or not gnss_ok:
        takeoff = _ground_level(ground) if np.isfinite(ground).any() else surface.z_min
        how = f"take-off at the {label} under the flight (30th percentile)"
    else:
        takeoff, how = offset, "take-off from absolute − relative altitude"
        # The GNSS datum and the DSM's must agree: the heights above ground this gives must be
        # those the relative altitudes say, give or take the terrain.
        agl = takeoff + rel - ground
        expected = float(np.nanmedian(rel))
        seen = float(np.nanmedian(agl))
        relief = float(np.nanpercentile(ground, 90) - np.nanpercentile(ground, 10))
        gap = seen - expected
        if math.isfinite(seen) and abs(gap) > max(5.0, relief + 0.15 * expected):
            why, und = _datum_hint(gap, lonlat)
            if und is not None:
                # the gap is the geoid: move the GNSS take-off into the DSM's datum by the geoid itself
                alt = offset - math.copysign(abs(und), gap)
                fix = f"take-off moved into the {label}'s datum by the EGM96 geoid ({alt:.1f} m)"
                how = f"take-off from absolute − relative altitude, moved by the EGM96 geoid into the {label}'s datum"
            else:
                alt = _ground_level(ground)
                fix = f"take-off taken from the {label} under the flight instead ({alt:.1f} m)"
                how = f"take-off at the {label} under the flight (GNSS heights disagree with it)"
            notes.append(f"the GNSS heights put the take-off {gap:+.1f} m off the {label} ({why}); {fix}")
            takeoff = alt
    z = np.empty(len(photos))
    sources = []
    for i in range(len(photos)):
        if np.isfinite(rel[i]):
            z[i], s = takeoff + rel[i], f"relative altitude; {how}"
        elif np.isfinite(gnss[i]) and math.isfinite(offset):
            z[i], s = takeoff + gnss[i] - offset, f"absolute altitude less the flight's offset; {how}"
        else:
            raise InputError("no altitude in the metadata", path=photos[i].path)
        sources.append(s)
    surf = surface if surface is not None else FlatSurface(takeoff)
    return HeightModel(
        z,
        tuple(sources),
        f"relative altitude + take-off; {how}",
        datum,
        takeoff,
        surf,
        tuple(notes),
        tuple(checks),
        gnss_ok,
    )


def _datum_hint(offset_m: float, lonlat: np.ndarray) -> tuple[str, float | None]:
    """Why two height sets disagree by ``offset_m``, and the geoid height when that explains it."""
    try:
        n = _undulation(lonlat)
    except DependencyError:
        return "another vertical datum?", None
    if abs(abs(offset_m) - abs(n)) < max(3.0, 0.15 * abs(n)):
        return f"the geoid is {n:+.1f} m here: one is ellipsoidal, the other orthometric", n
    return f"another vertical datum, or GNSS heights off; the geoid is {n:+.1f} m here", None


def _from_gnss(
    photos: Sequence[Photo],
    xy: np.ndarray,
    lonlat: np.ndarray,
    gnss: np.ndarray,
    ground: np.ndarray,
    surface: Surface | None,
    takeoff_elevation_m: float | None,
    gps_altitude: str,
    label: str,
    datum: str,
) -> HeightModel:
    """GPSAltitude alone: decide what it holds, check it, or refuse."""
    n = len(photos)
    notes: list[str] = []
    if not np.isfinite(gnss).any():
        raise InputError(
            "no altitude in the metadata (RelativeAltitude, AbsoluteAltitude or GPSAltitude): give flight_height_m",
            path=photos[0].path.parent,
        )
    check = check_altitudes(photos, gnss, "GPS altitude")
    checks = (check,) if check is not None else ()
    g = np.where(np.isfinite(gnss), gnss, np.nanmedian(gnss))
    has_takeoff = takeoff_elevation_m is not None and math.isfinite(takeoff_elevation_m)
    known_ground = np.isfinite(ground).any() or has_takeoff
    under = ground if np.isfinite(ground).any() else np.full(n, float(takeoff_elevation_m or 0.0))
    under = np.where(np.isfinite(under), under, np.nanmedian(under))
    base = (
        float(takeoff_elevation_m)  # type: ignore[arg-type]  # has_takeoff: not None
        if has_takeoff
        else (_ground_level(under) if known_ground else 0.0)
    )
    what = (
        f"{len(photos)} photos carry no RelativeAltitude, only a GPS altitude ({np.nanmin(gnss):.0f}–"
        f"{np.nanmax(gnss):.0f} m)"
    )
    give = (
        "give flight_height_m (height above take-off), or takeoff_elevation_m or a DSM "
        "(in the datum of the GPS altitude)"
    )
    if check is not None and not check.trusted:
        raise InputError(f"{what} that is not trustworthy ({check.describe()}): {give}")
    readings = _gnss_readings(photos, g, base, known_ground, gps_altitude, lonlat, datum, notes)
    if gps_altitude != "auto":
        key = gps_altitude if gps_altitude in readings else None
        if key is None:
            raise InputError(f"gps_altitude {gps_altitude} needs a ground model in a known datum: {give}")
        note = f"{what}: {readings[key][1]}, as told"
    else:
        key, note = _likeliest_reading(readings, under, flight_height_range_m(photos, xy), known_ground, what, give)
    z = readings[key][0]
    notes.insert(0, note)
    sources = (f"{readings[key][1]}; {label}",) * n
    surf = surface if surface is not None else FlatSurface(base)
    return HeightModel(
        np.asarray(z, float),
        sources,
        readings[key][1],
        datum,
        base,
        surf,
        tuple(notes),
        checks,
        check is None or check.trusted,
    )


def _gnss_readings(
    photos: Sequence[Photo],
    g: np.ndarray,
    base: float,
    known_ground: bool,
    gps_altitude: str,
    lonlat: np.ndarray,
    datum: str,
    notes: list[str],
) -> dict[str, tuple[np.ndarray, str]]:
    """Each reading of the GPS altitude → (camera elevations in the ground model's datum, how read).

    Height above take-off is what old DJI firmware (no XMP at all) wrote; other cameras follow
    EXIF's sea level or write ellipsoidal heights, so that reading is only offered for those DJI
    photos (or when asked for)."""
    readings: dict[str, tuple[np.ndarray, str]] = {}
    old_dji = all(p.make.strip().upper().startswith("DJI") and not p.has_xmp for p in photos)
    if old_dji or gps_altitude == "above-takeoff":
        readings["above-takeoff"] = (
            base + g,
            "GPS altitude read as height above take-off (old DJI firmware writes it so)",
        )
    if known_ground:
        readings["orthometric"] = (g, f"GPS altitude read as in {datum} (EXIF: orthometric)")
        try:
            und = _undulation(lonlat)
            readings["ellipsoidal"] = (
                g - und,
                f"GPS altitude read as ellipsoidal, made orthometric (EGM96 geoid {und:+.1f} m)",
            )
            readings["orthometric→ellipsoidal"] = (
                g + und,
                f"GPS altitude read as orthometric, made ellipsoidal (EGM96 geoid {und:+.1f} m)",
            )
        except DependencyError as e:
            notes.append(f"no geoid model: {e}")
    return readings


def _likeliest_reading(
    readings: dict[str, tuple[np.ndarray, str]],
    under: np.ndarray,
    bounds: tuple[float, float] | None,
    known_ground: bool,
    what: str,
    give: str,
) -> tuple[str, str]:
    """The reading whose height above the ground fits the photo spacing's range best, and the note
    that says so (and names the others that fit too); refuses when none is plausible."""
    fits = {}
    for key, (z, how) in readings.items():
        agl = float(np.median(z - under))
        if agl > 2.0 and (bounds is None or bounds[0] * 0.85 <= agl <= bounds[1] * 1.15):  # GNSS heights err by metres
            fits[key] = (agl, how)
    spacing = (
        f"the photo spacing says {bounds[0]:.0f}–{bounds[1]:.0f} m"
        if bounds
        else "the photo spacing could not bound it"
    )
    if not readings:
        raise InputError(
            f"{what}, which is a sea-level or ellipsoidal height, and there is no ground model to take it from; {give}"
        )
    if not fits:
        raise InputError(f"{what}: no reading of it is a plausible height above the ground ({spacing}); {give}")
    if bounds is None and not known_ground:
        raise InputError(f"{what} and {spacing}; {give}")
    # Several readings fit: the one nearest the middle of the spacing's range (geometric),
    # the EXIF standard (orthometric) on ties.
    mid = math.sqrt(bounds[0] * bounds[1]) if bounds else None
    order = ["orthometric", "above-takeoff", "orthometric→ellipsoidal", "ellipsoidal"]
    key = min(fits, key=lambda k: (abs(math.log(fits[k][0] / mid)) if mid else 0.0, order.index(k)))
    agl, how = fits[key]
    note = f"{what}: {how}; height above ground {agl:.0f} m ({spacing})"
    if len(fits) > 1:
        others = ", ".join(f"{k} {fits[k][0]:.0f} m" for k in fits if k != key)
        note += f"; other readings also fit ({others}): give flight_height_m if this is wrong"
    return key, note
