"""The survey-wide decisions, made once on a coarse grid: which photo owns each ground cell
(seamlines) and the colour gain of each photo (exposure balance).

Every photo is rectified at the coarse cell (decoded at a reduced size by the
JPEG decoder itself). Each cell first goes to the photo that sees it best
(:func:`~geoortho.orthophoto.rectify.preference_cost`): a Voronoi-like split. A band
around each of those borders is then handed to OpenCV's graph-cut seam finder
with a colour-difference cost on the balanced photos, which moves the seam inside
the band to where the two photos agree (around a building rather than through it).
Gains are solved jointly over all overlaps by least squares on log colour means
(:func:`solve_gains`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Literal, get_args

import cv2
import numpy as np
from affine import Affine
from rasterio.windows import Window
from scipy import ndimage

from geoortho.core.camera import PosedCamera
from geoortho.core.surface import FlatSurface, Surface
from geoortho.errors import InputError
from geoortho.feedback import Feedback, as_feedback
from geoortho.orthophoto.falloff import Falloff, estimate_falloff, frame_rho
from geoortho.orthophoto.rectify import (
    Projection,
    VisibilityGrid,
    bounds_window,
    intersect,
    keep_best,
    project_window,
    remap_bgr,
    slices_in,
    window_xyz,
)
from geoortho.photos.metadata import decode_photo, read_photo

__all__ = ["SeamPlan", "plan_seams", "read_photo_bgr"]

Balance = Literal["channels", "gain", "none"]
SeamMethod = Literal["graphcut", "voronoi"]
BALANCE: tuple[str, ...] = get_args(Balance)
SEAMS: tuple[str, ...] = get_args(SeamMethod)


@dataclass(frozen=True, eq=False)
class SeamPlan:
    """Coarse ownership labels (index into the cameras, −1 none) and per-photo BGR gains."""

    transform: Affine
    labels: np.ndarray  # int16 (rows, cols)
    gains: np.ndarray  # float32 (n_cameras, 3), BGR
    skipped: tuple[tuple[str, str], ...]
    notes: tuple[str, ...] = ()
    views_held_max: int = 0  # coarse views held at once while streaming (the survey's count if not streamed)
    movers: np.ndarray | None = None  # bool (rows, cols): where a photo showed what the others did not
    falloff: Falloff | None = None  # the lens's falloff, taken out of every photo's pixels

    def labels_for(self, out_transform: Affine, win: Window) -> np.ndarray:
        """The coarse labels read (nearest) at the centres of an output window's pixels."""
        return self._read(self.labels, out_transform, win)

    def movers_for(self, out_transform: Affine, win: Window) -> np.ndarray:
        """Where a photo showed what the others did not (a moved car), at an output window's pixels."""
        if self.movers is None:
            return np.zeros((win.height, win.width), bool)
        return self._read(self.movers, out_transform, win)

    def _read(self, grid: np.ndarray, out_transform: Affine, win: Window) -> np.ndarray:
        res, cres = out_transform.a, self.transform.a
        cols = np.floor(
            ((np.arange(win.col_off, win.col_off + win.width) + 0.5) * res + out_transform.c - self.transform.c) / cres
        ).astype(np.int64)
        rows = np.floor(
            (self.transform.f - (out_transform.f - (np.arange(win.row_off, win.row_off + win.height) + 0.5) * res))
            / cres
        ).astype(np.int64)
        rows = np.clip(rows, 0, grid.shape[0] - 1)
        cols = np.clip(cols, 0, grid.shape[1] - 1)
        return grid[np.ix_(rows, cols)]


def read_photo_bgr(path: str, reduction: int = 1, *, verify: bool = False) -> np.ndarray:
    """Decode a photo (BGR uint8), optionally at 1/2, 1/4 or 1/8 size straight from the JPEG's DCT.

    ``verify``: refuse (OSError) a JPEG whose entropy-coded data is corrupt. libjpeg under
    OpenCV (and Pillow, for a bad Huffman code) only warns "Corrupt JPEG data" and returns a
    grey-smeared image; simplejpeg's strict mode turns the warning into an error."""
    if verify:
        img = decode_photo(path, reduction)
        if img is not None:
            return img
    flag = {
        1: cv2.IMREAD_COLOR,
        2: cv2.IMREAD_REDUCED_COLOR_2,
        4: cv2.IMREAD_REDUCED_COLOR_4,
        8: cv2.IMREAD_REDUCED_COLOR_8,
    }[reduction]
    img = cv2.imread(str(path), flag | cv2.IMREAD_IGNORE_ORIENTATION)
    if img is None:
        raise OSError("the image cannot be decoded")
    return img


def _exposure(path: Any) -> float:
    """ISO · t / N² from the photo's EXIF (NaN when unknown or unreadable)."""

    try:
        return read_photo(path).exposure_value
    except InputError:
        return math.nan


@dataclass(frozen=True, eq=False)
class _View:
    index: int
    win: Window
    image: np.ndarray  # uint8 (rows, cols, 3)
    valid: np.ndarray  # bool
    cost: np.ndarray  # float32, inf where not valid
    rho: np.ndarray | None = None  # float32: squared radius in the frame over the half-diagonal's


@dataclass(frozen=True, eq=False)
class _Band:
    """What the graph cut needs of one photo: its coarse view cropped to the band around what it owns."""

    index: int
    corner: tuple[int, int]  # (col, row) on the coarse grid
    mask: np.ndarray  # uint8 0/255
    image: np.ndarray  # uint8 (rows, cols, 3)
    cost: np.ndarray  # float32
    parallax: np.ndarray | None = None  # float32 (rows, cols, 2): relief x the line of sight's tangent, metres


def _coarse_projection(
    cam: PosedCamera, surface: Surface, vis: VisibilityGrid | None, transform: Affine, win: Window
) -> Projection:
    """A photo's projection over a coarse window: computed once for the Voronoi split (its cost)
    and again when the photo is decoded (its maps), so that no window's arrays outlive their use."""
    x, y, z = window_xyz(transform, win, surface)
    return project_window(cam, x, y, z, vis)


def _coarse_view(
    i: int, cam: PosedCamera, surface: Surface, vis: VisibilityGrid | None, transform: Affine, win: Window, gsd_m: float
) -> _View:
    proj = _coarse_projection(cam, surface, vis, transform, win)
    reduction = 1
    for r in (2, 4, 8):  # decode no finer than the coarse cell needs
        if math.isfinite(gsd_m) and r * gsd_m <= transform.a:
            reduction = r
    img = read_photo_bgr(str(cam.file), reduction, verify=True)
    want = (math.ceil(cam.intrinsics.height_px / reduction), math.ceil(cam.intrinsics.width_px / reduction))
    if abs(img.shape[0] - want[0]) > 1 or abs(img.shape[1] - want[1]) > 1:
        raise OSError(
            f"decoded size {img.shape[1] * reduction}x{img.shape[0] * reduction} px is not the "
            f"camera's {cam.intrinsics.width_px}x{cam.intrinsics.height_px}"
        )
    sampled = remap_bgr(img, proj.map_x, proj.map_y, cv2.INTER_AREA if reduction > 1 else cv2.INTER_LINEAR, reduction)
    sampled[~proj.valid] = 0
    rho = frame_rho(proj.map_x, proj.map_y, cam.intrinsics.width_px, cam.intrinsics.height_px)
    return _View(i, win, sampled, proj.valid, proj.cost, rho)


def plan_seams(
    cams: Sequence[PosedCamera],
    boxes: Sequence[tuple[float, float, float, float] | None],
    gsd_m: Sequence[float],
    surface: Surface,
    vis: Sequence[VisibilityGrid | None],
    out_transform: Affine,
    out_shape: tuple[int, int],
    factor: int,
    *,
    seams: str = "graphcut",
    balance: str = "channels",
    band_m: float = 4.0,
    feedback: Feedback | None = None,
) -> SeamPlan:
    """Coarse labels and gains for the mosaic on ``out_transform`` (cells ``factor`` times coarser).

    Photos stream through: the Voronoi split needs only each photo's projection (no pixels);
    the photos are then decoded in order along the mosaic's longer axis, and a coarse view is
    held only while a later photo's window can still overlap it (its pairwise colour means go
    to the gains, its band around what it owns to the graph cut). Memory follows the photos
    across one sweep line, not the survey. A photo that fails to decode is left out and the
    plan made again without it."""
    fb = as_feedback(feedback)
    cres = out_transform.a * factor
    ctr = Affine(cres, 0, out_transform.c, 0, -cres, out_transform.f)
    cshape = (math.ceil(out_shape[0] / factor), math.ceil(out_shape[1] / factor))
    failed: dict[int, str] = {}
    while True:
        plan = _plan(cams, boxes, gsd_m, surface, vis, ctr, cshape, failed, seams, balance, band_m, fb)
        if isinstance(plan, SeamPlan):
            return plan
        for i, why in plan.items():
            fb.warning(f"skipped {cams[i].name}: {why}")
        failed.update(plan)


def _plan(
    cams: Sequence[PosedCamera],
    boxes: Sequence[tuple[float, float, float, float] | None],
    gsd_m: Sequence[float],
    surface: Surface,
    vis: Sequence[VisibilityGrid | None],
    ctr: Affine,
    cshape: tuple[int, int],
    failed: dict[int, str],
    seams: str,
    balance: str,
    band_m: float,
    fb: Feedback,
) -> SeamPlan | dict[int, str]:
    """One streamed plan, or the photos that newly failed to decode (the caller plans again without them)."""
    full = Window(0, 0, cshape[1], cshape[0])
    labels, wins, skipped = _first_split(cams, boxes, surface, vis, ctr, cshape, failed, fb)
    band_px = max(1, int(round(band_m / ctr.a)))
    relief = _relief(surface, ctr, full) if seams == "graphcut" else None
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * band_px + 1, 2 * band_px + 1))
    along_rows = cshape[0] >= cshape[1]  # sweep along the longer axis: fewer photos cross a sweep line

    def span(w: Window) -> tuple[int, int]:
        return (w.row_off, w.row_off + w.height) if along_rows else (w.col_off, w.col_off + w.width)

    pairs: list[tuple[int, int, float, np.ndarray]] = []
    blocks: dict[tuple[int, int], np.ndarray | None] = {}
    bands: list[_Band] = []
    active: list[_View] = []
    new_failures: dict[int, str] = {}
    held_max = 0
    votes = _Votes(ctr.a, cshape) if seams == "graphcut" and ctr.a <= TRANSIENT_MAX_CELL_M else None
    for k, i in enumerate(sorted(wins, key=lambda j: (span(wins[j])[0], j))):
        fb.check_canceled()
        start = span(wins[i])[0]
        if votes is not None:
            for v in active:
                if span(v.win)[1] <= start:
                    votes.retire(v)
        active = [v for v in active if span(v.win)[1] > start]  # no later photo can overlap these
        try:
            view = _coarse_view(i, cams[i], surface, vis[i], ctr, wins[i], gsd_m[i])
        except OSError as e:
            new_failures[i] = str(e)
            continue
        if balance != "none":
            for other in active:
                first, second = (other, view) if other.index < view.index else (view, other)
                seen = _overlap(first, second)  # one overlap for the gains and the falloff
                stat = _pair_stat(first, second, seen=seen) if seen is not None else None
                if stat is not None:
                    pairs.append(stat)
                    blocks[(first.index, second.index)] = _falloff_blocks(first, second, seen)
        if votes is not None:
            votes.add(view, active)
        if seams == "graphcut":
            band = _band(view, labels, full, kernel, _parallax(cams[i], ctr, view.win, relief))
            if band is not None:
                bands.append(band)
        active.append(view)
        held_max = max(held_max, len(active))
        fb.progress(0.2 + 0.4 * (k + 1) / len(wins))
    if new_failures:
        return new_failures

    falloff = estimate_falloff([b for b in blocks.values() if b is not None]) if balance != "none" else None
    if falloff is not None:
        # the graph cut's bands keep the falloff: taken out of them too, the seams were no better
        # (seed 4: visible seam pixels 1230 -> 1206, mismatch 1.99 -> 2.01 DN) and one crossed a car
        pairs = _without_falloff(pairs, blocks, falloff)
    gains, notes = _gains(pairs, cams, balance, fb)
    if falloff is not None:
        notes = (falloff.note(), *notes)
        fb.info(falloff.note())
    fb.progress(0.75)

    if seams == "graphcut" and len(wins) > 1:
        # in photo order, as OpenCV cuts pairs one after another: the same seams whatever the sweep
        labels = _graph_cut(sorted(bands, key=lambda b: b.index), labels, cshape, gains)
    if votes is not None:
        for v in active:
            votes.retire(v)
        votes.decide()
        moved = _without_transients(labels, votes)
        share = float((moved != labels).sum()) / max(1, int((labels >= 0).sum()))
        if share <= TRANSIENT_MAX_SHARE:
            labels = moved
        else:  # the photos disagree as a whole (placed by their GPS, not by an SfM): no mover is told
            votes.transient.clear()
            notes = (
                *notes,
                f"movers not looked for: {share:.0%} of the mosaic differs photo to photo (misregistered?)",
            )
    fb.progress(1.0)
    movers = None
    if votes is not None and votes.transient:
        movers = np.zeros(cshape, bool)
        for win, odd in votes.transient.values():
            movers[slices_in(win, full)] |= odd
    return SeamPlan(ctr, labels, gains, tuple(skipped), notes, held_max, movers, falloff)


#: Two photos disagree on a coarse cell where their colours (the pair's mean ratio taken out)
#: differ by more than this (RGB distance, DN)...
TRANSIENT_DN = 40.0
#: ... and a photo that disagrees there with at least this many others, and with half or more of
#: those that see the cell, shows what they do not: a car or a person that has moved on. It gives
#: the cell up to one that agrees (a moved car: once or not at all, never twice or cut in half by a
#: seam). On real crowns one side's view also disagrees so (toledo at full resolution: 3 % of the
#: mosaic moved, mostly in crowns and scrub; seam step 10.06 -> 10.70 DN); keeping off relief lost
#: cars on the synthetic survey (the relief's 20 m opening stands metres up on slopes).
TRANSIENT_MIN_OTHERS = 2
#: ... of at least this many others that see the cell: at the survey's edge, where two or three
#: photos meet at their frames' edges, vignetting and the view's angle decide more than content.
TRANSIENT_MIN_SEEN = 3
#: A photo's patch of such cells larger than this (m²) is no mover (a bus is 30 m²): the photos
#: disagree there as a whole (toledo at 0.3 m: 19,300 m² of the survey in patches up to 3,200 m²,
#: the seams' visible pixels 1285 -> 5138) and the seams stay as the cut left them.
TRANSIENT_MAX_M2 = 50.0
#: More of the mosaic than this to move, and the photos disagree as a whole, not over movers (the
#: tiny survey placed by its GPS: 10 %, and the blend's step 16.5 -> 24.0 DN; movers on the small
#: survey: 3.3 %; toledo at full resolution: 3 %).
TRANSIENT_MAX_SHARE = 0.06
#: The coarse cells must be this fine (m) to tell a mover from the photos' other differences: a car
#: then spans eight cells or more. (Toledo at 0.3 m, cells of 2.4 m: the patches found were single
#: cells of shrubs and frames' edges, a car one cell too; the seams' visible pixels 6148 -> 7110.)
TRANSIENT_MAX_CELL_M = 1.0


class _Votes:
    """Per photo, on its coarse window: how many others see each cell and how many disagree; and
    over the coarse grid, how many pairs disagree on each cell."""

    def __init__(self, cell_m: float, cshape: tuple[int, int]) -> None:
        self.cell_m2 = cell_m * cell_m
        self.full = Window(0, 0, cshape[1], cshape[0])
        self.pairs_against = np.zeros(cshape, np.uint16)
        self.seen: dict[int, np.ndarray] = {}
        self.against: dict[int, np.ndarray] = {}
        self.pending: dict[int, tuple[Window, np.ndarray, np.ndarray]] = {}
        self.transient: dict[int, tuple[Window, np.ndarray]] = {}
        # each photo's preference cost where it may take another's cells (it disagrees there with a
        # minority of the others), inf elsewhere: kept from its view, not projected again
        self.offers: dict[int, tuple[Window, np.ndarray]] = {}

    def add(self, view: _View, others: Sequence[_View]) -> None:
        self.seen[view.index] = np.zeros(view.valid.shape, np.uint16)
        self.against[view.index] = np.zeros(view.valid.shape, np.uint16)
        for other in others:
            inter = intersect(other.win, view.win)
            if inter is None:
                continue
            sa, sb = slices_in(inter, other.win), slices_in(inter, view.win)
            both = other.valid[sa] & view.valid[sb]
            if int(both.sum()) < 4:
                continue
            ia, ib = other.image[sa].astype(np.float32), view.image[sb].astype(np.float32)
            ratio = ib[both].mean(axis=0) / np.maximum(ia[both].mean(axis=0), 1.0)
            off = both & (np.linalg.norm(ia * ratio - ib, axis=2) > TRANSIENT_DN)
            self.pairs_against[slices_in(inter, self.full)] += off
            for idx, sl in ((other.index, sa), (view.index, sb)):
                self.seen[idx][sl] += both
                self.against[idx][sl] += off

    def retire(self, view: _View) -> None:
        seen, against = self.seen.pop(view.index, None), self.against.pop(view.index, None)
        if seen is None or against is None:
            return
        self.offers[view.index] = (view.win, np.where((seen >= 1) & (2 * against < seen), view.cost, np.inf))
        odd = (against >= TRANSIENT_MIN_OTHERS) & (2 * against >= seen) & (seen >= TRANSIENT_MIN_SEEN)
        if odd.any():
            labels, _ = ndimage.label(odd, structure=np.ones((3, 3), bool))
            small = np.bincount(labels.ravel()) * self.cell_m2 <= TRANSIENT_MAX_M2
            small[0] = False
            odd = small[labels]
        if odd.any():
            self.pending[view.index] = (view.win, odd, against)

    def decide(self) -> None:
        """The odd cells of each photo where fewer pairs of the other photos disagree among
        themselves than disagree with it: one photo against a consensus (or two, a car seen at two
        places by two), not a view-dependent look (a field bright towards the sun, shrubs'
        parallax: there the others disagree among themselves as much)."""
        for i, (win, odd, against) in self.pending.items():
            others_against = self.pairs_against[slices_in(win, self.full)].astype(np.int32) - against
            odd = odd & (others_against < against)
            if odd.any():  # a cell's worth round it: the coarse cell a car's edge shares
                grown = cv2.dilate(odd.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
                self.transient[i] = (win, grown)
        self.pending.clear()


def _without_transients(labels: np.ndarray, votes: _Votes) -> np.ndarray:
    """``labels`` with each cell whose owner shows something there that the others do not given
    to the photo that sees it best among those that agree with the rest there (kept where none
    does: where every photo differs, as round a tree's crown, the cut's seams stand)."""
    full = Window(0, 0, labels.shape[1], labels.shape[0])
    out: np.ndarray = labels.copy()
    for i, (win, odd) in sorted(votes.transient.items()):
        sl = slices_in(win, full)
        take = (out[sl] == i) & odd
        if not take.any():
            continue
        rr, cc = np.nonzero(take)
        box = Window(
            win.col_off + int(cc.min()), win.row_off + int(rr.min()), int(cc.max() - cc.min()) + 1,
            int(rr.max() - rr.min()) + 1,
        )  # fmt: skip
        want = np.zeros((box.height, box.width), bool)
        want[rr - int(rr.min()), cc - int(cc.min())] = True
        best = np.full(want.shape, np.inf, np.float32)
        owner = np.full(want.shape, -1, np.int16)
        for j, (wj, offer) in votes.offers.items():
            inter = intersect(wj, box) if j != i else None
            if inter is None:
                continue
            sub = slices_in(inter, box)
            keep_best(best, owner, sub, np.where(want[sub], offer[slices_in(inter, wj)], np.inf).astype(np.float32), j)
        moved = want & (owner >= 0)
        region = out[slices_in(box, full)]
        region[moved] = owner[moved]
    return out


def _first_split(
    cams: Sequence[PosedCamera],
    boxes: Sequence[tuple[float, float, float, float] | None],
    surface: Surface,
    vis: Sequence[VisibilityGrid | None],
    ctr: Affine,
    cshape: tuple[int, int],
    failed: dict[int, str],
    fb: Feedback,
) -> tuple[np.ndarray, dict[int, Window], list[tuple[str, str]]]:
    """Voronoi-like first split: each cell to the photo that sees it best. The labels, each
    photo's window on the coarse grid, and the photos skipped (with why)."""
    full = Window(0, 0, cshape[1], cshape[0])
    skipped: list[tuple[str, str]] = []
    wins: dict[int, Window] = {}
    best = np.full(cshape, np.inf, np.float32)
    labels = np.full(cshape, -1, np.int16)
    for i, (cam, box) in enumerate(zip(cams, boxes)):
        fb.check_canceled()
        if i in failed:
            skipped.append((cam.name, failed[i]))
            continue
        win = bounds_window(ctr, cshape, box) if box is not None else None
        if win is None:
            skipped.append((cam.name, "its footprint lies outside the mosaic"))
            continue
        wins[i] = win
        keep_best(best, labels, slices_in(win, full), _coarse_projection(cam, surface, vis[i], ctr, win).cost, i)
        fb.progress(0.2 * (i + 1) / len(cams))
    return labels, wins, skipped


def _gains(
    pairs: list[tuple[int, int, float, np.ndarray]], cams: Sequence[PosedCamera], balance: str, fb: Feedback
) -> tuple[np.ndarray, tuple[str, ...]]:
    """Each photo's colour gains from the overlapping pairs' statistics (ones when not balanced)."""
    if balance == "none":
        return np.ones((len(cams), 3), np.float32), ()
    pairs.sort(key=lambda p: (p[0], p[1]))  # the solution does not depend on the decoding order
    sol = solve_gains(pairs, len(cams), per_channel=balance == "channels", exposure=[_exposure(c.file) for c in cams])
    notes = sol.notes
    if sol.exposure_seeded:
        notes += (f"gains seeded by the EXIF exposure of {sol.exposure_seeded} photos",)
    for note in notes:
        fb.warning(note)
    return sol.gains, notes


#: Both views' pixels over their windows' intersection, where both see the ground unclipped, and
#: the intersection's slices in each.
_Overlap = tuple[np.ndarray, np.ndarray, np.ndarray, tuple[slice, slice], tuple[slice, slice]]


def _overlap(va: _View, vb: _View) -> _Overlap | None:
    """Both views' pixels over their windows' intersection and where both see the ground
    unclipped (a saturated pixel says nothing about exposure)."""
    inter = intersect(va.win, vb.win)
    if inter is None:
        return None
    sa, sb = slices_in(inter, va.win), slices_in(inter, vb.win)
    ia, ib = va.image[sa], vb.image[sb]
    both = (
        va.valid[sa]
        & vb.valid[sb]
        & (ia.max(axis=2) < 250)
        & (ib.max(axis=2) < 250)
        & (ia.min(axis=2) > 3)
        & (ib.min(axis=2) > 3)
    )
    return ia, ib, both, sa, sb


def _pair_stat(
    va: _View, vb: _View, min_overlap_px: int = 50, seen: _Overlap | None = None
) -> tuple[int, int, float, np.ndarray] | None:
    """(a, b, weight, log mean colour of a − of b) over the cells both photos see unclipped
    (``seen``: their :func:`_overlap`, when the caller has it)."""
    seen = seen if seen is not None else _overlap(va, vb)
    if seen is None:
        return None
    ia, ib, both, _, _ = seen
    k = int(both.sum())
    if k < min_overlap_px:
        return None
    ma = ia[both].astype(np.float64).mean(axis=0)
    mb = ib[both].astype(np.float64).mean(axis=0)
    return (va.index, vb.index, math.sqrt(k), np.log(ma) - np.log(mb))


#: An overlap is cut into this many blocks a side for the falloff: each block one point of it.
FALLOFF_BLOCKS = 6
#: A block needs this many cells both photos see.
FALLOFF_MIN_PX = 30


def _falloff_blocks(va: _View, vb: _View, seen: _Overlap | None = None) -> np.ndarray | None:
    """The overlap's blocks for :func:`geoortho.orthophoto.falloff.estimate_falloff`: per block,
    weight, log mean grey of a − of b, and the mean ``rho`` in each photo (``seen``: their
    :func:`_overlap`, when the caller has it)."""
    seen = seen if seen is not None else _overlap(va, vb)
    if seen is None or va.rho is None or vb.rho is None:
        return None
    ia, ib, both, sa, sb = seen
    if int(both.sum()) < FALLOFF_MIN_PX * 3:
        return None
    ga = ia.astype(np.float32).mean(axis=2)
    gb = ib.astype(np.float32).mean(axis=2)
    ra, rb = va.rho[sa], vb.rho[sb]
    rr, cc = np.nonzero(both)
    r_edges = np.linspace(rr.min(), rr.max() + 1, FALLOFF_BLOCKS + 1).astype(int)
    c_edges = np.linspace(cc.min(), cc.max() + 1, FALLOFF_BLOCKS + 1).astype(int)
    out = []
    for r0, r1 in zip(r_edges[:-1], r_edges[1:]):
        for c0, c1 in zip(c_edges[:-1], c_edges[1:]):
            m = both[r0:r1, c0:c1]
            k = int(m.sum())
            if k < FALLOFF_MIN_PX:
                continue
            d = math.log(float(ga[r0:r1, c0:c1][m].mean())) - math.log(float(gb[r0:r1, c0:c1][m].mean()))
            out.append((math.sqrt(k), d, float(ra[r0:r1, c0:c1][m].mean()), float(rb[r0:r1, c0:c1][m].mean())))
    return np.array(out, np.float64) if out else None


#: The ground under objects is the DSM opened by a square this wide (metres, on the coarse grid);
#: what stands RELIEF_MIN_M above it is relief the seams keep off.
RELIEF_WINDOW_M = 20.0
RELIEF_MIN_M = 0.5
#: A metre of parallax between two photos (relief x the difference of their lines of sight's
#: tangents) costs the seam as much as this colour difference (DN).
PARALLAX_DN_PER_M = 40.0


@dataclass(frozen=True, eq=False)
class _Relief:
    """The coarse grid's relief: height above the ground (0 under ``RELIEF_MIN_M``) and the DSM."""

    height: np.ndarray  # float32
    z: np.ndarray  # float64, the DSM's height at each coarse cell's centre


def _relief(surface: Surface, ctr: Affine, full: Window) -> _Relief | None:
    """Height above the ground (the DSM opened) on the coarse grid; None on flat ground."""
    if isinstance(surface, FlatSurface):
        return None
    _, _, z = window_xyz(ctr, full, surface)
    have = np.isfinite(z)
    if not have.any():
        return None
    z32 = np.where(have, z, np.nanmin(z)).astype(np.float32)
    k = max(3, int(round(RELIEF_WINDOW_M / ctr.a)) | 1)
    ground = cv2.morphologyEx(z32, cv2.MORPH_OPEN, cv2.getStructuringElement(cv2.MORPH_RECT, (k, k)))
    height = np.where(have, z32 - ground, 0.0).astype(np.float32)
    height[height < RELIEF_MIN_M] = 0.0
    return _Relief(height, z)


def _parallax(cam: PosedCamera, ctr: Affine, win: Window, relief: _Relief | None) -> np.ndarray | None:
    """Where relief stands, how far this photo displaces it (relief x its line of sight's tangent,
    x and y, metres) over the photo's coarse window: two photos disagree on a roof by the
    difference of theirs, which the graph cut then pays to cross. Worked out on the relief's cells
    only, from the DSM heights the relief was found on (the surface is not sampled again)."""
    if relief is None:
        return None
    sl = slices_in(win, Window(0, 0, relief.height.shape[1], relief.height.shape[0]))
    h = relief.height[sl]
    rows, cols = np.nonzero(h)
    if not len(rows):
        return None
    x, y = ctr * (cols + win.col_off + 0.5, rows + win.row_off + 0.5)
    cx, cy, cz = cam.pose.center
    dz = np.maximum(cz - relief.z[sl][rows, cols], 1e-3)
    out = np.zeros((*h.shape, 2), np.float32)
    out[rows, cols, 0] = h[rows, cols] * (x - cx) / dz
    out[rows, cols, 1] = h[rows, cols] * (y - cy) / dz
    return out


def _band(
    view: _View, labels: np.ndarray, full: Window, kernel: np.ndarray, parallax: np.ndarray | None = None
) -> _Band | None:
    """The view cropped to the band (``kernel`` wide) around the cells it owns after the Voronoi split."""
    own = (labels[slices_in(view.win, full)] == view.index).astype(np.uint8)
    if not own.any():
        return None
    band = cv2.dilate(own, kernel) & view.valid.astype(np.uint8)
    # Cropped to the band: OpenCV cuts every pair whose rectangles overlap, over the whole overlap.
    x, y, w, h = cv2.boundingRect(band)
    return _Band(
        view.index,
        (view.win.col_off + x, view.win.row_off + y),
        np.ascontiguousarray(band[y : y + h, x : x + w] * 255),
        view.image[y : y + h, x : x + w].copy(),
        view.cost[y : y + h, x : x + w].copy(),
        parallax[y : y + h, x : x + w].copy() if parallax is not None else None,
    )


def _without_falloff(
    pairs: list[tuple[int, int, float, np.ndarray]], blocks: dict[tuple[int, int], np.ndarray | None], falloff: Falloff
) -> list[tuple[int, int, float, np.ndarray]]:
    """The overlaps' log colour ratios with the falloff's part taken out (its mean over each
    overlap's blocks, in each photo)."""
    out = []
    for a, b, w, d in pairs:
        bl = blocks.get((a, b))
        if bl is None:
            out.append((a, b, w, d))
            continue
        wt = bl[:, 0] / bl[:, 0].sum()
        ra, rb = bl[:, 2], bl[:, 3]
        part = (wt * (falloff.c1 * (ra - rb) + falloff.c2 * (ra * ra - rb * rb))).sum()
        out.append((a, b, w, d - float(part)))
    return out


@dataclass(frozen=True)
class GainSolution:
    """Per-photo gains and whether they made the overlaps agree better."""

    gains: np.ndarray  # (n, 3) BGR
    mismatch_before: float  # overlap-weighted RMS of log colour differences
    mismatch_after: float
    exposure_seeded: int  # photos whose prior came from their EXIF exposure
    notes: tuple[str, ...] = ()


def solve_gains(
    rows: Sequence[tuple[int, int, float, np.ndarray]],
    n: int,
    *,
    per_channel: bool = True,
    prior_weight: float = 0.2,
    exposure: Sequence[float] | None = None,
    max_gain: float = 2.0,
) -> GainSolution:
    """Per-photo gains (n, 3) BGR that make overlapping photos agree.

    ``rows``: per overlapping pair (a, b, weight, log mean colour of a − of b), from :func:`_pair_stat`.
    Least squares on log colour means over each pairwise overlap, weighted by the overlap's size,
    with every photo pulled towards its prior gain: 1, or the inverse of its EXIF exposure
    (ISO · t / N², relative to the median) where ``exposure`` gives one. The pull holds chains of
    overlaps from drifting along a flight line (vignetting and sun angle bias each link a little);
    the mean log-gain is anchored at the priors'. Gains are kept within 1/max_gain..max_gain, and
    if they do not lower the overlaps' mismatch they are dropped for the priors (and said)."""
    prior = np.zeros(n)
    seeded = 0
    if exposure is not None:
        ev = np.asarray(exposure, float)
        ok = np.isfinite(ev) & (ev > 0)
        if ok.sum() >= 2 and np.ptp(np.log(ev[ok])) > 0.05:
            # How much brighter a photo comes out per unit of log exposure is the camera's tone
            # curve (1 in linear light, about 0.45 through an sRGB curve): fitted on the overlaps.
            le = np.where(ok, np.log(np.where(ok, ev, 1.0)), np.nan)
            pairs = [
                (w, float(np.mean(d)), le[a] - le[b])
                for a, b, w, d in rows
                if np.isfinite(le[a]) and np.isfinite(le[b])
            ]
            den = sum(w * w * e * e for w, _, e in pairs)
            slope = float(np.clip(sum(w * w * d * e for w, d, e in pairs) / den, 0.0, 1.2)) if den > 1e-9 else 0.0
            if slope > 0.05:
                prior[ok] = -slope * (le[ok] - np.median(le[ok]))
                seeded = int(ok.sum())
    gains = np.repeat(np.exp(prior)[:, None], 3, axis=1).astype(np.float32)
    if not rows:
        return GainSolution(gains, math.nan, math.nan, seeded)
    used = sorted({i for a, b, _, _ in rows for i in (a, b)})
    col = {i: k for k, i in enumerate(used)}
    m = len(used)
    A = np.zeros((len(rows) + m, m))
    rhs = np.zeros((len(rows) + m, 3))
    w_total = 0.0
    for r, (a, b, w, d) in enumerate(rows):
        A[r, col[a]], A[r, col[b]] = w, -w
        rhs[r] = -w * d  # log g_a − log g_b = −(log m_a − log m_b)
        w_total += w
    lam = prior_weight * w_total / m
    A[len(rows) :, :] = np.eye(m) * lam
    rhs[len(rows) :, :] = lam * prior[used][:, None]
    if not per_channel:
        rhs[: len(rows)] = rhs[: len(rows)].mean(axis=1, keepdims=True)
    log_g, *_ = np.linalg.lstsq(A, rhs, rcond=None)
    log_g += (prior[used].mean() - log_g.mean(axis=0))[None, :]
    log_g = np.clip(log_g, -math.log(max_gain), math.log(max_gain))

    def mismatch(lg: np.ndarray) -> float:
        res = [w * (d + lg[col[a]] - lg[col[b]]) for a, b, w, d in rows]
        ws = [w for _, _, w, _ in rows]
        return float(math.sqrt(np.sum(np.square(res)) / (3 * np.sum(np.square(ws)))))

    before = mismatch(np.zeros((m, 3)))
    after = mismatch(log_g)
    notes: list[str] = []
    if after >= before:
        notes.append(
            f"colour balance would not lower the overlaps' mismatch ({before:.4f} → {after:.4f} log units): "
            + ("gains from the EXIF exposure only" if seeded else "gains left at 1")
        )
        log_g = np.repeat(prior[used][:, None], 3, axis=1)
        after = mismatch(log_g)
    for i, k in col.items():
        gains[i] = np.exp(log_g[k])
    return GainSolution(gains, before, after, seeded, tuple(notes))


def _graph_cut(bands: list[_Band], labels: np.ndarray, cshape: tuple[int, int], gains: np.ndarray) -> np.ndarray:
    """Move each Voronoi seam, within its band, onto a low-difference path."""
    if len(bands) < 2:
        return labels
    full = Window(0, 0, cshape[1], cshape[0])
    masks = [cv2.UMat(b.mask) for b in bands]  # type: ignore[call-overload]
    # Balanced colours: the cut should follow content, not exposure differences.
    images = [b.image.astype(np.float32) * gains[b.index] for b in bands]
    # Relief: the two photos' displacements of it differ (parallax), added to the colours compared,
    # so the cut goes round a roof or a crown, which would otherwise agree in colour and be crossed
    # (the small survey: 12.9 % of the seams on objects, 5.4 % of the area).
    for img, b in zip(images, bands):
        if b.parallax is not None:
            img[..., :2] += PARALLAX_DN_PER_M * b.parallax
    # The cut's cost is how much the two balanced photos disagree in colour on either side of it:
    # agreement is rewarded, not edges. OpenCV's COST_COLOR_GRAD divides by the gradients, which
    # drew seams along edges, where any misregistration shows (small survey: 2.76 DN across seams,
    # Voronoi 2.42; this cost: 2.30; toledo 12.23 / 12.88 / 10.64).
    finder = cv2.detail.GraphCutSeamFinder("COST_COLOR")
    cut = finder.find(images, [b.corner for b in bands], masks)
    # Owners after the cut; cells claimed by several (or by none) keep the best-seeing photo among them.
    out_best = np.full(cshape, np.inf, np.float32)
    out = np.full(cshape, -1, np.int16)
    for b, m in zip(bands, cut):
        seam_mask = (m.get() if isinstance(m, cv2.UMat) else np.asarray(m)) > 0
        h, w = b.mask.shape
        sl = slices_in(Window(b.corner[0], b.corner[1], w, h), full)
        keep_best(out_best, out, sl, np.where(seam_mask, b.cost, np.inf), b.index)
    unclaimed = (out < 0) & (labels >= 0)
    out[unclaimed] = labels[unclaimed]
    return out
