"""sfm's report: residuals and accuracy at GCPs and checkpoints (CE90/LE90), the GPS fit, the
lenses, report.json and the result returned."""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from geoortho.core.crs import (
    heights_to_text,
)
from geoortho.core.gsd import depth_gsd_m
from geoortho.core.outputs import write_json
from geoortho.feedback import Feedback
from geoortho.reconstruction.sparse.adjust import Mapped, camera_centres, camera_focal_px, mean_reprojection_error_px
from geoortho.reconstruction.sparse.georef import GcpState, Georeference, plane_tilt
from geoortho.reconstruction.sparse.inputs import Inputs, Priors, Timer
from geoortho.reconstruction.sparse.lens import focal_drift, probe_free_focal

# Focal length changes beyond this (percent of the EXIF value) are reported.
FOCAL_DRIFT_WARN_PCT = 3.0
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


def _residual_table(states: list[GcpState], heights_usable: bool) -> list[dict[str, Any]]:
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


def write_report(
    output: Path,
    inputs: Inputs,
    mapped: Mapped,
    geo: Any,
    figures: Any,
    intrinsics: Any,
    mapper: str,
    lag: Any,
    sub_stats: list[dict[str, Any]],
    timer: Timer,
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


def sfm_result(output: Path, inputs: Inputs, mapped: Mapped, geo: Any, figures: Any, notes: list[str]) -> SfmResult:
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


def why_positions_did_not_fit(inputs: Inputs) -> str:
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


@dataclass(frozen=True)
class _Figures:
    """The accuracy figures of the georeferenced model."""

    gcp_rows: list[dict[str, Any]]
    control: dict[str, Any] | None
    check: dict[str, Any] | None
    mean_reprojection_px: float


def report_figures(rec: Any, inputs: Inputs, geo: Georeference) -> _Figures:
    rows = _residual_table(list(geo.states), geo.heights_usable)
    return _Figures(rows, _accuracy(rows, "control"), _accuracy(rows, "checkpoint"), mean_reprojection_error_px(rec))


def _report(
    inputs: Inputs,
    mapped: Mapped,
    geo: Georeference,
    figures: _Figures,
    intrinsics: list[dict[str, Any]],
    mapper: str,
    timer: Timer,
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
        "camera_plane_tilt_deg": plane_tilt(rec),
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


def announce(
    notes: list[str],
    mapped: Mapped,
    inputs: Inputs,
    geo: Georeference,
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


def intrinsics_report(mapped: Mapped, gcp_obs: int, notes: list[str]) -> list[dict[str, Any]]:
    """Per camera: the EXIF focal length (px), the final one, the drift in percent; with the focal
    held, the drift a free self-calibration would have reached (measured on a copy); the test of
    its lens distortion (reprojection with it refined and held at zero) and whether it was held."""
    rec, focal_prior = mapped.rec, mapped.focal_prior
    drift = focal_drift(rec, focal_prior)
    free = (
        probe_free_focal(rec, refine_distortion=not mapped.distortion_held) if mapped.focal_held and not gcp_obs else {}
    )
    out = []
    for cid, cam in rec.cameras.items():
        row: dict[str, Any] = {
            "camera_id": int(cid),
            "focal_exif_px": focal_prior.get(cid),
            "focal_px": camera_focal_px(cam),
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


def gps_accuracy(rec: Any, priors: Priors, notes: list[str]) -> dict[str, Any] | None:
    """Each stated position accuracy against the bundle-adjusted camera: per class (fixed, float,
    single, stated) the photos, their median stated sigma and the residuals measured; the photos
    off their stated accuracy (a fix lost at a turn), named in ``notes`` too. None when no photo
    states its accuracy (consumer GPS)."""
    if not priors.sigmas:
        return None
    centres = camera_centres(rec)
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


def _gps_residuals(rec: Any, priors: Priors) -> dict[str, Any] | None:
    """Camera centre − GPS position, as ODM's report gives it (the GPS are not truth)."""
    c = camera_centres(rec)
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
