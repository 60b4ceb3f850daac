"""Structure from Motion with pycolmap, made into a survey: GPS-seeded, GCP-constrained, honestly reported.

pycolmap does the photogrammetry (SIFT, matching, incremental mapping, bundle
adjustment). This module does what makes the result a survey:

* one COLMAP camera per camera body (make, model, image size, focal length),
  started from the metadata's focal length in pixels of the decoded image
  (EXIF size tags are not trusted);
* photo pairs chosen from the GPS positions (spatial matching) on larger
  blocks, all pairs on small ones;
* GPS positions as pose priors in a local Cartesian frame (the output CRS
  minus a round offset, so that coordinates stay small and single precision is
  safe); the mapper's bundle adjustment weighs them, then a robust similarity
  transform puts the model on them;
* GCPs from a gcp_list.txt are triangulated from their image observations and
  the model is moved onto them by a similarity (7 parameters), then refined by
  a bundle adjustment in which the control points are fixed 3D points observed
  in the photos; ``checkpoints`` are held out of both and reported separately.

Heights follow :mod:`geoortho.photos.footprint`: the take-off elevation (given, or the
flight's absolute − relative altitude) plus each photo's relative altitude.
GCP heights that are all equal are taken as placeholders: those GCPs then
control the model horizontally only, and their vertical residuals are not
reported.

Outputs in ``output``: ``model/`` (COLMAP binary model in the local frame, with
``georeference.json`` giving the CRS and offset), ``points.laz`` (georeferenced,
coloured), ``cameras.gpkg`` (camera centres, orientation, residuals),
``report.json``.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import shutil
import tempfile
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Literal, get_args

import numpy as np
from pyproj import CRS

from geoortho.core.camera import rotation_from_ypr, ypr_from_rotation
from geoortho.core.colmap import load_pycolmap
from geoortho.core.crs import (
    ELLIPSOIDAL,
    WGS84,
    crs_to_text,
    geoid_undulation_m,
    heights_label,
    heights_of,
    heights_to_text,
    horizontal_of,
    transformer,
    utm_crs_for,
    with_heights,
)
from geoortho.core.gsd import depth_gsd_m
from geoortho.core.outputs import temp_prefix, write_json, write_vector
from geoortho.core.parallel import map_ordered
from geoortho.core.pointcloud import write_las
from geoortho.core.styles import product_styles
from geoortho.errors import InputError
from geoortho.feedback import Feedback, as_feedback
from geoortho.gcp.io import GcpSet, heights_are_placeholders, read_gcp_file
from geoortho.photos.footprint import photo_cameras, working_crs
from geoortho.photos.heights import absolute_altitude, check_altitudes
from geoortho.photos.metadata import Photo, list_images, photo_seconds, read_photos
from geoortho.photos.positions import PositionFile, apply_positions, read_positions
from geoortho.reconstruction.splitmerge import finished, merge, partition, run_submodel, submodel_key

__all__ = ["SfmResult", "sfm", "MATCHING", "MAPPERS", "CAMERA_MODELS", "ce90", "le90"]

Matching = Literal["auto", "exhaustive", "spatial", "sequential"]
Mapper = Literal["incremental", "global"]
CameraModel = Literal["RADIAL", "SIMPLE_RADIAL", "OPENCV", "SIMPLE_PINHOLE", "PINHOLE"]
MATCHING: tuple[str, ...] = get_args(Matching)
MAPPERS: tuple[str, ...] = get_args(Mapper)
CAMERA_MODELS: tuple[str, ...] = get_args(CameraModel)
# A georeferenced model whose vertical is this far from the photos' gravity was bent by bad GPS heights.
MAX_TILT_DEG = 3.0
# Focal length changes beyond this (percent of the EXIF value) are reported.
FOCAL_DRIFT_WARN_PCT = 3.0
# Up to this many photos every pair is matched; above, pairs come from the GPS positions.
EXHAUSTIVE_MAX_PHOTOS = 40
# CE90 / LE90 from RMSE, normal errors (NSSDA; what OpenSfM/ODM reports):
# circular 90 % = 2.1460 σc with σc = sqrt((RMSEx² + RMSEy²) / 2); linear 90 % = 1.6449 RMSEz.
_CE90_PER_SIGMA = 2.1460
_LE90_PER_SIGMA = 1.6449


@dataclass(frozen=True)
class SfmResult:
    """The georeferenced reconstruction and its accuracy figures.

    Attributes
    ----------
    output : Path
        The SfM folder.
    model : Path
        COLMAP model (local frame; georeference.json gives CRS and offset).
    points : Path
        Georeferenced sparse points, coloured.
    cameras : Path
        Camera centres, orientation and residuals.
    report : Path
        report.json: registration, reprojection, GCP/checkpoint residuals.
    n_photos : int
        Photos read.
    n_registered : int
        Photos registered.
    crs : str
        CRS of the outputs.
    mean_reprojection_error_px : float
        Mean reprojection error, px.
    gcp_rmse_m : float
        3D RMSE at the control GCPs (NaN without).
    checkpoint_rmse_m : float
        3D RMSE at the checkpoints (NaN without).
    georeferenced_by : str
        What put the model in the CRS.
    notes : tuple of str
        What was assumed or checked, in words.
    """

    output: Path
    model: Path
    points: Path
    cameras: Path
    report: Path
    n_photos: int
    n_registered: int
    crs: str
    mean_reprojection_error_px: float
    gcp_rmse_m: float  # 3D RMSE over the control GCPs, NaN without
    checkpoint_rmse_m: float  # 3D RMSE over the checkpoints, NaN without
    georeferenced_by: str
    notes: tuple[str, ...] = field(default_factory=tuple)


def ce90(dx: np.ndarray, dy: np.ndarray) -> float:
    """Horizontal circular error at 90 % from the X and Y residuals (NaN if none)."""
    if len(dx) == 0:
        return math.nan
    sigma_c = math.sqrt((np.mean(np.square(dx)) + np.mean(np.square(dy))) / 2.0)
    return _CE90_PER_SIGMA * sigma_c


def le90(dz: np.ndarray) -> float:
    """Vertical linear error at 90 % from the Z residuals (NaN if none)."""
    return _LE90_PER_SIGMA * math.sqrt(np.mean(np.square(dz))) if len(dz) else math.nan


# ---------------------------------------------------------------------------------------------
# inputs


@dataclass(frozen=True)
class _Body:
    """Photos sharing one camera: same make, model, decoded size and focal length."""

    key: tuple[str, str, int, int, float]
    photos: tuple[Photo, ...]
    calibration: str = ""  # the factory calibration, named when bodies of one model differ by it

    @property
    def label(self) -> str:
        make, model, w, h, f = self.key
        return (
            f"{make} {model} {w}x{h}"
            + (f" f={f:g} mm" if math.isfinite(f) else "")
            + (f" ({self.calibration})" if self.calibration else "")
        )


def _factory_key(p: Photo) -> tuple[float, float, float]:
    if not math.isfinite(p.factory_focal_px):
        return (math.nan, math.nan, math.nan)
    return (round(p.factory_focal_px, 1), round(p.factory_cx_px, 1), round(p.factory_cy_px, 1))


def _bodies(photos: Sequence[Photo]) -> list[_Body]:
    """The photos grouped by camera; two drones of one model carry two factory calibrations, and
    each is its own body (the first photo's calibration was taken for both)."""
    groups: dict[tuple[str, str, int, int, float], list[Photo]] = {}
    for p in photos:
        f = round(p.focal_mm, 2) if math.isfinite(p.focal_mm) else math.nan
        groups.setdefault((p.make, p.model, p.width_px, p.height_px, f), []).append(p)
    out = []
    for k, v in groups.items():
        by_cal: dict[str, list[Photo]] = {}
        for p in v:
            by_cal.setdefault(repr(_factory_key(p)), []).append(p)
        if len(by_cal) == 1:
            out.append(_Body(k, tuple(v)))
            continue
        for ps in by_cal.values():
            fk = _factory_key(ps[0])
            said = f"factory calibration f={fk[0]:g} px" if math.isfinite(fk[0]) else "no factory calibration"
            out.append(_Body(k, tuple(ps), said))
    return out


def _camera_params(body: _Body, model: str) -> str:
    """Initial intrinsics for COLMAP: the maker's factory calibration where the photos carry one
    (focal length, optical centre, distortion), else the focal length from EXIF, the principal
    point at the centre and no distortion."""
    p = body.photos[0]
    factory = math.isfinite(p.factory_focal_px)
    f = p.factory_focal_px if factory else p.focal_px
    if not math.isfinite(f):
        return ""  # COLMAP then guesses 1.2 × the larger side and refines it
    # COLMAP: pixel (0, 0) is the top-left corner, as DJI's optical centre
    cx, cy = (p.factory_cx_px, p.factory_cy_px) if factory else (p.width_px / 2.0, p.height_px / 2.0)
    k1, k2, p1, p2, _k3 = (*p.factory_distortion, 0.0, 0.0, 0.0, 0.0, 0.0)[:5] if factory else (0.0,) * 5
    base = {
        "SIMPLE_PINHOLE": [f, cx, cy],
        "PINHOLE": [f, f, cx, cy],
        "SIMPLE_RADIAL": [f, cx, cy, k1],
        "RADIAL": [f, cx, cy, k1, k2],
        "OPENCV": [f, f, cx, cy, k1, k2, p1, p2],
    }[model]
    return ",".join(f"{v:.6f}" for v in base)


@dataclass(frozen=True)
class _Priors:
    """GPS camera positions in the local frame (CRS minus ``offset``), by image name."""

    crs: Any
    offset: np.ndarray  # (3,) added back to local coordinates
    positions: dict[str, np.ndarray]
    heights: str
    vertical_trusted: bool = True
    notes: tuple[str, ...] = ()
    # the 1-sigma horizontal and vertical accuracy (m) each photo states (RTK/PPK); the photos
    # not here are weighed at the survey's gps_sigma_m
    sigmas: dict[str, tuple[float, float]] = field(default_factory=dict)
    fixes: dict[str, str] = field(default_factory=dict)  # photo -> Photo.gps_fix

    def sigma_h_typical(self, default_m: float) -> float:
        """The median horizontal sigma of the positions (``default_m`` with none stated)."""
        values = [h for h, _ in self.sigmas.values() if math.isfinite(h)]
        return float(np.median(values)) if values else default_m


def _gps_priors(
    photos: Sequence[Photo], names: dict[Path, str], crs: Any, takeoff_elevation_m: float | None
) -> _Priors:
    """Camera positions from the metadata, heights per :mod:`geoortho.photos.heights`.

    SfM needs no height above ground, only camera elevations in one datum: a flight without
    RelativeAltitude keeps its GPS altitude as recorded (EXIF: orthometric) when no reading of it
    as a height above ground holds, and its trend over time decides whether it is trusted."""
    with_gps = [p for p in photos if p.has_gps and p.has_altitude]
    if not with_gps:
        return _Priors(crs, np.zeros(3), {}, "no GPS")
    notes: list[str] = []
    try:
        cams, heights = photo_cameras(with_gps, crs, takeoff_elevation_m=takeoff_elevation_m, gnss_takeoff=True)
        centres = np.array([c.pose.center for c in cams])
        trusted = heights.vertical_gps_trusted or heights.method.startswith("relative")
        label = heights.method
        notes += [n for n in heights.notes if "not trusted" in n or "drift" in n]
    except InputError as e:
        # No height above ground to be had: keep the recorded GNSS altitude (its own datum).
        xy = np.array(
            transformer(WGS84, crs).transform([p.longitude_deg for p in with_gps], [p.latitude_deg for p in with_gps])
        ).T
        z = np.array([absolute_altitude(p) for p in with_gps])
        centres = np.c_[xy, z]
        check = check_altitudes(with_gps, z, "GPS altitude")
        trusted = check is None or check.trusted
        label = "GPS altitude as recorded (EXIF says orthometric; not converted)"
        if not trusted:
            notes.append(f"GPS altitude not trusted ({check.describe()})")  # type: ignore[union-attr]
        elif "sea-level" not in str(e):
            notes.append(f"heights: {e}")
    centres, n_rtk_heights = _rtk_heights(with_gps, centres, notes)
    trusted = trusted or n_rtk_heights >= 3
    offset = np.array([*np.round(np.median(centres[:, :2], axis=0), -2), 0.0])
    positions = {names[p.path]: c - offset for p, c in zip(with_gps, centres)}
    sigmas = {names[p.path]: (p.gps_sigma_h_m, p.gps_sigma_v_m) for p in with_gps if math.isfinite(p.gps_sigma_h_m)}
    fixes = {names[p.path]: p.gps_fix for p in with_gps}
    return _Priors(crs, offset, positions, label, trusted, tuple(notes), sigmas, fixes)


#: A photo whose stated vertical accuracy is this good (m) is placed at its GNSS altitude.
RTK_HEIGHT_SIGMA_M = 0.5


def _rtk_heights(photos: Sequence[Photo], centres: np.ndarray, notes: list[str]) -> tuple[np.ndarray, int]:
    """The camera heights of photos with an RTK/PPK-grade vertical accuracy from their own GNSS
    altitude, not from the barometric RelativeAltitude plus take-off (0.1-0.5 m of noise where the
    receiver gives centimetres). Kept in the datum of the other heights: a user's take-off
    elevation in another datum moves them all by the median difference."""
    z = np.array([absolute_altitude(p) for p in photos])
    sigma_v = np.array([p.gps_sigma_v_m for p in photos])
    with np.errstate(invalid="ignore"):
        rtk = np.isfinite(z) & (sigma_v <= RTK_HEIGHT_SIGMA_M)
    if rtk.sum() < 3:
        return centres, 0
    shift = float(np.median(z[rtk] - centres[rtk, 2]))
    datum = 0.0 if abs(shift) < 1.0 else shift  # the same datum (metres of noise) or another
    out = centres.copy()
    out[rtk, 2] = z[rtk] - datum
    notes.append(
        f"heights of {int(rtk.sum())} photos from their GNSS altitude (stated vertical accuracy "
        f"{RTK_HEIGHT_SIGMA_M:g} m or better)"
        + (f", moved {-datum:+.2f} m onto the other heights' datum" if datum else "")
    )
    return out, int(rtk.sum())


def _image_names(photos: Sequence[Photo]) -> tuple[Path, dict[Path, str]]:
    """The photos' common folder and each photo's COLMAP image name (its path relative to that).
    A photo that is a link keeps its own name (its folder resolved, not the link): a folder of links
    picks photos for a run, and the link's target may lie anywhere."""
    root = Path(os.path.commonpath([str(p.path.parent.resolve()) for p in photos]))
    return root, {p.path: str((p.path.parent.resolve() / p.path.name).relative_to(root)) for p in photos}


# ---------------------------------------------------------------------------------------------
# the pycolmap stages


@dataclass
class _Timer:
    stages: dict[str, float] = field(default_factory=dict)

    def add(self, stage: str, t0: float) -> None:
        self.stages[stage] = self.stages.get(stage, 0.0) + time.perf_counter() - t0


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
    bodies: list[_Body],
    camera_model: str,
    max_image_size: int,
    max_features: int,
    workers: int,
) -> None:
    pc = load_pycolmap()
    for body in bodies:
        ro = pc.ImageReaderOptions()
        ro.camera_model = camera_model
        ro.camera_params = _camera_params(body, camera_model)
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


def _write_priors(db: Path, priors: _Priors, sigma_h_m: float, sigma_v_m: float) -> int:
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


def _spatial_distance_m(photos: Sequence[Photo], priors: _Priors) -> float:
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


def _matcher(how: str, photos: Sequence[Photo], priors: _Priors) -> str:
    """The matcher ``how`` names; for "auto", spatial on a large block with GPS, else exhaustive."""
    if how != "auto":
        return how
    enough_gps = len(priors.positions) >= 0.8 * len(photos)
    return "spatial" if enough_gps and len(photos) > EXHAUSTIVE_MAX_PHOTOS else "exhaustive"


def _match(db: Path, how: str, photos: Sequence[Photo], priors: _Priors, workers: int) -> str:
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


# ---------------------------------------------------------------------------------------------
# georeferencing


def _centres(rec: Any) -> dict[str, np.ndarray]:
    return {rec.image(i).name: rec.image(i).projection_center() for i in rec.reg_image_ids()}


def _align_to_gps(rec: Any, priors: _Priors, sigma_h_m: float) -> tuple[Any, int]:
    """Robust similarity from the model's camera centres onto their GPS positions."""
    pc = load_pycolmap()
    names = [n for n in _centres(rec) if n in priors.positions]
    if len(names) < 3:
        return None, 0
    ro = pc.RANSACOptions()
    ro.max_error = 3.0 * sigma_h_m
    ro.random_seed = 0
    sim = pc.align_reconstruction_to_locations(rec, names, np.array([priors.positions[n] for n in names]), 3, ro)
    if sim is not None:
        rec.transform(sim)
    return sim, len(names)


def _levelling_rotation(rec: Any, photos_by_name: dict[str, Photo]) -> np.ndarray | None:
    """Model → world rotation that makes the cameras look where their recorded attitude says
    (chordal mean over the photos). Gimbals hold pitch and roll to a degree or two, so this
    levels the model from gravity; its heading is only as good as the compass."""
    m = np.zeros((3, 3))
    k = 0
    for iid in rec.reg_image_ids():
        im = rec.image(iid)
        p = photos_by_name.get(im.name)
        if p is None:
            continue
        m += rotation_from_ypr(p.yaw_deg, p.pitch_deg, p.roll_deg) @ im.cam_from_world().rotation.matrix()
        k += 1
    if k < 3:
        return None
    u, _, vt = np.linalg.svd(m)
    r: np.ndarray = u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt
    return r


#: Camera centres farther than this from the flight's plane (take-off, landing, a line flown at
#: another height) do not level the model.
PLANE_OUTLIER_M = 3.0


def _camera_plane_levelling(centres: np.ndarray) -> tuple[np.ndarray, float, int] | None:
    """The rotation that makes the plane through the camera centres level (a drone on a height
    hold flies level lines), its tilt in degrees, and the centres it was fitted to; None for too
    few centres or ones that span no plane (a single line). Centres off the plane by more than
    PLANE_OUTLIER_M of the flight's scale (take-off, landing) are dropped, then it is fitted again."""
    if len(centres) < 6:
        return None
    keep = np.ones(len(centres), bool)
    normal = np.array([0.0, 0.0, 1.0])
    scale = 1.0
    for _ in range(4):
        pts = centres[keep]
        mid = pts.mean(axis=0)
        _, sv, vt = np.linalg.svd(pts - mid)
        if sv[1] < 0.05 * sv[0]:  # one line: no plane to level by
            return None
        normal = vt[2] if vt[2, 2] >= 0 else -vt[2]
        # the model's scale is unknown here: the spread of the centres along the flight sets it
        scale = float(sv[0]) / math.sqrt(len(pts))
        dist = np.abs((centres - mid) @ normal)
        spread = max(1.4826 * float(np.median(dist[keep])), 1e-3 * scale)
        new = dist <= max(4.0 * spread, 0.02 * scale)
        if new.sum() < 6 or (new == keep).all():
            keep = new if new.sum() >= 6 else keep
            break
        keep = new
    up = np.array([0.0, 0.0, 1.0])
    axis = np.cross(normal, up)
    sin_t, cos_t = float(np.linalg.norm(axis)), float(normal @ up)
    tilt = math.degrees(math.atan2(sin_t, cos_t))
    if sin_t < 1e-12:
        return np.eye(3), 0.0, int(keep.sum())
    k = axis / sin_t
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    rot = np.eye(3) + sin_t * kx + (1 - cos_t) * (kx @ kx)
    return rot, tilt, int(keep.sum())


def _plane_tilt(rec: Any) -> float | None:
    """Tilt of the plane through the georeferenced model's camera centres, degrees (None: no plane)."""
    plane = _camera_plane_levelling(np.array(list(_centres(rec).values())).reshape(-1, 3))
    return None if plane is None else round(plane[1], 3)


def _attitude_recorded(photos: Sequence[Photo]) -> bool:
    """Most photos carry a pitch and roll of their own (not the nadir assumed for none)."""
    assumed = sum(p.attitude_source.startswith("assumed") for p in photos)
    return assumed < 0.5 * max(len(photos), 1)


def _tilt_deg(rec: Any, photos_by_name: dict[str, Photo]) -> float:
    """How far the (georeferenced) model's vertical is from gravity as the photos' attitude gives it."""
    r = _levelling_rotation(rec, photos_by_name)
    return math.nan if r is None else math.degrees(math.acos(float(np.clip(r[2, 2], -1.0, 1.0))))


def _align_horizontal(
    rec: Any, priors: _Priors, photos_by_name: dict[str, Photo], sigma_h_m: float, notes: list[str]
) -> tuple[Any, str]:
    """Georeference with untrusted GPS heights: level the model from the photos' attitude (with no
    pitch and roll recorded: on the plane of the camera centres), then a robust 2-D similarity onto
    the GPS positions (scale, heading, east/north); the vertical offset is the median GPS height's
    (GCPs, when given, correct it next). Returns the similarity and how the model was levelled."""
    from skimage.measure import ransac
    from skimage.transform import SimilarityTransform

    pc = load_pycolmap()
    level = _levelling_rotation(rec, photos_by_name)
    centres = _centres(rec)
    names = [n for n in centres if n in priors.positions]
    if level is None or len(names) < 3:
        return None, ""
    how = "from the photos' attitude"
    if not _attitude_recorded(list(photos_by_name.values())):
        # No pitch or roll in the metadata: the nadir assumed levels the model only as well as the
        # camera hung plumb (a fixed mount tilted 3.5 deg tilted a real model 3.5 deg). A drone on
        # a height hold flies level lines: the plane of the camera centres is levelled instead.
        plane = _camera_plane_levelling(np.array([level @ centres[n] for n in centres]))
        if plane is not None:
            rot, tilt, used = plane
            level = rot @ level
            how = "on the plane of the camera centres"
            notes.append(
                f"no pitch or roll in the photos and no trusted GPS heights: the model is levelled on the plane "
                f"of {used} camera centres (a flight at one height); the nadir assumed was {tilt:.1f} deg off it"
            )
    src = np.array([level @ centres[n] for n in names])
    tgt = np.array([priors.positions[n] for n in names])
    model, inliers = ransac(
        (src[:, :2], tgt[:, :2]),
        SimilarityTransform,
        min_samples=2,
        residual_threshold=3.0 * sigma_h_m,
        max_trials=500,
        rng=0,
    )
    if model is None or inliers is None or inliers.sum() < 3:
        return None, ""
    scale = float(model.scale)
    c, s_ = math.cos(model.rotation), math.sin(model.rotation)
    rot = np.array([[c, -s_, 0.0], [s_, c, 0.0], [0.0, 0.0, 1.0]]) @ level
    tz = float(np.median(tgt[inliers, 2] - scale * src[inliers, 2]))
    sim = pc.Sim3d(scale, pc.Rotation3d(rot), np.array([*model.translation, tz]))
    rec.transform(sim)
    return sim, how


def _ill_conditioned(photos: Sequence[Photo], priors: _Priors) -> str:
    """Why self-calibrating the focal length is ill-posed here ('' if it is not): on a nadir-only,
    single-height block focal length and flying height trade off almost exactly."""
    nadir = all(p.pitch_deg <= -75.0 for p in photos)
    z = np.array([v[2] for v in priors.positions.values()]) if priors.positions else np.zeros(0)
    # untrusted GPS heights say nothing of the flight's: take it as flown at one height, as most are
    single = z.size == 0 or not priors.vertical_trusted or float(np.ptp(z)) < 10.0
    return "nadir-only, single-height block" if nadir and single else ""


def _focal_px(cam: Any) -> float:
    return float(np.mean([cam.params[i] for i in cam.focal_length_idxs()]))


def _focal_drift(rec: Any, priors_px: dict[int, float]) -> dict[int, float]:
    """Camera id → focal length change from its prior, percent."""
    return {
        cid: 100.0 * (_focal_px(cam) / priors_px[cid] - 1.0)
        for cid, cam in rec.cameras.items()
        if cid in priors_px and priors_px[cid] > 0
    }


def _probe_free_focal(rec: Any, refine_distortion: bool = True) -> dict[int, float]:
    """Focal lengths a bundle adjustment reaches when it may refine them (on a copy)."""
    pc = load_pycolmap()
    opts = _ba_options(refine_distortion=refine_distortion, robust=True)
    probe = _adjusted_copy(rec, opts, pc.BundleAdjustmentGauge.TWO_CAMS_FROM_WORLD)
    return {cid: _focal_px(cam) for cid, cam in probe.cameras.items()}


#: A camera's lens distortion is held at zero when holding it costs less than this share of the
#: block's mean reprojection error. Measured: the synthetic survey's distortion-free camera
#: reprojects 0.1578/0.1578 px (seed 3) and 0.1454/0.1453 px (seed 6) with k1, k2 refined/held,
#: while the refined k1 (-0.0027, -0.0038) domed the open ground +0.34/+0.51 GSD; toledo's
#: FC6310 (k1 -0.10) reprojects 0.76 px refined and 2.51 px held, the hard preset's camera (k1
#: -0.02) 0.220 and 0.262 px. The test costs 5 % of the sfm stage (hard preset: 2.7 of 50.5 s).
DISTORTION_SUPPORT_PCT = 1.0
#: The trial adjustments start from the mapper's converged block: a few iterations settle them.
DISTORTION_TRIAL_ITERATIONS = 10


def _hold_unsupported_distortion(mapped: _Mapped, notes: list[str]) -> _Mapped:
    """Hold at zero the lens distortion the photos cannot tell from none.

    On a nadir block, radial distortion trades against a dome of the whole block: a camera with
    none is given a k1 by the GPS priors' or the mapper's path, which bends the ground by a
    fraction of a GSD and that no reprojection residual shows. Each camera's distortion is tested
    on copies: the block adjusted with it refined, against it zeroed and held (the other cameras
    as they are). Both trials refine the focal length, even where the mapping held it: a focal
    length held wrong (a bad EXIF value) is otherwise partly absorbed by the distortion, which then
    looks supported (synthetic, EXIF focal 11 % long: 0.172 px held, 0.169 px refined). Where holding
    the distortion costs under DISTORTION_SUPPORT_PCT of the reprojection error, it is held at zero
    from here on (the block continues from that adjustment, its focal length held as before)."""
    pc = load_pycolmap()
    rec = mapped.rec
    cams = [cid for cid, cam in rec.cameras.items() if len(cam.extra_params_idxs())]
    if not cams or rec.num_reg_images() < 3:
        return mapped
    # split-merge: the submodels tested each lens on blocks of the same flight; where they agree,
    # the merged block (the test's time grows with photos^1.45) takes their answer
    decided = {cid: mapped.distortion_decided[cid] for cid in cams if cid in mapped.distortion_decided}
    for cid, (held_there, _, n_subs) in sorted(decided.items()):
        decided_by = f"its {n_subs} submodels each decided" if n_subs > 1 else "its submodel decided"
        notes.append(
            f"camera {cid}: lens distortion {'held at zero' if held_there else 'refined'} as {decided_by} "
            "(not tested again on the merged block)"
        )
    cams = [cid for cid in cams if cid not in decided]
    gauge = pc.BundleAdjustmentGauge.TWO_CAMS_FROM_WORLD
    trial = DISTORTION_TRIAL_ITERATIONS

    def zeroed(src: Any, ids: Sequence[int]) -> Any:
        out = pc.Reconstruction(src)
        for cid in ids:
            cam = out.camera(cid)
            params = np.array(cam.params)
            params[list(cam.extra_params_idxs())] = 0.0
            cam.params = params
        return out

    # The trials compare two adjustments of the same points: a sample of them, spread over every
    # photo's frame (where distortion shows), tells the same (see TRIAL_POINTS_PER_PHOTO).
    test: dict[int, tuple[float, float]] = {cid: figures for cid, (_, figures, _) in decided.items()}
    if cams:
        sample = _thinned(rec, TRIAL_POINTS_PER_PHOTO)
        refined_px = _mean_reprojection_px(_adjusted_copy(sample, _ba_options(iterations=trial), gauge))
        for cid in cams:
            held_copy = _adjusted_copy(
                zeroed(sample, [cid]), _ba_options(refine_distortion=False, iterations=trial), gauge
            )
            test[cid] = (refined_px, _mean_reprojection_px(held_copy))
    tested = frozenset(cid for cid in cams if test[cid][1] <= test[cid][0] * (1.0 + DISTORTION_SUPPORT_PCT / 100.0))
    held = tested | frozenset(cid for cid, (held_there, _, _) in decided.items() if held_there)
    if not held:
        return replace(mapped, distortion_test=test)
    opts = _ba_options(refine_focal=not mapped.focal_held, refine_distortion=False)
    block = _adjusted_copy(zeroed(rec, sorted(held)), opts, gauge)
    for cid in sorted(tested):
        a, b = test[cid]
        notes.append(
            f"camera {cid}: lens distortion held at zero: the photos do not support it (reprojection "
            f"{a:.3f} px refined, {b:.3f} px without, over a sample of {sample.num_points3D()} points; "
            "refined, it would bend the block into a dome)"
        )
    return replace(mapped, rec=block, distortion_test=test, distortion_held=held)


#: The distortion trials adjust at most this many points per photo, the longest tracks in each
#: cell of a TRIAL_GRID over its frame. Measured (the test's time, the held/refined ratio of
#: reprojection, all points → the sample): the medium survey 60 → 36 s, held both ways (1.000);
#: toledo 21 → 12 s, refined both ways (1.26 → 1.30 and 3.21 → 3.35), GCP RMSE unchanged. The
#: sample's reprojection is not the block's (toledo 0.88 against 0.75 px): only the ratio counts.
TRIAL_POINTS_PER_PHOTO = 1200
TRIAL_GRID = (8, 6)


def _thinned(rec: Any, per_photo: int) -> Any:
    """A copy of the block keeping, for each photo, at most ``per_photo`` of the points it sees:
    in each cell of a TRIAL_GRID over its frame, those of longest track (the strongest ties)."""
    pc = load_pycolmap()
    nx, ny = TRIAL_GRID
    per_cell = max(1, per_photo // (nx * ny))
    track = {pid: p.track.length() for pid, p in rec.points3D.items()}
    keep: set[int] = set()
    for iid in rec.reg_image_ids():
        im = rec.image(iid)
        cam = rec.camera(im.camera_id)
        seen = [(q.point3D_id, q.xy) for q in im.points2D if q.has_point3D()]
        if len(seen) <= per_photo:
            keep.update(pid for pid, _ in seen)
            continue
        ids = np.array([pid for pid, _ in seen], np.int64)
        xy = np.array([xy for _, xy in seen], float)
        cell = np.clip((xy[:, 0] * nx / cam.width).astype(int), 0, nx - 1) * ny + np.clip(
            (xy[:, 1] * ny / cam.height).astype(int), 0, ny - 1
        )
        length = np.array([track[int(pid)] for pid in ids])
        order = np.lexsort((-length, cell))  # by cell, longest track first within it
        rank = np.arange(order.size) - np.searchsorted(cell[order], cell[order], side="left")
        keep.update(int(pid) for pid in ids[order[rank < per_cell]])
    out = pc.Reconstruction(rec)
    for pid in track:
        if pid not in keep:
            out.delete_point3D(pid)
    return out


#: The adjustments after mapping stop when an iteration changes the cost by less than this share
#: (Ceres' own default; COLMAP sets none, so each ran to its iteration cap or a gradient test on
#: blocks the mapper had already converged). Measured, whole sfm on the same features and matches:
#: the medium survey (88 photos) 237 -> 162 s, its GCP adjustment 67 -> 8 iterations (73 -> 15 s),
#: the held block 28 -> 6, cameras 0.17 cm (h) from the truth both ways, GCP RMSE 0.84 mm both
#: ways; toledo 121 -> 72 s, a 101-iteration adjustment 14, the GCP RMSE the same to 1e-11 m.
BA_FUNCTION_TOLERANCE = 1e-6


def _ba_options(
    *, refine_focal: bool = True, refine_distortion: bool = True, robust: bool = False, iterations: int | None = None
) -> Any:
    """COLMAP's bundle-adjustment options, quiet: what each adjustment here refines, a soft-L1 loss
    when ``robust``, an iteration cap when given (Ceres' 100 otherwise), and a stop once an
    iteration changes the cost by less than BA_FUNCTION_TOLERANCE (see there)."""
    pc = load_pycolmap()
    opts = pc.BundleAdjustmentOptions()
    opts.print_summary = False
    opts.ceres.solver_options.function_tolerance = BA_FUNCTION_TOLERANCE
    opts.refine_focal_length = refine_focal
    opts.refine_extra_params = refine_distortion
    if robust:
        opts.ceres.loss_function_type = pc.LossFunctionType.SOFT_L1
    if iterations is not None:
        opts.ceres.solver_options.max_num_iterations = iterations
    return opts


def _mean_reprojection_px(rec: Any) -> float:
    """Mean reprojection error over the block's points, computed afresh (the points' stored errors
    are those of the last mapper step, not of an adjustment since)."""
    rec.update_point_3d_errors()
    return float(rec.compute_mean_reprojection_error())


def _adjusted_copy(rec: Any, opts: Any, gauge: Any) -> Any:
    """A copy of the block bundle-adjusted over all its registered photos with ``opts``, its gauge
    held by ``gauge``. COLMAP's adjuster itself, not pycolmap.bundle_adjustment: that one logs two
    INFO lines and leaves COLMAP's log level at INFO, so the mapping after it printed to stderr."""
    pc = load_pycolmap()
    copy = pc.Reconstruction(rec)
    cfg = pc.BundleAdjustmentConfig()
    for iid in copy.reg_image_ids():
        cfg.add_image(iid)
    cfg.fix_gauge(gauge)
    pc.create_default_bundle_adjuster(opts, cfg, copy).solve()
    return copy


def _gps_outliers(rec: Any, priors: _Priors) -> list[str]:
    """Photos whose GPS position is far off the model's (robust: 4 sigma and 3 m horizontally)."""
    c = _centres(rec)
    names = [n for n in c if n in priors.positions]
    if len(names) < 5:
        return []
    d = np.array([np.hypot(*(c[n] - priors.positions[n])[:2]) for n in names])
    sigma = 1.4826 * float(np.median(np.abs(d - np.median(d))))
    limit = max(3.0, float(np.median(d)) + 4.0 * sigma)
    return [n for n, v in zip(names, d) if v > limit]


@dataclass
class _GcpState:
    name: str
    surveyed: np.ndarray  # local frame
    observations: list[tuple[str, float, float]]  # (image, x, y) COLMAP pixels (corner origin)
    role: str  # "control" | "checkpoint"
    triangulated: np.ndarray | None = None
    inliers: int = 0
    reprojection_px: float = math.nan


def _gcp_states(
    gcps: GcpSet, crs: Any, offset: np.ndarray, checkpoints: set[str], registered: set[str], fb: Feedback
) -> list[_GcpState]:
    to_local = transformer(gcps.crs, crs)
    by_name = gcps.by_name()
    obs: dict[str, list[tuple[str, float, float]]] = {}
    known = {Path(n).name: n for n in registered}
    unmatched = set()
    for o in gcps.observations:
        image = o.image if o.image in registered else known.get(Path(o.image).name)
        if image is None:
            unmatched.add(o.image)
            continue
        # gcp_list.txt: (0, 0) is the centre of the top-left pixel; COLMAP: its top-left corner.
        obs.setdefault(o.gcp, []).append((image, o.x_px + 0.5, o.y_px + 0.5))
    if unmatched:
        fb.warning(
            f"GCP observations in {len(unmatched)} photo(s) not in the model ignored: "
            + ", ".join(sorted(unmatched)[:5])
            + (" ..." if len(unmatched) > 5 else "")
        )
    states = []
    for name, g in by_name.items():
        x, y = to_local.transform(g.x, g.y)
        local = np.array([x, y, g.z]) - offset
        states.append(_GcpState(name, local, obs.get(name, []), "checkpoint" if name in checkpoints else "control"))
    return states


def _triangulate(rec: Any, states: list[_GcpState], max_error_px: float = 4.0) -> None:
    """Each GCP from its observations in registered photos (robust; needs two or more)."""
    pc = load_pycolmap()
    by_name = {rec.image(i).name: rec.image(i) for i in rec.reg_image_ids()}
    for s in states:
        s.triangulated, s.inliers, s.reprojection_px = None, 0, math.nan
        ims = [(by_name[n], x, y) for n, x, y in s.observations if n in by_name]
        if len(ims) < 2:
            continue
        opts = pc.EstimateTriangulationOptions()
        opts.residual_type = pc.TriangulationResidualType.REPROJECTION_ERROR
        opts.ransac.max_error = max_error_px
        opts.ransac.random_seed = 0
        out = pc.estimate_triangulation(
            np.array([[x, y] for _, x, y in ims]),
            [im.cam_from_world() for im, _, _ in ims],
            [im.camera for im, _, _ in ims],
            opts,
        )
        if out is None:
            continue
        s.triangulated = np.asarray(out["xyz"], float).reshape(3)
        s.inliers = int(np.sum(out["inliers"]))
        s.reprojection_px = _reprojection_px(ims, s.surveyed)


def _reprojection_px(ims: list[tuple[Any, float, float]], xyz: np.ndarray) -> float:
    """Mean distance (px) between the observations and the surveyed point projected into the photos."""
    errs = []
    for im, x, y in ims:
        p = im.project_point(xyz)
        if p is not None:
            errs.append(math.hypot(p[0] - x, p[1] - y))
    return float(np.mean(errs)) if errs else math.nan


def _align_to_gcps(rec: Any, states: list[_GcpState], heights_usable: bool) -> Any:
    """Similarity from the triangulated control GCPs onto their surveyed positions."""
    pc = load_pycolmap()
    use = [s for s in states if s.role == "control" and s.triangulated is not None]
    if len(use) < 3:
        return None
    src = np.array([s.triangulated for s in use])
    tgt = np.array([s.surveyed for s in use])
    if not heights_usable:
        tgt[:, 2] = src[:, 2]  # placeholder heights: control horizontally, keep the GPS heights
    sim = pc.estimate_sim3d(src, tgt)
    if sim is not None:
        rec.transform(sim)
    return sim


def _gcp_bundle_adjust(rec: Any, states: list[_GcpState], refine_distortion: bool = True) -> int:
    """Bundle adjustment with the control GCPs as fixed 3D points observed in the photos.

    A COLMAP image cannot take new 2D points once it has some, so each GCP
    observation borrows a keypoint slot that no 3D point uses (its coordinates
    are restored afterwards). The fixed points hold the datum: no gauge is left
    free. Returns the number of GCP observations used.
    """
    pc = load_pycolmap()
    by_name = {rec.image(i).name: i for i in rec.reg_image_ids()}
    borrowed: list[tuple[int, int, np.ndarray]] = []
    gcp_points = []
    free_slots: dict[int, list[int]] = {}
    for s in states:
        if s.role != "control" or s.triangulated is None:
            continue
        track = pc.Track()
        for name, x, y in s.observations:
            iid = by_name.get(name)
            if iid is None:
                continue
            im = rec.image(iid)
            if iid not in free_slots:
                free_slots[iid] = [k for k, p in enumerate(im.points2D) if not p.has_point3D()]
            if not free_slots[iid]:
                continue
            k = free_slots[iid].pop()
            borrowed.append((iid, k, np.array(im.point2D(k).xy)))
            im.points2D[k].xy = np.array([x, y])
            track.add_element(iid, k)
        if track.length() >= 2:
            gcp_points.append(rec.add_point3D(s.surveyed, track, np.zeros(3, np.uint8)))
    n_obs = sum(rec.point3D(p).track.length() for p in gcp_points)
    if len(gcp_points) >= 3:
        cfg = pc.BundleAdjustmentConfig()
        for iid in rec.reg_image_ids():
            cfg.add_image(iid)
        for pid in gcp_points:
            cfg.add_constant_point(pid)
        opts = _ba_options(refine_distortion=refine_distortion, robust=True)
        pc.create_default_bundle_adjuster(opts, cfg, rec).solve()
    for pid in gcp_points:
        rec.delete_point3D(pid)
    for iid, k, xy in borrowed:
        rec.image(iid).points2D[k].xy = xy
    return n_obs if len(gcp_points) >= 3 else 0


# ---------------------------------------------------------------------------------------------
# report


def _residual_table(states: list[_GcpState], heights_usable: bool) -> list[dict[str, Any]]:
    rows = []
    for s in states:
        row: dict[str, Any] = {
            "name": s.name,
            "role": s.role,
            "observations": len(s.observations),
            "inliers": s.inliers,
        }
        if s.triangulated is None:
            row.update(
                dx_m=None,
                dy_m=None,
                dz_m=None,
                reprojection_px=None,
                note="seen in fewer than two registered photos" if len(s.observations) < 2 else "triangulation failed",
            )
        else:
            d = s.triangulated - s.surveyed
            row.update(
                dx_m=float(d[0]),
                dy_m=float(d[1]),
                dz_m=float(d[2]) if heights_usable else None,
                reprojection_px=s.reprojection_px if heights_usable else None,
            )
        rows.append(row)
    return rows


def _accuracy(rows: list[dict[str, Any]], role: str) -> dict[str, Any] | None:
    use = [r for r in rows if r["role"] == role and r["dx_m"] is not None]
    if not use:
        return None
    dx = np.array([r["dx_m"] for r in use])
    dy = np.array([r["dy_m"] for r in use])
    dz = np.array([r["dz_m"] for r in use if r["dz_m"] is not None])
    out: dict[str, Any] = {
        "n": len(use),
        "rmse_x_m": float(np.sqrt(np.mean(dx**2))),
        "rmse_y_m": float(np.sqrt(np.mean(dy**2))),
        "rmse_horizontal_m": float(np.sqrt(np.mean(dx**2 + dy**2))),
        "ce90_m": ce90(dx, dy),
    }
    if len(dz) == len(use):
        out.update(
            rmse_z_m=float(np.sqrt(np.mean(dz**2))),
            rmse_3d_m=float(np.sqrt(np.mean(dx**2 + dy**2 + dz**2))),
            le90_m=le90(dz),
        )
    else:
        out.update(rmse_z_m=None, rmse_3d_m=None, le90_m=None)
    return out


# ---------------------------------------------------------------------------------------------
# outputs


def _reprojection_errors(rec: Any) -> dict[int, tuple[float, int]]:
    """Mean reprojection error (px) and number of tie points, per registered image."""
    ids = list(rec.point3D_ids())
    err = {pid: rec.point3D(pid).error for pid in ids}
    out = {}
    for iid in rec.reg_image_ids():
        e = [err[p.point3D_id] for p in rec.image(iid).get_observation_points2D()]
        out[iid] = (float(np.mean(e)) if e else math.nan, len(e))
    return out


def _gsd_m(rec: Any) -> float:
    """Median over photos of (median depth of the photo's tie points) / focal length."""
    values = []
    for iid in rec.reg_image_ids():
        im = rec.image(iid)
        obs = im.get_observation_points2D()
        if len(obs) < 10:
            continue
        xyz = np.array([rec.point3D(p.point3D_id).xyz for p in obs[:: max(1, len(obs) // 200)]])
        m = im.cam_from_world().matrix()
        depth = xyz @ m[:, :3].T[:, 2] + m[2, 3]
        values.append(depth_gsd_m(float(np.median(depth)), im.camera.mean_focal_length()))
    return float(np.median(values)) if values else math.nan


def _write_points(path: Path, rec: Any, offset: np.ndarray, crs: Any) -> int:
    ids = list(rec.point3D_ids())
    xyz = np.array([rec.point3D(p).xyz for p in ids]).reshape(-1, 3) + offset
    rgb = np.array([rec.point3D(p).color for p in ids], float).reshape(-1, 3) / 255.0
    write_las(path, xyz, crs, rgb=rgb)
    return len(ids)


def _write_cameras(
    path: Path,
    rec: Any,
    photos: Sequence[Photo],
    names: dict[Path, str],
    priors: _Priors,
    crs: Any,
    reasons: dict[str, str],
    submodel: dict[str, int] | None = None,
) -> None:
    import geopandas as gpd
    import shapely

    reg = {}
    errs = _reprojection_errors(rec)
    for iid in rec.reg_image_ids():
        reg[rec.image(iid).name] = iid
    rows, geoms = [], []
    for p in photos:
        name = names[p.path]
        gps = priors.positions.get(name)
        sigma_h, sigma_v = priors.sigmas.get(name, (math.nan, math.nan))
        row: dict[str, Any] = {
            "image": name,
            "registered": name in reg,
            "reason": reasons.get(name, ""),
            "camera": f"{p.make} {p.model}".strip(),
            "gps_fix": p.gps_fix,
            "gps_sigma_h_m": sigma_h,  # as the photo states it (NaN: weighed at gps_sigma_m)
            "gps_sigma_v_m": sigma_v,
        }
        if submodel:  # split-merge: which submodel placed the photo (-1: none)
            row["submodel"] = submodel.get(name, -1)
        if name in reg:
            im = rec.image(reg[name])
            c = im.projection_center()
            yaw, pitch, roll = ypr_from_rotation(im.cam_from_world().rotation.matrix().T)
            e, n = errs.get(reg[name], (math.nan, 0))
            row.update(
                x=c[0] + priors.offset[0],
                y=c[1] + priors.offset[1],
                z=c[2] + priors.offset[2],
                yaw_deg=yaw,
                pitch_deg=pitch,
                roll_deg=roll,
                reprojection_px=e,
                tie_points=n,
            )
            if gps is not None:
                d = c - gps
                row.update(gps_dx_m=d[0], gps_dy_m=d[1], gps_dz_m=d[2])
            geoms.append(shapely.Point(*(c + priors.offset)))
        elif gps is not None:
            g = gps + priors.offset
            row.update(x=g[0], y=g[1], z=g[2])  # where the GPS put it
            geoms.append(shapely.Point(*g))
        else:
            geoms.append(None)
        rows.append(row)
    gdf = gpd.GeoDataFrame(rows, geometry=geoms, crs=crs)
    write_vector(path, {"cameras": gdf}, styles=product_styles("cameras"))


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


# ---------------------------------------------------------------------------------------------
# the algorithm


def sfm(
    images: Path,
    output: Path,
    gcp_list: Path | None = None,
    checkpoints: str = "",
    crs: CRS | None = None,
    matching: Matching = "auto",
    max_image_size: int = 2048,
    max_features: int = 8192,
    camera_model: CameraModel = "RADIAL",
    takeoff_elevation_m: float | None = None,
    gps_sigma_m: float = 2.0,
    local_frame: bool = False,
    seed: int = 0,
    workers: int = 0,
    mapper: Mapper = "incremental",
    split: int = 0,
    split_overlap_m: float = 30.0,
    positions: Path | None = None,
    positions_time_offset_s: float | None = None,
    *,
    feedback: Feedback | None = None,
) -> SfmResult:
    """Reconstruct camera poses and sparse points with pycolmap, georeferenced by GPS and GCPs.

    Parameters
    ----------
    images : Path
        Folder of photos (or a list of photo paths).
    output : Path
        Folder for ``model/``, ``points.laz``, ``cameras.gpkg`` and ``report.json``.
    gcp_list : Path
        OpenDroneMap gcp_list.txt: GCP coordinates and where photos see them
        (from ``gcp-find`` or typed in).
    checkpoints : str
        Comma-separated GCP names held out of the adjustment and only measured.
    crs : CRS
        Output CRS (projected). Default: the GCP file's if projected, else the photos' UTM zone.
    matching : str
        auto (exhaustive up to 40 photos, else spatial from GPS), exhaustive, spatial or sequential.
    max_image_size : int
        Photos are downscaled to this larger side for feature extraction (px).
    max_features : int
        SIFT features per photo, at least: COLMAP keeps whole scale levels until it has this
        many keypoints, and gives a keypoint with two orientations two features (toledo, 8,192
        asked: about 10,000 keypoints, 12,000 features).
    camera_model : str
        COLMAP camera model, one per camera body.
    takeoff_elevation_m : float
        Ground elevation of the take-off point, in the vertical datum of the ground
        model (the DSM, the ground elevation or the GCPs). Default: worked out from the
        photos (absolute − relative altitude, checked against the
        ground model; else the ground under the flight), and said.
    gps_sigma_m : float
        Horizontal standard deviation of the photos' GPS positions (vertical: twice that).
    local_frame : bool
        Without GPS and GCPs, still write a model in an arbitrary local frame.
    seed : int
        Random seed of the mapper (repeatable runs).
    workers : int
        Threads for pycolmap (0 = every core).
    mapper : str
        incremental (COLMAP's, GPS-prior weighted) or global (GLOMAP: rotation averaging and
        global positioning; see benchmarks/bench_sfm.py --mappers for which is faster here).
    split : int
        Split-merge for large blocks: reconstruct submodels of at most this many photos
        (clustered by GPS position; on the Dask cluster when one is given), align and merge
        them into one model (0 = one block).
    split_overlap_m : float
        Each submodel also takes the photos of its neighbours within this distance (m): the
        shared photos that tie the submodels together.
    positions : Path
        Post-processed (PPK) or surveyed camera positions that replace the photos' own: an
        RTKLIB .pos solution, a DJI Timestamp.MRK, or a CSV (image, x/lon, y/lat, z, sigma_h,
        sigma_v; a '# EPSG:…' line names its CRS). Each is weighed by its stated accuracy; a
        trajectory is matched to the photos by time, and a camera-to-GPS time lag that the
        block shows is found and the positions read again at it.
    positions_time_offset_s : float
        The .pos file's time minus the camera clock (s), e.g. 18 for GPS time against a camera
        on UTC. Default: found by laying the photos' own GPS positions on the trajectory.
    """
    fb = as_feedback(feedback)
    t_start = time.perf_counter()
    timer = _Timer()
    output = Path(output)
    _check_choice("camera model", camera_model, CAMERA_MODELS)
    _check_choice("mapper", mapper, MAPPERS)
    _check_choice("matching", matching, MATCHING)
    inputs = _read_inputs(
        images, gcp_list, checkpoints, crs, takeoff_elevation_m, local_frame, timer, fb,
        positions=positions, positions_time_offset_s=positions_time_offset_s,
    )  # fmt: skip
    notes = list(inputs.notes)
    output.mkdir(parents=True, exist_ok=True)
    work = Path(tempfile.mkdtemp(prefix=temp_prefix("sfm-work"), dir=output))
    try:
        db = work / "database.db"
        sub_stats: list[dict[str, Any]] = []
        if split and len(inputs.photos) > split:
            sub_kwargs = dict(
                gcp_list=gcp_list, checkpoints=checkpoints, crs=inputs.out_crs or crs, matching=matching,
                max_image_size=max_image_size, max_features=max_features, camera_model=camera_model,
                takeoff_elevation_m=takeoff_elevation_m, gps_sigma_m=gps_sigma_m, seed=seed, workers=workers,
                mapper=mapper, positions=positions,
                positions_time_offset_s=None if inputs.positions is None else inputs.positions.time_offset_s,
            )  # fmt: skip
            mapped, sub_stats = _split_reconstruct(inputs, output, split, split_overlap_m, sub_kwargs, timer, fb)
        else:
            mapped = _reconstruct(
                inputs, db, work, matching, mapper, camera_model, max_image_size, max_features, gps_sigma_m, seed,
                workers, timer, fb,
            )  # fmt: skip
        notes += mapped.notes
        t0 = time.perf_counter()
        mapped = _hold_unsupported_distortion(mapped, notes)
        timer.add("lens_distortion_test", t0)
        inputs, lag, geo = _georeference(mapped, inputs, gps_sigma_m, notes, timer, fb)
        intrinsics = _intrinsics_report(mapped, geo.gcp_obs_used, notes)
        if geo.gps_sim is None and not any(s.triangulated is not None for s in geo.states) and not local_frame:
            raise InputError(
                "the model could not be georeferenced (GPS did not fit, GCPs not triangulated)"
                + _why_positions_did_not_fit(inputs)
                + "; use local_frame to keep it anyway",
                path=images,
            )
        t0 = time.perf_counter()
        n_points = _write_model(output, work, db, mapped, inputs, geo, notes)
        timer.add("outputs", t0)
        figures = _figures(mapped.rec, inputs, geo)
        _write_report(output, inputs, mapped, geo, figures, intrinsics, mapper, lag, sub_stats, timer, t_start, notes)
        if not sub_stats:  # one block now: an earlier split's submodels describe another model
            shutil.rmtree(output / "submodels", ignore_errors=True)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    _announce(notes, mapped, inputs, geo, figures, n_points, fb)
    fb.set_progress(1.0)
    return _result(output, inputs, mapped, geo, figures, notes)


def _write_report(
    output: Path,
    inputs: _Inputs,
    mapped: _Mapped,
    geo: Any,
    figures: Any,
    intrinsics: Any,
    mapper: str,
    lag: Any,
    sub_stats: list[dict[str, Any]],
    timer: _Timer,
    t_start: float,
    notes: list[str],
) -> None:
    """report.json: the block, its georeference and figures, the GPS's accuracy as measured, the
    time lag or the positions file, and the submodels of a split block."""
    accuracy = gps_accuracy(mapped.rec, inputs.priors, notes)
    report = _report(inputs, mapped, geo, figures, intrinsics, mapper, timer, t_start, notes)
    report["gps_accuracy"] = accuracy
    if lag is not None and inputs.positions is None:
        report["gps_time_lag"] = lag
    if inputs.positions is not None:
        report["positions"] = _positions_report(inputs.positions, lag)
    write_json(output / "report.json", report | ({"submodels": sub_stats} if sub_stats else {}))


def _result(output: Path, inputs: _Inputs, mapped: _Mapped, geo: Any, figures: Any, notes: list[str]) -> SfmResult:
    return SfmResult(
        output=output,
        model=output / "model",
        points=output / "points.laz",
        cameras=output / "cameras.gpkg",
        report=output / "report.json",
        n_photos=len(inputs.photos),
        n_registered=len(mapped.registered),
        crs=inputs.crs_text,
        mean_reprojection_error_px=figures.mean_reprojection_px,
        gcp_rmse_m=_rmse3(figures.control),
        checkpoint_rmse_m=_rmse3(figures.check),
        georeferenced_by=geo.how,
        notes=tuple(notes),
    )


def _georeference(
    mapped: _Mapped, inputs: _Inputs, gps_sigma_m: float, notes: list[str], timer: _Timer, fb: Feedback
) -> tuple[_Inputs, Any, Any]:
    """The block's time lag found (and the positions read again at it), then the block put in
    the CRS by the GPS and by the GCPs; the inputs as read again, the lag and the georeference."""
    t0 = time.perf_counter()
    inputs, lag = _refine_time_lag(mapped, inputs, notes)
    geo = _georeference_by_gps(mapped.rec, inputs, gps_sigma_m)
    geo = _georeference_by_gcps(
        mapped.rec, inputs, mapped.registered, geo, fb, refine_distortion=not mapped.distortion_held
    )
    notes += geo.notes
    heights, heights_from = _heights_datum(inputs, geo)
    notes.append(
        f"heights' datum: {heights_label(heights)}" + (", from " if heights is not None else ": ") + heights_from
    )
    timer.add("georeferencing", t0)
    return inputs, lag, replace(geo, heights=heights, heights_from=heights_from)


def _why_positions_did_not_fit(inputs: _Inputs) -> str:
    """What most likely kept the positions off the block's geometry, when it can be told: the
    positions file that replaced the photos' own, deviations stated tighter than any receiver, or
    the maker's factory calibration the block started from."""
    causes = []
    if inputs.positions is not None:
        causes.append(f"the positions of {inputs.positions.path.name} (they replaced the photos' own)")
    sigmas = [h for h, _ in inputs.priors.sigmas.values() if math.isfinite(h)]
    if sigmas and float(np.median(sigmas)) <= 0.01:
        causes.append(f"deviations stated at {1000 * float(np.median(sigmas)):.0f} mm, tighter than the block fits")
    factory = [b.label for b in inputs.bodies if math.isfinite(b.photos[0].factory_focal_px)]
    if factory:
        causes.append(f"the factory calibration of {factory[0]} (a wrong one bends the block)")
    return f": check {'; or '.join(causes)}" if causes else ""


def _positions_report(positions: Any, lag: Any) -> dict[str, Any]:
    """What the report says of the positions file that replaced the photos' own."""
    return {
        "file": str(positions.path),
        "format": positions.source,
        "photos": len(positions.by_image),
        "photos_without": list(positions.photos_without),
        "lines_without": list(positions.lines_without),
        "n_lines_without": max(positions.n_lines_without, len(positions.lines_without)),
        "heights": positions.heights,
        "gps_distance_m": positions.gps_distance_m if math.isfinite(positions.gps_distance_m) else None,
        "far_from_gps": list(positions.far_from_gps),
        "time_offset_s": positions.time_offset_s,
        "time_offset_found": positions.offset_found,
        "time_lag": lag,
    }


def _check_choice(what: str, value: str, choices: tuple[str, ...]) -> None:
    if value not in choices:
        raise InputError(f"{what} {value!r} is not one of {', '.join(choices)}")


# -- the stages of sfm, each a function of small frozen records -----------------------------------


@dataclass(frozen=True)
class _Inputs:
    """What sfm works from: the photos, the GCPs and the GPS priors, checked."""

    photos: tuple[Photo, ...]
    skipped: tuple[tuple[str, str], ...]
    root: Path  # the folder image names are relative to
    names: dict[Path, str]  # photo path -> COLMAP image name
    gcps: GcpSet | None
    held_out: frozenset[str]  # checkpoint names
    out_crs: Any
    priors: _Priors
    bodies: tuple[_Body, ...]
    notes: tuple[str, ...]
    positions: PositionFile | None = None  # a positions file's, applied to the photos
    photos_as_read: tuple[Photo, ...] = ()  # before the positions file (a time lag reads it again)
    takeoff_elevation_m: float | None = None
    heights_given: Any = None  # the heights' datum --crs states (its vertical part), or None

    @property
    def crs_text(self) -> str:
        return crs_to_text(self.out_crs) if self.out_crs is not None else ""


def _read_gcps(gcp_list: Path | None, checkpoints: str, photos: list[Photo], notes: list[str]) -> tuple[Any, set[str]]:
    """The GCP file (None without one) and the GCPs held out as checkpoints."""
    gcps = read_gcp_file(gcp_list) if gcp_list else None
    if gcps is not None and not gcps.observations:
        raise InputError(
            "the GCP file has no image observations: SfM needs a gcp_list.txt "
            "(x y z px py image name rows), e.g. from gcp-find",
            path=gcp_list,
        )
    held_out = _checkpoint_names(checkpoints, gcps, photos, notes)
    if gcps is not None and held_out - set(gcps.by_name()):
        raise InputError(
            f"checkpoint(s) not in the GCP file: {', '.join(sorted(held_out - set(gcps.by_name())))}", path=gcp_list
        )
    return gcps, held_out


def _priors_for(
    photos: list[Photo], names: Any, out_crs: Any, takeoff_elevation_m: float | None, gcps: Any
) -> tuple[_Priors, list[str]]:
    """The photos' GPS as pose priors in the output CRS (its local frame's origin: the GCPs'
    median where no photo has GPS), and what their heights are, in words."""
    priors = (
        _gps_priors(photos, names, out_crs, takeoff_elevation_m)
        if out_crs is not None
        else _Priors(None, np.zeros(3), {}, "no GPS")
    )
    notes = [f"heights: {priors.heights}", *priors.notes]
    if gcps is not None and priors.positions and out_crs is not None:
        _check_gcps_near_photos(gcps, priors, out_crs)
    if gcps is not None and not priors.positions:
        to_local = transformer(gcps.crs, out_crs)
        xy = np.array([to_local.transform(g.x, g.y) for g in gcps.points])
        priors = _Priors(out_crs, np.array([*np.round(np.median(xy, axis=0), -2), 0.0]), {}, "no GPS")
    return priors, notes


def _read_inputs(
    images: Path,
    gcp_list: Path | None,
    checkpoints: str,
    crs: CRS | None,
    takeoff_elevation_m: float | None,
    local_frame: bool,
    timer: _Timer,
    fb: Feedback,
    *,
    positions: Path | None = None,
    positions_time_offset_s: float | None = None,
) -> _Inputs:
    t0 = time.perf_counter()
    paths = list_images(images) if isinstance(images, (str, os.PathLike)) else [Path(p) for p in images]
    # No feedback: SfM does not use the attitude, so its per-photo warnings would be noise here.
    photoset = read_photos(paths, require_gps=False, require_camera=False)
    photos = photoset.photos
    as_read = tuple(photos)
    contradicted = [p.image for p in photos if any(w.startswith("RtkFlag") for w in p.warnings)]
    position_file = None
    if positions is not None:
        position_file = read_positions(positions, photos, time_offset_s=positions_time_offset_s)
        photos = apply_positions(photos, position_file)
    for name, reason in photoset.skipped:
        fb.warning(f"skipped {name}: {reason}")
    timer.add("metadata", t0)
    if len(photos) < 3:
        raise InputError(f"SfM needs at least 3 readable photos, found {len(photos)}", path=images)
    root, names = _image_names(photos)
    early: list[str] = []
    if contradicted:
        early.append(
            f"{len(contradicted)} photo(s) state a fixed RTK solution with deviations of metres (weighed by the "
            "deviations): " + ", ".join(contradicted[:8]) + ("…" if len(contradicted) > 8 else "")
        )
    gcps, held_out = _read_gcps(gcp_list, checkpoints, photos, early)
    has_gps = sum(p.has_gps for p in photos)
    if has_gps < 3 and gcps is None and not local_frame:
        raise InputError(
            "fewer than 3 photos with GPS and no GCPs: the model would be arbitrary in scale, "
            "position and orientation; give a gcp_list.txt, or local_frame to accept that",
            path=images,
        )
    out_crs = _output_crs(crs, photos, gcps)
    priors, notes = _priors_for(photos, names, out_crs, takeoff_elevation_m, gcps)
    bodies = _bodies(photos)
    notes += _factory_calibration_notes(bodies)
    fb.info(
        f"{len(photos)} photos, {len(bodies)} camera bod{'y' if len(bodies) == 1 else 'ies'}: "
        + "; ".join(f"{b.label} ({len(b.photos)})" for b in bodies)
    )
    if len({(b.key[2], b.key[3]) for b in bodies}) > 1:
        notes.append("photos of several image sizes: each size is its own camera")
    return _Inputs(
        tuple(photos),
        tuple(photoset.skipped),
        root,
        names,
        gcps,
        frozenset(held_out),
        out_crs,
        priors,
        tuple(bodies),
        tuple([*(position_file.notes() if position_file is not None else []), *early, *notes]),
        position_file,
        as_read,
        takeoff_elevation_m,
        heights_of(crs) if crs is not None else None,
    )


#: The factory calibration's focal length and EXIF's may differ by this (%) before it is said.
FACTORY_VS_EXIF_PCT = 3.0


def _factory_calibration_notes(bodies: Sequence[_Body]) -> list[str]:
    """What each camera body starts from when its photos carry the maker's factory calibration."""
    out = []
    for b in bodies:
        p = b.photos[0]
        if not math.isfinite(p.factory_focal_px):
            continue
        line = (
            f"{b.label}: factory calibration as the starting intrinsics (focal length {p.factory_focal_px:.1f} px, "
            f"optical centre {p.factory_cx_px:.1f}, {p.factory_cy_px:.1f} px"
            + (", JPEG already undistorted" if p.dewarped else f", distortion {len(p.factory_distortion)} terms")
            + ")"
        )
        exif = p.exif_focal_px
        if math.isfinite(exif) and abs(p.factory_focal_px / exif - 1.0) * 100.0 > FACTORY_VS_EXIF_PCT:
            line += f"; EXIF's focal length gives {exif:.1f} px ({100.0 * (exif / p.factory_focal_px - 1.0):+.1f} %)"
        out.append(line)
    return out


#: Most photos stating a horizontal accuracy this good (m) make an RTK/PPK block: its GCPs check it.
RTK_BLOCK_SIGMA_M = 0.1


def _checkpoint_names(checkpoints: str, gcps: GcpSet | None, photos: Sequence[Photo], notes: list[str]) -> set[str]:
    """The GCPs held out as checkpoints: those named, ``all``, or ``none``; by default none, except
    in an RTK/PPK block (most photos to a decimetre or better), where every GCP checks the
    block the positions georeference."""
    text = checkpoints.strip()
    if text.lower() == "none":
        return set()
    if text.lower() == "all" or (not text and gcps is not None and _rtk_block(photos)):
        if gcps is None:
            raise InputError("checkpoints 'all' but no gcp_list is given")
        if not text:
            notes.append(
                "an RTK/PPK block: its GCPs are checkpoints, checking the georeference the photos' positions "
                "give (checkpoints 'none' to control the block with them)"
            )
        return set(gcps.by_name())
    held_out = {c.strip() for c in text.split(",") if c.strip()}
    if held_out and gcps is None:
        raise InputError("checkpoints are named but no gcp_list is given")
    return held_out


def _rtk_block(photos: Sequence[Photo]) -> bool:
    good = sum(math.isfinite(p.gps_sigma_h_m) and p.gps_sigma_h_m <= RTK_BLOCK_SIGMA_M for p in photos)
    return good >= 0.5 * max(len(photos), 1)


#: A time lag is taken when it exceeds this many of its standard errors, and this (s).
LAG_SIGMAS = 3.0
LAG_MIN_S = 0.002
LAG_MAX_S = 3.0


def _refine_time_lag(mapped: _Mapped, inputs: _Inputs, notes: list[str]) -> tuple[_Inputs, dict[str, Any] | None]:
    """A constant camera-to-GPS time lag, from the cameras' residuals along the trajectory's
    velocity: positions read ``lag`` too early put each camera ``velocity × lag`` behind its place
    on its path. The lag is measured on a copy of the block adjusted without the positions (a
    block held to wrong centimetre priors bends to them and hides most of it), fitted to the
    positions by a similarity, and the trajectory read again until the lag no longer moves; then
    the block is bundle-adjusted on the new positions. Without a positions file, the photos' own
    GPS (:func:`_lag_of_own_gps`); None with positions already at the exposures (events, a CSV)."""
    pf = inputs.positions
    if inputs.out_crs is None or len(inputs.priors.positions) < 5:
        return inputs, None
    if pf is None:
        return _lag_of_own_gps(mapped, inputs, notes)
    if pf.trajectory is None or pf.trajectory.is_events:
        return inputs, None  # positions at the exposures already (events, a CSV)
    free = _free_network(mapped.rec, refine_distortion=not mapped.distortion_held)
    to_crs = transformer(WGS84, inputs.out_crs)
    total, sigma, steps, priors, photos = 0.0, math.nan, 0, inputs.priors, inputs.photos
    while steps < 8:
        steps += 1
        if _align_to_gps(free, priors, 1.0)[0] is None:
            return inputs, None
        got = _lag_step(free, inputs, priors, pf, total, to_crs)
        if got is None:
            return inputs, None
        delta, sigma = got
        if abs(delta) <= max(LAG_SIGMAS * sigma, LAG_MIN_S) or abs(total + delta) > LAG_MAX_S:
            break
        total += delta
        photos = tuple(apply_positions(inputs.photos_as_read, pf.with_lag(inputs.photos_as_read, total)))
        fresh = _gps_priors(photos, inputs.names, inputs.out_crs, inputs.takeoff_elevation_m)
        shift = fresh.offset - inputs.priors.offset
        moved = {k: c + shift for k, c in fresh.positions.items()}
        priors = replace(fresh, offset=inputs.priors.offset, positions=moved)
    report = {"lag_s": round(total, 4), "sigma_s": round(sigma, 4), "iterations": steps, "applied": total != 0.0}
    if not total:
        notes.append(f"no camera-to-GPS time lag beyond ±{max(LAG_SIGMAS * sigma, LAG_MIN_S):.3f} s in {pf.path.name}")
        return inputs, report
    notes.append(
        f"camera-to-GPS time lag {total:+.3f} s (±{sigma:.3f}): the cameras lay along their paths from "
        f"{pf.path.name}'s positions; read again at it and bundle-adjusted on them"
    )
    inputs = replace(inputs, photos=photos, priors=priors)
    _align_to_gps(mapped.rec, priors, 1.0)
    _prior_bundle_adjustment(
        mapped.rec, priors, refine_focal=not mapped.focal_held, refine_distortion=not mapped.distortion_held
    )
    return inputs, report


def _free_network(rec: Any, refine_distortion: bool = True) -> Any:
    """A copy of the block bundle-adjusted on its photos alone (no position priors)."""
    pc = load_pycolmap()
    opts = _ba_options(refine_focal=False, refine_distortion=refine_distortion, iterations=FREE_NETWORK_ITERATIONS)
    return _adjusted_copy(rec, opts, pc.BundleAdjustmentGauge.THREE_POINTS)


#: The free network starts from the block the mapper adjusted: Ceres' 100 iterations spent most of
#: their time on steps it then refused (toledo: 31 solves for a 5e-5 cost change, 5.5-8.6 s); 10
#: left every camera centre within 0.02 mm of them in 4.4 s (5: 0.4 mm, 2.9 s). The lag it serves
#: is read from metres of GPS residuals.
FREE_NETWORK_ITERATIONS = 10


#: A consumer GPS's lag is taken when it moves the positions by this much (m) at the median speed,
#: and exceeds this (s): less is within its own noise.
OWN_GPS_LAG_MIN_M = 1.0
OWN_GPS_LAG_MIN_S = 0.1
#: A photo whose path turns more than this (deg) between its neighbours has no one velocity.
TURN_MAX_DEG = 30.0


def _own_gps_velocities(inputs: _Inputs) -> dict[str, np.ndarray]:
    """Each photo's velocity (m/s, local frame) from its neighbours' GPS positions and times, where
    the path runs straight through it (not at a turn) and the neighbours are within 10 s."""

    timed = sorted(
        (t, inputs.names[p.path])
        for p in inputs.photos
        if inputs.names[p.path] in inputs.priors.positions and math.isfinite(t := photo_seconds(p))
    )
    out: dict[str, np.ndarray] = {}
    for (t0, a), (t1, b), (t2, c) in zip(timed, timed[1:], timed[2:]):
        if not (0 < t1 - t0 <= 10.0 and 0 < t2 - t1 <= 10.0):
            continue
        pa, pb, pc_ = (inputs.priors.positions[n][:2] for n in (a, b, c))
        d1, d2 = pb - pa, pc_ - pb
        n1, n2 = float(np.linalg.norm(d1)), float(np.linalg.norm(d2))
        if n1 <= 0 or n2 <= 0 or math.degrees(math.acos(float(np.clip(d1 @ d2 / (n1 * n2), -1, 1)))) > TURN_MAX_DEG:
            continue
        out[b] = (pc_ - pa) / (t2 - t0)
    return out


def _lag_of_own_gps(mapped: _Mapped, inputs: _Inputs, notes: list[str]) -> tuple[_Inputs, dict[str, Any] | None]:
    """A lag between the photos' own GPS fixes and their exposures (a stale fix: the position of a
    moment before): the cameras of the block adjusted without the positions lie ``velocity × lag``
    ahead of them along the lines. When it is more than the GPS's noise, each position is moved
    by it before the georeference, and it is said."""
    velocity = _own_gps_velocities(inputs)
    if len(velocity) < 5:
        return inputs, None
    free = _free_network(mapped.rec, refine_distortion=not mapped.distortion_held)
    base = inputs.priors
    total, sigma, steps, priors = 0.0, math.nan, 0, base
    while steps < 6:
        steps += 1
        if _align_to_gps(free, priors, 2.0)[0] is None:
            return inputs, None
        centres = _centres(free)
        names = [n for n in velocity if n in centres]
        if len(names) < 5:
            return inputs, None
        rr = np.array([(centres[n] - priors.positions[n])[:2] for n in names])
        vv = np.array([velocity[n] for n in names])
        fitted = _lag_fit(rr, vv)
        if fitted is None:
            return inputs, None
        delta, sigma = fitted
        if abs(delta) <= max(LAG_SIGMAS * sigma, OWN_GPS_LAG_MIN_S) or abs(total + delta) > 10.0:
            break
        total += delta
        moved = {k: (c + np.r_[velocity[k] * total, 0.0]) if k in velocity else c for k, c in base.positions.items()}
        priors = replace(base, positions=moved)
    speed = float(np.median([np.linalg.norm(v) for v in velocity.values()]))
    report = {"lag_s": round(total, 3), "sigma_s": round(sigma, 3), "iterations": steps, "applied": False}
    if total == 0.0 or abs(total) * speed < OWN_GPS_LAG_MIN_M:
        return inputs, report
    report["applied"] = True
    notes.append(
        f"the photos' GPS fixes lag their exposures by {total:+.2f} s (±{sigma:.2f}; {abs(total) * speed:.1f} m "
        "along the lines at the median speed): each position moved along its line by it before the georeference"
    )
    return replace(inputs, priors=priors), report


def _lag_step(
    rec: Any, inputs: _Inputs, priors: _Priors, pf: PositionFile, lag_s: float, to_crs: Any
) -> tuple[float, float] | None:
    """The further lag (s) the residuals show along the velocities, and its standard error."""
    assert pf.trajectory is not None
    traj = pf.trajectory
    centres = _centres(rec)
    r, v = [], []
    for p in inputs.photos_as_read:
        name = inputs.names[p.path]
        t = pf.photo_times_s.get(p.image)
        if t is None or name not in centres or name not in priors.positions:
            continue
        a, b = traj.at(t + lag_s - 0.1), traj.at(t + lag_s + 0.1)
        if a is None or b is None:
            continue
        xa, ya = to_crs.transform(a.longitude_deg, a.latitude_deg)
        xb, yb = to_crs.transform(b.longitude_deg, b.latitude_deg)
        v.append([(xb - xa) / 0.2, (yb - ya) / 0.2])
        r.append((centres[name] - priors.positions[name])[:2])
    if len(r) < 5:
        return None
    return _lag_fit(np.array(r), np.array(v))


def _lag_fit(residuals: np.ndarray, velocity: np.ndarray) -> tuple[float, float] | None:
    """The lag (s) that best explains the residuals (n, 2; m) as ``velocity × lag`` (m/s), by least
    squares, and its standard error; None when nothing moves."""
    vv2 = float((velocity**2).sum())
    if vv2 <= 0:
        return None
    delta = float((residuals * velocity).sum() / vv2)
    spread = float(((residuals - delta * velocity) ** 2).sum()) / max(2 * len(residuals) - 1, 1)
    return delta, math.sqrt(spread / vv2)


def _prior_bundle_adjustment(rec: Any, priors: _Priors, refine_focal: bool, refine_distortion: bool = True) -> None:
    """A bundle adjustment of every registered photo with its position prior (its own covariance)."""
    pc = load_pycolmap()
    cfg = pc.BundleAdjustmentConfig()
    pose_priors = []
    for iid in rec.reg_image_ids():
        im = rec.image(iid)
        cfg.add_image(iid)
        pos = priors.positions.get(im.name)
        if pos is None:
            continue
        h, v = priors.sigmas.get(im.name, (2.0, 4.0))
        pose_priors.append(
            pc.PosePrior(
                corr_data_id=im.data_id,
                position=np.asarray(pos, float),
                position_covariance=np.diag([h**2, h**2, v**2]),
                coordinate_system=pc.PosePriorCoordinateSystem.CARTESIAN,
            )
        )
    opts = _ba_options(refine_focal=refine_focal, refine_distortion=refine_distortion)
    pc.create_pose_prior_bundle_adjuster(opts, pc.PosePriorBundleAdjustmentOptions(), cfg, pose_priors, rec).solve()


#: GCPs farther than this from every photo's GPS (and than the flight's size) are not of this flight.
GCP_FAR_M = 1000.0


def _check_gcps_near_photos(gcps: GcpSet, priors: _Priors, crs: Any) -> None:
    """Refuse GCPs that lie kilometres from the photos' GPS positions: the model would follow
    them there (a wrong CRS line, a wrong UTM zone, another site's file), silently."""
    pos = np.array(list(priors.positions.values()))[:, :2] + priors.offset[:2]
    t = transformer(gcps.crs, crs)
    gxy = np.array(t.transform([g.x for g in gcps.points], [g.y for g in gcps.points])).T
    if not np.isfinite(gxy).all():
        raise InputError(f"the GCPs cannot be placed in {crs_to_text(crs)}: is the file's CRS right?", path=gcps.path)
    nearest = np.min(np.linalg.norm(gxy[:, None, :] - pos[None, :, :], axis=2), axis=1)
    size = float(np.linalg.norm(pos.max(axis=0) - pos.min(axis=0)))
    if nearest.min() > max(GCP_FAR_M, size):
        raise InputError(
            f"the nearest GCP is {nearest.min() / 1000:,.1f} km from the photos' GPS positions (the flight is "
            f"{size:,.0f} m across): is the GCP file's CRS right ({crs_to_text(gcps.crs)})? is it this site's file?",
            path=gcps.path,
        )


@dataclass(frozen=True)
class _Mapped:
    """The mapper's answer: the largest model, and what became of every photo."""

    rec: Any  # pycolmap.Reconstruction (georeferenced in place by the next stages)
    n_models: int
    registered: frozenset[str]
    unregistered: dict[str, str]  # image name -> why
    matching: str  # how pairs were chosen
    focal_held: bool
    focal_prior: dict[int, float]  # camera id -> the focal length (px) it started from
    notes: tuple[str, ...]
    submodel: dict[str, int] = field(default_factory=dict)  # split-merge: image name -> its submodel
    profile: dict[str, Any] = field(default_factory=dict)  # where mapping spent its time (one block)
    # camera id -> (mean reprojection px with its lens distortion refined, with it held at zero)
    distortion_test: dict[int, tuple[float, float]] = field(default_factory=dict)
    # Cameras whose distortion stays at zero from here. COLMAP holds distortion for a whole
    # adjustment, not per camera: when any is held, the later adjustments hold every camera's at
    # the value the mapping gave it (the others' were refined there already).
    distortion_held: frozenset[int] = frozenset()
    # split-merge: camera id -> its submodels' tests of its lens distortion, when they all agree
    # (held at zero or refined); the merged block takes their answer instead of testing again
    distortion_decided: dict[int, tuple[bool, tuple[float, float], int]] = field(default_factory=dict)


def _reconstruct(
    inputs: _Inputs,
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
    timer: _Timer,
    fb: Feedback,
) -> _Mapped:
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
    ill = _ill_conditioned(photos, priors)
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
    focal_prior = {cid: _prior_focal(db, cid, _focal_px(cam)) for cid, cam in rec.cameras.items()}
    return _Mapped(
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


def _split_reconstruct(
    inputs: _Inputs,
    output: Path,
    split: int,
    overlap_m: float,
    sub_kwargs: dict[str, Any],
    timer: _Timer,
    fb: Feedback,
) -> tuple[_Mapped, list[dict[str, Any]]]:
    """Split-merge (:mod:`geoortho.reconstruction.splitmerge`): submodels by position, each reconstructed by
    :func:`sfm` into ``output/submodels`` (kept: a rerun reuses the ones finished), merged into one
    model for the georeferencing that follows."""

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
    body_of = {inputs.names[p.path]: b.label for b in _bodies(inputs.photos) for p in b.photos}
    rec, left_out, stats, came_from = merge(subs, home_of, inputs.priors.offset, fb, body_of)
    for n in path_of:
        if n not in home_of:
            left_out.setdefault(n, "no GPS position: split-merge cannot place it in a submodel")
    timer.add("merge", t0)
    if rec.num_reg_images() < 3:
        raise InputError("no submodel could be reconstructed and merged (see the warnings)", path=inputs.root)
    registered = frozenset(rec.image(i).name for i in rec.reg_image_ids())
    focal = {cid: _focal_px(cam) for cid, cam in rec.cameras.items()}
    how = f"split-merge: {len(groups)} submodels of at most {split} photos, {overlap_m:g} m overlap"
    notes = [f"{how}; {sum(s.ok for s in subs)} reconstructed"]
    decided = _submodels_lens_decisions(rec, [s for s in subs if s.ok])
    return _Mapped(
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


@dataclass(frozen=True)
class _Georeference:
    """How the model was put in the CRS, and the GCPs' state after it."""

    how: str
    gps_sim: Any  # the GPS similarity applied, or None
    tilt_deg: float  # the model's vertical against the photos' gravity (NaN: not measured)
    states: tuple[_GcpState, ...] = ()
    heights_usable: bool = True  # GCP heights are surveyed, not placeholders
    gcp_obs_used: int = 0  # GCP observations held fixed in the bundle adjustment
    notes: tuple[str, ...] = ()
    gcp_vs_gps: dict[str, Any] | None = None  # what the GCPs changed of the GPS georeference
    heights: Any = None  # the datum of the model's heights (:func:`_heights_datum`), None: not known
    heights_from: str = ""  # where it was learnt, or what to give


def _georeference_by_gps(rec: Any, inputs: _Inputs, gps_sigma_m: float) -> _Georeference:
    """Similarity onto the GPS positions; levelled from the gimbals when GPS heights are not trusted."""
    priors = inputs.priors
    if not priors.positions:
        return _Georeference("none (local frame)", None, math.nan)
    by_name = {inputs.names[p.path]: p for p in inputs.photos}
    notes: list[str] = []
    georef, gps_sim, tilt = "none (local frame)", None, math.nan
    if len(priors.sigmas) >= 0.5 * len(priors.positions):  # most photos state their accuracy (RTK/PPK)
        gps_sigma_m = priors.sigma_h_typical(gps_sigma_m)
    if priors.vertical_trusted:
        gps_sim, n_gps = _align_to_gps(rec, priors, gps_sigma_m)
        tilt = _tilt_deg(rec, by_name) if gps_sim is not None else math.nan
        if gps_sim is not None:
            georef = f"GPS of {n_gps} photos"
        # The GPS heights may still be wrong in a way no trend shows: a model they tilt
        # away from the gravity the gimbals saw is put on the GPS horizontally instead.
        # (without a recorded pitch and roll the nadir assumed is no gravity to hold them against)
        if math.isfinite(tilt) and tilt > MAX_TILT_DEG and _attitude_recorded(list(by_name.values())):
            notes.append(
                f"the GPS heights tilt the model {tilt:.1f} deg from the photos' vertical: "
                "GPS heights not trusted, model levelled from the photos' attitude"
            )
            gps_sim = None
    if gps_sim is None and (not priors.vertical_trusted or math.isfinite(tilt)):
        gps_sim, levelled = _align_horizontal(rec, priors, by_name, gps_sigma_m, notes)
        if gps_sim is not None:
            georef = (
                f"GPS of {len(priors.positions)} photos horizontally, levelled {levelled}, "
                "height from the median GPS altitude"
            )
            tilt = _tilt_deg(rec, by_name)
    if gps_sim is None:
        notes.append("the GPS positions did not fit the model (fewer than 3 consistent photos)")
    outliers = _gps_outliers(rec, priors) if gps_sim is not None else []
    if outliers:
        notes.append(
            f"{len(outliers)} photo(s) with GPS positions far off the model: "
            + ", ".join(outliers[:5])
            + ("…" if len(outliers) > 5 else "")
        )
    return _Georeference(georef, gps_sim, tilt, notes=tuple(notes))


def _georeference_by_gcps(
    rec: Any,
    inputs: _Inputs,
    registered: frozenset[str],
    gps: _Georeference,
    fb: Feedback,
    refine_distortion: bool = True,
) -> _Georeference:
    """Triangulate the GCPs; with 3 control GCPs, align onto them and bundle-adjust with them fixed."""
    if inputs.gcps is None:
        return gps
    notes = list(gps.notes)
    georef, gcp_obs_used, heights_usable = gps.how, 0, True
    states = _gcp_states(inputs.gcps, inputs.out_crs, inputs.priors.offset, set(inputs.held_out), set(registered), fb)
    zs = np.array([s.surveyed[2] for s in states])
    if heights_are_placeholders(zs):
        heights_usable = False
        notes.append(
            f"all GCP heights are {zs[0] + inputs.priors.offset[2]:g}: taken as placeholders; "
            "GCPs control the model horizontally only and their Z residuals are not reported"
        )
    _triangulate(rec, states)
    swapped = _swapped_pair(states, heights_usable)
    if swapped is not None:
        # Controlled by a mixed-up pair the model would bend (turned 180 deg on a 4-GCP block):
        # the pair checks instead, and the rest control if they are still 3.
        for st in states:
            if st.name in swapped["names"]:
                st.role = "checkpoint"
    gcp_sim = _align_to_gcps(rec, states, heights_usable)
    effect: dict[str, Any] | None = None
    if gcp_sim is not None and gps.gps_sim is not None:
        effect = _gcp_effect(rec, gcp_sim)
        if abs(effect["scale_change_pct"]) > GCP_SCALE_CHANGE_PCT or effect["rotation_deg"] > GCP_ROTATION_DEG:
            notes.append(
                f"the GCPs rescaled the GPS-georeferenced model by {effect['scale_change_pct']:+.1f} % and turned it "
                f"{effect['rotation_deg']:.2f} deg (moving the site's edge {effect['edge_shift_m']:.2f} m): check the "
                "GCPs' CRS and coordinates, or the photos' GPS"
            )
            fb.warning(notes[-1])
        cause = _shift_cause(effect, inputs, heights_usable and gps.how.startswith("GPS of"))
        if cause:
            effect["likely_cause"] = cause
            notes.append(cause)
            fb.warning(cause)
    if swapped is not None:
        effect = dict(effect or {})
        effect["swapped"] = swapped
        effect["likely_cause"] = (
            f"GCPs {swapped['names'][0]} and {swapped['names'][1]} look swapped: exchanged, their fit's RMSE "
            f"falls from {swapped['rmse_m']:.2f} m to {swapped['rmse_if_exchanged_m']:.2f} m; they are held out "
            "as checkpoints (check their names in the GCP file)"
        )
        notes.append(effect["likely_cause"])
        fb.warning(effect["likely_cause"])
    if gcp_sim is not None:
        georef = (
            f"{sum(s.role == 'control' and s.triangulated is not None for s in states)} GCPs"
            + (" (horizontally; heights from GPS)" if not heights_usable else "")
            + (f" after {georef}" if gps.gps_sim is not None else "")
        )
        if heights_usable:
            _triangulate(rec, states)
            gcp_obs_used = _gcp_bundle_adjust(rec, states, refine_distortion)
            if gcp_obs_used:
                georef += f"; bundle adjustment with {gcp_obs_used} GCP observations fixed"
    else:
        n_ok = sum(s.role == "control" and s.triangulated is not None for s in states)
        notes.append(f"only {n_ok} control GCP(s) triangulated (3 needed): GCPs not used for control")
    _triangulate(rec, states)
    return _Georeference(
        georef, gps.gps_sim, gps.tilt_deg, tuple(states), heights_usable, gcp_obs_used, tuple(notes), effect
    )


#: GCPs that change the GPS georeference's scale or rotation more than this are said (issue 48).
GCP_SCALE_CHANGE_PCT = 1.0
GCP_ROTATION_DEG = 0.5


#: A GCP georeference this far (horizontally) from the GPS's is not the GPS's bias (a few metres on
#: consumer drones) but a wrong CRS or datum of the GCP file (issue 48).
GCP_SHIFT_WARN_M = 30.0


def _shift_cause(effect: dict[str, Any], inputs: _Inputs, heights_compared: bool) -> str:
    """Name what a large shift between the GPS and the GCP georeference most likely is: the GCP
    file's CRS (horizontal), or heights in another vertical datum (the geoid's undulation here)."""
    h, v = float(effect["shift_horizontal_m"]), float(effect["shift_vertical_m"])
    if h > GCP_SHIFT_WARN_M:
        far = f"{h / 1000:.1f} km" if h >= 1000 else f"{h:.0f} m"
        return (
            f"the GCPs put the block {far} from where its photos' GPS puts it: the GCP file's CRS "
            f"({inputs.gcps.crs.name if inputs.gcps is not None else '?'}) is likely not the one its "
            "coordinates are in"
        )
    if not heights_compared or inputs.out_crs is None or abs(v) < 10.0:
        return ""

    lon, lat = transformer(inputs.out_crs, WGS84).transform(*inputs.priors.offset[:2])
    n = float(geoid_undulation_m(lon, lat))
    if abs(abs(v) - abs(n)) < 5.0 and abs(n) > 10.0:
        return (
            f"the GCPs move the block {v:+.1f} m vertically against the GPS heights, as the geoid's undulation "
            f"here ({n:+.1f} m): the GCP heights are likely in another vertical datum than the CRS says "
            "(orthometric against ellipsoidal)"
        )
    return ""


def _swapped_pair(states: list[_GcpState], heights_usable: bool) -> dict[str, Any] | None:
    """Two control GCPs whose surveyed coordinates, exchanged, fit their triangulated positions far
    better: a swapped pair of names in the GCP file (a common field mistake)."""
    pc = load_pycolmap()
    use = [s for s in states if s.role == "control" and s.triangulated is not None]
    if len(use) < 4:  # with 3 a similarity bends to almost any labelling
        return None
    src = np.array([s.triangulated for s in use], dtype=float)
    tgt = np.array([s.surveyed for s in use], dtype=float)
    if not heights_usable:
        src, tgt = src[:, :2], tgt[:, :2]

    def rmse(t: np.ndarray) -> float:
        a, b = (src, t) if src.shape[1] == 3 else (np.c_[src, np.zeros(len(src))], np.c_[t, np.zeros(len(t))])
        sim = pc.estimate_sim3d(a, b)
        if sim is None:
            return math.inf
        m = np.asarray(sim.matrix())
        return float(np.sqrt(np.mean(np.sum((a @ m[:, :3].T + m[:, 3] - b) ** 2, axis=1))))

    base = rmse(tgt)
    if not math.isfinite(base) or base < 0.05:  # GCPs that fit to 5 cm are not mixed up
        return None
    best = (math.inf, -1, -1)
    for i in range(len(use)):
        for j in range(i + 1, len(use)):
            t = tgt.copy()
            t[[i, j]] = t[[j, i]]
            best = min(best, (rmse(t), i, j))
    if best[0] > 0.25 * base:
        return None
    return {
        "names": [use[best[1]].name, use[best[2]].name],
        "rmse_m": round(base, 4),
        "rmse_if_exchanged_m": round(best[0], 4),
    }


def _gcp_effect(rec: Any, sim: Any) -> dict[str, Any]:
    """What the GCPs' similarity did to the GPS-georeferenced model: its scale change, its rotation,
    and how far these two (not the shift, the GPS's own bias) moved the camera farthest from the
    block's middle (the site's edge)."""
    rot = np.asarray(sim.rotation.matrix())
    angle = math.degrees(math.acos(float(np.clip((np.trace(rot) - 1.0) / 2.0, -1.0, 1.0))))
    centres = np.array(list(_centres(rec).values())).reshape(-1, 3)  # already moved by ``sim``
    inv = sim.inverse()
    before = np.array([inv * c for c in centres]) if len(centres) else centres
    moved = (centres - centres.mean(axis=0)) - (before - before.mean(axis=0)) if len(centres) else centres
    shift = float(np.linalg.norm(moved, axis=1).max()) if len(centres) else math.nan
    middle = centres.mean(axis=0) - before.mean(axis=0) if len(centres) else np.full(3, math.nan)
    return {
        "scale_change_pct": round((float(sim.scale) - 1.0) * 100.0, 4),
        "rotation_deg": round(angle, 4),
        "edge_shift_m": round(shift, 4),
        # where the GCPs moved the block's middle from the GPS's place (a GPS bias of a few metres,
        # or a wrong CRS/datum of the GCP file)
        "shift_horizontal_m": round(float(np.hypot(middle[0], middle[1])), 3),
        "shift_vertical_m": round(float(middle[2]), 3),
    }


def _heights_datum(inputs: _Inputs, geo: _Georeference) -> tuple[Any, str]:
    """The datum of the model's heights (a vertical CRS, :data:`ELLIPSOIDAL`, or None: not
    known) and where it was learnt. The model takes its heights from the GCPs when they control
    them, else from the photos' positions."""
    if inputs.out_crs is None:
        return None, "a local frame"
    example = f"e.g. {crs_to_text(inputs.out_crs)}+5773 for EGM96 heights"  # this survey's own grid
    gcps = inputs.gcps
    if gcps is not None and geo.heights_usable and "GCP" in geo.how and any(s.role == "control" for s in geo.states):
        stated = heights_of(gcps.crs)
        if stated is not None:
            return stated, f"the GCP file's CRS ({gcps.crs.name})"
        if inputs.heights_given is not None:
            return inputs.heights_given, "--crs (the GCP heights taken to be in it)"
        return None, (
            f"the GCP file's CRS ({gcps.crs.name}) names no vertical datum: give the GCPs' CRS with "
            f"their heights' datum ({example}), or --crs so"
        )
    if inputs.heights_given is not None:
        return inputs.heights_given, "--crs (the positions' heights taken to be in it, as given)"
    if inputs.positions is not None and inputs.priors.vertical_trusted:
        return ELLIPSOIDAL, f"the positions file {inputs.positions.path.name} (heights above the WGS 84 ellipsoid)"
    return None, (
        "the photos' GNSS heights, whose datum the tags do not state: give GCPs in a compound CRS "
        f"({example}), or --crs with a vertical part"
    )


def _write_model(
    output: Path, work: Path, db: Path, mapped: _Mapped, inputs: _Inputs, geo: _Georeference, notes: list[str]
) -> int:
    """The COLMAP model (+ georeference.json), the database, points.laz and cameras.gpkg; the points written."""
    rec, priors = mapped.rec, inputs.priors
    model_dir = output / "model"
    tmp_model = work / "model"
    tmp_model.mkdir()
    rec.write(tmp_model)
    write_json(
        tmp_model / "georeference.json",
        {
            "crs": inputs.crs_text,
            "vertical_crs": heights_to_text(geo.heights),
            "vertical_crs_from": geo.heights_from,
            "offset": priors.offset.tolist(),
            "note": "model coordinates + offset = coordinates in crs; heights in vertical_crs (null: not known)",
        },
    )
    if model_dir.exists():
        shutil.rmtree(model_dir)
    os.replace(tmp_model, model_dir)
    if db.exists():  # (a merged split model has none: its submodels had one each)
        os.replace(db, output / "database.db")
    if inputs.out_crs is None:
        notes.append("no CRS: points.laz and cameras.gpkg are not written (local frame only)")
        return 0
    n_points = _write_points(output / "points.laz", rec, priors.offset, with_heights(inputs.out_crs, geo.heights))
    _write_cameras(
        output / "cameras.gpkg",
        rec,
        inputs.photos,
        inputs.names,
        priors,
        inputs.out_crs,
        mapped.unregistered,
        mapped.submodel,
    )
    return n_points


@dataclass(frozen=True)
class _Figures:
    """The accuracy figures of the georeferenced model."""

    gcp_rows: list[dict[str, Any]]
    control: dict[str, Any] | None
    check: dict[str, Any] | None
    mean_reprojection_px: float


def _figures(rec: Any, inputs: _Inputs, geo: _Georeference) -> _Figures:
    rows = _residual_table(list(geo.states), geo.heights_usable)
    return _Figures(rows, _accuracy(rows, "control"), _accuracy(rows, "checkpoint"), _mean_reprojection_px(rec))


def _report(
    inputs: _Inputs,
    mapped: _Mapped,
    geo: _Georeference,
    figures: _Figures,
    intrinsics: list[dict[str, Any]],
    mapper: str,
    timer: _Timer,
    t_start: float,
    notes: list[str],
) -> dict[str, Any]:
    rec = mapped.rec
    return {
        "photos": len(inputs.photos) + len(inputs.skipped),
        "photos_read": len(inputs.photos),
        "registered": len(mapped.registered),
        "unregistered": mapped.unregistered,
        "skipped": dict(inputs.skipped),
        "camera_bodies": [{"camera": b.label, "photos": len(b.photos)} for b in inputs.bodies],
        "cameras": [_camera_record(c) for c in rec.cameras.values()],
        "matching": mapped.matching,
        "mapper": mapper,
        "models": mapped.n_models,
        "points": rec.num_points3D(),
        "mean_reprojection_error_px": figures.mean_reprojection_px,
        "mean_track_length": float(rec.compute_mean_track_length()),
        "mapping_profile": mapped.profile,
        "gsd_cm": _gsd_m(rec) * 100.0,
        "crs": inputs.crs_text,
        "vertical_crs": heights_to_text(geo.heights),
        "vertical_crs_from": geo.heights_from,
        "offset": inputs.priors.offset.tolist(),
        "heights": inputs.priors.heights,
        "vertical_gps_trusted": inputs.priors.vertical_trusted,
        "model_tilt_deg": None if not math.isfinite(geo.tilt_deg) else round(geo.tilt_deg, 3),
        "gcp_vs_gps": geo.gcp_vs_gps,
        # the other prior of the vertical: how far the camera centres' plane is from level
        "camera_plane_tilt_deg": _plane_tilt(rec),
        "intrinsics": intrinsics,
        "georeferenced_by": geo.how,
        "gps": _gps_residuals(rec, inputs.priors),
        "gcps": figures.gcp_rows,
        "gcp_accuracy": figures.control,
        "checkpoint_accuracy": figures.check,
        "ce90_le90": "NSSDA from RMSE: CE90 = 2.1460·sqrt((RMSEx²+RMSEy²)/2), LE90 = 1.6449·RMSEz",
        "seconds": {k: round(v, 2) for k, v in timer.stages.items()}
        | {"total": round(time.perf_counter() - t_start, 2)},
        "notes": notes,
    }


def _announce(
    notes: list[str],
    mapped: _Mapped,
    inputs: _Inputs,
    geo: _Georeference,
    figures: _Figures,
    n_points: int,
    fb: Feedback,
) -> None:
    for n in notes:
        # what the heights are is information; every other note is a condition to look at
        (fb.info if n.startswith("heights:") else fb.warning)(n)
    fb.info(
        f"registered {len(mapped.registered)}/{len(inputs.photos)} photos, {n_points} points, "
        f"reprojection {figures.mean_reprojection_px:.2f} px; georeferenced by {geo.how}"
    )
    check = figures.check
    if check:
        fb.info(
            f"checkpoints: RMSE horizontal {check['rmse_horizontal_m']:.3f} m"
            + (f", vertical {check['rmse_z_m']:.3f} m" if check["rmse_z_m"] is not None else "")
        )


def _prior_focal(db: Path, camera_id: int, fallback: float) -> float:
    """The focal length (px) the camera started from: the database keeps the imported value."""
    pc = load_pycolmap()
    try:
        with pc.Database.open(db) as d:
            cam = d.read_camera(camera_id)
            return float(cam.params[cam.focal_length_idxs()[0]])
    except Exception:  # noqa: BLE001 - an old database layout: the mapped value is all there is
        return fallback


def _intrinsics_report(mapped: _Mapped, gcp_obs: int, notes: list[str]) -> list[dict[str, Any]]:
    """Per camera: the EXIF focal length (px), the final one, the drift in percent; with the focal
    held, the drift a free self-calibration would have reached (measured on a copy); the test of
    its lens distortion (reprojection with it refined and held at zero) and whether it was held."""
    rec, focal_prior = mapped.rec, mapped.focal_prior
    drift = _focal_drift(rec, focal_prior)
    free = (
        _probe_free_focal(rec, refine_distortion=not mapped.distortion_held)
        if mapped.focal_held and not gcp_obs
        else {}
    )
    out = []
    for cid, cam in rec.cameras.items():
        row: dict[str, Any] = {
            "camera_id": int(cid),
            "focal_exif_px": focal_prior.get(cid),
            "focal_px": _focal_px(cam),
            "focal_drift_pct": drift.get(cid),
        }
        if cid in mapped.distortion_test:
            with_px, without_px = mapped.distortion_test[cid]
            row["distortion"] = {
                "reprojection_px_refined": round(with_px, 4),
                "reprojection_px_held_at_zero": round(without_px, 4),
                "held_at_zero": cid in mapped.distortion_held,
            }
        if cid in free and focal_prior.get(cid):
            row["free_focal_drift_pct"] = 100.0 * (free[cid] / focal_prior[cid] - 1.0)
            if abs(row["free_focal_drift_pct"]) > FOCAL_DRIFT_WARN_PCT:
                notes.append(
                    f"camera {cid}: self-calibration would move the focal length "
                    f"{row['free_focal_drift_pct']:+.1f} % off its starting value (EXIF's, or the factory "
                    "calibration's; not applied: ill-conditioned block; GCPs with heights would settle it)"
                )
        d = drift.get(cid)
        if d is not None and abs(d) > FOCAL_DRIFT_WARN_PCT:
            notes.append(
                f"camera {cid}: focal length {d:+.1f} % off the EXIF value "
                + (
                    "(GCP bundle adjustment)"
                    if gcp_obs
                    else "(self-calibration: check the EXIF focal length or the block geometry)"
                )
            )
        out.append(row)
    return out


def _rmse3(acc: dict[str, Any] | None) -> float:
    if not acc:
        return math.nan
    v = acc.get("rmse_3d_m")
    return float(v) if v is not None else float(acc["rmse_horizontal_m"])


def _camera_record(cam: Any) -> dict[str, Any]:
    return {
        "camera_id": int(cam.camera_id),
        "model": cam.model_name,
        "width": int(cam.width),
        "height": int(cam.height),
        "params": [float(v) for v in cam.params],
        "params_info": cam.params_info,
    }


#: A photo whose position is off the model by more than this many of its stated sigmas (per axis;
#: horizontally the distance against sqrt(2) sigma) is named; and by at least this much (m): the
#: model itself is no better than a centimetre or two.
ACCURACY_OUTLIER_SIGMAS = 3.0
ACCURACY_FLOOR_M = 0.05


def gps_accuracy(rec: Any, priors: _Priors, notes: list[str]) -> dict[str, Any] | None:
    """Each stated position accuracy against the bundle-adjusted camera: per class (fixed, float,
    single, stated) the photos, their median stated sigma and the residuals measured; the photos
    off their stated accuracy (a fix lost at a turn), named in ``notes`` too. None when no photo
    states its accuracy (consumer GPS)."""
    if not priors.sigmas:
        return None
    centres = _centres(rec)
    classes: dict[str, dict[str, Any]] = {}
    off: list[dict[str, Any]] = []
    for name, (sh, sv) in sorted(priors.sigmas.items()):
        fix = priors.fixes.get(name, "stated")
        entry = classes.setdefault(fix, {"photos": [], "sigma_h_m": [], "sigma_v_m": [], "dh_m": [], "dv_m": []})
        entry["photos"].append(name)
        entry["sigma_h_m"].append(sh)
        entry["sigma_v_m"].append(sv)
        if name not in centres or name not in priors.positions:
            continue
        d = centres[name] - priors.positions[name]
        dh, dv = float(np.hypot(d[0], d[1])), float(abs(d[2]))
        entry["dh_m"].append(dh)
        entry["dv_m"].append(dv)
        vertical_off = priors.vertical_trusted and dv > max(ACCURACY_OUTLIER_SIGMAS * sv, ACCURACY_FLOOR_M)
        if dh > max(ACCURACY_OUTLIER_SIGMAS * math.sqrt(2.0) * sh, ACCURACY_FLOOR_M) or vertical_off:
            off.append({"image": name, "fix": fix, "sigma_h_m": sh, "sigma_v_m": sv, "dh_m": dh, "dv_m": dv})
    table: dict[str, dict[str, Any]] = {}
    for fix, e in classes.items():
        dhs, dvs = np.array(e["dh_m"]), np.array(e["dv_m"])
        table[fix] = {
            "photos": len(e["photos"]),
            "sigma_h_m": float(np.median(e["sigma_h_m"])),
            "sigma_v_m": float(np.median(e["sigma_v_m"])),
            # per axis, as the sigma is stated: the horizontal distance's RMS over sqrt(2)
            "rmse_h_m": float(np.sqrt(np.mean(dhs**2) / 2.0)) if len(dhs) else None,
            "rmse_v_m": float(np.sqrt(np.mean(dvs**2))) if len(dvs) else None,
            "images": e["photos"] if fix != "fixed" else [],
        }
    n_consumer = len(priors.positions) - len(priors.sigmas)
    counts = ", ".join(f"{t['photos']} {fix}" for fix, t in sorted(table.items(), key=lambda kv: -kv[1]["photos"]))
    notes.append(
        f"positions weighted by their stated accuracy: {counts}"
        + (f"; {n_consumer} consumer GPS at the survey's gps_sigma_m" if n_consumer > 0 else "")
    )
    for fix in ("float", "single"):
        if fix in table:
            names = table[fix]["images"]
            notes.append(
                f"{len(names)} photo(s) without a fixed RTK solution ({fix}, stated "
                f"{table[fix]['sigma_h_m']:.2f} m): weighted by it: "
                + ", ".join(names[:8])
                + ("…" if len(names) > 8 else "")
            )
    if off:
        notes.append(
            f"{len(off)} photo(s) off their stated position accuracy (a fix lost or stale), held loosely by the "
            "robust prior: "
            + ", ".join(
                f"{o['image']} ({o['fix']}, stated {o['sigma_h_m']:.2f} m, off {o['dh_m']:.2f} m)" for o in off[:5]
            )
            + ("…" if len(off) > 5 else "")
        )
    return {"classes": table, "off_stated_accuracy": off, "consumer": n_consumer}


def _gps_residuals(rec: Any, priors: _Priors) -> dict[str, Any] | None:
    """Camera centre − GPS position, as ODM's report gives it (the GPS are not truth)."""
    c = _centres(rec)
    d = np.array([c[n] - priors.positions[n] for n in c if n in priors.positions])
    if len(d) == 0:
        return None
    out: dict[str, Any] = {
        "n": len(d),
        "mean_m": d.mean(axis=0).tolist(),
        "rmse_m": np.sqrt((d**2).mean(axis=0)).tolist(),
        "ce90_m": ce90(d[:, 0], d[:, 1]),
        "le90_m": le90(d[:, 2]),
    }
    names = [n for n in c if n in priors.positions]
    out.update(_gps_fit_spread(np.array([c[n][:2] for n in names]), np.array([priors.positions[n][:2] for n in names])))
    return out


def _similarity_2d(a: np.ndarray, b: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Least-squares similarity ``b ≈ s R a + t`` in the plane (Umeyama): scale, rotation, shift."""
    ma, mb = a.mean(axis=0), b.mean(axis=0)
    aa, bb = a - ma, b - mb
    u, sv, vt = np.linalg.svd(bb.T @ aa / len(a))
    flip = np.diag([1.0, float(np.sign(np.linalg.det(u @ vt)) or 1.0)])
    rot = u @ flip @ vt
    var = float((aa**2).sum() / len(a))
    scale = float(np.trace(np.diag(sv) @ flip)) / var if var > 0 else 1.0
    return scale, rot, mb - scale * rot @ ma


#: Bootstrap draws of the GPS fit's spread (rotation and scale the GPS scatter allows).
GPS_BOOTSTRAP = 200


def _gps_fit_spread(model_xy: np.ndarray, gps_xy: np.ndarray) -> dict[str, Any]:
    """How well the GPS fixes the georeference (the model is on the robust fit): the share of photos
    that fit it, the least-squares fit to all of them (its rotation, scale and how far it would move
    the site's edge from the robust one: a fit dragged by bad fixes), and the rotation and scale
    spread the inliers' scatter allows (bootstrap)."""
    if len(model_xy) < 5 or float(np.ptp(model_xy, axis=0).max()) <= 0:
        return {}
    d = np.hypot(*(model_xy - gps_xy).T)
    sigma = 1.4826 * float(np.median(np.abs(d - np.median(d))))
    inlier = d <= max(3.0, float(np.median(d)) + 4.0 * sigma)
    scale, rot, shift = _similarity_2d(model_xy, gps_xy)
    moved = (scale * model_xy @ rot.T + shift) - model_xy
    out: dict[str, Any] = {
        "inlier_share": round(float(inlier.mean()), 4),
        "lsq_rotation_deg": round(math.degrees(math.atan2(rot[1, 0], rot[0, 0])), 4),
        "lsq_scale_change_pct": round((scale - 1.0) * 100.0, 4),
        "robust_vs_lsq_m": round(float(np.hypot(*moved.T).max()), 4),
    }
    idx = np.flatnonzero(inlier)
    if len(idx) >= 5:
        rng = np.random.default_rng(0)
        angles, scales = [], []
        for _ in range(GPS_BOOTSTRAP):
            pick = rng.choice(idx, len(idx))
            if float(np.ptp(model_xy[pick], axis=0).max()) <= 0:
                continue
            s_, r_, _ = _similarity_2d(model_xy[pick], gps_xy[pick])
            angles.append(math.degrees(math.atan2(r_[1, 0], r_[0, 0])))
            scales.append((s_ - 1.0) * 100.0)
        out["rotation_sd_deg"] = round(float(np.std(angles)), 4)
        out["scale_sd_pct"] = round(float(np.std(scales)), 4)
    return out


def _output_crs(crs: CRS | None, photos: Sequence[Photo], gcps: GcpSet | None) -> CRS | None:
    """The model's map grid: horizontal (a compound CRS's vertical part is the heights' datum,
    :func:`_heights_datum`). A given CRS is a map grid: the faces that parse it say so."""
    if crs is not None:
        return horizontal_of(crs)
    if gcps is not None and gcps.crs.is_projected:
        return horizontal_of(gcps.crs)
    if any(p.has_gps for p in photos):
        return working_crs([p for p in photos if p.has_gps])
    if gcps is not None:
        g = gcps.points[0]
        lon, lat = transformer(gcps.crs, WGS84).transform(g.x, g.y)

        return utm_crs_for(lon, lat)
    return None
