"""sfm's products beside the report: the COLMAP model with georeference.json, points.laz and
cameras.gpkg."""

from __future__ import annotations

import math
import os
import shutil
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from pyproj import CRS

from geoortho.core.camera import ypr_from_rotation
from geoortho.core.crs import (
    heights_to_text,
    with_heights,
)
from geoortho.core.outputs import write_json, write_vector
from geoortho.core.pointcloud import write_las
from geoortho.core.styles import product_styles
from geoortho.photos.metadata import Photo
from geoortho.reconstruction.sparse.adjust import Mapped
from geoortho.reconstruction.sparse.georef import Georeference
from geoortho.reconstruction.sparse.inputs import Inputs, Priors


def _reprojection_errors(rec: Any) -> dict[int, tuple[float, int]]:
    """Mean reprojection error (px) and number of tie points, per registered image."""
    ids = list(rec.point3D_ids())
    err = {pid: rec.point3D(pid).error for pid in ids}
    out = {}
    for iid in rec.reg_image_ids():
        e = [err[p.point3D_id] for p in rec.image(iid).get_observation_points2D()]
        out[iid] = (float(np.mean(e)) if e else math.nan, len(e))
    return out


def _write_points(path: Path, rec: Any, offset: np.ndarray, crs: CRS) -> int:
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
    priors: Priors,
    crs: CRS,
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


def write_model(
    output: Path, work: Path, db: Path, mapped: Mapped, inputs: Inputs, geo: Georeference, notes: list[str]
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
