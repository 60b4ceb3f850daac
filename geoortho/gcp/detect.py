"""Coded-marker detection in a window of a photo, with retries, and the marker centre.

Runs in worker processes: everything here takes and returns plain data. The second look's task
(a missed marker carried from a photo that decoded it) is beside it, in :mod:`.carry`.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace

import cv2
import numpy as np

from geoortho.core.camera import in_frame
from geoortho.gcp.blur import deblurred, estimate_motion_blur
from geoortho.gcp.markers import CODED, get_dictionary, marker_cells, target_half_extent
from geoortho.gcp.refine import SATURATED
from geoortho.gcp.targets import PLACED_ID_MARGIN, fit_target
from geoortho.photos.metadata import decode_photo

__all__ = [
    "Detection",
    "SearchWindow",
    "detect_in_image",
    "detect_task",
    "fit_missed",
    "search_wide",
    "ground_turn",
    "init_worker",
    "marker_centre",
    "diagonal_intersection",
    "ATTEMPTS",
]

#: Tried in order on each window until the expected marker is found. "fast" thresholds at the
#: one scale the predicted marker size calls for (5x cheaper than OpenCV's three scales);
#: "deblur" reads a blurred photo with its blur undone (only there: see :func:`_attempts`).
ATTEMPTS = ("fast", "deblur", "plain", "clahe", "upscale", "glare")


@dataclass(frozen=True)
class SearchWindow:
    """Where to look: a square around a predicted pixel. ``radius_px`` 0 = the whole photo.

    ``wide_radius_px`` (when larger) is searched too if the marker is not in the
    first square and the prediction lies in the frame: the first square is sized
    from the flight's measured errors, the wide one from the stated uncertainty.
    """

    gcp: str
    marker_id: int
    x_px: float
    y_px: float
    radius_px: float
    side_px: float = 0.0  # expected marker side; 0 = unknown
    wide_radius_px: float = 0.0
    #: pixels per marker side along east and north at the GCP (row-major 2 × 2); () = unknown
    ground_px: tuple[float, ...] = ()
    #: another GCP predicted inside this window (targets without an id are then refused)
    ambiguous_with: str = ""

    @property
    def max_radius_px(self) -> float:
        return max(self.radius_px, self.wide_radius_px)


@dataclass(frozen=True)
class Detection:
    marker_id: int
    x_px: float  # centre, pixel-centre convention, whole-photo coordinates
    y_px: float
    corners_px: tuple[tuple[float, float], ...]
    attempt: str  # the detector attempt that decoded it, or "verified"/"fitted" (model fit)
    window: int  # index of the window it was found in (-1: whole photo)
    side_px: float
    score: float = math.nan  # model fit: normalised correlation
    id_margin: float = math.nan
    position_margin: float = math.nan
    blur_px: float = math.nan  # model fit: motion blur length at the target
    contrast_dn: float = math.nan  # model fit: white − black, grey levels
    worst_part: float = math.nan  # model fit, no id: largest mean residual over a part / contrast
    shape_margin: float = math.nan  # model fit, no id: over the best plain edge, bar, corner or blob
    reason: str = ""  # model fit refused: why (the detection is then not a find)
    refused_on: str = ""  # model fit refused: the threshold it failed first (targets.Fit.refused_on)
    near_px: float = math.nan  # searched within this of where the photo's other markers put it


def diagonal_intersection(corners: np.ndarray) -> np.ndarray:
    """Where the diagonals of a quadrilateral cross: the projection of a planar square's centre."""
    c = np.asarray(corners, float).reshape(4, 2)
    p, r = c[0], c[2] - c[0]
    q, s = c[1], c[3] - c[1]
    denom = r[0] * s[1] - r[1] * s[0]
    if abs(denom) < 1e-12:
        result: np.ndarray = c.mean(axis=0)
        return result
    t = ((q[0] - p[0]) * s[1] - (q[1] - p[1]) * s[0]) / denom
    result = p + t * r
    return result


def marker_centre(corners: np.ndarray) -> np.ndarray:
    """Centre of a marker from its four refined corners.

    The diagonals cross at the exact projected centre, but an intersection of
    two lines magnifies corner noise; the mean of the corners halves the noise
    but is biased by perspective. Measured on the synthetic ``small`` survey
    (near nadir): mean 0.14 px, diagonals 0.25 px mean error. So: the mean,
    moving to the diagonals as the two part (strong perspective, where the
    mean's bias exceeds the noise).
    """
    c = np.asarray(corners, float).reshape(4, 2)
    mean = c.mean(axis=0)
    diag = diagonal_intersection(c)
    gap = float(np.hypot(*(diag - mean)))
    w = min(1.0, max(0.0, (gap - 0.2) / 0.6))
    result: np.ndarray = mean + w * (diag - mean)
    return result


def _detector(
    dictionary: str,
    glare: bool = False,
    threshold_win_px: int = 0,
    refine: int = cv2.aruco.CORNER_REFINE_CONTOUR,
    min_perimeter_rate: float = 0.0,
) -> cv2.aruco.ArucoDetector:
    params = cv2.aruco.DetectorParameters()
    if threshold_win_px:
        params.adaptiveThreshWinSizeMin = params.adaptiveThreshWinSizeMax = threshold_win_px
    # OpenCV's default (3 % of the image's larger side) lets a small window's specks of a few
    # pixels through as candidates: 4.1 of a window's 4.6 ms (161 px, a 25 px marker)
    params.minMarkerPerimeterRate = max(params.minMarkerPerimeterRate, min_perimeter_rate)
    params.cornerRefinementMethod = refine
    params.cornerRefinementWinSize = 3
    params.cornerRefinementMaxIterations = 50
    params.cornerRefinementMinAccuracy = 0.01
    if glare:
        # A bright spot washes out part of the quiet zone and cells: look at more
        # threshold scales, accept less contrast and a few more wrong border bits.
        params.adaptiveThreshWinSizeMin = 5
        params.adaptiveThreshWinSizeMax = 53
        params.adaptiveThreshWinSizeStep = 4
        params.adaptiveThreshConstant = 3
        params.maxErroneousBitsInBorderRate = 0.5
        params.minOtsuStdDev = 2.0
    return cv2.aruco.ArucoDetector(get_dictionary(dictionary), params)


def _run(
    gray: np.ndarray, attempt: str, dictionary: str, side_px: float = 0.0, blur: tuple[float, float] | None = None
) -> list[tuple[int, np.ndarray]]:
    scale = 1.0
    img = gray
    win = 0
    if attempt == "fast":
        # about three marker cells (a 4x4 marker with its border is 6 cells wide)
        win = int(np.clip(side_px / 4, 3, 51)) | 1
    if attempt == "clahe":
        img = cv2.createCLAHE(clipLimit=3.0, tileGridSize=(4, 4)).apply(gray)
    elif attempt == "upscale":
        scale = 2.0
        img = cv2.resize(gray, None, fx=scale, fy=scale, interpolation=cv2.INTER_CUBIC)
    elif attempt == "deblur":
        # the photo's motion blur undone (a Wiener filter), and twice the pixels: a 15 px marker
        # blurred by 4-10 px reads again (targets.deblurred)
        if blur is None or blur[0] < DEBLUR_FROM_PX:
            return []
        scale = 2.0
        img = cv2.resize(deblurred(gray, blur), None, fx=scale, fy=scale, interpolation=cv2.INTER_CUBIC)
    elif attempt == "glare":
        # compress the highlights so a glare spot does not swamp the threshold
        lut = (255.0 * (np.arange(256) / 255.0) ** 1.8).astype(np.uint8)
        img = cv2.LUT(gray, lut)
    glare = attempt == "glare"
    # No quad under half the predicted side is kept (plausible_quad), and a quad's perimeter is at
    # least 4 sqrt(its area): candidates shorter than 2 sides (with a fifth off for blur) are skipped
    rate = 1.6 * side_px * scale / max(img.shape[:2]) if side_px > 0 else 0.0
    try:
        corners, ids, _ = _detector(dictionary, glare, win, min_perimeter_rate=rate).detectMarkers(img)
    except cv2.error:
        # OpenCV's contour refinement asserts on some degenerate candidates (seen on the toledo
        # photos: "nContours.size() >= 2"); its corner sub-pixel refinement does not
        refine = cv2.aruco.CORNER_REFINE_SUBPIX
        corners, ids, _ = _detector(dictionary, glare, win, refine, min_perimeter_rate=rate).detectMarkers(img)
    if ids is None:
        return []
    out = []
    for i, c in zip(ids.ravel(), corners):
        c = c.reshape(4, 2).astype(float)
        if scale != 1.0:
            # pixel centres: x_small = (x_big + 0.5) / s - 0.5
            c = (c + 0.5) / scale - 0.5
        out.append((int(i), c))
    return out


#: A photo blurred by this many marker sides or more is searched by the detector's "fast" attempt
#: and, where that reads nothing, with its blur undone ("deblur"). The other attempts read nothing
#: the fits do not find: on four degraded small surveys (14-16 px markers) nothing in 540 runs,
#: "glare" 2 of 306; on a planned degraded flight (105 photos) "glare" 0 of 105, in 0.66 s of a
#: worker's 18 s, and without it gcp_list.txt is the same on eight degraded surveys and a clean one.
SMEARED = 0.4

#: A photo blurred by this many pixels or more (and less than :data:`SMEARED`) is searched with its
#: blur undone ("deblur") right after the "fast" attempt, and by the other attempts where that
#: reads nothing. Its read spares a fit as in a smeared photo: on a degraded flight 21 fits of
#: 83 ms each were so read. On eight degraded surveys, recall +1 and +2 on two, -1 on one (a fit
#: at its score threshold), the same on five; the mean centre error 0.001-0.011 px lower on six,
#: 0.002-0.004 px higher on two.
DEBLUR_FROM_PX = 2.0


def detect_in_image(
    gray: np.ndarray,
    windows: list[SearchWindow],
    dictionary: str,
    attempts: tuple[str, ...] = ATTEMPTS,
    target: str = "aruco",
    blur: tuple[float, float] | None = None,
    fit: bool = True,
) -> list[Detection]:
    """Detect markers in each window (the whole image when ``radius_px`` is 0).

    Coded targets: retries go on until the window's expected id is decoded; every marker
    seen on the way is returned, so the caller can judge wrong ids too. Where none decodes,
    the expected marker is verified by fitting its model (:mod:`.targets`; :func:`fit_missed`),
    and only then is its wide window searched (:func:`search_wide`). Targets without a code are
    fitted in every window. ``blur``: the photo's motion blur (estimated when needed). ``fit``
    False: coded markers by the detector alone, in their own windows (:func:`second_look_task`
    fits them once every photo has been searched, then searches the wide windows).
    """
    h, w = gray.shape[:2]
    coded = target in CODED
    found: list[Detection] = []
    missed: list[int] = []
    unseen: list[int] = []  # coded windows the detector missed
    tries = [_attempts(attempts, blur, win.side_px) for win in windows]
    for k, win in enumerate(windows):
        if win.radius_px <= 0:
            if not coded:
                continue  # no prediction, no id: nothing to tell a target by
            # A whole photo has no expected id: run the cheap attempts and keep all they see.
            cheap = tuple(a for a in attempts if a in ("plain", "clahe"))
            _search(gray, (0, 0, w, h), win, cheap, dictionary, -1, found, stop_at_id=False)
            continue
        if coded:
            if not _search(gray, _square(win, win.radius_px, w, h), win, tries[k], dictionary, k, found, blur=blur):
                unseen.append(k)
            continue
        if win.ambiguous_with:
            continue
        missed.append(k)
    if not coded:
        return fit_missed(gray, windows, found, missed, target, dictionary, blur)
    if not fit:
        return found  # the fits, then the wide windows, in the second look (second_look_task)
    found = fit_missed(gray, windows, found, unseen, target, dictionary, blur)
    return search_wide(gray, windows, found, unseen, dictionary, blur, attempts)


def search_wide(
    gray: np.ndarray,
    windows: list[SearchWindow],
    found: list[Detection],
    ks: Sequence[int],
    dictionary: str,
    blur: tuple[float, float] | None,
    attempts: tuple[str, ...] = ATTEMPTS,
) -> list[Detection]:
    """The wide windows of coded windows ``ks`` whose marker is still not found, searched by the
    detector (``attempts`` by the photo's ``blur``, as in the window's own); its finds added to
    ``found`` (returned).

    The wide window is for a marker the prediction missed by more than the measured residual (a
    pose off), and it is never fitted (see _fit_model). It comes last, after the fits in the
    marker's own window, and not where the photo's markers found so far place it well inside
    that window: it is there, not decoded (blur, glare). Searched before the fits, on a flight
    rendered with shaken blur 38 wide windows cost 2.3 s of 8.5 s and read 2 markers, both inside
    their own window; on two degraded small surveys 122 decoded nothing, in 7.1 s."""
    h, w = gray.shape[:2]
    for k in ks:
        win = windows[k]
        if (
            win.wide_radius_px > win.radius_px
            and in_frame(win.x_px, win.y_px, w, h)
            and not _settled(found, windows, k)
            and not _placed_inside(windows, found, k)
        ):
            box = _square(win, win.wide_radius_px, w, h)
            _search(gray, box, win, _attempts(attempts, blur, win.side_px), dictionary, k, found, blur=blur)
    return found


def _settled(found: list[Detection], windows: list[SearchWindow], k: int) -> bool:
    """Is window ``k``'s marker found: accepted, or placed by the photo's other markers?"""
    return any(d.window == k and (accepted_in(d, windows[k]) or placed_by_others(d)) for d in found)


def _attempts(attempts: tuple[str, ...], blur: tuple[float, float] | None, side_px: float) -> tuple[str, ...]:
    """The detector's attempts for a coded window, of ``attempts`` (in their order), by the
    photo's motion blur (px): in a smeared photo the fast one and the blur undone; in a blurred
    one all; in a sharp one all but the blur undone (there is none to undo)."""
    if blur is None or blur[0] < DEBLUR_FROM_PX:
        return tuple(a for a in attempts if a != "deblur")
    if blur[0] >= SMEARED * side_px:
        return tuple(a for a in attempts if a in ("fast", "deblur"))
    return attempts


def _placed_inside(windows: list[SearchWindow], found: list[Detection], k: int) -> bool:
    """Do the photo's markers found so far place window ``k``'s marker, with its tolerance and
    its own half side, inside the window's (narrow) square? (:func:`local_prediction`)"""
    local = local_prediction(windows, found, k)
    if local is None:
        return False
    x, y, tolerance_px = local
    win = windows[k]
    reach = max(abs(x - win.x_px), abs(y - win.y_px)) + tolerance_px + 0.5 * win.side_px
    return reach <= win.radius_px


#: Saturated pixels, in marker areas, that make a window's glare a cause for the detector to miss
#: a whole marker (:func:`fit_missed`): near-edge fits in sharp photos of ten surveys found a
#: marker at 0.72 areas and none under 0.18; a clipped white cell or a car's glint is less.
GLARE_AREA = 0.1


def fit_missed(
    gray: np.ndarray,
    windows: list[SearchWindow],
    found: list[Detection],
    missed: Sequence[int],
    target: str,
    dictionary: str,
    blur: tuple[float, float] | None,
    carried: dict[int, tuple[float, float, float]] | None = None,
    turns: dict[int, float] | None = None,
) -> list[Detection]:
    """Windows ``missed`` (indices) fitted by their target's model, their fits and refusals
    added to ``found`` (returned).

    Coded markers: where two markers of the photo are found, only within a few pixels of where
    they put it (:func:`local_prediction`; on the blurred small surveys the window's prediction
    is 6-29 px off, theirs 0.3-1.9 px); else where a photo that decoded it puts it
    (``carried``: window -> (x, y, tolerance); :func:`carried_place`); only then in the whole
    window (its narrow one: the wide one is the detector's). A marker fitted so is an anchor for
    the rest. The whole-window fits come last because they cost most and fail most: on a
    degraded small survey, 29 of 50 failed at 0.65 s each, where a carried fit costs a fifth of
    that. ``turns``: window -> the marker's turn on the ground, where a photo decoded it
    (:func:`ground_turn`): its fits try only the rotations near it."""
    h, w = gray.shape[:2]
    coded = target in CODED
    to_fit: list[int] = []
    for k in missed:
        win = windows[k]
        # A target is kept only where the fit lies wholly in the photo: one cut by the frame cannot
        # be told from texture. One predicted nearer the edge than half its side may still be
        # whole (the prediction errs by a few sides): targets without a code are fitted in every
        # window; a coded one only where the detector had cause to miss a whole one (a blurred
        # photo, glare in the window: saturated pixels over a tenth of a marker's area, not a few
        # clipped ones). On a sharp, glare-free photo a coded miss there is a marker cut by the
        # frame; its fit would cost seconds (a clean flight's one such fit, at 6 saturated pixels,
        # held a worker 0.6 s, a third of the run, to refuse it as cut).
        # A coded marker predicted just beyond the edge may lie just inside it: see beyond_edge_px.
        off = -beyond_edge_px(win) if coded else 0.0
        if len(win.ground_px) != 4 or not in_frame(win.x_px, win.y_px, w, h, off, off):
            continue
        if blur is None:
            blur = estimate_motion_blur(gray)
        half = 0.5 * win.side_px
        if coded and not in_frame(win.x_px, win.y_px, w, h, half, half):
            x0, y0, x1, y1 = _square(win, win.radius_px, w, h)
            glare = int((gray[y0:y1, x0:x1] >= SATURATED).sum()) >= GLARE_AREA * win.side_px**2
            if not (blur[0] >= 2.0 or glare):
                continue
        to_fit.append(k)
    if not to_fit:
        return found
    assert blur is not None
    if not coded:
        for k in to_fit:
            _fit_model(gray, windows[k], k, target, dictionary, blur, found)
        return found
    carried, turns = carried or {}, turns or {}
    tried: dict[int, set[str]] = {k: set() for k in to_fit}  # "carried", "near", "wide"

    for last_resort in (False, True):
        while True:
            progress = False
            for k in to_fit:
                if _settled(found, windows, k):
                    continue
                local = local_prediction(windows, found, k)
                if local is not None and local[2] > 0.5 * windows[k].side_px:
                    local = None  # the photo's markers disagree: they place nothing
                # the carried place first: the ground of a 113 px square places a 14 px marker
                # better than two blurred markers' similarity (a marker lost on a degraded survey)
                if k in carried and "carried" not in tried[k]:
                    how, local = "carried", carried[k]
                elif local is not None and "near" not in tried[k]:
                    how = "near"
                elif last_resort and not tried[k]:
                    how = "wide"
                else:
                    continue
                tried[k].add(how)
                found[:] = [d for d in found if not (d.window == k and d.reason)]  # the new fit says why
                _fit_model(gray, windows[k], k, target, dictionary, blur, found, local, turns.get(k))
                progress |= _settled(found, windows, k)
            if not progress:
                break
    return found


def beyond_edge_px(win: SearchWindow) -> float:
    """How far (px) beyond the photo's edge a coded marker may be predicted and still be fitted: the
    prediction errs by more than a side, so one predicted just beyond may lie just inside, its id
    proving it (a degraded flight of 105 photos: 6 of 22 markers missed were so). Its window's
    radius, two sides at most."""
    return min(win.radius_px, 2.0 * win.side_px)


def place_tolerance(win: SearchWindow) -> float:
    """How far (px) a marker may lie from where another photo's ground puts it: 0.18 of a side,
    2.5 px at least (a blurred marker's fit slides along the blur, and 3 px off is a wrong place
    for a 14 px marker)."""
    return max(0.18 * win.side_px, 2.5)


def accepted_in(d: Detection, win: SearchWindow) -> bool:
    """A detection that finds the window's marker: its id, no refusal, inside the window."""
    return (
        d.marker_id == win.marker_id
        and not d.reason
        and math.hypot(d.x_px - win.x_px, d.y_px - win.y_px) <= win.max_radius_px
    )


def placed_by_others(d: Detection) -> bool:
    """A fit where the photo's other markers (or a photo that decoded it) put it, refused only
    because its code is too blurred to tell its id here: the marker, when its id was decoded in
    another photo (the caller's to know)."""
    return d.refused_on == "id_margin" and math.isfinite(d.near_px) and d.id_margin >= PLACED_ID_MARGIN


def local_prediction(windows: list[SearchWindow], found: list[Detection], k: int) -> tuple[float, float, float] | None:
    """Where the photo's markers found so far put window ``k``'s marker, and how far from there
    it may be (px): their offsets from their predictions as a similarity (shift, rotation, scale:
    the pose's position, yaw and height errors move every prediction alike). Needs two markers;
    None without. The tolerance is a quarter of a marker side, or three pixels and three times the
    similarity's worst residual, whichever is more (measured on the small survey's blurred photos:
    0.3-1.9 px from the truth, against 6-29 px for the prediction itself)."""
    anchors: dict[int, Detection] = {}
    for d in found:
        if d.window != k and d.window >= 0 and accepted_in(d, windows[d.window]):
            anchors.setdefault(d.window, d)
    if len(anchors) < 2:
        return None
    at = np.array([[windows[j].x_px, windows[j].y_px] for j in anchors])
    to = np.array([[d.x_px, d.y_px] for d in anchors.values()])
    move, worst_px = fit_similarity(at, to)
    win = windows[k]
    x, y = move(np.array([[win.x_px, win.y_px]]))[0]
    return float(x), float(y), max(0.25 * win.side_px, 3.0 + 3.0 * worst_px)


def fit_similarity(at: np.ndarray, to: np.ndarray) -> tuple[Callable[[np.ndarray], np.ndarray], float]:
    """The similarity (shift, rotation, scale) taking points ``at`` (n × 2) nearest ``to`` by least
    squares, as a function of n × 2 points, and its worst residual along x or y (px). In one photo,
    the pose's position, yaw and height errors move every prediction by such a map."""
    n = len(at)
    a = np.r_[
        np.c_[at[:, 0], -at[:, 1], np.ones(n), np.zeros(n)],
        np.c_[at[:, 1], at[:, 0], np.zeros(n), np.ones(n)],
    ]
    b = np.r_[to[:, 0], to[:, 1]]
    q, *_ = np.linalg.lstsq(a, b, rcond=None)

    def move(p: np.ndarray) -> np.ndarray:
        result: np.ndarray = np.c_[q[0] * p[:, 0] - q[1] * p[:, 1] + q[2], q[1] * p[:, 0] + q[0] * p[:, 1] + q[3]]
        return result

    return move, float(np.abs(a @ q - b).max())


def _fit_model(
    gray: np.ndarray,
    win: SearchWindow,
    k: int,
    target: str,
    dictionary: str,
    blur: tuple[float, float],
    found: list[Detection],
    local: tuple[float, float, float] | None = None,
    turn_deg: float | None = None,
) -> None:
    """The target by model fit, appended to ``found`` (refusals too, with their reason): in its
    window, then (targets without a code) the wide one; or, given ``local``
    (:func:`local_prediction`), only around where the photo's other markers put it (``turn_deg``:
    see :func:`.targets.fit_target`)."""
    h, w = gray.shape[:2]
    if local is None:
        radii = [win.radius_px]
        if win.wide_radius_px > win.radius_px and target not in CODED:
            # (a coded marker's wide window is the detector's: 0 of 21 fits there found a marker on
            # nine degraded surveys, at 0.45 s each, every miss inside its own window)
            radii.append(win.wide_radius_px)
        for radius in radii:
            d = _fit(gray, win, k, _square(win, radius, w, h), target, dictionary, blur)
            if d is not None:
                found.append(d)
                if not d.reason:
                    break
        return
    x, y, tol = local
    # the box holds the coarse search's template (search.coarse_search) centred anywhere within tol
    base = np.abs(np.array(win.ground_px, float).reshape(2, 2)).sum(axis=1).max()
    reach = base * target_half_extent(target) * 1.2 + blur[0] / 2 + 3
    box = _square(replace(win, x_px=x, y_px=y), tol + reach, w, h)
    d = _fit(gray, win, k, box, target, dictionary, blur, local, turn_deg)
    if d is None:
        return
    off = math.hypot(d.x_px - x, d.y_px - y)
    if off > tol:  # (refused for this first: the place is what a near search stands on)
        why = f"{off:.1f} px from where this photo's other markers put it (> {tol:.1f} px)"
        d = replace(d, reason=why, refused_on="place")
    found.append(replace(d, near_px=tol))


def _fit(
    gray: np.ndarray,
    win: SearchWindow,
    k: int,
    box: tuple[int, int, int, int],
    target: str,
    dictionary: str,
    blur: tuple[float, float],
    near: tuple[float, float, float] | None = None,
    turn_deg: float | None = None,
) -> Detection | None:
    """The window's target by model fit, as a detection (refused ones carry their reason);
    ``near``: see :func:`.targets.fit_target`."""

    coded = target in CODED
    cells = marker_cells(dictionary, win.marker_id) if coded else None
    base = np.array(win.ground_px, float).reshape(2, 2)
    fit = fit_target(
        gray,
        box,
        target,
        base,
        cells=cells,
        dictionary=dictionary if coded else "",
        marker_id=win.marker_id,
        blur=blur,
        predicted_xy=(win.x_px, win.y_px),
        near=near,
        turn_deg=turn_deg,
    )
    if fit is None:
        return None
    reason = fit.reason
    corners = np.array(fit.corners_px)
    if not reason and not np.all(in_frame(corners[:, 0], corners[:, 1], gray.shape[1], gray.shape[0], 1, 1)):
        reason = f"the {'marker' if coded else target} fitted is cut by the photo's edge"
    side = float(np.sqrt(abs(cv2.contourArea(corners.astype(np.float32)))))
    return Detection(
        win.marker_id,
        fit.x_px,
        fit.y_px,
        fit.corners_px,
        "verified" if coded else "fitted",
        k,
        side,
        fit.score,
        fit.id_margin,
        fit.position_margin,
        fit.blur_px,
        fit.contrast_dn,
        fit.worst_part,
        fit.shape_margin,
        reason,
        fit.refused_on if reason == fit.reason else "edge",
    )


def _square(win: SearchWindow, radius_px: float, w: int, h: int) -> tuple[int, int, int, int]:
    x0 = int(max(0, np.floor(win.x_px - radius_px)))
    y0 = int(max(0, np.floor(win.y_px - radius_px)))
    x1 = int(min(w, np.ceil(win.x_px + radius_px) + 1))
    y1 = int(min(h, np.ceil(win.y_px + radius_px) + 1))
    return x0, y0, x1, y1


def plausible_quad(corners: np.ndarray, win: SearchWindow) -> bool:
    """A decoded quadrilateral shaped like a marker: convex, opposite sides within 1.5x of each
    other (a small square seen in perspective is near a parallelogram, however foreshortened);
    where the window predicts the view, no more than 1.6x as uneven as predicted (and 2x allowed)
    and its size within 2x of the predicted side. Weak dictionaries (AprilTag 16h5: 5 bits apart)
    decode texture beside a real marker as a skewed quad (sides 37, 9.5, 32, 35 px); no marker
    looks like that, while a phone's low view of one is 88 x 38 px and stays."""
    c = np.asarray(corners, float).reshape(4, 2)
    sides = np.linalg.norm(np.roll(c, -1, axis=0) - c, axis=1)
    if sides.min() <= 0 or not cv2.isContourConvex(c.astype(np.float32)):
        return False
    if max(sides[0], sides[2]) > 1.5 * min(sides[0], sides[2]) or max(sides[1], sides[3]) > 1.5 * min(
        sides[1], sides[3]
    ):
        return False
    if len(win.ground_px) == 4:
        m = np.asarray(win.ground_px, float).reshape(2, 2)
        a, b = np.linalg.norm(m[:, 0]), np.linalg.norm(m[:, 1])
        expected = max(a, b) / min(a, b) if min(a, b) > 0 else 1.0
        uneven = float(sides.max() / sides.min())
        if uneven > 2.0 and uneven > 1.6 * expected:
            return False
    if win.side_px > 0:
        side = math.sqrt(abs(float(cv2.contourArea(c.astype(np.float32)))))
        if not 0.5 <= side / win.side_px <= 2.0:
            return False
    return True


def _search(
    gray: np.ndarray,
    box: tuple[int, int, int, int],
    win: SearchWindow,
    attempts: tuple[str, ...],
    dictionary: str,
    k: int,
    found: list[Detection],
    *,
    stop_at_id: bool = True,
    blur: tuple[float, float] | None = None,
) -> bool:
    """Run the attempts on one crop until the window's id is seen; True if it was.

    The "deblur" attempt's read of the window's id is a find like any other: its centre is as
    good as the model fit's on the same windows (mean error 0.065-0.093 px on eight degraded
    surveys, the fit's 0.064-0.133 px; on real ground blurred 6-10 px, 0.23 px against the fit's
    0.24-0.30 px), and it spares the fit (two thirds of a degraded flight's time went to fits).
    Other ids it reads are left out: through the filter's rings, only the expected id at its
    predicted place is proof enough."""
    x0, y0, x1, y1 = box
    if x1 - x0 < 8 or y1 - y0 < 8:
        return False
    h, w = gray.shape[:2]
    crop = gray[y0:y1, x0:x1]
    for attempt in attempts:
        if attempt == "fast" and win.side_px <= 0:
            continue
        # upscaling helps small markers only; a prediction outside the frame is a long
        # shot (the marker is most likely out of view): do not spend the retries on it
        if attempt == "upscale" and (crop.size > 4_000_000 or win.side_px >= 48):
            continue
        if attempt not in ("fast", "plain") and not in_frame(win.x_px, win.y_px, w, h):
            continue
        hits = [(mid, c) for mid, c in _run(crop, attempt, dictionary, win.side_px, blur) if plausible_quad(c, win)]
        deblur = attempt == "deblur"
        for mid, c in hits:
            if deblur and mid != win.marker_id:
                continue
            c = c + [x0, y0]
            centre = marker_centre(c)
            side = float(np.sqrt(abs(cv2.contourArea(c.astype(np.float32)))))
            corners = tuple(map(tuple, c.tolist()))
            found.append(Detection(mid, float(centre[0]), float(centre[1]), corners, attempt, k, side))
        if stop_at_id and any(mid == win.marker_id for mid, _ in hits):
            return True
    return False


def paint_channel(bgr: np.ndarray) -> np.ndarray:
    """The image a target without a code is fitted in: each pixel's darkest colour channel.

    Targets are neutral paint (white bars, black and white boards) while the ground seldom is:
    grass and soil are low in blue, so in grey a white cross on yellow grass is 90 grey levels
    over a ground that varies by 46, in the darkest channel 120 over 35. Neutral paint keeps
    its level in every channel, so the target's own contrast is what grey gives; grey ground
    (asphalt, concrete) is unchanged."""
    return bgr.min(axis=2) if bgr.ndim == 3 else bgr


def detect_task(
    args: tuple[str, list[SearchWindow], str, str, bool, tuple[str, ...]],
) -> tuple[str, list[Detection], str, tuple[float, float]]:
    """Worker entry: decode one photo and search its windows (``fit``, ``attempts``: see
    :func:`detect_in_image`); and the photo's motion blur (length px, direction deg). Coded markers
    are searched in grey, as the detector reads them; other targets are fitted in
    :func:`paint_channel`."""
    path, windows, dictionary, target, fit, attempts = args

    coded = target in CODED
    try:
        img = _read_photo(path, grey=coded)
    except OSError as e:
        return path, [], str(e), (math.nan, math.nan)
    if img is None:
        return path, [], "cannot decode the image", (math.nan, math.nan)
    gray = img if coded else cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    blur = estimate_motion_blur(gray)
    searched = gray if coded else paint_channel(img)
    dets = detect_in_image(searched, windows, dictionary, attempts, target=target, blur=blur, fit=fit)
    return path, dets, "", blur


#: The dictionaries tried where no marker decodes in the one given: each ArUco family's largest
#: (a family's smaller dictionaries are its first ids) and the others whole.
PROBED = (
    "DICT_4X4_1000",
    "DICT_5X5_1000",
    "DICT_6X6_1000",
    "DICT_7X7_1000",
    "DICT_ARUCO_ORIGINAL",
    "DICT_ARUCO_MIP_36H12",
    "DICT_APRILTAG_16H5",
    "DICT_APRILTAG_25H9",
    "DICT_APRILTAG_36H10",
    "DICT_APRILTAG_36H11",
)


def probe_task(args: tuple[str, list[SearchWindow], tuple[str, ...], str]) -> dict[str, list[tuple[str, float]]]:
    """Worker entry: per dictionary, the GCPs of one photo whose expected id the detector's plain
    attempt decodes in their window as that dictionary, in a marker's shape and size, each with
    its side over the predicted side. ``unsized``: a dictionary tried at any size (a marker size
    given wrong by more than the detector's 2x)."""
    path, windows, dictionaries, unsized = args
    gray = read_grey(path)
    seen: dict[str, list[tuple[str, float]]] = {}
    if gray is None:
        return seen
    h, w = gray.shape[:2]
    for win in windows:
        if win.radius_px <= 0:
            continue
        x0, y0, x1, y1 = _square(win, win.radius_px, w, h)
        if x1 - x0 < 8 or y1 - y0 < 8:
            continue
        crop = gray[y0:y1, x0:x1]
        for name in (*dictionaries, unsized) if unsized else dictionaries:
            free = replace(win, side_px=0.0) if name == unsized else win
            for mid, c in _run(crop, "plain", name, free.side_px):
                if mid == win.marker_id and plausible_quad(c, free):
                    seen.setdefault(name, []).append((win.gcp, side_ratio(c, win)))
                    break
    return seen


def side_ratio(corners: np.ndarray | Sequence[Sequence[float]], win: SearchWindow) -> float:
    """A decoded marker's side over the side its window predicts (NaN without a prediction). The
    detector's corners sit on the centres of the border's outer pixels: its side is a pixel
    short (gf_spot_exact's 38 decoded 14 px markers: 0.96 px)."""
    expected = win.side_px
    if len(win.ground_px) == 4:
        ex, nx, ey, ny = win.ground_px
        expected = math.sqrt(abs(ex * ny - nx * ey))
    side = math.sqrt(abs(float(cv2.contourArea(np.asarray(corners, np.float32).reshape(4, 2)))))
    return (side + 1.0) / expected if expected > 0 else math.nan


def ground_turn(corners_px: Sequence[Sequence[float]], ground_px: Sequence[float]) -> float:
    """A square marker's turn on the ground (degrees, modulo 90; :func:`.targets.fit_target`'s
    angle) from its corners in a photo and the photo's ``ground_px`` there: the same in every
    photo, to their yaw errors' difference (a few degrees)."""
    c = np.asarray(corners_px, float)
    edge = np.linalg.solve(np.array(ground_px, float).reshape(2, 2), c[1] - c[0])  # in east/north sides
    return math.degrees(math.atan2(-edge[1], edge[0])) % 90.0


def _read_photo(path: str, *, grey: bool) -> np.ndarray | None:
    """A photo's pixels (BGR or grey), None when nothing decodes it; OSError for a corrupt JPEG
    (strict: it would be searched as grey smears, with libjpeg noise on stderr)."""
    img = decode_photo(path, grey=grey)
    if img is None:  # not a JPEG: OpenCV's own way
        flags = cv2.IMREAD_GRAYSCALE if grey else cv2.IMREAD_COLOR
        img = cv2.imread(path, flags | cv2.IMREAD_IGNORE_ORIENTATION)
    return img


def read_grey(path: str) -> np.ndarray | None:
    """A photo in grey, or None when it cannot be read."""
    try:
        return _read_photo(path, grey=True)
    except OSError:
        return None


def init_worker() -> None:
    cv2.setNumThreads(1)  # one photo per process; OpenCV's own threads would oversubscribe
