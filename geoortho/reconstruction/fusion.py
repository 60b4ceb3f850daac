"""A reference photo's depth map: the points of its pairs carried into it and kept where enough pairs
agree on the depth; and the cloud of all of them, thinned to one point per voxel.
"""

from __future__ import annotations

import math
import time
import warnings
from collections.abc import Iterator
from dataclasses import dataclass, replace
from pathlib import Path

import cv2
import numpy as np

from geoortho.core.outputs import append_by_tile
from geoortho.reconstruction.dense_pairs import DepthJob, View, partners_seeing
from geoortho.reconstruction.stereo import MIN_PAIR_POINTS, pair_points, read_view, textured_mask

#: A reference photo whose textured share is below this gives "no texture" as its reason.
_MIN_TEXTURED_SHARE = 0.05


@dataclass(frozen=True)
class _DepthResult:
    """One reference photo's consistent points, already thinned to voxel means (with counts)."""

    xyz: np.ndarray  # (N, 3) float32, local frame (metres from the survey's middle: float32 keeps 0.1 mm)
    rgb: np.ndarray  # (N, 3) float32, 0..255
    counts: np.ndarray  # (N,) float32, points averaged in each
    n_matched: int
    n_consistent: int
    single_pair: bool = False  # one pair only gave points: kept as its left-right check left them
    partners: tuple[str, ...] = ()  # the photos it was matched with (the pairs that gave points)
    reason: str = ""  # why no point was kept


def depth_task(job: DepthJob) -> _DepthResult:
    """One reference photo: its pairs' points, kept where ``min_views`` pairs agree on the depth
    (a photo that has one working pair only keeps that pair's left-right checked points)."""
    cv2.setNumThreads(1)  # one photo per process already fills the cores
    ref = job.ref
    img_ref = read_view(ref)
    per_pair: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = []
    zmaps = []
    partners: list[str] = []
    n_raw = 0
    z_relief = math.inf  # the nearest depth a pair's probe found: every later pair searches it too
    for other, rng, floor_z in zip(job.neighbours, job.depth_ranges, job.floors_z):
        if len(per_pair) >= job.wanted:
            break
        img_other = read_view(other)
        rng = (min(rng[0], z_relief), rng[1])
        got = pair_points(ref, other, img_ref, img_other, rng) or pair_points(other, ref, img_other, img_ref, rng)
        if got is None or len(got[0]) < MIN_PAIR_POINTS:
            continue
        xyz, rgb, z_near = got
        z_relief = min(z_relief, z_near)
        n_raw += len(xyz)
        idx, depth, zmap = _into_reference(ref, xyz, rng, z_near, floor_z)
        zmaps.append(zmap)
        per_pair.append((xyz, rgb, idx, depth))
        partners.append(other.name)
    empty = _DepthResult(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.float32), np.zeros(0, np.float32), n_raw, 0)
    if not per_pair:
        textured = float(textured_mask(img_ref).mean())
        if textured < _MIN_TEXTURED_SHARE:
            return replace(empty, reason=f"no texture: {textured:.0%} of the photo has contrast to match")
        return replace(empty, reason=f"matching failed: none of its {len(job.neighbours)} candidate pairs gave depth")
    single = len(per_pair) < job.min_views
    if single:
        # one working pair (the survey's edge, a partner turned away): its points as the pair left them
        xyz, rgb, idx, depth = per_pair[0]
        keep = np.isfinite(depth)
        out_xyz, out_rgb = [xyz[keep]], [rgb[keep][:, ::-1]]
    else:
        out_xyz, out_rgb = _agreeing(job, per_pair, zmaps)
    xyz_all = np.concatenate(out_xyz)
    if not len(xyz_all):
        return replace(empty, reason="matching failed: its pairs did not agree on any depth")
    ones = np.ones(len(xyz_all), np.float32)
    mean_xyz, mean_rgb, counts = _voxel_means(xyz_all, np.concatenate(out_rgb), ones, job.voxel_m)
    return _DepthResult(mean_xyz, mean_rgb, counts, n_raw, len(xyz_all), single, partners=tuple(partners))


def _into_reference(
    ref: View, xyz: np.ndarray, rng: tuple[float, float], z_near: float, floor_z: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A pair's points in the reference photo (rectification undone: its own undistorted scaled
    frame): each point's pixel (flat index), its depth (NaN outside the band the tie points
    allow) and the pair's depth map (nearest point per pixel, NaN where none)."""
    w, h = ref.size
    cam = (xyz.astype(np.float64) - ref.C) @ ref.R
    depth = cam[:, 2]
    pix, _ = cv2.projectPoints(cam.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), ref.K, ref.dist)
    pix = pix.reshape(-1, 2)
    col = np.round(pix[:, 0]).astype(np.int64)
    row = np.round(pix[:, 1]).astype(np.int64)
    # The sparse points bound the reference's depths; a band of 10 % of their spread plus
    # 2 % of the depth around them (toledo: +-4 m at 110 m) keeps relief the sparse points
    # missed and drops shadow and sky-edge mismatches (toledo: up to 20 m under the ground).
    lo, hi = rng
    pad = 0.1 * (hi - lo) + 0.02 * hi
    lo = min(lo, z_near)  # relief a probe found nearer than the tie points
    inside = (depth > lo - pad) & (depth < hi + pad) & (col >= 0) & (col < w) & (row >= 0) & (row < h)
    # Depth is measured along the reference's axis: at a tilted photo's far corner a point
    # 15 m under the ground is still inside the band (toledo: 27 points at 118.5 m against
    # 104.6-115.5 + 3.4 m, a 19 m pit in the DSM and DTM at the survey's edge). Nothing the
    # pair sees lies that far under the lowest tie point it shares.
    inside &= xyz[:, 2] > floor_z - pad
    idx = np.where(inside, row * w + col, 0)
    zbuf = np.full(w * h, np.inf, np.float32)
    np.minimum.at(zbuf, idx[inside], depth[inside].astype(np.float32))
    return idx, np.where(inside, depth, np.nan), np.where(np.isfinite(zbuf), zbuf, np.nan)


def _agreeing(
    job: DepthJob, per_pair: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]], zmaps: list[np.ndarray]
) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Each pair's points (and colours, RGB) where enough pairs agree on the reference's depth."""
    stack = np.vstack(zmaps)
    with np.errstate(invalid="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN pixels (seen by no pair) are expected
        med = np.nanmedian(stack, axis=0)
    tol = job.depth_tolerance * med
    agree = (np.abs(stack - med) <= tol).sum(axis=0)
    # where one other photo alone sees the ground at all (the survey's edge, seen by two
    # photos), no second pair can agree: that pair's left-right checked depth is all there is.
    # (Counted over every photo near, not the pairs used: a ref's border seen by photos it was
    # not paired with is theirs to measure, and single pairs there let mismatches through:
    # small survey, open-ground RMSE 1.9 -> 5.7 GSD counting the pairs, 4.6 the candidates.)
    need = np.clip(partners_seeing(job.ref, job.nearby or job.neighbours, med), 1, job.min_views)
    out_xyz, out_rgb = [], []
    for xyz, rgb, idx, depth in per_pair:
        with np.errstate(invalid="ignore"):
            keep = (agree[idx] >= need[idx]) & (np.abs(depth - med[idx]) <= tol[idx])
        out_xyz.append(xyz[keep])
        out_rgb.append(rgb[keep][:, ::-1])  # BGR -> RGB
    return out_xyz, out_rgb


def _voxel_means(
    xyz: np.ndarray, rgb: np.ndarray, weight: np.ndarray, voxel_m: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Weighted mean position and colour per voxel, and the weight in it (float32 out). A mean of
    points in a voxel stays in that voxel, so means of means (weighted by counts) equal the mean
    of all. Built one column at a time: a merge costs about 40 bytes a point, not 100."""
    flat = np.zeros(len(xyz), np.int64)
    for k in range(3):
        key = np.floor(xyz[:, k] / voxel_m).astype(np.int64)
        key -= key.min()
        flat = flat * (int(key.max()) + 1) + key  # one integer per voxel: a 1-D sort
    del key
    _, inverse = np.unique(flat, return_inverse=True)
    del flat
    inverse = inverse.ravel()
    total = np.bincount(inverse, weight)
    n = len(total)
    out_xyz = np.empty((n, 3), np.float32)
    out_rgb = np.empty((n, 3), np.float32)
    for k in range(3):
        out_xyz[:, k] = np.bincount(inverse, xyz[:, k] * weight, n) / total
        out_rgb[:, k] = np.bincount(inverse, rgb[:, k] * weight, n) / total
    return out_xyz, out_rgb, total.astype(np.float32)


class Fusion:
    """One point per voxel over every depth map, merged as the maps arrive: memory holds the cloud
    so far and the maps not yet merged, not every map's points.

    Past ``max_points`` held, the cloud would still grow with the survey's area; the points are
    then spilled to files on disk, one per square tile of ``TILE_VOXELS`` voxels (a voxel lies
    in one tile, so a tile's voxel means are the whole cloud's there), and each tile is merged
    on its own at the end: memory then follows a tile, not the survey."""

    TILE_VOXELS = 512

    def __init__(
        self, voxel_m: float, merge_every: int = 2_000_000, max_points: int = 4_000_000, spill_dir: Path | None = None
    ) -> None:
        self.voxel_m = voxel_m
        self.merge_every = merge_every
        self.max_points = max_points
        self.spill_dir = spill_dir
        self.parts: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        self.pending = 0
        self.merged = 0
        self.seconds = 0.0
        self.tiles: dict[int, Path] = {}
        self.lo = np.full(3, np.inf)

    @property
    def spilled(self) -> bool:
        return bool(self.tiles)

    def add(self, xyz: np.ndarray, rgb: np.ndarray, counts: np.ndarray) -> None:
        if len(xyz):
            self.lo = np.minimum(self.lo, xyz.min(axis=0))
        if self.spilled:
            self._spill(xyz, rgb, counts)
            return
        self.parts.append((xyz, rgb, counts))
        self.pending += len(xyz)
        # merged when the maps not yet merged are a quarter of the cloud so far: each point is merged
        # O(log n) times, and the last merge holds at most 1.25 x the cloud
        if self.pending >= max(self.merge_every, self.merged // 4):
            self._merge()
            if self.merged > self.max_points and self.spill_dir is not None:
                parts, self.parts, self.merged = self.parts, [], 0
                for part in parts:
                    self._spill(*part)

    def _spill(self, xyz: np.ndarray, rgb: np.ndarray, counts: np.ndarray) -> None:
        assert self.spill_dir is not None
        spill_dir = self.spill_dir
        t0 = time.perf_counter()
        tx, ty = (np.floor(np.floor(xyz[:, k] / self.voxel_m) / self.TILE_VOXELS).astype(np.int64) for k in (0, 1))
        rows = np.empty((len(xyz), 7), np.float32)
        rows[:, :3], rows[:, 3:6], rows[:, 6] = xyz, rgb, counts

        def file_of(key: int) -> Path:
            return self.tiles.setdefault(key, spill_dir / f"dense_{key}.f32")

        # one integer a tile: the local frame is near the survey, so |tx|, |ty| < 2^20
        append_by_tile(rows, tx * (1 << 21) + ty, file_of)
        self.seconds += time.perf_counter() - t0

    def _merge(self) -> None:
        t0 = time.perf_counter()
        if len(self.parts) > 1:
            xyz, rgb, w = (np.concatenate(a) for a in zip(*self.parts))
            self.parts = []  # the parts are copied: let them go before the merge allocates
            self.parts = [_voxel_means(xyz, rgb, w, self.voxel_m)]
            del xyz, rgb, w
        self.merged = len(self.parts[0][0]) if self.parts else 0
        self.pending = 0
        self.seconds += time.perf_counter() - t0

    def chunks(self) -> Iterator[tuple[np.ndarray, np.ndarray]]:
        """The fused cloud a part at a time (the whole, or a spilled tile after another): positions
        (N, 3, local frame) and colours (N, 3, 0..255)."""
        if not self.spilled:
            self._merge()
            if self.parts and len(self.parts[0][0]):
                xyz, rgb, _ = self.parts[0]
                yield xyz, np.clip(rgb, 0.0, 255.0)
            return
        for key in sorted(self.tiles):
            t0 = time.perf_counter()
            path = self.tiles[key]
            rows = np.fromfile(path, np.float32).reshape(-1, 7)
            path.unlink()
            xyz, rgb, _ = _voxel_means(rows[:, :3], rows[:, 3:6], rows[:, 6].astype(np.float64), self.voxel_m)
            del rows
            self.seconds += time.perf_counter() - t0
            yield xyz, np.clip(rgb, 0.0, 255.0)
        self.tiles = {}
