"""Pieces every later step of sfm shares: camera centres and focal lengths of a pycolmap
reconstruction, bundle-adjustment options and copies, the similarity onto the GPS, and what
mapping hands on (:class:`Mapped`)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from geoortho.core.colmap import load_pycolmap
from geoortho.photos.metadata import Photo
from geoortho.reconstruction.sparse.inputs import Priors


def camera_centres(rec: Any) -> dict[str, np.ndarray]:
    return {rec.image(i).name: rec.image(i).projection_center() for i in rec.reg_image_ids()}


def align_to_gps(rec: Any, priors: Priors, sigma_h_m: float) -> tuple[Any, int]:
    """Robust similarity from the model's camera centres onto their GPS positions."""
    pc = load_pycolmap()
    names = [n for n in camera_centres(rec) if n in priors.positions]
    if len(names) < 3:
        return None, 0
    ro = pc.RANSACOptions()
    ro.max_error = 3.0 * sigma_h_m
    ro.random_seed = 0
    sim = pc.align_reconstruction_to_locations(rec, names, np.array([priors.positions[n] for n in names]), 3, ro)
    if sim is not None:
        rec.transform(sim)
    return sim, len(names)


def ill_conditioned(photos: Sequence[Photo], priors: Priors) -> str:
    """Why self-calibrating the focal length is ill-posed here ('' if it is not): on a nadir-only,
    single-height block focal length and flying height trade off almost exactly."""
    nadir = all(p.pitch_deg <= -75.0 for p in photos)
    z = np.array([v[2] for v in priors.positions.values()]) if priors.positions else np.zeros(0)
    # untrusted GPS heights say nothing of the flight's: take it as flown at one height, as most are
    single = z.size == 0 or not priors.vertical_trusted or float(np.ptp(z)) < 10.0
    return "nadir-only, single-height block" if nadir and single else ""


def camera_focal_px(cam: Any) -> float:
    return float(np.mean([cam.params[i] for i in cam.focal_length_idxs()]))


#: The adjustments after mapping stop when an iteration changes the cost by less than this share
#: (Ceres' own default; COLMAP sets none, so each ran to its iteration cap or a gradient test on
#: blocks the mapper had already converged). Measured, whole sfm on the same features and matches:
#: the medium survey (88 photos) 237 -> 162 s, its GCP adjustment 67 -> 8 iterations (73 -> 15 s),
#: the held block 28 -> 6, cameras 0.17 cm (h) from the truth both ways, GCP RMSE 0.84 mm both
#: ways; toledo 121 -> 72 s, a 101-iteration adjustment 14, the GCP RMSE the same to 1e-11 m.
BA_FUNCTION_TOLERANCE = 1e-6


def ba_options(
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


def mean_reprojection_error_px(rec: Any) -> float:
    """Mean reprojection error over the block's points, computed afresh (the points' stored errors
    are those of the last mapper step, not of an adjustment since)."""
    rec.update_point_3d_errors()
    return float(rec.compute_mean_reprojection_error())


def adjusted_copy(rec: Any, opts: Any, gauge: Any) -> Any:
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


@dataclass(frozen=True)
class Mapped:
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


def prior_focal(db: Path, camera_id: int, fallback: float) -> float:
    """The focal length (px) the camera started from: the database keeps the imported value."""
    pc = load_pycolmap()
    try:
        with pc.Database.open(db) as d:
            cam = d.read_camera(camera_id)
            return float(cam.params[cam.focal_length_idxs()[0]])
    except Exception:  # noqa: BLE001 - an old database layout: the mapped value is all there is
        return fallback
