"""The lens's light falloff (vignetting), measured on the photos' overlaps and taken out.

A photo is darker towards its corners: on toledo's DJI photos about a tenth of the brightness
mid-way out (the mean of its photos), on the synthetic survey 25 % at the corner. Where two photos
meet, one sees a ground point near its centre and the other near its edge, so every seam carries a
step no per-photo gain can take out (issue 75: toledo's seam step 13 DN after balancing).

The falloff is measured where the photos overlap: a ground point seen by two photos at radii
``r_a`` and ``r_b`` (squared, over the frame's half-diagonal: ``rho``) gives

    log I_a - log I_b = (log e_a - log e_b) + f(rho_a) - f(rho_b),   f(rho) = c1 rho + c2 rho^2

with ``e`` each photo's exposure. Over blocks of one overlap the exposures are one constant;
taking each overlap's weighted mean out leaves ``c1`` and ``c2`` to a robust least squares over
every block of every overlap (Huber weights: relief's parallax and moving cars disagree too). The
photos' pixels are then divided by ``exp(f(rho))`` before the gains, the seams and the blend.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["Falloff", "estimate_falloff", "falloff_gain", "frame_rho"]

#: A falloff darker than this at the frame's corner (share of the centre's brightness lost) is no
#: lens's vignetting a survey camera has; the fit is then taken for content and not applied.
MAX_CORNER_LOSS = 0.45
#: Below this at the corner (share), the falloff is not worth taking out (and not told from noise).
MIN_CORNER_LOSS = 0.02
#: Blocks of overlap the fit needs, in overlaps of at least this many pairs.
MIN_BLOCKS = 40
MIN_PAIRS = 4
#: Huber's threshold on the blocks' residuals (log units: 4 %).
HUBER_LOG = 0.04


@dataclass(frozen=True)
class Falloff:
    """``log(brightness / centre's) = c1 rho + c2 rho^2`` over the frame (rho: squared radius over
    the half-diagonal's)."""

    c1: float
    c2: float
    n_blocks: int
    n_pairs: int

    def loss_at(self, rho: float) -> float:
        """The share of the centre's brightness lost at ``rho``."""
        return 1.0 - math.exp(self.c1 * rho + self.c2 * rho * rho)

    def note(self) -> str:
        return (
            f"lens falloff measured on {self.n_pairs} overlaps ({self.n_blocks} blocks): "
            f"{100 * self.loss_at(0.25):.0f} % darker half-way out, {100 * self.loss_at(1.0):.0f} % at the "
            "frame's corners; taken out before balancing"
        )


def frame_rho(map_x: np.ndarray, map_y: np.ndarray, width_px: int, height_px: int, reduction: int = 1) -> np.ndarray:
    """Squared radius from the frame's centre over the half-diagonal's (float32), at photo pixel
    coordinates ``map_x``, ``map_y`` of a photo decoded at 1/``reduction``."""
    cx, cy = width_px / 2.0, height_px / 2.0
    s = float(reduction)
    rho = ((map_x * s - cx) ** 2 + (map_y * s - cy) ** 2) / (cx * cx + cy * cy)
    return np.asarray(rho, np.float32)


def falloff_gain(rho: np.ndarray, falloff: Falloff | None) -> np.ndarray | None:
    """The gain (float32) that takes the falloff out at ``rho``; None when there is none."""
    if falloff is None:
        return None
    r = np.clip(rho, 0.0, 1.5)
    result: np.ndarray | None = np.exp(-(falloff.c1 * r + falloff.c2 * r * r)).astype(np.float32)
    return result


def estimate_falloff(pairs: list[np.ndarray]) -> Falloff | None:
    """The falloff from each overlap's blocks: per overlap an array (k, 4) of ``weight, log grey of
    a - of b, rho_a, rho_b``. None when the overlaps cannot tell it (too few, too alike in
    radius), or it is no lens's (brightening outwards, darker than ``MAX_CORNER_LOSS``) or too
    small to matter."""
    rows = [p for p in pairs if len(p) >= 3]
    if len(rows) < MIN_PAIRS or sum(len(p) for p in rows) < MIN_BLOCKS:
        return None
    ys, xs, ws = [], [], []
    for p in rows:
        w, d, ra, rb = p[:, 0], p[:, 1], p[:, 2], p[:, 3]
        x = np.c_[ra - rb, ra * ra - rb * rb]
        # the pair's exposure ratio is one constant over its blocks: weighted means taken out
        sw = w.sum()
        ys.append(d - (w * d).sum() / sw)
        xs.append(x - (w[:, None] * x).sum(axis=0) / sw)
        ws.append(w)
    y, x, w0 = np.concatenate(ys), np.vstack(xs), np.concatenate(ws)
    if np.linalg.matrix_rank(x * np.sqrt(w0)[:, None]) < 2 or np.std(x[:, 0]) < 0.02:
        return None
    w = w0.copy()
    coef = np.zeros(2)
    for _ in range(5):  # iteratively reweighted: Huber
        sw = np.sqrt(w)
        coef, *_ = np.linalg.lstsq(x * sw[:, None], y * sw, rcond=None)
        res = np.abs(y - x @ coef)
        w = w0 * np.where(res <= HUBER_LOG, 1.0, HUBER_LOG / np.maximum(res, 1e-12))
    f = Falloff(float(coef[0]), float(coef[1]), len(y), len(rows))
    profile = [f.loss_at(r) for r in (0.25, 0.5, 0.75, 1.0)]
    darkening = all(b >= a - 0.005 for a, b in zip([0.0, *profile], profile))  # no brighter outwards
    if not darkening or not (MIN_CORNER_LOSS <= profile[-1] <= MAX_CORNER_LOSS):
        return None
    return f
