"""The coarse search for a target: its template at every rotation correlated with the window round the
prediction, and the candidates near it.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import cv2
import numpy as np

from geoortho.gcp.look import Renderer, marker_affine, masked_ncc_score, to_marker
from geoortho.gcp.markers import (
    CODED,
    CROSS_BAR,
    target_half_extent,
)


def cross_band_of(dx: np.ndarray, dy: np.ndarray, A: np.ndarray, bar: float) -> np.ndarray:
    """Pixels (offsets from the centre) on a cross's bars or the ground right beside them.

    A cross is its bars and their edges: the ground further in between the arms (grass,
    tarmac) is not part of the target and, textured, only lowers the score of the true one."""
    u, v = to_marker(dx, dy, A)
    side_px = math.sqrt(abs(np.linalg.det(A)))
    result: np.ndarray = np.minimum(np.abs(u), np.abs(v)) <= bar / 2 + max(0.1, 1.5 / side_px)
    return result


def _angles(kind: str) -> np.ndarray:
    """Rotations to try, 10° apart over the target's period (a circle has none). A coded marker is
    searched by its border alone, square: over 90°, its quarter turn told by the code after."""
    if kind == "circle":
        return np.array([0.0])
    return np.arange(0.0, {"checkerboard": 180.0}.get(kind, 90.0), 10.0)


def coarse_reach(kind: str, base: np.ndarray, cells: np.ndarray | None, blur: tuple[float, float]) -> int:
    """The coarse templates' half size (px): the target's board turned any way, 20 % larger, and half
    its blur."""
    return int(math.ceil(np.abs(base).sum(axis=1).max() * target_half_extent(kind, cells) * 1.2 + blur[0] / 2 + 1))


def coarse_search(
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
    reach = coarse_reach(kind, base, cells, blur)
    size = 2 * reach + 1
    if size >= min(crop.shape):
        return None
    ys, xs = np.mgrid[0:size, 0:size]
    rend = Renderer(kind, cells, xs, ys)
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
        A = marker_affine(base, float(angle), scale, 0.0, 0.0)
        tpl, cover = rend.render(reach, reach, A, blur[0], blur[1], 0.5)
        t = tpl.reshape(size, size).astype(np.float32)
        keep = cover > 0.999
        if kind == "cross":
            keep &= cross_band_of(xs.ravel() - reach, ys.ravel() - reach, A, CROSS_BAR)
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
    rend: Renderer,
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
    u, v = to_marker(dx, dy, A)
    lim = 0.5 - 1.0 / (6 if cells is None else cells.shape[0])
    result: np.ndarray = (np.abs(u) < lim) & (np.abs(v) < lim)
    return result


def _quarter_turn(
    crop: np.ndarray,
    rend: Renderer,
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
        tpl, cover = rend.render(reach, reach, marker_affine(base, a, scale, 0.0, 0.0), blur[0], blur[1], 0.5)
        score = masked_ncc_score(patch, tpl, (cover > 0.999).astype(np.float64))
        if score > best:
            best, out = score, a
    return out
