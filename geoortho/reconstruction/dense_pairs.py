"""Which photos a dense surface pairs: each registered photo's view, its best neighbours from the SfM
model (shared points, a baseline that gives depth, similar directions), and extra pairs for ground
no pair measured.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from geoortho.core.gsd import depth_gsd_m

MIN_SHARED_POINTS = 30
_MIN_BASE_RATIO = 0.08  # baseline / height: below, depth is noise
_MAX_VIEW_ANGLE_DEG = 20.0
#: Candidate partners tried per photo, as a multiple of the pairs wanted: a pair that cannot be
#: rectified or matched (a sliver of overlap, a heading turned 90 degrees) is replaced by the next.
_CANDIDATES_PER_PAIR = 2
#: Planning the pairs, each reference's ground is sampled every this many pixels (working size).
COVER_STEP_PX = 16
#: A reference's best pairs are the photos beside it in its strip and the next: they see its middle
#: twice but its outer corners once, so at a strip's end and along the survey's edge ground seen by
#: two or three photos got no depth map at all. A reference takes one more candidate (at most
#: ``_MAX_EXTRA_PAIRS``) when that pair lets it measure at least this share of its samples of such
#: ground. Breaklines survey: ground seen by two photos with no depth map planned on it 11.4 % ->
#: 1.8 %, for 9 pairs more than 105; that edge held two thirds of the DTM's squared error.
_MIN_EXTRA_GAIN = 0.02
_MAX_EXTRA_PAIRS = 2


@dataclass(frozen=True)
class View:
    """One photo as the matcher sees it: scaled intrinsics, pose in the local frame."""

    name: str
    path: Path
    K: np.ndarray  # 3x3 at the working scale, pixel-centre convention
    dist: np.ndarray  # OpenCV distortion coefficients (normalised coordinates: scale-free)
    size: tuple[int, int]  # (width, height) at the working scale
    R: np.ndarray  # world-from-camera
    C: np.ndarray  # centre, local frame (CRS minus origin)


@dataclass(frozen=True)
class DepthJob:
    """A reference photo, its neighbours, the depth range the sparse points give each pair, and
    what the filter needs: everything a worker needs travels with the job (an executor such as
    Dask's runs no initializer)."""

    ref: View
    neighbours: tuple[View, ...]  # candidates, best first: more than wanted, so a failed pair is replaced
    depth_ranges: tuple[tuple[float, float], ...]
    #: each pair's lowest shared tie point, elevation in the local frame (-inf: no "up" known)
    floors_z: tuple[float, ...]
    min_views: int
    depth_tolerance: float
    voxel_m: float
    wanted: int = 3  # pairs to match (the first that give points)
    nearby: tuple[View, ...] = ()  # every other photo that may see its ground (the nearest)


@dataclass(frozen=True)
class Cover:
    """The pairs added where ground seen by two photos had no depth map planned."""

    extra: dict[str, list[str]]  # reference -> the candidates it now matches besides its best
    share_before: float  # of the ground seen by two photos, the share a depth map was planned on
    share_after: float

    def as_report(self) -> dict[str, float]:
        return {"seen_twice_before": round(self.share_before, 4), "seen_twice_after": round(self.share_after, 4)}


def pairs_for_unmeasured_ground(jobs: list[DepthJob], cell_m: float) -> tuple[list[DepthJob], Cover]:
    """Each job's candidates reordered so that its ``wanted`` first ones take in, greedily, the
    ground seen by two photos that no other depth map would measure (see ``_MIN_EXTRA_GAIN``).
    Ground is a grid of ``cell_m`` on the plane each reference sees at its pairs' median depth;
    a sample counts as measured where as many planned pairs see it as the agreement test needs."""
    step = COVER_STEP_PX
    samples = []
    for job in jobs:
        depth = float(np.median([0.5 * (lo + hi) for lo, hi in job.depth_ranges]))
        cols, rows = _sample_grid(job.ref, step)
        world = _ground_at(job.ref, cols.ravel(), rows.ravel(), depth)
        others = np.sum([_in_view(v, world) for v in job.nearby or job.neighbours], axis=0)
        sees = np.array([_in_view(v, world) for v in job.neighbours])
        cell = np.floor(world[:, :2] / cell_m).astype(np.int64)
        samples.append((others, np.clip(others, 1, job.min_views), sees, cell))
    lo = np.min([c.min(axis=0) for *_, c in samples], axis=0)
    hi = np.max([c.max(axis=0) for *_, c in samples], axis=0)
    at = [(cell - lo).T for *_, cell in samples]  # each sample's place in the ground grid
    measured = np.zeros(tuple(hi - lo + 1), bool)
    seen_twice = np.zeros_like(measured)
    order = [list(range(len(j.neighbours))) for j in jobs]
    wanted = [j.wanted for j in jobs]
    for (others, need, sees, _), (ix, iy), o, n in zip(samples, at, order, wanted):
        seen_twice[ix[others >= 1], iy[others >= 1]] = True
        ok = sees[o[:n]].sum(axis=0) >= need
        measured[ix[ok], iy[ok]] = True
    before = float(measured[seen_twice].mean()) if seen_twice.any() else 1.0
    extra: dict[str, list[str]] = {}
    for _ in range(_MAX_EXTRA_PAIRS):
        for i, ((others, need, sees, _), (ix, iy), job) in enumerate(zip(samples, at, jobs)):
            o, n = order[i], wanted[i]
            if n >= len(o):
                continue
            have = sees[o[:n]].sum(axis=0)
            open_ = (others >= 1) & (have < need) & ~measured[ix, iy]
            gains = [int((open_ & (have + sees[k] >= need)).sum()) for k in o[n:]]
            best = int(np.argmax(gains))
            if gains[best] < _MIN_EXTRA_GAIN * len(others):
                continue
            o.insert(n, o.pop(n + best))
            wanted[i] = n + 1
            extra.setdefault(job.ref.name, []).append(job.neighbours[o[n]].name)
            ok = have + sees[o[n]] >= need
            measured[ix[ok], iy[ok]] = True
    after = float(measured[seen_twice].mean()) if seen_twice.any() else 1.0
    out = [
        replace(
            job,
            neighbours=tuple(job.neighbours[k] for k in o),
            depth_ranges=tuple(job.depth_ranges[k] for k in o),
            floors_z=tuple(job.floors_z[k] for k in o),
            wanted=n,
        )
        for job, o, n in zip(jobs, order, wanted)
    ]
    return out, Cover(extra, before, after)


def view_of(cam: Any, scale: float, origin: np.ndarray) -> View:
    intr = cam.intrinsics
    size = (int(round(intr.width_px * scale)), int(round(intr.height_px * scale)))
    # The photo is resized to whole pixels, so each axis has its own scale: one scale for both
    # (640 x 427 from 960 x 640) put the rows' principal point 0.17 px off, and pairs read as
    # parallax what was that offset (true poses, tiny survey: pair biases -0.2..+0.9 GSD, median
    # +0.34; per axis -0.2..+0.2, median -0.02).
    sx, sy = size[0] / intr.width_px, size[1] / intr.height_px
    K = intr.matrix.copy()
    K[0, 0] *= sx
    K[1, 1] *= sy
    K[0, 2] = (K[0, 2] + 0.5) * sx - 0.5
    K[1, 2] = (K[1, 2] + 0.5) * sy - 0.5
    return View(
        cam.name, cam.path, K, intr.dist_coeffs.reshape(-1, 1), size, cam.pose.rotation, cam.pose.center - origin
    )


_Pairs = list[tuple[int, tuple[int, ...], tuple[tuple[float, float], ...], tuple[float, ...]]]


def plan_pairs(cams: list[Any], pts: np.ndarray, neighbours: int, up: bool = True) -> tuple[_Pairs, float]:
    """Each photo's best neighbours with the pairs' depth ranges and lowest shared tie point
    (elevation, model frame; -inf where the model has no known ``up``), and the survey's median
    GSD (model units, metres when georeferenced) at full resolution.

    Each photo keeps only the tie points it sees (their indices and depths), and the points two
    photos share are counted for every pair at once (a sparse product), so that only the pairs that
    share enough are looked at: a mask of every point for every photo and a test of every pair
    took 13 GB and minutes on 748 photos (720,000 tie points), growing with the photos cubed."""
    from scipy import sparse

    seen_idx, seen_depth = [], []
    for c in cams:
        px, d = c.project(pts)
        w, h = c.intrinsics.width_px, c.intrinsics.height_px
        idx = np.flatnonzero((d > 0) & (px[:, 0] >= 0) & (px[:, 0] < w) & (px[:, 1] >= 0) & (px[:, 1] < h))
        seen_idx.append(idx)
        seen_depth.append(d[idx])
    counts = np.array([len(i) for i in seen_idx], np.int64)
    members = np.concatenate(seen_idx) if cams else np.zeros(0, np.int64)
    visible = sparse.csr_matrix(
        (np.ones(len(members), np.int32), members, np.r_[0, np.cumsum(counts)]), shape=(len(cams), len(pts))
    )
    shared_counts = (visible @ visible.T).tocsr()
    centres = np.array([c.pose.center for c in cams])
    axes = np.array([c.pose.rotation[:, 2] for c in cams])
    jobs: _Pairs = []
    gsds = []
    for i, c in enumerate(cams):
        if counts[i] < MIN_SHARED_POINTS:
            continue
        height = float(np.median(seen_depth[i]))
        gsds.append(depth_gsd_m(height, c.intrinsics.focal_px))
        row = slice(shared_counts.indptr[i], shared_counts.indptr[i + 1])
        others, n_others = shared_counts.indices[row], shared_counts.data[row]
        scored = []
        for j, n_shared in sorted(zip(others.tolist(), n_others.tolist())):
            if j == i or n_shared < MIN_SHARED_POINTS:
                continue
            ratio = float(np.linalg.norm(centres[i] - centres[j])) / height
            angle = math.degrees(math.acos(float(np.clip(axes[i] @ axes[j], -1.0, 1.0))))
            if ratio < _MIN_BASE_RATIO or angle > _MAX_VIEW_ANGLE_DEG:
                continue
            shared, in_i, _ = np.intersect1d(seen_idx[i], seen_idx[j], assume_unique=True, return_indices=True)
            lo, hi = np.percentile(seen_depth[i][in_i], [1, 99])
            floor = float(np.percentile(pts[shared, 2], 1)) if up else -math.inf
            scored.append((n_shared * min(1.0, ratio / 0.25), j, (float(lo), float(hi)), floor))
        scored.sort(reverse=True)
        best = scored[: neighbours * _CANDIDATES_PER_PAIR]
        if best:
            jobs.append((i, tuple(b[1] for b in best), tuple(b[2] for b in best), tuple(b[3] for b in best)))
    return jobs, float(np.median(gsds))


#: Photos, nearest first, counted for whether another photo sees a reference's ground.
_NEARBY_VIEWS = 40


def nearest_views(views: Sequence[View], centres: np.ndarray, i: int) -> tuple[View, ...]:
    d = np.linalg.norm(centres - centres[i], axis=1)
    order = [int(j) for j in np.argsort(d, kind="stable") if j != i]
    return tuple(views[j] for j in order[:_NEARBY_VIEWS])


def partners_seeing(ref: View, partners: Sequence[View], depth: np.ndarray, step_px: int = 8) -> np.ndarray:
    """How many of ``partners`` see each pixel of ``ref`` (flat, row-major) at ``depth`` (flat;
    NaN: the median depth measured), on a grid of ``step_px`` carried to every pixel."""
    w, h = ref.size
    cols, rows = _sample_grid(ref, step_px)
    d = depth.reshape(h, w)[rows, cols]
    d = np.where(np.isfinite(d), d, np.nanmedian(depth) if np.isfinite(depth).any() else 1.0)
    world = _ground_at(ref, cols.ravel(), rows.ravel(), d.ravel())
    count = np.zeros(len(world), np.int64)
    for p in partners:
        count += _in_view(p, world)
    n_rows, n_cols = len(rows), len(cols[0])
    coarse = count.reshape(n_rows, n_cols)
    # each pixel takes its grid cell's count (the last row and column reach the photo's edge)
    r = np.minimum(np.arange(h) // step_px, n_rows - 1)
    c = np.minimum(np.arange(w) // step_px, n_cols - 1)
    return coarse[r][:, c].ravel()


def _sample_grid(ref: View, step_px: int) -> tuple[np.ndarray, np.ndarray]:
    """Columns and rows (2-D) of ``ref``'s pixels every ``step_px``, each its step's centre."""
    w, h = ref.size
    cols, rows = np.meshgrid(np.arange(step_px // 2, w, step_px), np.arange(step_px // 2, h, step_px))
    return cols, rows


def _ground_at(ref: View, cols: np.ndarray, rows: np.ndarray, depth: np.ndarray | float) -> np.ndarray:
    """The points (local frame) that ``ref``'s pixels (working size) see at ``depth`` along its axis."""
    pts = np.c_[cols, rows].astype(np.float64).reshape(-1, 1, 2)
    norm = cv2.undistortPoints(pts, ref.K, ref.dist).reshape(-1, 2)
    cam = np.c_[norm, np.ones(len(norm))] * np.reshape(depth, (-1, 1))
    return np.asarray(ref.C + cam @ ref.R.T)


def _in_view(view: View, world: np.ndarray) -> np.ndarray:
    """Which of ``world``'s points (local frame) fall in ``view``'s frame, in front of it."""
    local = (world - view.C) @ view.R
    w, h = view.size
    inside: np.ndarray = local[:, 2] > 0
    # a pinhole test with a wide margin first: OpenCV's projection with distortion is the cost
    # here, and most of the photos near a reference see little or none of its ground
    with np.errstate(divide="ignore", invalid="ignore"):
        xn, yn = local[:, 0] / local[:, 2], local[:, 1] / local[:, 2]
    u = view.K[0, 0] * xn + view.K[0, 2]
    v = view.K[1, 1] * yn + view.K[1, 2]
    inside &= (u > -0.25 * w) & (u < 1.25 * w) & (v > -0.25 * h) & (v < 1.25 * h)
    idx = np.flatnonzero(inside)
    if len(idx):
        pix, _ = cv2.projectPoints(local[idx].reshape(-1, 1, 3), np.zeros(3), np.zeros(3), view.K, view.dist)
        x, y = pix.reshape(-1, 2).T
        inside[idx] = (x >= -0.5) & (x < w - 0.5) & (y >= -0.5) & (y < h - 0.5)
    return inside
