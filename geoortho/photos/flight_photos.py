"""A flight's photos taken together: when each was taken, photos far from the rest, a heading from the
course where the metadata gives none, positions as longitude and latitude.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import replace

import numpy as np

from geoortho.photos.photo import Photo
from geoortho.photos.tags import NO_ATTITUDE, wrap_deg


def drop_far_away(photos: list[Photo]) -> tuple[list[Photo], list[tuple[str, str]]]:
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
        return a is not None and b is not None and abs(wrap_deg(a - b)) < 30.0

    out = list(photos)
    for k, (_, i) in enumerate(timed):
        p = photos[i]
        if not p.yaw_unknown:
            continue
        c_in = courses[k - 1] if k > 0 else None
        c_out = courses[k] if k < len(courses) else None
        if agree(c_in, c_out):
            yaw = c_in + wrap_deg(c_out - c_in) / 2  # type: ignore[operator]
        elif c_in is not None and (c_out is None or agree(c_in, courses[k - 2] if k > 1 else None)):
            yaw = c_in  # last photo of a line: the way in continues the line
        elif c_out is not None:
            yaw = c_out  # first photo of a line
        else:
            continue
        yaw = wrap_deg(yaw)
        # The course replaces the "top to the north" guess: say that, not both.
        kept = tuple(w for w in p.warnings if not w.startswith(NO_ATTITUDE))
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
