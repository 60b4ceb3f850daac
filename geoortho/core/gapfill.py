"""Fill gaps in a grid without ringing: harmonic (Laplace) interpolation, coarse to fine.

A harmonic fill obeys the maximum principle — every filled value lies between
the lowest and highest values on the gap's rim — so it cannot overshoot the
way an IDW-plus-smoothing fill (GDAL's fillnodata with smoothing passes, as
OpenDroneMap runs it) rings at building edges. Solved on an image pyramid:
each level starts from the coarser level's answer and relaxes, so large
gaps cost a few sweeps per level instead of thousands.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
from scipy import ndimage

from geoortho.core.kernels import compiled

__all__ = [
    "block_means",
    "block_sums",
    "distance_cells",
    "fill_gaps_by_windows",
    "fill_harmonic",
    "fill_smooth",
    "gap_mask",
]

OVERRELAX = 1.7  # measured best of 1.0-1.85 on a ramp through a 40-cell hole


def distance_cells(inside: np.ndarray) -> np.ndarray:
    """The Euclidean distance (cells, float32) of each ``inside`` cell to the nearest cell that is
    not, 0 on those; infinite when every cell is inside. OpenCV's exact transform: scipy's took 7 of
    the demo's 66 s in ``dem`` (98 calls), and agrees to 1e-5 cells.

    An exact distance is the square root of a whole number of cells squared, and it is returned so:
    OpenCV's serial and parallel paths differ by a float32 unit in the last place (348,646 cells of a
    1,906 x 1,830 grid), and a DSM made on one core differed from one made on two in 1,402 cells, one
    of them by 6 m (a roof's edge falling to the other side)."""
    inside = np.asarray(inside, bool)
    if inside.all():
        return np.full(inside.shape, np.inf, np.float32)
    d = cv2.distanceTransform(inside.astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    # whole below 2,000 cells whichever path rounded (an ulp of d moves d² by under 0.25 there)
    return np.sqrt(np.rint(np.square(d, dtype=np.float64))).astype(np.float32)


def gap_mask(
    known: np.ndarray, max_gap_cells: float, beyond: tuple[np.ndarray | None, ...] = (None,) * 4
) -> np.ndarray:
    """Unknown cells that are gaps inside the data: within ``max_gap_cells`` of known cells on
    both sides (a morphological closing by a disc), not the outside of the cloud's outline.

    ``beyond`` (top, bottom, left, right): for a window of a larger grid, which cells of the row
    or column just past that edge count as known (the data goes on there); None: no data past it."""
    if known.all() or not (known.any() or any(e is not None and e.any() for e in beyond)):
        return np.zeros_like(known)
    # closing with no data beyond the grid's edge: pad, dilate by the radius, erode by it; past a
    # window's edge one row of what is known there is enough (no distance is measured past the array)
    pad = int(math.ceil(max_gap_cells)) + 2
    top, bottom, left, right = (1 if e is not None else pad for e in beyond)
    h, w = known.shape
    k = np.pad(known, ((top, bottom), (left, right)))
    strips = (
        np.s_[top - 1, left : left + w],
        np.s_[top + h, left : left + w],
        np.s_[top : top + h, left - 1],
        np.s_[top : top + h, left + w],
    )
    for edge, strip in zip(beyond, strips):
        if edge is not None:
            k[strip] = edge
    near = distance_cells(~k) <= max_gap_cells
    closed = distance_cells(near) > max_gap_cells
    return np.asarray(closed[top : top + h, left : left + w] & ~known)


def fill_harmonic(z: np.ndarray, known: np.ndarray, fill: np.ndarray | None = None, *, sweeps: int = 30) -> np.ndarray:
    """``z`` with the cells of ``fill`` (default: every unknown cell) solved from Laplace's equation,
    the known cells fixed. Other cells are NaN."""
    z, known, target, out = _fill_inputs(z, known, fill)
    if not target.any() or not known.any():
        return out
    solved = _solve(np.where(known, z, 0.0), known, sweeps)
    out[target] = solved[target]
    return out


def block_sums(z: np.ndarray, known: np.ndarray, f: int) -> tuple[np.ndarray, np.ndarray]:
    """The sum of the ``known`` cells' values and their count in each f x f block of ``z`` (the
    grid padded to whole blocks): a block mean is their ratio where the count is not 0."""
    h, w = z.shape
    hp, wp = -(-h // f) * f, -(-w // f) * f
    zs, ks = np.zeros((hp, wp)), np.zeros((hp, wp))
    zs[:h, :w] = np.where(known, z, 0.0)
    ks[:h, :w] = known
    return zs.reshape(hp // f, f, wp // f, f).sum(axis=(1, 3)), ks.reshape(hp // f, f, wp // f, f).sum(axis=(1, 3))


def block_means(z: np.ndarray, known: np.ndarray, f: int, min_share: float = 0.5) -> np.ndarray:
    """The mean of the ``known`` cells of each f x f block of ``z`` where at least ``min_share``
    of the block is known, NaN elsewhere: a block that is mostly gap is no sample of the surface
    (its edge stays where the grid's is)."""
    total, n = block_sums(z, known, f)
    return np.where(n >= min_share * f * f, total / np.maximum(n, 1), np.nan)


def _fill_inputs(
    z: np.ndarray, known: np.ndarray, fill: np.ndarray | None
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A fill's grid (float64), its known cells (finite ones only), the cells to fill (default:
    every unknown one), and the output with the known cells in place, NaN elsewhere."""
    z = np.asarray(z, np.float64)
    known = np.asarray(known, bool) & np.isfinite(z)
    target = ~known if fill is None else (np.asarray(fill, bool) & ~known)
    return z, known, target, np.where(known, z, np.nan)


def _solve(z: np.ndarray, known: np.ndarray, sweeps: int) -> np.ndarray:
    h, w = z.shape
    if known.all():
        return z
    if h <= 2 or w <= 2 or not known.any():
        v = z[known].mean() if known.any() else 0.0
        return np.where(known, z, v)
    # coarser level: mean of the known cells of each 2x2 block
    zsum, ksum = block_sums(z, known, 2)
    kc = ksum > 0
    zc = np.where(kc, zsum / np.maximum(ksum, 1), 0.0)
    coarse = _solve(zc, kc, sweeps)
    cur = np.repeat(np.repeat(coarse, 2, axis=0), 2, axis=1)[:h, :w]
    cur = np.where(known, z, cur)
    # red-black Gauss-Seidel sweeps, over-relaxed, mirrored edges (no flux through the grid border)
    cur = np.ascontiguousarray(cur, np.float64)
    kernel = compiled(_sor_sweeps) if h * w >= COMPILED_MIN_CELLS else None
    if kernel is not None:
        kernel(cur, np.ascontiguousarray(known), sweeps, OVERRELAX)
        return cur
    # the four neighbours' mean by OpenCV's filter (a tenth of numpy's pad-and-slice time)
    parity = (np.arange(h)[:, None] + np.arange(w)[None, :]) % 2
    colours = [~known & (parity == c) for c in (0, 1)]
    for _ in range(sweeps):
        for free in colours:
            avg = np.asarray(cv2.filter2D(cur, -1, _NEIGHBOURS, borderType=cv2.BORDER_REPLICATE), np.float64)
            avg -= cur
            avg *= OVERRELAX
            avg += cur
            np.copyto(cur, avg, where=free)
    return cur


_NEIGHBOURS = np.array([[0.0, 0.25, 0.0], [0.25, 0.0, 0.25], [0.0, 0.25, 0.0]])

#: Levels of at least this many cells are swept by the compiled loop: one pass a colour that skips
#: the known cells (the numpy path makes four whole-grid passes a colour). The demo survey's DEM
#: (6.3 M cells a grid): its harmonic fills 20 s -> 7 s, the sweeps themselves 2 s of it. Smaller
#: levels stay in numpy: a process that fills only small grids never loads numba (0.4 s).
COMPILED_MIN_CELLS = 65_536


def _sor_sweeps(cur: np.ndarray, known: np.ndarray, sweeps: int, overrelax: float) -> None:
    """The numpy path's sweeps in place, as one loop over the cells of each colour (compiled: see
    :func:`geoortho.core.kernels.compiled`): a border cell's missing neighbour is itself."""
    h, w = cur.shape
    for _ in range(sweeps):
        for colour in range(2):
            for i in range(h):
                up, down = max(i - 1, 0), min(i + 1, h - 1)
                for j in range((i + colour) % 2, w, 2):
                    if known[i, j]:
                        continue
                    v = cur[i, j]
                    left = cur[i, j - 1] if j > 0 else v
                    right = cur[i, j + 1] if j < w - 1 else v
                    cur[i, j] = v + overrelax * (0.25 * (cur[up, j] + cur[down, j] + left + right) - v)


def warm() -> None:
    """Compile the sweeps into numba's cache (``make`` runs it ahead, so no command pays for it)."""
    z = np.zeros((300, 300))
    known = np.zeros(z.shape, bool)
    known[::7, ::7] = True
    fill_harmonic(z, known, sweeps=1)


#: The thin-plate surface is solved on a grid of blocks with at most this many unknown cells (a
#: sparse direct solve: ~1 s at 50 k), then carried to the fine grid.
THIN_PLATE_MAX_UNKNOWNS = 60_000
#: Where fewer known cells than this share weigh on a gap cell, the known cells' departures from
#: the blocks' surface fade out.
RESIDUAL_FADE = 0.2


def fill_smooth(z: np.ndarray, known: np.ndarray, fill: np.ndarray | None = None) -> np.ndarray:
    """``z`` with the cells of ``fill`` (default: every unknown cell) solved as a thin plate: the
    surface of least bending through the ``known`` cells (least squares on its second
    differences, scipy's sparse solver), on blocks, then carried to the fine grid with the
    known cells' departures from it filled harmonically.

    A harmonic fill has no curvature: under a building on a crest it sags (the demo survey: 0.3 m
    under a 10 m roof), and pinned to a single cell it is a cone (a dot in a hillshade). The
    thin plate carries the slope and the bend of the ground around a gap into it. It is clipped
    to the known values' range (widened by a tenth of it), so that far from any data it does
    not run away. Other cells are NaN."""
    z, known, target, out = _fill_inputs(z, known, fill)
    if not target.any() or not known.any():
        return out
    h, w = z.shape
    f = max(1, int(math.ceil(math.sqrt(int(target.sum()) / THIN_PLATE_MAX_UNKNOWNS))))
    hp, wp = -(-h // f) * f, -(-w // f) * f
    zsum, ksum = block_sums(z, known, f)
    kc = ksum > 0
    tc = (block_sums(z, target, f)[1] > 0) & ~kc
    coarse = _thin_plate(np.where(kc, zsum / np.maximum(ksum, 1), 0.0), kc, tc)
    lo, hi = float(z[known].min()), float(z[known].max())
    coarse = np.clip(coarse, lo - 0.1 * (hi - lo), hi + 0.1 * (hi - lo))
    if f == 1:
        out[target] = coarse[target]
        return out
    # bilinear between block centres (OpenCV's half-pixel alignment), nearest past them
    have = np.isfinite(coarse)
    nearest = ndimage.distance_transform_edt(~have, return_distances=False, return_indices=True)
    up = cv2.resize(coarse[tuple(nearest)].astype(np.float64), (wp, hp), interpolation=cv2.INTER_LINEAR)[:h, :w]
    # the known cells' departures from the blocks' surface, carried a few blocks into the gaps (a
    # normalised Gaussian that fades where no known cell is near: a harmonic fill of them over the
    # whole grid took 120 bytes a cell, 0.7 GB on the demo's DTM)
    k = known.astype(np.float32)
    r = np.where(known, z - up, 0.0).astype(np.float32)
    sigma = float(f)
    num = cv2.GaussianBlur(r, (0, 0), sigma, borderType=cv2.BORDER_REFLECT)
    den = cv2.GaussianBlur(k, (0, 0), sigma, borderType=cv2.BORDER_REFLECT)
    correction = num / np.maximum(den, RESIDUAL_FADE)
    out[target] = (up + correction)[target]
    return out


def _thin_plate(z: np.ndarray, known: np.ndarray, free: np.ndarray) -> np.ndarray:
    """The ``free`` cells minimising the sum of squared second differences (xx, yy and twice xy)
    over every stencil that lies on known or free cells, the known cells fixed; NaN elsewhere."""
    from scipy import sparse
    from scipy.sparse.linalg import spsolve

    h, w = z.shape
    out = np.where(known, z, np.nan)
    if not free.any():
        return out
    # solved as a departure from the harmonic fill: the tiny ridge that keeps the system regular
    # pulls a cell few stencils reach (a grid's corner) towards it, not towards 0 (a surface 100 m
    # up: 4.5 cm low under a 16 m roof, 0.37 m at a corner)
    base = _solve(np.where(known, z, 0.0), known, 30)
    z = np.where(known, z, base)
    index = np.full((h, w), -1, np.int64)
    index[free] = np.arange(int(free.sum()))
    inside = known | free
    rows_a: list[np.ndarray] = []
    cols_a: list[np.ndarray] = []
    vals_a: list[np.ndarray] = []
    rhs: list[np.ndarray] = []
    n_eq = 0
    # each stencil: the cells it reads as (row offset, col offset, weight)
    stencils = (
        ((0, -1, 1.0), (0, 0, -2.0), (0, 1, 1.0)),
        ((-1, 0, 1.0), (0, 0, -2.0), (1, 0, 1.0)),
        ((0, 0, math.sqrt(2)), (0, 1, -math.sqrt(2)), (1, 0, -math.sqrt(2)), (1, 1, math.sqrt(2))),
    )
    for stencil in stencils:
        r_lo = -min(dr for dr, _, _ in stencil)
        r_hi = h - max(dr for dr, _, _ in stencil)
        c_lo = -min(dc for _, dc, _ in stencil)
        c_hi = w - max(dc for _, dc, _ in stencil)
        rr, cc = np.mgrid[r_lo:r_hi, c_lo:c_hi]
        rr, cc = rr.ravel(), cc.ravel()
        ok = np.ones(len(rr), bool)
        touches = np.zeros(len(rr), bool)
        for dr, dc, _ in stencil:
            ok &= inside[rr + dr, cc + dc]
            touches |= free[rr + dr, cc + dc]
        rr, cc = rr[ok & touches], cc[ok & touches]
        eq = n_eq + np.arange(len(rr))
        b = np.zeros(len(rr))
        for dr, dc, wgt in stencil:
            idx = index[rr + dr, cc + dc]
            is_free = idx >= 0
            rows_a.append(eq[is_free])
            cols_a.append(idx[is_free])
            vals_a.append(np.full(int(is_free.sum()), wgt))
            b -= wgt * z[rr + dr, cc + dc]  # the free cells at the harmonic fill: d solves the rest
        rhs.append(b)
        n_eq += len(rr)
    a = sparse.csr_matrix(
        (np.concatenate(vals_a), (np.concatenate(rows_a), np.concatenate(cols_a))), shape=(n_eq, int(free.sum()))
    )
    normal = (a.T @ a).tocsc()
    # a free cell no stencil ties to the data (an island of free cells) would make it singular
    normal = normal + sparse.identity(normal.shape[0], format="csc") * 1e-9
    solved = spsolve(normal, a.T @ np.concatenate(rhs))
    out[free] = base[free] + solved
    return out


def fill_gaps_by_windows(z: np.ndarray, max_gap_cells: float, tile_cells: int = 1024) -> tuple[np.ndarray, int]:
    """``z`` (float32, NaN: no data) with its gaps inside the data filled, as :func:`gap_mask` and
    :func:`fill_harmonic` on the whole grid would, in memory that follows a window, not the grid
    (the whole-grid pair takes ~120 bytes a cell: 2.2 GB for a 19 M-cell DSM).

    The gap mask is found tile by tile, each with a halo of twice the gap (what a closing by that
    radius depends on), so it is the whole grid's; tiles with no unknown cell are skipped. Each gap
    is then filled in its bounding box and a ring around it: two cells where the gap is enclosed by
    data (a harmonic fill there depends only on its rim: the whole grid's fill to the solver's
    precision), the gap's limit where it is open to the outside (within 2.4 mm of the whole grid's
    fill on a 19 M-cell DSM, whose fill took 2.2 GB and 28 s; windowed, 0.4 GB). Returns the grid
    and the number of cells filled."""
    known = np.isfinite(z)
    h, w = z.shape
    if known.all() or not known.any():
        return z, 0
    halo = int(math.ceil(2 * max_gap_cells)) + 2
    gaps = np.zeros((h, w), bool)
    for r0 in range(0, h, tile_cells):
        for c0 in range(0, w, tile_cells):
            r1, c1 = min(h, r0 + tile_cells), min(w, c0 + tile_cells)
            if known[r0:r1, c0:c1].all():
                continue
            wr0, wc0, wr1, wc1 = max(0, r0 - halo), max(0, c0 - halo), min(h, r1 + halo), min(w, c1 + halo)
            g = gap_mask(known[wr0:wr1, wc0:wc1], max_gap_cells)
            gaps[r0:r1, c0:c1] = g[r0 - wr0 : r1 - wr0, c0 - wc0 : c1 - wc0]
    if not gaps.any():
        return z, 0
    out = np.array(z, np.float32, copy=True)
    labels, _ = ndimage.label(gaps, structure=np.ones((3, 3), bool))
    ring = int(math.ceil(max_gap_cells)) + 2
    for k, box in enumerate(ndimage.find_objects(labels), start=1):
        if box is None:
            continue
        rs, cs = box
        # a gap enclosed by data depends only on its rim; one open to the outside is solved with as
        # much of the outside as the closing saw
        o0, o1, p0, p1 = max(0, rs.start - 1), min(h, rs.stop + 1), max(0, cs.start - 1), min(w, cs.stop + 1)
        grown = ndimage.binary_dilation(labels[o0:o1, p0:p1] == k, structure=np.ones((3, 3), bool))
        is_open = (grown & ~known[o0:o1, p0:p1] & ~gaps[o0:o1, p0:p1]).any()
        m = ring if is_open else 2
        b0, b1 = max(0, rs.start - m), min(h, rs.stop + m)
        a0, a1 = max(0, cs.start - m), min(w, cs.stop + m)
        target = labels[b0:b1, a0:a1] == k
        filled = fill_harmonic(z[b0:b1, a0:a1], known[b0:b1, a0:a1], target)
        out[b0:b1, a0:a1][target] = filled[target]
    return out, int(gaps.sum())
