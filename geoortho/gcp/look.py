"""A target as a photo shows it: its reflectance carried through the projection's local affine, rendered
with the photo's motion blur and defocus (sub-pixel samples), and the look-alikes a fit must beat.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from functools import cache
from typing import Any, TypeVar

import numpy as np

from geoortho.gcp.kernels import compiled
from geoortho.gcp.markers import (
    CODED,
    CROSS_BAR,
    coded_cells_at,
    get_dictionary,
    marker_cells,
    target_half_extent,
    target_reflectance,
)

SUBSAMPLES = 32  # per pixel: pixel area, motion path and defocus at once


_T = TypeVar("_T")


def kept_in(store: dict[bytes, _T], key: bytes, make: Callable[[], _T], keep: int) -> _T:
    """``store[key]``, made by ``make()`` when missing; the store is emptied first when it holds
    more than ``keep`` (a fit's evaluations come near each other: the latest few are the ones asked
    again)."""
    if key not in store:
        if len(store) > keep:
            store.clear()
        store[key] = make()
    return store[key]


@cache
def subsample_offsets(n: int = SUBSAMPLES) -> tuple[np.ndarray, ...]:
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


def marker_affine(base: np.ndarray, angle_deg: float, scale: float, e1: float, e2: float) -> np.ndarray:
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


def to_marker(dx: np.ndarray, dy: np.ndarray, A: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixel offsets from the centre → marker-frame coordinates (sides), through ``A``'s inverse."""
    i00, i01, i10, i11 = _inverse(A)
    return i00 * dx + i01 * dy, i10 * dx + i11 * dy


class Renderer:
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
        self.sx, self.sy, self.st, self.nx, self.ny = subsample_offsets(samples)
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
        pu, pv = to_marker(self.xs - cx, self.ys - cy, A)
        su, sv = to_marker(sdx, sdy, A)
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
        """:func:`masked_ncc_score` of ``img`` with every coded pattern of ``all_cells`` (k, n, n) rendered at
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


def masked_ncc_score(img: np.ndarray, tpl: np.ndarray, w: np.ndarray) -> float:
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


def best_alternative(
    kind: str, rend: Renderer, fit: tuple[Any, ...], pix: np.ndarray, weight: np.ndarray, bar: float
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
def coded_patterns(dictionary: str) -> np.ndarray:
    """Every id of the dictionary in its four rotations, id-major: (4 × ids, n, n)."""
    n_ids = get_dictionary(dictionary).bytesList.shape[0]
    return np.array([np.rot90(marker_cells(dictionary, i), k) for i in range(n_ids) for k in range(4)])
