"""The survey's truth beside its photos: rasters (DSM, DTM, true orthophoto), poses and footprints,
GCP files, the point cloud and survey.json."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np
from affine import Affine
from pyproj import CRS

from geoortho.core.camera import Intrinsics, Pose, pixel_rays, rotation_from_ypr
from geoortho.core.crs import transformer
from geoortho.core.outputs import write_cog, write_json, write_text, write_vector
from geoortho.core.pointcloud import write_las
from geoortho.core.surface import sample_grid
from geoortho.elevation.grid import NODATA
from geoortho.feedback import Feedback, split
from geoortho.synthetic.flight import RTK_SIGMA_M, Shot, write_ppk_trajectory
from geoortho.synthetic.presets import (
    CAMERA_MODEL,
    ERROR_MODEL,
    FOCAL_35MM,
    FOCAL_MM,
    GPS_LAG_S,
    GPS_MINUS_UTC_S,
    MAKER_MAKE,
    MOUNT_TILT_AZIMUTH_DEG,
    MOUNT_TILT_DEG,
    PATHOLOGIES,
    PPK_LAG_S,
    SENSOR_HEIGHT_MM,
    SENSOR_WIDTH_MM,
    SLOPE_AZIMUTH_DEG,
    SLOPE_DEG,
    WRONG_FLIGHT_HEIGHT_FACTOR,
    SynthPreset,
)
from geoortho.synthetic.scene import Scene, remap3


def true_footprint(
    scene: Scene, shot: Shot, intr: Intrinsics, per_side: int = 40, max_range_m: float = 1000.0
) -> tuple[np.ndarray, bool]:
    """The image border cast onto the DSM: polygon vertices (N, 2) and whether any ray missed."""
    pose = Pose.from_ypr((shot.x, shot.y, shot.z), shot.yaw_deg, shot.pitch_deg, shot.roll_deg)
    border = intr.border_pixels(per_side)
    hits = scene.surface.intersect(
        pose.center, pixel_rays(border, intr, pose), max_range_m=max_range_m, step_m=scene.transform.a
    )
    return hits.points[:, :2], not bool(hits.hit.all())


def write_truth(
    truth: Path,
    scene: Scene,
    shots: list[Shot],
    intr: Intrinsics,
    p: SynthPreset,
    results: list[dict[str, Any]],
    seed: int,
    fb: Feedback,
    pathologies: Sequence[str] = (),
    undulation_m: float = 0.0,
    degradations: dict[str, Any] | None = None,
    pixels: bool = True,
) -> None:
    """Every truth product: rasters, poses and footprints, GCP files, survey.json, ortho, point cloud."""
    steps = split(fb, [1, 1, 3, 2, 1])
    _write_truth_rasters(truth, scene, pathologies, undulation_m)
    steps[0].progress(1.0)
    _write_poses_and_footprints(truth, scene, shots, intr, results)
    steps[1].progress(1.0)
    _write_gcp_files(truth, scene)
    if "ppk" in pathologies:
        write_ppk_trajectory(truth / "trajectory.pos", scene, shots, np.random.default_rng([seed, 23]))
    dropped = {"image": s.name, "how": s.dropped} if (s := next((s for s in shots if s.dropped), None)) else None
    rtk = (
        {
            "float": [s.name for s in shots if s.rtk_flag == 34],
            "lost_fix": [s.name for s in shots if s.rtk_flag == 16],
            "true_sigma_m": {"fixed": RTK_SIGMA_M[50], "float": RTK_SIGMA_M[34], "single": RTK_SIGMA_M[16]},
        }
        if any(s.rtk_flag >= 0 for s in shots)
        else None
    )
    _write_survey_json(
        truth, scene, intr, p, seed, pathologies, undulation_m, shots[0].maker if shots else "dji", dropped, rtk,
        degradations, pixels,
    )  # fmt: skip
    steps[2].progress(1.0)
    _write_true_ortho(truth / "ortho.tif", scene, p.ortho_cell_m, steps[3])
    _write_points(truth / "points.laz", scene, p, np.random.default_rng(seed + 7))
    steps[4].progress(1.0)


def _write_truth_rasters(truth: Path, scene: Scene, pathologies: Sequence[str], undulation_m: float) -> None:
    """The true DSM and DTM, and the DSMs the pathologies ask for (another datum, a partial one)."""

    write_cog(truth / "dsm.tif", scene.dsm, transform=scene.transform, crs=scene.crs, nodata=NODATA)
    write_cog(truth / "dtm.tif", scene.dtm, transform=scene.transform, crs=scene.crs, nodata=NODATA)
    if "dsm-datum" in pathologies:
        write_cog(
            truth / "dsm_other_datum.tif",
            scene.dsm - np.float32(undulation_m),
            transform=scene.transform,
            crs=scene.crs,
            nodata=NODATA,
        )
    if "partial-dsm" in pathologies:
        fx0, _, fx1, _ = scene.flight_box
        c0 = int((fx0 + 0.4 * (fx1 - fx0) - scene.transform.c) / scene.transform.a)
        write_cog(
            truth / "dsm_partial.tif",
            scene.dsm[:, c0:],
            transform=scene.transform @ Affine.translation(c0, 0),
            crs=scene.crs,
            nodata=NODATA,
        )


def _pose_record(s: Shot) -> dict[str, Any]:
    R = rotation_from_ypr(s.yaw_deg, s.pitch_deg, s.roll_deg)
    return {
        "image": s.name,
        "x": s.x,
        "y": s.y,
        "z": s.z,
        "yaw_deg": s.yaw_deg,
        "pitch_deg": s.pitch_deg,
        "roll_deg": s.roll_deg,
        "rotation_world_from_camera": R.tolist(),
        "recorded": {
            "latitude_deg": s.rec_lat,
            "longitude_deg": s.rec_lon,
            "gps_altitude_m": s.rec_gps_alt_m,
            "relative_altitude_m": s.rec_rel_alt_m,
            "absolute_altitude_m": s.rec_abs_alt_m,
            "gimbal_yaw_deg": s.rec_yaw_deg,
            "gimbal_pitch_deg": s.rec_pitch_deg,
            "gimbal_roll_deg": s.rec_roll_deg,
            "flight_yaw_deg": s.flight_yaw_deg,
        },
        "oblique": s.oblique,
        "has_xmp": s.has_xmp,
        "has_gps": s.has_gps,
        "corrupt": s.corrupt,
        "blur_px": s.blur_px,
        "exposure_gain": s.exposure_gain,
        "exposure_time_s": s.exposure_time_s,
        "exif_focal_mm": s.exif_focal_mm,
    }


def _write_poses_and_footprints(
    truth: Path, scene: Scene, shots: list[Shot], intr: Intrinsics, results: list[dict[str, Any]]
) -> None:
    import geopandas as gpd
    import shapely

    polys, clipped = [], []
    for s in shots:
        ring, clip = true_footprint(scene, s, intr)
        polys.append(shapely.make_valid(shapely.Polygon(ring)))
        clipped.append(clip)
    gdf = gpd.GeoDataFrame(
        {"image": [s.name for s in shots], "clipped": clipped, "oblique": [s.oblique for s in shots]},
        geometry=polys,
        crs=scene.crs,
    )
    write_vector(truth / "footprints.gpkg", {"footprints": gdf})
    write_json(truth / "poses.json", [_pose_record(s) for s in shots])
    write_json(truth / "markers.json", results)


def _write_gcp_files(truth: Path, scene: Scene) -> None:
    """GCP files as a surveyor hands them over: UTM with an EPSG line, WGS84 text and CSV."""

    gcps = [m for m in scene.markers if not m.decoy]
    to_ll = transformer(scene.crs, CRS.from_epsg(4326))
    utm_lines = [f"EPSG:{scene.crs.to_epsg()}"] + [f"{m.name} {m.x:.4f} {m.y:.4f} {m.z:.4f}" for m in gcps]
    write_text(truth / "gcp_utm.txt", "\n".join(utm_lines) + "\n")
    ll_lines = ["EPSG:4979"]
    csv_lines = ["name,lat,lon,alt"]
    for m in gcps:
        lon, lat = to_ll.transform(m.x, m.y)
        ll_lines.append(f"{m.name} {lat:.9f} {lon:.9f} {m.z:.4f}")
        csv_lines.append(f"{m.name},{lat:.9f},{lon:.9f},{m.z:.4f}")
    write_text(truth / "gcp_wgs84.txt", "\n".join(ll_lines) + "\n")
    write_text(truth / "gcp_wgs84.csv", "\n".join(csv_lines) + "\n")


def renderer_digest() -> str:
    """A digest of the synthetic renderer's source: a survey written by other code is drawn again."""
    import hashlib

    h = hashlib.sha256()
    for f in sorted(Path(__file__).parent.glob("*.py")):
        h.update(f.read_bytes())
    return h.hexdigest()[:16]


def _write_survey_json(
    truth: Path,
    scene: Scene,
    intr: Intrinsics,
    p: SynthPreset,
    seed: int,
    pathologies: Sequence[str],
    undulation_m: float,
    maker: str = "dji",
    dropped: dict[str, str] | None = None,
    rtk: dict[str, Any] | None = None,
    degradations: dict[str, Any] | None = None,
    pixels: bool = True,
) -> None:

    write_json(
        truth / "survey.json",
        {
            "preset": asdict(p),
            "seed": seed,
            "crs": f"EPSG:{scene.crs.to_epsg()}",
            "vertical": "WGS84 ellipsoidal height, m",
            "pixel_convention": "(0,0) is the centre of the top-left pixel (OpenCV, OpenDroneMap gcp_list.txt)",
            "attitude_convention": "yaw clockwise from north, pitch -90 nadir, roll right-down positive; "
            "poses.json's yaw_deg from the CRS's grid north, the photos' recorded yaw from true north",
            "camera": {
                "make": MAKER_MAKE[maker],
                "model": CAMERA_MODEL,
                "sensor_width_mm": SENSOR_WIDTH_MM,
                "sensor_height_mm": SENSOR_HEIGHT_MM,
                "focal_mm": FOCAL_MM,
                "focal_35mm": FOCAL_35MM,
                "width_px": intr.width_px,
                "height_px": intr.height_px,
                "focal_px": intr.focal_px,
                "cx_px": intr.cx_px,
                "cy_px": intr.cy_px,
                "distortion": list(p.distortion),
            },
            "pathologies": {k: PATHOLOGIES[k] for k in pathologies},
            **({"water": dict(zip(("x", "y", "radius_m"), scene.water))} if scene.water is not None else {}),
            **({"cover": scene.cover} if scene.cover else {}),
            **(
                {"facades": {"style": scene.facade_style, "buildings": list(scene.building_records)}}
                if scene.facade_style
                else {}
            ),
            **({"movers": [m.record() for m in scene.movers]} if scene.movers else {}),
            **(
                {"mount_tilt": {"deg": MOUNT_TILT_DEG, "azimuth_deg": MOUNT_TILT_AZIMUTH_DEG}}
                if "no-attitude" in pathologies
                else {}
            ),
            **({"slope": {"deg": SLOPE_DEG, "azimuth_deg": SLOPE_AZIMUTH_DEG}} if "slope" in pathologies else {}),
            **({"dropped_photo": dropped} if dropped else {}),
            **({"rtk": rtk} if rtk else {}),
            **({"degradations": degradations} if degradations else {}),
            **({"pixels": "markers only, on flat grey, without camera effects"} if not pixels else {}),
            **({"gps_lag_s": GPS_LAG_S} if "gps-lag" in pathologies else {}),
            **(
                {"ppk": {"pos": "trajectory.pos", "lag_s": PPK_LAG_S, "gps_minus_camera_clock_s": GPS_MINUS_UTC_S}}
                if "ppk" in pathologies
                else {}
            ),
            **(
                {"user_flight_height_m": round(p.altitude_m * WRONG_FLIGHT_HEIGHT_FACTOR, 1)}
                if "wrong-flight-height" in pathologies
                else {}
            ),
            "flight_height_m": p.altitude_m,
            "renderer": renderer_digest(),
            "geoid_undulation_m": undulation_m,
            "home": {"x": scene.home[0], "y": scene.home[1], "ground_z": scene.home[2]},
            "flight_box": list(scene.flight_box),
            "gsd_cm_at_home_height": p.altitude_m * SENSOR_WIDTH_MM / FOCAL_MM / intr.width_px * 100,
            "marker_size_m": scene.marker_size_m,
            "dictionary": scene.dictionary,
            "target": scene.target,
            "markers": [asdict(m) for m in scene.markers],
            "error_model": dict(ERROR_MODEL),
        },
    )


def _write_true_ortho(path: Path, scene: Scene, cell_m: float, progress: Feedback) -> None:
    """The true orthophoto over the flown area (plus a little), coloured from the scene itself."""

    fx0, fy0, fx1, fy1 = scene.flight_box
    pad = 15.0
    oc = cell_m
    ox0, oy1 = math.floor((fx0 - pad) / oc) * oc, math.ceil((fy1 + pad) / oc) * oc
    ocols = int(round((fx1 + pad - ox0) / oc))
    orows = int(round((oy1 - (fy0 - pad)) / oc))
    ot = Affine(oc, 0, ox0, 0, -oc, oy1)
    ortho = np.empty((3, orows, ocols), np.uint8)
    band = max(1, 2_000_000 // ocols)
    surf = scene.surface
    for r0 in range(0, orows, band):
        r1 = min(orows, r0 + band)
        cc, rr = np.meshgrid(np.arange(ocols) + 0.5, np.arange(r0, r1) + 0.5)
        x = ox0 + cc.ravel() * oc
        y = oy1 - rr.ravel() * oc
        z = surf.elevation(x, y)
        col = scene.color(x, y, z)
        ortho[:, r0:r1] = np.clip(col.T.reshape(3, r1 - r0, ocols) * 255 + 0.5, 0, 255).astype(np.uint8)
        progress.progress(r1 / orows)
    write_cog(path, ortho, transform=ot, crs=scene.crs, compress="DEFLATE", band_names=("red", "green", "blue"))


def _write_points(path: Path, scene: Scene, p: SynthPreset, rng: np.random.Generator) -> None:

    fx0, fy0, fx1, fy1 = scene.flight_box
    pad = 20.0
    area = (fx1 - fx0 + 2 * pad) * (fy1 - fy0 + 2 * pad)
    n = int(area * p.points_per_m2)
    x = rng.uniform(fx0 - pad, fx1 + pad, n)
    y = rng.uniform(fy0 - pad, fy1 + pad, n)
    surf = scene.surface
    z = surf.elevation(x, y)
    ground = scene.dtm
    c, r = scene.colrow(x, y)
    g = sample_grid(ground, c, r)
    hag = z - g
    cls = np.where(hag < 0.15, 2, np.where(hag > 2.0, 6, 1)).astype(np.uint8)
    # Trees are objects with the tree colour: class 5 (high vegetation).
    obj = remap3(scene.objects, c.astype(np.float32), r.astype(np.float32))
    tree = (cls != 2) & (np.abs(obj[:, 1] - 0.34) < 0.02) & (np.abs(obj[:, 0] - 0.20) < 0.02)
    cls[tree] = 5
    rgb = scene.color(x, y, z)
    write_las(path, np.c_[x, y, z], scene.crs, rgb=rgb, classification=cls)
