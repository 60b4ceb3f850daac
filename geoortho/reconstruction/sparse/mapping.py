"""The pycolmap stages of sfm: features, matching (exhaustive, spatial from the GPS, or
sequential), incremental or global mapping with its profile, and split-merge into submodels."""

from __future__ import annotations

import contextlib
import json
import math
import shutil
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from geoortho.core.colmap import load_pycolmap
from geoortho.core.parallel import map_ordered
from geoortho.errors import InputError
from geoortho.feedback import Feedback
from geoortho.photos.metadata import Photo
from geoortho.reconstruction.sparse.adjust import Mapped, camera_focal_px, ill_conditioned, prior_focal
from geoortho.reconstruction.sparse.inputs import (
    EXHAUSTIVE_MAX_PHOTOS,
    Body,
    Inputs,
    Mapper,
    Priors,
    Timer,
    camera_bodies,
    colmap_camera_params,
)
from geoortho.reconstruction.splitmerge import finished, merge, partition, run_submodel, submodel_key

#: How often COLMAP's database is read for the progress of its features and matching (s).
PROGRESS_POLL_S = 1.0


@contextlib.contextmanager
def _rows_as_progress(db: Path, table: str, total: int, fb: Feedback, start: float, end: float) -> Iterator[None]:
    """While COLMAP fills ``table`` of its database ``db`` (a row a photo's features, a row a
    pair's matches), the bar moves from ``start`` to ``end`` with the rows written, read once a
    second: COLMAP's calls take no callback, and a bar that stood a minute read as hung (issue 77:
    61 s and 45 s on the demo's features and matching)."""
    import sqlite3

    stop = threading.Event()

    def poll() -> None:
        while not stop.wait(PROGRESS_POLL_S):
            try:
                # immutable: no lock at all. A reader's shared lock made COLMAP's writer meet
                # SQLITE_BUSY, which its checks turn into an abort (a worker lost now and then).
                # A count read mid-write may be off or fail: it only moves a bar.
                uri = f"file:{db}?mode=ro&immutable=1"
                with contextlib.closing(sqlite3.connect(uri, uri=True, timeout=0.2)) as con:
                    n = int(con.execute(f"SELECT COUNT(*) FROM {table}").fetchone()[0])
            except sqlite3.Error:  # COLMAP writing: the next second
                continue
            try:
                fb.set_progress(start + (end - start) * min(1.0, n / max(total, 1)))
            except Exception:  # noqa: BLE001 (a display that failed: the work goes on)
                return

    watcher = threading.Thread(target=poll, name=f"colmap-{table}", daemon=True)
    watcher.start()
    try:
        yield
    finally:
        stop.set()
        watcher.join()


def _pairs_expected(how: str, n_photos: int) -> int:
    """About how many pairs a matcher matches: every pair, or each photo's nearest neighbours."""
    if how == "exhaustive":
        return n_photos * (n_photos - 1) // 2
    return n_photos * min(SPATIAL_MAX_NEIGHBOURS, max(n_photos - 1, 1)) // 2


def _import_and_extract(
    db: Path,
    image_root: Path,
    names: dict[Path, str],
    bodies: list[Body],
    camera_model: str,
    max_image_size: int,
    max_features: int,
    workers: int,
) -> None:
    pc = load_pycolmap()
    for body in bodies:
        ro = pc.ImageReaderOptions()
        ro.camera_model = camera_model
        ro.camera_params = colmap_camera_params(body, camera_model)
        # One import per body in SINGLE mode: the body's photos share one camera.
        pc.import_images(db, image_root, pc.CameraMode.SINGLE, [names[p.path] for p in body.photos], ro)
    eo = pc.FeatureExtractionOptions()
    eo.max_image_size = max_image_size
    eo.num_threads = workers or -1
    eo.sift.max_num_features = max_features
    # Drone photos are sharp and large: the upsampled first octave (COLMAP's default -1) costs
    # about 3x the time for features too small to matter at survey scale.
    eo.sift.first_octave = 0
    pc.extract_features(db, image_root, [names[p.path] for b in bodies for p in b.photos], extraction_options=eo)


def _write_priors(db: Path, priors: Priors, sigma_h_m: float, sigma_v_m: float) -> int:
    """Each photo's position prior, with its own covariance where it states its accuracy
    (RTK/PPK), else ``sigma_h_m`` and ``sigma_v_m``; the number written."""
    pc = load_pycolmap()
    n = 0
    with pc.Database.open(db) as d:
        d.clear_pose_priors()  # COLMAP's own priors: raw EXIF latitude/longitude/altitude
        for im in d.read_all_images():
            pos = priors.positions.get(im.name)
            if pos is not None:
                h, v = priors.sigmas.get(im.name, (sigma_h_m, sigma_v_m))
                # a stated vertical accuracy counts only where the height is the receiver's own
                v = v if priors.vertical_trusted else max(v, sigma_v_m)
                cov = np.diag([h**2, h**2, v**2])
                d.write_pose_prior(
                    pc.PosePrior(
                        corr_data_id=im.data_id,
                        position=np.asarray(pos, float),
                        position_covariance=cov,
                        coordinate_system=pc.PosePriorCoordinateSystem.CARTESIAN,
                    )
                )
                n += 1
    return n


#: The spatial matcher's radius, in footprint widths (the footprint's long side), and the most
#: neighbours each photo is matched with, nearest first. 16, not 30: toledo (57 photos at 2048 px,
#: 2 cores) matched 507 pairs in 54 s instead of 965 in 84 s, mapped in 70 s instead of 78, with
#: all 57 registered, 0.755 px against 0.765 and the GCPs' horizontal RMSE 0.709 m both ways
#: (at 12 neighbours, 415 pairs, 44 s, still 57 registered: 16 keeps a margin for crossing lines).
SPATIAL_RADIUS_FOOTPRINTS = 1.5
SPATIAL_MAX_NEIGHBOURS = 16


def _spatial_distance_m(photos: Sequence[Photo], priors: Priors) -> float:
    """Centres closer than SPATIAL_RADIUS_FOOTPRINTS footprints may overlap: the spatial matcher's radius."""
    heights = [p.relative_altitude_m for p in photos if math.isfinite(p.relative_altitude_m)]
    widths = [
        p.sensor_width_mm / p.focal_mm
        for p in photos
        if math.isfinite(p.sensor_width_mm) and math.isfinite(p.focal_mm) and p.focal_mm > 0
    ]
    if heights and widths:
        return SPATIAL_RADIUS_FOOTPRINTS * float(np.median(heights)) * float(np.median(widths))
    pos = np.array(list(priors.positions.values()))
    # Without heights: 8 × the median spacing between neighbouring photos.
    d = np.linalg.norm(pos[:, None, :2] - pos[None, :, :2], axis=2)
    np.fill_diagonal(d, np.inf)
    return 8.0 * float(np.median(d.min(axis=1)))


def _matcher(how: str, photos: Sequence[Photo], priors: Priors) -> str:
    """The matcher ``how`` names; for "auto", spatial on a large block with GPS, else exhaustive."""
    if how != "auto":
        return how
    enough_gps = len(priors.positions) >= 0.8 * len(photos)
    return "spatial" if enough_gps and len(photos) > EXHAUSTIVE_MAX_PHOTOS else "exhaustive"


def _match(db: Path, how: str, photos: Sequence[Photo], priors: Priors, workers: int) -> str:
    """Match with the matcher ``how`` (spatial, sequential or exhaustive: see :func:`_matcher`)."""
    pc = load_pycolmap()
    mo = pc.FeatureMatchingOptions()
    mo.num_threads = workers or -1
    if how == "spatial":
        if not priors.positions:
            raise InputError("spatial matching needs GPS positions; use exhaustive or sequential")
        po = pc.SpatialPairingOptions()
        po.ignore_z = True
        po.max_distance = _spatial_distance_m(photos, priors)
        po.max_num_neighbors = SPATIAL_MAX_NEIGHBOURS
        pc.match_spatial(db, matching_options=mo, pairing_options=po)
        return f"spatial (neighbours within {po.max_distance:.0f} m, at most {po.max_num_neighbors})"
    if how == "sequential":
        pc.match_sequential(db, matching_options=mo)
        return "sequential"
    pc.match_exhaustive(db, matching_options=mo)
    return "exhaustive"


#: COLMAP incremental-mapper options that differ from its defaults ("mapper." for the inner
#: mapper's). Measured with the same features and matches, the whole sfm after mapping as usual:
#:
#: - a global bundle adjustment each time the model grows by 40 % (COLMAP: 10 %): the 35-photo
#:   small survey mapped in 21.8 s instead of 32.0 s, with the same registration, reprojection
#:   (0.167 px) and GCP RMSE (1.47 against 1.50 mm);
#: - the global adjustments skip 3D points that add no coverage to their photos, and run one
#:   refinement round (COLMAP: up to 5), the local ones one (COLMAP: 2): the medium survey (88
#:   photos, 9,500 tracks per photo) mapped in 110 s instead of 204, its cameras 0.17 cm (h) and
#:   0.24 cm (v) from the truth both ways; toledo (57 real photos, 12,000 features each) in 64 s
#:   instead of 124, GCP RMSE 0.709 m both ways, the cameras within 20 cm of the other run's
#:   (12 cm in height, which its GPS does not fix). The final adjustments are unchanged.
INCREMENTAL_OPTIONS: dict[str, Any] = {
    "ba_global_frames_ratio": 1.4,
    "ba_global_points_ratio": 1.4,
    "mapper.ba_global_ignore_redundant_points3D": True,
    "ba_global_max_refinements": 1,
    "ba_local_max_refinements": 1,
}


def _map(
    db: Path,
    image_root: Path,
    work: Path,
    use_priors: bool,
    workers: int,
    seed: int,
    refine_focal: bool = True,
    mapper: Mapper = "incremental",
    on_photo: Callable[[], None] | None = None,
) -> list[Any]:
    """The mapper's models, largest first; ``on_photo`` is called as each photo joins one
    (incremental only)."""
    pc = load_pycolmap()
    if mapper == "global":
        # GLOMAP: rotation averaging + global positioning, one bundle adjustment; it takes no pose
        # priors (the GPS georeference the model afterwards, as for the incremental one).
        g = pc.GlobalPipelineOptions()
        g.num_threads = workers or -1
        g.random_seed = seed
        g.min_model_size = 3
        g.mapper.bundle_adjustment.refine_focal_length = refine_focal
        work.mkdir(parents=True, exist_ok=True)
        models = pc.global_mapping(db, image_root, work, g)
        return sorted(models.values(), key=lambda r: -r.num_reg_images())
    o = pc.IncrementalPipelineOptions()
    for key, value in INCREMENTAL_OPTIONS.items():
        inner, _, name = key.rpartition(".")
        setattr(o.mapper if inner else o, name, value)
    o.ba_refine_focal_length = refine_focal
    o.use_prior_position = use_priors
    o.use_robust_loss_on_prior_position = True
    o.min_model_size = 3
    o.num_threads = workers or -1
    o.random_seed = seed
    models = pc.incremental_mapping(db, image_root, work, o, next_image_callback=on_photo)
    return sorted(models.values(), key=lambda r: -r.num_reg_images())


#: A registration step this many times the median also ran a whole-model adjustment.
ADJUSTMENT_STEP_RATIO = 3.0


def _mapping_profile(marks: Sequence[float], rec: Any) -> dict[str, Any]:
    """Where incremental mapping spent its time, from when each photo joined (``marks``, starting
    at the mapper's start) and the model it built: tracks per photo, and the time in steps that
    also adjusted the whole model (the global bundle adjustments, which grow with the model)."""
    steps = np.diff(np.asarray(marks, float))
    tracks = np.array([rec.image(i).num_points3D for i in rec.reg_image_ids()], float)
    out: dict[str, Any] = {
        "points": int(rec.num_points3D()),
        "tracks_per_photo_median": float(np.median(tracks)) if tracks.size else 0.0,
        "tracks_per_photo_max": int(tracks.max()) if tracks.size else 0,
        "registration_steps": int(steps.size),
    }
    if steps.size:
        median = float(np.median(steps))
        slow = steps > ADJUSTMENT_STEP_RATIO * median
        out |= {
            "median_step_s": round(median, 3),
            "adjustment_steps": int(np.count_nonzero(slow)),
            "adjustment_s": round(float((steps[slow] - median).sum()), 2),
            "slowest_step_s": round(float(steps.max()), 2),
        }
    return out


def _why_unregistered(db: Path, names: list[str], registered: set[str], elsewhere: set[str]) -> dict[str, str]:
    pc = load_pycolmap()
    reasons = {}
    with pc.Database.open(db) as d:
        ids = {im.name: im.image_id for im in d.read_all_images()}
        pairs, tvgs = d.read_two_view_geometries()
        matched: dict[int, int] = {}
        for pair_id, tvg in zip(pairs, tvgs):
            if len(tvg.inlier_matches) >= 15:
                a, b = _pair_ids(pair_id)
                matched[a] = matched.get(a, 0) + 1
                matched[b] = matched.get(b, 0) + 1
        keypoints = {iid: d.num_keypoints_for_image(iid) for iid in ids.values()}
        typical = float(np.median(list(keypoints.values()))) if keypoints else 0.0
        for name in names:
            if name in registered:
                continue
            iid = ids.get(name)
            n_kp = keypoints.get(iid, 0) if iid is not None else 0
            if iid is None or n_kp == 0:
                reasons[name] = "no features (blank, blurred or unreadable photo)"
            elif name in elsewhere:
                reasons[name] = "registered only in a separate, smaller model (no overlap linking it)"
            elif n_kp < 0.25 * typical:
                # a photo with a fraction of its neighbours' features was spoiled, not off the block
                reasons[name] = (
                    f"few features ({n_kp} against a median of {typical:.0f}): blurred, blown out or featureless"
                )
            elif matched.get(iid, 0) == 0:
                reasons[name] = "no verified matches with any other photo (no overlap?)"
            else:
                reasons[name] = f"matched {matched[iid]} photo(s) but registration failed"
    return reasons


def _pair_ids(pair: Any) -> tuple[int, int]:
    if isinstance(pair, tuple):
        return int(pair[0]), int(pair[1])
    pair = int(pair)
    b = pair % 2147483647
    return (pair - b) // 2147483647, b


def reconstruct(
    inputs: Inputs,
    db: Path,
    work: Path,
    matching: str,
    mapper: Mapper,
    camera_model: str,
    max_image_size: int,
    max_features: int,
    gps_sigma_m: float,
    seed: int,
    workers: int,
    timer: Timer,
    fb: Feedback,
) -> Mapped:
    """Features, GPS priors, matching and mapping into ``db`` and ``work``."""
    photos, priors = inputs.photos, inputs.priors
    notes: list[str] = []
    load_pycolmap().Database.open(db).close()
    t0 = time.perf_counter()
    fb.info("features ...")
    with _rows_as_progress(db, "keypoints", len(photos), fb, 0.0, 0.3):
        _import_and_extract(
            db, inputs.root, inputs.names, list(inputs.bodies), camera_model, max_image_size, max_features, workers
        )
    timer.add("features", t0)
    fb.set_progress(0.3)
    fb.check_canceled()
    # Untrusted GPS heights must not bend the model: their prior is made uninformative.
    sigma_v = 2.0 * gps_sigma_m if priors.vertical_trusted else 1.0e3
    n_priors = _write_priors(db, priors, gps_sigma_m, sigma_v) if priors.positions else 0
    t0 = time.perf_counter()
    matcher = _matcher(matching, photos, priors)
    with _rows_as_progress(db, "matches", _pairs_expected(matcher, len(photos)), fb, 0.3, 0.55):
        how = _match(db, matcher, photos, priors, workers)
    timer.add("matching", t0)
    fb.info(f"matching: {how}")
    fb.set_progress(0.55)
    fb.check_canceled()
    t0 = time.perf_counter()
    ill = ill_conditioned(photos, priors)
    if ill:
        notes.append(
            f"focal length held at the EXIF value during mapping: {ill} (self-calibration "
            "trades focal length for flying height there)"
        )
    marks = [time.perf_counter()]
    models = _map(
        db,
        inputs.root,
        work / "sparse",
        n_priors >= 3,
        workers,
        seed,
        refine_focal=not ill,
        mapper=mapper,
        on_photo=lambda: marks.append(time.perf_counter()),
    )
    timer.add("mapping", t0)
    fb.set_progress(0.85)
    if not models:
        raise InputError(
            "no model could be built: the photos do not overlap enough (or show no texture); see the log for matches",
            path=inputs.root,
        )
    rec = models[0]
    registered = {rec.image(i).name for i in rec.reg_image_ids()}
    elsewhere = {rec2.image(i).name for rec2 in models[1:] for i in rec2.reg_image_ids()}
    if len(models) > 1:
        notes.append(
            f"{len(models)} separate models; the largest ({len(registered)} photos) is kept, "
            f"{len(elsewhere)} photos are only in the others"
        )
    reasons = _why_unregistered(db, list(inputs.names.values()), registered, elsewhere)
    for name, why in sorted(reasons.items()):
        fb.warning(f"not registered: {name}: {why}")
    focal_prior = {cid: prior_focal(db, cid, camera_focal_px(cam)) for cid, cam in rec.cameras.items()}
    return Mapped(
        rec,
        len(models),
        frozenset(registered),
        reasons,
        how,
        bool(ill),
        focal_prior,
        tuple(notes),
        profile=_mapping_profile(marks, rec),
    )


def split_reconstruct(
    inputs: Inputs,
    output: Path,
    split: int,
    overlap_m: float,
    sub_kwargs: dict[str, Any],
    timer: Timer,
    fb: Feedback,
    sfm: Callable[..., Any],
) -> tuple[Mapped, list[dict[str, Any]]]:
    """Split-merge (:mod:`geoortho.reconstruction.splitmerge`): submodels by position, each reconstructed by
    ``sfm`` (the algorithm itself, handed down: it sits above this module) into ``output/submodels``
    (kept: a rerun reuses the ones finished), merged into one model for the georeferencing that follows."""

    if split < 3 or overlap_m < 0:
        raise InputError(f"split {split}: submodels need at least 3 photos, and an overlap of 0 m or more")
    placed = [p for p in inputs.photos if inputs.names[p.path] in inputs.priors.positions]
    if len(placed) < len(inputs.photos) // 2 or len(placed) < 3:
        raise InputError("split-merge places photos by their GPS positions: most photos have none", path=inputs.root)
    names = [inputs.names[p.path] for p in placed]
    xy = np.array([inputs.priors.positions[n][:2] for n in names])
    groups, home = partition(names, xy, split, overlap_m)
    path_of = {inputs.names[p.path]: p.path for p in inputs.photos}
    fb.info(
        f"split into {len(groups)} submodels of at most {split} photos (+ neighbours within {overlap_m:g} m): "
        + ", ".join(str(len(g)) for g in groups)
        + " photos"
    )
    t0 = time.perf_counter()
    folder = output / "submodels"
    outputs = [folder / f"submodel_{k:02d}" for k in range(len(groups))]
    for stale in set(folder.glob("submodel_*")) - set(outputs):  # of an earlier split into more submodels
        shutil.rmtree(stale, ignore_errors=True)
    done: dict[int, Any] = {}
    tasks, keys = [], {}
    for k, (g, sub_output) in enumerate(zip(groups, outputs)):
        paths = [str(path_of[n]) for n in g]
        keys[k] = submodel_key(paths, sub_kwargs)
        if (earlier := finished(sub_output, k, keys[k])) is not None:
            done[k] = earlier
        else:
            tasks.append((k, paths, sub_output, sub_kwargs, sfm, keys[k]))
    if done:
        fb.info(
            f"split-merge: {len(done)} of {len(groups)} submodels reused from an earlier run "
            f"({', '.join(str(k) for k in sorted(done))}); {len(tasks)} to make"
        )
    for s in map_ordered(run_submodel, tasks, workers=1, feedback=fb):
        done[s.index] = s
    subs = [done[k] for k in sorted(done)]
    timer.add("submodels", t0)
    for s in subs:
        if not s.ok:
            fb.warning(f"submodel {s.index} ({len(s.photos)} photos) failed: {s.message}")
    t0 = time.perf_counter()
    home_of = dict(zip(names, home))
    body_of = {inputs.names[p.path]: b.label for b in camera_bodies(inputs.photos) for p in b.photos}
    rec, left_out, stats, came_from = merge(subs, home_of, inputs.priors.offset, fb, body_of)
    for n in path_of:
        if n not in home_of:
            left_out.setdefault(n, "no GPS position: split-merge cannot place it in a submodel")
    timer.add("merge", t0)
    if rec.num_reg_images() < 3:
        raise InputError("no submodel could be reconstructed and merged (see the warnings)", path=inputs.root)
    registered = frozenset(rec.image(i).name for i in rec.reg_image_ids())
    focal = {cid: camera_focal_px(cam) for cid, cam in rec.cameras.items()}
    how = f"split-merge: {len(groups)} submodels of at most {split} photos, {overlap_m:g} m overlap"
    notes = [f"{how}; {sum(s.ok for s in subs)} reconstructed"]
    decided = _submodels_lens_decisions(rec, [s for s in subs if s.ok])
    return Mapped(
        rec, len(groups), registered, left_out, how, False, focal, tuple(notes), came_from, distortion_decided=decided
    ), stats


def _submodels_lens_decisions(rec: Any, subs: Sequence[Any]) -> dict[int, tuple[bool, tuple[float, float], int]]:
    """Per camera of the merged model: whether its distortion was held at zero, where every
    submodel that tested a camera its photos were on decided the same (with the first one's
    figures, and how many decided), from the submodels' reports. A submodel that did not test
    (too few photos, or a model without distortion) or that disagrees leaves it to the merged test."""
    pc = load_pycolmap()
    merged_camera = {rec.image(i).name: rec.image(i).camera_id for i in rec.reg_image_ids()}
    votes: dict[int, dict[int, tuple[bool, tuple[float, float]] | None]] = {}
    for s in subs:
        try:
            report = json.loads((s.output / "report.json").read_text(encoding="utf-8"))
        except (OSError, ValueError):
            return {}  # a submodel without its report: none carried, the merged block tested
        tests = {
            row["camera_id"]: (
                bool(row["distortion"]["held_at_zero"]),
                (row["distortion"]["reprojection_px_refined"], row["distortion"]["reprojection_px_held_at_zero"]),
            )
            for row in report.get("intrinsics", [])
            if "distortion" in row
        }
        sub = pc.Reconstruction(str(s.output / "model"))
        for i in sub.reg_image_ids():
            im = sub.image(i)
            if im.name in merged_camera:
                votes.setdefault(merged_camera[im.name], {})[s.index] = tests.get(im.camera_id)
    decided = {}
    for cid, by_sub in votes.items():
        answers = {v[0] if v is not None else None for v in by_sub.values()}
        if len(answers) == 1 and None not in answers:
            first = by_sub[min(by_sub)]
            assert first is not None
            decided[cid] = (first[0], first[1], len(by_sub))
    return decided
