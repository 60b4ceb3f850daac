"""Camera positions from a file: post-processed (PPK) or surveyed positions that replace the ones
the photos carry, each with its accuracy.

Three formats, told apart by their content:

* **RTKLIB ``.pos``** (RTKPOST's solution): a trajectory (an epoch every 0.1-1 s) or one line per
  camera event. Header lines begin with ``%``; the columns are the time (``yyyy/mm/dd
  hh:mm:ss.sss`` or GPS week and seconds), latitude, longitude and height (degrees and metres,
  ellipsoidal unless RTKPOST was told otherwise), Q (1 fix, 2 float, 3 SBAS, 4 DGPS, 5 single,
  6 PPP), the satellites, then sdn, sde and sdu, the standard deviations (m). The photos are
  matched by time: the camera's clock (EXIF DateTimeOriginal and SubSecTimeOriginal) plus an
  offset, given or found by laying the photos' own GPS positions on the trajectory.
* **DJI ``Timestamp.MRK``** (the PPK event file of the Phantom 4 RTK, Matrice 300/350 RTK and
  Mavic 3 Enterprise): a line per photo in shooting order, with the GPS time of week, the
  antenna-to-camera offsets (mm), latitude, longitude, ellipsoidal height, the standard deviations
  (m) and the RTK flag (50 fixed, 34 float, 16 single). Matched to the photos by their order.
* **CSV**: a header row naming the columns: the image, x/easting/longitude, y/northing/latitude,
  z/height, and optionally sigma_h and sigma_v (1 sigma, m) and crs. A ``# EPSG:25829`` comment
  line (or a crs column) names the CRS; latitude/longitude columns are read as WGS 84.

Heights are ellipsoidal (WGS 84) unless the file says otherwise: an RTKLIB header's
``height=.../geodetic`` (RTKPOST's geoid heights), a CSV's compound CRS (``EPSG:32629+5773``), its
``# heights: orthometric`` line or a column named for sea level (``h_msl``, ``orthometric``). Those
are taken above the EGM96 geoid and turned into ellipsoidal heights. A height no camera flies at
is refused.

Every file is checked against the photos' own GPS: when its positions lie farther from it than a
consumer receiver errs (``MAX_GPS_DISTANCE_M``, the median over the photos), it is another site's
file, a wrong CRS or a wrong order, and it is refused with the distance. A DJI MRK with more or
fewer events than photos is aligned to them by their own GPS, so the photo left without one is
the one that has none.

A photo with no position in the file keeps its own, and is named; so are lines that match no photo.
"""

from __future__ import annotations

import csv
import datetime as dt
import itertools
import math
import os
import re
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, cast

import numpy as np

from geoortho.core.crs import WGS84, transformer
from geoortho.errors import InputError
from geoortho.photos.flight_photos import photo_seconds
from geoortho.photos.photo import Photo
from geoortho.photos.tags import DEFAULT_SIGMA_M, RTK_FLAGS, floor_sigma

__all__ = ["Position", "PositionFile", "Trajectory", "apply_positions", "read_positions"]

#: RTKLIB's solution quality Q -> our fix classes (SBAS, DGPS and single point are metres; PPP
#: converges to decimetres).
RTKLIB_Q = {1: "fixed", 2: "float", 3: "single", 4: "single", 5: "single", 6: "float"}
#: Epochs closer than this (s) make a trajectory to interpolate in; farther apart, camera events.
TRAJECTORY_MAX_STEP_S = 1.0
#: A camera event matches an epoch within this (s), once the clock offset is applied.
EVENT_MATCH_S = 0.5
#: A camera clock runs on local time: within this of GPS time (s). Farther is another day's file.
MAX_CLOCK_OFFSET_S = 15 * 3600.0
#: A photo's own GPS lies within this (m) of its post-processed position (consumer GNSS at worst).
MAX_GPS_DISTANCE_M = 30.0
#: Ellipsoidal heights a camera can have (m): below the Dead Sea's shore, above any drone's ceiling.
HEIGHT_RANGE_M = (-500.0, 9000.0)
#: Lines of a positions file named in the notes and the report (the rest are counted).
MAX_NAMED_LINES = 20
GPS_WEEK_EPOCH = dt.datetime(1980, 1, 6, tzinfo=dt.timezone.utc)


@dataclass(frozen=True)
class Position:
    latitude_deg: float
    longitude_deg: float
    height_m: float
    sigma_h_m: float
    sigma_v_m: float
    fix: str


@dataclass(frozen=True)
class Trajectory:
    """An RTKLIB trajectory: epochs (s, the file's time scale), positions and their accuracy."""

    t_s: np.ndarray
    lat: np.ndarray
    lon: np.ndarray
    h: np.ndarray
    sigma_h: np.ndarray
    sigma_v: np.ndarray
    fix: tuple[str, ...]
    heights: str = "ellipsoidal"  # as the header stated them (converted to ellipsoidal when not)

    def at(self, t: float) -> Position | None:
        """The position interpolated at ``t`` (None outside the epochs or in a gap)."""
        k = int(np.searchsorted(self.t_s, t))
        if k == 0 or k >= len(self.t_s):
            if k < len(self.t_s) and abs(self.t_s[k] - t) < 1e-6:
                return self._epoch(k)
            return None
        t0, t1 = self.t_s[k - 1], self.t_s[k]
        if t1 - t0 > 2.0 * self.step_s:
            return None
        u = (t - t0) / (t1 - t0)
        worse = k - 1 if self.sigma_h[k - 1] >= self.sigma_h[k] else k
        return Position(
            float(self.lat[k - 1] + u * (self.lat[k] - self.lat[k - 1])),
            float(self.lon[k - 1] + u * (self.lon[k] - self.lon[k - 1])),
            float(self.h[k - 1] + u * (self.h[k] - self.h[k - 1])),
            float(self.sigma_h[worse]),
            float(self.sigma_v[worse]),
            self.fix[worse],
        )

    def _epoch(self, k: int) -> Position:
        return Position(
            float(self.lat[k]), float(self.lon[k]), float(self.h[k]),
            float(self.sigma_h[k]), float(self.sigma_v[k]), self.fix[k],
        )  # fmt: skip

    @property
    def step_s(self) -> float:
        return float(np.median(np.diff(self.t_s))) if len(self.t_s) > 1 else math.inf

    @property
    def is_events(self) -> bool:
        return self.step_s > TRAJECTORY_MAX_STEP_S

    def nearest_epoch(self, t: float) -> int | None:
        k = int(np.argmin(np.abs(self.t_s - t)))
        return k if abs(self.t_s[k] - t) <= EVENT_MATCH_S else None


@dataclass(frozen=True)
class PositionFile:
    """Positions read from a file and matched to photos (by image file name)."""

    path: Path
    source: str  # "RTKLIB .pos", "DJI MRK" or "CSV"
    by_image: dict[str, Position]
    photos_without: tuple[str, ...] = ()  # photos the file has no position for
    lines_without: tuple[str, ...] = ()  # the file's lines (or events) no photo matched
    time_offset_s: float | None = None  # the file's time minus the camera clock, as used
    offset_found: bool = False  # found from the photos' own GPS, not given
    trajectory: Trajectory | None = field(default=None, compare=False)
    photo_times_s: dict[str, float] = field(default_factory=dict, compare=False)
    heights: str = "ellipsoidal"  # the file's heights as stated: "ellipsoidal" or what was converted
    n_lines_without: int = -1  # lines matching no photo, all of them (only the first are named)
    gps_distance_m: float = math.nan  # median horizontal distance to the photos' own GPS
    far_from_gps: tuple[str, ...] = ()  # photos farther than MAX_GPS_DISTANCE_M from their own GPS

    def notes(self) -> list[str]:
        out = [
            f"positions of {len(self.by_image)} photos from {self.path.name} ({self.source}); heights {self.heights}"
        ]
        if math.isfinite(self.gps_distance_m):
            out.append(
                f"{self.path.name}: {self.gps_distance_m:.1f} m from the photos' own GPS (median; refused beyond "
                f"{MAX_GPS_DISTANCE_M:g} m)"
            )
        if self.far_from_gps:
            out.append(
                f"{len(self.far_from_gps)} photo(s) lie more than {MAX_GPS_DISTANCE_M:g} m from their own GPS in "
                f"{self.path.name} (a wrong line?): "
                + ", ".join(self.far_from_gps[:8])
                + ("…" if len(self.far_from_gps) > 8 else "")
            )
        if self.time_offset_s is not None:
            how = "found from the photos' own GPS" if self.offset_found else "as given"
            out.append(f"{self.path.name}: time offset {self.time_offset_s:+.3f} s (file time − camera clock; {how})")
        if self.photos_without:
            out.append(
                f"{len(self.photos_without)} photo(s) have no position in {self.path.name} and keep their own: "
                + ", ".join(self.photos_without[:8])
                + ("…" if len(self.photos_without) > 8 else "")
            )
        if self.lines_without:
            n = max(self.n_lines_without, len(self.lines_without))
            out.append(
                f"{n:,} position(s) in {self.path.name} match no photo: "
                + ", ".join(self.lines_without[:8])
                + ("…" if n > 8 else "")
            )
        return out

    def with_lag(self, photos: Sequence[Photo], lag_s: float) -> PositionFile:
        """The trajectory read again at each photo's time moved by ``lag_s``."""
        if self.trajectory is None or self.time_offset_s is None:
            return self
        moved = _match_trajectory(self.path, self.trajectory, photos, self.time_offset_s + lag_s, self.offset_found)
        return _checked(moved, photos)


def read_positions(
    path: str | os.PathLike[str], photos: Sequence[Photo], *, time_offset_s: float | None = None
) -> PositionFile:
    """Read a positions file and match it to ``photos`` (see the module's text for the formats)."""
    path = Path(path)
    try:
        with open(path, encoding="utf-8-sig", errors="replace") as f:
            head = [line.rstrip("\r\n") for line in itertools.islice(f, 60)]
    except OSError as e:
        raise InputError(f"cannot be read ({e.strerror or e})", path=path) from None
    if not any(line.strip() for line in head) and not path.read_text(errors="replace").strip():
        raise InputError("is empty", path=path)
    rtklib = any(line.startswith("%") for line in head[:40]) or path.suffix.lower() == ".pos"
    mrk = path.suffix.lower() == ".mrk" or bool(head and re.match(r"\s*\d+\s+\d+\.\d+\s+\[\d+\]", head[0]))
    if not (rtklib or mrk):  # a CSV is read as a stream: one of a million rows is not held whole
        return _checked(_read_csv(path, photos), photos)
    lines = path.read_text(encoding="utf-8-sig", errors="replace").splitlines()
    if rtklib:
        traj = _read_rtklib(path, lines)
        if traj.is_events and time_offset_s is None and not any(p.has_gps for p in photos):
            raise InputError("camera events and photos without GPS: give the time offset", path=path)
        offset, found = (
            (time_offset_s, False) if time_offset_s is not None else (_find_offset(path, traj, photos), True)
        )
        return _checked(_match_trajectory(path, traj, photos, offset, found), photos)
    return _checked(_read_mrk(path, lines, photos), photos)


def _distances_m(pairs: Sequence[tuple[float, float, float, float]]) -> np.ndarray:
    """Geodesic distances (m) of (lat1, lon1, lat2, lon2) pairs on the WGS 84 ellipsoid."""
    from pyproj import Geod

    if not pairs:
        return np.zeros(0)
    a = np.asarray(pairs, float)
    _, _, d = Geod(ellps="WGS84").inv(a[:, 1], a[:, 0], a[:, 3], a[:, 2])
    return np.asarray(d, float)


def _checked(pf: PositionFile, photos: Sequence[Photo]) -> PositionFile:
    """The file's heights within what a camera can have, and its positions where the photos' own GPS
    says they were taken: refused, naming the distance, when they lie farther off than a consumer
    receiver errs (a wrong CRS line, another site's file)."""
    lo, hi = HEIGHT_RANGE_M
    for name, q in pf.by_image.items():
        if not (lo <= q.height_m <= hi):
            raise InputError(
                f"{name}: height {q.height_m:.6g} m is no camera's height (ellipsoidal, {lo:g} to {hi:g} m): "
                "another unit or column?",
                path=pf.path,
            )
    own = {p.image: p for p in photos if p.has_gps}
    names = [n for n in pf.by_image if n in own]
    if not names:
        return pf
    q_of = pf.by_image
    d = _distances_m(
        [(own[n].latitude_deg, own[n].longitude_deg, q_of[n].latitude_deg, q_of[n].longitude_deg) for n in names]
    )
    median = float(np.median(d))
    if median > MAX_GPS_DISTANCE_M:
        where = f"{median / 1000:,.1f} km" if median >= 10_000 else f"{median:,.0f} m"
        raise InputError(
            f"its positions lie {where} from the photos' own GPS (median of {len(names)} photos; a consumer "
            f"receiver is within {MAX_GPS_DISTANCE_M:g} m): a wrong CRS, another site's file or another order",
            path=pf.path,
        )
    far = tuple(n for n, x in zip(names, d) if x > MAX_GPS_DISTANCE_M)
    return replace(pf, gps_distance_m=median, far_from_gps=far)


def apply_positions(photos: Sequence[Photo], positions: PositionFile) -> list[Photo]:
    """The photos with the file's positions, heights and accuracy where it has them."""
    out = []
    for p in photos:
        q = positions.by_image.get(p.image)
        if q is None:
            out.append(p)
            continue
        out.append(
            replace(
                p,
                latitude_deg=q.latitude_deg,
                longitude_deg=q.longitude_deg,
                absolute_altitude_m=q.height_m,
                gps_altitude_m=q.height_m,
                gps_sigma_h_m=floor_sigma(q.sigma_h_m),
                gps_sigma_v_m=floor_sigma(q.sigma_v_m),
                gps_fix=q.fix,
            )
        )
    return out


# -- RTKLIB ---------------------------------------------------------------------------------------


def _read_rtklib(path: Path, lines: list[str]) -> Trajectory:
    """RTKPOST's solution: latitude and longitude in degrees or in degrees, minutes and seconds (its
    ``ddd mm ss`` output), heights ellipsoidal or geodetic (above the geoid; turned ellipsoidal)."""
    rows: list[tuple[float, float, float, float, int, float, float]] = []
    header = "\n".join(line for line in lines[:60] if line.startswith("%")).lower()
    dms = "d'\"" in header or "(dms)" in header
    m = re.search(r"height\s*=\s*([^,)\s]+)", header)
    datum = m.group(1) if m else "wgs84/ellipsoidal"
    geodetic = "geodetic" in datum or "geoid" in datum or "msl" in datum
    for n, line in enumerate(lines, 1):
        s = line.strip()
        if not s or s.startswith("%"):
            if "x-ecef" in s.lower():
                raise InputError(f"line {n}: ECEF solutions are not read; output latitude/longitude/height", path=path)
            continue
        parts = s.split()
        try:
            if "/" in parts[0]:  # yyyy/mm/dd hh:mm:ss.sss
                when = dt.datetime.strptime(f"{parts[0]} {parts[1]}", "%Y/%m/%d %H:%M:%S.%f")
                t = when.replace(tzinfo=dt.timezone.utc).timestamp()
            else:  # GPS week, seconds of week
                t = (GPS_WEEK_EPOCH + dt.timedelta(weeks=int(parts[0]), seconds=float(parts[1]))).timestamp()
            if dms or (len(parts) >= 13 and _looks_dms(parts)):
                lat, lon, rest = _dms(parts[2:5]), _dms(parts[5:8]), parts[8:]
            else:
                lat, lon, rest = float(parts[2]), float(parts[3]), parts[4:]
            h = float(rest[0])
            q = int(rest[1])
            sdn, sde, sdu = float(rest[3]), float(rest[4]), float(rest[5])
        except (IndexError, ValueError, OverflowError):
            raise InputError(f"line {n}: not an RTKLIB solution line ({s[:60]!r})", path=path) from None
        if not (-90.0 <= lat <= 90.0 and -180.0 <= lon <= 180.0 and math.isfinite(h) and math.isfinite(t)):
            raise InputError(f"line {n}: latitude {lat:g}, longitude {lon:g}, height {h:g} out of range", path=path)
        rows.append((t, lat, lon, h, q, max(sdn, sde), sdu))
    if not rows:
        raise InputError("holds no solution line", path=path)
    a = np.array(sorted(rows), dtype=float)
    fix = tuple(RTKLIB_Q.get(int(q), "single") for q in a[:, 4])
    # a deviation of zero or less (or none) is not stated: the fix class's, as in the other formats
    sh, sv = a[:, 5].copy(), a[:, 6].copy()
    for k, f in enumerate(fix):
        dh, dv = DEFAULT_SIGMA_M.get(f, DEFAULT_SIGMA_M["single"])
        sh[k] = sh[k] if math.isfinite(sh[k]) and sh[k] > 0 else dh
        sv[k] = sv[k] if math.isfinite(sv[k]) and sv[k] > 0 else dv
    height_m = a[:, 3]
    heights = "ellipsoidal"
    if geodetic:
        from geoortho.core.crs import geoid_undulation_m

        height_m = height_m + np.asarray(geoid_undulation_m(a[:, 2], a[:, 1]), float)
        heights = f"geodetic in the header ({datum}): EGM96 geoid heights turned ellipsoidal"
    return Trajectory(a[:, 0], a[:, 1], a[:, 2], height_m, sh, sv, fix, heights)


def _looks_dms(parts: list[str]) -> bool:
    """Degrees, minutes and seconds: whole degrees and whole minutes below 60 before the seconds."""
    try:
        return (
            re.fullmatch(r"-?\d+", parts[2]) is not None
            and re.fullmatch(r"\d+", parts[3]) is not None
            and int(parts[3]) < 60
            and re.fullmatch(r"-?\d+", parts[5]) is not None
            and 0 <= float(parts[4]) < 60
        )
    except (IndexError, ValueError):
        return False


def _dms(parts: list[str]) -> float:
    """``ddd mm ss.sss`` (the sign on the degrees, "-0" too) as decimal degrees."""
    d, m, sec = float(parts[0]), float(parts[1]), float(parts[2])
    if not (0 <= m < 60 and 0 <= sec < 60):
        raise ValueError("minutes or seconds out of range")
    value = abs(d) + m / 60.0 + sec / 3600.0
    return -value if parts[0].strip().startswith("-") else value


def _local_xy(lat: np.ndarray, lon: np.ndarray, lat0: float, lon0: float) -> np.ndarray:
    """Metres east and north of (lat0, lon0): enough to match photos to a trajectory."""
    xy: np.ndarray = np.c_[(lon - lon0) * 111_320.0 * math.cos(math.radians(lat0)), (lat - lat0) * 110_574.0]
    return xy


def _find_offset(path: Path, traj: Trajectory, photos: Sequence[Photo]) -> float:
    """The file's time minus the camera clock: each photo's own GPS position laid on the trajectory
    (its nearest point, between epochs) gives one; their median is taken."""
    with_gps = [p for p in photos if p.has_gps and math.isfinite(photo_seconds(p))]
    if len(with_gps) < 3:
        raise InputError(
            "fewer than 3 photos with GPS and a time to match to the positions: give the time offset", path=path
        )
    lat0, lon0 = float(np.median(traj.lat)), float(np.median(traj.lon))
    txy = _local_xy(traj.lat, traj.lon, lat0, lon0)
    from scipy.spatial import cKDTree

    tree = cKDTree(txy)
    candidates = []
    for p in with_gps:
        pxy = _local_xy(np.array([p.latitude_deg]), np.array([p.longitude_deg]), lat0, lon0)[0]
        dist, k = tree.query(pxy)
        if dist > MAX_GPS_DISTANCE_M:
            continue
        t = float(traj.t_s[k])
        if not traj.is_events:  # between epochs: the nearest point of the segments either side
            best = dist
            for a, b in ((k - 1, k), (k, k + 1)):
                if a < 0 or b >= len(traj.t_s):
                    continue
                seg = txy[b] - txy[a]
                u = float(np.clip((pxy - txy[a]) @ seg / max(float(seg @ seg), 1e-12), 0.0, 1.0))
                d = float(np.linalg.norm(txy[a] + u * seg - pxy))
                if d < best:
                    best, t = d, float(traj.t_s[a] + u * (traj.t_s[b] - traj.t_s[a]))
        candidates.append(t - photo_seconds(p))
    if len(candidates) < 3:
        raise InputError(
            f"its positions do not pass over the photos (no epoch within {MAX_GPS_DISTANCE_M:g} m of 3 photos' "
            "own GPS): another flight's file?",
            path=path,
        )
    offset = float(np.median(candidates))
    if abs(offset) > MAX_CLOCK_OFFSET_S:
        raise InputError(
            f"its times lie {offset / 86400.0:+.2f} days from the photos' clock: a file from another day? "
            "(give the time offset if the camera clock was wrong)",
            path=path,
        )
    spread = float(np.median(np.abs(np.array(candidates) - offset)))
    if spread > 2.0:
        raise InputError(
            f"the photos match its times inconsistently (the offsets spread {spread:.1f} s): photos of more than one "
            "flight, a camera clock that jumped, or another flight's file",
            path=path,
        )
    return offset


def _match_trajectory(
    path: Path, traj: Trajectory, photos: Sequence[Photo], offset: float, found: bool
) -> PositionFile:
    by_image: dict[str, Position] = {}
    without: list[str] = []
    times: dict[str, float] = {}
    used: set[int] = set()
    for p in photos:
        tp = photo_seconds(p)
        if not math.isfinite(tp):
            without.append(p.image)
            continue
        t = tp + offset
        times[p.image] = t
        if traj.is_events:
            k = traj.nearest_epoch(t)
            q = None if k is None else traj._epoch(k)
            if k is not None:
                used.add(k)
        else:
            q = traj.at(t)
        if q is None:
            without.append(p.image)
        else:
            by_image[p.image] = q
    if not by_image:
        why = "a file from another flight?" if found else "is the time offset given right (file time − camera clock)?"
        raise InputError(f"no photo's time falls within its times (offset {offset:+.1f} s): {why}", path=path)
    unused = [f"event {k + 1}" for k in range(len(traj.t_s)) if k not in used] if traj.is_events else []
    return PositionFile(
        path, "RTKLIB .pos", by_image, tuple(without), tuple(unused[:MAX_NAMED_LINES]), offset, found, traj, times,
        heights=traj.heights, n_lines_without=len(unused),
    )  # fmt: skip


# -- DJI Timestamp.MRK ------------------------------------------------------------------------------


def _read_mrk(path: Path, lines: list[str], photos: Sequence[Photo]) -> PositionFile:
    """A line per photo: index, GPS seconds of week, [week], N/E/V offsets (mm), then ``lat,Lat``,
    ``lon,Lon``, ``h,Ellh``, the three standard deviations (m, comma separated) and ``flag,Q``;
    matched to the photos in shooting order."""
    events: list[tuple[int, Position]] = []
    for n, line in enumerate(lines, 1):
        s = line.strip()
        if not s:
            continue
        tagged = {tag: value for value, tag in re.findall(r"(-?\d+(?:\.\d+)?),\s*([A-Za-z]+)\b", s)}
        stds = re.search(r"(\d+\.\d+),\s+(\d+\.\d+),\s+(\d+\.\d+)", s)
        try:
            index = int(s.split()[0])
            lat, lon, h = float(tagged["Lat"]), float(tagged["Lon"]), float(tagged["Ellh"])
            flag = int(float(tagged.get("Q", "0")))
        except (KeyError, ValueError, IndexError):
            raise InputError(f"line {n}: not a DJI MRK event line ({s[:60]!r})", path=path) from None
        fix = RTK_FLAGS.get(flag, "single")
        dh, dv = DEFAULT_SIGMA_M.get(fix, DEFAULT_SIGMA_M["single"])
        if stds is not None:
            sn, se, su = (float(v) for v in stds.groups())
            # a deviation of zero is not stated (a RANSAC on zero weights asserts): the fix class's
            dh = max(sn, se) if max(sn, se) > 0 else dh
            dv = su if su > 0 else dv
        events.append((index, Position(lat, lon, h, dh, dv, fix)))
    if not events:
        raise InputError("holds no event line", path=path)
    ordered = sorted(photos, key=lambda p: (photo_seconds(p) if math.isfinite(photo_seconds(p)) else 0.0, p.image))
    events.sort(key=lambda e: e[0])
    pairs = _align_events(ordered, [q for _, q in events])
    by_image = {ordered[i].image: events[j][1] for i, j in pairs}
    used_p, used_e = {i for i, _ in pairs}, {j for _, j in pairs}
    without = tuple(p.image for i, p in enumerate(ordered) if i not in used_p)
    extra = [f"event {events[j][0]}" for j in range(len(events)) if j not in used_e]
    return PositionFile(path, "DJI MRK", by_image, without, tuple(extra[:MAX_NAMED_LINES]), n_lines_without=len(extra))


def _align_events(photos: Sequence[Photo], events: Sequence[Position]) -> list[tuple[int, int]]:
    """(photo, event) index pairs, both in shooting order. With as many events as photos, one to one.
    Otherwise (an event missing, a photo deleted), aligned on the photos' own GPS where they have it:
    the alignment that keeps the order and costs least, a pair costing its distance (capped) and a
    photo or an event left alone ``MAX_GPS_DISTANCE_M``; without GPS, in order from the first."""
    m, n = len(photos), len(events)
    located = sum(p.has_gps for p in photos)
    if m == n or located < 3:
        return [(i, i) for i in range(min(m, n))]
    gap = MAX_GPS_DISTANCE_M
    band = abs(m - n) + 2
    idx = [(i, j) for i in range(m) for j in range(max(0, i - band), min(n, i + band + 1)) if photos[i].has_gps]
    d = _distances_m(
        [
            (photos[i].latitude_deg, photos[i].longitude_deg, events[j].latitude_deg, events[j].longitude_deg)
            for i, j in idx
        ]
    )
    cost = {ij: min(float(x), gap * 2.0) for ij, x in zip(idx, d)}
    # edit-distance table: best[i, j] aligns the first i photos with the first j events, in a band
    # as wide as the counts differ (and two more): a few events missing, not a shuffled file
    best = np.full((m + 1, n + 1), np.inf)
    best[: band + 1, 0] = np.arange(min(m, band) + 1) * gap
    best[0, : band + 1] = np.arange(min(n, band) + 1) * gap
    for i in range(1, m + 1):
        for j in range(max(1, i - band), min(n, i + band) + 1):
            best[i, j] = min(
                best[i - 1, j - 1] + cost.get((i - 1, j - 1), gap * 2.0), best[i - 1, j] + gap, best[i, j - 1] + gap
            )
    pairs: list[tuple[int, int]] = []
    i, j = m, n
    while i > 0 and j > 0:
        if best[i, j] == best[i - 1, j - 1] + cost.get((i - 1, j - 1), gap * 2.0):
            pairs.append((i - 1, j - 1))
            i, j = i - 1, j - 1
        elif best[i, j] == best[i - 1, j] + gap:
            i -= 1
        else:
            j -= 1
    return pairs[::-1]


# -- CSV ---------------------------------------------------------------------------------------------

#: CSV height columns named for the geoid (sea level), and ``# heights: ...`` words that say so.
_ORTHOMETRIC_COLUMNS = ("h_msl", "height_msl", "msl", "amsl", "alt_msl", "altitude_msl", "orthometric",
                        "orthometric_height", "h_orth", "elevation_msl")  # fmt: skip
_ORTHOMETRIC_WORDS = ("orthometric", "msl", "sea level", "geoid", "egm96", "egm2008", "amsl")


_COLUMNS = {
    "image": ("image", "name", "file", "filename", "photo", "label", "image_name"),
    "x": ("x", "easting", "east", "e", "lon", "long", "longitude"),
    "y": ("y", "northing", "north", "n", "lat", "latitude"),
    "z": (
        "z",
        "height",
        "h",
        "alt",
        "altitude",
        "ellh",
        "elevation",
        "height_m",
        "z_m",
        "altitude_m",
        "h_ell",
        "ellipsoidal_height",
        *_ORTHOMETRIC_COLUMNS,
    ),  # fmt: skip
    "sigma_h": ("sigma_h", "sigma_h_m", "sh", "std_h", "stdh", "accuracy_h", "xy_accuracy", "horizontal_accuracy"),
    "sigma_v": ("sigma_v", "sigma_v_m", "sv", "std_v", "stdv", "accuracy_v", "z_accuracy", "vertical_accuracy"),
    "crs": ("crs", "epsg", "srs"),
}


def _read_csv(path: Path, photos: Sequence[Photo]) -> PositionFile:
    with open(path, encoding="utf-8-sig", errors="replace", newline="") as f:
        return _read_csv_stream(path, f, photos)


def _read_csv_stream(path: Path, f: Iterable[str], photos: Sequence[Photo]) -> PositionFile:
    said: dict[str, str] = {"crs": "", "heights": ""}
    at = [0]  # the number of the line the reader took last
    body = _csv_lines(f, said, at)
    first = next(body, None)
    if first is None:
        raise InputError("has no header row", path=path)
    try:
        dialect: Any = csv.Sniffer().sniff(first, delimiters=",;\t")
    except csv.Error:
        dialect = csv.excel
    # read as a stream: a file of a million rows keeps the rows that match photos, and counts the rest
    rows = csv.reader(itertools.chain([first], body), dialect)
    header = [h.strip().lower() for h in next(rows)]
    header_line = at[0]
    col = _csv_columns(path, header, header_line)
    lonlat = header[col["x"]] in ("lon", "long", "longitude") or header[col["y"]] in ("lat", "latitude")
    crs_text = said["crs"]
    orthometric = header[col["z"]] in _ORTHOMETRIC_COLUMNS or said["heights"] == "orthometric"
    by_name = {p.image.lower(): p for p in photos} | {Path(p.image).stem.lower(): p for p in photos}
    by_image: dict[str, Position] = {}
    line_of: dict[str, int] = {}
    lines_without: list[str] = []
    n_without = 0
    to_ll_cache: dict[str, object] = {}
    stated_crs: set[str] = set()
    for row in rows:
        n = at[0]
        crs_text = said["crs"] or crs_text  # a comment line may come after the header too
        if not any(c.strip() for c in row):
            continue
        if len(row) <= max(col.values()):
            raise InputError(f"line {n}: {len(row)} columns, the header has {len(header)}", path=path)
        name = row[col["image"]].strip()
        p = by_name.get(name.lower()) or by_name.get(Path(name).stem.lower())
        if p is None:
            n_without += 1
            if len(lines_without) < MAX_NAMED_LINES:
                lines_without.append(f"{name[:80]} (line {n})")
            continue
        if p.image in line_of:
            raise InputError(f"line {n}: {p.image} has a position on line {line_of[p.image]} too: keep one", path=path)
        line_of[p.image] = n
        number = _csv_number(path, n, row, header, col)
        x, y, z = number("x"), number("y"), number("z")
        sh = number("sigma_h") if "sigma_h" in col and row[col["sigma_h"]].strip() else math.nan
        sv = number("sigma_v") if "sigma_v" in col and row[col["sigma_v"]].strip() else math.nan
        row_crs = row[col["crs"]].strip() if "crs" in col else ""
        crs_of_row = row_crs or crs_text or ("EPSG:4326" if lonlat else "")
        lon, lat, z_ell, vertical = _csv_position(path, n, x, y, z, crs_of_row, orthometric, to_ll_cache)
        stated_crs.add(vertical)
        stated = math.isfinite(sh) and sh > 0
        by_image[p.image] = Position(
            float(lat), float(lon), z_ell, sh if stated else math.nan,
            (sv if math.isfinite(sv) and sv > 0 else 2.0 * sh) if stated else math.nan,
            "stated" if stated else "consumer",
        )  # fmt: skip
    if not by_image:
        raise InputError("no line matches a photo by its image name", path=path)
    without = tuple(p.image for p in photos if p.image not in by_image)
    heights = "; ".join(sorted(stated_crs))
    return PositionFile(
        path, "CSV", by_image, without, tuple(lines_without), heights=heights, n_lines_without=n_without
    )


def _csv_lines(f: Iterable[str], said: dict[str, str], at: list[int]) -> Iterator[str]:
    """The file's non-blank lines that are no comment, one at a time (``at[0]``: the last one's
    number); ``said`` takes the CRS a comment line names ('crs') and what a ``# heights:`` line
    says of the heights ('heights': 'orthometric' or 'ellipsoidal')."""
    for n, raw in enumerate(f, 1):
        line = raw.rstrip("\r\n")
        if line.lstrip().startswith("#"):
            m = re.search(r"(EPSG:\d+(?:\+\d+)?|crs\s*[:=]\s*\S+)", line, re.IGNORECASE)
            if m and not said["crs"]:
                said["crs"] = re.sub(r"^crs\s*[:=]\s*", "", m.group(1), flags=re.IGNORECASE)
            told = re.search(r"heights?\s*[:=]\s*(.+)", line, re.IGNORECASE)
            if told and not said["heights"]:
                words = told.group(1).lower()
                said["heights"] = "orthometric" if any(w in words for w in _ORTHOMETRIC_WORDS) else (
                    "ellipsoidal" if "ellips" in words else "")  # fmt: skip
            continue
        if line.strip():
            at[0] = n
            yield line


def _csv_columns(path: Path, header: list[str], line: int) -> dict[str, int]:
    """Each known column's index (the first header cell that names it); image, x, y and z required."""
    col: dict[str, int] = {}
    for key, names in _COLUMNS.items():
        for i, h in enumerate(header):
            if h in names and key not in col:
                col[key] = i
    missing = [k for k in ("image", "x", "y", "z") if k not in col]
    if missing:
        raise InputError(
            f"line {line}: the header names no {', '.join(missing)} column "
            "(image, x/easting/longitude, y/northing/latitude, z/height; sigma_h, sigma_v optional)",
            path=path,
        )
    return col


def _csv_number(path: Path, n: int, row: list[str], header: list[str], col: dict[str, int]) -> Callable[[str], float]:
    """Reads a column of line ``n`` as a number, or refuses naming the line and the column."""

    def number(key: str) -> float:
        text_v = row[col[key]].strip()
        try:
            return float(text_v)
        except ValueError:
            raise InputError(f"line {n}: {text_v!r} is not a number in column {header[col[key]]}", path=path) from None

    return number


def _csv_position(
    path: Path, n: int, x: float, y: float, z: float, crs_text: str, orthometric: bool, cache: dict[str, object]
) -> tuple[float, float, float, str]:
    """Line ``n``'s (x, y, z) in ``crs_text`` as WGS 84 longitude, latitude (degrees) and ellipsoidal
    height (m), and how its heights were read. A compound CRS's vertical datum (``+5773``) is
    applied by PROJ; ``orthometric`` (said by the file) puts the heights on the EGM96 geoid."""
    from pyproj import CRS
    from pyproj.exceptions import CRSError

    if not crs_text:
        raise InputError(
            f"line {n}: x/y without a CRS: add a '# EPSG:…' line or a crs column (or name the columns lat/lon)",
            path=path,
        )
    if crs_text not in cache:
        try:
            crs = CRS.from_user_input(crs_text)
            vertical = next((c for c in crs.sub_crs_list if c.is_vertical), None) if crs.is_compound else None
            if vertical is not None:
                to = transformer(crs, CRS("EPSG:4979"))
                cache[crs_text] = (to, True, f"{vertical.name} in the CRS ({crs_text}), turned ellipsoidal")
            else:
                cache[crs_text] = (transformer(crs, WGS84), False, "")
        except CRSError:
            raise InputError(f"line {n}: unknown CRS {crs_text!r}", path=path) from None
    to, three_d, said = cast("tuple[Any, bool, str]", cache[crs_text])
    if three_d:
        lon, lat, h = to.transform(x, y, z)
    else:
        lon, lat = to.transform(x, y)
        h = z
    if not (math.isfinite(lat) and math.isfinite(lon) and abs(lat) <= 90 and abs(lon) <= 180):
        raise InputError(f"line {n}: ({x:g}, {y:g}) is no position in {crs_text}", path=path)
    if not math.isfinite(h):
        raise InputError(f"line {n}: height {z:g} cannot be turned ellipsoidal in {crs_text}", path=path)
    if not three_d and orthometric:
        from geoortho.core.crs import geoid_undulation_m

        h = z + float(geoid_undulation_m(lon, lat))
        said = "orthometric as the file says (EGM96 geoid), turned ellipsoidal"
    elif not three_d:
        said = "ellipsoidal (WGS 84) as read; say '# heights: orthometric' for heights above sea level"
    return float(lon), float(lat), float(h), said
