"""A candidate refined into a fit: the target's model fitted to the pixels (centre, rotation, scale,
shape, blur, defocus; soft-L1), converged for crosses and circles, polished on a checkerboard's saddle.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable
from typing import NamedTuple

import cv2
import numpy as np

from geoortho.gcp.kernels import compiled
from geoortho.gcp.look import SUBSAMPLES, Renderer, kept_in, marker_affine, subsample_offsets, to_marker
from geoortho.gcp.markers import (
    CODED,
    CROSS_BAR,
    target_half_extent,
)

SATURATED = 250  # grey levels at or above: glare, not target
#: The short polish stops at a step under this share of its parameters' norm (the centre in window
#: pixels and the turn in degrees make it 0.001-0.004). scipy's default, 1e-8, took 10.4 Jacobians a
#: polish on a degraded small survey, this 7.9: on seven degraded and clean small surveys 565 markers
#: found (564 before), none wrong, mean centre error 0.002 px higher on one, the same or lower
#: (by up to 0.016 px) on the others; 0.88-0.91x the time.
POLISH_XTOL = 1e-5


class TargetModel(NamedTuple):
    """The target a fit looks for: its kind, its predicted frame (marker frame → pixel offsets,
    before the fit's turn and scale) and, for a coded marker, its cells."""

    kind: str
    base: np.ndarray
    cells: np.ndarray | None


class FitCandidate(NamedTuple):
    """One refined fit in a window, with what acceptance asks of it."""

    score: float  # masked normalised correlation of the model with the pixels
    cx: float  # centre, window pixels
    cy: float
    angle: float
    scale: float
    blen: float  # motion blur length px, direction deg, defocus px
    bdeg: float
    dpx: float
    A: np.ndarray  # marker frame → pixel offsets
    rend: Renderer
    pix: np.ndarray  # the scored pixels, their weights
    weight: np.ndarray
    contrast: float  # fitted white − black, grey levels
    worst_part: float


def censored_fit(
    pix: np.ndarray, tpl: np.ndarray, w: np.ndarray, cover: np.ndarray, raw: np.ndarray, glare: np.ndarray | None
) -> tuple[np.ndarray, np.ndarray]:
    """A coded marker's scored pixels with the clipped ones that still say something: a pixel at
    the clip is at least the clip less the glare fitted there; where that bound is brighter than
    half way from the fitted black to the fitted white, the pixel is bright paint (white paint in
    sun clips), and it is scored at its bound. Where glare alone would clip black paint, it says
    nothing and stays out."""
    hot = (raw >= SATURATED) & (cover > 0.999)
    if not hot.any() or w.sum() < 8:
        return pix, w
    gain, offset, var = level_fit_of(pix, tpl, w)
    if var < 1e-9:
        return pix, w
    mid = offset + 0.5 * gain
    bound = SATURATED - (0.0 if glare is None else glare)
    says = hot & (gain > 0) & (bound > mid)
    if not says.any():
        return pix, w
    return np.where(says, bound, pix), np.where(says, 1.0, w)


def level_fit_of(pix: np.ndarray, tpl: np.ndarray, w: np.ndarray) -> tuple[float, float, float]:
    """Weighted least squares of the pixels on the template: gain (white − black, grey levels),
    offset (black), and the template's weighted variance (near 0: the gain means nothing)."""
    sw = max(w.sum(), 1e-9)
    mt = (w * tpl).sum() / sw
    dt = tpl - mt
    var = float((w * dt * dt).sum())
    gain = float((w * dt * pix).sum() / max(var, 1e-12))
    return gain, float((w * pix).sum() / sw - gain * mt), var


def _parts(kind: str, u: np.ndarray, v: np.ndarray) -> np.ndarray | None:
    """Each pixel's part of the target (−1: none): checkerboard quadrants; a cross's four arms and
    the four corners of ground between them; a circle's disc and four sectors of its board."""
    if kind == "checkerboard":
        return np.where((np.abs(u) <= 0.5) & (np.abs(v) <= 0.5), (u >= 0) * 1 + (v >= 0) * 2, -1)
    quad = (u >= v) * 1 + (u >= -v) * 2  # the four sectors between the diagonals
    if kind == "cross":
        # its four arms (the ground between them is whatever it is: grass, tarmac, not the target)
        span = (np.abs(u) <= 0.5) & (np.abs(v) <= 0.5)
        arm = np.minimum(np.abs(u), np.abs(v)) <= CROSS_BAR / 2 - 0.04
        return np.where(span & arm, quad, -1)
    if kind == "circle":
        r = np.hypot(u, v)
        return np.where(r <= 0.3, 4, np.where((r >= 0.62) & (r <= target_half_extent(kind)), quad, -1))
    return None


def worst_part_of(
    kind: str,
    dx: np.ndarray,
    dy: np.ndarray,
    A: np.ndarray,
    pix: np.ndarray,
    tpl: np.ndarray,
    weight: np.ndarray,
    gain: float,
) -> float:
    """The largest mean residual over any part of the target, as a share of its contrast: texture
    that fits a target as a whole rarely has every part of it (NaN for coded markers)."""
    part = _parts(kind, *to_marker(dx, dy, A))
    if part is None or gain <= 0:
        return math.nan
    sw = max(weight.sum(), 1e-9)
    resid = pix - gain * tpl
    resid = resid - (weight * resid).sum() / sw  # the offset
    worst = 0.0
    groups = [part == k for k in range(int(part.max()) + 1)]
    if kind == "circle":  # a small circle's board sectors hold a few pixels each: the ring as a whole too
        groups.append((part >= 0) & (part < 4))
    for g in groups:
        w = weight * g
        if w.sum() >= 6:  # a mean of fewer pixels is noise
            worst = max(worst, abs(float((w * resid).sum() / w.sum())))
    return worst / gain


class TargetFit:
    """One refinement's least-squares problem: the patch's pixels round the start, which of them
    are fitted and which censored (clipped), the target's renderer, and the parameters' start,
    free entries and bounds. The parameters, 13 of them: centre x, y, turn, log scale, shape
    correction e1, e2, blur as a vector x, y, defocus px, a cross's bar width, and a glare spot's
    centre x, y and log size; the levels (gain, offset, the ground beyond a coded board, the
    glare's amplitude) are solved in closed form at each step, never searched."""

    def __init__(
        self,
        crop: np.ndarray,
        model: TargetModel,
        start: tuple[float, float, float],
        blur: tuple[float, float],
        shape: tuple[float, float, float, float],
        samples: int,
    ) -> None:
        kind, base, cells = model
        self.base = base
        cx0, cy0, angle0 = start
        half = target_half_extent(kind, cells)
        reach = int(math.ceil(np.abs(base).sum(axis=1).max() * half * 1.15 + blur[0] / 2 + 3))
        gx0, gx1 = max(0, int(cx0) - reach), min(crop.shape[1], int(cx0) + reach + 1)
        gy0, gy1 = max(0, int(cy0) - reach), min(crop.shape[0], int(cy0) + reach + 1)
        self.origin = (gx0, gy0)
        ys, xs = np.mgrid[gy0:gy1, gx0:gx1]
        self.xs, self.ys = xs, ys
        pix = crop[gy0:gy1, gx0:gx1].ravel().astype(np.float64)
        rend = Renderer(kind, cells, xs, ys)
        A0 = marker_affine(base, angle0, 1.0, 0.0, 0.0)
        # A coded marker's board (quiet zone included) stands on ground of its own: a blurred pixel
        # at the board's rim is partly board, partly ground. The model gives the board's share and
        # the ground beyond it is one more level, solved with the gain: the rims' ramps, where the
        # border's edges are, then place the marker along the blur too. On six degraded small
        # surveys (seeds 11 and 5, three renderings each) a fit 3.0 px off is gone and the mean
        # centre error falls by 0.01-0.05 px, recall within 2 markers of 90 either way. The other
        # targets keep the pixels wholly on the model, on which their thresholds were calibrated.
        self.rim = rim = kind in CODED
        if rim:
            _, cover0 = rend.render(cx0, cy0, A0, blur[0], blur[1], 0.7)
            use = (cover0 > 0.5) & (pix < SATURATED)
        else:
            _, cover0 = rend.render(cx0, cy0, A0 * 0.9, 0.0, 0.0, 0.0)
            use = (cover0 > 0.999) & (pix < SATURATED)
        if use.sum() < 12:
            use = (cover0 > 0.5) & ~np.isnan(pix)
        bx, by = blur[0] * math.cos(math.radians(blur[1])), blur[0] * math.sin(math.radians(blur[1]))
        self.side = side = float(np.sqrt(abs(np.linalg.det(base))))
        # A glare spot: an additive bright blob (its saturated core is masked), fitted as one more
        # term where the patch has saturated pixels, started at their centroid.
        hot = pix >= SATURATED
        self.glare = glare = bool(hot.any())
        gx, gy = (xs.ravel()[hot].mean(), ys.ravel()[hot].mean()) if glare else (cx0, cy0)
        # blur as a vector (x, y): no wrap-around of its direction for the optimiser
        scale0, e10, e20, defocus0 = shape
        x0 = np.array(
            [cx0, cy0, angle0, math.log(scale0), e10, e20, bx, by, defocus0, CROSS_BAR, gx, gy, math.log(0.25 * side)]
        )
        self.free = [i for i in range(13) if (i != 9 or kind == "cross") and (i < 10 or glare)]
        # Clipped pixels (white paint in sun, glare) are censored: they say the model is at least the
        # clip there. Scored one-sided, they pull a model that is darker there, never a brighter one.
        if rim:
            use = use | ((cover0 > 0.5) & (pix >= SATURATED))
        self.censor = hot[use] if rim else np.zeros(int(use.sum()), bool)
        self.solved = ~self.censor  # the rows the levels are solved on
        self.xf, self.yf = xs.ravel()[use].astype(float), ys.ravel()[use].astype(float)
        # the fit renders only the pixels it uses (a pixel's value depends on no other): 30-48 % of
        # the patch's square (median 42 %, the tiny degraded survey's 63 refinements)
        self.fitted = Renderer(kind, cells, self.xf, self.yf, samples=samples)
        self.path = subsample_offsets(samples)[2][None, :]  # the motion path's samples (−½…½)
        # A difference step in one parameter moves the model or the glare term, never both (but for
        # the blur's): each term is kept by the parameters it depends on, and a Jacobian's columns
        # for the other term's reuse it (a glare fit's 13 columns: 3 renders and 8 spots saved).
        self.rendered: dict[bytes, tuple[np.ndarray, np.ndarray]] = {}
        self.spotted: dict[bytes, np.ndarray] = {}
        self.no_spot = np.empty(0)
        self.seen = pix[use]
        self.seen_solved = self.seen[self.solved]
        # Motion blur is the photo's (measured from its texture), so the target's stays near it, and
        # defocus is a pixel or two: a model free to smear itself fits any texture.
        tol = max(2.5, 0.4 * blur[0])
        max_defocus = 1.0 + 0.08 * side
        x0[8] = min(x0[8], 0.9 * max_defocus)
        # the estimate can be wrong on real texture: the box holds both no blur and the estimate
        bx_lo, bx_hi, by_lo, by_hi = min(0.0, bx) - tol, max(0.0, bx) + tol, min(0.0, by) - tol, max(0.0, by) + tol
        lo = np.array([cx0 - reach, cy0 - reach, angle0 - 25, -0.25, -0.2, -0.2, bx_lo, by_lo, 0.0, 0.08])
        hi = np.array([cx0 + reach, cy0 + reach, angle0 + 25, 0.25, 0.2, 0.2, bx_hi, by_hi, max_defocus, 0.45])
        self.lo = np.r_[lo, gx - side, gy - side, math.log(0.05 * side + 0.5)]
        self.hi = np.r_[hi, gx + side, gy + side, math.log(side + 1.0)]
        self.x0 = np.clip(x0, self.lo, self.hi)  # (a start from an earlier fit may sit a rounding error outside)

    def placed(self, p: np.ndarray) -> tuple[float, float, np.ndarray, float, float, float]:
        """The renderer's arguments at ``p``: centre, affine, blur length and direction, defocus."""
        cx, cy, ang, ls, e1, e2, vx, vy, dpx = p[:9]
        A = marker_affine(self.base, ang, math.exp(ls), e1, e2)
        return cx, cy, A, math.hypot(vx, vy), math.degrees(math.atan2(vy, vx)), abs(dpx)

    def model(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        self.fitted.bar = min(max(float(p[9]), 0.08), 0.45)
        return self.fitted.render(*self.placed(p))

    def spot(self, p: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """The glare term at ``p`` on pixels (x, y). The glare is in the scene, so the camera's motion
        smears it as it smears the target: the spot averaged along the same path (a spot narrower
        than the blur makes a flat-topped streak, not a longer Gaussian)."""
        var = math.exp(2 * p[12])
        kernel = compiled("_glare_exponent")
        path = self.path
        if kernel is not None:
            e = kernel(x.ravel().astype(float), y.ravel().astype(float), p[10], p[11], p[6], p[7], path[0], var)
            result: np.ndarray = np.exp(e, out=e).mean(axis=1).reshape(x.shape)
            return result
        dx = x.ravel()[:, None] - p[10] + p[6] * path
        dy = y.ravel()[:, None] - p[11] - p[7] * path
        result = np.exp(-(dx * dx + dy * dy) / (2 * var)).mean(axis=1).reshape(x.shape)
        return result

    def terms(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The model (its value and share on each pixel) and the glare term (empty: none), kept."""
        t, cover = kept_in(self.rendered, p[:10].tobytes(), lambda: self.model(p), 32)
        return t, cover, self.glare_term(p)

    def glare_term(self, p: np.ndarray) -> np.ndarray:
        if not self.glare:
            return self.no_spot
        return kept_in(self.spotted, p[[6, 7, 10, 11, 12]].tobytes(), lambda: self.spot(p, self.xf, self.yf), 32)

    def design(self, p: np.ndarray) -> np.ndarray:
        t, cover, g = self.terms(p)
        cols = [t * cover, 1.0 - cover, np.ones_like(t)] if self.rim else [t, np.ones_like(t)]
        return np.column_stack([*cols, g] if self.glare else cols)

    def models(self, ps: list[np.ndarray]) -> list[tuple[np.ndarray, np.ndarray]]:
        """:meth:`model` at each of ``ps``, kept as :meth:`terms` keeps it; a coded marker's that
        are not kept rendered in one call."""
        rendered = self.rendered
        keys = [p[:10].tobytes() for p in ps]
        out = {key: rendered[key] for key in keys if key in rendered}
        todo = {key: p for key, p in zip(keys, ps) if key not in out}
        if todo:
            if self.fitted.lut is not None:
                made = self.fitted.render_rows([self.placed(p) for p in todo.values()])
            else:
                made = [self.model(p) for p in todo.values()]
            out.update(zip(todo, made))
            if len(rendered) + len(todo) > 32:
                rendered.clear()
            rendered.update(zip(todo, made))
        return [out[key] for key in keys]

    def residual_rows(self, qs: np.ndarray) -> np.ndarray:
        """The residuals at each row of ``qs`` (free parameters): the Jacobian's columns and a
        scan's points each in one compiled call of the render and one of the levels."""
        ps = []
        for q in qs:
            p = self.x0.copy()
            p[self.free] = q
            ps.append(p)
        seen, solved, censor = self.seen, self.solved, self.censor
        kernel = compiled("_level_residuals", len(ps))
        if kernel is None:
            rows = []
            for p in ps:
                d = self.design(p)
                # gain, offset (and glare amplitude) in closed form
                coef, *_ = np.linalg.lstsq(d[solved], self.seen_solved, rcond=None)
                r = d @ coef - seen
                r[censor] = np.minimum(r[censor], 0.0)
                rows.append(r / 8.0)
            return np.array(rows)
        looks = self.models(ps)
        spots = [self.glare_term(p) for p in ps]
        t, cover = np.array([m[0] for m in looks]), np.array([m[1] for m in looks])
        result: np.ndarray = kernel(t, cover, np.array(spots).reshape(len(ps), -1), self.rim, seen, solved, censor)
        return result

    def residuals(self, q: np.ndarray) -> np.ndarray:
        result: np.ndarray = self.residual_rows(q[None])[0]
        return result

    def batched(self, fun: Callable[[np.ndarray], np.ndarray], points: Iterable[np.ndarray]) -> np.ndarray:
        # scipy's map for its finite differences, whose fun is the residuals: the points at once
        return self.residual_rows(np.array(list(points)))

    def solve(self, converge: bool, evaluations: int) -> np.ndarray:
        """The fitted parameters: run to convergence (``converge``), or a short polish (scipy's
        soft-L1 least squares); a coded marker then placed along its blur. The start where the
        optimiser fails."""
        from scipy.optimize import least_squares

        x0, free, lo, hi = self.x0, self.free, self.lo, self.hi
        try:
            if converge:
                p = _converge(self.residual_rows, x0, free, lo, hi, self.side, evaluations)
                if self.rim:
                    p = _along_blur(self.residual_rows, p, free, lo, hi)
            else:
                scales = np.array([0.3, 0.3, 2.0, 0.03, 0.03, 0.03, 1.0, 1.0, 0.3, 0.02, 1.0, 1.0, 0.1])
                sol = least_squares(
                    self.residuals,
                    x0[free],
                    bounds=(lo[free], hi[free]),
                    loss="soft_l1",
                    f_scale=2.0,
                    diff_step=1e-3,
                    max_nfev=80,
                    xtol=POLISH_XTOL,
                    x_scale=scales[free],
                    workers=self.batched,
                )
                p = x0.copy()
                p[free] = sol.x
                if self.rim:  # the verdict's place too: a marker scored 1 px off along its blur scores low
                    p = _along_blur(self.residual_rows, p, free, lo, hi)
        except (ValueError, np.linalg.LinAlgError):
            p = x0
        return p

    def glare_image(self, p: np.ndarray) -> tuple[int, int, np.ndarray] | None:
        """The fitted glare over the patch (its corner, its image), to take off the pixels before
        scoring; None without glare."""
        if not self.glare:
            return None
        d = self.design(p)
        coef, *_ = np.linalg.lstsq(d[self.solved], self.seen_solved, rcond=None)
        gxx, gyy = self.xs.astype(float), self.ys.astype(float)
        return (*self.origin, coef[-1] * self.spot(p, gxx, gyy))  # the last term


def refine_fit(
    crop: np.ndarray,
    model: TargetModel,
    start: tuple[float, float, float],
    blur: tuple[float, float],
    converge: bool | None = None,
    shape: tuple[float, float, float, float] = (1.0, 0.0, 0.0, 0.7),
    samples: int = SUBSAMPLES,
    evaluations: int = 30,
) -> tuple[tuple[float, ...], tuple[int, int, np.ndarray] | None]:
    """Least-squares fit of the model's geometry, blur and defocus to the pixels around ``start``
    (and ``shape``: scale, shape correction e1 and e2, defocus px), with its optimiser run to
    convergence (``converge``; by default for :data:`CONVERGED` kinds): the parameters, and the
    fitted glare (:meth:`TargetFit.glare_image`)."""
    fit = TargetFit(crop, model, start, blur, shape, samples)
    p = fit.solve((model.kind in CONVERGED) if converge is None else converge, evaluations)
    cx, cy, ang, ls, e1, e2, vx, vy, dpx, bar = p[:10]
    return (
        float(cx),
        float(cy),
        float(ang),
        float(math.exp(ls)),
        float(e1),
        float(e2),
        float(math.hypot(vx, vy)),
        float(math.degrees(math.atan2(vy, vx))),
        float(abs(dpx)),
        float(bar),
    ), fit.glare_image(p)


#: Targets whose model is fitted to convergence. The others get a short polish from the coarse
#: place, turn and size (scipy's own differences, which barely move the model), and their
#: thresholds were calibrated on that: fitted to convergence, texture passes as a 2 x 2
#: checkerboard (an X-junction is everywhere; calibrate_targets: 6-8 of 200 impostors accepted, 4
#: polished), and a coded marker's fit bends its shape and blur towards the expected id, so a
#: marker of another id painted at the very place reached an id margin of 0.19 (0.095 polished)
#: and was accepted. Crosses accept no impostor either way, circles none with their score and size
#: checks (:data:`SCORE_BY_KIND`, :data:`SIZE_TOLERANCE`), and both gain recall at 12 px: crosses
#: 0.963 -> 0.988 (small, seed 7), circles 0.925 -> 0.978 (seed 11), real crops 0.54 -> 0.58 and
#: 0.74 -> 0.81.
CONVERGED = frozenset({"cross", "circle"})


def _converge(
    residual_rows: Callable[[np.ndarray], np.ndarray],  # of rows of the free parameters
    x0: np.ndarray,
    free: list[int],
    lo: np.ndarray,
    hi: np.ndarray,
    side: float,
    evaluations: int = 30,
) -> np.ndarray:
    """:func:`refine_fit`'s least squares, run to convergence: the parameters (``x0``, the ``free``
    ones within ``lo``..``hi``) at the end.

    The model is rendered from a fixed set of samples per pixel, so it moves in steps: scipy's
    finite differences (relative to the value: 1e-8 for the terms that start at 0) see no change
    and the fit stays where it started. Here the optimiser works in steps from the start in units
    that move the model by about half a pixel, its Jacobian by differences over a tenth of one
    (about the samples' spacing)."""
    from scipy.optimize import least_squares

    unit = np.array([0.5, 0.5, math.degrees(1.0 / side), 0.03, 0.03, 0.03, 0.5, 0.5, 0.3, 0.02, 1.0, 1.0, 0.1])[free]
    start = x0[free]
    upper = (hi[free] - start) / unit

    last: dict[bytes, np.ndarray] = {}  # the latest point's residuals: scipy asks them, then its Jacobian

    def at(d: np.ndarray) -> np.ndarray:
        # a copy: scipy scales what it is given in place under a robust loss
        result: np.ndarray = kept_in(last, d.tobytes(), lambda: residual_rows((start + d * unit)[None])[0], 0).copy()
        return result

    def jac(d: np.ndarray) -> np.ndarray:
        r0 = at(d)
        steps = np.where(d + 0.1 <= upper, 0.1, -0.1)
        shifted = residual_rows(np.array([start + (d + h * e) * unit for h, e in zip(steps, np.eye(len(d)))]))
        return np.column_stack([(r - r0) / h for r, h in zip(shifted, steps)])

    sol = least_squares(
        at,
        np.zeros(len(free)),
        jac=jac,
        bounds=((lo[free] - start) / unit, upper),
        loss="soft_l1",
        f_scale=2.0,
        max_nfev=evaluations,  # of the residuals: most fits converge in 20-26
    )
    p: np.ndarray = x0.copy()
    p[free] = start + sol.x * unit
    return p


#: The blur (px) from which a coded fit's centre is scanned along it (:func:`_along_blur`).
ALONG_BLUR_FROM_PX = 2.0


def along_reach(blur_px: float) -> float:
    """How far (px) the centre may move along a blur of ``blur_px`` beyond a fit's own pixel: a
    quarter of the blur, 2.5 px at most; none under :data:`ALONG_BLUR_FROM_PX`."""
    return min(2.5, 0.25 * blur_px) if blur_px >= ALONG_BLUR_FROM_PX else 0.0


def _along_blur(
    residual_rows: Callable[[np.ndarray], np.ndarray],  # of rows of the free parameters
    p: np.ndarray,
    free: list[int],
    lo: np.ndarray,
    hi: np.ndarray,
) -> np.ndarray:
    """The fitted parameters ``p`` (:func:`refine_fit`'s) with the centre moved along the blur to where
    the cost is least, scanned in quarter pixels.

    The model's samples lie a blur length / :data:`SUBSAMPLES` apart along the motion path (0.3 px
    for 9.5 px), so a step of a twentieth of a pixel that way barely changes the model: the
    optimiser's differences see no slope and the centre stays where it started, up to 1.5 px off
    on the degraded small surveys while 0.2 px at most across the blur. The cost over the scan
    does slope: it is the whole patch's, its steps at every pixel's own places. Run after the
    short polish as well (the verdict's place): recall +4 on the ten degraded small surveys, none
    lost, and a sixteenth less time (fewer candidates refined before one passes)."""
    length = math.hypot(p[6], p[7])
    if length < ALONG_BLUR_FROM_PX:
        return p
    ux, uy = p[6] / length, -p[7] / length  # the blur as seen (image y down): see _Renderer
    reach = max(1.0, along_reach(length))
    offsets = np.arange(-reach, reach + 1e-9, 0.25)

    def moved(off: float) -> np.ndarray:
        q = p.copy()
        q[0], q[1] = p[0] + off * ux, p[1] + off * uy
        result: np.ndarray = np.clip(q, lo, hi)[free]
        return result

    def cost(r: np.ndarray) -> float:
        z = (r / 2.0) ** 2  # soft_l1 at f_scale 2, as fitted
        return float(np.sum(2.0 * (np.sqrt(1.0 + z) - 1.0)))

    costs = np.array([cost(r) for r in residual_rows(np.array([moved(o) for o in offsets]))])
    i = int(np.argmin(costs))
    best = float(offsets[i])
    if 0 < i < len(offsets) - 1:  # the parabola's vertex through the least and its neighbours
        a, b, c = costs[i - 1 : i + 2]
        den = a - 2 * b + c
        if den > 0:
            best += 0.25 * float(np.clip(0.5 * (a - c) / den, -0.5, 0.5))
    out = p.copy()
    out[0], out[1] = p[0] + best * ux, p[1] + best * uy
    result: np.ndarray = np.clip(out, lo, hi)
    return result


def saddle_point(crop: np.ndarray, cx: float, cy: float, A: np.ndarray) -> tuple[float, float]:
    """A checkerboard's centre polished as the saddle point (OpenCV cornerSubPix), kept only when
    it stays within a quarter square of the fit."""
    quarter = float(np.sqrt(abs(np.linalg.det(A)))) / 4
    win = int(max(2, min(10, round(quarter))))
    pt = np.array([[[cx, cy]]], np.float32)
    if not (win + 1 <= cx < crop.shape[1] - win - 1 and win + 1 <= cy < crop.shape[0] - win - 1):
        return cx, cy
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 40, 0.001)
    out = cv2.cornerSubPix(crop.astype(np.float32), pt.copy(), (win, win), (-1, -1), crit)[0, 0]
    if math.hypot(out[0] - cx, out[1] - cy) <= quarter:
        return float(out[0]), float(out[1])
    return cx, cy
