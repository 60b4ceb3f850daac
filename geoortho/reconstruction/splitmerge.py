"""Split-merge SfM for large blocks: submodels of about N photos, reconstructed apart, merged.

A block of thousands of photos is one mapping problem whose time grows faster than the photo
count. OpenDroneMap splits it: cluster the photos by position into overlapping submodels,
reconstruct each (on other nodes when there are some), align them and merge. Here:

1. **Split** (:func:`partition`): the photos' GPS positions are cut in two at the median of
   the longer axis, again and again, until every group holds at most N photos (groups of equal
   size, compact); each group then takes in the photos of the others within M metres of one
   of its own — the overlap that ties neighbours together.
2. **Reconstruct** each submodel with :func:`geoortho.reconstruction.sparse.sfm` on its photos (GPS
   and the GCPs it sees georeference it on its own), as a task of :mod:`geoortho.core.parallel`:
   on the Dask cluster when there is one, else one after the other (pycolmap uses every core).
   A submodel that fails is reported with its photos; the others are merged. Each submodel's
   output is kept (``OUTPUT/submodels/submodel_KK``) with a record of what made it
   (:func:`finished`): an sfm killed mid-way, rerun, reuses the submodels already made and redoes
   the others alone.
3. **Align**: a submodel without GCP control is put on its already merged neighbours by a
   similarity fitted to the camera centres of the photos they share (≥ 3), when they share
   enough; GCP-controlled submodels are in the CRS already.
4. **Merge** into one COLMAP model: every photo from its *home* submodel (the group it fell in
   before the overlap), the 3D points whose tracks keep two or more such photos. ``sfm`` then
   georeferences the merged model by GPS and GCPs as it would any (a similarity, the GCP
   bundle adjustment) and measures it with the same checkpoints.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from geoortho.core.colmap import load_pycolmap
from geoortho.errors import GeoorthoError
from geoortho.feedback import Feedback

__all__ = ["partition", "Submodel", "finished", "record"]

#: The record a finished submodel leaves beside its products (:func:`record`).
RECORD_NAME = "submodel.json"


def partition(names: Sequence[str], xy: np.ndarray, size: int, overlap_m: float) -> tuple[list[list[str]], list[int]]:
    """Groups of at most ``size`` photos by position (recursive median cuts along the longer axis),
    each widened by the photos of other groups within ``overlap_m`` of one of its own.

    Returns the widened groups and each photo's home group (its group before widening)."""
    home = np.zeros(len(names), int)
    stack = [np.arange(len(names))]
    groups: list[np.ndarray] = []
    while stack:
        idx = stack.pop()
        if len(idx) <= size:
            groups.append(idx)
            continue
        pts = xy[idx]
        axis = int(np.ptp(pts[:, 0]) < np.ptp(pts[:, 1]))
        order = idx[np.argsort(pts[:, axis], kind="stable")]
        # cut into parts that each fill whole groups as evenly as possible
        n_parts = math.ceil(len(idx) / size)
        cut = len(idx) * (n_parts // 2) // n_parts
        stack += [order[cut:], order[:cut]]
    groups.sort(key=lambda g: (float(xy[g, 0].mean()), float(xy[g, 1].mean())))
    widened = []
    for k, g in enumerate(groups):
        home[g] = k
        d = np.hypot(xy[:, None, 0] - xy[None, g, 0], xy[:, None, 1] - xy[None, g, 1]).min(axis=1)
        widened.append([names[int(i)] for i in np.flatnonzero(d <= overlap_m)])
    return widened, home.tolist()


@dataclass(frozen=True)
class Submodel:
    """One submodel's run: its photos, where its output is, and how it went."""

    index: int
    photos: tuple[str, ...]
    output: Path
    ok: bool
    message: str  # why it failed, or how it was georeferenced
    n_registered: int = 0
    gcp_rmse_m: float = math.nan
    checkpoint_rmse_m: float = math.nan
    seconds: float = 0.0
    reused: bool = False  # made by an earlier, interrupted run (:func:`finished`)


def run_submodel(args: tuple[int, list[str], Path, dict[str, Any], Callable[..., Any], dict[str, Any]]) -> Submodel:
    """A task: reconstruct one submodel (on a pool or cluster worker, or here) with ``sfm``, the
    reconstruction function the task carries (passed by the caller: split-merge knows nothing of
    how a block is reconstructed, and the two modules do not import each other). A submodel that
    succeeds leaves its record (:func:`record`) as soon as it is made, wherever it ran: a run
    killed while others were still working finds it."""
    import time

    k, paths, output, kwargs, sfm, key = args
    t = time.perf_counter()
    names = tuple(Path(p).name for p in paths)
    try:
        r = sfm([Path(p) for p in paths], output, **kwargs)
    except GeoorthoError as e:
        return Submodel(k, names, output, False, " ".join(str(e).split()), seconds=time.perf_counter() - t)
    sub = Submodel(
        k,
        names,
        output,
        True,
        r.georeferenced_by,
        r.n_registered,
        r.gcp_rmse_m,
        r.checkpoint_rmse_m,
        time.perf_counter() - t,
    )
    record(sub, key)
    return sub


def submodel_key(paths: Sequence[str], kwargs: dict[str, Any]) -> dict[str, Any]:
    """What makes a submodel: its photos (name, size, time written), its options, the files they
    name (GCP observations, positions: by content) and the geoortho version."""
    import hashlib
    import os

    from geoortho.version import __version__

    def stat(path: str) -> list[Any]:
        st = os.stat(path)
        return [Path(path).name, st.st_size, st.st_mtime_ns]

    files = {
        name: hashlib.sha256(Path(kwargs[name]).read_bytes()).hexdigest()
        for name in ("gcp_list", "positions")
        if kwargs.get(name)
    }
    return {
        "photos": [stat(p) for p in paths],
        "options": {k: str(v) for k, v in sorted(kwargs.items())},
        "files": files,
        "geoortho": __version__,
    }


def finished(output: Path, index: int, key: dict[str, Any]) -> Submodel | None:
    """The submodel made earlier in ``output`` from the same photos and options, if it finished
    (its record is written after its products); None: it is to be made."""
    path = output / RECORD_NAME
    try:
        saved = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    if not isinstance(saved, dict) or saved.get("key") != json.loads(json.dumps(key)):
        return None
    r = saved.get("result") or {}
    if not (output / "model" / "georeference.json").is_file():
        return None
    return Submodel(
        index,
        tuple(r.get("photos") or ()),
        output,
        True,
        str(r.get("message", "")),
        int(r.get("n_registered", 0)),
        _number(r.get("gcp_rmse_m")),
        _number(r.get("checkpoint_rmse_m")),
        float(r.get("seconds", 0.0)),
        reused=True,
    )


def _number(value: Any) -> float:
    return float(value) if isinstance(value, (int, float)) else math.nan


def record(sub: Submodel, key: dict[str, Any]) -> None:
    """A finished submodel's record: what made it, and how it went (a failed one leaves none,
    so that a rerun makes it again)."""
    from geoortho.core.outputs import write_json

    result = {
        "photos": list(sub.photos),
        "message": sub.message,
        "n_registered": sub.n_registered,
        "gcp_rmse_m": sub.gcp_rmse_m if math.isfinite(sub.gcp_rmse_m) else None,
        "checkpoint_rmse_m": sub.checkpoint_rmse_m if math.isfinite(sub.checkpoint_rmse_m) else None,
        "seconds": round(sub.seconds, 2),
    }
    write_json(sub.output / RECORD_NAME, {"key": key, "result": result})


def merge(
    subs: Sequence[Submodel],
    home: dict[str, int],
    offset: np.ndarray,
    fb: Feedback,
    body_of: dict[str, Any] | None = None,
) -> tuple[Any, dict[str, str], list[dict[str, Any]], dict[str, int]]:
    """One reconstruction in the frame ``CRS − offset`` from the submodels that succeeded, with one
    camera per camera body (``body_of``: image name -> its body; the first submodel's calibration
    of it, as the GCP-controlled ones come first): every submodel calibrated the same lens, and the
    adjustments that follow refine it once, not once per submodel.

    Returns it, the photos not in it (with why), per-submodel statistics (shared photos and
    how far their centres disagree with the merged ones), and the submodel each photo in it
    came from."""
    pycolmap = load_pycolmap()
    merged = pycolmap.Reconstruction()
    placed: dict[str, np.ndarray] = {}  # image name -> centre in the merged frame
    stats: list[dict[str, Any]] = []
    ok = [s for s in subs if s.ok]
    # GCP-controlled submodels first (they are in the CRS), then by size
    ok.sort(key=lambda s: ("GCP" not in s.message, -s.n_registered))
    owner = _owners(ok, home)
    recs: list[tuple[Any, dict[int, int]]] = []  # each submodel, in the merged frame, and its photos' ids
    keypoints: dict[int, np.ndarray] = {}  # merged image -> its keypoints
    cameras: dict[Any, int] = {}  # camera body (or submodel and camera) -> merged camera id
    for s in ok:
        rec, centres, shared, aligned = _in_merged_frame(s, offset, placed)
        gaps = [float(np.linalg.norm(centres[n] - placed[n])) for n in shared]
        stats.append(_submodel_stats(s, shared, gaps, aligned))
        image_ids = _add_own_photos(merged, rec, s.index, owner, placed, centres, cameras, body_of or {})
        recs.append((rec, image_ids))
        for i, new_id in image_ids.items():
            keypoints[new_id] = np.array([p.xy for p in rec.image(i).points2D])
    n_joined = _add_points(merged, recs, keypoints)
    failed = {s.index: s.message for s in subs if not s.ok}
    left_out = {
        n: f"submodel {k} failed: {failed[k]}" if k in failed else f"not registered in submodel {k}"
        for n, k in home.items()
        if n not in placed
    }
    merged.update_point_3d_errors()
    fb.info(
        f"merged {len(ok)} of {len(subs)} submodels: {len(placed)} photos, {merged.num_points3D():,} points "
        f"({n_joined:,} seen from two submodels joined)" + (f"; {len(left_out)} photos left out" if left_out else "")
    )
    return merged, left_out, stats, {n: owner[n] for n in placed}


def _owners(ok: Sequence[Submodel], home: dict[str, int]) -> dict[str, int]:
    """A photo's submodel: its group's if that one succeeded, else the first that has it."""
    owner: dict[str, int] = {}
    for s in ok:
        for n in s.photos:
            if home.get(n) == s.index or (n not in owner and not any(t.index == home.get(n) for t in ok)):
                owner.setdefault(n, s.index)
    return owner


def _in_merged_frame(
    s: Submodel, offset: np.ndarray, placed: dict[str, np.ndarray]
) -> tuple[Any, dict[str, np.ndarray], list[str], str]:
    """A submodel moved into the merged frame (and, without GCPs, aligned on the photos it shares
    with those placed); its photos' centres, the shared photos and how it was aligned."""
    pycolmap = load_pycolmap()
    model = s.output / "model"
    rec = pycolmap.Reconstruction(str(model))
    sub_offset = np.asarray(json.loads((model / "georeference.json").read_text())["offset"], float)
    shift = sub_offset - offset  # merged frame = submodel frame + shift
    rec.transform(pycolmap.Sim3d(1.0, pycolmap.Rotation3d(), shift))
    centres = {rec.image(i).name: rec.image(i).projection_center() for i in rec.reg_image_ids()}
    shared = sorted(set(centres) & set(placed))
    aligned = ""
    if "GCP" not in s.message and len(shared) >= 3:
        src = np.array([centres[n] for n in shared])
        dst = np.array([placed[n] for n in shared])
        sim = pycolmap.estimate_sim3d(src, dst)
        if sim is not None:
            rec.transform(sim)
            centres = {rec.image(i).name: rec.image(i).projection_center() for i in rec.reg_image_ids()}
            aligned = f"aligned on {len(shared)} shared photos"
    return rec, centres, shared, aligned


def _submodel_stats(s: Submodel, shared: list[str], gaps: list[float], aligned: str) -> dict[str, Any]:
    return {
        "submodel": s.index,
        "photos": len(s.photos),
        "registered": s.n_registered,
        "georeferenced_by": s.message,
        "aligned": aligned or "as georeferenced",
        "shared_photos": len(shared),
        "shared_centre_rms_m": round(math.sqrt(float(np.mean(np.square(gaps)))), 4) if gaps else None,
        "gcp_rmse_m": None if not math.isfinite(s.gcp_rmse_m) else round(s.gcp_rmse_m, 4),
        "checkpoint_rmse_m": None if not math.isfinite(s.checkpoint_rmse_m) else round(s.checkpoint_rmse_m, 4),
        "seconds": round(s.seconds, 1),
        "reused": s.reused,
    }


def _add_own_photos(
    merged: Any,
    rec: Any,
    index: int,
    owner: dict[str, int],
    placed: dict[str, np.ndarray],
    centres: dict[str, Any],
    cameras: dict[Any, int],
    body_of: dict[str, Any],
) -> dict[int, int]:
    """The submodel's photos it owns (not placed yet) added to ``merged``, on the merged camera of
    their body (added from this submodel's calibration when it is the first to bring the body);
    its image ids -> the merged ones."""
    pycolmap = load_pycolmap()
    image_ids: dict[int, int] = {}
    for i in sorted(rec.reg_image_ids()):
        im = rec.image(i)
        if owner.get(im.name) != index or im.name in placed:
            continue
        body = body_of.get(im.name, (index, im.camera_id))
        if body not in cameras:
            c = rec.camera(im.camera_id)
            cameras[body] = merged.num_cameras() + 1
            cam = pycolmap.Camera(
                model=c.model, width=c.width, height=c.height, params=c.params, camera_id=cameras[body]
            )
            merged.add_camera_with_trivial_rig(cam)
        points = pycolmap.Point2DList([pycolmap.Point2D(p.xy) for p in im.points2D])
        image_ids[i] = merged.num_images() + 1
        new = pycolmap.Image(name=im.name, points2D=points, camera_id=cameras[body], image_id=image_ids[i])
        merged.add_image_with_trivial_frame(new, im.cam_from_world())
        placed[im.name] = centres[im.name]
    return image_ids


def _add_points(merged: Any, recs: list[tuple[Any, dict[int, int]]], keypoints: dict[int, np.ndarray]) -> int:
    """Points, from every submodel onto the merged photos; the points seen from two submodels.

    A photo a submodel shares with another is the same photo with the same features (extraction
    is deterministic): its observations join the owner's copy, and points seen from both
    submodels become one — the tie that lets the bundle adjustment that follows make the
    submodels one block, not several held only by the GCPs."""
    pycolmap = load_pycolmap()
    by_name = {merged.image(i).name: i for i in merged.reg_image_ids()}
    occupied: dict[tuple[int, int], int] = {}  # (merged image, keypoint) -> merged point
    n_joined = 0
    for rec, image_ids in recs:
        to_merged = dict(image_ids)
        for i in rec.reg_image_ids():
            name = rec.image(i).name
            if i not in to_merged and name in by_name:
                kp = np.array([p.xy for p in rec.image(i).points2D])
                mine = keypoints[by_name[name]]
                if kp.shape == mine.shape and np.allclose(kp, mine, atol=1e-3):
                    to_merged[i] = by_name[name]
        for p in rec.points3D.values():
            els: dict[int, int] = {}  # merged image -> keypoint (one observation per photo)
            for e in p.track.elements:
                if e.image_id in to_merged:
                    els.setdefault(to_merged[e.image_id], e.point2D_idx)
            if len(els) < 2:
                continue
            known = {occupied[(i, j)] for i, j in els.items() if (i, j) in occupied}
            if known:
                # seen already from another submodel: its new observations join that point
                target = min(known)
                seen = {e.image_id for e in merged.point3D(target).track.elements}
                for i, j in els.items():
                    if (i, j) not in occupied and i not in seen:
                        merged.add_observation(target, pycolmap.TrackElement(i, j))
                        occupied[(i, j)] = target
                        seen.add(i)
                n_joined += 1
                continue
            track = pycolmap.Track()
            for i, j in els.items():
                track.add_element(i, j)
            pid = merged.add_point3D(p.xyz, track, p.color)
            for i, j in els.items():
                occupied[(i, j)] = pid
    return n_joined
