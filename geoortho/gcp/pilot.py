"""The search over the photos: a few pilot photos first, read by the detector's cheapest attempt, which
measure the flight's common offset; the other photos in windows narrowed by it; a second look where a
marker was still missed, placed by the photos that decoded it.
"""

from __future__ import annotations

import math
import re
from collections.abc import Sequence
from concurrent.futures import Executor
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
from pyproj import CRS

from geoortho.core.camera import in_frame, pixel_rays
from geoortho.core.crs import crs_to_text, transformer
from geoortho.core.gsd import marker_gsd_m
from geoortho.core.parallel import cores, map_ordered
from geoortho.core.surface import FlatSurface, Surface, read_surface
from geoortho.errors import InputError
from geoortho.feedback import Feedback, split
from geoortho.gcp.carry import CarryJob, second_look_task
from geoortho.gcp.detect import (
    ATTEMPTS,
    PROBED,
    Detection,
    SearchWindow,
    beyond_edge_px,
    detect_task,
    probe_task,
    side_ratio,
)
from geoortho.gcp.io import GcpSet
from geoortho.gcp.markers import CODED
from geoortho.gcp.verdicts import Results, closer_prediction, decoded_in, nearest_detection
from geoortho.photos.footprint import PhotoCamera, photo_cameras, working_crs
from geoortho.photos.metadata import Photo

#: A search window reaches this many marker sides beyond the prediction's error, and is never
#: under this radius (px): predict_windows sizes them so, and _rescaled keeps it when the size
#: the markers are searched at changes.
WINDOW_REACH_SIDES = 1.5
MIN_WINDOW_PX = 24.0


def predict_windows(
    cams: Sequence[PhotoCamera],
    names: Sequence[str],
    xyz: np.ndarray,
    ids: dict[str, int],
    *,
    margin_pct: float,
    position_uncertainty_m: float,
    height_uncertainty_m: float,
    attitude_uncertainty_deg: float,
    marker_size_m: float,
    residual_m: float | None = None,
) -> dict[str, list[SearchWindow]]:
    """Per image: the windows to search, centred on each GCP's predicted pixel, that reach the frame.

    With ``residual_m`` (the flight's measured prediction error, after its common
    offset is applied to ``xyz``) each window is that small, and the stated
    uncertainties size its wide fallback.
    """
    out: dict[str, list[SearchWindow]] = {}
    tan_att = math.tan(math.radians(attitude_uncertainty_deg))
    for cam in cams:
        px, _ = cam.project(xyz)
        w, h = cam.intrinsics.width_px, cam.intrinsics.height_px
        mx, my = w * margin_pct / 100.0, h * margin_pct / 100.0
        d = xyz - cam.pose.center
        rng = np.linalg.norm(d, axis=1)
        depth = d @ cam.pose.rotation[:, 2]
        # Pixel size on the horizontal plane of a flat marker, sqrt(depth³ / (f² · height)): constant
        # across a nadir photo, growing with obliquity (geometric mean of the two directions)
        above_m = np.maximum(cam.pose.center[2] - xyz[:, 2], 1e-6)
        depth = np.maximum(depth, 1e-9)
        gsd_m = marker_gsd_m(depth, cam.intrinsics.focal_px, above_m)
        # a height error moves the prediction by dz · (horizontal / vertical) of the ray
        slope = np.hypot(d[:, 0], d[:, 1]) / np.maximum(np.abs(d[:, 2]), 1e-6)
        err_m = position_uncertainty_m + height_uncertainty_m * slope + rng * tan_att
        marker_px = marker_size_m / gsd_m
        radius = err_m / gsd_m + WINDOW_REACH_SIDES * marker_px
        # pixels per marker side along east and north: the target's shape before its rotation
        east = cam.project(xyz + [marker_size_m, 0.0, 0.0])[0] - px
        north = cam.project(xyz + [0.0, marker_size_m, 0.0])[0] - px
        for j, name in enumerate(names):
            x, y = px[j]
            if not (np.isfinite(x) and np.isfinite(y)) or name not in ids:
                continue
            wide = float(max(radius[j], MIN_WINDOW_PX))
            narrow = (
                wide
                if residual_m is None
                else float(min(wide, max(residual_m / gsd_m[j] + WINDOW_REACH_SIDES * marker_px[j], MIN_WINDOW_PX)))
            )
            # The prediction may be off by the window's error part: a marker just inside the
            # frame can be predicted just outside it. Search when the window reaches the frame;
            # the margin is enforced on the detected centre (_judge).
            slack = max(0.0, narrow - WINDOW_REACH_SIDES * marker_px[j])
            if not in_frame(x, y, w, h, mx - slack, my - slack):
                continue
            jac = (east[j, 0], north[j, 0], east[j, 1], north[j, 1])
            out.setdefault(cam.photo.image, []).append(
                SearchWindow(
                    name,
                    ids[name],
                    float(x),
                    float(y),
                    narrow,
                    float(marker_px[j]),
                    wide if narrow < wide else 0.0,
                    tuple(float(v) for v in jac) if np.isfinite(jac).all() else (),
                )
            )
    if residual_m is not None:
        # two GCPs predicted in one window: a target without an id could be either
        for image, wins in out.items():
            out[image] = [
                replace(
                    w,
                    ambiguous_with=next(
                        (
                            o.gcp
                            for o in wins
                            if o is not w and math.hypot(o.x_px - w.x_px, o.y_px - w.y_px) <= w.radius_px
                        ),
                        "",
                    ),
                )
                for w in wins
            ]
    return out


@dataclass
class _Plan:
    """Where each photo is to be searched."""

    cams: dict[str, PhotoCamera]  # photos with a pose, by image name
    unplaced: list[Photo]  # searched whole
    windows: dict[str, list[SearchWindow]]
    names: list[str]
    xyz: np.ndarray  # GCPs in the working CRS
    work: CRS | None
    path_of: dict[str, str]


def plan_search(
    photos: list[Photo],
    gcps: GcpSet,
    ids: dict[str, int],
    dsm: Path | None,
    takeoff_elevation_m: float | None,
    flight_height_m: float | None,
    uncertainty: dict[str, float],
    fb: Feedback,
) -> _Plan:
    placed = [p for p in photos if _has_pose(p)]
    unplaced = [p for p in photos if not _has_pose(p)]
    for p in unplaced:
        fb.warning(f"{p.image}: no usable position/altitude/camera: searched whole")
    names = [p.name for p in gcps.points]
    plan = _Plan({}, unplaced, {}, names, np.zeros((0, 3)), None, {p.image: str(p.path) for p in photos})
    if not placed:
        return plan
    plan.work = work = working_crs(placed, gcps.crs if gcps.crs.is_projected else None)
    t = transformer(gcps.crs, work)
    gx, gy = t.transform(np.array([p.x for p in gcps.points]), np.array([p.y for p in gcps.points]))
    plan.xyz = np.c_[gx, gy, [p.z for p in gcps.points]]
    # The ground model: the DSM, else the GCPs themselves (flat at their median height). The
    # take-off is then worked out as everywhere else (geoortho.photos.heights), unless given.
    surface: Surface = read_surface(dsm, work) if dsm is not None else FlatSurface(float(np.median(plan.xyz[:, 2])))
    try:
        placed_cams, heights = photo_cameras(
            placed,
            work,
            surface,
            takeoff_elevation_m,
            flight_height_m=flight_height_m,
            ground_label="DSM" if dsm is not None else "GCPs' median height",
        )
    except InputError as e:
        # No trustworthy camera height: predictions would be wrong, so search whole photos.
        fb.warning(f"camera heights unknown ({e}): every photo is searched whole")
        plan.unplaced = list(photos)
        return plan
    plan.cams = {c.photo.image: c for c in placed_cams}
    fb.info(f"camera heights: {heights.method} ({heights.takeoff_elevation_m:.2f} m)")
    for note in heights.notes:
        fb.warning(note)
    plan.windows = predict_windows(placed_cams, names, plan.xyz, ids, **uncertainty)
    if not plan.windows:
        raise InputError(_none_inside(placed_cams, gcps, plan.xyz, work, ids, uncertainty), path=gcps.path)
    return plan


def _none_inside(
    cams: list[PhotoCamera], gcps: GcpSet, xyz: np.ndarray, work: CRS, ids: dict[str, int], unc: dict[str, float]
) -> str:
    """Why no GCP is predicted in any photo, with the likely cause when one can be found: the
    columns swapped, or the file's CRS line naming another CRS than its numbers are in."""
    centres = np.array([c.pose.center[:2] for c in cams])
    with np.errstate(invalid="ignore"):
        d = np.hypot(*(xyz[:, None, :2] - centres[None]).transpose(2, 0, 1))
    nearest = float(np.nanmin(d)) if np.isfinite(d).any() else float("inf")
    far = f"the nearest is {nearest / 1000:.1f} km from the flight" if math.isfinite(nearest) else "none maps near it"
    own = working_crs([c.photo for c in cams])  # the photos' own UTM zone
    msg = (
        f"none of the {len(xyz)} GCPs falls inside any photo; {far} — is the CRS right? "
        f"(file: {crs_to_text(gcps.crs)}, photos: {crs_to_text(own)})"
    )
    raw = np.array([[p.x, p.y, p.z] for p in gcps.points])
    names = [p.name for p in gcps.points]

    def lands(x: np.ndarray, y: np.ndarray, crs: CRS) -> bool:
        with np.errstate(invalid="ignore"):
            wx, wy = transformer(crs, work).transform(x, y)
        return bool(predict_windows(cams, names, np.c_[wx, wy, raw[:, 2]], ids, **unc))

    if lands(raw[:, 1], raw[:, 0], gcps.crs):
        return msg + "; with x and y swapped they fall on the flight: the columns look swapped"
    if not gcps.crs.equals(own) and lands(raw[:, 0], raw[:, 1], own):
        return msg + f"; read as {crs_to_text(own)} they fall on the flight: the file's CRS looks wrong"
    return msg


def search_photos(
    plan: _Plan,
    pool: Executor | None,
    workers: int,
    dictionary: str,
    ids: dict[str, int],
    uncertainty: dict[str, float],
    fb: Feedback,
    target: str = "aruco",
    auto_kinds: tuple[str, ...] = (),
) -> tuple[Results, dict[str, list[SearchWindow]], tuple[float, float] | None, str, float, str]:
    """Detect in a few pilot photos with the stated uncertainty, measure the flight's common
    offset and the markers' size there, then search the rest in windows sized by what was
    measured. ``auto``: the pilot photos are searched for each target type and the one found
    most is used. Also the markers' side measured (m; NaN when too few were decoded) and the
    dictionary searched (another than the one given when only it decodes: :func:`_probe`)."""
    windows = dict(plan.windows)
    searched = [im for im in plan.cams if im in windows]
    pilot = _pilot_images(searched, windows, plan.cams, workers)
    rest = [im for im in searched if im not in set(pilot)]
    s_quick, s_pilot, s_refit, s_rest = split(
        fb, [0.4 * len(pilot), len(pilot), 0.5 * len(pilot), len(rest) + len(plan.unplaced)]
    )

    def run(
        jobs: list[tuple[str, list[SearchWindow]]],
        kind: str,
        f: Feedback,
        fit: bool = True,
        attempts: tuple[str, ...] = ATTEMPTS,
    ) -> Results:
        items = [(plan.path_of[im], wins, dictionary, kind, fit, attempts) for im, wins in jobs]
        return map_ordered(detect_task, items, workers=1 if pool is None else workers, executor=pool, feedback=f)

    # Coded markers in the pilot: the detector alone first. A model fit in a window sized for the
    # stated uncertainty costs seconds; in the window narrowed by the measured offset, a fraction.
    def pilot_run(ims: list[str], kind: str, f: Feedback, attempts: tuple[str, ...] = ATTEMPTS) -> Results:
        return run([(im, windows[im]) for im in ims], kind, f, fit=kind not in CODED, attempts=attempts)

    coded = target in CODED

    def offset_of(results: Results) -> tuple[np.ndarray, float, int] | None:
        return _flight_offset(
            results,
            windows,
            plan.cams,
            dict(zip(plan.names, plan.xyz)),
            consensus_m=None if coded else max(1.5, 2.0 * uncertainty["marker_size_m"]),
        )

    results = None
    if coded:
        # The detector's cheapest read first, in twice as many photos: the offset needs a few
        # markers in more than one photo, and a pilot photo with one missed is searched again with
        # the rest, every attempt in its narrowed window. The other attempts in the wide windows
        # (a blurred photo's blur undone over 500 px squares) cost a degraded flight's pilot four
        # times as much; they run only where this read gives no offset.
        more = _pilot_images(searched, windows, plan.cams, workers, times=2)
        quick = pilot_run(more, target, s_quick, attempts=("fast",))
        if len({path for path, *_ in decoded_in(quick, windows)}) >= 2 and offset_of(quick) is not None:
            pilot, results = more, quick
            rest = [im for im in searched if im not in set(pilot)]
    if target == "auto":
        target, results = _choose_target(pilot, windows, pilot_run, auto_kinds, s_pilot)
    elif results is None:
        results = pilot_run(pilot, target, s_pilot)
        if target in CODED and next(decoded_in(results, windows), None) is None:
            ratio, other = _probe(plan, pilot, windows, dictionary, ids, pool, workers)
            if ratio is not None:
                measured = uncertainty["marker_size_m"] * ratio
                fb.warning(
                    f"no marker decodes at the size given ({uncertainty['marker_size_m']:g} m) in the first "
                    f"{len(pilot)} photos; they decode at {measured:.2f} m a side: searched at that "
                    "(give --marker-size-m when that is their size; else the camera heights are off)"
                )
                windows = _rescaled(windows, ratio)
                uncertainty = dict(uncertainty, marker_size_m=measured)
                results = pilot_run(pilot, target, s_pilot)
            elif other is not None:
                fb.warning(
                    f"no marker decodes as {dictionary} in the first {len(pilot)} photos, while {other[1]} of the "
                    f"GCPs' markers decode as {other[0]} where predicted: searched as {other[0]} "
                    f"(give --dictionary {other[0]})"
                )
                dictionary = other[0]
                results = pilot_run(pilot, target, s_pilot)
    coded = target in CODED
    offset = offset_of(results)
    # pilot photos where the detector missed a coded marker: fitted in their narrowed windows
    # with the rest, or here (in the wide ones) when the decoded markers were too few to measure
    unfitted = [
        Path(path).name
        for path, dets, *_ in results
        if coded and any(nearest_detection(dets, k, w) is None for k, w in enumerate(windows[Path(path).name]))
    ]
    if unfitted and offset is None:
        again = {Path(r[0]).name: r for r in run([(im, windows[im]) for im in unfitted], target, s_refit)}
        results = [again.get(Path(r[0]).name, r) for r in results]
        offset = offset_of(results)
    elif unfitted:
        rest += unfitted
        refit = set(unfitted)
        results = [r for r in results if Path(r[0]).name not in refit]
    if offset is None and not coded:
        # Without an id, a fit is trusted only where the flight's measured offset puts its GCP:
        # fits that agree on no common offset are texture, or the GCPs are not where the file says.
        why = (
            f"the {target} fits in the first {len(pilot)} photos agree on no common flight offset "
            "(at least 3 fits of 2 GCPs within a few metres): not the targets, or the GCP file is off"
        )
        fb.warning(f"nothing accepted: {why}")
        results = [(p, [replace(d, reason=d.reason or why) for d in dets], e, b) for p, dets, e, b in results]
        return results, windows, None, target, math.nan, dictionary
    if offset is not None:
        rest, results = _narrow_windows(plan, windows, rest, pilot, results, offset, ids, uncertainty, target, fb)
    # photos without a pose are searched whole, for coded markers only (nothing else tells a target)
    whole = [SearchWindow("", -1, 0.0, 0.0, 0.0)]
    jobs = [(im, windows[im]) for im in rest] + [(p.image, whole) for p in plan.unplaced if target in CODED]
    # coded markers by the detector alone here: the ones it misses are fitted once every photo has
    # been searched, where the photos that decoded them put them (_second_look)
    results += run(jobs, target, s_rest, fit=not coded)
    marker_m = math.nan
    if coded:  # every photo searched by the detector: the fits to come need the markers' true size
        marker_m, windows = _marker_size(results, windows, uncertainty["marker_size_m"], fb)
    shift = None if offset is None else (float(offset[0][0]), float(offset[0][1]))
    return results, windows, shift, target, marker_m, dictionary


def _probe(
    plan: _Plan,
    pilot: list[str],
    windows: dict[str, list[SearchWindow]],
    given: str,
    ids: dict[str, int],
    pool: Executor | None,
    workers: int,
) -> tuple[float | None, tuple[str, int] | None]:
    """Where no marker decoded in the pilot photos, what the photos say was given wrong: the
    markers' size (their side over the predicted, when the dictionary given decodes the GCPs'
    ids at any size: the detector keeps only half to twice the predicted side), else the
    dictionary they decode in (the smallest of its family that holds every GCP id, and how many
    GCPs decoded). Two GCPs at least (or the one there is) must agree; (None, None) when none
    does. A wrong size or dictionary otherwise finds nothing, and says only that."""
    own = _aruco_family(given)  # its own ids decoded nothing: nor would its family's larger ones
    tried = tuple(d for d in PROBED if d != given and (own is None or _aruco_family(d) != own))
    items = [(plan.path_of[im], windows[im], tried, given) for im in pilot]
    seen: dict[str, list[tuple[str, float]]] = {}
    for found in map_ordered(probe_task, items, workers=1 if pool is None else workers, executor=pool):
        for name, hits in found.items():
            seen.setdefault(name, []).extend(hits)
    enough = min(2, len(ids))
    unsized = seen.pop(given, [])
    if len({g for g, _ in unsized}) >= enough:
        ratio = float(np.median([r for _, r in unsized]))
        # at about the size given they were missed for another cause (blur: the ladder's "plain"
        # attempt is skipped on a smeared photo): neither the size nor the dictionary was wrong
        return (ratio, None) if abs(ratio - 1.0) > MARKER_SIZE_TOLERANCE else (None, None)
    if not seen:
        return None, None
    name, hits = max(seen.items(), key=lambda kv: len({g for g, _ in kv[1]}))
    n_gcps = len({g for g, _ in hits})
    if n_gcps < enough:
        return None, None
    family = _aruco_family(name)
    if family is not None:  # the family's smallest that holds every id
        size = next(n for n in (50, 100, 250, 1000) if n > max(ids.values()))
        name = f"{family}_{size}"
    return None, (name, n_gcps)


def _aruco_family(dictionary: str) -> str | None:
    """An ArUco dictionary's family ("DICT_4X4" for DICT_4X4_50): its dictionaries of 50, 100, 250
    and 1000 ids are each the first ids of the next. None for the others (AprilTag, original)."""
    m = re.fullmatch(r"(DICT_[4-7]X[4-7])_\d+", dictionary)
    return m.group(1) if m else None


def _rescaled(windows: dict[str, list[SearchWindow]], ratio: float) -> dict[str, list[SearchWindow]]:
    """The windows for markers ``ratio`` times the size they were predicted for."""

    def one(w: SearchWindow) -> SearchWindow:
        grow = WINDOW_REACH_SIDES * w.side_px * (ratio - 1.0)
        return replace(
            w,
            side_px=w.side_px * ratio,
            ground_px=tuple(v * ratio for v in w.ground_px),
            radius_px=max(w.radius_px + grow, MIN_WINDOW_PX),
            wide_radius_px=max(w.wide_radius_px + grow, MIN_WINDOW_PX) if w.wide_radius_px > 0 else 0.0,
        )

    return {im: [one(w) for w in wins] for im, wins in windows.items()}


#: How far the markers' measured size may be from the size given before the search and the fits
#: use the measured one: a fit's size tolerance is tighter than this, the detector's twice it.
MARKER_SIZE_TOLERANCE = 0.15


def _marker_size(
    results: Results, windows: dict[str, list[SearchWindow]], given_m: float, fb: Feedback
) -> tuple[float, dict[str, list[SearchWindow]]]:
    """The markers' side (m) as the decoded ones measure: the median of their sides over the
    sides the windows predict for the size given (NaN with fewer than 3). The detector decodes a
    marker from half to twice the predicted side, while a model fit holds its size to a few per
    cent: a size given wrong (0.55 m markers searched as the default 1 m) left the fits failing,
    recall 0.38 against 0.92, at six times the time. Beyond :data:`MARKER_SIZE_TOLERANCE` the
    windows take the measured size (the fits are made in them), said."""
    ratios = [r for _, d, win in decoded_in(results, windows) if math.isfinite(r := side_ratio(d.corners_px, win))]
    if len(ratios) < 3:
        return math.nan, windows
    ratio = float(np.median(ratios))
    measured = given_m * ratio
    if abs(ratio - 1.0) <= MARKER_SIZE_TOLERANCE:
        return measured, windows
    fb.warning(
        f"the {len(ratios)} markers decoded measure {measured:.2f} m a side (median) at the camera heights "
        f"used, not the {given_m:g} m given: the rest are fitted at {measured:.2f} m (give --marker-size-m "
        "when that is their size; else the camera heights are off)"
    )
    return measured, _rescaled(windows, ratio)


def _narrow_windows(
    plan: _Plan,
    windows: dict[str, list[SearchWindow]],
    rest: list[str],
    pilot: list[str],
    results: Results,
    offset: tuple[np.ndarray, float, int],
    ids: dict[str, int],
    uncertainty: dict[str, float],
    target: str,
    fb: Feedback,
) -> tuple[list[str], Results]:
    """The flight's measured offset said, and the windows of the photos still to search placed
    with it and sized by its residual (``windows`` updated); the photos to search and the
    results kept."""
    shift_m, residual_m, n_used = offset
    fb.info(
        f"flight offset from {n_used} detections in {len(pilot)} photos: {shift_m[0]:+.2f} m E, "
        f"{shift_m[1]:+.2f} m N; windows sized for a {residual_m:.1f} m residual "
        f"(wide fallback: the stated uncertainty)"
    )
    coded = target in CODED
    if not coded:
        # a target without an id is told by position: search every photo again, in windows
        # placed with the measured offset (the pilot's were sized for the stated uncertainty)
        rest, results = rest + pilot, []
    narrowed = predict_windows(
        [plan.cams[im] for im in rest],
        plan.names,
        plan.xyz + [shift_m[0], shift_m[1], 0.0],
        ids,
        residual_m=residual_m,
        **uncertainty,
    )
    if not coded:  # a target without an id is only trusted where the measured offset puts it
        narrowed = {im: [replace(w, wide_radius_px=0.0) for w in ws] for im, ws in narrowed.items()}
    for im in rest:
        windows.pop(im)
    windows.update(narrowed)
    rest = [im for im in rest if im in windows]
    return rest, results


def _choose_target(
    pilot: list[str],
    windows: dict[str, list[SearchWindow]],
    run: Any,
    kinds: tuple[str, ...],
    fb: Feedback,
) -> tuple[str, Results]:
    """``--target auto``: the type found in most pilot windows (coded markers first: a decoded id
    is proof). Said as an info line with every type's count."""
    counts: dict[str, int] = {}
    best: tuple[str, Results] | None = None
    steps = split(fb, [1] * len(kinds))
    for kind, step in zip(kinds, steps):
        res = run(pilot, kind, step)
        n = sum(
            1
            for path, dets, *_ in res
            for k, win in enumerate(windows[Path(path).name])
            if (f := nearest_detection(dets, k, win)) is not None and f[1] <= win.max_radius_px
        )
        counts[kind] = n
        if best is None or n > counts[best[0]]:
            best = (kind, res)
        if kind in CODED and n >= 3:
            break  # decoded ids: no other type needs trying
    assert best is not None
    fb.info(
        f"target: {best[0]} (found in the first {len(pilot)} photos: "
        + ", ".join(f"{k} {n}" for k, n in counts.items())
        + ")"
    )
    return best


def _has_pose(p: Photo) -> bool:
    return p.has_gps and p.has_altitude and math.isfinite(p.focal_px)


def _pilot_images(
    images: list[str],
    windows: dict[str, list[SearchWindow]],
    cams: dict[str, PhotoCamera],
    workers: int,
    times: int = 1,
) -> list[str]:
    """The photos searched first to measure the flight's offset: those with the most
    predictions well inside the frame (``times`` as many). All when the flight is too small to gain."""
    n = times * max(4, 2 * (workers or cores()))
    if len(images) < 3 * n:
        return list(images)

    def inside(im: str) -> int:
        w, h = cams[im].intrinsics.width_px, cams[im].intrinsics.height_px
        return sum(bool(in_frame(v.x_px, v.y_px, w, h, 0.15 * w, 0.15 * h)) for v in windows[im])

    ranked = sorted(images, key=lambda im: -inside(im))
    return [im for im in images if im in set(ranked[:n])]  # keep the flight order


def _flight_offset(
    results: Results,
    windows: dict[str, list[SearchWindow]],
    cams: dict[str, PhotoCamera],
    xyz_of: dict[str, np.ndarray],
    consensus_m: float | None = None,
) -> tuple[np.ndarray, float, int] | None:
    """The flight's common ground offset of the predictions and the largest residual, metres.

    A detected marker's ray, cast from the recorded pose onto the GCP's height,
    lands at the GCP plus the GPS bias (the part common to the flight); what is
    left varies per photo (attitude, height, GPS noise). Needs 3 detections.
    ``consensus_m`` (targets without an id, where a fit may be texture): only the
    largest set of offsets that agree within this many metres counts, and it must hold
    3 detections of 2 GCPs (of 1 when the file has one) — texture lands anywhere.
    """
    shifts, gcp_of = [], []
    for path, dets, *_ in results:
        image = Path(path).name
        cam = cams[image]
        for k, win in enumerate(windows[image]):
            found = nearest_detection(dets, k, win)
            if found is None or found[1] > win.max_radius_px:
                continue
            d = found[0]
            if d.attempt == "fitted" and closer_prediction(d, found[1], win, windows[image]):
                continue
            ray = pixel_rays(np.array([[d.x_px, d.y_px]]), cam.intrinsics, cam.pose)[0]
            g = xyz_of[win.gcp]
            if ray[2] > -1e-3:
                continue
            hit = cam.pose.center + (g[2] - cam.pose.center[2]) / ray[2] * ray
            shifts.append(hit[:2] - g[:2])
            gcp_of.append(win.gcp)
    if len(shifts) < 3:
        return None
    s = np.array(shifts)
    if consensus_m is not None:
        near = np.linalg.norm(s[:, None] - s[None], axis=2) <= consensus_m
        keep = near[int(np.argmax(near.sum(axis=1)))]
        keep = np.linalg.norm(s - np.median(s[keep], axis=0), axis=1) <= consensus_m
        if keep.sum() < 3 or len({g for g, k in zip(gcp_of, keep) if k}) < min(2, len(xyz_of)):
            return None
        s = s[keep]
    shift_m = np.median(s, axis=0)
    worst_m = float(np.linalg.norm(s - shift_m, axis=1).max())
    # half again the worst residual seen, never under a metre: the pilot photos are a sample
    return shift_m, max(1.0, 1.5 * worst_m), len(shifts)


def second_look(
    results: Results,
    windows: dict[str, list[SearchWindow]],
    plan: _Plan,
    dictionary: str,
    target: str,
    pool: Executor | None,
    workers: int,
) -> Results:
    """Coded markers not found in a photo once every photo is searched, fitted again
    (:func:`.carry.second_look_task`): where the nearest photo that decoded them puts them
    (:func:`.carry.carried_place`), else in their whole window. A blurred photo often has no
    marker of its own found to place the others by; a sharp neighbour has. A marker so carried is
    taken as one placed by its photo's other markers (:func:`_placed`)."""
    donors: dict[str, list[tuple[str, Detection, SearchWindow]]] = {}
    for path, d, win in decoded_in(results, windows):
        donors.setdefault(win.gcp, []).append((path, d, win))
    jobs: dict[str, list[CarryJob]] = {}
    for path, dets, error, _ in results:
        image = Path(path).name
        cam = plan.cams.get(image)
        if cam is None or error:
            continue
        for k, win in enumerate(windows.get(image, [])):
            if len(win.ground_px) != 4 or nearest_detection(dets, k, win):
                continue
            w, h = cam.photo.width_px, cam.photo.height_px
            # a marker predicted just beyond the frame may lie just inside it: the photo is looked
            # at again for it too (fit_missed fits it there), though no ground is carried to it
            beyond = -beyond_edge_px(win)
            if not in_frame(win.x_px, win.y_px, w, h, beyond, beyond):
                continue
            carries = jobs.setdefault(path, [])
            if not in_frame(win.x_px, win.y_px, w, h) or not donors.get(win.gcp):
                continue
            # the nearest camera sees the ground most alike (least turned, least parallax)
            here = np.asarray(cam.pose.center)
            d_path, d, d_win = min(
                donors[win.gcp], key=lambda dd: float(np.linalg.norm(plan.cams[Path(dd[0]).name].pose.center - here))
            )
            carries.append((k, d_path, (d.x_px, d.y_px), d_win.ground_px, d.corners_px))
    if not jobs:
        return results
    by_path = {path: (dets, blur) for path, dets, _, blur in results}
    items = [
        (path, windows[Path(path).name], by_path[path][0], js, dictionary, target, by_path[path][1])
        for path, js in jobs.items()
    ]
    # the photos with the most markers to fit first: a long one started last holds the pool open
    items.sort(key=lambda item: -len(item[3]))
    looked = dict(map_ordered(second_look_task, items, workers=1 if pool is None else workers, executor=pool))
    return [(path, looked.get(path, dets), error, blur) for path, dets, error, blur in results]
