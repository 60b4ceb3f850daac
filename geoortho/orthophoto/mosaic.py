"""The orthophoto: photos rectified on the DSM tile by tile, seams, balance, blending, hole fill, COG.

:func:`mosaic` works from posed cameras and a surface (tests give it the true
poses); :func:`ortho` is the algorithm: poses from an ``sfm`` folder or from
the photo metadata, surface from a DSM or flat ground.
"""

from __future__ import annotations

import contextlib
import math
import os
import tempfile
import time
from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Literal, get_args

import cv2
import numpy as np
from affine import Affine
from pyproj import CRS
from rasterio.windows import Window

from geoortho.core.camera import PosedCamera
from geoortho.core.crs import crs_to_text, horizontal_unit_m
from geoortho.core.outputs import atomic_path, temp_prefix, write_json
from geoortho.core.parallel import imap_ordered, map_ordered
from geoortho.core.sfm_model import cameras_from_sfm
from geoortho.core.surface import FlatSurface, GridSurface, Surface, read_surface, sample_grid, whole_surface
from geoortho.elevation.coverage import MEASURED, footprint_polygons, seen_area_m2, seen_count, source_path
from geoortho.errors import InputError, ParameterError
from geoortho.feedback import Feedback, as_feedback, split
from geoortho.orthophoto.falloff import falloff_gain, frame_rho
from geoortho.orthophoto.provenance import (
    INPAINTED,
    NONE,
    OCCLUDED,
    SEEN,
    SourceWriter,
    seamlines_path,
    write_seamlines,
)
from geoortho.orthophoto.rectify import (
    BlockTops,
    VisibilityGrid,
    block_tops,
    bounds_window,
    intersect,
    keep_best,
    preference_cost,
    project_window,
    remap_bgr,
    slices_in,
    visibility_grid,
    window_xyz,
)
from geoortho.orthophoto.seams import BALANCE, SEAMS, Balance, SeamMethod, SeamPlan, plan_seams, read_photo_bgr
from geoortho.photos.footprint import compute_footprints, photo_cameras, photos_with_altitude, working_crs
from geoortho.photos.heights import GpsAltitude

DsmOffset = Literal["correct", "refuse", "ignore"]
DSM_OFFSET: tuple[str, ...] = get_args(DsmOffset)

__all__ = ["OrthoResult", "ortho", "mosaic", "BLEND", "BALANCE", "SEAMS", "COMPRESS", "INTERPOLATION"]

Blend = Literal["multiband", "feather", "none"]
Compression = Literal["DEFLATE", "JPEG"]
Interpolation = Literal["bilinear", "bicubic", "lanczos", "nearest"]
BLEND: tuple[str, ...] = get_args(Blend)
COMPRESS: tuple[str, ...] = get_args(Compression)
_INTERPOLATION = {
    "bilinear": cv2.INTER_LINEAR,
    "bicubic": cv2.INTER_CUBIC,
    "lanczos": cv2.INTER_LANCZOS4,
    "nearest": cv2.INTER_NEAREST,
}
INTERPOLATION: tuple[str, ...] = get_args(Interpolation)
_BANDS = 5  # multi-band levels: the lowest spans 2**5 px on each side of a seam
#: A photo's pixel past its seam, where the seam plan found movers, that differs from the owner's by
#: more than this (RGB distance, smoothed over a pixel) is not blended in.
_FOREIGN_DN = 40.0
_CACHE_BYTES = 600 * 2**20  # decoded photos kept per worker


@dataclass(frozen=True)
class OrthoResult:
    """The orthophoto and what was measured while making it.

    Attributes
    ----------
    output : Path
        Orthophoto (COG, RGB + alpha).
    preview : Path
        PNG preview (None when not asked for).
    report : Path
        Report JSON: resolution, GSD, coverage, holes, seam colour mismatch, gains.
    crs : str
        CRS of the orthophoto.
    resolution_m : float
        Pixel size, metres.
    median_gsd_m : float
        Median GSD of the photos, metres.
    width_px : int
        Width of the orthophoto.
    height_px : int
        Height of the orthophoto.
    n_photos : int
        Photos given.
    n_used : int
        Photos in the mosaic.
    coverage_px : int
        Pixels with data.
    holes_filled_px : int
        Pixels inpainted inside the coverage.
    holes_left_px : int
        Holes left transparent (wider than max_hole_px).
    seam_mismatch_raw : float
        Colour difference across seams before balancing, DN.
    seam_mismatch_balanced : float
        Colour difference across seams after balancing, DN.
    poses : str
        Where the poses came from.
    surface : str
        What the photos were rectified on.
    skipped : tuple of (str, str)
        Photos left out, and why.
    notes : tuple of str
        What was assumed or checked, in words.
    seconds : dict of str to float
        Time spent in each step.
    area_m2 : float
        Ground the orthophoto shows (opaque pixels).
    seen_1_m2 : float
        Ground seen by at least one of the photos used (their frames cast on the surface).
    seen_2_m2 : float
        Ground seen by at least two of them.
    share_of_seen_1 : float
        Share of ``seen_1_m2`` the orthophoto shows.
    share_of_seen_2 : float
        Share of ``seen_2_m2`` the orthophoto shows.
    on_interpolated_m2 : float
        Ground the orthophoto shows on DSM cells that were interpolated or a fallback plane (from the
        DSM's ``_source.tif`` when it has one; otherwise the ground past the DSM's grid, on its plane).
    dsm_offset_m : float
        The DSM's height above the SfM's points (median), as measured before any correction (NaN:
        not measured: no SfM, or too few points over the DSM).
    holes_inside_m2 : float
        Transparent ground the mosaic surrounds (holes inside it, not its outer edge).
    holes_inside_n : float
        How many such holes.
    largest_hole_m2 : float
        The largest of them.
    occluded_m2 : float
        Ground no photo sees (a true occlusion on the DSM), drawn from the seen ground round it
        (not from what hides it), marked 2 in the source raster; band 1 names the photo that has
        it in frame most directly.
    source : Path
        ``<name>_source.tif``: each pixel's photo (band 1, 1-based, named in its attribute table)
        and how it was drawn (band 2: 1 seen, 2 occluded, 3 inpainted).
    seamlines : Path
        ``<name>_seamlines.gpkg``: one polygon per photo region, with the photo's name, GSD, view
        angle, capture time and area.
    """

    output: Path
    preview: Path | None
    report: Path
    crs: str
    resolution_m: float
    median_gsd_m: float
    width_px: int
    height_px: int
    n_photos: int
    n_used: int
    coverage_px: int
    holes_filled_px: int
    holes_left_px: int
    seam_mismatch_raw: float
    seam_mismatch_balanced: float
    poses: str
    surface: str
    skipped: tuple[tuple[str, str], ...] = ()
    notes: tuple[str, ...] = ()
    seconds: dict[str, float] = field(default_factory=dict)
    area_m2: float = 0.0
    seen_1_m2: float = 0.0
    seen_2_m2: float = 0.0
    share_of_seen_1: float = 0.0
    share_of_seen_2: float = 0.0
    on_interpolated_m2: float = 0.0
    dsm_offset_m: float = math.nan
    holes_inside_m2: float = 0.0
    holes_inside_n: float = 0.0
    largest_hole_m2: float = 0.0
    occluded_m2: float = 0.0
    source: Path | None = None
    seamlines: Path | None = None


#: The orthophoto is said to fall short below this share of the ground the photos saw.
MIN_SHARE_OF_SEEN = 0.95
#: Coverage is measured on a grid of at most this many cells.
COVERAGE_CELLS = 4_000_000


def measure_coverage(
    ortho: Path, cams: Sequence[PosedCamera], surface: Surface, dsm_source: Path | None
) -> dict[str, float]:
    """The orthophoto's opaque area against the ground its photos saw (by >= 1 and >= 2 of them),
    and how much of it lies on interpolated DSM cells, measured on a grid of at most
    :data:`COVERAGE_CELLS` cells over the orthophoto's extent."""
    import rasterio
    from rasterio.enums import Resampling

    with rasterio.open(ortho) as ds:
        crs = ds.crs
        f = max(1, math.ceil(math.sqrt(ds.width * ds.height / COVERAGE_CELLS)))
        shape = (max(1, ds.height // f), max(1, ds.width // f))
        alpha = ds.read_masks(1, out_shape=shape, resampling=Resampling.nearest) > 0
        t = ds.transform @ Affine.scale(ds.width / shape[1], ds.height / shape[0])
    cell_m2 = abs(t.a * t.e)
    polys = footprint_polygons(cams, surface)
    seen = seen_count(polys, t, shape)
    out = {
        "area_m2": float(alpha.sum()) * cell_m2,
        # the areas from the footprints themselves: the dem on the same DSM states the same figures
        "seen_1_m2": seen_area_m2(polys, 1),
        "seen_2_m2": seen_area_m2(polys, 2),
        "share_of_seen_1": float((alpha & (seen >= 1)).sum()) / max(int((seen >= 1).sum()), 1),
        "share_of_seen_2": float((alpha & (seen >= 2)).sum()) / max(int((seen >= 2).sum()), 1),
        "on_interpolated_m2": 0.0,
        **_holes_inside(alpha, cell_m2, ortho, f),
        "occluded_m2": 0.0,
    }
    own_source = source_path(ortho)
    if own_source.is_file():
        with rasterio.open(own_source) as ds:
            how = ds.read(2, out_shape=shape, resampling=Resampling.nearest)
        out["occluded_m2"] = float((alpha & (how == OCCLUDED)).sum()) * cell_m2
    if dsm_source is not None and dsm_source.is_file():
        from rasterio.warp import reproject

        src_grid = np.zeros(shape, np.uint8)
        with rasterio.open(dsm_source) as ds:
            # onto the orthophoto's grid, in its CRS (an ortho made with --crs is in another)
            reproject(rasterio.band(ds, 1), src_grid, dst_transform=t, dst_crs=crs, resampling=Resampling.nearest)
        out["on_interpolated_m2"] = float((alpha & (src_grid != MEASURED)).sum()) * cell_m2
    elif isinstance(surface, GridSurface):
        # the ortho's DSM has its holes filled on reading: what is left off it lies past its grid

        rows, cols = np.nonzero(alpha)
        x, y = t * (cols + 0.5, rows + 0.5)
        c, r = surface.colrow(np.asarray(x), np.asarray(y))
        raw = sample_grid(surface.grid, c, r)
        out["on_interpolated_m2"] = float((~np.isfinite(raw)).sum()) * cell_m2
    return out


def _holes_inside(alpha: np.ndarray, cell_m2: float, ortho: Path | None = None, f: int = 1) -> dict[str, float]:
    """Transparent pixels the mosaic surrounds (not its outer edge): their area, how many holes,
    the largest. ``alpha`` is the mosaic's mask read every ``f`` pixels; each hole found on it is
    measured again on ``ortho``'s own pixels round it: a decimated read pinches a narrow inlet of
    the outer edge shut (toledo: "1 hole, 0.1 m²" where the full mask had none)."""
    from scipy import ndimage

    holes = ndimage.binary_fill_holes(alpha) & ~alpha
    labels, n = ndimage.label(holes, structure=np.ones((3, 3), bool))
    sizes = (np.bincount(labels.ravel())[1:] * cell_m2) if n else np.zeros(0)
    if n and ortho is not None and f > 1:
        import rasterio

        with rasterio.open(ortho) as ds:
            sizes = np.array([_hole_at_full_resolution(ds, box, f) for box in ndimage.find_objects(labels)])
        sizes = sizes[sizes > 0]
        n = len(sizes)
    return {
        "holes_inside_m2": float(sizes.sum()),
        "holes_inside_n": float(n),
        "largest_hole_m2": float(sizes.max()) if n else 0.0,
    }


def _hole_at_full_resolution(ds: Any, box: tuple[slice, slice], f: int) -> float:
    """The area (m²) of the transparent pixels round a hole of the decimated mask (its ``box``) that
    the orthophoto ``ds``'s full mask encloses: none of them reaches the window's edge (two
    decimated cells out)."""
    from rasterio.windows import Window

    r0, c0 = max(0, (box[0].start - 2) * f), max(0, (box[1].start - 2) * f)
    r1, c1 = min(ds.height, (box[0].stop + 2) * f), min(ds.width, (box[1].stop + 2) * f)
    empty = ds.read_masks(1, window=Window(c0, r0, c1 - c0, r1 - r0)) == 0
    result: float = float(_enclosed(empty).sum()) * abs(ds.transform.a * ds.transform.e)
    return result


# ---------------------------------------------------------------------------------------------
# one tile (runs in a worker)


@dataclass(frozen=True, eq=False)
class _Context:
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


_CTX: _Context | None = None
_CACHE: OrderedDict[str, np.ndarray] = OrderedDict()


def _init_worker(ctx: _Context) -> None:
    global _CTX
    _CTX = ctx
    _CACHE.clear()
    cv2.setNumThreads(1)


_VIS_SURFACE: tuple[GridSurface, tuple[BlockTops, ...]] | None = None


def _init_visibility(surface: GridSurface, tops: tuple[BlockTops, ...]) -> None:
    global _VIS_SURFACE
    _VIS_SURFACE = (surface, tops)


def _visibility_task(job: tuple[PosedCamera, tuple[float, float, float, float], str]) -> VisibilityGrid | None:
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


def _enclosed(empty: np.ndarray) -> np.ndarray:
    """The ``empty`` pixels not connected to the tile's border."""
    # 4-connected, as the holes are counted (scipy's fill_holes): a diagonal touch does not let one out
    n, comp = cv2.connectedComponents(empty.astype(np.uint8), connectivity=4)
    if n <= 1:
        return np.zeros_like(empty)
    outside = np.zeros(n, bool)
    for edge in (comp[0], comp[-1], comp[:, 0], comp[:, -1]):
        outside[np.unique(edge)] = True
    outside[0] = True  # label 0: the rendered pixels
    result: np.ndarray = ~outside[comp]
    return result


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


def _render_tile(win: Window) -> tuple[Window, np.ndarray, np.ndarray, dict[str, float]]:
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
    radius = 2**_BANDS if ctx.blend == "multiband" else (_FEATHER_PX if ctx.blend == "feather" else 1)
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
    holes = coverage & ~labelled | _enclosed(~labelled)
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
    ctx: _Context,
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
    blender = cv2.detail.MultiBandBlender(0, _BANDS) if blend == "multiband" else cv2.detail.FeatherBlender(0.05)
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


# ---------------------------------------------------------------------------------------------
# the whole mosaic


def _grid(
    boxes: Sequence[tuple[float, float, float, float]],
    surface: Surface,
    resolution_m: float,
) -> tuple[Affine, tuple[int, int]]:
    xmin = min(b[0] for b in boxes)
    ymin = min(b[1] for b in boxes)
    xmax = max(b[2] for b in boxes)
    ymax = max(b[3] for b in boxes)
    if isinstance(surface, GridSurface) and not surface.extend:
        sx0, sy0, sx1, sy1 = surface.bounds
        xmin, ymin, xmax, ymax = max(xmin, sx0), max(ymin, sy0), min(xmax, sx1), min(ymax, sy1)
    r = resolution_m
    x0, y1 = math.floor(xmin / r) * r, math.ceil(ymax / r) * r
    cols, rows = int(math.ceil((xmax - x0) / r)), int(math.ceil((y1 - ymin) / r))
    return Affine(r, 0, x0, 0, -r, y1), (rows, cols)


@dataclass(frozen=True)
class MosaicOptions:
    """How the mosaic is made: ortho's options, grouped (their defaults are ortho's too)."""

    seams: SeamMethod = "graphcut"
    balance: Balance = "channels"
    blend: Blend = "multiband"
    max_hole_px: int = 64
    compress: Compression = "DEFLATE"
    interpolation: Interpolation = "bilinear"
    tile_px: int = 1024
    #: False skips the line-of-sight test: a plain, not true, orthophoto (faster; the tests
    #: compare against it to show that walls do not ghost).
    occlusion: bool = True
    workers: int = 0

    def check(self) -> None:
        if (
            self.seams not in SEAMS
            or self.balance not in BALANCE
            or self.blend not in BLEND
            or self.compress.upper() not in COMPRESS
        ):
            raise InputError(
                f"choose seams from {SEAMS}, balance from {BALANCE}, blend from {BLEND}, compress from {COMPRESS}"
            )
        if self.interpolation not in _INTERPOLATION:
            raise InputError(f"interpolation {self.interpolation!r} is not one of {', '.join(INTERPOLATION)}")


def mosaic(
    cams: Sequence[PosedCamera],
    surface: Surface,
    crs: CRS,
    output: str | os.PathLike[str],
    resolution_m: float | None = None,
    options: MosaicOptions = MosaicOptions(),
    *,
    preview: str | os.PathLike[str] | None = None,
    poses: str = "given",
    notes: Sequence[str] = (),
    skipped: Sequence[tuple[str, str]] = (),
    dsm_source: str | os.PathLike[str] | None = None,
    dsm_offset_m: float = math.nan,
    feedback: Feedback | None = None,
) -> OrthoResult:
    """Orthorectify posed photos onto ``surface`` and mosaic them into a COG at ``output``.

    The stages: place each photo on the surface, choose the resolution and the grid, the
    occlusion grids, seams and gains (on a coarse grid), render the tiles in parallel, write
    the COG and the report."""
    fb = as_feedback(feedback)
    options.check()
    output = Path(output)
    started = time.time()
    try:
        return _mosaic(cams, surface, crs, output, resolution_m, options, preview, poses, notes, skipped, dsm_source,
                       dsm_offset_m, fb)  # fmt: skip
    except BaseException:
        # canceled or failed after some products were written (the COG, then its source raster,
        # seamlines and report): none of this run's is left, as if it had not started
        report = output.with_name(output.stem + "_report.json")
        shown = Path(preview) if preview is not None else None
        for path in (output, source_path(output), seamlines_path(output), report, shown):
            with contextlib.suppress(OSError):
                if path is not None and path.is_file() and path.stat().st_mtime >= started - 1.0:
                    path.unlink()
        raise


def _mosaic(
    cams: Sequence[PosedCamera],
    surface: Surface,
    crs: CRS,
    output: Path,
    resolution_m: float | None,
    options: MosaicOptions,
    preview: str | os.PathLike[str] | None,
    poses: str,
    notes: Sequence[str],
    skipped: Sequence[tuple[str, str]],
    dsm_source: str | os.PathLike[str] | None,
    dsm_offset_m: float,
    fb: Feedback,
) -> OrthoResult:
    times: dict[str, float] = {}
    t0 = time.perf_counter()
    notes = list(notes)
    skipped = list(skipped)
    st_vis, st_plan, st_tiles, st_write = split(fb, [2, 2, 10, 1])
    placed = _without_other_flights(_place(cams, surface, fb), fb)
    skipped += placed.skipped
    resolution_m, median_gsd = _resolution(resolution_m, placed.gsds, notes, fb)
    transform, shape = _grid(placed.boxes, surface, resolution_m)
    if shape[0] * shape[1] > 4e9:
        raise InputError(f"the mosaic would be {shape[1]}x{shape[0]} px: give a coarser resolution")
    plan, totals, used, preview_path = _build_mosaic(
        placed, surface, crs, transform, shape, output, options, preview, resolution_m, (t0, times),
        (st_vis, st_plan, st_tiles), fb,
    )  # fmt: skip
    skipped += plan.skipped
    notes.extend(plan.notes)
    st_write.progress(1.0)

    cover = measure_coverage(output, placed.cams, surface, Path(dsm_source) if dsm_source is not None else None)
    notes.extend(_coverage_notes(cover, fb))
    raw, bal = _ratio(totals, "seam_raw", "seam_n"), _ratio(totals, "seam_bal", "seam_n")
    if options.balance != "none" and math.isfinite(raw) and math.isfinite(bal) and bal >= raw:
        notes.append(f"colour balance did not lower the colour mismatch across seams ({raw:.2f} → {bal:.2f} DN)")
        fb.warning(notes[-1])

    result = OrthoResult(
        output=output,
        preview=preview_path,
        report=output.with_name(output.stem + "_report.json"),
        crs=crs_to_text(crs),
        resolution_m=resolution_m,
        median_gsd_m=median_gsd,
        width_px=shape[1],
        height_px=shape[0],
        n_photos=len(cams),
        n_used=len(used),
        coverage_px=int(totals.get("coverage", 0)),
        holes_filled_px=int(totals.get("filled", 0)),
        holes_left_px=int(totals.get("holes_left", 0)),
        seam_mismatch_raw=raw,
        seam_mismatch_balanced=bal,
        poses=poses,
        surface=_describe(surface),
        skipped=tuple(skipped),
        notes=tuple(notes),
        seconds=times,
        dsm_offset_m=dsm_offset_m,
        source=source_path(output),
        seamlines=seamlines_path(output),
        **cover,
    )
    gains = {c.name: [float(g) for g in plan.gains[i]] for i, c in enumerate(placed.cams)}
    unused = sorted(c.name for i, c in enumerate(placed.cams) if i not in used)
    _write_report(result, totals, gains, time.perf_counter() - t0, plan.views_held_max, unused)
    fb.info(
        f"ortho: {output} ({shape[1]}x{shape[0]} px, {result.n_used} photos used); seam mismatch "
        f"{result.seam_mismatch_raw:.1f} → {result.seam_mismatch_balanced:.1f} DN after balancing"
    )
    return result


def _build_mosaic(
    placed: Any,
    surface: Surface,
    crs: CRS,
    transform: Affine,
    shape: tuple[int, int],
    output: Path,
    options: MosaicOptions,
    preview: str | os.PathLike[str] | None,
    resolution_m: float,
    clock: tuple[float, dict[str, float]],
    steps: tuple[Feedback, Feedback, Feedback],
    fb: Feedback,
) -> tuple[Any, dict[str, float], set[int], Path | None]:
    """Visibility, seams and gains, the tiles, the COG: the mosaic's plan, its tile totals, the
    photos used and the preview written. The temporaries (visibility grids, the tiled mosaic) sit
    beside the output, on the same disk. ``clock``: the mosaic's start (the visibility's seconds
    count the placing of the photos too, as the report always has) and the seconds of each step."""
    st_vis, st_plan, st_tiles = steps
    t0, times = clock
    output.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix=temp_prefix(output.name), dir=output.parent) as work_dir:
        if isinstance(surface, GridSurface) and os.name == "posix":
            # the workers map one file of the DSM instead of each holding a copy (posix only: Windows
            # cannot remove a file still mapped when the folder goes)
            surface = surface.mapped(work_dir)
        vis = _visibility(placed, surface, options, Path(work_dir), st_vis)
        times["visibility"] = time.perf_counter() - t0

        t1 = time.perf_counter()
        plan = _seams_and_gains(placed, surface, vis, transform, shape, options, st_plan)
        bad = {name for name, _ in plan.skipped}
        box_windows = tuple(
            None if c.name in bad else bounds_window(transform, shape, b) for c, b in zip(placed.cams, placed.boxes)
        )
        times["seams_and_balance"] = time.perf_counter() - t1
        fb.info(
            f"mosaic {shape[1]}x{shape[0]} px at {resolution_m * 100:.2f} cm, {len(placed.cams) - len(bad)} photos; "
            f"gains {plan.gains.min():.3f}..{plan.gains.max():.3f}"
        )

        t2 = time.perf_counter()
        ctx = _Context(
            placed.cams, box_windows, vis, surface, transform, shape, plan, options.blend, int(options.max_hole_px),
            2 ** (_BANDS + 1), _INTERPOLATION[options.interpolation],
        )  # fmt: skip
        tiled = Path(work_dir) / "mosaic.tif"
        sources = SourceWriter(Path(work_dir), crs, transform, shape)
        try:
            totals, used = _render(ctx, crs, tiled, options, st_tiles, sources)
        finally:
            sources.close()
        times["tiles"] = time.perf_counter() - t2
        t3 = time.perf_counter()
        _write_cog(tiled, output, options.compress.upper())
        preview_path = _write_preview(output, Path(preview)) if preview else None
        sources.finish(source_path(output), [c.name for c in placed.cams])
        times["cog"] = time.perf_counter() - t3
    t4 = time.perf_counter()
    _, n_regions = write_seamlines(
        source_path(output), placed.cams, placed.gsds, placed.taken_at, seamlines_path(output)
    )
    totals["seamline_photos"] = float(n_regions)
    times["seamlines"] = time.perf_counter() - t4
    return plan, totals, used, preview_path


def _visibility(
    placed: Any, surface: Surface, options: MosaicOptions, work_dir: Path, fb: Feedback
) -> tuple[VisibilityGrid | None, ...]:
    """Each photo's occlusion grid over its window of the DSM (None on flat ground or when off)."""
    if not (options.occlusion and isinstance(surface, GridSurface)):
        return (None,) * len(placed.cams)
    jobs = [
        (cam, box, str(work_dir / f"visibility_{i}.npy")) for i, (cam, box) in enumerate(zip(placed.cams, placed.boxes))
    ]
    # a photo's rays march over its DSM window: seconds a photo on a fine DSM, so in parallel
    return tuple(
        map_ordered(
            _visibility_task,
            jobs,
            workers=options.workers,
            initializer=_init_visibility,
            # the skip levels made here once (full-grid passes), sent with the DSM (1/64 of it)
            initargs=(surface, block_tops(surface)),
            feedback=fb,
        )
    )


def _seams_and_gains(
    placed: Any,
    surface: Surface,
    vis: tuple[VisibilityGrid | None, ...],
    transform: Affine,
    shape: tuple[int, int],
    options: MosaicOptions,
    fb: Feedback,
) -> Any:
    # Seams and gains are decided on cells 8x coarser (and no more than 2 Mpx): the graph cut's time
    # grows with the cells in the seam bands.
    factor = max(8, int(math.ceil(math.sqrt(shape[0] * shape[1] / 2.0e6))))
    return plan_seams(
        list(placed.cams),
        list(placed.boxes),
        list(placed.gsds),
        surface,
        list(vis),
        transform,
        shape,
        factor,
        seams=options.seams,
        balance=options.balance,
        feedback=fb,
    )


def _coverage_notes(cover: dict[str, Any], fb: Feedback) -> list[str]:
    """The orthophoto's area against the ground its photos saw; a warning when it misses some."""
    notes = [
        f"the orthophoto shows {cover['area_m2']:,.0f} m²: {cover['share_of_seen_1']:.1%} of the "
        f"{cover['seen_1_m2']:,.0f} m² its photos saw, {cover['share_of_seen_2']:.1%} of the "
        f"{cover['seen_2_m2']:,.0f} m² seen by >= 2; {cover['on_interpolated_m2']:,.0f} m² of it on an "
        f"interpolated surface, {cover['occluded_m2']:,.1f} m² seen by no photo (occluded: drawn from the "
        "seen ground round it, marked in the source raster)"
    ]
    fb.info(notes[-1])
    if cover["holes_inside_m2"] > 0:
        notes.append(
            f"{cover['holes_inside_n']:.0f} holes inside the orthophoto, {cover['holes_inside_m2']:,.1f} m² "
            f"(the largest {cover['largest_hole_m2']:,.1f} m²)"
        )
        fb.warning(notes[-1])
    if cover["share_of_seen_1"] < MIN_SHARE_OF_SEEN:
        notes.append(
            f"the orthophoto misses {1 - cover['share_of_seen_1']:.0%} of the ground its photos saw "
            f"(less than {MIN_SHARE_OF_SEEN:.0%} covered)"
        )
        fb.warning(notes[-1])
    return notes


def _ratio(totals: dict[str, float], a: str, n: str) -> float:
    """A mean over the tiles: the sum of ``a`` over the count ``n`` (NaN when nothing was counted)."""
    return totals.get(a, 0.0) / totals[n] if totals.get(n) else math.nan


def _write_report(
    result: OrthoResult,
    totals: dict[str, float],
    gains_bgr: dict[str, list[float]],
    seconds_total: float,
    coarse_views_held_max: int,
    unused: list[str],
) -> None:
    """``<name>_report.json``: the result's figures, and the seam and gain details behind them."""
    write_json(
        result.report,
        {
            **{k: v for k, v in result.__dict__.items() if k not in ("skipped", "notes")},
            "skipped": [{"image": n, "reason": w} for n, w in result.skipped],
            # placed on the surface, but no pixel of theirs in the mosaic (others' views were chosen)
            "not_in_mosaic": unused,
            "notes": list(result.notes),
            "seam_step_dn": _ratio(totals, "step_seam", "step_n"),
            "texture_step_dn": _ratio(totals, "step_other", "other_n"),
            "seam_pixels": int(totals.get("seam_n", 0)),
            # seam pixels where the two balanced photos differ by more than VISIBLE_SEAM_DN (low-passed):
            # the seam one can see, which a long seam through agreeing ground does not inflate
            "seam_visible_pixels": int(totals.get("seam_visible", 0)),
            "gains_bgr": gains_bgr,
            # the seam pass streams photos: how many coarse views it held at once (memory)
            "coarse_views_held_max": coarse_views_held_max,
            "seconds_total": seconds_total,
        },
    )


@dataclass(frozen=True)
class _Placed:
    """The photos that see the surface, where they land and their GSD; the others and why."""

    cams: tuple[PosedCamera, ...]
    boxes: tuple[tuple[float, float, float, float], ...]  # ground bounding box of each footprint
    gsds: tuple[float, ...]  # GSD at the image centre, metres
    skipped: tuple[tuple[str, str], ...]
    taken_at: tuple[str, ...] = ()  # each photo's capture time (ISO 8601, "" when unknown)


MIN_AXIS_BELOW_HORIZON_DEG = 20.0


def _place(cams: Sequence[PosedCamera], surface: Surface, fb: Feedback) -> _Placed:
    """Cast each photo's border onto the surface (as the footprints stage does); leave out those that miss it."""
    if not cams:
        raise InputError("no photo sees the surface: nothing to mosaic")
    centres = np.array([c.pose.center for c in cams])
    ground = surface.elevation(centres[:, 0], centres[:, 1])
    heights = centres[:, 2] - np.where(np.isfinite(ground), ground, surface.z_min)
    max_range = 5.0 * float(np.median(heights[heights > 0])) if (heights > 0).any() else 1000.0
    table = compute_footprints(cams, surface, max_range_m=max_range)
    kept: list[PosedCamera] = []
    boxes: list[tuple[float, float, float, float]] = []
    gsds: list[float] = []
    skipped: list[tuple[str, str]] = []
    axis_z = np.array([(c.pose.rotation @ [0.0, 0.0, 1.0])[2] for c in cams])
    below_horizon_deg = np.degrees(np.arcsin(np.clip(-axis_z, -1.0, 1.0)))
    for i, cam in enumerate(cams):
        if below_horizon_deg[i] < MIN_AXIS_BELOW_HORIZON_DEG:
            # a view along the ground rectifies into a smear of stretched pixels, never a map
            why = (
                f"it looks at the horizon (view axis {abs(below_horizon_deg[i]):.0f} deg "
                f"{'below' if below_horizon_deg[i] >= 0 else 'above'} it, "
                f"less than {MIN_AXIS_BELOW_HORIZON_DEG:.0f}): not a mapping photo"
            )
            skipped.append((cam.name, why))
            fb.warning(f"skipped {cam.name}: {why}")
            continue
        # rays that missed end at the range limit: the box reaches that far
        ring = table.rings[i]
        box = (float(ring[:, 0].min()), float(ring[:, 1].min()), float(ring[:, 0].max()), float(ring[:, 1].max()))
        sees = heights[i] > 0 and np.isfinite(table.gsd_min_m[i])  # some ray met the surface
        if sees and isinstance(surface, GridSurface) and not surface.extend:
            sx0, sy0, sx1, sy1 = surface.bounds
            sees = not (box[2] <= sx0 or box[0] >= sx1 or box[3] <= sy0 or box[1] >= sy1)
        if not sees:
            skipped.append((cam.name, "its footprint misses the surface (outside the DSM or camera below it)"))
            fb.warning(f"skipped {cam.name}: outside the surface")
            continue
        kept.append(cam)
        boxes.append(box)
        gsds.append(float(table.gsd_m[i]))
    if not kept:
        raise InputError("no photo sees the surface: nothing to mosaic")
    return _Placed(tuple(kept), tuple(boxes), tuple(gsds), tuple(skipped))


#: Photos taken this far apart in time are of different flights; a flight of one photo, or of under
#: ``OTHER_FLIGHT_SHARE`` of them (a stray photo of another day in the folder: its shadows,
#: cars and crops are not the survey's) is left out of the mosaic, named.
FLIGHT_GAP_S = 2 * 3600.0
OTHER_FLIGHT_SHARE = 0.1


def _without_other_flights(placed: _Placed, fb: Feedback) -> _Placed:
    """``placed`` with each photo's capture time (read once, for the flights here and the
    seamlines' table), less the photos of a small other flight (by the cameras' clocks)."""
    from geoortho.photos.metadata import photo_seconds, read_photo

    taken_at, seconds = [], []
    for cam in placed.cams:
        try:
            photo = read_photo(cam.file)
        except (InputError, ValueError, OSError):  # no file (a planned camera), no EXIF: no time
            taken_at.append("")
            seconds.append(math.nan)
            continue
        taken_at.append(photo.taken_at)
        seconds.append(photo_seconds(photo))
    placed = replace(placed, taken_at=tuple(taken_at))
    t = np.array(seconds)
    timed = np.flatnonzero(np.isfinite(t))
    if len(timed) < 3:
        return placed
    order = timed[np.argsort(t[timed], kind="stable")]
    flights = np.split(order, np.flatnonzero(np.diff(t[order]) > FLIGHT_GAP_S) + 1)
    main = max(flights, key=len)
    why: dict[int, str] = {}
    for flight in flights:
        if flight is main or len(flight) >= max(OTHER_FLIGHT_SHARE * len(timed), 2):
            continue
        hours = (float(np.median(t[flight])) - float(np.median(t[main]))) / 3600.0
        for i in flight:
            why[int(i)] = (
                f"taken {abs(hours):,.1f} h {'before' if hours < 0 else 'after'} the {len(main)} photos of the "
                "survey's flight: another flight over the site, left out of the mosaic and its seams"
            )
    if not why:
        return placed
    for i in sorted(why):
        fb.warning(f"skipped {placed.cams[i].name}: {why[i]}")
    keep = [i for i in range(len(placed.cams)) if i not in why]
    return _Placed(
        tuple(placed.cams[i] for i in keep),
        tuple(placed.boxes[i] for i in keep),
        tuple(placed.gsds[i] for i in keep),
        (*placed.skipped, *((placed.cams[i].name, why[i]) for i in sorted(why))),
        tuple(taken_at[i] for i in keep),
    )


def _resolution(
    resolution_m: float | None, gsds: Sequence[float], notes: list[str], fb: Feedback
) -> tuple[float, float]:
    """The pixel size (given, else the median GSD to 3 digits) and the median GSD, metres."""
    finite = [g for g in gsds if math.isfinite(g)]
    median_gsd = float(np.median(finite)) if finite else math.nan
    if not resolution_m:  # None or 0: the photos' median GSD
        if not math.isfinite(median_gsd):
            raise InputError("the GSD could not be found; give a resolution")
        resolution_m = float(f"{median_gsd:.3g}")
        fb.info(f"resolution {resolution_m * 100:.2f} cm: the median GSD")
    elif math.isfinite(median_gsd) and resolution_m < 0.95 * median_gsd:
        notes.append(
            f"the resolution {resolution_m * 100:.2f} cm is finer than the photos' median GSD "
            f"{median_gsd * 100:.2f} cm: pixels are interpolated, not resolved"
        )
        fb.warning(notes[-1])
    if resolution_m <= 0:
        raise InputError("the resolution must be positive")
    if math.isfinite(median_gsd) and not 0.1 * median_gsd <= resolution_m <= 100 * median_gsd:
        # a mosaic of a few pixels, or 100x more pixels than the photos resolve: neither is a product
        raise ParameterError(
            "resolution_m",
            f"{resolution_m:g} m is not within 0.1 to 100 x the photos' median GSD ({median_gsd * 100:.2f} cm): "
            f"give {0.1 * median_gsd:.3g} to {100 * median_gsd:.3g} m",
        )
    return resolution_m, median_gsd


def _render(
    ctx: _Context, crs: CRS, target: Path, options: MosaicOptions, progress: Feedback, sources: SourceWriter
) -> tuple[dict[str, float], set[int]]:
    """Every tile rendered (in parallel) into the tiled GeoTIFF ``target``, each pixel's source
    into ``sources``.

    Returns the tiles' summed statistics and the photos used."""
    import rasterio
    from rasterio.enums import ColorInterp

    shape, tile_px = ctx.shape, options.tile_px
    tiles = [
        Window(c, r, min(tile_px, shape[1] - c), min(tile_px, shape[0] - r))
        for r in range(0, shape[0], tile_px)
        for c in range(0, shape[1], tile_px)
    ]
    totals: dict[str, float] = {}
    used: set[int] = set()
    profile = {
        "driver": "GTiff",
        "width": shape[1],
        "height": shape[0],
        "count": 4,
        "dtype": "uint8",
        "crs": crs,
        "transform": ctx.transform,
        "tiled": True,
        "blockxsize": 512,
        "blockysize": 512,
        "BIGTIFF": "IF_SAFER",
    }
    with rasterio.open(target, "w", **profile) as dst:
        dst.colorinterp = [ColorInterp.red, ColorInterp.green, ColorInterp.blue, ColorInterp.alpha]
        for win, rgba, source, stats in imap_ordered(
            _render_tile, tiles, workers=options.workers, initializer=_init_worker, initargs=(ctx,), feedback=progress
        ):
            dst.write(rgba, window=win)
            sources.write(source, win)
            used |= stats.pop("used")  # type: ignore[arg-type]
            for k, v in stats.items():
                totals[k] = totals.get(k, 0.0) + v
    return totals, used


def _describe(surface: Surface) -> str:
    if isinstance(surface, FlatSurface):
        return f"flat ground at {surface.elevation_m:.2f} m"
    cell = surface.cell_m if isinstance(surface, GridSurface) else math.nan
    return f"DSM, cells of {cell:g}"


def _write_cog(src_path: Path, target: Path, compress: str) -> None:
    """The finished mosaic as a COG: RGBA with DEFLATE, or RGB + mask with JPEG (JPEG has no alpha)."""
    import rasterio
    from rasterio.shutil import copy as rio_copy

    opts: dict[str, Any] = {
        "driver": "COG",
        "compress": compress,
        "blocksize": 512,
        "BIGTIFF": "IF_SAFER",
        "overview_resampling": "average",
        "num_threads": "ALL_CPUS",
    }
    with atomic_path(target) as tmp:
        if compress == "JPEG":
            rgb_mask = src_path.with_name("rgb_mask.tif")
            with rasterio.Env(GDAL_TIFF_INTERNAL_MASK=True), rasterio.open(src_path) as src:
                prof = {**src.profile, "count": 3}
                with rasterio.open(rgb_mask, "w", **prof) as dst:
                    for _, w in src.block_windows(1):
                        dst.write(src.read((1, 2, 3), window=w), window=w)
                        dst.write_mask(src.read(4, window=w), window=w)
            with rasterio.Env(GDAL_TIFF_INTERNAL_MASK=True):
                rio_copy(rgb_mask, tmp, quality=90, **opts)
        else:
            rio_copy(src_path, tmp, predictor=2, **opts)


def _write_preview(ortho_path: Path, target: Path, max_side_px: int = 2048) -> Path:
    """A PNG of the whole mosaic, read from the COG's overviews."""
    import rasterio
    from rasterio.enums import Resampling

    with rasterio.open(ortho_path) as src:
        scale = max(1.0, max(src.width, src.height) / max_side_px)
        h, w = max(1, int(src.height / scale)), max(1, int(src.width / scale))
        rgb = src.read((1, 2, 3), out_shape=(3, h, w), resampling=Resampling.average)
        alpha = src.dataset_mask(out_shape=(h, w))
    bgra = np.dstack([rgb[2], rgb[1], rgb[0], alpha])
    with atomic_path(target) as tmp:
        ok, buf = cv2.imencode(".png", bgra)
        if not ok:
            raise OSError("PNG encoding failed")
        Path(tmp).write_bytes(buf.tobytes())
    return target


# ---------------------------------------------------------------------------------------------
# the algorithm


def ortho(
    images: Path,
    output: Path,
    sfm: Path | None = None,
    dsm: Path | None = None,
    resolution_m: float | None = None,
    crs: CRS | None = None,
    ground_elevation_m: float | None = None,
    takeoff_elevation_m: float | None = None,
    seams: SeamMethod = MosaicOptions.seams,
    balance: Balance = MosaicOptions.balance,
    blend: Blend = MosaicOptions.blend,
    max_hole_px: int = MosaicOptions.max_hole_px,
    compress: Compression = MosaicOptions.compress,
    preview: Path | None = None,
    interpolation: Interpolation = MosaicOptions.interpolation,
    tile_px: int = MosaicOptions.tile_px,
    workers: int = MosaicOptions.workers,
    flight_height_m: float | None = None,
    gps_altitude: GpsAltitude = "auto",
    dsm_offset: DsmOffset = "correct",
    max_dsm_offset_m: float = 1.0,
    *,
    feedback: Feedback | None = None,
) -> OrthoResult:
    """Orthophoto mosaic: photos orthorectified on the DSM, seams, colour balance, blending, hole fill, COG.

    Poses come from an sfm output folder or, without one, from the photo
    metadata (GPS, altitude, gimbal: a direct-georeferencing mosaic for a field
    check). The surface is the DSM when given (occlusions handled: a true
    orthophoto), else flat ground.

    Parameters
    ----------
    images : Path
        Folder of photos.
    output : Path
        Orthophoto GeoTIFF (COG, RGB + alpha; JPEG: RGB + mask). A report
        ``<name>_report.json`` is written beside it.
    sfm : Path
        Output folder of the sfm algorithm (poses and calibrated cameras).
    dsm : Path
        Surface model to rectify on (e.g. from the dem algorithm).
    resolution_m : float
        Ground size of an output pixel, metres; default (or 0): the photos' median GSD.
    crs : CRS
        Output CRS (projected); default the SfM model's or the photos' UTM zone.
    ground_elevation_m : float
        Flat ground elevation when no DSM is given (default: the SfM points'
        median height, or the take-off elevation).
    takeoff_elevation_m : float
        Ground elevation of the take-off point, in the vertical datum of the ground
        model (the DSM, the ground elevation or the GCPs). Default: worked out from the
        photos (absolute − relative altitude, checked against the
        ground model; else the ground under the flight), and said.
    seams : str
        graphcut (seams moved onto low-difference paths) or voronoi (best-seeing photo).
    balance : str
        channels (per-photo RGB gains solved over all overlaps), gain (one gain per photo) or none.
    blend : str
        multiband, feather or none across seams.
    max_hole_px : int
        Holes inside the coverage up to this width (px) are inpainted; wider ones stay transparent.
    compress : str
        DEFLATE (lossless, RGBA) or JPEG (quality 90, RGB + mask).
    preview : Path
        Also write a PNG preview (at most 2048 px a side).
    interpolation : str
        How photos are sampled: bilinear, bicubic, lanczos or nearest.
    tile_px : int
        Side of the processing tiles (memory grows with its square).
    workers : int
        Processes for the tiles (0 = every core).
    flight_height_m : float
        For poses from metadata: flight height above the take-off ground, instead of the
        photos' altitudes (cameras that write only a sea-level GPS altitude).
    gps_altitude : str
        For poses from metadata without RelativeAltitude: what GPSAltitude holds (auto,
        above-takeoff, orthometric, ellipsoidal).
    dsm_offset : str
        With sfm and a DSM: the DSM's vertical offset from the SfM points is measured; beyond
        max_dsm_offset_m it is corrected (the DSM moved onto the points), refused, or ignored.
    max_dsm_offset_m : float
        Largest vertical offset between the DSM and the SfM points taken as agreement.
    """

    fb = as_feedback(feedback)
    images = Path(images)
    notes: list[str] = []
    skipped: list[tuple[str, str]] = []
    if dsm_offset not in DSM_OFFSET:
        raise InputError(f"dsm_offset {dsm_offset!r} is not one of {', '.join(DSM_OFFSET)}")
    pts = None
    if sfm is not None:
        cams, out_crs, pts, skipped = cameras_from_sfm(sfm, images, crs)
        poses = f"sfm ({Path(sfm)})"
        default_ground = float(np.median(pts[:, 2])) if len(pts) else None
    else:
        # one photo without an altitude is skipped, as in footprints, not the end of the mosaic
        photoset = photos_with_altitude(images, None, flight_height_m, fb, fb)
        skipped = list(photoset.skipped)
        out_crs = working_crs(photoset.photos, crs)
        cams, default_ground, poses = None, None, "photo metadata (direct georeferencing)"
    if abs(horizontal_unit_m(out_crs) - 1.0) > 1e-9:
        # poses, heights and resolution_m are metres: a feet grid would be silently mis-scaled
        raise InputError(
            f"the orthophoto is made in a CRS in metres and {crs_to_text(out_crs)} is not: "
            "give crs in metres (and reproject the product if feet are wanted)"
        )
    measured_offset = math.nan
    surface = _given_surface(dsm, ground_elevation_m, default_ground, out_crs, notes, fb)
    if cams is None:
        placed, heights = photo_cameras(
            photoset.photos, out_crs, surface, takeoff_elevation_m, flight_height_m=flight_height_m,
            gps_altitude=gps_altitude,
        )  # fmt: skip
        cams = list(placed)
        surface = heights.surface
        notes.append(f"heights: {heights.method}; vertical datum: {heights.datum}")
        for note in heights.notes:
            notes.append(note)
            fb.warning(note)
    elif isinstance(surface, GridSurface) and pts is not None and len(pts):
        flown_m = float(np.median([c.pose.center[2] for c in cams]) - np.median(pts[:, 2])) if len(cams) else math.nan
        surface, measured_offset = _check_dsm_against_points(
            surface, pts, dsm_offset, max_dsm_offset_m, notes, fb, flown_m
        )
    if len(cams) == 0:
        raise InputError("no registered photo to rectify", path=sfm or images)
    options = MosaicOptions(
        seams=seams, balance=balance, blend=blend, max_hole_px=max_hole_px, compress=compress,
        interpolation=interpolation, tile_px=tile_px, workers=workers,
    )  # fmt: skip
    return mosaic(
        cams, surface, out_crs, output, resolution_m, options, preview=preview, poses=poses, notes=notes,
        skipped=skipped, dsm_source=source_path(dsm) if dsm is not None else None, dsm_offset_m=measured_offset,
        feedback=fb,
    )  # fmt: skip


def _given_surface(
    dsm: Path | None,
    ground_elevation_m: float | None,
    default_ground: float | None,
    crs: CRS,
    notes: list[str],
    fb: Feedback,
) -> Any:
    """The surface to rectify on: the DSM, else flat ground at the given elevation, else at the
    SfM points' median height; None when nothing gives one (the metadata's heights then do)."""
    if dsm is not None:
        return _read_dsm(Path(dsm), crs, fb, notes)
    if ground_elevation_m is not None:
        return FlatSurface(float(ground_elevation_m))
    if default_ground is not None:
        notes.append(f"no DSM: flat ground at the SfM points' median height {default_ground:.2f} m")
        return FlatSurface(default_ground)
    return None


#: A DSM whose heights spread about the SfM points' by more than this share of the flight height
#: (robust sigma), or this many metres at least, is not the same surface: no offset is applied.
MAX_DSM_SPREAD_SHARE = 0.05
MIN_DSM_SPREAD_M = 2.0
#: No two vertical datums differ by more than this (m): the geoid lies within -106..+85 m of the
#: ellipsoid. A larger offset is another unit, a fill value or another place.
MAX_DATUM_OFFSET_M = 150.0


def _check_dsm_against_points(
    surface: GridSurface,
    pts: np.ndarray,
    how: str,
    max_offset_m: float,
    notes: list[str],
    fb: Feedback,
    flown_m: float = math.nan,
) -> tuple[GridSurface, float]:
    """Measure the DSM's vertical offset from the SfM points (median of point − DSM over the points
    inside it; the sparse points lie on the surface, roofs and trees included). Beyond
    ``max_offset_m``: move the DSM onto the points (correct), refuse, or only say it (ignore).

    An offset is a datum's, tens of metres at most: one larger than ``MAX_DATUM_OFFSET_M``, or
    heights that spread about the points more than a DSM of the same surface does (a share of the
    cameras' height over the points, ``flown_m``), say another unit, an undeclared fill or another
    place. Such a DSM is refused
    whatever ``how`` says: moved, it made a 50 m site's orthophoto 6.8 km wide."""
    z = surface.grid
    c, r = surface.colrow(pts[:, 0], pts[:, 1])

    dsm_z = sample_grid(z, c, r).astype(float)
    ok = np.isfinite(dsm_z)
    if ok.sum() < 20:
        notes.append(f"DSM vs SfM points: only {int(ok.sum())} points over the DSM, offset not measured")
        fb.warning(notes[-1])
        return surface, math.nan
    factor, why = _feet_against_points(pts[ok, 2], dsm_z[ok], surface.height_unit)
    if why:
        notes.append(why)
        fb.warning(why)
        surface = replace(surface, grid=surface.grid * np.float32(factor), height_unit="metre")
        dsm_z = dsm_z * factor
    d = pts[ok, 2] - dsm_z[ok]
    offset = float(np.median(d))
    spread = float(1.4826 * np.median(np.abs(d - offset)))
    text = (
        f"DSM vs SfM points: the DSM is {-offset:+.2f} m off the points (median of {int(ok.sum())}, "
        f"spread {spread:.2f} m)"
    )
    if abs(offset) <= max_offset_m:
        notes.append(text)
        fb.info(text)
        return surface, -offset
    limit_m = max(MIN_DSM_SPREAD_M, MAX_DSM_SPREAD_SHARE * flown_m) if math.isfinite(flown_m) else MIN_DSM_SPREAD_M
    if abs(offset) > MAX_DATUM_OFFSET_M or spread > limit_m:
        why = (
            f"more than any two vertical datums differ ({MAX_DATUM_OFFSET_M:.0f} m)"
            if abs(offset) > MAX_DATUM_OFFSET_M
            else f"its heights spread about them beyond {limit_m:.1f} m"
        )
        raise InputError(
            f"{text}: {why}: not the surface the photos saw (another unit, an undeclared fill value or another "
            "place?); give the DSM of this site in metres, or none"
        )
    if how == "refuse":
        raise InputError(f"{text}: another vertical datum? give a DSM in the SfM's datum, or dsm_offset correct")
    if how == "ignore":
        notes.append(text + ": not corrected (dsm_offset ignore)")
        fb.warning(notes[-1])
        return surface, -offset
    notes.append(text + f": corrected (DSM moved {offset:+.2f} m onto the points)")
    fb.warning(notes[-1])
    return replace(surface, grid=surface.grid + np.float32(offset)), -offset


FOOT_M = 0.3048


def _feet_against_points(points_z: np.ndarray, dsm_z: np.ndarray, unit: str) -> tuple[float, str]:
    """A DSM whose heights are in another unit than read (feet under a CRS in metres; metres under a
    CRS in feet): against the SfM points (metres) its heights scale 0.3048 or 3.28, which no datum
    shift does. With relief, the robust slope of the points on the DSM says it; on flat ground, the
    points' median height being the DSM's so converted. The factor to apply (1: none) and why."""
    if len(points_z) < 20:
        return 1.0, ""
    from scipy.stats import siegelslopes

    rng = np.random.default_rng(0)
    pick = rng.choice(len(points_z), min(len(points_z), 1500), replace=False)
    pz, dz = points_z[pick], dsm_z[pick]
    factor = FOOT_M if unit == "metre" else 1.0 / FOOT_M
    what = "feet, not metres" if unit == "metre" else f"metres, not {unit} as its CRS says"
    relief = float(np.subtract(*np.percentile(dz, [90, 10])))
    mid_p, mid_d = float(np.median(pz)), float(np.median(dz))
    if relief > 3.0:
        slope = float(siegelslopes(pz, dz)[0])
        if abs(slope / factor - 1.0) < 0.1:
            return factor, (
                f"the DSM's heights scale {slope:.3f} against the SfM points: they are {what} "
                "(converted; give a DSM in metres, or with its vertical unit in its CRS)"
            )
        return 1.0, ""
    if abs(mid_p - mid_d) > 5.0 and abs(mid_p - factor * mid_d) < 1.0:
        return factor, (
            f"the DSM lies at {mid_d:.1f} where the SfM points are at {mid_p:.1f} m: its heights are {what} "
            "(converted; give a DSM in metres)"
        )
    return 1.0, ""


def _read_dsm(path: Path, crs: CRS, fb: Feedback, notes: list[str]) -> GridSurface:
    """The DSM in the output CRS, its small nodata holes filled (reported)."""

    surf = read_surface(path, crs, extend=True)
    if surf.undeclared_fill is not None:
        notes.append(
            f"DSM: {surf.undeclared_fill[1]:,} cells hold {surf.undeclared_fill[0]:g}, a fill value its nodata does "
            "not declare: read as no data"
        )
        fb.warning(notes[-1])
    if surf.height_unit != "metre":
        notes.append(f"DSM: its CRS gives its heights in {surf.height_unit}: converted to metres")
        fb.info(notes[-1])
    whole = whole_surface(surf)
    if whole.n_interpolated:
        notes.append(f"DSM: {whole.n_interpolated} nodata cells inside the data filled by interpolation")
        fb.warning(notes[-1])
    # Wider holes take the ground plane the DSM is continued by beyond its edge: a hole is ground the
    # photos saw (water, canopy the matcher missed), never a reason to leave the mosaic empty there.
    rest = whole.on_ground
    if rest.any():
        # holes inside the DSM's data apart from the grid's margin beyond it: the dem stage said how
        # much of the ground the photos saw has a value, and a margin is no hole in that
        holes = _enclosed(rest)
        wide = max(4.0, 10.0 / surf.cell_m) * surf.cell_m
        said = []
        if holes.any():
            said.append(f"{float(holes.sum()) * surf.cell_m**2:,.0f} m² of holes wider than {wide:.0f} m in it")
        if (rest & ~holes).any():
            said.append(f"{float((rest & ~holes).sum()) * surf.cell_m**2:,.0f} m² of its grid beyond its data")
        notes.append(f"DSM: {' and '.join(said)} rendered on the ground plane near them")
        (fb.warning if holes.any() else fb.info)(notes[-1])
    return whole.surface
