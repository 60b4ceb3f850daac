"""Where each pixel of the orthophoto came from: ``<name>_source.tif`` and the seamlines.

``<name>_source.tif`` (beside the orthophoto, a COG): band 1 ``photo``, the photo each pixel was
drawn from (1-based, 0: none), named in a raster attribute table (GDAL's ``.aux.xml``, which QGIS
shows in the layer's attribute table and legend); band 2 ``how``, how it was drawn
(:data:`SOURCE_KINDS`).

``<name>_seamlines.gpkg``: one polygon per photo region of the mosaic (the regions a seam bounds),
with the photo's name, GSD, view angle from the vertical, capture time, and the area it gives; a
surveyor clicks a smear or a ghost and reads which photo made it.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any
from xml.sax.saxutils import escape

import numpy as np

from geoortho.core.camera import PosedCamera
from geoortho.core.outputs import atomic_path, write_vector
from geoortho.core.styles import paletted, product_styles, write_raster_style

__all__ = [
    "INPAINTED",
    "NONE",
    "OCCLUDED",
    "SEAMLINE_CELLS",
    "SEEN",
    "SOURCE_KINDS",
    "SourceWriter",
    "seamlines_path",
    "write_seamlines",
    "how_style",
]

#: Band 2 (``how``): how each pixel was drawn.
NONE, SEEN, OCCLUDED, INPAINTED = 0, 1, 2, 3
SOURCE_KINDS = {
    NONE: "no data",
    SEEN: "seen by its photo (line of sight on the DSM)",
    OCCLUDED: "seen by no photo (occluded): hidden ground from the seen ground round it, the rest from the photo "
    "that has it in frame most directly",
    INPAINTED: "inpainted (a hole no photo's frame held)",
}

#: The ``how`` codes' colours in QGIS (the source raster's default style).
HOW_COLOURS = {SEEN: "#1a9641", OCCLUDED: "#7b3294", INPAINTED: "#d7191c"}


def how_style() -> Any:
    """The source raster's QGIS style: band 2 (how) paletted, each code with its meaning."""
    return paletted(2, HOW_COLOURS, SOURCE_KINDS)


#: The seamlines are traced on the source raster read at most this many cells (its overviews).
SEAMLINE_CELLS = 4_000_000


def seamlines_path(ortho: str | os.PathLike[str]) -> Path:
    p = Path(ortho)
    return p.with_name(p.stem + "_seamlines.gpkg")


class SourceWriter:
    """The source raster written tile by tile (a tiled GeoTIFF in ``work_dir``), then as a COG."""

    def __init__(self, work_dir: Path, crs: Any, transform: Any, shape: tuple[int, int]) -> None:
        import rasterio

        self.tiled = Path(work_dir) / "source.tif"
        self.ds = rasterio.open(
            self.tiled, "w", driver="GTiff", width=shape[1], height=shape[0], count=2, dtype="uint16",
            crs=crs, transform=transform, nodata=0, tiled=True, blockxsize=512, blockysize=512, BIGTIFF="IF_SAFER",
        )  # fmt: skip

    def write(self, source: np.ndarray, window: Any) -> None:
        self.ds.write(source, window=window)

    def close(self) -> None:
        self.ds.close()

    def finish(self, target: Path, names: Sequence[str]) -> Path:
        """The COG at ``target`` (nearest overviews: a photo number is no average) with its table."""
        import rasterio
        from rasterio.shutil import copy as rio_copy

        self.close()
        with rasterio.open(self.tiled, "r+") as ds:
            ds.set_band_description(1, "photo")
            ds.set_band_description(2, "how")
            ds.update_tags(2, **{f"how_{k}": v for k, v in SOURCE_KINDS.items()})
        with atomic_path(target) as tmp:
            rio_copy(
                self.tiled, tmp, driver="COG", compress="DEFLATE", blocksize=512, overview_resampling="nearest",
                BIGTIFF="IF_SAFER",
            )  # fmt: skip
        _write_attribute_table(target, names)
        write_raster_style(target, how_style())
        return target


def _write_attribute_table(raster: Path, names: Sequence[str]) -> None:
    """Band 1's raster attribute table (photo number -> name) in the raster's ``.aux.xml``."""
    rows = "".join(f'<Row index="{k}"><F>{k + 1}</F><F>{escape(n)}</F></Row>' for k, n in enumerate(names))
    # Type 0 integer, 2 string; usage 5 min-max (the value), 2 name
    xml = (
        '<PAMDataset><PAMRasterBand band="1"><GDALRasterAttributeTable tableType="thematic">'
        '<FieldDefn index="0"><Name>value</Name><Type>0</Type><Usage>5</Usage></FieldDefn>'
        '<FieldDefn index="1"><Name>photo</Name><Type>2</Type><Usage>2</Usage></FieldDefn>'
        f"{rows}</GDALRasterAttributeTable></PAMRasterBand></PAMDataset>\n"
    )
    aux = raster.with_name(raster.name + ".aux.xml")
    with atomic_path(aux) as tmp:
        Path(tmp).write_text(xml, encoding="utf-8")


def _view_angle_deg(cam: PosedCamera) -> float:
    """The camera axis's angle from the vertical (0: nadir)."""
    axis_z = float((cam.pose.rotation @ np.array([0.0, 0.0, 1.0]))[2])
    return float(math.degrees(math.acos(min(1.0, max(-1.0, -axis_z)))))


def write_seamlines(
    source: Path, cams: Sequence[PosedCamera], gsds_m: Sequence[float], taken_at: Sequence[str], target: Path
) -> tuple[Path, int]:
    """One polygon per photo region of ``source`` (band 1) in a GeoPackage at ``target``: the
    photo's name, GSD (cm), view angle (deg), capture time (``taken_at``, ISO 8601, "" when
    unknown), the share of pixels drawn from it that no photo saw (occluded), and its area (m²).
    Returns the file and how many photos it holds."""
    import geopandas as gpd
    import rasterio
    import shapely
    from rasterio.enums import Resampling
    from rasterio.features import shapes

    with rasterio.open(source) as ds:
        scale = max(1.0, math.sqrt(ds.width * ds.height / SEAMLINE_CELLS))
        h, w = max(1, round(ds.height / scale)), max(1, round(ds.width / scale))
        photo = ds.read(1, out_shape=(h, w), resampling=Resampling.nearest)
        how = ds.read(2, out_shape=(h, w), resampling=Resampling.nearest)
        transform = ds.transform @ ds.transform.scale(ds.width / w, ds.height / h)
        crs = ds.crs
    by_photo: dict[int, list[Any]] = {}
    for geom, value in shapes(photo.astype(np.int32), mask=photo > 0, transform=transform, connectivity=8):
        by_photo.setdefault(int(value), []).append(shapely.geometry.shape(geom))
    cell_m2 = abs(transform.a * transform.e)
    counts = np.bincount(photo.ravel(), minlength=len(cams) + 1)
    occluded = np.bincount(photo.ravel(), weights=(how == OCCLUDED).ravel(), minlength=len(cams) + 1)
    rows = []
    for value in sorted(by_photo):
        cam = cams[value - 1]
        rows.append(
            {
                "photo": cam.name,
                "photo_index": value,
                "gsd_cm": round(100.0 * float(gsds_m[value - 1]), 3),
                "view_angle_deg": round(_view_angle_deg(cam), 2),
                "taken_at": taken_at[value - 1],
                "area_m2": round(float(counts[value]) * cell_m2, 2),
                "occluded_share": round(float(occluded[value]) / max(float(counts[value]), 1.0), 4),
                "geometry": shapely.union_all(by_photo[value]),
            }
        )
    frame = (
        gpd.GeoDataFrame(rows, geometry="geometry", crs=crs)
        if rows
        else gpd.GeoDataFrame({"photo": [], "geometry": []}, geometry="geometry", crs=crs)
    )
    write_vector(target, {"seamlines": frame}, styles=product_styles("seamlines"))
    return target, len(rows)
