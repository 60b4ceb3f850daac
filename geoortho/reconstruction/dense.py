"""Dense surface from the photos themselves, on CPU: rectified pairs, OpenCV SGBM, multi-view check.

Each registered photo is a reference: it is paired with its best neighbours from the SfM
model (shared sparse points, a baseline/height ratio that gives depth, similar view
directions), each pair is rectified (``cv2.stereoRectify``) and matched by semi-global block
matching (``cv2.StereoSGBM``, left-right checked), and the pair's points are reprojected into
the reference photo. A point is kept where at least ``min_views`` pairs agree on the depth
within ``depth_tolerance``. The cloud is georeferenced like the SfM model (its CRS and offset)
and thinned to one point per voxel of about a GSD, so ``dem`` takes it as it is.

Here: :func:`dense`, its work planned, run and written. Beside it: :mod:`.dense_pairs` (which
photos pair), :mod:`.stereo` (one pair's depths) and :mod:`.fusion` (a reference's pairs fused,
the cloud thinned).
"""

from __future__ import annotations

import math
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from geoortho.core.copc import COPC_SUFFIX, is_copc_path, write_copc
from geoortho.core.outputs import work_folder, write_json
from geoortho.core.parallel import imap_ordered
from geoortho.errors import InputError, ParameterError
from geoortho.feedback import Feedback, as_feedback, split
from geoortho.reconstruction.dense_pairs import (
    COVER_STEP_PX,
    MIN_SHARED_POINTS,
    Cover,
    DepthJob,
    nearest_views,
    pairs_for_unmeasured_ground,
    plan_pairs,
    view_of,
)
from geoortho.reconstruction.fusion import Fusion, depth_task

__all__ = ["DenseResult", "dense"]
#: ``dense`` warns when more than this share of the registered photos gives no depth map.
MAX_SHARE_WITHOUT_MAP = 0.05


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
    copc : Path
        The cloud also as a COPC file, which QGIS opens and streams (None when not asked for).
    """

    output: Path
    report: Path
    n_photos: int
    n_depth_maps: int
    n_points: int
    crs: str
    notes: tuple[str, ...] = field(default_factory=tuple)
    copc: Path | None = None


def dense(
    sfm: Path,
    images: Path,
    output: Path,
    max_image_size: int = 1024,
    neighbours: int = 3,
    min_views: int = 2,
    depth_tolerance: float = 0.003,
    workers: int = 0,
    copc: Path | None = None,
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
    copc : Path
        The cloud also as a Cloud-Optimized Point Cloud (its name ends in .copc.laz), which QGIS
        opens as a layer and streams, with no indexing step.
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
    if copc is not None and not is_copc_path(copc):
        raise ParameterError("copc", f"{copc}: a COPC file's name ends in {COPC_SUFFIX}")
    cams, crs, pts, skipped = cameras_from_sfm(sfm, images, local_frame_ok=True)
    notes = [f"{name}: {why}" for name, why in skipped]
    if crs is None:
        notes.append("the SfM model is in a local frame (no GPS, no GCPs): the cloud has no CRS and model units")
        fb.warning("dense: the SfM model is in a local frame: the cloud has no CRS (georeference the sfm run)")
    if len(cams) < 2:
        raise InputError(f"{len(cams)} registered photo(s) on disk: a dense surface needs 2 or more", path=sfm)
    if len(pts) < MIN_SHARED_POINTS:
        raise InputError(f"the SfM model has {len(pts)} sparse points: too few to choose pairs", path=sfm)
    work = _planned_work(cams, pts, crs is not None, max_image_size, neighbours, min_views, depth_tolerance)
    if not work.jobs:
        raise InputError("no pair of photos overlaps with enough baseline for depth", path=sfm)
    seconds = {"plan": _lap(clock)}
    s_maps, s_write = split(fb, [9, 1] if copc is None else [9, 1.5])
    with work_folder(output) as spill:
        fusion = Fusion(work.voxel_m, spill_dir=Path(spill))
        maps = _depth_maps(work, fusion, workers, s_maps)
        seconds["depth_maps"] = _lap(clock) - seconds["plan"]
        peak_before_write_mb = _peak_memory_mb()["main"]
        t_write = time.perf_counter()
        heights, _ = model_heights(sfm)  # the cloud's header says its heights' datum where the SfM knew it
        cloud_crs = with_heights(crs, heights) if crs is not None else None
        n_written, fallback = _write_cloud(output, fusion, pts, work.origin, cloud_crs, notes, fb)
        seconds["fusion"] = fusion.seconds  # merges, spills and (spilled) the tiles' merges
        seconds["write"] = time.perf_counter() - t_write  # a spilled cloud's tiles merged included
        if copc is not None:
            t_copc = time.perf_counter()
            written = write_copc(output, Path(copc))
            seconds["copc"] = time.perf_counter() - t_copc
            fb.info(f"dense: the cloud as COPC too: {written.n_nodes:,} octree nodes, {written.depth + 1} levels")
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
    return DenseResult(
        output, report, len(cams), maps.n_maps, n_written, crs_text, tuple(notes), None if copc is None else Path(copc)
    )


@dataclass(frozen=True)
class _Work:
    """The depth maps to make: a job per reference photo, and the photos that have no partner."""

    jobs: list[DepthJob]
    no_partner: list[str]
    origin: np.ndarray  # the local frame's origin in the model's frame
    scale: float  # the photos' median working scale
    voxel_m: float  # about one depth-map pixel on the ground
    cover: Cover | None = None

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
    views = [view_of(c, s, origin) for c, s in zip(cams, scales)]
    scale = float(np.median(scales))
    pairs, gsd = plan_pairs(cams, pts, neighbours, up=up)
    voxel = gsd / scale if pairs else math.nan
    centres = np.array([v.C for v in views])
    jobs = [
        DepthJob(
            views[i], tuple(views[j] for j in nbrs), rngs, tuple(f - origin[2] for f in floors), min_views,
            tolerance, voxel, neighbours, nearest_views(views, centres, i),
        )
        for i, nbrs, rngs, floors in pairs
    ]  # fmt: skip
    planned = {j.ref.name for j in jobs}
    cover = None
    if jobs:
        jobs, cover = pairs_for_unmeasured_ground(jobs, COVER_STEP_PX * voxel)
    return _Work(jobs, [v.name for v in views if v.name not in planned], origin, scale, voxel, cover)


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


def _depth_maps(work: _Work, fusion: Fusion, workers: int, fb: Feedback) -> _Maps:
    """Every job's depth map, made by the workers and fused as it arrives."""
    maps = _Maps(
        no_map={n: "no partner: no other photo shares its view with a baseline for depth" for n in work.no_partner}
    )
    for job, got in zip(work.jobs, imap_ordered(depth_task, work.jobs, workers=workers, feedback=fb)):
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
    output: Path, fusion: Fusion, pts: np.ndarray, origin: np.ndarray, crs: Any, notes: list[str], fb: Feedback
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
