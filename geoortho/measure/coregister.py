"""Two DSMs of one site brought onto each other on the ground that did not change.

The second surface is moved by a shift (x, y, z), a turn about the vertical and a tilt (two
slopes), found by Gauss-Newton on the height differences: each cell's difference changes with the
shift as the second surface's slope there, so slopes in every direction (walls, banks, crowns) fix
the horizontal shift and flat ground the vertical. Cells that changed (a pile moved, a trench dug)
disagree with the rest: each step weighs the cells by Tukey's biweight on the differences, so they
drop out. The fit runs coarse to fine (cells averaged 16, 8, 4, 2 to one), so that a start metres
apart (two flights on GPS alone) is inside the finest level's reach.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

#: Tukey's biweight: a difference beyond this many robust spreads weighs nothing.
TUKEY_C = 4.685
#: Iterations a level at most, and the step (metres, radians) below which a level is done.
MAX_ITERATIONS = 40
CONVERGED = 1e-4
#: The coarsest level's cells at most this many of the grid's (each level halves it).
COARSEST = 16


@dataclass(frozen=True)
class Fit:
    """How the second surface sits on the first.

    ``params``: dx, dy, dz (metres, the CRS's units), turn (radians, counter-clockwise), tilt_x, tilt_y
    (rise per unit east and north), about ``centre``; ``inliers``: the cells of the reference grid
    that agreed (stable ground); ``residual``: their robust spread (NMAD); ``sigma``: each
    parameter's 1 sigma."""

    params: np.ndarray
    centre: tuple[float, float]
    inliers: np.ndarray
    residual: float
    sigma: np.ndarray


def nmad(x: np.ndarray) -> float:
    """The normalized median absolute deviation (the standard deviation of normal data)."""
    x = x[np.isfinite(x)]
    return float(1.4826 * np.median(np.abs(x - np.median(x)))) if x.size else math.nan


@dataclass(frozen=True)
class Grid:
    """A north-up surface: heights (NaN where none), its first cell centre, its cell, its slopes."""

    z: np.ndarray
    x0: float
    y0: float
    cell: float
    slope_x: np.ndarray  # d height / d east
    slope_y: np.ndarray  # d height / d north

    @classmethod
    def of(cls, z: np.ndarray, x0: float, y0: float, cell: float) -> Grid:
        z32 = np.ascontiguousarray(z, np.float32)
        g_rows, g_cols = np.gradient(z32, cell)
        return cls(
            z32, x0, y0, cell, np.ascontiguousarray(g_cols, np.float32), np.ascontiguousarray(-g_rows, np.float32)
        )  # fmt: skip  (rows run south)

    def coarser(self, f: int) -> Grid:
        """Averaged ``f`` cells to one."""
        if f == 1:
            return self
        h, w = self.z.shape[0] // f * f, self.z.shape[1] // f * f
        z = self.z[:h, :w].reshape(h // f, f, w // f, f).mean(axis=(1, 3))
        half = (f - 1) * self.cell / 2
        return Grid.of(z, self.x0 + half, self.y0 - half, self.cell * f)

    def centres(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Every cell with a height: its x, y and height."""
        rr, cc = np.nonzero(np.isfinite(self.z))
        return self.x0 + cc * self.cell, self.y0 - rr * self.cell, self.z[rr, cc].astype(np.float64)


def cells_of(
    b: Grid, xs: np.ndarray, ys: np.ndarray, params: np.ndarray, centre: tuple[float, float]
) -> tuple[np.ndarray, np.ndarray]:
    """Where points (xs, ys) of the first surface fall on the second's grid once it is moved by
    ``params``: fractional (column, row) of its cell centres."""
    dx, dy, _, turn, _, _ = params
    u, v = xs - centre[0], ys - centre[1]
    c, s = math.cos(turn), math.sin(turn)
    return (centre[0] + c * u - s * v + dx - b.x0) / b.cell, (b.y0 - (centre[1] + s * u + c * v + dy)) / b.cell


def moved(b: Grid, xs: np.ndarray, ys: np.ndarray, params: np.ndarray, centre: tuple[float, float]) -> tuple[
    np.ndarray, np.ndarray, np.ndarray
]:  # fmt: skip
    """The second surface, moved by ``params``, at points (xs, ys): its height (NaN off it) and
    its slopes there (d height / d east, d height / d north)."""
    from geoortho.core.surface import sample_grid

    dx, dy, dz, turn, tx, ty = params
    u, v = xs - centre[0], ys - centre[1]
    cols, rows = cells_of(b, xs, ys, params, centre)
    z = sample_grid(b.z, cols, rows).astype(np.float64) - dz - tx * u - ty * v
    return (
        z,
        sample_grid(b.slope_x, cols, rows).astype(np.float64),
        sample_grid(b.slope_y, cols, rows).astype(np.float64),
    )


def coregister(a: Grid, b: Grid) -> Fit:
    """Where ``b`` sits on ``a``."""
    rows, cols = a.z.shape
    centre = (a.x0 + cols * a.cell / 2, a.y0 - rows * a.cell / 2)
    params = np.zeros(6)
    levels = [f for f in (16, 8, 4, 2, 1) if f <= COARSEST and min(rows, cols) // f >= 32] or [1]
    for f in levels:
        ac, bc = a.coarser(f), b.coarser(f)
        xs, ys, za = ac.centres()
        for _ in range(MAX_ITERATIONS):
            step, _, _ = _step(bc, xs, ys, za, params, centre)
            params = params + step
            if np.max(np.abs(step[:3])) < CONVERGED and abs(step[3]) * 1e3 < CONVERGED:
                break
    xs, ys, za = a.centres()
    _, weights, normal = _step(b, xs, ys, za, params, centre)
    zb, _, _ = moved(b, xs, ys, params, centre)
    diff = zb - za
    residual = nmad(diff[weights > 0])
    inliers = np.zeros(a.z.shape, bool)
    rr, cc = np.nonzero(np.isfinite(a.z))
    inliers[rr, cc] = weights > 0
    try:  # the fit's own spread: optimistic where the residuals are correlated (said as such)
        sigma = np.sqrt(np.clip(np.diag(np.linalg.inv(normal)), 0, None)) * residual
    except np.linalg.LinAlgError:
        sigma = np.full(6, np.inf)
    return Fit(params, centre, inliers, residual, sigma)


def _step(
    b: Grid, xs: np.ndarray, ys: np.ndarray, za: np.ndarray, params: np.ndarray, centre: tuple[float, float]
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One Gauss-Newton step, each cell weighed by Tukey's biweight: the step, the weights, the
    normal matrix."""
    zb, sx, sy = moved(b, xs, ys, params, centre)
    r = zb - za
    ok = np.isfinite(r) & np.isfinite(sx) & np.isfinite(sy)
    r0 = np.where(ok, r, 0.0)
    spread = max(nmad(r[ok]), 1e-3)
    t = (r0 - np.median(r[ok])) / (TUKEY_C * spread)
    w = np.where(ok & (np.abs(t) < 1), (1 - t * t) ** 2, 0.0)
    u, v = xs - centre[0], ys - centre[1]
    sx, sy = np.where(ok, sx, 0.0), np.where(ok, sy, 0.0)
    # d r / d (dx, dy, dz, turn, tilt_x, tilt_y): the moved surface's slopes for the shift and the turn
    jac = np.stack([sx, sy, -np.ones_like(u), -sx * v + sy * u, -u, -v], axis=1)
    jw = jac * w[:, None]
    normal = jac.T @ jw + np.eye(6) * 1e-9
    return np.linalg.solve(normal, -(jw.T @ r0)), w, normal
