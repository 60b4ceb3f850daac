"""Ground points of an output window projected into a photo: sampling maps, visibility, preference.

The output grid is north-up; pixel (col, row) has its centre at
``transform * (col + 0.5, row + 0.5)``. A ground point is (x, y, z) with z from
the surface; it is projected into each photo with the full camera model
(distortion included) and sampled there with ``cv2.remap``.

Occlusion (what makes a *true* orthophoto): a ground point takes a photo's
pixel only if the straight line from it to the camera clears the DSM. The test
is a ray march on the DSM grid, done once per photo over its footprint
(:func:`visibility_grid`), then read at every output pixel with bilinear
weights and a threshold of one — a pixel next to an occluded cell counts as
occluded, so roof colour never lands on the ground beside a wall.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from affine import Affine
from rasterio.errors import WindowError
from rasterio.windows import Window, intersection

from geoortho.core.camera import PosedCamera
from geoortho.core.kernels import compiled
from geoortho.core.surface import FlatSurface, GridSurface, Surface, sample_grid

__all__ = [
    "intersect",
    "slices_in",
    "BlockTops",
    "VisibilityGrid",
    "block_tops",
    "visibility_grid",
    "window_xyz",
    "project_window",
    "keep_best",
    "remap_bgr",
]

_REMAP_MAX = 32000  # cv2.remap wants map sides below SHRT_MAX


def intersect(a: Window, b: Window) -> Window | None:
    """The cells two grid windows share (rasterio's intersection); None when they share none."""
    try:
        return intersection(a, b)
    except WindowError:
        return None


def slices_in(win: Window, origin: Window) -> tuple[slice, slice]:
    """``win``'s place inside ``origin`` (which contains it), as array slices."""
    r, c = win.row_off - origin.row_off, win.col_off - origin.col_off
    return slice(r, r + win.height), slice(c, c + win.width)


def bounds_window(
    transform: Affine, shape: tuple[int, int], bounds: tuple[float, float, float, float]
) -> Window | None:
    """The grid cells touching ``bounds`` (xmin, ymin, xmax, ymax), clipped to the grid."""
    xmin, ymin, xmax, ymax = bounds
    res = transform.a
    c0 = max(0, int(math.floor((xmin - transform.c) / res)))
    c1 = min(shape[1], int(math.ceil((xmax - transform.c) / res)))
    r0 = max(0, int(math.floor((transform.f - ymax) / res)))
    r1 = min(shape[0], int(math.ceil((transform.f - ymin) / res)))
    if c1 <= c0 or r1 <= r0:
        return None
    return Window(c0, r0, c1 - c0, r1 - r0)


@dataclass(frozen=True, eq=False)
class VisibilityGrid:
    """1 where the camera sees the DSM cell, 0 where the DSM hides it; on a window of the DSM grid.

    Held in a file (``path``, uint8 .npy, mapped when read), not in memory: a survey's photos'
    grids would otherwise be held at once, in every worker that renders tiles."""

    path: Path
    transform: Affine

    def sample(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        t = self.transform
        cols, rows = (x - t.c) / t.a - 0.5, (y - t.f) / t.e - 0.5
        grid = np.load(self.path, mmap_mode="r")
        ok = np.isfinite(cols) & np.isfinite(rows)
        if not ok.any():
            return np.full(np.shape(cols), np.nan, np.float32)
        # the cells around the samples only (a cell of margin: their bilinear neighbours)
        h, w = grid.shape
        c0 = int(np.clip(np.floor(cols[ok].min()) - 1, 0, w))
        c1 = int(np.clip(np.ceil(cols[ok].max()) + 2, c0, w))
        r0 = int(np.clip(np.floor(rows[ok].min()) - 1, 0, h))
        r1 = int(np.clip(np.ceil(rows[ok].max()) + 2, r0, h))
        if c1 <= c0 or r1 <= r0:
            return np.full(np.shape(cols), np.nan, np.float32)
        return sample_grid(np.asarray(grid[r0:r1, c0:c1], np.float32), cols - c0, rows - r0)


@dataclass(frozen=True, eq=False)
class BlockTops:
    """The highest DSM value a bilinear sample can read anywhere in each block of ``block`` cells
    (the block and a ring of one cell); +inf where it may read no data or beyond the grid.

    A ray rising through a block above its top cannot be blocked there: the march jumps to where
    it leaves the block instead of sampling every cell (the same samples decide, so the same grid)."""

    top: np.ndarray  # float32, (rows / block, cols / block), rounded up
    block: int
    transform: Affine

    @classmethod
    def of(cls, surface: GridSurface, block: int) -> BlockTops:
        from scipy import ndimage

        g = np.where(np.isfinite(surface.grid), surface.grid, np.inf).astype(np.float32)
        g = ndimage.maximum_filter(np.pad(g, 1, constant_values=np.inf), size=3)[1:-1, 1:-1]
        nr, nc = g.shape
        g = np.pad(g, ((0, (-nr) % block), (0, (-nc) % block)), constant_values=np.inf)
        top = g.reshape(g.shape[0] // block, block, g.shape[1] // block, block).max(axis=(1, 3))
        return cls(top, block, surface.transform)

    def clear_run(
        self, x: np.ndarray, y: np.ndarray, ceiling: np.ndarray, ux: np.ndarray, uy: np.ndarray
    ) -> np.ndarray:
        """Horizontal metres from (x, y) along (ux, uy) to the edge of its block where the block's
        top is at most ``ceiling``; 0 elsewhere."""
        t, b = self.transform, self.block
        cf, rf = (x - t.c) / t.a, (y - t.f) / t.e  # cell-corner coordinates
        with np.errstate(invalid="ignore"):
            bc, br = np.floor(cf / b), np.floor(rf / b)
        out = np.zeros(np.shape(x))
        inside = np.flatnonzero((bc >= 0) & (bc < self.top.shape[1]) & (br >= 0) & (br < self.top.shape[0]))
        bci, bri = bc[inside].astype(np.intp), br[inside].astype(np.intp)
        clear = self.top[bri, bci] <= ceiling[inside]
        i, bci, bri = inside[clear], bci[clear], bri[clear]
        dc, dr = ux[i] / t.a, uy[i] / t.e  # cells per metre along the ray
        with np.errstate(divide="ignore", invalid="ignore"):
            ec = np.where(dc > 0, ((bci + 1) * b - cf[i]) / dc, np.where(dc < 0, (bci * b - cf[i]) / dc, np.inf))
            er = np.where(dr > 0, ((bri + 1) * b - rf[i]) / dr, np.where(dr < 0, (bri * b - rf[i]) / dr, np.inf))
        out[i] = np.maximum(np.minimum(ec, er), 0.0)
        return out


#: Block sides (cells) of the visibility march's skip levels, coarsest first: 128/32/8 measured
#: 5x faster than plain marching on a 5 cm DSM (8 alone 2x, 32 alone 4x), the grids identical.
SKIP_BLOCKS = (128, 32, 8)


def block_tops(surface: GridSurface) -> tuple[BlockTops, ...]:
    """The skip levels of :func:`visibility_grid` for ``surface``."""
    return tuple(BlockTops.of(surface, b) for b in SKIP_BLOCKS)


def visibility_grid(
    cam: PosedCamera,
    surface: GridSurface,
    bounds: tuple[float, float, float, float],
    path: Path,
    tolerance_m: float = 0.05,
    tops: Sequence[BlockTops] = (),
) -> VisibilityGrid | None:
    """Line of sight from each DSM cell in ``bounds`` to the camera, marched over the DSM a cell at
    a time (past blocks of ``tops`` that the ray clears); kept in ``path``."""
    win = bounds_window(surface.transform, surface.grid.shape, bounds)
    if win is None:
        return None
    # One cell of margin so that bilinear reads at the window edge see real values.
    r0, c0 = max(0, win.row_off - 1), max(0, win.col_off - 1)
    r1 = min(surface.grid.shape[0], win.row_off + win.height + 1)
    c1 = min(surface.grid.shape[1], win.col_off + win.width + 1)
    tr = surface.transform
    z = surface.grid[r0:r1, c0:c1].astype(np.float64)
    cc, rr = np.meshgrid(np.arange(c0, c1) + 0.5, np.arange(r0, r1) + 0.5)
    x, y = tr.c + cc * tr.a, tr.f + rr * tr.e
    cx, cy, cz = cam.pose.center
    dx, dy, dz = cx - x, cy - y, cz - z
    dh = np.hypot(dx, dy)
    with np.errstate(divide="ignore", invalid="ignore"):
        ux, uy, rise = dx / dh, dy / dh, dz / dh  # rise: metres up per metre towards the camera
    vis = np.isfinite(z) & (dz > 0)
    step = surface.cell_m
    # Rays climb out of the DSM's height range after (z_max − z) / rise metres; the camera stops them too.
    reach = np.where(vis, np.minimum((surface.z_max - z) / np.maximum(rise, 1e-9), dh), 0.0)
    idx = np.flatnonzero(vis & (reach > step * 0.5))
    fx, fy, fz = x.ravel(), y.ravel(), z.ravel()
    fux, fuy, frise, freach = ux.ravel(), uy.ravel(), rise.ravel(), reach.ravel()
    occluded = np.zeros(z.size, bool)
    kernel = compiled(_march_rays) if idx.size >= COMPILED_MIN_RAYS else None
    if kernel is not None:
        rays = np.stack([fx[idx], fy[idx], fz[idx], fux[idx], fuy[idx], frise[idx], freach[idx]])
        ground, ground_f = surface.ground_base() if surface.extend else (np.zeros((1, 1)), 1)
        flat, levels = _packed_tops(tops)
        blocked_rays = np.zeros(idx.size, np.bool_)
        geo = np.array([tr.a, tr.c, tr.e, tr.f, step, tolerance_m])
        # (GridSurface keeps its grid contiguous float32: the kernel's one signature takes it as is)
        kernel(rays, surface.grid, geo, flat, levels, surface.extend, ground.astype(np.float64), ground_f, blocked_rays)
        occluded[idx[blocked_rays]] = True
        idx = idx[:0]
    k = np.ones(idx.size, np.int64)  # each ray's next sample, k steps from its cell
    while idx.size:
        t = k * step
        px, py = fx[idx] + fux[idx] * t, fy[idx] + fuy[idx] * t
        ceiling = fz[idx] + frise[idx] * t + tolerance_m
        jump = np.zeros(idx.size)
        for level in tops:
            todo = np.flatnonzero(jump <= 0)
            if not todo.size:
                break
            jump[todo] = level.clear_run(px[todo], py[todo], ceiling[todo], fux[idx[todo]], fuy[idx[todo]])
        look = jump <= 0
        blocked = np.zeros(idx.size, bool)
        if look.any():
            blocked[look] = surface.elevation(px[look], py[look]) > ceiling[look]
        occluded[idx[blocked]] = True
        # a ray that cleared a block goes on at its first sample past the block's edge
        k = np.where(look, k + 1, np.maximum(k + 1, np.ceil((t + jump) / step).astype(np.int64)))
        keep = ~blocked & (freach[idx] > (k - 1) * step + step * 0.5)  # as if every sample were taken
        idx, k = idx[keep], k[keep]
    vis = vis & ~occluded.reshape(z.shape)
    np.save(path, vis.astype(np.uint8))
    return VisibilityGrid(Path(path), Affine(tr.a, 0, tr.c + c0 * tr.a, 0, tr.e, tr.f + r0 * tr.e))


#: Photos with at least this many rays to march take the compiled loop (one pass a ray, stopping
#: where it is blocked; the numpy path samples every live ray at each step). Below, a process that
#: marches only small windows never loads numba (0.4 s a worker).
COMPILED_MIN_RAYS = 100_000


def _packed_tops(tops: Sequence[BlockTops]) -> tuple[np.ndarray, np.ndarray]:
    """The skip levels as one float32 buffer, and per level (offset, rows, cols, block)."""
    flat = np.concatenate([t.top.ravel() for t in tops]) if tops else np.zeros(1, np.float32)
    levels = np.zeros((len(tops), 4), np.int64)
    offset = 0
    for i, t in enumerate(tops):
        levels[i] = (offset, t.top.shape[0], t.top.shape[1], t.block)
        offset += t.top.size
    return np.ascontiguousarray(flat, np.float32), levels


def _march_rays(
    rays: np.ndarray,
    grid: np.ndarray,
    geo: np.ndarray,
    tops: np.ndarray,
    levels: np.ndarray,
    extend: bool,
    base: np.ndarray,
    base_f: int,
    blocked: np.ndarray,
) -> None:
    """:func:`visibility_grid`'s march, a ray at a time (compiled: see
    :func:`geoortho.core.kernels.compiled`). ``rays`` rows: x, y, z, ux, uy, rise, reach; ``geo``:
    the DSM's a, c, e, f, the step and the tolerance. The DSM is read as ``sample_grid`` reads it
    (OpenCV 5's remap: float32 weights, two lerps along the row and one across, each a fused
    multiply-add; no data where any of the four cells is off the grid or none), so the two paths
    agree to the bit; with ``extend``, continued by the ground ``base`` as ``GridSurface`` is."""
    a, c, e, f, step, tolerance = geo[0], geo[1], geo[2], geo[3], geo[4], geo[5]
    nr, nc = grid.shape
    for i in range(rays.shape[1]):
        x, y, z, ux, uy, rise, reach = (
            rays[0, i], rays[1, i], rays[2, i], rays[3, i], rays[4, i], rays[5, i], rays[6, i],
        )  # fmt: skip
        k = 1
        while True:
            t = k * step
            px, py = x + ux * t, y + uy * t
            ceiling = z + rise * t + tolerance
            jump = 0.0
            cf, rf = (px - c) / a, (py - f) / e
            for lv in range(levels.shape[0]):
                if jump > 0:
                    break
                offset, rows, cols, b = levels[lv, 0], levels[lv, 1], levels[lv, 2], levels[lv, 3]
                bc, br = math.floor(cf / b), math.floor(rf / b)
                if bc < 0 or bc >= cols or br < 0 or br >= rows or not (tops[offset + br * cols + bc] <= ceiling):
                    continue
                dc, dr = ux / a, uy / e
                ec = ((bc + 1) * b - cf) / dc if dc > 0 else ((bc * b - cf) / dc if dc < 0 else math.inf)
                er = ((br + 1) * b - rf) / dr if dr > 0 else ((br * b - rf) / dr if dr < 0 else math.inf)
                jump = max(min(ec, er), 0.0)
            if jump <= 0:
                col, row = np.float32(cf - 0.5), np.float32(rf - 0.5)
                ic, ir = math.floor(col), math.floor(row)
                height = math.nan
                if 0 <= ic and ic + 1 < nc and 0 <= ir and ir + 1 < nr:
                    wc, wr = float(col) - ic, float(row) - ir  # exact; see core.surface._march_each
                    # a float32 fused multiply-add: the product of two float32 is exact in float64
                    g00, g01, g10, g11 = grid[ir, ic], grid[ir, ic + 1], grid[ir + 1, ic], grid[ir + 1, ic + 1]
                    top = np.float32(float(g01 - g00) * wc + float(g00))
                    bottom = np.float32(float(g11 - g10) * wc + float(g10))
                    height = float(np.float32(float(bottom - top) * wr + float(top)))
                if extend and math.isnan(height):
                    bi = min(max(round(rf - 0.5), 0), nr - 1) // base_f
                    bj = min(max(round(cf - 0.5), 0), nc - 1) // base_f
                    height = base[bi, bj]
                if height > ceiling:
                    blocked[i] = True
                    break
                k += 1
            else:
                k = max(k + 1, math.ceil((t + jump) / step))
            if not reach > (k - 1) * step + step * 0.5:
                break


def warm() -> None:
    """Compile the march into numba's cache (``make`` runs it ahead, so no command pays for it)."""
    kernel = compiled(_march_rays)
    if kernel is None:
        return
    rays = np.array([[0.5], [0.5], [0.0], [1.0], [0.0], [0.1], [4.0]])
    flat, levels = _packed_tops(())
    geo = np.array([1.0, 0.0, -1.0, 8.0, 1.0, 0.05])
    kernel(rays, np.zeros((8, 8), np.float32), geo, flat, levels, False, np.zeros((1, 1)), 1, np.zeros(1, np.bool_))


def window_xyz(transform: Affine, win: Window, surface: Surface) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Ground points at the centres of the window's pixels: x, y, z (rows, cols) float64; z NaN off the DSM."""
    res = transform.a
    xs = transform.c + (np.arange(win.col_off, win.col_off + win.width) + 0.5) * res
    ys = transform.f - (np.arange(win.row_off, win.row_off + win.height) + 0.5) * res
    x, y = np.meshgrid(xs, ys)
    if isinstance(surface, FlatSurface):
        z = np.full(x.shape, surface.elevation_m)
    else:
        z = surface.elevation(x, y)
    return x, y, z


@dataclass(frozen=True, eq=False)
class Projection:
    """A photo seen from an output window: sampling maps, where it is usable, and how much it is preferred."""

    map_x: np.ndarray  # float32 (rows, cols), photo column of each output pixel
    map_y: np.ndarray
    in_frame: np.ndarray  # bool: inside the photo and on the surface
    valid: np.ndarray  # bool: in_frame and not occluded
    cost: np.ndarray  # float32: lower is preferred (see preference_cost)


def preference_cost(
    cam: PosedCamera, x: np.ndarray, y: np.ndarray, z: np.ndarray, map_x: np.ndarray, map_y: np.ndarray
) -> np.ndarray:
    """How badly this photo sees each ground point: the tangent of the line of sight's angle from
    the vertical (relief displacement and smear grow with it) plus the distance from the principal
    point over the half-diagonal (vignetting and distortion grow with that)."""
    cx, cy, cz = cam.pose.center
    dx = (x - cx).astype(np.float32)
    dy = (y - cy).astype(np.float32)
    dz = np.maximum((cz - z).astype(np.float32), np.float32(1e-3))
    intr = cam.intrinsics
    half_diag = np.float32(0.5 * math.hypot(intr.width_px, intr.height_px))
    off_vertical = np.sqrt(dx * dx + dy * dy) / dz
    u, v = map_x - np.float32(intr.cx_px), map_y - np.float32(intr.cy_px)
    result: np.ndarray = off_vertical + np.float32(0.5) * np.sqrt(u * u + v * v) / half_diag
    return result


def project_grid(
    cam: PosedCamera,
    x: np.ndarray,
    y: np.ndarray,
    z: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pixel column, row and depth (float32, the grid's shape) of ground points: the camera model of
    :func:`geoortho.core.camera.project_points` written out per component, so that a million points cost
    a few array passes (offsets from the camera are taken in float64 first: CRS coordinates are large)."""
    c = cam.pose.center
    dx = (x - c[0]).astype(np.float32)
    dy = (y - c[1]).astype(np.float32)
    dz = (z - c[2]).astype(np.float32)
    r = cam.pose.rotation.astype(np.float32)  # world-from-camera: camera coords = R^T d
    xc = r[0, 0] * dx + r[1, 0] * dy + r[2, 0] * dz
    yc = r[0, 1] * dx + r[1, 1] * dy + r[2, 1] * dz
    zc = r[0, 2] * dx + r[1, 2] * dy + r[2, 2] * dz
    with np.errstate(divide="ignore", invalid="ignore"):
        xn, yn = xc / zc, yc / zc
    intr = cam.intrinsics
    if intr.has_distortion:
        k1, k2, p1, p2, k3 = (np.float32(v) for v in intr.dist_coeffs[:5])
        r2 = xn * xn + yn * yn
        radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        xy = xn * yn
        xd = xn * radial + 2 * p1 * xy + p2 * (r2 + 2 * xn * xn)
        yd = yn * radial + p1 * (r2 + 2 * yn * yn) + 2 * p2 * xy
        xn, yn = xd, yd
    f = np.float32(intr.focal_px)
    mx = xn * f + np.float32(intr.cx_px)
    my = yn * f + np.float32(intr.cy_px)
    behind = ~(zc > 0)
    mx[behind] = np.nan
    my[behind] = np.nan
    return mx, my, zc


def project_window(
    cam: PosedCamera,
    x: np.ndarray,
    y: np.ndarray,
    z: np.ndarray,
    visibility: VisibilityGrid | None,
    margin_px: float = 1.0,
) -> Projection:
    """Project the window's ground points into ``cam``."""
    ok = np.isfinite(z)
    mx, my, depth = project_grid(cam, x, y, np.where(ok, z, 0.0))
    intr = cam.intrinsics
    with np.errstate(invalid="ignore"):
        in_frame = (
            ok
            & (depth > 0)
            & (mx >= margin_px - 0.5)
            & (my >= margin_px - 0.5)
            & (mx <= intr.width_px - 0.5 - margin_px)
            & (my <= intr.height_px - 0.5 - margin_px)
        )
    valid = in_frame.copy()
    if visibility is not None and valid.any():
        v = visibility.sample(x[valid], y[valid])
        # beyond the visibility grid (the DSM's edge, where the ground is its plane) nothing hides
        valid[valid] = ~(v < 0.999)
    cost = preference_cost(cam, x, y, np.where(ok, z, 0.0), mx, my)
    cost[~valid] = np.inf
    return Projection(mx, my, in_frame, valid, cost)


def keep_best(best: np.ndarray, labels: np.ndarray, sl: tuple[slice, slice], cost: np.ndarray, index: int) -> None:
    """Give photo ``index`` the cells of ``best[sl]`` where its ``cost`` is lower (``labels`` too)."""
    better = cost < best[sl]
    best[sl][better] = cost[better]
    labels[sl][better] = index


def remap_bgr(
    image: np.ndarray, map_x: np.ndarray, map_y: np.ndarray, interpolation: int = cv2.INTER_LINEAR, reduction: int = 1
) -> np.ndarray:
    """Sample a photo (rows, cols, 3) at full-resolution pixel coordinates; ``reduction`` when the
    photo was decoded at 1/reduction of its size."""
    if reduction != 1:
        map_x = (map_x + 0.5) / reduction - 0.5
        map_y = (map_y + 0.5) / reduction - 0.5
    if max(map_x.shape) >= _REMAP_MAX:
        out = np.empty(map_x.shape + (3,), image.dtype)
        for r in range(0, map_x.shape[0], 8192):
            for c in range(0, map_x.shape[1], 8192):
                out[r : r + 8192, c : c + 8192] = remap_bgr(
                    image, map_x[r : r + 8192, c : c + 8192], map_y[r : r + 8192, c : c + 8192], interpolation
                )
        return out
    return cv2.remap(
        image,
        np.nan_to_num(map_x, nan=-1e4),
        np.nan_to_num(map_y, nan=-1e4),
        interpolation,
        borderMode=cv2.BORDER_REFLECT,
    )
