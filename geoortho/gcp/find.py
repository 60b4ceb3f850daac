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

Here: :func:`gcp_find` and its result. Beside it: :mod:`.pilot` (steps 1-3: the windows, the pilot
photos, the flight's offset, the search), :mod:`.verdicts` (step 4) and :mod:`.find_outputs`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from pyproj import CRS

from geoortho.core.crs import crs_to_text
from geoortho.core.parallel import process_pool
from geoortho.errors import InputError
from geoortho.feedback import Feedback, as_feedback, split
from geoortho.gcp.detect import (
    init_worker,
)
from geoortho.gcp.find_outputs import write_detections, write_gcp_list, write_review
from geoortho.gcp.io import GcpSet, marker_id_of, read_gcp_file
from geoortho.gcp.markers import CODED, TARGETS, Dictionary, FindTarget, get_dictionary
from geoortho.gcp.pilot import plan_search, predict_windows, search_photos, second_look
from geoortho.gcp.verdicts import DETECTED, Observation, judge_candidates, warn_counts
from geoortho.photos.metadata import list_images, read_photos

__all__ = ["GcpFindResult", "gcp_find", "Observation", "predict_windows"]


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
        plan = plan_search(photos.photos, gcps, ids, dsm, takeoff_elevation_m, flight_height_m, uncertainty, fb)
        s_read.progress(1.0)
        results, windows, offset_m, used, marker_m, searched_as = search_photos(
            plan, pool, workers, dictionary, ids, uncertainty, s_detect, target, auto_kinds
        )
        if used in CODED:
            results = second_look(results, windows, plan, searched_as, used, pool, workers)
    work = plan.work

    frames = {p.image: (p.width_px, p.height_px) for p in photos.photos}
    observations = judge_candidates(results, windows, ids, fb, frames, margin, coded=used in CODED)
    s_detect.progress(1.0)
    # ODM works in a projected CRS: a geographic GCP file is written in the photos' UTM zone.
    out_crs = crs if crs is not None else (work if gcps.crs.is_geographic and work is not None else gcps.crs)
    written = write_gcp_list(output, observations, gcps, out_crs)
    det_path = write_detections(detections, observations, gcps) if detections is not None else None
    review_path = (
        write_review(review, observations, {p.image: p.path for p in photos.photos}) if review is not None else None
    )
    warn_counts(observations, fb)
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
