"""One tile of the mosaic, as a pool or cluster worker renders it: the photos over it rectified on the
DSM, occlusion, seams and multi-band blending, the holes filled; and one photo's visibility grid.
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from affine import Affine
from rasterio.windows import Window

from geoortho.core.camera import PosedCamera
from geoortho.core.surface import GridSurface, Surface
from geoortho.orthophoto.coverage import enclosed
from geoortho.orthophoto.falloff import falloff_gain, frame_rho
from geoortho.orthophoto.provenance import (
    INPAINTED,
    NONE,
    OCCLUDED,
    SEEN,
)
from geoortho.orthophoto.rectify import (
    BlockTops,
    VisibilityGrid,
    intersect,
    keep_best,
    preference_cost,
    project_window,
    remap_bgr,
    slices_in,
    visibility_grid,
    window_xyz,
)
from geoortho.orthophoto.seams import SeamPlan, read_photo_bgr

BANDS = 5  # multi-band levels: the lowest spans 2**5 px on each side of a seam
#: A photo's pixel past its seam, where the seam plan found movers, that differs from the owner's by
#: more than this (RGB distance, smoothed over a pixel) is not blended in.
_FOREIGN_DN = 40.0
_CACHE_BYTES = 600 * 2**20  # decoded photos kept per worker


# ---------------------------------------------------------------------------------------------
# one tile (runs in a worker)


@dataclass(frozen=True, eq=False)
class TileContext:
    cams: tuple[PosedCamera, ...]
    boxes: tuple[Window | None, ...]  # each photo's footprint on the output grid
    vis: tuple[VisibilityGrid | None, ...]
    surface: Surface
    transform: Affine
    shape: tuple[int, int]
    plan: SeamPlan
    blend: str
    max_hole_px: int
    pad_px: int
    interpolation: int


_CTX: TileContext | None = None
_CACHE: OrderedDict[str, np.ndarray] = OrderedDict()


def init_worker(ctx: TileContext) -> None:
    global _CTX
    _CTX = ctx
    _CACHE.clear()
    cv2.setNumThreads(1)


_VIS_SURFACE: tuple[GridSurface, tuple[BlockTops, ...]] | None = None


def init_visibility(surface: GridSurface, tops: tuple[BlockTops, ...]) -> None:
    global _VIS_SURFACE
    _VIS_SURFACE = (surface, tops)


def visibility_task(job: tuple[PosedCamera, tuple[float, float, float, float], str]) -> VisibilityGrid | None:
    """One photo's visibility grid, written to its file (a pool or cluster task)."""
    assert _VIS_SURFACE is not None
    surface, tops = _VIS_SURFACE
    cam, box, path = job
    return visibility_grid(cam, surface, box, Path(path), tops=tops)


def _photo(path: Path) -> np.ndarray:
    key = str(path)
    img = _CACHE.get(key)
    if img is not None:
        _CACHE.move_to_end(key)
        return img
    img = read_photo_bgr(key)
    _CACHE[key] = img
    while sum(a.nbytes for a in _CACHE.values()) > _CACHE_BYTES and len(_CACHE) > 1:
        _CACHE.popitem(last=False)
    return img


@dataclass
class _Patch:
    """A photo's rectified pixels over part of a padded tile."""

    sl: tuple[slice, slice]  # where in the padded tile
    bgr: np.ndarray  # float32, gains not applied
    valid: np.ndarray


def _gather(
    patches: dict[int, _Patch],
    idx: np.ndarray,
    rows: np.ndarray,
    cols: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Photo ``idx[k]``'s colour at (rows[k], cols[k]) of the padded tile, and whether it has one."""
    out = np.zeros((len(idx), 3), np.float32)
    ok = np.zeros(len(idx), bool)
    for i in np.unique(idx):
        p = patches.get(int(i))
        if p is None:
            continue
        k = np.flatnonzero(idx == i)
        r, c = rows[k] - p.sl[0].start, cols[k] - p.sl[1].start
        inside = (r >= 0) & (c >= 0) & (r < p.bgr.shape[0]) & (c < p.bgr.shape[1])
        k, r, c = k[inside], r[inside], c[inside]
        good = p.valid[r, c]
        out[k[good]] = p.bgr[r[good], c[good]]
        ok[k[good]] = True
    return out, ok


VISIBLE_SEAM_DN = 10.0
_FEATHER_PX = 8  # feathering ramps over twice this across a seam


def _seam_stats(
    lab: np.ndarray, patches: dict[int, _Patch], gains: np.ndarray, result: np.ndarray, core: tuple[slice, slice]
) -> dict[str, float]:
    """Across each seam (neighbouring pixels owned by different photos, in the tile's core): how far
    the two photos' colours at the same ground point differ before and after the gains, and the
    output's step across seams against its step between other neighbours (texture)."""
    stats = {
        "seam_n": 0.0,
        "seam_raw": 0.0,
        "seam_bal": 0.0,
        "step_seam": 0.0,
        "step_n": 0.0,
        "step_other": 0.0,
        "other_n": 0.0,
        "seam_visible": 0.0,
    }
    sub = lab[core]
    res = result[core].astype(np.float32)
    # Seams show as colour steps, not as noise or texture resampled differently: compare low-passed colours.
    smooth = {i: _Patch(p.sl, cv2.GaussianBlur(p.bgr, (0, 0), 2.0), p.valid) for i, p in patches.items()}
    r0, c0 = core[0].start, core[1].start
    for a, b, ra, rb in (
        (sub[:, :-1], sub[:, 1:], res[:, :-1], res[:, 1:]),
        (sub[:-1, :], sub[1:, :], res[:-1, :], res[1:, :]),
    ):
        both = (a >= 0) & (b >= 0)
        seam = both & (a != b)
        other = both & (a == b)
        if other.any():
            stats["step_other"] += float(np.abs(ra[other] - rb[other]).mean(axis=1).sum())
            stats["other_n"] += float(other.sum())
        if not seam.any():
            continue
        rr, cc = np.nonzero(seam)
        stats["step_seam"] += float(np.abs(ra[seam] - rb[seam]).mean(axis=1).sum())
        stats["step_n"] += float(len(rr))
        rows, cols = rr + r0, cc + c0
        va, oka = _gather(smooth, a[seam], rows, cols)
        vb, okb = _gather(smooth, b[seam], rows, cols)
        ok = oka & okb
        if not ok.any():
            continue
        ga, gb = gains[a[seam][ok]], gains[b[seam][ok]]
        stats["seam_raw"] += float(np.abs(va[ok] - vb[ok]).mean(axis=1).sum())
        diff = np.abs(va[ok] * ga - vb[ok] * gb).mean(axis=1)
        stats["seam_bal"] += float(diff.sum())
        stats["seam_n"] += float(ok.sum())
        stats["seam_visible"] += float((diff > VISIBLE_SEAM_DN).sum())
    return stats


def _fill_holes(bgr: np.ndarray, holes: np.ndarray, max_hole_px: int) -> np.ndarray:
    """Inpaint the hole components no wider than ``max_hole_px``; return which pixels were filled."""
    if not holes.any() or max_hole_px <= 0:
        return np.zeros_like(holes)
    h8 = holes.astype(np.uint8)
    n, comp = cv2.connectedComponents(h8, connectivity=8)
    # Half-width of each hole: the largest distance from inside it to its edge.
    dist = cv2.distanceTransform(h8, cv2.DIST_L2, 3)
    widest = np.zeros(n, np.float32)
    np.maximum.at(widest, np.asarray(comp, np.intp).ravel(), dist.ravel())
    # (a hole with no edge in the tile has the distance transform's huge value: no product of it)
    small = widest <= 0.5 * max_hole_px
    small[0] = False
    fill: np.ndarray = small[comp] & holes
    if fill.any():
        bgr[:] = cv2.inpaint(bgr, fill.astype(np.uint8), 5, cv2.INPAINT_TELEA)
    return fill


#: Pixels standing this much above the hidden ground nearest them (m) are what hides it (a roof, a
#: crown): hidden ground is never drawn from them.
_OCCLUDER_M = 0.5
#: How far from hidden ground (px) that test reaches: a wall's hidden strip is as wide as the wall
#: is high times its view's tangent (a 6 m wall at 0.3: 1.8 m, 36 px at 5 cm).
_OCCLUDER_REACH_PX = 48
#: The nearest ground's colours carried into hidden ground are softened over this (px, a Gaussian's
#: sigma): copied alone they streak across the strip.
_HIDDEN_SOFTEN_PX = 3.0


def _ground_behind(bgr: np.ndarray, hidden: np.ndarray, labelled: np.ndarray, z: np.ndarray) -> None:
    """Ground no photo sees, drawn from the ground round it. The photo that has it in frame most
    directly shows there what hides it (the roof, the wall's face): drawn from that photo, a roof
    ran on past its wall by the strip's width, a second edge beside it."""
    if not hidden.any():
        return
    # worked on the hidden cells' box and its reach only
    rr, cc = np.nonzero(hidden)
    m = 2 * _OCCLUDER_REACH_PX + 8
    box = (
        slice(max(0, int(rr.min()) - m), int(rr.max()) + m + 1),
        slice(max(0, int(cc.min()) - m), int(cc.max()) + m + 1),
    )
    img, hid, lab, zz = bgr[box], hidden[box], labelled[box], z[box]
    reach = cv2.getStructuringElement(cv2.MORPH_RECT, (2 * _OCCLUDER_REACH_PX + 1,) * 2)
    # only the hidden ground: a roof's own edge cells hidden behind its rim keep their view
    # (breaklines survey: redrawn as ground, 5 % of the roof edges moved 0.5 m in)
    low = cv2.erode(np.where(np.isfinite(zz), zz, np.inf).astype(np.float32), reach)
    with np.errstate(invalid="ignore"):
        hid = hid & (zz <= low + _OCCLUDER_M)
    if not hid.any():
        return
    near = cv2.dilate(hid.astype(np.uint8), reach) > 0
    with np.errstate(invalid="ignore"):
        above = near & ~(zz <= _nearest(hid, zz) + _OCCLUDER_M)
    source = lab & ~hid & ~above
    if not source.any():
        return
    weight = hid.astype(np.float32)
    carried = _nearest(source, img.astype(np.float32)) * weight[..., None]
    soft = cv2.GaussianBlur(carried, (0, 0), _HIDDEN_SOFTEN_PX)
    norm = cv2.GaussianBlur(weight, (0, 0), _HIDDEN_SOFTEN_PX)
    img[hid] = np.clip(soft[hid] / np.maximum(norm[hid], 1e-6)[:, None] + 0.5, 0, 255).astype(np.uint8)


def _nearest(at: np.ndarray, values: np.ndarray) -> np.ndarray:
    """Each pixel's value of ``values`` at the nearest pixel of ``at`` (OpenCV's distance transform,
    its 5 x 5 mask: within half a pixel of the exact nearest)."""
    _, label = cv2.distanceTransformWithLabels((~at).astype(np.uint8), cv2.DIST_L2, 5, labelType=cv2.DIST_LABEL_PIXEL)
    rows, cols = np.nonzero(at)  # the labels number the zero pixels in this order, from 1
    return np.asarray(values[rows[label - 1], cols[label - 1]])


def render_tile(win: Window) -> tuple[Window, np.ndarray, np.ndarray, dict[str, float]]:
    ctx = _CTX
    assert ctx is not None
    pad = ctx.pad_px
    rows, cols = ctx.shape
    r0, c0 = max(0, win.row_off - pad), max(0, win.col_off - pad)
    pw = Window(c0, r0, min(cols, win.col_off + win.width + pad) - c0, min(rows, win.row_off + win.height + pad) - r0)
    core = slices_in(win, pw)
    x, y, z = window_xyz(ctx.transform, pw, ctx.surface)
    shape = (pw.height, pw.width)
    planned = ctx.plan.labels_for(ctx.transform, pw)
    best = np.full(shape, np.inf, np.float32)
    best_lab = np.full(shape, -1, np.int16)
    planned_ok = np.zeros(shape, bool)
    coverage = np.zeros(shape, bool)
    projs: dict[int, tuple[tuple[slice, slice], Any]] = {}
    for i, box in enumerate(ctx.boxes):
        sub = intersect(box, pw) if box is not None else None
        if sub is None:
            continue
        sl = slices_in(sub, pw)
        p = project_window(ctx.cams[i], x[sl], y[sl], z[sl], ctx.vis[i])
        if not p.in_frame.any():
            continue
        projs[i] = (sl, p)
        coverage[sl] |= p.in_frame
        keep_best(best, best_lab, sl, p.cost, i)
        planned_ok[sl] |= (planned[sl] == i) & p.valid
    # The plan's owner where it sees the pixel at full resolution, else the best photo that does.
    lab = np.where(planned_ok, planned, best_lab).astype(np.int16)
    occluded = _occluded_from_nearest(ctx, projs, coverage & (lab < 0), x, y, z)
    lab = np.where(occluded >= 0, occluded, lab).astype(np.int16)
    occluded_px = occluded >= 0

    # Each photo's pixels are rendered this far beyond what it owns: the multiband pyramid reads
    # them, feathering overlaps them, and without blending one pixel lets the seam be measured.
    radius = 2**BANDS if ctx.blend == "multiband" else (_FEATHER_PX if ctx.blend == "feather" else 1)
    kernel = cv2.getStructuringElement(cv2.MORPH_RECT, (2 * radius + 1, 2 * radius + 1)) if radius else None
    patches: dict[int, _Patch] = {}
    for i in np.unique(lab[lab >= 0]):
        sl, p = projs[int(i)]
        own = (lab[sl] == i).astype(np.uint8)
        usable = p.valid | (occluded_px[sl] & p.in_frame)
        need = (cv2.dilate(own, kernel) if kernel is not None else own).astype(bool) & usable
        rr, cc = np.nonzero(need)
        r0, r1, c0, c1 = rr.min(), rr.max() + 1, cc.min(), cc.max() + 1
        cam = ctx.cams[int(i)]
        img = _photo(cam.file)
        mx, my = p.map_x[r0:r1, c0:c1], p.map_y[r0:r1, c0:c1]
        bgr = remap_bgr(img, mx, my, ctx.interpolation).astype(np.float32)
        lift = falloff_gain(frame_rho(mx, my, cam.intrinsics.width_px, cam.intrinsics.height_px), ctx.plan.falloff)
        if lift is not None:  # the lens's falloff out, as the gains were solved for
            bgr *= lift[..., None]
        psl = (slice(sl[0].start + r0, sl[0].start + r1), slice(sl[1].start + c0, sl[1].start + c1))
        patches[int(i)] = _Patch(psl, bgr, need[r0:r1, c0:c1])

    gains = ctx.plan.gains
    labelled = lab >= 0
    out = _blended(ctx.blend, lab, labelled, patches, gains, shape, ctx.plan.movers_for(ctx.transform, pw))
    stats = _seam_stats(lab, patches, gains, out, core)
    _ground_behind(out, occluded_px, labelled, z)  # (occluded pixels are labelled: drawn from a photo)
    # transparent pixels the rendered ones enclose are holes too: a sliver between two frames' edges
    # (the demo: 3, 0.1 m², at the mosaic's edge) is no photo's, but a map has no slit in it
    holes = coverage & ~labelled | enclosed(~labelled)
    filled = _fill_holes(out, holes, ctx.max_hole_px)
    alpha = labelled | filled
    out[~alpha] = 0
    stats.update(
        coverage=float(coverage[core].sum()),
        filled=float(filled[core].sum()),
        holes_left=float((holes & ~filled)[core].sum()),
        occluded=float(occluded_px[core].sum()),
    )
    rgba = np.empty((4, win.height, win.width), np.uint8)
    rgba[0], rgba[1], rgba[2] = out[core][..., 2], out[core][..., 1], out[core][..., 0]
    rgba[3] = np.where(alpha[core], 255, 0)
    # the source of each pixel: its photo (1-based) and how it was rendered
    source = np.zeros((2, win.height, win.width), np.uint16)
    seen = labelled[core] & ~occluded_px[core]
    source[0] = np.where(labelled[core], lab[core].astype(np.int32) + 1, 0)
    source[1] = np.select([seen, occluded_px[core], filled[core]], [SEEN, OCCLUDED, INPAINTED], NONE)
    used = {int(i) for i in np.unique(lab[core]) if i >= 0}
    return win, rgba, source, {**stats, "used": used}  # type: ignore[dict-item]


def _occluded_from_nearest(
    ctx: TileContext,
    projs: dict[int, tuple[tuple[slice, slice], Any]],
    holes: np.ndarray,
    x: np.ndarray,
    y: np.ndarray,
    z: np.ndarray,
) -> np.ndarray:
    """For the cells in some photo's frame that no photo sees (a true occlusion: the ground behind a
    wall that every photo's line of sight meets first), the photo that has them in frame most
    directly (-1 elsewhere): drawn from it and marked, not left a hole."""
    best = np.full(holes.shape, np.inf, np.float32)
    lab = np.full(holes.shape, -1, np.int16)
    if not holes.any():
        return lab
    for i, (sl, p) in projs.items():
        here = holes[sl] & p.in_frame
        if not here.any():
            continue
        zz = z[sl]
        cost = preference_cost(ctx.cams[i], x[sl], y[sl], np.where(np.isfinite(zz), zz, 0.0), p.map_x, p.map_y)
        keep_best(best, lab, sl, np.where(here, cost, np.inf).astype(np.float32), i)
    return lab


def _blended(
    blend: str,
    lab: np.ndarray,
    labelled: np.ndarray,
    patches: dict[int, _Patch],
    gains: np.ndarray,
    shape: tuple[int, int],
    movers: np.ndarray | None = None,
) -> np.ndarray:
    """The tile (BGR, 0 where no photo) from each photo's balanced patch, blended across the seams
    (``movers``: where the seam plan found a photo showing what the others did not)."""
    out = np.zeros(shape + (3,), np.uint8)
    if blend == "none" or len(patches) == 1:
        for i, patch in patches.items():
            m = lab[patch.sl] == i
            out[patch.sl][m] = np.clip(patch.bgr[m] * gains[i] + 0.5, 0, 255).astype(np.uint8)
        return out
    if not patches:
        return out
    blender = cv2.detail.MultiBandBlender(0, BANDS) if blend == "multiband" else cv2.detail.FeatherBlender(0.05)
    blender.prepare((0, 0, shape[1], shape[0]))
    if movers is not None and movers.any():
        _without_foreign(lab, patches, gains, shape, movers)
    for i, patch in patches.items():
        # Multiband blends across the seam masks by its pyramid; feathering needs the masks to
        # overlap (OpenCV weighs each mask by the distance to its own edge): the grown region.
        own = (lab[patch.sl] == i) if blend == "multiband" else patch.valid
        m = (own & patch.valid).astype(np.uint8) * 255
        img16 = np.clip(patch.bgr * gains[i] + 0.5, 0, 255).astype(np.int16)
        blender.feed(img16, m, (patch.sl[1].start, patch.sl[0].start))
    res, _ = blender.blend(None, None)  # type: ignore[call-overload]  # OpenCV allocates the outputs
    res = res.get() if isinstance(res, cv2.UMat) else np.asarray(res)
    out[labelled] = np.clip(res[: shape[0], : shape[1]][labelled], 0, 255).astype(np.uint8)
    return out


def _without_foreign(
    lab: np.ndarray, patches: dict[int, _Patch], gains: np.ndarray, shape: tuple[int, int], movers: np.ndarray
) -> None:
    """Within ``movers``, each patch's pixels beyond its own region that disagree with the owner's
    by more than ``_FOREIGN_DN`` take the owner's colour (in place): the blend reads a photo's
    pixels up to 32 px past its seam, and a car that had moved on came out there as a faint ghost
    (the small survey, seed 4: three). Elsewhere the blend is as it was: over a misregistration
    (photos placed by their GPS) it is what softens the seam (the tiny survey's step: 16.5 DN
    blended, 24.6 with every foreign pixel refused)."""
    owner = np.zeros(shape + (3,), np.float32)
    for i, patch in patches.items():
        m = (lab[patch.sl] == i) & patch.valid
        owner[patch.sl][m] = patch.bgr[m] * gains[i]
    labelled = lab >= 0
    for i, patch in patches.items():
        foreign = patch.valid & labelled[patch.sl] & (lab[patch.sl] != i) & movers[patch.sl]
        if not foreign.any():
            continue
        diff = np.sqrt(np.sum((patch.bgr * gains[i] - owner[patch.sl]) ** 2, axis=2))
        diff = cv2.GaussianBlur(np.where(foreign, diff, 0.0).astype(np.float32), (0, 0), 1.0)
        swap = foreign & (diff > _FOREIGN_DN)
        if swap.any():
            patch.bgr[swap] = owner[patch.sl][swap] / np.maximum(gains[i], 1e-6)
