"""The posed photos placed on the surface for a mosaic: each one's footprint and GSD, photos that look
at the horizon or belong to another flight left out, and the mosaic's resolution.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from geoortho.core.camera import PosedCamera
from geoortho.core.surface import GridSurface, Surface
from geoortho.errors import InputError, ParameterError
from geoortho.feedback import Feedback
from geoortho.photos.footprint import compute_footprints


@dataclass(frozen=True)
class _Placed:
    """The photos that see the surface, where they land and their GSD; the others and why."""

    cams: tuple[PosedCamera, ...]
    boxes: tuple[tuple[float, float, float, float], ...]  # ground bounding box of each footprint
    gsds: tuple[float, ...]  # GSD at the image centre, metres
    skipped: tuple[tuple[str, str], ...]
    taken_at: tuple[str, ...] = ()  # each photo's capture time (ISO 8601, "" when unknown)


MIN_AXIS_BELOW_HORIZON_DEG = 20.0


def place_photos(cams: Sequence[PosedCamera], surface: Surface, fb: Feedback) -> _Placed:
    """Cast each photo's border onto the surface (as the footprints stage does); leave out those that miss it."""
    if not cams:
        raise InputError("no photo sees the surface: nothing to mosaic")
    centres = np.array([c.pose.center for c in cams])
    ground = surface.elevation(centres[:, 0], centres[:, 1])
    heights = centres[:, 2] - np.where(np.isfinite(ground), ground, surface.z_min)
    max_range = 5.0 * float(np.median(heights[heights > 0])) if (heights > 0).any() else 1000.0
    table = compute_footprints(cams, surface, max_range_m=max_range)
    kept: list[PosedCamera] = []
    boxes: list[tuple[float, float, float, float]] = []
    gsds: list[float] = []
    skipped: list[tuple[str, str]] = []
    axis_z = np.array([(c.pose.rotation @ [0.0, 0.0, 1.0])[2] for c in cams])
    below_horizon_deg = np.degrees(np.arcsin(np.clip(-axis_z, -1.0, 1.0)))
    for i, cam in enumerate(cams):
        if below_horizon_deg[i] < MIN_AXIS_BELOW_HORIZON_DEG:
            # a view along the ground rectifies into a smear of stretched pixels, never a map
            why = (
                f"it looks at the horizon (view axis {abs(below_horizon_deg[i]):.0f} deg "
                f"{'below' if below_horizon_deg[i] >= 0 else 'above'} it, "
                f"less than {MIN_AXIS_BELOW_HORIZON_DEG:.0f}): not a mapping photo"
            )
            skipped.append((cam.name, why))
            fb.warning(f"skipped {cam.name}: {why}")
            continue
        # rays that missed end at the range limit: the box reaches that far
        ring = table.rings[i]
        box = (float(ring[:, 0].min()), float(ring[:, 1].min()), float(ring[:, 0].max()), float(ring[:, 1].max()))
        sees = heights[i] > 0 and np.isfinite(table.gsd_min_m[i])  # some ray met the surface
        if sees and isinstance(surface, GridSurface) and not surface.extend:
            sx0, sy0, sx1, sy1 = surface.bounds
            sees = not (box[2] <= sx0 or box[0] >= sx1 or box[3] <= sy0 or box[1] >= sy1)
        if not sees:
            skipped.append((cam.name, "its footprint misses the surface (outside the DSM or camera below it)"))
            fb.warning(f"skipped {cam.name}: outside the surface")
            continue
        kept.append(cam)
        boxes.append(box)
        gsds.append(float(table.gsd_m[i]))
    if not kept:
        raise InputError("no photo sees the surface: nothing to mosaic")
    return _Placed(tuple(kept), tuple(boxes), tuple(gsds), tuple(skipped))


#: Photos taken this far apart in time are of different flights; a flight of one photo, or of under
#: ``OTHER_FLIGHT_SHARE`` of them (a stray photo of another day in the folder: its shadows,
#: cars and crops are not the survey's) is left out of the mosaic, named.
FLIGHT_GAP_S = 2 * 3600.0
OTHER_FLIGHT_SHARE = 0.1


def without_other_flights(placed: _Placed, fb: Feedback) -> _Placed:
    """``placed`` with each photo's capture time (read once, for the flights here and the
    seamlines' table), less the photos of a small other flight (by the cameras' clocks)."""
    from geoortho.photos.metadata import photo_seconds, read_photo

    taken_at, seconds = [], []
    for cam in placed.cams:
        try:
            photo = read_photo(cam.file)
        except (InputError, ValueError, OSError):  # no file (a planned camera), no EXIF: no time
            taken_at.append("")
            seconds.append(math.nan)
            continue
        taken_at.append(photo.taken_at)
        seconds.append(photo_seconds(photo))
    placed = replace(placed, taken_at=tuple(taken_at))
    t = np.array(seconds)
    timed = np.flatnonzero(np.isfinite(t))
    if len(timed) < 3:
        return placed
    order = timed[np.argsort(t[timed], kind="stable")]
    flights = np.split(order, np.flatnonzero(np.diff(t[order]) > FLIGHT_GAP_S) + 1)
    main = max(flights, key=len)
    why: dict[int, str] = {}
    for flight in flights:
        if flight is main or len(flight) >= max(OTHER_FLIGHT_SHARE * len(timed), 2):
            continue
        hours = (float(np.median(t[flight])) - float(np.median(t[main]))) / 3600.0
        for i in flight:
            why[int(i)] = (
                f"taken {abs(hours):,.1f} h {'before' if hours < 0 else 'after'} the {len(main)} photos of the "
                "survey's flight: another flight over the site, left out of the mosaic and its seams"
            )
    if not why:
        return placed
    for i in sorted(why):
        fb.warning(f"skipped {placed.cams[i].name}: {why[i]}")
    keep = [i for i in range(len(placed.cams)) if i not in why]
    return _Placed(
        tuple(placed.cams[i] for i in keep),
        tuple(placed.boxes[i] for i in keep),
        tuple(placed.gsds[i] for i in keep),
        (*placed.skipped, *((placed.cams[i].name, why[i]) for i in sorted(why))),
        tuple(taken_at[i] for i in keep),
    )


def mosaic_resolution(
    resolution_m: float | None, gsds: Sequence[float], notes: list[str], fb: Feedback
) -> tuple[float, float]:
    """The pixel size (given, else the median GSD to 3 digits) and the median GSD, metres."""
    finite = [g for g in gsds if math.isfinite(g)]
    median_gsd = float(np.median(finite)) if finite else math.nan
    if not resolution_m:  # None or 0: the photos' median GSD
        if not math.isfinite(median_gsd):
            raise InputError("the GSD could not be found; give a resolution")
        resolution_m = float(f"{median_gsd:.3g}")
        fb.info(f"resolution {resolution_m * 100:.2f} cm: the median GSD")
    elif math.isfinite(median_gsd) and resolution_m < 0.95 * median_gsd:
        notes.append(
            f"the resolution {resolution_m * 100:.2f} cm is finer than the photos' median GSD "
            f"{median_gsd * 100:.2f} cm: pixels are interpolated, not resolved"
        )
        fb.warning(notes[-1])
    if resolution_m <= 0:
        raise InputError("the resolution must be positive")
    if math.isfinite(median_gsd) and not 0.1 * median_gsd <= resolution_m <= 100 * median_gsd:
        # a mosaic of a few pixels, or 100x more pixels than the photos resolve: neither is a product
        raise ParameterError(
            "resolution_m",
            f"{resolution_m:g} m is not within 0.1 to 100 x the photos' median GSD ({median_gsd * 100:.2f} cm): "
            f"give {0.1 * median_gsd:.3g} to {100 * median_gsd:.3g} m",
        )
    return resolution_m, median_gsd
