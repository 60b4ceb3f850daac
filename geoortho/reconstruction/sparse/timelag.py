"""The camera-to-GPS time lag: measured from the flight's own GPS or from a positions file, and the
priors moved by it."""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Any

import numpy as np
from pyproj import Transformer

from geoortho.core.colmap import load_pycolmap
from geoortho.core.crs import (
    WGS84,
    transformer,
)
from geoortho.photos.metadata import photo_seconds
from geoortho.photos.positions import PositionFile, apply_positions
from geoortho.reconstruction.sparse.adjust import Mapped, adjusted_copy, align_to_gps, ba_options, camera_centres
from geoortho.reconstruction.sparse.inputs import Inputs, Priors, gps_priors

#: A time lag is taken when it exceeds this many of its standard errors, and this (s).
LAG_SIGMAS = 3.0
LAG_MIN_S = 0.002
LAG_MAX_S = 3.0


def refine_time_lag(mapped: Mapped, inputs: Inputs, notes: list[str]) -> tuple[Inputs, dict[str, Any] | None]:
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
    to_model = transformer(WGS84, inputs.out_crs)
    total, sigma, steps, priors, photos = 0.0, math.nan, 0, inputs.priors, inputs.photos
    while steps < 8:
        steps += 1
        if align_to_gps(free, priors, 1.0)[0] is None:
            return inputs, None
        got = _lag_step(free, inputs, priors, pf, total, to_model)
        if got is None:
            return inputs, None
        delta, sigma = got
        if abs(delta) <= max(LAG_SIGMAS * sigma, LAG_MIN_S) or abs(total + delta) > LAG_MAX_S:
            break
        total += delta
        photos = tuple(apply_positions(inputs.photos_as_read, pf.with_lag(inputs.photos_as_read, total)))
        fresh = gps_priors(photos, inputs.names, inputs.out_crs, inputs.takeoff_elevation_m)
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
    align_to_gps(mapped.rec, priors, 1.0)
    _prior_bundle_adjustment(
        mapped.rec, priors, refine_focal=not mapped.focal_held, refine_distortion=not mapped.distortion_held
    )
    return inputs, report


def _free_network(rec: Any, refine_distortion: bool = True) -> Any:
    """A copy of the block bundle-adjusted on its photos alone (no position priors)."""
    pc = load_pycolmap()
    opts = ba_options(refine_focal=False, refine_distortion=refine_distortion, iterations=FREE_NETWORK_ITERATIONS)
    return adjusted_copy(rec, opts, pc.BundleAdjustmentGauge.THREE_POINTS)


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


def _own_gps_velocities(inputs: Inputs) -> dict[str, np.ndarray]:
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


def _lag_of_own_gps(mapped: Mapped, inputs: Inputs, notes: list[str]) -> tuple[Inputs, dict[str, Any] | None]:
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
        if align_to_gps(free, priors, 2.0)[0] is None:
            return inputs, None
        centres = camera_centres(free)
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
    rec: Any, inputs: Inputs, priors: Priors, pf: PositionFile, lag_s: float, to_model: Transformer
) -> tuple[float, float] | None:
    """The further lag (s) the residuals show along the velocities, and its standard error."""
    assert pf.trajectory is not None
    traj = pf.trajectory
    centres = camera_centres(rec)
    r, v = [], []
    for p in inputs.photos_as_read:
        name = inputs.names[p.path]
        t = pf.photo_times_s.get(p.image)
        if t is None or name not in centres or name not in priors.positions:
            continue
        a, b = traj.at(t + lag_s - 0.1), traj.at(t + lag_s + 0.1)
        if a is None or b is None:
            continue
        xa, ya = to_model.transform(a.longitude_deg, a.latitude_deg)
        xb, yb = to_model.transform(b.longitude_deg, b.latitude_deg)
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


def _prior_bundle_adjustment(rec: Any, priors: Priors, refine_focal: bool, refine_distortion: bool = True) -> None:
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
    opts = ba_options(refine_focal=refine_focal, refine_distortion=refine_distortion)
    pc.create_pose_prior_bundle_adjuster(opts, pc.PosePriorBundleAdjustmentOptions(), cfg, pose_priors, rec).solve()
