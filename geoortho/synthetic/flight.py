"""The synthetic flight: a lawnmower plan (or a given one) flown over the scene, the true poses and
what the drone records of them, RTK and PPK positions, and the pathologies applied."""

from __future__ import annotations

import datetime as dt
import math
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import cv2
import numpy as np
from pyproj import CRS

from geoortho.core.camera import Intrinsics, rotation_from_ypr, ypr_from_rotation
from geoortho.core.crs import grid_north, transformer
from geoortho.errors import InputError
from geoortho.synthetic.cover import EPOCH_GPS_OFFSET_M
from geoortho.synthetic.presets import (
    ATTITUDE_NOISE_SIGMA_DEG,
    CAMERA_MODEL,
    DRIFT_M,
    DROPPED_BLUR_PX,
    DROPPED_GAIN,
    EXPOSURE_STEP,
    FOCAL_MM,
    GPS_ALT_BIAS_SIGMA_M,
    GPS_BIAS_SIGMA_M,
    GPS_LAG_S,
    GPS_MINUS_UTC_S,
    GPS_NOISE_SIGMA_M,
    JUMP_M,
    MOUNT_TILT_AZIMUTH_DEG,
    MOUNT_TILT_DEG,
    POOR_GPS_SIGMA_M,
    PPK_EPOCH_S,
    PPK_LAG_S,
    PPK_SIGMA_M,
    REL_ALT_NOISE_SIGMA_M,
    SENSOR_WIDTH_MM,
    TRUE_ATTITUDE_JITTER_DEG,
    WRONG_CALIBRATION_FACTOR,
    WRONG_FOCAL_FACTOR,
    SynthPreset,
)
from geoortho.synthetic.scene import Scene, footprint_size_m


@dataclass(frozen=True)
class Shot:
    """One planned and flown photo: the true pose and what the drone recorded."""

    name: str
    x: float
    y: float
    z: float
    yaw_deg: float
    pitch_deg: float
    roll_deg: float
    rec_lat: float = float("nan")
    rec_lon: float = float("nan")
    rec_gps_alt_m: float = float("nan")
    rec_rel_alt_m: float = float("nan")
    rec_abs_alt_m: float = float("nan")
    rec_yaw_deg: float = 0.0
    rec_pitch_deg: float = 0.0
    rec_roll_deg: float = 0.0
    flight_yaw_deg: float = 0.0
    flight_pitch_deg: float = 0.0
    flight_roll_deg: float = 0.0
    time: str = ""
    oblique: bool = False
    has_xmp: bool = True
    has_attitude: bool = True  # EXIF GPSImgDirection where there is no XMP
    has_gps: bool = True
    corrupt: bool = False
    blur_px: float = 0.0
    exposure_gain: float = 1.0
    exposure_time_s: float = 1.0 / 800.0
    exif_focal_mm: float = FOCAL_MM  # what EXIF says (the wrong-focal pathology lies)
    maker: str = "dji"  # whose tags carry the metadata (MAKERS)
    dropped: str = ""  # the dropped-photo pathology: how this photo was spoiled
    rtk_flag: int = -1  # the rtk pathology: DJI's RtkFlag (50 fixed, 34 float, 16 single); -1 none
    rtk_sigma_h_m: float = float("nan")  # the stated 1-sigma accuracy (RtkStdLon/Lat, GPSXYAccuracy)
    rtk_sigma_v_m: float = float("nan")
    subsec: str = ""  # EXIF SubSecTimeOriginal (the ppk pathology's stamps fall between seconds)
    # DJI's factory calibration tags (the factory-calibration pathologies): focal length and optical
    # centre (px, corner origin) and DewarpData's distortion; NaN: none written
    cal_focal_px: float = float("nan")
    cal_cx_px: float = float("nan")
    cal_cy_px: float = float("nan")
    cal_distortion: tuple[float, ...] = ()


def plan_flight(preset: SynthPreset, scene: Scene, rng: np.random.Generator) -> list[Shot]:
    """Lawnmower lines north–south across the flown area, yaw alternating; obliques around it."""
    fw, fh = footprint_size_m(preset)
    along = fh * (1 - preset.front_overlap)
    across = fw * (1 - preset.side_overlap)
    fx0, fy0, fx1, fy1 = scene.flight_box
    n_lines = max(2, int(math.ceil((fx1 - fx0) / across)) + 1)
    n_along = max(2, int(math.ceil((fy1 - fy0) / along)) + 1)
    xs = (fx0 + fx1) / 2 + (np.arange(n_lines) - (n_lines - 1) / 2) * across
    ys = (fy0 + fy1) / 2 + (np.arange(n_along) - (n_along - 1) / 2) * along
    z = scene.home[2] + preset.altitude_m
    j = TRUE_ATTITUDE_JITTER_DEG
    shots: list[Shot] = []
    for li, x in enumerate(xs):
        heading = 0.0 if li % 2 == 0 else 180.0
        line_ys = ys if heading == 0.0 else ys[::-1]
        for y in line_ys:
            shots.append(
                Shot(
                    "",
                    float(x + rng.normal(0, 0.3)),
                    float(y + rng.normal(0, 0.3)),
                    float(z + rng.normal(0, 0.2)),
                    float(heading + rng.normal(0, j)),
                    float(-90.0 + rng.normal(0, j)),
                    float(rng.normal(0, j / 2)),
                )
            )
    for k in range(preset.n_oblique):
        a = 2 * np.pi * k / preset.n_oblique + rng.uniform(-0.2, 0.2)
        r = max(fx1 - fx0, fy1 - fy0) * 0.55
        cx, cy = (fx0 + fx1) / 2 + r * np.sin(a), (fy0 + fy1) / 2 + r * np.cos(a)
        look = (np.degrees(a) + 180.0 + rng.uniform(-40, 40)) % 360.0
        shots.append(
            Shot(
                "",
                float(cx),
                float(cy),
                float(z + rng.normal(0, 0.3)),
                float((look + 180) % 360 - 180),
                float(rng.uniform(-70.0, -45.0)),
                float(rng.normal(0, 1.0)),
                oblique=True,
            )
        )
    return shots


def fly_plan(plan: Path, scene: Scene, rng: np.random.Generator) -> tuple[list[Shot], tuple[int, int]]:
    """The photos of a ``plan`` (plan.gpkg or its folder) as this scene's shots: planned position,
    height and attitude, flown with the same wander as the built-in flight, and the pixel size of the
    plan's camera. Heights: the plan's absolute ones when it was planned on a DTM (the scene's
    truth/dtm.tif), else its altitude above the take-off over the scene's home point. The camera's
    field of view must be the synthetic camera's; its pixel count may differ (a 12 MP plan renders
    12 MP photos)."""
    from geoortho.planning.check import read_plan_photos  # here: 0.9 s (geopandas) in every render worker

    photos, summary = read_plan_photos(plan)
    cam = summary.get("camera", {})
    w, h = int(cam.get("width_px") or 0), int(cam.get("height_px") or 0)
    if (
        min(w, h) < 64
        or abs(cam.get("focal_mm", 0) / max(cam.get("sensor_width_mm", 1e-9), 1e-9) - FOCAL_MM / SENSOR_WIDTH_MM) > 1e-6
    ):
        raise InputError(
            f"the plan's camera ({cam.get('name')}, focal {cam.get('focal_mm')} mm on a "
            f"{cam.get('sensor_width_mm')} mm sensor) has not the synthetic camera's field of view "
            f"({CAMERA_MODEL}, {FOCAL_MM} mm on {SENSOR_WIDTH_MM} mm): plan with --camera {CAMERA_MODEL} "
            "(any --image-width-px/--image-height-px)",
            path=plan,
        )
    t = transformer(CRS.from_user_input(photos.crs), scene.crs)
    x, y = t.transform(photos.geometry.x.to_numpy(), photos.geometry.y.to_numpy())
    on_dtm = str(summary.get("ground", {}).get("model", "")).startswith("DTM")
    z = photos["z_m"].to_numpy() if on_dtm else scene.home[2] + photos["altitude_m"].to_numpy()
    j = TRUE_ATTITUDE_JITTER_DEG
    shots = [
        Shot(
            "",
            float(xi + rng.normal(0, 0.3)),
            float(yi + rng.normal(0, 0.3)),
            float(zi + rng.normal(0, 0.2)),
            float(_wrap180(hd + rng.normal(0, j))),
            float(pt + rng.normal(0, j)),
            float(rng.normal(0, j / 2)),
            oblique=pt > -80.0,
        )
        for xi, yi, zi, hd, pt in zip(x, y, z, photos["grid_heading_deg"], photos["pitch_deg"])
    ]
    return shots, (w, h)


def drone_records(shots: list[Shot], scene: Scene, preset: SynthPreset, rng: np.random.Generator) -> list[Shot]:
    """Add what the drone writes: noisy GPS, heights, gimbal and aircraft attitude, time."""
    to_ll = transformer(scene.crs, CRS.from_epsg(4326))
    bias = rng.normal(0, GPS_BIAS_SIGMA_M, 2)
    alt_bias = rng.normal(0, GPS_ALT_BIAS_SIGMA_M)
    t0 = dt.datetime(2026, 5, 14, 10, 0, 0)
    # The drone writes yaw from true north; the truth's yaw is from the grid's north.

    lon_t, lat_t = to_ll.transform(np.array([s.x for s in shots]), np.array([s.y for s in shots]))
    convergence, _ = grid_north(scene.crs, lon_t, lat_t)
    out = []
    for i, s in enumerate(shots):
        ex, ey = s.x + bias[0] + rng.normal(0, GPS_NOISE_SIGMA_M), s.y + bias[1] + rng.normal(0, GPS_NOISE_SIGMA_M)
        lon, lat = to_ll.transform(ex, ey)
        n = ATTITUDE_NOISE_SIGMA_DEG
        true_yaw = s.yaw_deg - float(convergence[i])
        fyaw = true_yaw + rng.normal(0, 2.0)  # the aircraft points a little off the gimbal
        out.append(
            replace(
                s,
                name=f"DJI_{i + 1:04d}.JPG",
                rec_lat=lat,
                rec_lon=lon,
                rec_gps_alt_m=s.z + alt_bias + rng.normal(0, 0.3),
                rec_rel_alt_m=s.z - scene.home[2] + rng.normal(0, REL_ALT_NOISE_SIGMA_M),
                rec_abs_alt_m=s.z + alt_bias + rng.normal(0, 0.3),
                rec_yaw_deg=_wrap180(true_yaw + rng.normal(0, n)),
                rec_pitch_deg=s.pitch_deg + rng.normal(0, n),
                rec_roll_deg=s.roll_deg + rng.normal(0, n),
                flight_yaw_deg=_wrap180(fyaw),
                flight_pitch_deg=float(rng.uniform(-8, -3)),
                flight_roll_deg=float(rng.normal(0, 2)),
                time=(t0 + dt.timedelta(seconds=2 * i)).strftime("%Y:%m:%d %H:%M:%S"),
                exposure_gain=float(rng.uniform(0.9, 1.1)),
            )
        )
    if preset.hard:
        idx = rng.permutation(len(out))
        for k in idx[:3]:
            out[k] = replace(out[k], has_xmp=False)
        out[idx[3]] = replace(out[idx[3]], has_gps=False)
        out[idx[4]] = replace(out[idx[4]], corrupt=True)
        for k in idx[5:9]:
            out[k] = replace(out[k], blur_px=float(rng.uniform(3, 6)))
    return out


RTK_SIGMA_M = {50: (0.02, 0.03), 34: (0.3, 0.45), 16: (1.5, 3.0)}  # RtkFlag -> true 1-sigma H, V


def _stale_fixes(shots: list[Shot], lag_s: float, interval_s: float = 2.0) -> list[Shot]:
    """Each recorded position moved to where the camera was ``lag_s`` before its exposure: back
    along the straight path from the previous photo (the first: from the next), photos
    ``interval_s`` apart."""
    out = []
    for i, s in enumerate(shots):
        j = i - 1 if i > 0 else 1
        dx, dy = shots[j].x - s.x, shots[j].y - s.y
        share = (lag_s / interval_s) * (1.0 if i > 0 else -1.0)
        out.append(_fix_moved(s, dx * share, dy * share))
    return out


def _fix_moved(s: Shot, east_m: float, north_m: float) -> Shot:
    """The photo with its recorded GPS fix moved east and north by so many metres."""
    return replace(
        s,
        rec_lat=s.rec_lat + north_m / 111_320.0,
        rec_lon=s.rec_lon + east_m / (111_320.0 * math.cos(math.radians(s.rec_lat))),
    )


def _stamped_early(s: Shot, lag_s: float) -> Shot:
    """The photo's time stamp ``lag_s`` before its exposure, to the millisecond."""
    stamp = dt.datetime.strptime(s.time, "%Y:%m:%d %H:%M:%S") - dt.timedelta(seconds=lag_s)
    return replace(s, time=stamp.strftime("%Y:%m:%d %H:%M:%S"), subsec=f"{stamp.microsecond // 1000:03d}")


def write_ppk_trajectory(path: Path, scene: Scene, shots: list[Shot], rng: np.random.Generator) -> None:
    """The camera's path as RTKPOST writes it: an epoch every PPK_EPOCH_S in GPS time, the true
    centres (each exposure's, the path straight between them) with a fixed solution's noise."""
    exposures = []
    for s in shots:
        stamp = dt.datetime.strptime(s.time, "%Y:%m:%d %H:%M:%S") + dt.timedelta(milliseconds=int(s.subsec or 0))
        exposures.append((stamp + dt.timedelta(seconds=PPK_LAG_S + GPS_MINUS_UTC_S)).replace(tzinfo=dt.timezone.utc))
    t = np.array([e.timestamp() for e in exposures])
    centres = np.array([[s.x, s.y, s.z] for s in shots])
    order = np.argsort(t)
    t, centres = t[order], centres[order]
    epochs = np.arange(math.floor(t[0]) - 4.0, t[-1] + 4.0, PPK_EPOCH_S)
    xyz = np.c_[[np.interp(epochs, t, centres[:, k]) for k in range(3)]].T
    sh, sv = PPK_SIGMA_M
    xyz += np.c_[rng.normal(0, sh, (len(epochs), 2)), rng.normal(0, sv, len(epochs))]
    lon, lat = transformer(scene.crs, CRS.from_epsg(4326)).transform(xyz[:, 0], xyz[:, 1])
    lines = [
        "% program   : geoortho synth (an RTKPOST solution's layout)",
        "% pos mode  : kinematic",
        "% (lat/lon/height=WGS84/ellipsoidal,Q=1:fix,2:float,3:sbas,4:dgps,5:single,6:ppp,ns=# of satellites)",
        "%  GPST                  latitude(deg) longitude(deg)  height(m)   Q  ns   sdn(m)   sde(m)   sdu(m)  "
        "sdne(m)  sdeu(m)  sdun(m) age(s)  ratio",
    ]
    for k, e in enumerate(epochs):
        when = dt.datetime.fromtimestamp(float(e), dt.timezone.utc)
        lines.append(
            f"{when:%Y/%m/%d %H:%M:%S}.{when.microsecond // 1000:03d}   {lat[k]:.9f}   {lon[k]:.9f}  "
            f"{xyz[k, 2]:9.4f}   1  14   {sh:.4f}   {sh:.4f}   {sv:.4f}   0.0000   0.0000   0.0000   0.00  "
            f"{999.9:6.1f}"
        )
    path.write_text("\n".join(lines) + "\n")


def _rtk_indices(shots: list[Shot]) -> tuple[list[int], int]:
    """The photos of the rtk pathology without a fixed solution: three in a row mid-flight
    (float), and the one where the flight turns most (the fix lost there)."""
    n = len(shots)
    mid = max(0, int(0.4 * n) - 1)
    floats = [i for i in range(mid, min(n, mid + 3))]
    xy = np.array([[s.x, s.y] for s in shots])
    turn = np.zeros(n)
    for i in range(1, n - 1):
        a, b = xy[i] - xy[i - 1], xy[i + 1] - xy[i]
        na, nb = float(np.linalg.norm(a)), float(np.linalg.norm(b))
        if na > 0 and nb > 0:
            turn[i] = math.degrees(math.acos(float(np.clip(a @ b / (na * nb), -1.0, 1.0))))
    turn[floats] = -1.0
    lost = int(np.argmax(turn)) if turn.max() > 0 else (3 * n) // 4
    return floats, lost


def _rtk_positions(shots: list[Shot], scene: Scene, rng: np.random.Generator) -> list[Shot]:
    """Record each photo's position as an RTK receiver gives it: the true camera centre with the
    receiver's own error (its class's sigma), the sigma stated beside it, no common bias."""
    to_ll = transformer(scene.crs, CRS.from_epsg(4326))
    floats, lost = _rtk_indices(shots)
    out = []
    for i, s in enumerate(shots):
        flag = 34 if i in floats else 16 if i == lost else 50
        sh, sv = RTK_SIGMA_M[flag]
        e, n, u = rng.normal(0.0, sh), rng.normal(0.0, sh), rng.normal(0.0, sv)
        lon, lat = to_ll.transform(s.x + e, s.y + n)
        # a receiver states its deviation roughly: within -30 %..+10 % of the true one
        stated_h, stated_v = sh * float(rng.uniform(0.7, 1.1)), sv * float(rng.uniform(0.7, 1.1))
        out.append(
            replace(
                s,
                rec_lat=float(lat),
                rec_lon=float(lon),
                rec_abs_alt_m=s.z + u,
                rec_gps_alt_m=s.z + u,
                rtk_flag=flag,
                rtk_sigma_h_m=stated_h,
                rtk_sigma_v_m=stated_v,
            )
        )
    return out


def _wrap180(a: float) -> float:
    return float((a + 180.0) % 360.0 - 180.0)


def apply_pathologies(
    shots: list[Shot], scene: Scene, pathologies: Sequence[str], undulation_m: float, rng: np.random.Generator
) -> list[Shot]:
    """Make the recorded metadata as wrong as the named consumer-drone pathologies make it."""
    out = list(shots)
    n = len(out)
    # a rotation of MOUNT_TILT_DEG about the horizontal axis square to its azimuth
    az = math.radians(MOUNT_TILT_AZIMUTH_DEG)
    axis = np.array([math.cos(az), -math.sin(az), 0.0])  # east-north: square to (sin az, cos az)
    mount = cv2.Rodrigues(math.radians(MOUNT_TILT_DEG) * axis)[0]
    for i, s in enumerate(out):
        orthometric = s.rec_gps_alt_m - undulation_m  # the recorded GNSS height, made orthometric
        if "no-relative-altitude" in pathologies or "altitude-drift" in pathologies:
            s = replace(s, rec_rel_alt_m=math.nan, rec_abs_alt_m=math.nan, rec_gps_alt_m=orthometric)
        if "ellipsoidal-gps" in pathologies:
            s = replace(s, rec_rel_alt_m=math.nan, rec_abs_alt_m=math.nan)
        if "altitude-drift" in pathologies:
            s = replace(
                s, rec_gps_alt_m=s.rec_gps_alt_m + DRIFT_M * i / max(1, n - 1) + (JUMP_M if i >= int(0.6 * n) else 0.0)
            )
        if "wrong-focal" in pathologies:
            s = replace(s, exif_focal_mm=FOCAL_MM * WRONG_FOCAL_FACTOR)
        if "free-heading" in pathologies and not s.oblique:
            turn = float(rng.uniform(-180.0, 180.0))
            s = replace(
                s,
                yaw_deg=_wrap180(s.yaw_deg + turn),
                rec_yaw_deg=_wrap180(s.rec_yaw_deg + turn),
                flight_yaw_deg=_wrap180(s.flight_yaw_deg + turn),
            )
        if "second-epoch" in pathologies:  # another day's GPS: the whole flight off by one offset
            east, north, up = EPOCH_GPS_OFFSET_M
            s = replace(
                _fix_moved(s, east, north), rec_gps_alt_m=s.rec_gps_alt_m + up, rec_abs_alt_m=s.rec_abs_alt_m + up
            )
        if "poor-gps" in pathologies:
            east, north = rng.normal(0.0, POOR_GPS_SIGMA_M, 2)
            s = _fix_moved(s, float(east), float(north))
        if "no-attitude" in pathologies:
            # the true camera tilted towards one fixed direction; nothing of it in the metadata
            yaw, pitch, roll = ypr_from_rotation(mount @ rotation_from_ypr(s.yaw_deg, s.pitch_deg, s.roll_deg))
            s = replace(s, yaw_deg=yaw, pitch_deg=pitch, roll_deg=roll, has_xmp=False, has_attitude=False, maker="exif")
        if "exposure-steps" in pathologies and abs(_wrap180(s.yaw_deg)) > 90.0 and not s.oblique:
            s = replace(
                s, exposure_gain=s.exposure_gain * EXPOSURE_STEP, exposure_time_s=s.exposure_time_s * EXPOSURE_STEP
            )
        out[i] = s
    if "gps-lag" in pathologies:
        out = _stale_fixes(out, GPS_LAG_S)
    if "rtk" in pathologies:
        out = _rtk_positions(out, scene, rng)
    if "ppk" in pathologies:
        out = [_stamped_early(s, PPK_LAG_S) for s in out]
    if "dropped-photo" in pathologies:
        nadir = [i for i, s in enumerate(out) if not s.oblique]
        k = nadir[len(nadir) // 2]
        if rng.random() < 0.5:
            out[k] = replace(out[k], dropped="smeared", blur_px=DROPPED_BLUR_PX)
        else:
            out[k] = replace(out[k], dropped="blown out", exposure_gain=out[k].exposure_gain * DROPPED_GAIN)
    return out


def with_blur(shots: list[Shot], blur_px: float, seed: int) -> list[Shot]:
    """Half the photos motion-blurred, each by a length drawn between a third of ``blur_px`` and it."""
    if blur_px <= 0:
        return shots
    rng = np.random.default_rng([seed, 13])
    return [replace(s, blur_px=float(rng.uniform(blur_px / 3, blur_px))) if rng.random() < 0.5 else s for s in shots]


def with_calibration(shots: list[Shot], intr: Intrinsics, p: SynthPreset, pathologies: tuple[str, ...]) -> list[Shot]:
    """The maker's calibration tags, true or (wrong-calibration) with a focal length off."""
    if "factory-calibration" not in pathologies and "wrong-calibration" not in pathologies:
        return shots
    factor = WRONG_CALIBRATION_FACTOR if "wrong-calibration" in pathologies else 1.0
    return [
        replace(
            s,
            cal_focal_px=intr.focal_px * factor,
            cal_cx_px=intr.cx_px + 0.5,  # corner origin, as DJI writes it
            cal_cy_px=intr.cy_px + 0.5,
            cal_distortion=tuple((*p.distortion, 0.0, 0.0, 0.0, 0.0, 0.0)[:5]),
        )
        for s in shots
    ]
