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


def test_sea_level_altitudes_refused_in_qgis_as_on_the_command_line(provider, tmp_path):
    """Mini 4 Pro frames with XMP stripped to AbsoluteAltitude (348 and 1190 m) and no RelativeAltitude:
    no height above ground to be had, so QGIS shows geoortho's one line naming what to give."""
    from qgis.core import QgsProcessingException

    images = real_data("dji_mini4pro_defects") / "images"
    with pytest.raises(QgsProcessingException, match="flight_height_m"):
        qgis_run("footprints", {"IMAGES": str(images), "OUTPUT": str(tmp_path / "q.gpkg")})
    cli = geoortho_cli("footprints", "--images", str(images), "--output", str(tmp_path / "c.gpkg"), check=False)
    # the command line names the option by its flag; QGIS's line (above) is the machine face's
    assert cli.returncode == 2 and "--flight-height-m" in cli.stderr and "flight_height_m" not in cli.stderr
    assert not (tmp_path / "q.gpkg").exists() and not (tmp_path / "c.gpkg").exists()


@pytest.mark.parametrize("folder, flight_height_m", [("dji_mini4pro_defects", 100.0), ("toledo_dji", None)])
def test_real_photos_footprints_as_on_the_command_line(provider, tmp_path, folder, flight_height_m):
    images = real_data(folder) / "images"
    from qgis.core import QgsProcessingFeedback

    feedback = QgsProcessingFeedback()
    params = {"IMAGES": str(images), "OUTPUT": str(tmp_path / "q.gpkg")}
    args = ["--images", str(images), "--output", str(tmp_path / "c.gpkg"), "--json", "--quiet"]
    if flight_height_m is not None:
        params["FLIGHT_HEIGHT_M"] = flight_height_m
        args += ["--flight-height-m", str(flight_height_m)]
    r = qgis_run("footprints", params, feedback)
    cli = json.loads(geoortho_cli("footprints", *args).stdout)
    assert r["N_SKIPPED"] == cli["n_skipped"] == 0
    assert r["N_PHOTOS"] == cli["n_photos"] > 0
    assert r["HEIGHT_SOURCE"] == cli["height_source"]
    if flight_height_m is not None:  # said, in QGIS's log too
        assert "flight height given" in r["HEIGHT_SOURCE"] and "flight height given" in feedback.textLog()
    a = gpd.read_file(tmp_path / "q.gpkg", layer="footprints").sort_values("image")
    b = gpd.read_file(Path(cli["output"]), layer="footprints").sort_values("image")
    assert list(a["image"]) == list(b["image"])
    assert a.geometry.reset_index(drop=True).symmetric_difference(b.geometry.reset_index(drop=True)).area.max() < 1e-6
