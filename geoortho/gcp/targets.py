"""Predict-and-verify: find a target of known look where the prediction puts it, by fitting its model.

A detector (OpenCV's ArUco) needs sharp, unsaturated cells to decode an id. Where it
gives up — motion blur, defocus, a glare spot, or a target with no code at all —
geoortho still knows which target should be where, at which size and (from the
pose) with which perspective; only its rotation on the ground is unknown. So:

1. Render the expected target (its reflectance pattern, :func:`geoortho.gcp.markers.target_reflectance`)
   through the local affine of the projection, blurred by the photo's estimated motion
   blur, at each rotation; correlate it with the window (OpenCV ``matchTemplate``, normalised,
   masked to the target's own area).
2. From the best peak, fit the model to the pixels: centre, rotation, scale, a small
   shape correction, blur length/direction and defocus, with gain and offset solved in
   closed form (scipy ``least_squares``, soft-L1 so a glare spot does not pull it);
   saturated pixels are masked out, never trusted.
3. Accept only with a correlation score and margins that keep precision at 1.0: over
   the second-best position in the window (a look-alike nearby) and, for coded markers,
   over every other id of the dictionary in every rotation, rendered at the fitted
   geometry.

The fitted model is the whole target, so its centre is what the issue asks of each
shape: a checkerboard's saddle (then polished by OpenCV ``cornerSubPix``, which finds
exactly that), a cross's two bar centre lines crossing, a circle's ellipse centre.

Here: the thresholds, :func:`fit_target` and its verdict. Beside it: :mod:`.look` (the target
rendered as a photo shows it), :mod:`.blur` (a photo's motion blur), :mod:`.search` (step 1) and
:mod:`.refine` (step 2).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from functools import partial

import cv2
import numpy as np

from geoortho.gcp.kernels import compiled_now
from geoortho.gcp.look import ALTERNATIVES, Renderer, best_alternative, coded_patterns, marker_affine, masked_ncc_score
from geoortho.gcp.markers import (
    CODED,
    marker_cells,
    paint_target,
    target_half_extent,
)
from geoortho.gcp.refine import (
    SATURATED,
    FitCandidate,
    TargetModel,
    along_reach,
    censored_fit,
    level_fit_of,
    refine_fit,
    saddle_point,
    worst_part_of,
)
from geoortho.gcp.search import coarse_reach, coarse_search, cross_band_of

__all__ = ["Fit", "fit_target", "min_score", "THRESHOLDS"]

#: Acceptance thresholds (normalised correlation, masked), chosen with
#: benchmarks/calibrate_targets.py (targets rendered into real photos against bare texture, other
#: target types and, for coded markers, another id at the very place) and the synthetic surveys.
#: Coded, 150 trials a role: the other-id impostors' id margin reaches 0.095, true markers' p5 0.04
#: (median 0.2): 0.12 keeps a margin over the worst impostor for 2 % of recall.
THRESHOLDS = {
    "score": 0.80,  # the fitted model explains the window
    "id_margin": 0.12,  # coded: over the best other id (any quarter turn) at the same place
    "position_margin": 0.12,  # over the best look-alike elsewhere in the window
    "contrast_dn": 60.0,  # a board is black and white (100+ grey levels apart): faint texture fits any shape
    "shape_margin": 0.12,  # no id: over the best plain edge, bar, corner or blob at the place
    "worst_part": 0.12,  # no id: mean residual over any part (quadrant, arm, ...) / contrast
}
#: The score asked of a circle: fitted to convergence (:data:`CONVERGED`), its model explains any
#: blurred dark blob well (calibrate_targets, 200 impostors: a checkerboard under glare and 8 px of
#: blur 0.95, an ArUco marker under 11 px 0.88, texture 0.81; 0.79 at most polished). True circles:
#: p5 0.947 on real crops (2 of 85 below 0.90), 0.97 at least on the 12 px surveys.
SCORE_BY_KIND = {"circle": 0.90}
#: How far a circle's fitted size may stray from the prediction's: a circle is any dark blob to a
#: model fitted to convergence, and a checkerboard's black square, half its board, fits as a circle
#: 0.82 of the size (calibrate_targets, under glare and 8 px of blur, score 0.95). The prediction's
#: size is off by the camera height's error (10 % is common; real crops: 4 %).
SIZE_TOLERANCE = {"circle": 0.15}
#: The contrast a coded marker's fit needs: black and white paint a metre across. Texture fitted
#: as the expected id reached a score of 0.84 and an id margin of 0.20 at 66 grey levels, 24 px
#: from the marker (degraded small survey, seed 5, spot glare, line blur); true markers fitted on
#: the six degraded small surveys had 104 at least (p5 151-193), calibrate_targets' 92.7 at least
#: (its contrasts drawn at random, from dull to full).
CONTRAST_BY_KIND = {"aruco": 85.0, "apriltag": 85.0}
#: The samples per pixel and the evaluations of the last steps of an accepted coded fit's centre
#: (:func:`_centred`).
CENTRE_SUBSAMPLES = 256
CENTRE_EVALUATIONS = 4
#: The id margin a coded marker placed by its photo's other markers needs, when its id was decoded
#: in another photo (:func:`.detect.placed_by_others`).
PLACED_ID_MARGIN = 0.0


def min_score(kind: str) -> float:
    """The normalised correlation a fit of ``kind`` needs."""
    return SCORE_BY_KIND.get(kind, THRESHOLDS["score"])


def min_contrast(kind: str) -> float:
    """The fitted contrast (white − black, grey levels) a fit of ``kind`` needs."""
    return CONTRAST_BY_KIND.get(kind, THRESHOLDS["contrast_dn"])


@dataclass(frozen=True)
class Fit:
    """A fitted target: where and how it looks, and how sure."""

    x_px: float
    y_px: float
    angle_deg: float
    scale: float
    blur_px: float
    blur_deg: float
    defocus_px: float
    score: float
    id_margin: float  # NaN for targets without an id
    position_margin: float
    corners_px: tuple[tuple[float, float], ...]
    contrast_dn: float = math.nan  # fitted white − black, grey levels
    worst_part: float = math.nan  # no id: the largest mean residual over a part, share of the contrast
    shape_margin: float = math.nan  # targets without an id: over the best simpler pattern at the place
    reason: str = ""  # why it was refused; "" = accepted
    id_score: float = math.nan  # coded: the expected id's correlation over the code cells
    refused_on: str = ""  # the first threshold it failed ("score", "id_margin", ...); "" = accepted


def fit_target(
    gray: np.ndarray,
    box: tuple[int, int, int, int],
    kind: str,
    base: np.ndarray,
    *,
    cells: np.ndarray | None = None,
    dictionary: str = "",
    marker_id: int = -1,
    blur: tuple[float, float] = (0.0, 0.0),
    predicted_xy: tuple[float, float] | None = None,
    near: tuple[float, float, float] | None = None,
    turn_deg: float | None = None,
) -> Fit | None:
    """Find and fit one target of ``kind`` in ``box`` (x0, y0, x1, y1) of a grey photo.

    ``base``: 2 × 2 pixels per marker side along the target's u (east at angle 0) and v
    (north): the projection's Jacobian at the GCP times the marker side. ``blur``: the
    photo's motion blur (length px, direction deg). ``predicted_xy``: for targets without an
    id, where the GCP is predicted (photo pixels): of the targets in the box that pass the
    score, the one nearest it is taken, unless another is about as near (ambiguous).
    ``near`` (x, y, radius; photo pixels): the target's centre is known to lie within radius of
    (x, y) — the search starts only there. ``turn_deg``: the target's turn on the ground (as
    :func:`marker_affine`'s angle) is known to a few degrees, modulo its period: only the rotations
    within 10° of it are tried. None when the box is too small."""
    x0, y0, x1, y1 = box
    crop: np.ndarray = gray[y0:y1, x0:x1].astype(np.float32)
    if crop.shape[0] < 8 or crop.shape[1] < 8:
        return None
    matched = crop
    photo = None  # the photo's part of the crop, where it goes beyond the photo
    if kind in CODED:
        # A coded marker near the photo's edge: its blurred board (and the model's margin) may reach
        # past it. The crop goes on beyond the edge as pixels that say nothing (NaN: no fit or
        # score uses them), and the coarse match sees the edge's pixels repeated there; the id
        # proves the marker, and one whose corners leave the photo is refused (detect._fit).
        out = coarse_reach(kind, base, cells, blur) + 1
        h, w = gray.shape[:2]
        pads = (max(0, out - y0), max(0, y1 + out - h), max(0, out - x0), max(0, x1 + out - w))
        if any(pads):
            top, bottom, left, right = pads
            matched = cv2.copyMakeBorder(crop, top, bottom, left, right, cv2.BORDER_REPLICATE)
            crop = cv2.copyMakeBorder(crop, top, bottom, left, right, cv2.BORDER_CONSTANT, value=math.nan)
            x0, y0, x1, y1 = box = (x0 - left, y0 - top, x1 + right, y1 + bottom)
            photo = (left, top, crop.shape[1] - right, crop.shape[0] - bottom)
    by_place = predicted_xy is not None and kind not in CODED
    within = None if near is None else (near[0] - x0, near[1] - y0, near[2])
    coarse = coarse_search(
        matched, kind, base, cells, blur, max_peaks=4 if by_place else 6, absolute=by_place, near=within,
        turn_deg=turn_deg, photo=photo,
    )  # fmt: skip
    if not coarse:
        return None
    verdict = partial(_verdict, crop, box, kind, base, cells, dictionary, marker_id, by_place)
    coded_id = kind in CODED and bool(dictionary) and cells is not None
    side = float(np.sqrt(abs(np.linalg.det(base))))
    scored: list[FitCandidate] = []
    for cx, cy, a, size_f, _ in coarse:
        cand = _score(crop, TargetModel(kind, base * size_f, cells), (cx, cy, a), blur)
        if coded_id and cand.score >= min_score(kind) and cand.contrast >= min_contrast(kind):
            # a coded marker is proven by its id at its place: the first candidate (best coarse
            # match first) that passes is the marker, and the rest are not refined
            fit = verdict(cand, math.nan, math.nan, "")
            if not fit.refused_on:
                return _centred(fit, cand, crop, box, kind, base, cells, near is not None)
        scored.append(cand)
    fits = sorted(scored, key=lambda f: -f.score)
    margins = [_shape_margin(kind, f) for f in fits]
    ambiguous = ""
    if by_place:
        # several targets of one kind may share a window: the prediction tells them apart. Only fits
        # that pass as targets themselves count (texture that fits a little is no rival).
        assert predicted_xy is not None
        px, py = predicted_xy[0] - x0, predicted_xy[1] - y0
        board = 2 * target_half_extent(kind) * side  # fits closer than a board apart: one target
        kept: list[int] = []
        for i, f in enumerate(fits):  # best first
            if _passes(kind, f, margins[i]) and all(
                math.hypot(f.cx - fits[j].cx, f.cy - fits[j].cy) > board for j in kept
            ):
                kept.append(i)
        kept.sort(key=lambda i: math.hypot(fits[i].cx - px, fits[i].cy - py))
        kept = kept or [0]  # none passes: the best, to say why
        own = math.hypot(fits[kept[0]].cx - px, fits[kept[0]].cy - py)
        dists = [math.hypot(fits[i].cx - px, fits[i].cy - py) for i in kept[1:]]
        # a rival counts when it is about as near, and inside the part of the window the
        # prediction's error spans (the window less a target and a half each side)
        reach = max(px, py, (x1 - x0) - px, (y1 - y0) - py) - 1.5 * side  # the box may be cut by the frame
        dists = [d for d in dists if d <= reach]
        pos_margin = (min(dists) - (2 * own + 3 * side)) / side if dists else math.inf
        if pos_margin < 0:
            ambiguous = f"two {kind} targets about as near the prediction ({own:.0f} and {min(dists):.0f} px)"
        fits, margins = [fits[i] for i in kept], [margins[i] for i in kept]
    best = fits[0]
    if not by_place:
        others = (f.score for f in fits[1:] if math.hypot(f.cx - best.cx, f.cy - best.cy) > 0.75 * side)
        pos_margin = best.score - max(others, default=-1.0)
    fit = verdict(best, margins[0], pos_margin, ambiguous)
    return _centred(fit, best, crop, box, kind, base, cells, near is not None)


def _verdict(
    crop: np.ndarray,
    box: tuple[int, int, int, int],
    kind: str,
    base: np.ndarray,
    cells: np.ndarray | None,
    dictionary: str,
    marker_id: int,
    by_place: bool,
    cand: FitCandidate,
    shape_margin: float,
    pos_margin: float,
    ambiguous: str,
) -> Fit:
    """The fit of one refined candidate: its id checked (coded), and the first threshold it fails
    (``by_place``: a target without an id told by the prediction; ``pos_margin`` is then the margin
    of its distance over a rival's)."""
    x0, y0 = box[0], box[1]
    score, cx, cy, angle, scale, blen, bdeg, dpx, A, rend, pix, weight, contrast, worst_part = cand
    t = THRESHOLDS
    id_margin = id_score = math.nan
    if kind in CODED and dictionary and cells is not None:
        id_score, id_margin = _id_scores(cand, cells, dictionary, marker_id)
    if kind == "checkerboard":
        cx, cy = saddle_point(crop, cx, cy, A)
    corners = np.array([[-0.5, 0.5], [0.5, 0.5], [0.5, -0.5], [-0.5, -0.5]]) @ A.T + [cx + x0, cy + y0]
    size = math.sqrt(abs(np.linalg.det(A)) / abs(np.linalg.det(base)))  # fitted / predicted
    # the first threshold the fit fails, and why in words
    refusals = (
        ("score", score < min_score(kind), f"best {kind} match scores {score:.2f} < {min_score(kind):.2f}"),
        (
            "size",
            kind in SIZE_TOLERANCE and abs(math.log(size)) > math.log1p(SIZE_TOLERANCE.get(kind, 0.0)),
            f"the {kind} fitted is {size:.0%} of the predicted size (within {SIZE_TOLERANCE.get(kind, 0.0):.0%})",
        ),
        (
            "contrast_dn",
            contrast < min_contrast(kind),
            f"the {kind} fitted has a contrast of {contrast:.0f} < {min_contrast(kind):.0f} grey levels",
        ),
        (
            "worst_part",
            worst_part > t["worst_part"],
            f"a part of the {kind} is off by {worst_part:.0%} of its contrast > {t['worst_part']:.0%}",
        ),
        (
            "shape_margin",
            kind in ALTERNATIVES and shape_margin < t["shape_margin"],
            f"a plain edge, bar, corner or blob fits within {shape_margin:.2f} < {t['shape_margin']:.2f}",
        ),
        (
            "id_margin",
            kind in CODED and id_margin < t["id_margin"],
            f"id {marker_id} beats the next id by only {id_margin:.2f} < {t['id_margin']:.2f}",
        ),
        ("ambiguous", bool(ambiguous), ambiguous),
        # (a coded marker is proven by its id at this place: a look-alike elsewhere in the window
        # that is not this id does not count against it; calibrate_targets: 0 of 450 impostors
        # pass score, contrast and id margin without this test, and no true marker is moved)
        (
            "position_margin",
            not by_place and kind not in CODED and pos_margin < t["position_margin"],
            f"a look-alike in the window scores within {pos_margin:.2f} < {t['position_margin']:.2f}",
        ),
        ("window", not (0 <= cx < crop.shape[1] and 0 <= cy < crop.shape[0]), "the fit left the window"),
    )
    refused_on, reason = next(((name, why) for name, failed, why in refusals if failed), ("", ""))
    return Fit(
        float(cx + x0), float(cy + y0), float(angle % 360.0), float(scale), float(blen), float(bdeg % 180.0),
        float(dpx), float(score), float(id_margin), float(pos_margin), tuple(map(tuple, corners.tolist())),
        float(contrast), float(worst_part), float(shape_margin), reason, float(id_score), refused_on,
    )  # fmt: skip


def _centred(
    fit: Fit,
    cand: FitCandidate,
    crop: np.ndarray,
    box: tuple[int, int, int, int],
    kind: str,
    base: np.ndarray,
    cells: np.ndarray | None,
    placed: bool = False,
) -> Fit:
    """A coded fit that is accepted, or placed (refused only on its id margin), with its centre
    where its model fitted to convergence puts it, started from the fit itself (its place, turn,
    size, shape, blur and defocus). The verdict stands on the short polish, on which the thresholds
    were set; the centre does not (six degraded small surveys: mean centre error 0.17-0.39 px from
    0.22-0.41, recall the same or one more). Any other fit as it is, and one refused on its id
    margin that cannot be taken as placed (``placed``: it was searched where its place was known;
    its margin under :data:`PLACED_ID_MARGIN`): 11 of the 22 refused so on a degraded survey."""
    if kind not in CODED or fit.refused_on not in ("", "id_margin"):
        return fit
    if fit.refused_on and not (placed and fit.id_margin >= PLACED_ID_MARGIN):
        return fit  # it cannot be taken as placed: a refusal where its polish put it
    # the shape correction back from A = scale · shape · base · rot (see _affine)
    a = math.radians(cand.angle)
    rot = np.array([[math.cos(a), math.sin(a)], [-math.sin(a), math.cos(a)]])
    shape = cand.A @ np.linalg.inv(base @ rot) / cand.scale
    e1, e2 = 0.5 * (shape[0, 0] - shape[1, 1]), 0.5 * (shape[0, 1] + shape[1, 0])
    start, size = (cand.cx, cand.cy, cand.angle), (cand.scale, e1, e2, cand.dpx)
    blur = (cand.blen, cand.bdeg)
    model = TargetModel(kind, base, cells)
    (cx, cy, ang, scale, e1, e2, blen, bdeg, dpx, _), _ = refine_fit(
        crop, model, start, blur, converge=True, shape=size
    )
    # the model's 32 samples a pixel leave it a few grey levels off the exact integral, enough to
    # hold a centre 0.05-0.2 px from the optimum; a few steps with 256 take it there
    (cx, cy, *_), _ = refine_fit(
        crop, model, (cx, cy, ang), (blen, bdeg), converge=True, shape=(scale, e1, e2, dpx),
        samples=CENTRE_SUBSAMPLES, evaluations=CENTRE_EVALUATIONS,
    )  # fmt: skip
    dx, dy = cx - cand.cx, cy - cand.cy
    # a pixel or more away is not the same optimum, but along the blur, where the polish could not
    # tell the place (see _along_blur)
    b = math.radians(cand.bdeg)
    along = dx * math.cos(b) - dy * math.sin(b)
    across = math.hypot(dx - along * math.cos(b), dy + along * math.sin(b))
    if across >= 1.0 or abs(along) >= 1.0 + along_reach(cand.blen):
        return fit
    corners = tuple((x + dx, y + dy) for x, y in fit.corners_px)
    return replace(fit, x_px=float(cx + box[0]), y_px=float(cy + box[1]), corners_px=corners)


def _id_scores(cand: FitCandidate, cells: np.ndarray, dictionary: str, marker_id: int) -> tuple[float, float]:
    """A coded candidate's score for its expected id, and the margin over the best other id.

    Ids differ only inside the border: the code cells alone are scored, the expected id in any
    quarter turn (a marker is laid at any heading; the border alone fixed the fit's) against
    every other id in any quarter turn, each rendered at the same place."""
    _, cx, cy, _, _, blen, bdeg, dpx, A, rend, pix, weight, _, _ = cand
    u, v = rend.uv(cx, cy, A, blen, bdeg, dpx)
    lim = 0.5 - 1.0 / cells.shape[0]
    # a pixel speaks for the code when at least half of its samples (pixel area, motion path)
    # fall on the code cells: demanding all of them leaves a blurred marker a few pixels
    on_code = ((np.abs(u) <= lim) & (np.abs(v) <= lim)).mean(axis=1) >= 0.5
    scores = list(rend.ncc_ids(pix, weight * on_code, cx, cy, A, blen, bdeg, dpx, coded_patterns(dictionary)))
    mine = slice(4 * marker_id, 4 * marker_id + 4)
    id_score = max(scores[mine])
    return id_score, id_score - max(scores[: mine.start] + scores[mine.stop :])


def _shape_margin(kind: str, f: FitCandidate) -> float:
    """A fit's score over the best simpler pattern at its place (NaN: coded, or not worth asking)."""
    if kind not in ALTERNATIVES or f.score < min_score(kind) or f.contrast < min_contrast(kind):
        return math.nan
    alt = best_alternative(kind, f.rend, (f.cx, f.cy, f.A, f.blen, f.bdeg, f.dpx), f.pix, f.weight, f.rend.bar)
    return f.score - alt


def _passes(kind: str, f: FitCandidate, shape_margin: float) -> bool:
    """Would this fit of a target without an id be accepted on its own (score, contrast, parts, shape)?"""
    t = THRESHOLDS
    return (
        f.score >= min_score(kind)
        and f.contrast >= min_contrast(kind)
        and shape_margin >= t["shape_margin"]
        and not f.worst_part > t["worst_part"]
    )


def _score(
    crop: np.ndarray, model: TargetModel, start: tuple[float, float, float], blur: tuple[float, float]
) -> FitCandidate:
    """Refine from one candidate; its final score on every pixel the model covers (saturated ones
    out, but for a coded marker's clipped paint: :func:`censored_fit`)."""
    kind, base, cells = model
    fit, glare = refine_fit(crop, model, start, blur)
    cx, cy, angle, scale, e1, e2, blen, bdeg, dpx, bar = fit
    crops = [crop]
    raw = crop
    glare_at = None
    if glare is not None:
        # take the fitted glare spot off (a saturated pixel is scored only where it says how bright
        # the paint is at least: see _censored)
        gx0, gy0, spot = glare
        glare_at = np.zeros(crop.shape, np.float32)
        glare_at[gy0 : gy0 + spot.shape[0], gx0 : gx0 + spot.shape[1]] = spot
        crop = crop.copy()
        sub = crop[gy0 : gy0 + spot.shape[0], gx0 : gx0 + spot.shape[1]]
        hot = sub >= SATURATED
        sub -= spot.astype(np.float32)
        sub[hot] = 255.0
        # saturated white paint looks like glare to the fit: the photo as it is may be the better
        # explanation (taken only where it is; for coded markers glare is always taken off)
        crops = [crop] if kind in CODED else [crop, crops[0]]
    as_is = crops[-1]
    A = marker_affine(base, angle, scale, e1, e2)
    half = target_half_extent(kind, cells)
    reach = int(math.ceil(np.abs(A).sum(axis=1).max() * half + blen / 2 + 2 * dpx + 2))
    gx0, gx1 = max(0, int(cx) - reach), min(crop.shape[1], int(cx) + reach + 2)
    gy0, gy1 = max(0, int(cy) - reach), min(crop.shape[0], int(cy) + reach + 2)
    ys, xs = np.mgrid[gy0:gy1, gx0:gx1]
    rend = Renderer(kind, cells, xs, ys, bar)
    tpl, cover = rend.render(cx, cy, A, blen, bdeg, dpx)
    band = cross_band_of(xs.ravel() - cx, ys.ravel() - cy, A, bar) if kind == "cross" else True
    best = -math.inf
    for c in crops:
        p = c[gy0:gy1, gx0:gx1].ravel()
        unsaturated = p < SATURATED  # (and in the photo: beyond its edge a crop is NaN)
        p = np.where(np.isnan(p), 0.0, p)
        if kind not in CODED and c is as_is:
            # white paint in sun clips: where no glare is taken off, a saturated pixel where the
            # model is white says what it should (only on the dark parts is it glare). Coded ids
            # keep them out as they are: a cell clipped by glare must not vote for the id that has
            # it white (one clipped where glare alone would not clip black paint is white: _censored).
            unsaturated |= tpl >= 0.5
        w = ((cover > 0.999) & unsaturated & band).astype(np.float64)
        if kind in CODED:
            g = None if glare_at is None else glare_at[gy0:gy1, gx0:gx1].ravel()
            p, w = censored_fit(p, tpl, w, cover, raw[gy0:gy1, gx0:gx1].ravel(), g)
        score = masked_ncc_score(p, tpl, w)
        if score > best:
            best, pix, weight = score, p, w
    # the fitted contrast (white − black, grey levels): the least-squares gain of the model
    gain, _, _ = level_fit_of(pix, tpl, weight)
    worst = worst_part_of(kind, xs.ravel() - cx, ys.ravel() - cy, A, pix, tpl, weight, gain)
    return FitCandidate(best, cx, cy, angle, scale, blen, bdeg, dpx, A, rend, pix, weight, gain, worst)


def warm() -> None:
    """Compile the fits' kernels into numba's cache, by a small fit that takes each path (a clipped
    coded marker under glare), so that no command pays for it."""
    with compiled_now():
        side, cx, cy = 15.0, 40.4, 39.7
        img = np.full((80, 80), 110.0)
        a = math.radians(-24.0)
        A = side * np.array([[math.cos(a), math.sin(a)], [math.sin(a), -math.cos(a)]])
        cells = marker_cells("DICT_4X4_50", 9)
        paint_target(img, "aruco", cx, cy, A, cells, 240.0, 45.0)
        yy, xx = np.mgrid[0:80, 0:80]
        img += 150.0 * np.exp(-((xx - cx - 7.0) ** 2 + (yy - cy + 4.0) ** 2) / 72.0)
        grey = np.clip(img, 0, 255).astype(np.uint8)
        fit_target(grey, (10, 10, 71, 71), "aruco", A, cells=cells, dictionary="DICT_4X4_50", marker_id=9)
