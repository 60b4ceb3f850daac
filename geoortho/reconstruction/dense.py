"""Dense surface from the photos themselves, on CPU: rectified pairs, OpenCV SGBM, multi-view check.

Each registered photo is a reference: it is paired with its best neighbours from the SfM
model (shared sparse points, a baseline/height ratio that gives depth, similar view
directions), each pair is rectified (``cv2.stereoRectify``) and matched by semi-global block
matching (``cv2.StereoSGBM``, left-right checked), and the pair's points are reprojected into
the reference photo. A point is kept where at least ``min_views`` pairs agree on the depth
within ``depth_tolerance``. The cloud is georeferenced like the SfM model (its CRS and offset)
and thinned to one point per voxel of about a GSD, so ``dem`` takes it as it is.
"""

from __future__ import annotations

import math
import time
import warnings
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from geoortho.core.gsd import depth_gsd_m
from geoortho.core.outputs import append_by_tile, work_folder, write_json
from geoortho.core.parallel import imap_ordered
from geoortho.errors import InputError
from geoortho.feedback import Feedback, as_feedback, split

__all__ = ["DenseResult", "dense"]

_MIN_SHARED_POINTS = 30
_MIN_PAIR_POINTS = 100  # a pair that gives fewer points matched a sliver or nothing
_MIN_BASE_RATIO = 0.08  # baseline / height: below, depth is noise
_MAX_VIEW_ANGLE_DEG = 20.0
# Local contrast (grey-level standard deviation over 7 x 7 px) below which a pixel has no texture to
# match: SGBM's smoothness term would fill such areas (calm water, snow, fresh tarmac) from their
# edges with made-up depths. A flat synthetic pond measures ~1 DN (90th percentile 1.5); real fields
# 2-5 DN at the 5th percentile (toledo_dji: 3 DN would drop 4 % of the DSM cells, 2 DN 1 %).
_MIN_TEXTURE_DN = 2.0
_TEXTURE_WINDOW_PX = 7
#: SGBM's block (px, at the working size). A wider block fattens the nearer surface: a roof or a
#: crown grows by about half a block over the ground beside it, and pairs of one reference fatten
#: alike, so the agreement test keeps it. Issue 74, demo survey (DSM |dZ| p95 within 3 m of
#: objects): block 5 and tolerance 0.01 0.72 m; block 3 0.63; tolerance 0.005 0.61; both 0.53;
#: block 3 and tolerance 0.003 0.47. Real photos (toledo_dji): measured DSM cells 66.8 -> 64.1 %,
#: DTM cells off its 5 m median 0.57 -> 0.44 %, dense 173 -> 109 s.
_BLOCK_PX = 3
#: ``dense`` warns when more than this share of the registered photos gives no depth map.
MAX_SHARE_WITHOUT_MAP = 0.05
#: Candidate partners tried per photo, as a multiple of the pairs wanted: a pair that cannot be
#: rectified or matched (a sliver of overlap, a heading turned 90 degrees) is replaced by the next.
_CANDIDATES_PER_PAIR = 2
#: A reference photo whose textured share is below this gives "no texture" as its reason.
_MIN_TEXTURED_SHARE = 0.05
#: Planning the pairs, each reference's ground is sampled every this many pixels (working size).
_COVER_STEP_PX = 16
#: A reference's best pairs are the photos beside it in its strip and the next: they see its middle
#: twice but its outer corners once, so at a strip's end and along the survey's edge ground seen by
#: two or three photos got no depth map at all. A reference takes one more candidate (at most
#: ``_MAX_EXTRA_PAIRS``) when that pair lets it measure at least this share of its samples of such
#: ground. Breaklines survey: ground seen by two photos with no depth map planned on it 11.4 % ->
#: 1.8 %, for 9 pairs more than 105; that edge held two thirds of the DTM's squared error.
_MIN_EXTRA_GAIN = 0.02
_MAX_EXTRA_PAIRS = 2


@dataclass(frozen=True)
class DenseResult:
    """The dense cloud and what went into it.

    Attributes
    ----------
    output : Path
        Dense point cloud (LAZ, coloured, CRS in the header).
    report : Path
        Report JSON: views, pairs, depth maps, points before and after filtering, seconds per step.
    n_photos : int
        Registered photos in the SfM model.
    n_depth_maps : int
        Photos that gave a filtered depth map.
    n_points : int
        Points written.
    crs : str
        CRS of the cloud.
    notes : tuple of str
        What was assumed or checked, in words.
    """

    output: Path
    report: Path
    n_photos: int
    n_depth_maps: int
    n_points: int
    crs: str
    notes: tuple[str, ...] = field(default_factory=tuple)


@dataclass(frozen=True)
class _View:
    """One photo as the matcher sees it: scaled intrinsics, pose in the local frame."""

    name: str
    path: Path
    K: np.ndarray  # 3x3 at the working scale, pixel-centre convention
    dist: np.ndarray  # OpenCV distortion coefficients (normalised coordinates: scale-free)
    size: tuple[int, int]  # (width, height) at the working scale
    R: np.ndarray  # world-from-camera
    C: np.ndarray  # centre, local frame (CRS minus origin)


@dataclass(frozen=True)
class _Job:
    """A reference photo, its neighbours, the depth range the sparse points give each pair, and
    what the filter needs: everything a worker needs travels with the job (an executor such as
    Dask's runs no initializer)."""

    ref: _View
    neighbours: tuple[_View, ...]  # candidates, best first: more than wanted, so a failed pair is replaced
    depth_ranges: tuple[tuple[float, float], ...]
    #: each pair's lowest shared tie point, elevation in the local frame (-inf: no "up" known)
    floors_z: tuple[float, ...]
    min_views: int
    depth_tolerance: float
    voxel_m: float
    wanted: int = 3  # pairs to match (the first that give points)
    nearby: tuple[_View, ...] = ()  # every other photo that may see its ground (the nearest)


def dense(
    sfm: Path,
    images: Path,
    output: Path,
    max_image_size: int = 1024,
    neighbours: int = 3,
    min_views: int = 2,
    depth_tolerance: float = 0.003,
    workers: int = 0,
    *,
    feedback: Feedback | None = None,
) -> DenseResult:
    """Dense point cloud from the photos and their SfM poses (CPU), ready for the dem algorithm.

    Parameters
    ----------
    sfm : Path
        Output folder of the sfm algorithm (poses, calibrated cameras, sparse points).
    images : Path
        Folder of the photos the SfM model was made from.
    output : Path
        Dense cloud to write (LAZ or LAS); a report ``<name>_report.json`` is written beside it.
    max_image_size : int
        Photos are matched at this larger side (px): the depth maps' resolution.
    neighbours : int
        Neighbour photos each reference photo is matched with.
    min_views : int
        A point is kept where at least this many pairs agree on its depth.
    depth_tolerance : float
        Agreement between pairs, as a fraction of the depth (0.003: about a pixel of disparity at a
        baseline of a fifth of the height, working size 1024 px).
    workers : int
        Processes for the depth maps (0 = every core).
    """
    # here, not at the top: the depth-map workers import this module and need none of these
    # (pycolmap, laspy: 0.3 -> 0.9 s a worker, with the DEM tiles they once took too; pyproj alone 70 ms)
    from geoortho.core.crs import crs_to_text, heights_to_text, with_heights
    from geoortho.core.sfm_model import cameras_from_sfm, model_heights

    fb = as_feedback(feedback)
    clock = time.perf_counter()
    output = Path(output)
    if min_views < 1 or neighbours < min_views:
        raise InputError(f"need neighbours ({neighbours}) >= min_views ({min_views}) >= 1")
    if max_image_size < 256:
        raise InputError(f"max_image_size {max_image_size} px: give 256 or more")
    cams, crs, pts, skipped = cameras_from_sfm(sfm, images, local_frame_ok=True)
    notes = [f"{name}: {why}" for name, why in skipped]
    if crs is None:
        notes.append("the SfM model is in a local frame (no GPS, no GCPs): the cloud has no CRS and model units")
        fb.warning("dense: the SfM model is in a local frame: the cloud has no CRS (georeference the sfm run)")
    if len(cams) < 2:
        raise InputError(f"{len(cams)} registered photo(s) on disk: a dense surface needs 2 or more", path=sfm)
    if len(pts) < _MIN_SHARED_POINTS:
        raise InputError(f"the SfM model has {len(pts)} sparse points: too few to choose pairs", path=sfm)
    work = _planned_work(cams, pts, crs is not None, max_image_size, neighbours, min_views, depth_tolerance)
    if not work.jobs:
        raise InputError("no pair of photos overlaps with enough baseline for depth", path=sfm)
    seconds = {"plan": _lap(clock)}
    s_maps, s_write = split(fb, [9, 1])
    with work_folder(output) as spill:
        fusion = _Fusion(work.voxel_m, spill_dir=Path(spill))
        maps = _depth_maps(work, fusion, workers, s_maps)
        seconds["depth_maps"] = _lap(clock) - seconds["plan"]
        peak_before_write_mb = _peak_memory_mb()["main"]
        t_write = time.perf_counter()
        heights, _ = model_heights(sfm)  # the cloud's header says its heights' datum where the SfM knew it
        cloud_crs = with_heights(crs, heights) if crs is not None else None
        n_written, fallback = _write_cloud(output, fusion, pts, work.origin, cloud_crs, notes, fb)
        seconds["fusion"] = fusion.seconds  # merges, spills and (spilled) the tiles' merges
        seconds["write"] = time.perf_counter() - t_write  # a spilled cloud's tiles merged included
    s_write.progress(1.0)
    seconds["total"] = _lap(clock)
    notes.extend(_missing_maps_notes(maps, len(cams), fb))
    crs_text = crs_to_text(crs) if crs is not None else ""
    report = output.with_name(output.stem + "_report.json")
    write_json(
        report,
        {
            "output": str(output),
            "crs": crs_text or None,
            "vertical_crs": heights_to_text(heights) if crs is not None else None,
            "photos": len(cams),
            **maps.as_report(),
            **work.as_report(),
            "max_image_size": max_image_size,
            "points_written": n_written,
            "fusion_spilled_to_disk": fusion.spilled,
            "seconds": seconds,
            "peak_memory_mb": {**_peak_memory_mb(), "main_before_write": peak_before_write_mb},
            "notes": notes,
            "fallback": fallback or None,  # what the cloud is when no depth map gave a point
        },
    )
    fb.info(
        f"dense: {n_written} points from {maps.n_maps} depth maps ({maps.n_matched} matched, "
        f"{maps.n_consistent} consistent) in {seconds['total']:.0f} s"
    )
    return DenseResult(output, report, len(cams), maps.n_maps, n_written, crs_text, tuple(notes))


@dataclass(frozen=True)
class _Work:
    """The depth maps to make: a job per reference photo, and the photos that have no partner."""

    jobs: list[_Job]
    no_partner: list[str]
    origin: np.ndarray  # the local frame's origin in the model's frame
    scale: float  # the photos' median working scale
    voxel_m: float  # about one depth-map pixel on the ground
    cover: _Cover | None = None

    def as_report(self) -> dict[str, Any]:
        return {
            "candidates": {j.ref.name: [v.name for v in j.neighbours] for j in self.jobs},
            "extra_pairs": self.cover.extra if self.cover else {},
            "planned_cover": self.cover.as_report() if self.cover else None,
            "image_scale": self.scale,
            "depth_map_megapixels": sum(j.ref.size[0] * j.ref.size[1] for j in self.jobs) / 1e6,
            "voxel_m": self.voxel_m,
        }


def _planned_work(
    cams: list[Any], pts: np.ndarray, up: bool, max_image_size: int, neighbours: int, min_views: int, tolerance: float
) -> _Work:
    origin = np.asarray(np.round(np.mean([c.pose.center for c in cams], axis=0), -2), float)
    # each photo at max_image_size (camera bodies may differ in size); the survey's scale for the voxel
    scales = [min(1.0, max_image_size / max(c.intrinsics.width_px, c.intrinsics.height_px)) for c in cams]
    views = [_view(c, s, origin) for c, s in zip(cams, scales)]
    scale = float(np.median(scales))
    pairs, gsd = _plan(cams, pts, neighbours, up=up)
    voxel = gsd / scale if pairs else math.nan
    centres = np.array([v.C for v in views])
    jobs = [
        _Job(
            views[i], tuple(views[j] for j in nbrs), rngs, tuple(f - origin[2] for f in floors), min_views,
            tolerance, voxel, neighbours, _nearest_views(views, centres, i),
        )
        for i, nbrs, rngs, floors in pairs
    ]  # fmt: skip
    planned = {j.ref.name for j in jobs}
    cover = None
    if jobs:
        jobs, cover = _pairs_for_unmeasured_ground(jobs, _COVER_STEP_PX * voxel)
    return _Work(jobs, [v.name for v in views if v.name not in planned], origin, scale, voxel, cover)


@dataclass(frozen=True)
class _Cover:
    """The pairs added where ground seen by two photos had no depth map planned."""

    extra: dict[str, list[str]]  # reference -> the candidates it now matches besides its best
    share_before: float  # of the ground seen by two photos, the share a depth map was planned on
    share_after: float

    def as_report(self) -> dict[str, float]:
        return {"seen_twice_before": round(self.share_before, 4), "seen_twice_after": round(self.share_after, 4)}


def _pairs_for_unmeasured_ground(jobs: list[_Job], cell_m: float) -> tuple[list[_Job], _Cover]:
    """Each job's candidates reordered so that its ``wanted`` first ones take in, greedily, the
    ground seen by two photos that no other depth map would measure (see ``_MIN_EXTRA_GAIN``).
    Ground is a grid of ``cell_m`` on the plane each reference sees at its pairs' median depth;
    a sample counts as measured where as many planned pairs see it as the agreement test needs."""
    step = _COVER_STEP_PX
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
    return out, _Cover(extra, before, after)


@dataclass
class _Maps:
    """What the depth maps gave, as the report counts it."""

    n_matched: int = 0
    n_consistent: int = 0
    n_maps: int = 0
    used: dict[str, list[str]] = field(default_factory=dict)  # each depth map's partners
    single_pair: list[str] = field(default_factory=list)
    no_map: dict[str, str] = field(default_factory=dict)  # photo -> why it gave none

    def as_report(self) -> dict[str, Any]:
        return {
            "depth_maps": self.n_maps,
            "pairs": sum(len(v) for v in self.used.values()),
            "views": self.used,  # each depth map's partners (the pairs that gave points)
            "points_matched": self.n_matched,
            "points_consistent": self.n_consistent,
            "no_depth_map": dict(sorted(self.no_map.items())),
            "single_pair_depth_maps": self.single_pair,
        }


def _depth_maps(work: _Work, fusion: _Fusion, workers: int, fb: Feedback) -> _Maps:
    """Every job's depth map, made by the workers and fused as it arrives."""
    maps = _Maps(
        no_map={n: "no partner: no other photo shares its view with a baseline for depth" for n in work.no_partner}
    )
    for job, got in zip(work.jobs, imap_ordered(_depth_task, work.jobs, workers=workers, feedback=fb)):
        maps.n_matched += got.n_matched
        maps.n_consistent += got.n_consistent
        if got.n_consistent:
            maps.n_maps += 1
            fusion.add(got.xyz, got.rgb, got.counts)
            maps.used[job.ref.name] = list(got.partners)
            if got.single_pair:
                maps.single_pair.append(job.ref.name)
        else:
            maps.no_map[job.ref.name] = got.reason
    return maps


def _write_cloud(
    output: Path, fusion: _Fusion, pts: np.ndarray, origin: np.ndarray, crs: Any, notes: list[str], fb: Feedback
) -> tuple[int, str]:
    """Write the fused cloud (or, where no depth map gave a point, the tie points, said in
    ``notes``); the points written and what the cloud fell back to ("" for none)."""
    from geoortho.core.pointcloud import write_las_parts  # not in the workers (see dense)

    if not np.isfinite(fusion.lo).all():
        # Water, snow, fresh tarmac: no depth map anywhere. The SfM's tie points are the only
        # measurement there is: they are the cloud, and that is said loudly (never an empty product).
        fallback = f"the SfM's {len(pts)} tie points"
        notes.append(
            f"no depth could be measured in any photo (textureless ground: water, snow; or poses that do not "
            f"fit): the cloud is {fallback}, and a surface made from it is mostly interpolated"
        )
        fb.warning(f"dense: {notes[-1]}")
        tie = np.asarray(pts, float) - origin
        write_las_parts(output, [(tie, None, None)], crs, lowest=tie.min(axis=0), offset=origin)
        return len(tie), fallback
    n_written = 0

    def parts() -> Iterator[tuple[np.ndarray, np.ndarray, None]]:
        nonlocal n_written
        for xyz, rgb in fusion.chunks():
            n_written += len(xyz)
            rgb /= 255.0  # in place: no second copy of the cloud's colours
            yield xyz, rgb, None

    write_las_parts(output, parts(), crs, lowest=fusion.lo, offset=origin)
    return n_written, ""


def _missing_maps_notes(maps: _Maps, n_photos: int, fb: Feedback) -> list[str]:
    """The photos that gave no depth map, or one from a single pair: a warning past 5 %."""
    notes = []
    if maps.no_map:
        listed = ", ".join(f"{k} ({v.split(':')[0]})" for k, v in sorted(maps.no_map.items())[:5])
        notes.append(
            f"{len(maps.no_map)} of {n_photos} registered photos gave no depth map: {listed}"
            + ("" if len(maps.no_map) <= 5 else ", ...")
        )
        if len(maps.no_map) / n_photos > MAX_SHARE_WITHOUT_MAP:
            fb.warning(f"dense: {notes[-1]}")
        else:
            fb.info(notes[-1])
    if maps.single_pair:
        notes.append(
            f"{len(maps.single_pair)} depth map(s) from one pair only (no second partner agreed or existed; "
            "left-right checked): " + ", ".join(maps.single_pair[:5]) + (", ..." if len(maps.single_pair) > 5 else "")
        )
    return notes


def _lap(clock: float) -> float:
    return time.perf_counter() - clock


def _peak_memory_mb() -> dict[str, float]:
    """Peak resident memory of this process and of the largest finished worker (MB; Linux units)."""
    import resource

    return {
        "main": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
        "largest_worker": resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024,
    }


def _view(cam: Any, scale: float, origin: np.ndarray) -> _View:
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
    return _View(
        cam.name, cam.path, K, intr.dist_coeffs.reshape(-1, 1), size, cam.pose.rotation, cam.pose.center - origin
    )


_Pairs = list[tuple[int, tuple[int, ...], tuple[tuple[float, float], ...], tuple[float, ...]]]


def _plan(cams: list[Any], pts: np.ndarray, neighbours: int, up: bool = True) -> tuple[_Pairs, float]:
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
        if counts[i] < _MIN_SHARED_POINTS:
            continue
        height = float(np.median(seen_depth[i]))
        gsds.append(depth_gsd_m(height, c.intrinsics.focal_px))
        row = slice(shared_counts.indptr[i], shared_counts.indptr[i + 1])
        others, n_others = shared_counts.indices[row], shared_counts.data[row]
        scored = []
        for j, n_shared in sorted(zip(others.tolist(), n_others.tolist())):
            if j == i or n_shared < _MIN_SHARED_POINTS:
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


def _read(view: _View) -> np.ndarray:
    img = cv2.imread(str(view.path), cv2.IMREAD_COLOR)
    if img is None:
        raise InputError("cannot be decoded", path=view.path)
    if (img.shape[1], img.shape[0]) != view.size:
        img = cv2.resize(img, view.size, interpolation=cv2.INTER_AREA)
    return img


def _sgbm(left: np.ndarray, right: np.ndarray, min_d: int, n_d: int) -> np.ndarray:
    """Disparities (px, float; 0 or less where none) of ``left`` against ``right`` in
    ``[min_d, min_d + n_d)``: the right image shifted by the smallest disparity, so that SGBM
    searches only the range that matters (and an image narrower than minDisparity +
    numDisparities makes OpenCV fail)."""
    shifted = np.zeros_like(right)
    shifted[:, min_d:] = right[:, : right.shape[1] - min_d]
    bs = _BLOCK_PX
    sgbm = cv2.StereoSGBM.create(
        minDisparity=0,
        numDisparities=n_d,
        blockSize=bs,
        P1=8 * 3 * bs * bs,
        P2=32 * 3 * bs * bs,
        disp12MaxDiff=1,
        uniquenessRatio=10,
        speckleWindowSize=100,
        speckleRange=2,
        mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY,
    )
    raw = sgbm.compute(left, shifted)
    return np.where(raw > 0, raw.astype(np.float32) / 16.0 + min_d, 0.0).astype(np.float32)


#: Objects may stand this share of the depth above the ground the tie points bound: a wood
#: whose crowns gave no tie point (fine repetitive leaves) stands 7-12 m under a 30 m flight.
_MAX_RELIEF_SHARE = 0.45
#: Disparities found on this share of a probe's valid pixels nearer than the tie points widen
#: the search: fewer are mismatches.
_MIN_PROBE_SHARE = 0.002


def _probe_near(
    left: np.ndarray, right: np.ndarray, valid: np.ndarray, f: float, baseline: float, zmin: float, zmax: float
) -> float:
    """The nearest depth really in the pair, searched down to ``_MAX_RELIEF_SHARE`` above the
    ground (or as near as the canvas allows) at half resolution: a quarter of the pixels and half
    the disparities, an eighth of a full search per level. ``zmin`` when nothing nearer is found.

    The depth range comes from the SfM's tie points, and a wood or a car park may have none:
    searched only there, its crowns matched the ground below and were dropped as inconsistent
    (the synthetic wood: 5 % of its cells measured, the DSM 9.6 m low over it)."""
    z_probe = max((1.0 - _MAX_RELIEF_SHARE) * zmax, _nearest_searchable(left.shape[1], f, baseline, zmax))
    if z_probe >= zmin * 0.97:
        return zmin
    small_l = cv2.resize(left, None, fx=0.5, fy=0.5, interpolation=cv2.INTER_AREA)
    small_r = cv2.resize(right, None, fx=0.5, fy=0.5, interpolation=cv2.INTER_AREA)
    small_v = cv2.resize(valid, (small_l.shape[1], small_l.shape[0]), interpolation=cv2.INTER_NEAREST) > 0
    fh = 0.5 * f
    min_d, n_d = _disparity_range(fh, baseline, z_probe, zmax)
    if n_d > small_l.shape[1] // 2 or min_d + n_d >= small_l.shape[1]:
        return zmin
    disp = _sgbm(small_l, small_r, min_d, n_d)
    ok = (disp > 0) & small_v
    z = fh * baseline / disp[ok]
    near = z[z < zmin * 0.97]
    if len(near) < max(1.0, _MIN_PROBE_SHARE * ok.sum()):
        return zmin
    return max(z_probe, float(np.percentile(near, 1)) * 0.95)


def _disparity_range(f: float, baseline: float, zmin: float, zmax: float) -> tuple[int, int]:
    """SGBM's smallest disparity and number of disparities (a multiple of 16) for depths
    ``zmin``..``zmax``, with 15 % to spare each way."""
    min_d = max(0, int(math.floor(f * baseline / zmax * 0.85)))
    return min_d, max(16, int(math.ceil((f * baseline / zmin * 1.15 - min_d) / 16.0)) * 16)


def _nearest_searchable(width_px: int, f: float, baseline: float, zmax: float) -> float:
    """The nearest depth a canvas ``width_px`` wide can search: at most half its width of
    disparities beyond the farthest depth's."""
    min_d, _ = _disparity_range(f, baseline, zmax, zmax)
    return f * baseline * 1.15 / (min_d + (width_px // 2) // 16 * 16)


def _pair(
    a: _View, b: _View, img_a: np.ndarray, img_b: np.ndarray, depth_range: tuple[float, float]
) -> tuple[np.ndarray, np.ndarray, float] | None:
    """Points (local frame) and colours (BGR) of one rectified pair, ``a`` as the left image, and
    the nearest depth searched (the tie points', or nearer where a probe found relief);
    None when the pair rectifies the other way round (then ``b`` must be the left image)."""
    rect = _rectify(a, b)
    if rect is None:
        return None
    R1, R2, P1, P2, size = rect
    horizontal = abs(P2[0, 3]) > abs(P2[1, 3])
    shift = P2[0, 3] if horizontal else P2[1, 3]
    if shift > 0:
        return None
    f = float(P1[0, 0])
    baseline = abs(float(shift)) / f
    zmin, zmax = depth_range
    if not 0 < zmin <= zmax:  # points behind or at the camera: a broken pose, not a stereo pair
        return None
    map_a = cv2.initUndistortRectifyMap(a.K, a.dist, R1, P1, size, cv2.CV_32FC1)
    map_b = cv2.initUndistortRectifyMap(b.K, b.dist, R2, P2, size, cv2.CV_32FC1)  # one canvas for both
    left = cv2.remap(img_a, map_a[0], map_a[1], cv2.INTER_LINEAR)
    right = cv2.remap(img_b, map_b[0], map_b[1], cv2.INTER_LINEAR)
    # Texture is measured in the photo (its border reflected), not on the canvas: there the black
    # beyond the photo's edge lends texture to a flat pond cut by the edge. SGBM's blocks that
    # straddle the edge match the black too, so the photo's edge band is dropped as well.
    inside = cv2.remap(np.full(img_a.shape[:2], 255, np.uint8), map_a[0], map_a[1], cv2.INTER_NEAREST)
    inside = cv2.erode(inside, np.ones((_TEXTURE_WINDOW_PX, _TEXTURE_WINDOW_PX), np.uint8))
    textured = cv2.remap(_textured(img_a).astype(np.uint8) * 255, map_a[0], map_a[1], cv2.INTER_NEAREST)
    valid = np.minimum(inside, textured)
    if not horizontal:  # vertical pairs: transposed, SGBM searches along rows
        left, right, valid = cv2.transpose(left), cv2.transpose(right), cv2.transpose(valid)
    # A search range past the canvas (toledo, two bodies: the smallest disparity alone was
    # wider than the image): SGBM cannot search it and the overlap is a sliver at best.
    min_d, n_d = _disparity_range(f, baseline, zmin, zmax)
    if n_d > left.shape[1] // 2 or min_d + n_d >= left.shape[1]:
        return None
    zmin = _probe_near(left, right, valid, f, baseline, zmin, zmax)
    min_d, n_d = _disparity_range(f, baseline, zmin, zmax)
    disp = _sgbm(left, right, min_d, n_d)
    ok = (disp > 0) & (valid > 0)
    if not horizontal:
        disp = np.asarray(cv2.transpose(disp))
        ok = np.asarray(cv2.transpose(ok.astype(np.uint8))) > 0
        left = np.asarray(cv2.transpose(left))
    rr, cc = np.nonzero(ok)
    z = f * baseline / disp[rr, cc]
    keep = (z > zmin * 0.8) & (z < zmax * 1.2)  # loose: a's rectified depth, the range is ref's
    rr, cc, z = rr[keep], cc[keep], z[keep]

    rect = np.c_[(cc - P1[0, 2]) * z / f, (rr - P1[1, 2]) * z / f, z]
    world = (rect @ R1) @ a.R.T + a.C  # rectified -> camera a -> local frame
    return world.astype(np.float32), left[rr, cc], zmin


#: A rectified canvas holds at most this many times the reference photo's pixels (the focal
#: length is lowered to fit): a pair turned 45 degrees needs about twice.
_MAX_CANVAS_RATIO = 2.5


def _rectify(a: _View, b: _View) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, tuple[int, int]] | None:
    """Rectifying rotations and projections of the pair (``a`` left) on a canvas that holds the
    part of ``a`` that ``b`` can match, at ``a``'s own focal length.

    OpenCV's ``stereoRectify`` keeps the photo's size and zooms until the canvas holds only valid
    pixels (alpha 0): for a pair whose headings differ (a camera turning freely from photo to
    photo), that zoom reached 5 to 20 times, and the disparities left the canvas. Its rotations
    are kept; the projections are made here."""
    R = b.R.T @ a.R
    T = (b.R.T @ (a.C - b.C)).reshape(3, 1)
    R1, R2, _, _, _, _, _ = cv2.stereoRectify(
        a.K, a.dist, b.K, b.dist, a.size, R, T, flags=cv2.CALIB_ZERO_DISPARITY, alpha=-1
    )
    t = (R2 @ T).ravel()  # a's centre in the rectified frame of b
    horizontal = abs(t[0]) > abs(t[1])
    f = float(a.K[0, 0])

    def extent(v: _View, rot: np.ndarray) -> np.ndarray:
        w, h = v.size
        n = 16
        edge = np.linspace(0, 1, n)
        xs = np.r_[edge * (w - 1), np.full(n, w - 1.0), edge[::-1] * (w - 1), np.zeros(n)]
        ys = np.r_[np.zeros(n), edge * (h - 1), np.full(n, h - 1.0), edge[::-1] * (h - 1)]
        P = np.array([[f, 0, 0], [0, f, 0], [0, 0, 1]], float)
        out = cv2.undistortPoints(np.c_[xs, ys].reshape(-1, 1, 2).astype(np.float64), v.K, v.dist, R=rot, P=P)
        pts = out.reshape(-1, 2)
        return np.array([pts[:, 0].min(), pts[:, 1].min(), pts[:, 0].max(), pts[:, 1].max()])

    ea, eb = extent(a, R1), extent(b, R2)
    if not (np.isfinite(ea).all() and np.isfinite(eb).all()):
        return None
    # across the baseline both photos must hold the row; along it, a's pixels are the ones matched
    if horizontal:
        x0, x1, y0, y1 = ea[0], ea[2], max(ea[1], eb[1]), min(ea[3], eb[3])
    else:
        x0, x1, y0, y1 = max(ea[0], eb[0]), min(ea[2], eb[2]), ea[1], ea[3]
    if x1 - x0 < 32 or y1 - y0 < 32:
        return None
    scale = min(1.0, math.sqrt(_MAX_CANVAS_RATIO * a.size[0] * a.size[1] / ((x1 - x0) * (y1 - y0))))
    fs = f * scale
    size = (int(math.ceil((x1 - x0) * scale)) + 1, int(math.ceil((y1 - y0) * scale)) + 1)
    P1 = np.array([[fs, 0, -x0 * scale, 0], [0, fs, -y0 * scale, 0], [0, 0, 1, 0]], float)
    P2 = P1.copy()
    P2[0, 3] = fs * t[0] if horizontal else 0.0
    P2[1, 3] = 0.0 if horizontal else fs * t[1]
    return R1, R2, P1, P2, size


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


def _textured(img: np.ndarray) -> np.ndarray:
    """Pixels with enough local contrast to be matched (see ``_MIN_TEXTURE_DN``)."""
    grey = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY).astype(np.float32)
    k = (_TEXTURE_WINDOW_PX, _TEXTURE_WINDOW_PX)
    mean = cv2.blur(grey, k)
    var = cv2.blur(grey * grey, k) - mean * mean
    return np.asarray(var >= _MIN_TEXTURE_DN**2)


def _depth_task(job: _Job) -> _DepthResult:
    """One reference photo: its pairs' points, kept where ``min_views`` pairs agree on the depth
    (a photo that has one working pair only keeps that pair's left-right checked points)."""
    cv2.setNumThreads(1)  # one photo per process already fills the cores
    ref = job.ref
    img_ref = _read(ref)
    per_pair: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = []
    zmaps = []
    partners: list[str] = []
    n_raw = 0
    z_relief = math.inf  # the nearest depth a pair's probe found: every later pair searches it too
    for other, rng, floor_z in zip(job.neighbours, job.depth_ranges, job.floors_z):
        if len(per_pair) >= job.wanted:
            break
        img_other = _read(other)
        rng = (min(rng[0], z_relief), rng[1])
        got = _pair(ref, other, img_ref, img_other, rng) or _pair(other, ref, img_other, img_ref, rng)
        if got is None or len(got[0]) < _MIN_PAIR_POINTS:
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
        textured = float(_textured(img_ref).mean())
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
    ref: _View, xyz: np.ndarray, rng: tuple[float, float], z_near: float, floor_z: float
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
    job: _Job, per_pair: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]], zmaps: list[np.ndarray]
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
    need = np.clip(_partners_seeing(job.ref, job.nearby or job.neighbours, med), 1, job.min_views)
    out_xyz, out_rgb = [], []
    for xyz, rgb, idx, depth in per_pair:
        with np.errstate(invalid="ignore"):
            keep = (agree[idx] >= need[idx]) & (np.abs(depth - med[idx]) <= tol[idx])
        out_xyz.append(xyz[keep])
        out_rgb.append(rgb[keep][:, ::-1])  # BGR -> RGB
    return out_xyz, out_rgb


#: Photos, nearest first, counted for whether another photo sees a reference's ground.
_NEARBY_VIEWS = 40


def _nearest_views(views: Sequence[_View], centres: np.ndarray, i: int) -> tuple[_View, ...]:
    d = np.linalg.norm(centres - centres[i], axis=1)
    order = [int(j) for j in np.argsort(d, kind="stable") if j != i]
    return tuple(views[j] for j in order[:_NEARBY_VIEWS])


def _partners_seeing(ref: _View, partners: Sequence[_View], depth: np.ndarray, step_px: int = 8) -> np.ndarray:
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


def _sample_grid(ref: _View, step_px: int) -> tuple[np.ndarray, np.ndarray]:
    """Columns and rows (2-D) of ``ref``'s pixels every ``step_px``, each its step's centre."""
    w, h = ref.size
    cols, rows = np.meshgrid(np.arange(step_px // 2, w, step_px), np.arange(step_px // 2, h, step_px))
    return cols, rows


def _ground_at(ref: _View, cols: np.ndarray, rows: np.ndarray, depth: np.ndarray | float) -> np.ndarray:
    """The points (local frame) that ``ref``'s pixels (working size) see at ``depth`` along its axis."""
    pts = np.c_[cols, rows].astype(np.float64).reshape(-1, 1, 2)
    norm = cv2.undistortPoints(pts, ref.K, ref.dist).reshape(-1, 2)
    cam = np.c_[norm, np.ones(len(norm))] * np.reshape(depth, (-1, 1))
    return np.asarray(ref.C + cam @ ref.R.T)


def _in_view(view: _View, world: np.ndarray) -> np.ndarray:
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


class _Fusion:
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
