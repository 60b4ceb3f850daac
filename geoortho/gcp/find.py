"""Find GCP markers in photos and write OpenDroneMap's gcp_list.txt.

1. Project every GCP into every photo with the metadata pose (footprint.py),
   on the DSM's datum when one is given.
2. Size a search window around each prediction from the position, height
   and attitude uncertainty at the photo's GSD; keep the (photo, GCP) pairs
   whose window reaches the frame minus a margin (the margin is then checked
   on the detected centre).
3. Detect the coded marker in that window at full resolution, retrying
   harder cases (CLAHE, ×2 upscale, a glare-tolerant threshold; in a blurred
   photo first its measured blur undone by a Wiener filter); corners are
   refined on the marker's edges (OpenCV's contour refinement: 0.03 px mean
   centre error on the synthetic survey, against 0.18 px with corner
   sub-pixel refinement). A few pilot photos go first, read by the
   detector's cheapest attempt (all of them only where that reads too few):
   their detections measure the flight's common offset (GPS bias), and the
   other photos are searched in windows sized by the residual left after
   it — a tenth of the area — with the stated uncertainty as a fallback when
   the marker is not there (searched by the detector only, after the fits
   below).
   Where the detector cannot decode a marker (blur, glare), its model is
   fitted (verified) in its window; where two other markers of the photo
   were found, only within a few pixels of where they put it. A marker still not found is
   fitted again where the nearest photo that decoded it puts it: the ground
   around it there, matched in this photo's (narrow) window.
4. Keep only detections with the GCP's id within the window: a wrong id, an
   id not in the GCP file, or a marker too far from its prediction is
   reported, never written. A verified marker whose code is too blurred to
   tell its id in this photo is taken only when its place was given by the
   photo's other markers, or by another photo's ground, and its id was
   decoded in another photo.

Photos without a usable pose (no GPS, no altitude) are searched whole; there
only ids of the GCP file are accepted. The take-off elevation, unless given,
is taken as the median GCP elevation: GCPs lie on the ground of the surveyed
area, which is a better guess than a consumer drone's GNSS height.
"""

from __future__ import annotations

import math
import os
import re
from collections.abc import Iterator, Sequence
from concurrent.futures import Executor
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
from pyproj import CRS

from geoortho.core.camera import in_frame, pixel_rays
from geoortho.core.crs import crs_to_text, transformer
from geoortho.core.gsd import marker_gsd_m
from geoortho.core.outputs import atomic_path, write_text, write_vector
from geoortho.core.parallel import map_ordered, process_pool
from geoortho.core.styles import product_styles
from geoortho.core.surface import FlatSurface, Surface, read_surface
from geoortho.errors import InputError
from geoortho.feedback import Feedback, as_feedback, split
from geoortho.gcp.detect import (
    ATTEMPTS,
    PROBED,
    CarryJob,
    Detection,
    SearchWindow,
    beyond_edge_px,
    detect_task,
    fit_similarity,
    init_worker,
    placed_by_others,
    probe_task,
    second_look_task,
    side_ratio,
)
from geoortho.gcp.io import GcpSet, marker_id_of, read_gcp_file
from geoortho.gcp.markers import CODED, TARGETS, Dictionary, FindTarget, get_dictionary
from geoortho.photos.footprint import PhotoCamera, photo_cameras, working_crs
from geoortho.photos.metadata import Photo, list_images, read_photos

__all__ = ["GcpFindResult", "gcp_find", "Observation", "predict_windows"]

# Statuses of a candidate, as written to the detections table.
DETECTED = "detected"
NOT_FOUND = "not found"
TOO_FAR = "too far from prediction"
WRONG_ID = "id not in GCP file"
IN_MARGIN = "inside the margin"
AMBIGUOUS = "ambiguous"


@dataclass(frozen=True)
class Observation:
    """One candidate (photo, GCP) pair and what became of it."""

    image: str
    gcp: str
    marker_id: int
    status: str
    predicted_x_px: float = math.nan
    predicted_y_px: float = math.nan
    window_px: float = 0.0
    x_px: float = math.nan
    y_px: float = math.nan
    error_px: float = math.nan  # detection − prediction
    attempt: str = ""
    side_px: float = math.nan
    corners_px: tuple[tuple[float, float], ...] = ()
    method: str = ""  # decoded (the detector read its id), verified (coded, by model fit), fitted (no code)
    score: float = math.nan  # model fit: normalised correlation
    id_margin: float = math.nan  # verified: over the best other id or rotation
    position_margin: float = math.nan  # model fit: over the best look-alike in the window
    blur_px: float = math.nan  # model fit: motion blur length at the target
    contrast_dn: float = math.nan  # model fit: the target's white − black, grey levels
    worst_part: float = math.nan  # model fit, no id: largest mean residual over a part, share of the contrast
    shape_margin: float = math.nan  # model fit, no id: over the best plain edge, bar, corner or blob
    photo_blur_px: float = math.nan  # the photo's motion blur, estimated from its texture
    reason: str = ""  # why a candidate was not accepted, when there is more to say than its status


@dataclass(frozen=True)
class GcpFindResult:
    """What gcp-find wrote and found.

    Attributes
    ----------
    output : Path
        OpenDroneMap gcp_list.txt.
    detections : Path
        Every candidate and what became of it (None when not asked for).
    review : Path
        PNG contact sheet of the detections (None when not asked for).
    n_observations : int
        Observations written.
    n_gcps_found : int
        GCPs seen at least once.
    n_candidates : int
        (photo, GCP) pairs searched.
    crs : str
        CRS of gcp_list.txt.
    flight_offset_m : tuple of float
        The flight's common position error measured on the pilot photos (east, north, metres).
    marker_size_m : float
        The markers' side as the decoded ones measure, metres (the median over them, at the
        camera heights used; NaN when fewer than 3 were decoded). Where it differs from the size
        given by more than 15 %, the markers the detector missed were fitted at it, with a warning.
    dictionary : str
        The marker dictionary searched: the one given, or, where no marker decoded in it in the
        first photos, the one the GCPs' markers decode in there (with a warning); "" for
        targets without a code.
    """

    output: Path
    detections: Path | None
    review: Path | None
    n_observations: int
    n_gcps_found: int
    n_candidates: int
    crs: str
    #: the flight's common position error measured on the pilot photos (east, north, metres)
    flight_offset_m: tuple[float, float] | None = None
    #: the markers' side as the decoded ones measure (m; NaN when fewer than 3 were decoded)
    marker_size_m: float = math.nan
    #: the marker dictionary searched ("" for targets without a code)
    dictionary: str = ""


def _marker_ids(gcps: GcpSet, dictionary: str, target: str = "aruco") -> dict[str, int]:
    if target not in CODED and target != "auto":
        return {p.name: i for i, p in enumerate(gcps.points)}  # no code: an index to tell windows apart
    n_ids = get_dictionary(dictionary).bytesList.shape[0]
    ids = {}
    for p in gcps.points:
        mid = marker_id_of(p.name)
        if mid is None or mid >= n_ids:
            continue
        ids[p.name] = mid
    if not ids:
        raise InputError(f"no GCP name ends in a marker id of {dictionary} (e.g. GCP07 → id 7)", path=gcps.path)
    return ids


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


def gcp_find(
    images: Path,
    gcp_file: Path,
    output: Path,
    dictionary: Dictionary = "DICT_4X4_50",
    margin: float = 0.0,
    dsm: Path | None = None,
    takeoff_elevation_m: float | None = None,
    gcp_crs: CRS | None = None,
    crs: CRS | None = None,
    detections: Path | None = None,
    review: Path | None = None,
    marker_size_m: float = 1.0,
    position_uncertainty_m: float = 5.0,
    height_uncertainty_m: float = 5.0,
    attitude_uncertainty_deg: float = 3.0,
    workers: int = 0,
    target: FindTarget = "aruco",
    flight_height_m: float | None = None,
    *,
    feedback: Feedback | None = None,
) -> GcpFindResult:
    """Find coded GCP markers in the photos and write OpenDroneMap's gcp_list.txt.

    Predicts where each GCP appears in each photo from the photo metadata,
    detects the ArUco/AprilTag marker in a window there, and writes only
    detections whose id and position agree with the prediction. GCP names end
    in their marker id (``GCP07`` is marker 7).

    Parameters
    ----------
    images : Path
        Folder of photos.
    gcp_file : Path
        GCP coordinates: text with a CRS line, CSV with named columns,
        gcp_list.txt or OpenSfM ground_control_points.json.
    output : Path
        gcp_list.txt to write.
    dictionary : str
        Marker dictionary (OpenCV name: ArUco DICT_4X4_50 … or AprilTag DICT_APRILTAG_36H11 …).
    margin : float
        Reject detections whose centre is closer to the photo border than this, percent of its size.
    dsm : Path
        DSM or DTM (same vertical datum as the GCPs) for the camera heights.
    takeoff_elevation_m : float
        Ground elevation of the take-off point, in the vertical datum of the ground
        model (the DSM, the ground elevation or the GCPs). Default: worked out from the
        photos (absolute − relative altitude, checked against the
        ground model; else the ground under the flight), and said.
    gcp_crs : CRS
        CRS of the GCP file when it does not say.
    crs : CRS
        CRS of gcp_list.txt. Default: the GCP file's, or the photos' UTM zone if that is geographic.
    detections : Path
        Also write every candidate, found or not and why (GeoPackage or CSV).
    review : Path
        Also write a PNG contact sheet of every detection for a person to check.
    marker_size_m : float
        Side of the markers' black square, metres.
    position_uncertainty_m : float
        How far the photos' GPS positions may be off, metres (sizes the search windows).
    height_uncertainty_m : float
        How far the camera heights may be off, metres.
    attitude_uncertainty_deg : float
        How far the recorded gimbal attitude may be off, degrees.
    workers : int
        Processes for detection; 0 uses every core.
    target : str
        What the GCPs look like on the ground: aruco or apriltag (coded markers of the
        dictionary: decoded, and verified by model fit where the detector gives up),
        checkerboard (2 × 2 squares: its saddle point), cross (two bars: where their centre
        lines cross), circle (a disc: its ellipse's centre), or auto (each tried on the
        first photos; the one found most is used, and said). Targets without a code are
        told apart by position only: two GCPs predicted in one window are both refused.
    flight_height_m : float
        Flight height above the take-off ground, for photos whose altitudes give no height
        above ground (else they are searched whole).
    """
    fb = as_feedback(feedback)
    s_read, s_detect, s_write = split(fb, [1, 8, 1])
    gcps, ids, auto_kinds = _gcps_and_targets(gcp_file, gcp_crs, dictionary, target)
    uncertainty = dict(
        margin_pct=margin,
        position_uncertainty_m=position_uncertainty_m,
        height_uncertainty_m=height_uncertainty_m,
        attitude_uncertainty_deg=attitude_uncertainty_deg,
        marker_size_m=marker_size_m,
    )
    # The pool starts first: its workers import OpenCV while the metadata is read.
    paths = list_images(images)
    with process_pool(workers, len(paths), initializer=init_worker, min_items_for_pool=4) as pool:
        photos = read_photos(paths, require_gps=False, require_camera=False, feedback=s_read)
        if not photos.photos:
            raise InputError(f"no readable photo ({photos.summary()})", path=images)
        plan = _plan(photos.photos, gcps, ids, dsm, takeoff_elevation_m, flight_height_m, uncertainty, fb)
        s_read.progress(1.0)
        results, windows, offset_m, used, marker_m, searched_as = _search(
            plan, pool, workers, dictionary, ids, uncertainty, s_detect, target, auto_kinds
        )
        if used in CODED:
            results = _second_look(results, windows, plan, searched_as, used, pool, workers)
    work = plan.work

    frames = {p.image: (p.width_px, p.height_px) for p in photos.photos}
    observations = _judge(results, windows, ids, fb, frames, margin, coded=used in CODED)
    s_detect.progress(1.0)
    # ODM works in a projected CRS: a geographic GCP file is written in the photos' UTM zone.
    out_crs = crs if crs is not None else (work if gcps.crs.is_geographic and work is not None else gcps.crs)
    written = write_gcp_list(output, observations, gcps, out_crs)
    det_path = write_detections(detections, observations, gcps) if detections is not None else None
    review_path = (
        write_review(review, observations, {p.image: p.path for p in photos.photos}) if review is not None else None
    )
    _warn_counts(observations, fb)
    s_write.progress(1.0)
    accepted = [o for o in observations if o.status == DETECTED]
    fb.info(
        f"{len(accepted)} observations of {len({o.gcp for o in accepted})} GCPs in "
        f"{len({o.image for o in accepted})} photos ({len(observations)} candidates); {photos.summary()}"
    )
    n_gcps = len({o.gcp for o in accepted})
    return GcpFindResult(
        written,
        det_path,
        review_path,
        len(accepted),
        n_gcps,
        len(observations),
        crs_to_text(out_crs),
        offset_m,
        marker_m,
        searched_as if used in CODED else "",
    )


def _gcps_and_targets(
    gcp_file: Path, gcp_crs: CRS | None, dictionary: str, target: str
) -> tuple[Any, dict[str, int], tuple[str, ...]]:
    """The GCP file, each GCP's marker id, and the target kinds ``auto`` tries (none for a named
    target); a bad dictionary or target is refused before the file is read."""
    get_dictionary(dictionary)
    if target not in (*TARGETS, "auto"):
        raise InputError(f"unknown target {target!r}; choose one of {', '.join(TARGETS)}, auto")
    if target == "apriltag" and "APRILTAG" not in str(dictionary).upper():
        raise InputError(
            f"--target apriltag needs an AprilTag --dictionary (e.g. DICT_APRILTAG_36H11), not {dictionary}"
        )
    gcps = read_gcp_file(gcp_file, gcp_crs)
    if target != "auto":
        return gcps, _marker_ids(gcps, dictionary, target), ()
    coded = "apriltag" if "APRILTAG" in str(dictionary).upper() else "aruco"
    try:  # names ending in marker ids: coded markers are a candidate
        return gcps, _marker_ids(gcps, dictionary), (coded, "checkerboard", "cross", "circle")
    except InputError:
        return gcps, _marker_ids(gcps, dictionary, "checkerboard"), ("checkerboard", "cross", "circle")


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


def _plan(
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


Results = list[tuple[str, list[Detection], str, tuple[float, float]]]  # photo, found, error, its blur


def _search(
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
        if len({path for path, *_ in _decoded(quick, windows)}) >= 2 and offset_of(quick) is not None:
            pilot, results = more, quick
            rest = [im for im in searched if im not in set(pilot)]
    if target == "auto":
        target, results = _choose_target(pilot, windows, pilot_run, auto_kinds, s_pilot)
    elif results is None:
        results = pilot_run(pilot, target, s_pilot)
        if target in CODED and next(_decoded(results, windows), None) is None:
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
        if coded and any(_nearest(dets, k, w) is None for k, w in enumerate(windows[Path(path).name]))
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
    ratios = [r for _, d, win in _decoded(results, windows) if math.isfinite(r := side_ratio(d.corners_px, win))]
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
            if (f := _nearest(dets, k, win)) is not None and f[1] <= win.max_radius_px
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
    n = times * max(4, 2 * (workers or os.cpu_count() or 1))
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
            found = _nearest(dets, k, win)
            if found is None or found[1] > win.max_radius_px:
                continue
            d = found[0]
            if d.attempt == "fitted" and _closer_prediction(d, found[1], win, windows[image]):
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


def _second_look(
    results: Results,
    windows: dict[str, list[SearchWindow]],
    plan: _Plan,
    dictionary: str,
    target: str,
    pool: Executor | None,
    workers: int,
) -> Results:
    """Coded markers not found in a photo once every photo is searched, fitted again
    (:func:`.detect.second_look_task`): where the nearest photo that decoded them puts them
    (:func:`.detect.carried_place`), else in their whole window. A blurred photo often has no
    marker of its own found to place the others by; a sharp neighbour has. A marker so carried is
    taken as one placed by its photo's other markers (:func:`_placed`)."""
    donors: dict[str, list[tuple[str, Detection, SearchWindow]]] = {}
    for path, d, win in _decoded(results, windows):
        donors.setdefault(win.gcp, []).append((path, d, win))
    jobs: dict[str, list[CarryJob]] = {}
    for path, dets, error, _ in results:
        image = Path(path).name
        cam = plan.cams.get(image)
        if cam is None or error:
            continue
        for k, win in enumerate(windows.get(image, [])):
            if len(win.ground_px) != 4 or _nearest(dets, k, win):
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


def _nearest(dets: list[Detection], k: int, win: SearchWindow) -> tuple[Detection, float] | None:
    """The detection of window ``k``'s own id nearest its prediction, and how far it is (px)."""
    mine = [
        (d, math.hypot(d.x_px - win.x_px, d.y_px - win.y_px))
        for d in dets
        if d.window == k and d.marker_id == win.marker_id and not d.reason
    ]
    return min(mine, key=lambda de: de[1]) if mine else None


def _decoded(results: Results, windows: dict[str, list[SearchWindow]]) -> Iterator[tuple[str, Detection, SearchWindow]]:
    """Each window whose marker the detector decoded: (photo path, the detection, the window)."""
    for path, dets, *_ in results:
        for k, win in enumerate(windows.get(Path(path).name, [])):
            found = _nearest(dets, k, win)
            if found is not None and found[0].attempt not in ("verified", "fitted") and found[1] <= win.max_radius_px:
                yield path, found[0], win


def _decoded_gcps(results: Results, windows: dict[str, list[SearchWindow]]) -> set[str]:
    """GCPs whose marker the detector decoded in their window of some photo."""
    return {win.gcp for _, _, win in _decoded(results, windows)}


def _placed(dets: list[Detection], k: int, win: SearchWindow) -> tuple[Detection, float] | None:
    """A coded marker fitted where the photo's other markers put it, refused only because its code
    is too blurred to tell its id here (:func:`.detect.placed_by_others`): taken
    when its GCP's id was decoded in another photo. Its place is then the proof: another marker
    within a few pixels of where this one must be is no marker of the survey (they stand metres
    apart), and texture there does not reach the fit's score."""
    mine = [
        (d, math.hypot(d.x_px - win.x_px, d.y_px - win.y_px))
        for d in dets
        if d.window == k and d.marker_id == win.marker_id and placed_by_others(d)
    ]
    return min(mine, key=lambda de: de[1]) if mine else None


def _judge(
    results: Results,
    windows: dict[str, list[SearchWindow]],
    ids: dict[str, int],
    fb: Feedback,
    frames: dict[str, tuple[int, int]],
    margin_pct: float,
    *,
    coded: bool = True,
) -> list[Observation]:
    """Turn raw detections into accepted observations and rejected candidates."""
    by_id = {v: k for k, v in ids.items()}
    obs: list[Observation] = []
    decoded = _decoded_gcps(results, windows) if coded else set()
    for path, dets, error, photo_blur in results:
        image = Path(path).name
        if error:
            fb.warning(f"{image}: {error}")
        wins = windows.get(image, [])
        if not wins:  # searched whole: any id of the file, once
            obs += _judge_whole_photo(image, dets, by_id, photo_blur[0])
            continue
        for k, win in enumerate(wins):
            obs.append(
                _judge_window(image, k, win, wins, dets, decoded, photo_blur[0], frames[image], margin_pct, coded)
            )
        # markers seen whose id is in no GCP file: recorded, never written
        for mid in sorted({d.marker_id for d in dets if d.marker_id not in by_id and coded}):
            d = next(d for d in dets if d.marker_id == mid)
            obs.append(Observation(image, "", mid, WRONG_ID, x_px=d.x_px, y_px=d.y_px, attempt=d.attempt))
    if not coded:
        obs = _agree_within_photos(obs)
    return _one_per_gcp(obs)


def _judge_whole_photo(
    image: str, dets: list[Detection], by_id: dict[int, str], photo_blur: float
) -> list[Observation]:
    """A photo searched whole: each id of the GCP file once, any other id recorded as wrong."""
    obs: list[Observation] = []
    seen: dict[int, Detection] = {}
    for d in dets:
        if d.marker_id in by_id:
            seen.setdefault(d.marker_id, d)
        else:
            obs.append(Observation(image, "", d.marker_id, WRONG_ID, x_px=d.x_px, y_px=d.y_px, attempt=d.attempt))
    for mid, d in sorted(seen.items()):
        obs.append(
            Observation(
                image,
                by_id[mid],
                mid,
                DETECTED,
                x_px=d.x_px,
                y_px=d.y_px,
                attempt=d.attempt,
                side_px=d.side_px,
                corners_px=d.corners_px,
                method="decoded",
                photo_blur_px=photo_blur,
            )
        )
    return obs


def _judge_window(
    image: str,
    k: int,
    win: SearchWindow,
    wins: list[SearchWindow],
    dets: list[Detection],
    decoded: set[str],
    photo_blur: float,
    frame: tuple[int, int],
    margin_pct: float,
    coded: bool,
) -> Observation:
    """The verdict on window ``k``: its target found (and where), too far, in the margin,
    ambiguous, or not found with the best refused candidate's reason."""
    base: dict[str, Any] = dict(
        image=image,
        gcp=win.gcp,
        marker_id=win.marker_id if coded else -1,
        predicted_x_px=win.x_px,
        predicted_y_px=win.y_px,
        window_px=win.max_radius_px,
        photo_blur_px=photo_blur,
    )
    if win.ambiguous_with and not coded:
        return Observation(**base, status=AMBIGUOUS, reason=f"{win.ambiguous_with} is predicted in the same window")
    found = _nearest(dets, k, win)
    note = ""
    if found is None and win.gcp in decoded:
        found = _placed(dets, k, win)
        if found is not None:
            note = (
                f"id read in other photos (here {found[0].id_margin:.2f} over the next id), "
                "placed by this photo's other markers"
            )
    if found is None:
        refused = [d for d in dets if d.window == k and d.reason]
        why = max(refused, key=lambda d: d.score).reason if refused else "nothing like the target in the window"
        return Observation(**base, status=NOT_FOUND, reason=why)
    d, err = found
    status, reason = (DETECTED if err <= win.max_radius_px else TOO_FAR), note
    w, h = frame
    if status == DETECTED and not in_frame(d.x_px, d.y_px, w, h, w * margin_pct / 100.0, h * margin_pct / 100.0):
        status = IN_MARGIN
    if status == DETECTED and not coded:
        other = _closer_prediction(d, err, win, wins)
        if other:
            status, reason = AMBIGUOUS, f"the target found is as near {other}'s prediction"
    return Observation(
        **base,
        status=status,
        x_px=d.x_px,
        y_px=d.y_px,
        error_px=err,
        attempt=d.attempt,
        side_px=d.side_px,
        corners_px=d.corners_px,
        method=d.attempt if d.attempt in ("verified", "fitted") else "decoded",
        score=d.score,
        id_margin=d.id_margin,
        position_margin=d.position_margin,
        blur_px=d.blur_px,
        contrast_dn=d.contrast_dn,
        worst_part=d.worst_part,
        shape_margin=d.shape_margin,
        reason=reason,
    )


def _one_per_gcp(obs: list[Observation]) -> list[Observation]:
    """One detection per (image, GCP): windows of two GCPs can overlap."""
    seen_pairs: set[tuple[str, str]] = set()
    unique = []
    for o in obs:
        key = (o.image, o.gcp)
        if o.status == DETECTED:
            if key in seen_pairs:
                continue
            seen_pairs.add(key)
        unique.append(o)
    return unique


def _agree_within_photos(obs: list[Observation]) -> list[Observation]:
    """Targets without an id: in one photo, the pose's error moves every GCP's prediction nearly
    alike, so each fit's offset from its prediction must agree with the photo's other fits (within
    2.5 target sides, plus 3 % of the distance for a yaw or scale error). A fit that disagrees is
    refused; of two that disagree, both."""
    out = list(obs)
    by_image: dict[str, list[int]] = {}
    for i, o in enumerate(obs):
        if o.status == DETECTED:
            by_image.setdefault(o.image, []).append(i)
    for idx in by_image.values():
        if len(idx) < 2:
            continue
        off = np.array([[obs[i].x_px - obs[i].predicted_x_px, obs[i].y_px - obs[i].predicted_y_px] for i in idx])
        at = np.array([[obs[i].predicted_x_px, obs[i].predicted_y_px] for i in idx])
        for k, i in enumerate(idx):
            others = [j for j in range(len(idx)) if j != k]
            if len(others) >= 2:
                # the others' errors as a similarity (shift, rotation, scale: yaw and height errors)
                move, fit_px = fit_similarity(at[others], at[others] + off[others])
                expected = move(at[k : k + 1])[0] - at[k]
                dev = float(np.linalg.norm(off[k] - expected))
                tol = 2.5 * max(obs[i].side_px, 1.0) + float(fit_px)
            else:  # one other: a shift, with 3 % of the distance for a yaw or scale error
                dev = float(np.linalg.norm(off[k] - off[others[0]]))
                tol = 2.5 * max(obs[i].side_px, 1.0) + 0.03 * float(np.linalg.norm(at[others[0]] - at[k]))
            if dev > tol:
                out[i] = replace(
                    obs[i],
                    status=NOT_FOUND,
                    reason=f"{dev:.0f} px from where this photo's other targets put it (> {tol:.0f} px)",
                )
    return out


def _closer_prediction(d: Detection, err_px: float, win: SearchWindow, wins: list[SearchWindow]) -> str:
    """A target without an id belongs to the window only when no other GCP is predicted about as
    near it: another prediction within twice the own distance plus three target sides."""
    for o in wins:
        if o is win:
            continue
        if math.hypot(d.x_px - o.x_px, d.y_px - o.y_px) <= 2 * err_px + 3 * max(win.side_px, 1.0):
            return o.gcp
    return ""


def _warn_counts(observations: list[Observation], fb: Feedback) -> None:
    per_gcp: dict[str, int] = {}
    for o in observations:
        if o.status == DETECTED:
            per_gcp[o.gcp] = per_gcp.get(o.gcp, 0) + 1
    for g, n in sorted(per_gcp.items()):
        if n < 3:
            fb.warning(f"GCP {g} is seen in only {n} photo(s); OpenDroneMap wants at least 3")
    if len(per_gcp) < 3:
        fb.warning(f"only {len(per_gcp)} GCP(s) found; OpenDroneMap needs at least 3")


def write_gcp_list(path: Path, observations: list[Observation], gcps: GcpSet, crs: CRS) -> Path:
    """gcp_list.txt as OpenDroneMap reads it: CRS line, then ``x y z px py image name``."""

    t = transformer(gcps.crs, crs)
    by_name = gcps.by_name()
    lines = [crs_to_text(crs)]
    geographic = crs.is_geographic
    for o in sorted((o for o in observations if o.status == DETECTED), key=lambda o: (o.gcp, o.image)):
        g = by_name[o.gcp]
        x, y = t.transform(g.x, g.y)
        fmt = "{:.9f} {:.9f}" if geographic else "{:.4f} {:.4f}"
        lines.append(f"{fmt.format(x, y)} {g.z:.4f} {o.x_px:.3f} {o.y_px:.3f} {o.image} {o.gcp}")
    return write_text(path, "\n".join(lines) + "\n")


def write_detections(path: Path, observations: list[Observation], gcps: GcpSet) -> Path:
    """Every candidate as a table: GeoPackage (points at the GCP) or CSV, by extension."""
    import geopandas as gpd
    import shapely

    by_name = gcps.by_name()
    rows: list[dict[str, Any]] = []
    for o in observations:
        r = {k: getattr(o, k) for k in Observation.__dataclass_fields__ if k != "corners_px"}
        r["corners_px"] = ";".join(f"{x:.3f} {y:.3f}" for x, y in o.corners_px)
        rows.append(r)
    path = Path(path)
    if path.suffix.lower() == ".csv":
        import csv
        import io

        buf = io.StringIO()
        wr = csv.DictWriter(buf, fieldnames=list(rows[0]) if rows else ["image"])
        wr.writeheader()
        wr.writerows(rows)
        return write_text(path, buf.getvalue())
    geoms = [shapely.Point(by_name[o.gcp].x, by_name[o.gcp].y) if o.gcp in by_name else None for o in observations]
    gdf = gpd.GeoDataFrame(rows, geometry=geoms, crs=gcps.crs)
    return write_vector(path, {"detections": gdf}, styles=product_styles("detections"))


def write_review(
    path: Path, observations: list[Observation], paths: dict[str, Path], crop_px: int = 128, columns: int = 8
) -> Path:
    """PNG contact sheet: a crop around each detection, centre marked, labelled GCP / image; model
    fits are marked (V verified on blue, F fitted on orange, a yellow centre), decoded ones plain."""
    import cv2

    accepted = [o for o in observations if o.status == DETECTED]
    tiles = []
    cache: dict[str, np.ndarray] = {}
    half = crop_px // 2
    for o in sorted(accepted, key=lambda o: (o.gcp, o.image)):
        img = cache.get(o.image)
        if img is None:
            cache.clear()  # one photo in memory at a time (observations are sorted by GCP)
            read = cv2.imread(str(paths[o.image]), cv2.IMREAD_COLOR)
            if read is None:
                continue  # a photo that cannot be read again is left off the contact sheet
            img = cache[o.image] = read
        # crop scaled so the marker fills about half the tile
        scale = max(1.0, (crop_px * 0.5) / max(o.side_px, 1.0))
        m = np.array([[scale, 0, half - scale * o.x_px], [0, scale, half - scale * o.y_px]])
        tile = cv2.warpAffine(img, m, (crop_px, crop_px + 18), flags=cv2.INTER_LINEAR, borderValue=(40, 40, 40))
        # a person checks verified and fitted detections (model fits, no id decoded) first:
        # their label says so, on a colour of its own
        look = {"verified": ("V ", (160, 60, 0), (0, 255, 255)), "fitted": ("F ", (0, 90, 200), (0, 255, 255))}
        prefix, bar_bgr, mark_bgr = look.get(o.method, ("", (0, 0, 0), (0, 0, 255)))
        cv2.drawMarker(tile, (half, half), mark_bgr, cv2.MARKER_CROSS, 14, 1)
        label = f"{prefix}{o.gcp} {Path(o.image).stem}"[:22]
        cv2.rectangle(tile, (0, crop_px), (crop_px, crop_px + 18), bar_bgr, -1)
        cv2.putText(tile, label, (2, crop_px + 13), cv2.FONT_HERSHEY_SIMPLEX, 0.35, (255, 255, 255), 1, cv2.LINE_AA)
        tiles.append(tile)
    if not tiles:
        tiles = [np.zeros((crop_px + 18, crop_px, 3), np.uint8)]
    rows = [tiles[i : i + columns] for i in range(0, len(tiles), columns)]
    blank = np.zeros_like(tiles[0])
    sheet = np.vstack([np.hstack(r + [blank] * (columns - len(r))) for r in rows])
    with atomic_path(path) as tmp:
        ok, buf = cv2.imencode(".png", sheet)
        if not ok:
            raise InputError("cannot encode the review sheet", path=path)
        Path(tmp).write_bytes(buf.tobytes())
    return Path(path)
