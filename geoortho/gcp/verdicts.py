"""Each candidate judged into an observation: detected where it was predicted, too far, another id,
inside the margin, ambiguous; one per GCP and photo, and the photos' markers agreeing with each other.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from geoortho.core.camera import in_frame
from geoortho.feedback import Feedback
from geoortho.gcp.detect import (
    Detection,
    SearchWindow,
    fit_similarity,
    placed_by_others,
)

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


Results = list[tuple[str, list[Detection], str, tuple[float, float]]]  # photo, found, error, its blur


def nearest_detection(dets: list[Detection], k: int, win: SearchWindow) -> tuple[Detection, float] | None:
    """The detection of window ``k``'s own id nearest its prediction, and how far it is (px)."""
    mine = [
        (d, math.hypot(d.x_px - win.x_px, d.y_px - win.y_px))
        for d in dets
        if d.window == k and d.marker_id == win.marker_id and not d.reason
    ]
    return min(mine, key=lambda de: de[1]) if mine else None


def decoded_in(
    results: Results, windows: dict[str, list[SearchWindow]]
) -> Iterator[tuple[str, Detection, SearchWindow]]:
    """Each window whose marker the detector decoded: (photo path, the detection, the window)."""
    for path, dets, *_ in results:
        for k, win in enumerate(windows.get(Path(path).name, [])):
            found = nearest_detection(dets, k, win)
            if found is not None and found[0].attempt not in ("verified", "fitted") and found[1] <= win.max_radius_px:
                yield path, found[0], win


def _decoded_gcps(results: Results, windows: dict[str, list[SearchWindow]]) -> set[str]:
    """GCPs whose marker the detector decoded in their window of some photo."""
    return {win.gcp for _, _, win in decoded_in(results, windows)}


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


def judge_candidates(
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
    found = nearest_detection(dets, k, win)
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
        other = closer_prediction(d, err, win, wins)
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


def closer_prediction(d: Detection, err_px: float, win: SearchWindow, wins: list[SearchWindow]) -> str:
    """A target without an id belongs to the window only when no other GCP is predicted about as
    near it: another prediction within twice the own distance plus three target sides."""
    for o in wins:
        if o is win:
            continue
        if math.hypot(d.x_px - o.x_px, d.y_px - o.y_px) <= 2 * err_px + 3 * max(win.side_px, 1.0):
            return o.gcp
    return ""


def warn_counts(observations: list[Observation], fb: Feedback) -> None:
    per_gcp: dict[str, int] = {}
    for o in observations:
        if o.status == DETECTED:
            per_gcp[o.gcp] = per_gcp.get(o.gcp, 0) + 1
    for g, n in sorted(per_gcp.items()):
        if n < 3:
            fb.warning(f"GCP {g} is seen in only {n} photo(s); OpenDroneMap wants at least 3")
    if len(per_gcp) < 3:
        fb.warning(f"only {len(per_gcp)} GCP(s) found; OpenDroneMap needs at least 3")
