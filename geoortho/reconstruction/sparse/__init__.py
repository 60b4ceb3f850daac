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

The algorithm is here; its steps are the modules beside it, each importing only those before it:
:mod:`.inputs` (photos, camera bodies, GPS priors, GCPs, the output CRS), :mod:`.adjust` (what
the steps after mapping share), :mod:`.mapping` (the pycolmap stages and split-merge),
:mod:`.lens` (the lens test), :mod:`.timelag` (the camera-to-GPS lag), :mod:`.georef` (onto the
GPS or the GCPs), :mod:`.report` and :mod:`.outputs`.
"""

from __future__ import annotations

import shutil
import tempfile
import time
from pathlib import Path
from typing import Any

from pyproj import CRS

from geoortho.core.outputs import temp_prefix
from geoortho.errors import InputError
from geoortho.feedback import Feedback, as_feedback
from geoortho.reconstruction.sparse.georef import georeference
from geoortho.reconstruction.sparse.inputs import (
    CAMERA_MODELS,
    MAPPERS,
    MATCHING,
    CameraModel,
    Mapper,
    Matching,
    Timer,
    check_choice,
    read_inputs,
)
from geoortho.reconstruction.sparse.lens import hold_unsupported_distortion
from geoortho.reconstruction.sparse.mapping import reconstruct, split_reconstruct
from geoortho.reconstruction.sparse.outputs import write_model
from geoortho.reconstruction.sparse.report import (
    SfmResult,
    announce,
    ce90,
    intrinsics_report,
    le90,
    report_figures,
    sfm_result,
    why_positions_did_not_fit,
    write_report,
)

__all__ = ["SfmResult", "sfm", "MATCHING", "MAPPERS", "CAMERA_MODELS", "ce90", "le90"]


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
    timer = Timer()
    output = Path(output)
    check_choice("camera model", camera_model, CAMERA_MODELS)
    check_choice("mapper", mapper, MAPPERS)
    check_choice("matching", matching, MATCHING)
    inputs = read_inputs(
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
            mapped, sub_stats = split_reconstruct(inputs, output, split, split_overlap_m, sub_kwargs, timer, fb, sfm)
        else:
            mapped = reconstruct(
                inputs, db, work, matching, mapper, camera_model, max_image_size, max_features, gps_sigma_m, seed,
                workers, timer, fb,
            )  # fmt: skip
        notes += mapped.notes
        t0 = time.perf_counter()
        mapped = hold_unsupported_distortion(mapped, notes)
        timer.add("lens_distortion_test", t0)
        inputs, lag, geo = georeference(mapped, inputs, gps_sigma_m, notes, timer, fb)
        intrinsics = intrinsics_report(mapped, geo.gcp_obs_used, notes)
        if geo.gps_sim is None and not any(s.triangulated is not None for s in geo.states) and not local_frame:
            raise InputError(
                "the model could not be georeferenced (GPS did not fit, GCPs not triangulated)"
                + why_positions_did_not_fit(inputs)
                + "; use local_frame to keep it anyway",
                path=images,
            )
        t0 = time.perf_counter()
        n_points = write_model(output, work, db, mapped, inputs, geo, notes)
        timer.add("outputs", t0)
        figures = report_figures(mapped.rec, inputs, geo)
        write_report(output, inputs, mapped, geo, figures, intrinsics, mapper, lag, sub_stats, timer, t_start, notes)
        if not sub_stats:  # one block now: an earlier split's submodels describe another model
            shutil.rmtree(output / "submodels", ignore_errors=True)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    announce(notes, mapped, inputs, geo, figures, n_points, fb)
    fb.set_progress(1.0)
    return sfm_result(output, inputs, mapped, geo, figures, notes)
