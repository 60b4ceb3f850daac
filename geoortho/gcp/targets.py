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
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, replace
from functools import cache, partial
from typing import Any, NamedTuple, TypeVar

import cv2
import numpy as np

from geoortho.gcp.kernels import compiled, compiled_now
from geoortho.gcp.markers import (
    CODED,
    CROSS_BAR,
    coded_cells_at,
    get_dictionary,
    marker_cells,
    paint_target,
    target_half_extent,
    target_reflectance,
)

__all__ = ["Fit", "estimate_motion_blur", "fit_target", "min_score", "THRESHOLDS"]

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
SATURATED = 250  # grey levels at or above: glare, not target
SUBSAMPLES = 32  # per pixel: pixel area, motion path and defocus at once
#: The samples per pixel and the evaluations of the last steps of an accepted coded fit's centre
#: (:func:`_centred`).
CENTRE_SUBSAMPLES = 256
CENTRE_EVALUATIONS = 4
#: The id margin a coded marker placed by its photo's other markers needs, when its id was decoded
#: in another photo (:func:`.detect.placed_by_others`).
PLACED_ID_MARGIN = 0.0
#: The short polish stops at a step under this share of its parameters' norm (the centre in window
#: pixels and the turn in degrees make it 0.001-0.004). scipy's default, 1e-8, took 10.4 Jacobians a
#: polish on a degraded small survey, this 7.9: on seven degraded and clean small surveys 565 markers
#: found (564 before), none wrong, mean centre error 0.002 px higher on one, the same or lower
#: (by up to 0.016 px) on the others; 0.88-0.91x the time.
POLISH_XTOL = 1e-5


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


_T = TypeVar("_T")


def _kept(store: dict[bytes, _T], key: bytes, make: Callable[[], _T], keep: int) -> _T:
    """``store[key]``, made by ``make()`` when missing; the store is emptied first when it holds
    more than ``keep`` (a fit's evaluations come near each other: the latest few are the ones asked
    again)."""
    if key not in store:
        if len(store) > keep:
            store.clear()
        store[key] = make()
    return store[key]


@cache
def _offsets(n: int = SUBSAMPLES) -> tuple[np.ndarray, ...]:
    """Fixed sample offsets per pixel: (x, y) uniform in the pixel, t along the motion path
    (−½…½), (nx, ny) standard normal for defocus.

    A low-discrepancy (additive recurrence) sequence: the template is a smooth,
    deterministic function of the parameters, which the least-squares fit needs."""
    from scipy.special import ndtri

    steps = np.sqrt(np.array([2.0, 3.0, 5.0, 7.0, 11.0])) % 1.0
    q = (0.5 + np.outer(np.arange(1, n + 1), steps)) % 1.0
    normal = ndtri(np.clip(q[:, 3:], 1e-3, 1 - 1e-3))
    cols = np.c_[q[:, :3] - 0.5, normal]
    cols -= cols.mean(axis=0)  # no bias: a sample set off-centre would shift every fitted centre
    cols[:, 3:] /= cols[:, 3:].std(axis=0)
    return tuple(cols.T)


def _fit_reflectance(kind: str, u: np.ndarray, v: np.ndarray, cells: np.ndarray | None, bar: float) -> np.ndarray:
    """The model's reflectance: the target, with NaN outside the area the model covers.

    A cross is painted on unknown ground: the ground inside its span is modelled as one
    dark level. A circle's board may stand at any rotation: only the disc inscribed in it."""
    if kind == "cross":
        out = target_reflectance(kind, u, v, bar=bar)
        span = (np.abs(u) <= 0.5) & (np.abs(v) <= 0.5)
        return np.where(span & np.isnan(out), 0.0, out)
    out = target_reflectance(kind, u, v, cells)
    if kind == "circle":
        out = np.where(u * u + v * v <= target_half_extent(kind) ** 2, out, np.nan)
    return out


def _affine(base: np.ndarray, angle_deg: float, scale: float, e1: float, e2: float) -> np.ndarray:
    """Marker frame (u right, v up, in sides) → pixel offsets: the pose's ground Jacobian × the
    target's rotation on the ground × scale, with a small symmetric shape correction."""
    a = math.radians(angle_deg)
    rot = np.array([[math.cos(a), math.sin(a)], [-math.sin(a), math.cos(a)]])
    shape = np.array([[1 + e1, e2], [e2, 1 - e1]])
    result: np.ndarray = scale * shape @ base @ rot
    return result


#: A coded table's "on the board" weight: a sample reads white (0 or 1) + _ON × on (0 or 1), so one
#: gather and one sum over a pixel's samples give both counts (white < _ON for any sample count).
_ON = 1024.0
_BLOCK = 256  # pixels a coded render takes at once


def _coded_lookup(cells: np.ndarray) -> tuple[np.ndarray, int, float]:
    """A coded marker as one table over its board's cells with one more ring around them, flat:
    white (1.0 on white cells and the quiet zone) + :data:`_ON` on the board (0 on the ground
    beyond); with the cells across (border included) and the board's half side in marker sides."""
    n = cells.shape[0]
    white = np.zeros((n + 4, n + 4))
    on = np.zeros((n + 4, n + 4))
    on[1:-1, 1:-1] = 1.0
    white[1:-1, 1:-1] = 1.0  # the quiet zone
    white[2:-2, 2:-2] = cells.astype(float)
    return (white + _ON * on).ravel(), n, target_half_extent("aruco", n)


def _inverse(A: np.ndarray) -> tuple[float, float, float, float]:
    """A 2 × 2 matrix's inverse in closed form, row by row (the renderer asks it thousands of times
    a fit)."""
    det = A[0, 0] * A[1, 1] - A[0, 1] * A[1, 0]
    return A[1, 1] / det, -A[0, 1] / det, -A[1, 0] / det, A[0, 0] / det


def _to_marker(dx: np.ndarray, dy: np.ndarray, A: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixel offsets from the centre → marker-frame coordinates (sides), through ``A``'s inverse."""
    i00, i01, i10, i11 = _inverse(A)
    return i00 * dx + i01 * dy, i10 * dx + i11 * dy


class _Renderer:
    """Renders the target model into a fixed grid of pixels (a patch of the photo)."""

    def __init__(
        self,
        kind: str,
        cells: np.ndarray | None,
        xs: np.ndarray,
        ys: np.ndarray,
        bar: float = CROSS_BAR,
        samples: int = SUBSAMPLES,
    ):
        self.kind, self.cells, self.bar = kind, cells, bar
        self.xs, self.ys = xs.astype(float).ravel(), ys.astype(float).ravel()
        self.sx, self.sy, self.st, self.nx, self.ny = _offsets(samples)
        self.lut = _coded_lookup(cells) if kind in CODED and cells is not None else None

    def _sample_offsets(self, blur_px: float, blur_deg: float, defocus_px: float) -> tuple[np.ndarray, np.ndarray]:
        """Each sample's offset (px) from its pixel's centre: pixel area, motion path, defocus."""
        sdx, sdy = self._offset_rows([(blur_px, blur_deg, defocus_px)])
        return sdx[0], sdy[0]

    def _offset_rows(self, blurs: Sequence[tuple[float, float, float]]) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`_sample_offsets` for each (blur px, blur deg, defocus px) of ``blurs``, as rows."""
        # blur direction anticlockwise from x as seen (image y points down)
        along_x = np.array([[blur_px * math.cos(math.radians(deg))] for blur_px, deg, _ in blurs])
        along_y = np.array([[blur_px * math.sin(math.radians(deg))] for blur_px, deg, _ in blurs])
        defocus = np.array([[d] for *_, d in blurs], float)
        return self.sx + along_x * self.st + defocus * self.nx, self.sy - along_y * self.st + defocus * self.ny

    def _separable(
        self, cx: float, cy: float, A: np.ndarray, blur_px: float, blur_deg: float, defocus_px: float
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The marker-frame coordinates as a pixel's part plus a sample's: the model is affine, so
        u = M·(pixel − centre) + M·(sample offset), each part computed once on its own axis
        (pixels, samples) and the grid of every sample of every pixel is one outer sum."""
        sdx, sdy = self._sample_offsets(blur_px, blur_deg, defocus_px)
        pu, pv = _to_marker(self.xs - cx, self.ys - cy, A)
        su, sv = _to_marker(sdx, sdy, A)
        return pu, su, pv, sv

    def uv(
        self, cx: float, cy: float, A: np.ndarray, blur_px: float, blur_deg: float, defocus_px: float
    ) -> tuple[np.ndarray, np.ndarray]:
        """Marker-frame coordinates of every sample of every pixel (pixels × samples)."""
        pu, su, pv, sv = self._separable(cx, cy, A, blur_px, blur_deg, defocus_px)
        return np.add.outer(pu, su), np.add.outer(pv, sv)

    def render(
        self, cx: float, cy: float, A: np.ndarray, blur_px: float, blur_deg: float, defocus_px: float
    ) -> tuple[np.ndarray, np.ndarray]:
        """Mean reflectance per pixel, and the share of its samples that fall on the model."""
        if self.lut is not None:
            # a coded marker is a grid of cells: each sample's cell read from a table (the same
            # values as target_reflectance, a third of the work), its column and row straight
            # from the separable parts, scaled to cells (the table has one more ring around),
            # in blocks of pixels that stay in the cache: 2.8x faster than one pass over every
            # sample. (float32 was a fifth faster again, but read a sample on a cell's edge in
            # the next cell: 1 of 576,000.)
            table, n, half = self.lut
            kernel = compiled("_coded_render")
            if kernel is not None:
                return self._coded_rows(kernel, [(cx, cy, A, blur_px, blur_deg, defocus_px)])[0]
            pu, su, pv, sv = self._separable(cx, cy, A, blur_px, blur_deg, defocus_px)
            pu, pv = pu * n + (half * n + 1), -pv * n + (half * n + 1)
            su, sv = su * n, -sv * n
            packed = np.empty(len(pu))
            for a in range(0, len(pu), _BLOCK):
                col = np.add.outer(pu[a : a + _BLOCK], su)
                row = np.add.outer(pv[a : a + _BLOCK], sv)
                # clipped to the ring, truncation is the floor
                # (np.maximum/np.minimum: np.clip's Python wrapper cost 5 % of a degraded run)
                ci = np.minimum(np.maximum(col, 0, out=col), n + 3, out=col).astype(np.int32)
                ri = np.minimum(np.maximum(row, 0, out=row), n + 3, out=row).astype(np.int32)
                ri *= n + 4
                ri += ci
                packed[a : a + _BLOCK] = table.take(ri).sum(axis=1)
            count = np.floor(packed / _ON)
            white = packed - _ON * count
            return white / np.maximum(count, 1), count / len(su)
        u, v = self.uv(cx, cy, A, blur_px, blur_deg, defocus_px)
        r = _fit_reflectance(self.kind, u, v, self.cells, self.bar)
        ok = np.isfinite(r)
        cover = ok.mean(axis=1)
        value = np.where(ok, r, 0.0).sum(axis=1) / np.maximum(ok.sum(axis=1), 1)
        return value, cover

    def render_rows(
        self, places: list[tuple[float, float, np.ndarray, float, float, float]]
    ) -> list[tuple[np.ndarray, np.ndarray]]:
        """:meth:`render` at each of ``places`` (its arguments), a coded marker's in one compiled call."""
        kernel = compiled("_coded_render", len(places)) if self.lut is not None else None
        if kernel is None:
            return [self.render(*place) for place in places]
        return self._coded_rows(kernel, places)

    def _coded_rows(
        self, kernel: Callable[..., Any], places: list[tuple[float, float, np.ndarray, float, float, float]]
    ) -> list[tuple[np.ndarray, np.ndarray]]:
        assert self.lut is not None
        table, n, half = self.lut
        sdx, sdy = self._offset_rows([place[3:] for place in places])
        value, cover = kernel(
            self.xs, self.ys, np.array([p[0] for p in places], float), np.array([p[1] for p in places], float),
            sdx, sdy, np.array([_inverse(p[2]) for p in places]), table, n, half * n + 1, _ON,
        )  # fmt: skip
        return list(zip(value, cover))

    def ncc_ids(
        self,
        img: np.ndarray,
        w: np.ndarray,
        cx: float,
        cy: float,
        A: np.ndarray,
        blur_px: float,
        blur_deg: float,
        defocus_px: float,
        all_cells: np.ndarray,
    ) -> np.ndarray:
        """:func:`_ncc` of ``img`` with every coded pattern of ``all_cells`` (k, n, n) rendered at
        the same place, without rendering them: a template is linear in its cells (pixel = Σ cell
        share × cell + quiet-zone share), so each correlation's sums are dot products with the
        cells. A dictionary of 2,320 ids in four turns took 8 s per fit rendered; this, a few ms."""
        u, v = self.uv(cx, cy, A, blur_px, blur_deg, defocus_px)
        n = all_cells.shape[1]
        board, inside, idx = coded_cells_at(u, v, n)
        nb = np.maximum(board.sum(axis=1), 1).astype(float)
        rows = np.nonzero(inside)[0]
        W = np.zeros((len(img), n * n))
        np.add.at(W, (rows, idx[inside]), 1.0 / nb[rows])
        const = (board & ~inside).sum(axis=1) / nb
        img = np.asarray(img, float)
        w = np.asarray(w, float)
        sw = w.sum()
        if sw < 8:
            return np.full(len(all_cells), -1.0)
        f = all_cells.reshape(len(all_cells), -1).astype(float)
        s_t = f @ (W.T @ w) + float(w @ const)
        s_it = f @ (W.T @ (w * img)) + float(w @ (img * const))
        s_tt = (
            np.einsum("ki,ij,kj->k", f, W.T @ (w[:, None] * W), f) + 2 * f @ (W.T @ (w * const)) + float(w @ const**2)
        )
        mi = float(w @ img) / sw
        var_i = float(w @ (img - mi) ** 2)
        mt = s_t / sw
        num = s_it - sw * mi * mt
        var_t = np.maximum(s_tt - sw * mt * mt, 0.0)
        den = np.sqrt(var_i * var_t)
        return np.where(den > 1e-12, num / np.where(den > 1e-12, den, 1.0), -1.0)


def _ncc(img: np.ndarray, tpl: np.ndarray, w: np.ndarray) -> float:
    """Weighted normalised correlation."""
    sw = w.sum()
    if sw < 8:
        return -1.0
    mi, mt = (w * img).sum() / sw, (w * tpl).sum() / sw
    di, dt = img - mi, tpl - mt
    den = math.sqrt(float((w * di * di).sum() * (w * dt * dt).sum()))
    return float((w * di * dt).sum() / den) if den > 1e-12 else -1.0


#: Simpler patterns that texture matches about as well as a target: a target without an id must
#: explain its pixels better than each of them (either polarity, any rotation, a small shift) at
#: the fitted place and size. A circle's own alternative (a blob) is the circle: none for it.
ALTERNATIVES = {
    "checkerboard": ("edge", "bar", "corner", "blob"),
    "cross": ("edge", "bar", "corner", "ell", "blob"),
    "circle": ("edge", "bar", "corner"),
}
_ALT_SAMPLES = 8  # per pixel: enough for the margin, a quarter of the fit's cost


def _alternative_templates(kind: str, u: np.ndarray, v: np.ndarray, bar: float) -> np.ndarray:
    """Every alternative of ``kind`` (rotations × shifts × sizes) at marker-frame samples ``u, v``
    (pixels × samples): (k, pixels), each the share of a pixel's samples that are 'on'."""
    out = []
    shifts = (-0.3, -0.15, 0.0, 0.15, 0.3)
    for alt in ALTERNATIVES[kind]:
        period = 180 if alt in ("edge", "bar") else 360
        angles = np.radians(np.arange(0, period, 15)) if alt != "blob" else np.zeros(1)
        for a in angles:
            c, s = math.cos(a), math.sin(a)
            ur, vr = c * u + s * v, -s * u + c * v
            if alt == "edge":
                out += [(ur >= d).mean(axis=1) for d in shifts]
            elif alt == "bar":
                out += [(np.abs(ur - d) <= w / 2).mean(axis=1) for d in shifts for w in (bar, 2 * bar)]
            else:
                for du in (-0.2, 0.0, 0.2):
                    for dv in (-0.2, 0.0, 0.2):
                        x, y = ur - du, vr - dv
                        if alt == "corner":
                            on = (x >= 0) & (y >= 0)
                        elif alt == "blob":
                            out += [(x * x + y * y <= r * r).mean(axis=1) for r in (0.2, 0.35, 0.5)]
                            continue
                        else:  # ell: two arms of the cross (a corner of paths, kerbs)
                            arm_x = (np.abs(y) <= bar / 2) & (x >= -bar / 2) & (x <= 0.5)
                            arm_y = (np.abs(x) <= bar / 2) & (y >= -bar / 2) & (y <= 0.5)
                            on = arm_x | arm_y
                        out.append(on.mean(axis=1))
    return np.array(out, np.float64)


def _best_alternative(
    kind: str, rend: _Renderer, fit: tuple[Any, ...], pix: np.ndarray, weight: np.ndarray, bar: float
) -> float:
    """The best |normalised correlation| of any simpler pattern at the fitted place."""
    sw = weight.sum()
    if sw < 8:
        return 1.0
    cx, cy, A, blen, bdeg, dpx = fit
    u, v = rend.uv(cx, cy, A, blen, bdeg, dpx)
    step = max(1, u.shape[1] // _ALT_SAMPLES)
    tpl = _alternative_templates(kind, u[:, ::step], v[:, ::step], bar)
    di = pix - (weight * pix).sum() / sw
    dt = tpl - (tpl @ weight / sw)[:, None]
    den = np.sqrt((dt * dt) @ weight * float((weight * di * di).sum()))
    ncc = np.where(den > 1e-12, (dt @ (weight * di)) / np.maximum(den, 1e-12), 0.0)
    return float(np.abs(ncc).max())


@cache
def _coded_patterns(dictionary: str) -> np.ndarray:
    """Every id of the dictionary in its four rotations, id-major: (4 × ids, n, n)."""
    n_ids = get_dictionary(dictionary).bytesList.shape[0]
    return np.array([np.rot90(marker_cells(dictionary, i), k) for i in range(n_ids) for k in range(4)])


def estimate_motion_blur(gray: np.ndarray, tile_px: int = 128, max_tiles: int = 24) -> tuple[float, float]:
    """A photo's motion blur (length px, direction deg from the x axis, anticlockwise in the image)
    from the cepstrum of its texture: a straight blur of length L puts a negative peak at L along
    its direction (the zeros of its sinc spectrum repeat every 1/L). (0, 0) when none stands out."""
    h, w = gray.shape[:2]
    if h < tile_px or w < tile_px:
        return 0.0, 0.0
    ny, nx = h // tile_px, w // tile_px
    # the most textured tiles, ranked on every 4th pixel (16x cheaper; a ranking needs no more)
    sub = gray[: ny * tile_px : 4, : nx * tile_px : 4].astype(np.float32)
    var = sub.reshape(ny, tile_px // 4, nx, tile_px // 4).var(axis=(1, 3)).ravel()
    keep = [divmod(int(i), nx) for i in np.argsort(-var)[:max_tiles] if var[i] > 4.0]
    if not keep:
        return 0.0, 0.0
    win = np.outer(np.hanning(tile_px), np.hanning(tile_px)).astype(np.float32)
    power = np.zeros((tile_px, tile_px), np.float64)
    for ty, tx in keep:
        t = gray[ty * tile_px : (ty + 1) * tile_px, tx * tile_px : (tx + 1) * tile_px].astype(np.float32)
        spec = cv2.dft((t - t.mean()) * win, flags=cv2.DFT_COMPLEX_OUTPUT)
        power += cv2.magnitude(spec[..., 0], spec[..., 1]) ** 2
    cep = np.fft.fftshift(np.real(np.fft.ifft2(np.log(power / len(keep) + 1e-3))))
    c = tile_px // 2
    yy, xx = np.mgrid[-c : tile_px - c, -c : tile_px - c]
    r = np.hypot(xx, yy)
    # a real image's cepstrum is symmetric: its peak at (dx, dy) is also at (-dx, -dy), equal to the
    # last bit, and which one argmin took changed from run to run (seen after other work in the same
    # process: the angle then differed by 1e-14 degrees, and marker fits that start from it by up to
    # 0.3 px): one half-plane only
    ring = (r >= 2.5) & (r <= tile_px / 3) & ((yy < 0) | ((yy == 0) & (xx > 0)))
    vals = np.where(ring, cep, np.inf)
    k = int(np.argmin(vals))
    ky, kx = divmod(k, tile_px)
    spread = float(np.std(cep[ring]))
    if -cep[ky, kx] < 4.0 * spread:
        return 0.0, 0.0
    dx, dy = xx[ky, kx], yy[ky, kx]
    return float(math.hypot(dx, dy)), float(math.degrees(math.atan2(-dy, dx)) % 180.0)


def motion_kernel(length_px: float, angle_deg: float) -> np.ndarray:
    """A straight motion-blur kernel: the path of a point moving ``length_px`` at ``angle_deg``
    (anticlockwise from the x axis as seen), its exact length: a camera's blur is not a whole
    number of pixels (an odd-sized line kernel made 7.6 px a 9 px blur while the truth said 7.6).
    The path is sampled finely and spread over the pixels it crosses (bilinear)."""
    n = max(2, int(math.ceil(16 * length_px)))
    t = ((np.arange(n) + 0.5) / n - 0.5) * length_px
    a = math.radians(angle_deg)
    r = int(math.ceil(length_px / 2)) + 1
    x, y = r + t * math.cos(a), r - t * math.sin(a)
    return spread_path(x, y, np.ones_like(t), 2 * r + 1)


def spread_path(x: np.ndarray, y: np.ndarray, weight: np.ndarray, size: int) -> np.ndarray:
    """A kernel ``size`` square from the samples of a path (pixel x, y, and each sample's weight),
    each spread over the four pixels around it (bilinear); normalised to sum 1."""
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    fx, fy = x - x0, y - y0
    kernel = np.zeros((size, size), np.float64)
    for dx, dy, wgt in ((0, 0, (1 - fx) * (1 - fy)), (1, 0, fx * (1 - fy)), (0, 1, (1 - fx) * fy), (1, 1, fx * fy)):
        np.add.at(kernel, (y0 + dy, x0 + dx), wgt * weight)
    result: np.ndarray = (kernel / kernel.sum()).astype(np.float32)
    return result


#: The Wiener filter's noise-to-signal power (of a spectrum normalised to the kernel's): of 0.003,
#: 0.01 and 0.03, the first decoded the most blurred markers (a degraded flight and three small
#: surveys, 4-10 px of blur on 14-16 px markers: 84, 29, 22 and 30 of 106, 47, 47 and 47).
DEBLUR_NOISE = 0.003


def deblurred(gray: np.ndarray, blur: tuple[float, float]) -> np.ndarray:
    """A grey crop with a straight motion ``blur`` (length px, direction deg) undone by a Wiener
    filter, as uint8. The blur's sinc spectrum has zeros that no inverse crosses: the filter leaves
    those frequencies out, and a marker's cells come back sharp enough for the detector to read,
    its centre as well as a model fit places it (:func:`.detect._search`)."""
    img = gray.astype(np.float64)
    kernel = motion_kernel(*blur).astype(np.float64)
    pad = np.zeros(img.shape)
    kh, kw = kernel.shape
    pad[:kh, :kw] = kernel
    pad = np.roll(pad, (-(kh // 2), -(kw // 2)), axis=(0, 1))  # centred on the origin: no shift
    H = np.fft.rfft2(pad)
    out = np.fft.irfft2(np.fft.rfft2(img) * np.conj(H) / (np.abs(H) ** 2 + DEBLUR_NOISE), s=img.shape)
    return np.clip(np.rint(out), 0, 255).astype(np.uint8)


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
    :func:`_affine`'s angle) is known to a few degrees, modulo its period: only the rotations
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
        out = _coarse_reach(kind, base, cells, blur) + 1
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
    coarse = _coarse(
        matched, kind, base, cells, blur, max_peaks=4 if by_place else 6, absolute=by_place, near=within,
        turn_deg=turn_deg, photo=photo,
    )  # fmt: skip
    if not coarse:
        return None
    verdict = partial(_verdict, crop, box, kind, base, cells, dictionary, marker_id, by_place)
    coded_id = kind in CODED and bool(dictionary) and cells is not None
    side = float(np.sqrt(abs(np.linalg.det(base))))
    scored: list[_Candidate] = []
    for cx, cy, a, size_f, _ in coarse:
        cand = _score(crop, kind, base * size_f, cells, (cx, cy, a), blur)
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
    cand: _Candidate,
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
        cx, cy = _saddle(crop, cx, cy, A)
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
    cand: _Candidate,
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
    (cx, cy, ang, scale, e1, e2, blen, bdeg, dpx, _), _ = _refine(
        crop, kind, base, cells, start, blur, converge=True, shape=size
    )
    # the model's 32 samples a pixel leave it a few grey levels off the exact integral, enough to
    # hold a centre 0.05-0.2 px from the optimum; a few steps with 256 take it there
    (cx, cy, *_), _ = _refine(
        crop, kind, base, cells, (cx, cy, ang), (blen, bdeg), converge=True, shape=(scale, e1, e2, dpx),
        samples=CENTRE_SUBSAMPLES, evaluations=CENTRE_EVALUATIONS,
    )  # fmt: skip
    dx, dy = cx - cand.cx, cy - cand.cy
    # a pixel or more away is not the same optimum, but along the blur, where the polish could not
    # tell the place (see _along_blur)
    b = math.radians(cand.bdeg)
    along = dx * math.cos(b) - dy * math.sin(b)
    across = math.hypot(dx - along * math.cos(b), dy + along * math.sin(b))
    if across >= 1.0 or abs(along) >= 1.0 + _along_reach(cand.blen):
        return fit
    corners = tuple((x + dx, y + dy) for x, y in fit.corners_px)
    return replace(fit, x_px=float(cx + box[0]), y_px=float(cy + box[1]), corners_px=corners)


def _id_scores(cand: _Candidate, cells: np.ndarray, dictionary: str, marker_id: int) -> tuple[float, float]:
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
    scores = list(rend.ncc_ids(pix, weight * on_code, cx, cy, A, blen, bdeg, dpx, _coded_patterns(dictionary)))
    mine = slice(4 * marker_id, 4 * marker_id + 4)
    id_score = max(scores[mine])
    return id_score, id_score - max(scores[: mine.start] + scores[mine.stop :])


def _shape_margin(kind: str, f: _Candidate) -> float:
    """A fit's score over the best simpler pattern at its place (NaN: coded, or not worth asking)."""
    if kind not in ALTERNATIVES or f.score < min_score(kind) or f.contrast < min_contrast(kind):
        return math.nan
    alt = _best_alternative(kind, f.rend, (f.cx, f.cy, f.A, f.blen, f.bdeg, f.dpx), f.pix, f.weight, f.rend.bar)
    return f.score - alt


def _passes(kind: str, f: _Candidate, shape_margin: float) -> bool:
    """Would this fit of a target without an id be accepted on its own (score, contrast, parts, shape)?"""
    t = THRESHOLDS
    return (
        f.score >= min_score(kind)
        and f.contrast >= min_contrast(kind)
        and shape_margin >= t["shape_margin"]
        and not f.worst_part > t["worst_part"]
    )


class _Candidate(NamedTuple):
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
    rend: _Renderer
    pix: np.ndarray  # the scored pixels, their weights
    weight: np.ndarray
    contrast: float  # fitted white − black, grey levels
    worst_part: float


def _score(
    crop: np.ndarray,
    kind: str,
    base: np.ndarray,
    cells: np.ndarray | None,
    start: tuple[float, float, float],
    blur: tuple[float, float],
) -> _Candidate:
    """Refine from one candidate; its final score on every pixel the model covers (saturated ones
    out, but for a coded marker's clipped paint: :func:`_censored`)."""
    fit, glare = _refine(crop, kind, base, cells, start, blur)
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
    A = _affine(base, angle, scale, e1, e2)
    half = target_half_extent(kind, cells)
    reach = int(math.ceil(np.abs(A).sum(axis=1).max() * half + blen / 2 + 2 * dpx + 2))
    gx0, gx1 = max(0, int(cx) - reach), min(crop.shape[1], int(cx) + reach + 2)
    gy0, gy1 = max(0, int(cy) - reach), min(crop.shape[0], int(cy) + reach + 2)
    ys, xs = np.mgrid[gy0:gy1, gx0:gx1]
    rend = _Renderer(kind, cells, xs, ys, bar)
    tpl, cover = rend.render(cx, cy, A, blen, bdeg, dpx)
    band = _cross_band(xs.ravel() - cx, ys.ravel() - cy, A, bar) if kind == "cross" else True
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
            p, w = _censored(p, tpl, w, cover, raw[gy0:gy1, gx0:gx1].ravel(), g)
        score = _ncc(p, tpl, w)
        if score > best:
            best, pix, weight = score, p, w
    # the fitted contrast (white − black, grey levels): the least-squares gain of the model
    gain, _, _ = _level_fit(pix, tpl, weight)
    worst = _worst_part(kind, xs.ravel() - cx, ys.ravel() - cy, A, pix, tpl, weight, gain)
    return _Candidate(best, cx, cy, angle, scale, blen, bdeg, dpx, A, rend, pix, weight, gain, worst)


def _censored(
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
    gain, offset, var = _level_fit(pix, tpl, w)
    if var < 1e-9:
        return pix, w
    mid = offset + 0.5 * gain
    bound = SATURATED - (0.0 if glare is None else glare)
    says = hot & (gain > 0) & (bound > mid)
    if not says.any():
        return pix, w
    return np.where(says, bound, pix), np.where(says, 1.0, w)


def _level_fit(pix: np.ndarray, tpl: np.ndarray, w: np.ndarray) -> tuple[float, float, float]:
    """Weighted least squares of the pixels on the template: gain (white − black, grey levels),
    offset (black), and the template's weighted variance (near 0: the gain means nothing)."""
    sw = max(w.sum(), 1e-9)
    mt = (w * tpl).sum() / sw
    dt = tpl - mt
    var = float((w * dt * dt).sum())
    gain = float((w * dt * pix).sum() / max(var, 1e-12))
    return gain, float((w * pix).sum() / sw - gain * mt), var


def _cross_band(dx: np.ndarray, dy: np.ndarray, A: np.ndarray, bar: float) -> np.ndarray:
    """Pixels (offsets from the centre) on a cross's bars or the ground right beside them.

    A cross is its bars and their edges: the ground further in between the arms (grass,
    tarmac) is not part of the target and, textured, only lowers the score of the true one."""
    u, v = _to_marker(dx, dy, A)
    side_px = math.sqrt(abs(np.linalg.det(A)))
    result: np.ndarray = np.minimum(np.abs(u), np.abs(v)) <= bar / 2 + max(0.1, 1.5 / side_px)
    return result


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


def _worst_part(
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
    part = _parts(kind, *_to_marker(dx, dy, A))
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


def _angles(kind: str) -> np.ndarray:
    """Rotations to try, 10° apart over the target's period (a circle has none). A coded marker is
    searched by its border alone, square: over 90°, its quarter turn told by the code after."""
    if kind == "circle":
        return np.array([0.0])
    return np.arange(0.0, {"checkerboard": 180.0}.get(kind, 90.0), 10.0)


def _coarse_reach(kind: str, base: np.ndarray, cells: np.ndarray | None, blur: tuple[float, float]) -> int:
    """The coarse templates' half size (px): the target's board turned any way, 20 % larger, and half
    its blur."""
    return int(math.ceil(np.abs(base).sum(axis=1).max() * target_half_extent(kind, cells) * 1.2 + blur[0] / 2 + 1))


def _coarse(
    crop: np.ndarray,
    kind: str,
    base: np.ndarray,
    cells: np.ndarray | None,
    blur: tuple[float, float],
    max_peaks: int = 3,
    absolute: bool = False,
    near: tuple[float, float, float] | None = None,
    turn_deg: float | None = None,
    photo: tuple[int, int, int, int] | None = None,
) -> list[tuple[float, float, float, float, float]] | None:
    """Candidate positions, rotations and sizes by masked template matching, best first;
    ``near`` (x, y, radius in crop pixels): centres within radius of (x, y) only; ``turn_deg``:
    rotations within 10° of it only (see :func:`fit_target`); ``photo`` (x0, y0, x1, y1): centres
    in this part of the crop only (the rest lies beyond the photo's edge)."""
    reach = _coarse_reach(kind, base, cells, blur)
    size = 2 * reach + 1
    if size >= min(crop.shape):
        return None
    ys, xs = np.mgrid[0:size, 0:size]
    rend = _Renderer(kind, cells, xs, ys)
    coded = kind in CODED and cells is not None
    maps, used = [], []
    # the predicted size is off by the camera height's error (10 % is common): three sizes
    angles = _angles(kind)
    if turn_deg is not None and len(angles) > 1:
        period = 10.0 * len(angles)
        off = np.abs((angles - turn_deg + period / 2) % period - period / 2)
        angles = angles[off <= 10.0]
    places = None
    if near is not None:
        # the place is known to a few pixels: the correlation is needed there only (a disc of some
        # 20 places), not over the crop (OpenCV's masked match costs its Fourier transforms
        # whatever the crop: 1.9 ms a template on a 45 px crop, 0.1 ms at the disc's places)
        disc = _near_disc((crop.shape[0] - size + 1, crop.shape[1] - size + 1), reach, near)
        at = (int(round(near[1])) - reach, int(round(near[0])) - reach)
        if 0 <= at[0] < disc.shape[0] and 0 <= at[1] < disc.shape[1]:
            disc[at] = True
        places = np.nonzero(disc)
        windows = np.lib.stride_tricks.sliding_window_view(crop, (size, size))[places].astype(np.float64)
    for angle, scale in ((a, f) for a in angles for f in (0.88, 1.0, 1.12)):
        A = _affine(base, float(angle), scale, 0.0, 0.0)
        tpl, cover = rend.render(reach, reach, A, blur[0], blur[1], 0.5)
        t = tpl.reshape(size, size).astype(np.float32)
        keep = cover > 0.999
        if kind == "cross":
            keep &= _cross_band(xs.ravel() - reach, ys.ravel() - reach, A, CROSS_BAR)
        elif coded:
            keep &= ~_code_cells(xs.ravel() - reach, ys.ravel() - reach, A, cells)
        m = keep.reshape(size, size).astype(np.float32)
        if m.sum() < 8 or t[m > 0].std() < 1e-3:
            continue
        if places is None:
            res = cv2.matchTemplate(crop, t, cv2.TM_CCOEFF_NORMED, mask=m)
            res = np.nan_to_num(res, nan=-1.0, posinf=-1.0, neginf=-1.0)
        else:
            res = np.full(disc.shape, -2.0, np.float32)  # (where _near_candidates never looks)
            res[places] = _masked_ncc(windows, t, m)
        if photo is not None:  # no centre beyond the edge
            beyond = np.ones(res.shape, bool)
            beyond[max(0, photo[1] - reach) : photo[3] - reach, max(0, photo[0] - reach) : photo[2] - reach] = False
            res[beyond] = -1.0
        maps.append(res)
        used.append((float(angle), scale))
    if not maps:
        return None
    # the peaks of every rotation at distinct places, best first (a glare spot can lower the
    # true one below a look-alike: each is refined and the fits compete)
    top = np.max(maps, axis=0)
    angle_of = np.argmax(maps, axis=0)
    side = float(np.sqrt(abs(np.linalg.det(base))))
    out: list[tuple[float, float, float, float, float]] = []
    if near is not None:
        return _near_candidates(crop, kind, base, blur, rend, maps, used, reach, near, coded)
    work = top.copy()
    for _ in range(max_peaks):
        _, mx, _, loc = cv2.minMaxLoc(work)
        if mx < (0.6 if absolute else 0.3) or (out and mx < out[0][4] - (0.3 if absolute else 0.5)):
            break
        a, f = used[angle_of[loc[1], loc[0]]]
        if coded:
            a = _quarter_turn(crop, rend, loc, base, a, f, blur)
        out.append((loc[0] + reach, loc[1] + reach, a, f, float(mx)))
        cv2.circle(work, loc, int(math.ceil(0.75 * side)), -2.0, -1)
    return out


def _near_disc(shape: tuple[int, int], reach: int, near: tuple[float, float, float]) -> np.ndarray:
    """Of a match map (``shape``; a place is its template's corner, ``reach`` px from the centre),
    the places whose centre lies within ``near`` (x, y, radius; crop pixels)."""
    ry, rx = np.mgrid[0 : shape[0], 0 : shape[1]]
    result: np.ndarray = np.hypot(rx + reach - near[0], ry + reach - near[1]) <= near[2]
    return result


def _masked_ncc(windows: np.ndarray, t: np.ndarray, m: np.ndarray) -> np.ndarray:
    """OpenCV's masked TM_CCOEFF_NORMED of template ``t`` (mask ``m``, 0 or 1) on each of
    ``windows`` (k × its shape): the template and each window less their means over the mask,
    correlated over it; -1 where either is flat there."""
    w = m.astype(np.float64)
    n = w.sum()
    tz = w * (t - (w * t).sum() / n)
    num = np.einsum("kij,ij->k", windows, tz)
    s1 = np.einsum("kij,ij->k", windows, w)
    s2 = np.einsum("kij,ij->k", windows * windows, w)
    den = (tz * tz).sum() * (s2 - s1 * s1 / n)
    with np.errstate(invalid="ignore", divide="ignore"):
        out = num / np.sqrt(den)
    return np.where(den > 0, out, -1.0)


def _near_candidates(
    crop: np.ndarray,
    kind: str,
    base: np.ndarray,
    blur: tuple[float, float],
    rend: _Renderer,
    maps: list[np.ndarray],
    used: list[tuple[float, float]],
    reach: int,
    near: tuple[float, float, float],
    coded: bool,
) -> list[tuple[float, float, float, float, float]]:
    """Candidates where the place is known (``near``: x, y, radius in crop pixels)."""
    top_shape = maps[0].shape
    out: list[tuple[float, float, float, float, float]] = []
    # the place is known to a few pixels, the turn is not: the best place of each rotation
    # there, each refined (under glare the best rotation's peak can be one 20 degrees off)
    outside = ~_near_disc(top_shape, reach, near)
    by_angle: dict[float, tuple[float, Sequence[int], float]] = {}
    for res, (a, f) in zip(maps, used):
        r = np.where(outside, -2.0, res)
        _, mx, _, loc = cv2.minMaxLoc(r)
        if mx > by_angle.get(a, (-3.0,))[0]:
            by_angle[a] = (float(mx), loc, f)
    ranked = sorted(by_angle.items(), key=lambda kv: -kv[1][0])
    for a, (mx, loc, f) in ranked[:3]:
        if coded:
            a = _quarter_turn(crop, rend, loc, base, a, f, blur)
        out.append((loc[0] + reach, loc[1] + reach, a, f, mx))
    # and every rotation from the known place itself, best there first (a coded fit stops at the
    # first that passes): blur and glare pull the peaks a few pixels aside, and the short polish
    # does not bring them back. (Only the three best cost 3 of 545 markers on the degraded small
    # surveys and saved under a tenth of the time.)
    at = (int(round(near[0])) - reach, int(round(near[1])) - reach)
    if 0 <= at[0] < top_shape[1] and 0 <= at[1] < top_shape[0]:
        turns = sorted({a for a, _ in used})
        here = [(max(res[at[1], at[0]] for res, (b, _) in zip(maps, used) if b == a), a) for a in turns]
        for mx, a in sorted(here, reverse=True):
            if coded:
                a = _quarter_turn(crop, rend, at, base, a, 1.0, blur)
            out.append((near[0], near[1], float(a), 1.0, float(mx)))
    return out


def _code_cells(dx: np.ndarray, dy: np.ndarray, A: np.ndarray, cells: np.ndarray | None) -> np.ndarray:
    """Pixels (offsets from the centre) on a coded marker's code cells, inside its black border."""
    u, v = _to_marker(dx, dy, A)
    lim = 0.5 - 1.0 / (6 if cells is None else cells.shape[0])
    result: np.ndarray = (np.abs(u) < lim) & (np.abs(v) < lim)
    return result


def _quarter_turn(
    crop: np.ndarray,
    rend: _Renderer,
    loc: Sequence[int],
    base: np.ndarray,
    angle: float,
    scale: float,
    blur: tuple[float, float],
) -> float:
    """Of a coded marker's border found at ``angle``, the quarter turn whose code matches best."""
    size = int(math.isqrt(rend.xs.size))
    reach = size // 2
    patch = crop[loc[1] : loc[1] + size, loc[0] : loc[0] + size].astype(np.float64).ravel()
    best, out = -math.inf, angle
    for k in range(4):
        a = angle + 90.0 * k
        tpl, cover = rend.render(reach, reach, _affine(base, a, scale, 0.0, 0.0), blur[0], blur[1], 0.5)
        score = _ncc(patch, tpl, (cover > 0.999).astype(np.float64))
        if score > best:
            best, out = score, a
    return out


def _refine(
    crop: np.ndarray,
    kind: str,
    base: np.ndarray,
    cells: np.ndarray | None,
    start: tuple[float, float, float],
    blur: tuple[float, float],
    converge: bool | None = None,
    shape: tuple[float, float, float, float] = (1.0, 0.0, 0.0, 0.7),
    samples: int = SUBSAMPLES,
    evaluations: int = 30,
) -> tuple[tuple[float, ...], tuple[int, int, np.ndarray] | None]:
    """Least-squares fit of the model's geometry, blur and defocus to the pixels around ``start``
    (and ``shape``: scale, shape correction e1 and e2, defocus px), with its optimiser run to
    convergence (``converge``; by default for :data:`CONVERGED` kinds)."""
    # One piece: the model, its glare term, residuals and bounds are closures over the patch's
    # pixels, mask and renderer; split, they would pass the same eight arrays to each other.
    from scipy.optimize import least_squares

    cx0, cy0, angle0 = start
    half = target_half_extent(kind, cells)
    reach = int(math.ceil(np.abs(base).sum(axis=1).max() * half * 1.15 + blur[0] / 2 + 3))
    gx0, gx1 = max(0, int(cx0) - reach), min(crop.shape[1], int(cx0) + reach + 1)
    gy0, gy1 = max(0, int(cy0) - reach), min(crop.shape[0], int(cy0) + reach + 1)
    ys, xs = np.mgrid[gy0:gy1, gx0:gx1]
    pix = crop[gy0:gy1, gx0:gx1].ravel().astype(np.float64)
    rend = _Renderer(kind, cells, xs, ys)
    A0 = _affine(base, angle0, 1.0, 0.0, 0.0)
    # A coded marker's board (quiet zone included) stands on ground of its own: a blurred pixel at
    # the board's rim is partly board, partly ground. The model gives the board's share and the
    # ground beyond it is one more level, solved with the gain: the rims' ramps, where the border's
    # edges are, then place the marker along the blur too. On six degraded small surveys (seeds 11
    # and 5, three renderings each) a fit 3.0 px off is gone and the mean centre error falls by
    # 0.01-0.05 px, recall within 2 markers of 90 either way. The other targets keep the pixels
    # wholly on the model, on which their thresholds were calibrated.
    rim = kind in CODED
    if rim:
        _, cover0 = rend.render(cx0, cy0, A0, blur[0], blur[1], 0.7)
        use = (cover0 > 0.5) & (pix < SATURATED)
    else:
        _, cover0 = rend.render(cx0, cy0, A0 * 0.9, 0.0, 0.0, 0.0)
        use = (cover0 > 0.999) & (pix < SATURATED)
    if use.sum() < 12:
        use = (cover0 > 0.5) & ~np.isnan(pix)
    bx, by = blur[0] * math.cos(math.radians(blur[1])), blur[0] * math.sin(math.radians(blur[1]))
    side = float(np.sqrt(abs(np.linalg.det(base))))
    # A glare spot: an additive bright blob (its saturated core is masked), fitted as one more
    # term where the patch has saturated pixels, started at their centroid.
    hot = pix >= SATURATED
    glare = bool(hot.any())
    gx, gy = (xs.ravel()[hot].mean(), ys.ravel()[hot].mean()) if glare else (cx0, cy0)
    # blur as a vector (x, y): no wrap-around of its direction for the optimiser
    scale0, e10, e20, defocus0 = shape
    x0 = np.array(
        [cx0, cy0, angle0, math.log(scale0), e10, e20, bx, by, defocus0, CROSS_BAR, gx, gy, math.log(0.25 * side)]
    )
    free = [i for i in range(13) if (i != 9 or kind == "cross") and (i < 10 or glare)]
    # Clipped pixels (white paint in sun, glare) are censored: they say the model is at least the
    # clip there. Scored one-sided, they pull a model that is darker there, never a brighter one.
    if rim:
        use = use | ((cover0 > 0.5) & (pix >= SATURATED))
    censor = hot[use] if rim else np.zeros(int(use.sum()), bool)
    solved = ~censor  # the rows the levels are solved on
    xf, yf = xs.ravel()[use].astype(float), ys.ravel()[use].astype(float)
    # the fit renders only the pixels it uses (a pixel's value depends on no other): 30-48 % of
    # the patch's square (median 42 %, the tiny degraded survey's 63 refinements)
    fitted = _Renderer(kind, cells, xf, yf, samples=samples)

    def placed(p: np.ndarray) -> tuple[float, float, np.ndarray, float, float, float]:
        """The renderer's arguments at ``p``: centre, affine, blur length and direction, defocus."""
        cx, cy, ang, ls, e1, e2, vx, vy, dpx = p[:9]
        A = _affine(base, ang, math.exp(ls), e1, e2)
        return cx, cy, A, math.hypot(vx, vy), math.degrees(math.atan2(vy, vx)), abs(dpx)

    def model(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        fitted.bar = min(max(float(p[9]), 0.08), 0.45)
        return fitted.render(*placed(p))

    path = _offsets(samples)[2][None, :]  # the motion path's samples, as the target's (−½…½)

    def spot(p: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        # the glare is in the scene, so the camera's motion smears it as it smears the target:
        # the spot averaged along the same path (a spot narrower than the blur makes a flat-topped
        # streak, not a longer Gaussian)
        var = math.exp(2 * p[12])
        kernel = compiled("_glare_exponent")
        if kernel is not None:
            e = kernel(x.ravel().astype(float), y.ravel().astype(float), p[10], p[11], p[6], p[7], path[0], var)
            result: np.ndarray = np.exp(e, out=e).mean(axis=1).reshape(x.shape)
            return result
        dx = x.ravel()[:, None] - p[10] + p[6] * path
        dy = y.ravel()[:, None] - p[11] - p[7] * path
        result = np.exp(-(dx * dx + dy * dy) / (2 * var)).mean(axis=1).reshape(x.shape)
        return result

    # A difference step in one parameter moves the model or the glare term, never both (but for
    # the blur's): each term is kept by the parameters it depends on, and a Jacobian's columns for
    # the other term's reuse it (a glare fit's 13 columns: 3 renders and 8 spots saved).
    rendered: dict[bytes, tuple[np.ndarray, np.ndarray]] = {}
    spotted: dict[bytes, np.ndarray] = {}

    no_spot = np.empty(0)

    def terms(p: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The model (its value and share on each pixel) and the glare term (empty: none), kept."""
        t, cover = _kept(rendered, p[:10].tobytes(), lambda: model(p), 32)
        return t, cover, glare_term(p)

    def glare_term(p: np.ndarray) -> np.ndarray:
        return _kept(spotted, p[[6, 7, 10, 11, 12]].tobytes(), lambda: spot(p, xf, yf), 32) if glare else no_spot

    def design(p: np.ndarray) -> np.ndarray:
        t, cover, g = terms(p)
        cols = [t * cover, 1.0 - cover, np.ones_like(t)] if rim else [t, np.ones_like(t)]
        return np.column_stack([*cols, g] if glare else cols)

    seen = pix[use]
    seen_solved = seen[solved]

    def models(ps: list[np.ndarray]) -> list[tuple[np.ndarray, np.ndarray]]:
        """:func:`model` at each of ``ps``, kept as :func:`terms` keeps it; a coded marker's that
        are not kept rendered in one call."""
        keys = [p[:10].tobytes() for p in ps]
        out = {key: rendered[key] for key in keys if key in rendered}
        todo = {key: p for key, p in zip(keys, ps) if key not in out}
        if todo:
            if fitted.lut is not None:
                made = fitted.render_rows([placed(p) for p in todo.values()])
            else:
                made = [model(p) for p in todo.values()]
            out.update(zip(todo, made))
            if len(rendered) + len(todo) > 32:
                rendered.clear()
            rendered.update(zip(todo, made))
        return [out[key] for key in keys]

    def residual_rows(qs: np.ndarray) -> np.ndarray:
        """The residuals at each row of ``qs`` (free parameters): the Jacobian's columns and a
        scan's points each in one compiled call of the render and one of the levels."""
        ps = []
        for q in qs:
            p = x0.copy()
            p[free] = q
            ps.append(p)
        kernel = compiled("_level_residuals", len(ps))
        if kernel is None:
            rows = []
            for p in ps:
                d = design(p)
                # gain, offset (and glare amplitude) in closed form
                coef, *_ = np.linalg.lstsq(d[solved], seen_solved, rcond=None)
                r = d @ coef - seen
                r[censor] = np.minimum(r[censor], 0.0)
                rows.append(r / 8.0)
            return np.array(rows)
        looks = models(ps)
        spots = [glare_term(p) for p in ps]
        t, cover = np.array([m[0] for m in looks]), np.array([m[1] for m in looks])
        result: np.ndarray = kernel(t, cover, np.array(spots).reshape(len(ps), -1), rim, seen, solved, censor)
        return result

    def residuals(q: np.ndarray) -> np.ndarray:
        result: np.ndarray = residual_rows(q[None])[0]
        return result

    def batched(fun: Callable[[np.ndarray], np.ndarray], points: Iterable[np.ndarray]) -> np.ndarray:
        # scipy's map for its finite differences, whose fun is the residuals: the points at once
        return residual_rows(np.array(list(points)))

    # Motion blur is the photo's (measured from its texture), so the target's stays near it, and
    # defocus is a pixel or two: a model free to smear itself fits any texture.
    tol = max(2.5, 0.4 * blur[0])
    max_defocus = 1.0 + 0.08 * side
    x0[8] = min(x0[8], 0.9 * max_defocus)
    # the estimate can be wrong on real texture: the box holds both no blur and the estimate
    bx_lo, bx_hi, by_lo, by_hi = min(0.0, bx) - tol, max(0.0, bx) + tol, min(0.0, by) - tol, max(0.0, by) + tol
    lo = np.array([cx0 - reach, cy0 - reach, angle0 - 25, -0.25, -0.2, -0.2, bx_lo, by_lo, 0.0, 0.08])
    hi = np.array([cx0 + reach, cy0 + reach, angle0 + 25, 0.25, 0.2, 0.2, bx_hi, by_hi, max_defocus, 0.45])
    lo = np.r_[lo, gx - side, gy - side, math.log(0.05 * side + 0.5)]
    hi = np.r_[hi, gx + side, gy + side, math.log(side + 1.0)]
    x0 = np.clip(x0, lo, hi)  # (a start from an earlier fit may sit a rounding error outside)
    try:
        if (kind in CONVERGED) if converge is None else converge:
            p = _converge(residual_rows, x0, free, lo, hi, side, evaluations)
            if rim:
                p = _along_blur(residual_rows, p, free, lo, hi)
        else:
            scales = np.array([0.3, 0.3, 2.0, 0.03, 0.03, 0.03, 1.0, 1.0, 0.3, 0.02, 1.0, 1.0, 0.1])
            sol = least_squares(
                residuals,
                x0[free],
                bounds=(lo[free], hi[free]),
                loss="soft_l1",
                f_scale=2.0,
                diff_step=1e-3,
                max_nfev=80,
                xtol=POLISH_XTOL,
                x_scale=scales[free],
                workers=batched,
            )
            p = x0.copy()
            p[free] = sol.x
            if rim:  # the verdict's place too: a marker scored 1 px off along its blur scores low
                p = _along_blur(residual_rows, p, free, lo, hi)
    except (ValueError, np.linalg.LinAlgError):
        p = x0
    glare_img = None
    if glare:
        # the fitted glare, to take off the pixels before scoring
        d = design(p)
        coef, *_ = np.linalg.lstsq(d[solved], seen_solved, rcond=None)
        gxx, gyy = xs.astype(float), ys.astype(float)
        glare_img = coef[-1] * spot(p, gxx, gyy)  # the last term
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
    ), (None if glare_img is None else (gx0, gy0, glare_img))


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
    """:func:`_refine`'s least squares, run to convergence: the parameters (``x0``, the ``free``
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
        result: np.ndarray = _kept(last, d.tobytes(), lambda: residual_rows((start + d * unit)[None])[0], 0).copy()
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


def _along_reach(blur_px: float) -> float:
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
    """The fitted parameters ``p`` (:func:`_refine`'s) with the centre moved along the blur to where
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
    reach = max(1.0, _along_reach(length))
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


def _saddle(crop: np.ndarray, cx: float, cy: float, A: np.ndarray) -> tuple[float, float]:
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
