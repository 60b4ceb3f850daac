"""Real files through QGIS: lidar in feet, DJI photos with defects and lying EXIF sizes."""

from __future__ import annotations

import json
from pathlib import Path

import geopandas as gpd
import numpy as np
import pytest
import rasterio
from conftest import geoortho_cli, qgis_run
from realdata import real_data


def test_feet_lidar_dsm_opens_in_qgis_in_feet(provider, tmp_path):
    from qgis.core import Qgis, QgsRasterLayer

    las = real_data("pdal_las") / "autzen_trim.las"
    r = qgis_run("dem", {"POINTS": str(las), "OUTPUT": str(tmp_path / "dsm.tif")})
    assert r["UNITS"] == "horizontal foot, vertical foot"
    layer = QgsRasterLayer(r["OUTPUT"], "dsm")
    assert layer.isValid() and layer.crs().isValid()
    assert layer.crs().mapUnits() == Qgis.DistanceUnit.Feet  # QGIS reads the CRS we wrote, feet and all
    assert layer.rasterUnitsPerPixelX() == pytest.approx(1 / 0.3048)  # 1 m cells, in feet
    stats = layer.dataProvider().bandStatistics(1)
    assert 400 < stats.minimumValue and stats.maximumValue < 530  # feet, as the header says
    geoortho_cli("dem", "--points", str(las), "--output", str(tmp_path / "cli.tif"), "--quiet")
    with rasterio.open(r["OUTPUT"]) as a, rasterio.open(tmp_path / "cli.tif") as b:
        assert a.crs == b.crs and np.array_equal(a.read(1), b.read(1))


@pytest.mark.parametrize("folder, n_skipped", [("dji_mini4pro_defects", 1), ("toledo_dji", 0)])
def test_real_photos_footprints_as_on_the_command_line(provider, tmp_path, folder, n_skipped):
    images = real_data(folder) / "images"
    from qgis.core import QgsProcessingFeedback

    feedback = QgsProcessingFeedback()
    r = qgis_run("footprints", {"IMAGES": str(images), "OUTPUT": str(tmp_path / "q.gpkg")}, feedback)
    cli = json.loads(geoortho_cli("footprints", "--images", str(images), "--output", str(tmp_path / "c.gpkg"),
                                  "--json", "--quiet").stdout)
    assert r["N_SKIPPED"] == cli["n_skipped"] == n_skipped
    assert r["N_PHOTOS"] == cli["n_photos"] > 0
    log = feedback.textLog()
    if n_skipped:  # the bad photo is reported in QGIS's log, by name, and the rest go on
        assert "skipped DJI_20251001132715_0396_D_POOR_SHARPNESS.JPG" in log
    a = gpd.read_file(tmp_path / "q.gpkg", layer="footprints").sort_values("image")
    b = gpd.read_file(Path(cli["output"]), layer="footprints").sort_values("image")
    assert list(a["image"]) == list(b["image"])
    assert a.geometry.reset_index(drop=True).symmetric_difference(b.geometry.reset_index(drop=True)).area.max() < 1e-6
