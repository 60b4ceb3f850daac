"""The second look at a photo (a worker task): a marker its detector missed, placed where the
nearest photo that decoded it puts it, by the ground round it matched in this photo's window, then
fitted there (:func:`.detect.fit_missed`). Takes and returns plain data.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import cv2
import numpy as np

from geoortho.core.camera import in_frame
from geoortho.gcp.detect import (
    Detection,
    SearchWindow,
    accepted_in,
    fit_missed,
    ground_turn,
    place_tolerance,
    read_grey,
    search_wide,
)
from geoortho.gcp.refine import SATURATED

__all__ = ["CarryJob", "carried_place", "second_look_task"]

#: What ground carried over from another photo must score (OpenCV's normalised correlation) to
#: place a marker, and by how much it must beat the best place more than a marker side away.
CARRY_SCORE = 0.5
CARRY_MARGIN = 0.1


def carried_place(
    gray: np.ndarray,
    win: SearchWindow,
    donor: np.ndarray,
    donor_xy: tuple[float, float],
    donor_ground_px: Sequence[float],
) -> tuple[float, float, float] | None:
    """Where a photo that found the marker puts it in this one: the ground around it there (four
    marker sides each way), mapped by the two photos' projections of the marker (``ground_px``)
    and matched in this photo's window; (x, y, tolerance px), or None when no place stands out.

    A blurred photo often has no marker found to place the rest by; a sharp neighbour has, and
    its textured ground locates far better than the blurred marker alone. The match's place is
    where the marker's centre is, to the yaw error's turn of the patch and the parallax of what
    stands on it. Measured on two degraded small surveys (38 places): 0.3 and 1.0 px from the truth
    (medians; p90 0.5 and 1.6 px, the latter a curved blur path's), one 3.5 px. The tolerance
    (:func:`place_tolerance`) is tighter than a photo's own markers give."""
    g_here = np.array(win.ground_px, float).reshape(2, 2)
    g_there = np.array(donor_ground_px, float).reshape(2, 2)
    if abs(np.linalg.det(g_there)) < 1e-9 or win.side_px <= 0:
        return None
    back = g_there @ np.linalg.inv(g_here)  # this photo's pixel offsets -> the donor's
    half = int(math.ceil(4 * win.side_px))
    size = 2 * half + 1
    # template pixel t -> donor pixel donor_xy + back (t - half)
    warp = np.c_[back, np.asarray(donor_xy, float) - back @ [half, half]]
    flags = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
    tpl = cv2.warpAffine(donor.astype(np.float32), warp, (size, size), flags=flags)
    inside = cv2.warpAffine(np.ones(donor.shape[:2], np.float32), warp, (size, size), flags=flags)
    mask = ((inside > 0.999) & (tpl < SATURATED)).astype(np.float32)
    if mask.mean() < 0.5:
        return None
    h, w = gray.shape[:2]
    # Searched in the window the flight's measured errors give, not the wide one (the stated
    # uncertainty: the detector's): on six degraded surveys 172 of 173 places were the same either
    # way, one more was found (a rival in the wide window had hidden it), at a fifth of the cost.
    reach = win.radius_px + half
    x0, y0 = max(0, int(win.x_px - reach)), max(0, int(win.y_px - reach))
    x1, y1 = min(w, int(win.x_px + reach) + 1), min(h, int(win.y_px + reach) + 1)
    if x1 - x0 <= size or y1 - y0 <= size:
        return None
    res = cv2.matchTemplate(gray[y0:y1, x0:x1].astype(np.float32), tpl, cv2.TM_CCOEFF_NORMED, mask=mask)
    res = np.nan_to_num(res, nan=-1.0, posinf=-1.0, neginf=-1.0)
    _, best, _, (bx, by) = cv2.minMaxLoc(res)
    rival = res.copy()
    cv2.circle(rival, (bx, by), int(math.ceil(win.side_px)), -1.0, -1)
    if best < CARRY_SCORE or best - rival.max() < CARRY_MARGIN:
        return None

    def vertex(a: float, b: float, c: float) -> float:  # a parabola's peak, from its 3 samples
        d = a - 2 * b + c
        return 0.0 if d >= 0 else float(np.clip(0.5 * (a - c) / d, -0.5, 0.5))

    fx = vertex(res[by, bx - 1], best, res[by, bx + 1]) if 0 < bx < res.shape[1] - 1 else 0.0
    fy = vertex(res[by - 1, bx], best, res[by + 1, bx]) if 0 < by < res.shape[0] - 1 else 0.0
    return x0 + bx + fx + half, y0 + by + fy + half, place_tolerance(win)


#: A window to fit where another photo found its marker: (window index, donor photo, the marker's
#: centre there, its ``ground_px`` there, its corners there).
CarryJob = tuple[int, str, tuple[float, float], tuple[float, ...], tuple[tuple[float, float], ...]]


def second_look_task(
    args: tuple[str, list[SearchWindow], list[Detection], list[CarryJob], str, str, tuple[float, float]],
) -> tuple[str, list[Detection]]:
    """Worker entry, once every photo has been searched by the detector: the windows of one photo
    whose coded marker it did not decode, fitted (:func:`fit_missed`) where a photo that decoded it
    puts it (``jobs``; :func:`carried_place`) and at the turn it has there (:func:`ground_turn`),
    else where this photo's markers put it, else in the whole window; ``blur``: the photo's, as its
    search measured it. Returns the photo and its detections: ``found`` and the new fits (refusals
    with their reason)."""
    path, windows, found, jobs, dictionary, target, blur = args
    gray = read_grey(path)
    if gray is None:  # its search already said why
        return path, found
    h, w = gray.shape[:2]
    carried: dict[int, tuple[float, float, float]] = {}
    turns: dict[int, float] = {}
    donors: dict[str, np.ndarray | None] = {}
    for k, donor_path, donor_xy, donor_ground, donor_corners in jobs:
        turns[k] = ground_turn(donor_corners, donor_ground)
        if donor_path not in donors:
            donors[donor_path] = read_grey(donor_path)
        donor, win = donors[donor_path], windows[k]
        if donor is None or not in_frame(win.x_px, win.y_px, w, h, 0.5 * win.side_px, 0.5 * win.side_px):
            continue
        place = carried_place(gray, win, donor, donor_xy, donor_ground)
        if place is not None:
            carried[k] = place
    missed = [k for k, win in enumerate(windows) if not any(accepted_in(d, win) for d in found if d.window == k)]
    fitted = fit_missed(gray, windows, list(found), missed, target, dictionary, blur, carried, turns)
    return path, search_wide(gray, windows, fitted, missed, dictionary, blur)
