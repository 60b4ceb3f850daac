"""What footprints writes: the footprint layers of the GeoPackage and the overlap raster."""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from pyproj import CRS

from geoortho.core.outputs import write_cog, write_vector
from geoortho.core.styles import overlap as overlap_style
from geoortho.core.styles import product_styles, write_raster_style
from geoortho.errors import InputError
from geoortho.photos.heights import HeightModel
from geoortho.photos.photo_cameras import FootprintTable, PhotoCamera


def write_layers(
    output: Path,
    fp: Any,
    cam_layer: Any,
    work: CRS,
    out_crs: CRS | None,
    overlap: Path | None,
    cell_m: float,
    extra: dict[str, Any] | None = None,
) -> Path | None:
    """The overlap raster (in the working CRS), then the layers in the output CRS; the overlap's path."""

    overlap_path = write_overlap(overlap, fp.geometry.values, work, cell_m) if overlap is not None else None
    layers = {"footprints": fp, "cameras": cam_layer, **(extra or {})}
    if out_crs is not None and not out_crs.equals(work):
        layers = {name: layer.to_crs(out_crs) for name, layer in layers.items()}
    write_vector(output, layers, styles=product_styles(*layers))
    return overlap_path


def _with_ground(ground: str, source: str) -> str:
    """A photo's height source naming its ground once: the heights' own sources often end with it."""
    return source if ground in source else f"{ground}; {source}"


def layers_of_footprints(
    cams: Sequence[PhotoCamera], table: FootprintTable, heights: HeightModel, ground: str, work: CRS
) -> tuple[Any, Any]:
    """The footprints layer (one polygon and its figures per photo) and the cameras layer."""
    import geopandas as gpd
    import shapely

    polys = shapely.polygons(table.rings)
    bad = ~shapely.is_valid(polys)
    if bad.any():
        polys[bad] = shapely.make_valid(polys[bad])
    records = {
        "image": [c.photo.image for c in cams],
        "gsd_cm": table.gsd_m * 100,
        "gsd_min_cm": table.gsd_min_m * 100,
        "gsd_max_cm": table.gsd_max_m * 100,
        "altitude_m": table.altitude_m,
        "pitch_deg": [c.photo.pitch_deg for c in cams],
        "yaw_deg": [c.photo.yaw_deg for c in cams],
        "roll_deg": [c.photo.roll_deg for c in cams],
        "area_m2": shapely.area(polys),
        "clipped": table.clipped,
        "outside_dsm": table.outside,
        "height_source": [_with_ground(ground, c.height_source) for c in cams],
        "vertical_datum": [heights.datum] * len(cams),
        "attitude_source": [c.photo.attitude_source for c in cams],
        "grid_convergence_deg": [c.grid_convergence_deg for c in cams],
        "camera": [f"{c.photo.make} {c.photo.model}".strip() for c in cams],
        "focal_px": [c.intrinsics.focal_px for c in cams],
        "taken_at": [c.photo.taken_at for c in cams],
        "gps_fix": [c.photo.gps_fix for c in cams],
        "gps_sigma_h_m": [c.photo.gps_sigma_h_m for c in cams],
        "gps_sigma_v_m": [c.photo.gps_sigma_v_m for c in cams],
    }
    fp = gpd.GeoDataFrame(records, geometry=polys, crs=work)
    centers = np.array([c.pose.center for c in cams])
    cam_layer = gpd.GeoDataFrame(
        {
            "image": records["image"],
            "z_m": centers[:, 2],
            "latitude_deg": [c.photo.latitude_deg for c in cams],
            "longitude_deg": [c.photo.longitude_deg for c in cams],
            "relative_altitude_m": [c.photo.relative_altitude_m for c in cams],
            "yaw_deg": records["yaw_deg"],
            "pitch_deg": records["pitch_deg"],
            "roll_deg": records["roll_deg"],
            "gsd_cm": records["gsd_cm"],
            "gps_fix": records["gps_fix"],
            "gps_sigma_h_m": records["gps_sigma_h_m"],
            "gps_sigma_v_m": records["gps_sigma_v_m"],
        },
        geometry=shapely.points(centers[:, :2]),
        crs=work,
    )
    return fp, cam_layer


def write_overlap(path: str | os.PathLike[str], polygons: Sequence[Any], crs: CRS, cell_m: float) -> Path:
    """Raster of how many polygons cover each cell (uint16 COG, 0 = not covered is nodata)."""
    import shapely
    from rasterio.features import MergeAlg, rasterize
    from rasterio.transform import from_origin

    x0, y0, x1, y1 = shapely.total_bounds(np.asarray(polygons))
    x0, y0 = math.floor(x0 / cell_m) * cell_m, math.floor(y0 / cell_m) * cell_m
    cols, rows = int(math.ceil((x1 - x0) / cell_m)), int(math.ceil((y1 - y0) / cell_m))
    if cols * rows > 400_000_000:
        raise InputError(f"overlap raster of {cols}x{rows} cells is too large; raise overlap_cell_m")
    transform = from_origin(x0, y0 + rows * cell_m, cell_m, cell_m)
    # Vertices closer than half a cell change no cell: simplify first (rasterio reads every vertex
    # through __geo_interface__, the slow part for thousands of footprints).
    simple = shapely.simplify(np.asarray(polygons), cell_m / 2)
    count = rasterize(
        ((g, 1) for g in simple),
        out_shape=(rows, cols),
        transform=transform,
        merge_alg=MergeAlg.add,
        dtype="uint16",
        fill=0,
    )
    out = write_cog(path, count, transform=transform, crs=crs, nodata=0)
    write_raster_style(out, overlap_style(out))
    return out
