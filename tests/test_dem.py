"""DSM/DTM against the synthetic truth, the ground filter against producers' labels, units, bad input."""

from __future__ import annotations

import json
import subprocess
import sys

import laspy
import numpy as np
import pytest
import rasterio
from conftest import RecordingFeedback, real_data
from rasterio.warp import Resampling, reproject
from scipy import ndimage

from geoortho.elevation import Grid, dem, grid_points
from geoortho.errors import InputError, ParameterError
from geoortho.gapfill import fill_harmonic, gap_mask
from geoortho.pointcloud import open_points


def _on_our_grid(truth_path, ours_path, resampling=Resampling.average):
    with rasterio.open(ours_path) as o:
        z = o.read(1, masked=True).filled(np.nan).astype(float)
        tr, crs = o.transform, o.crs
    out = np.full(z.shape, np.nan)
    with rasterio.open(truth_path) as t:
        reproject(rasterio.band(t, 1), out, dst_transform=tr, dst_crs=crs, resampling=resampling, dst_nodata=np.nan)
    return z, out


def _kappa(pred, truth):
    n = len(pred)
    tp, tn = np.sum(pred & truth), np.sum(~pred & ~truth)
    fp, fn = np.sum(pred & ~truth), np.sum(~pred & truth)
    po = (tp + tn) / n
    pe = ((tp + fp) * (tp + fn) + (tn + fn) * (tn + fp)) / n**2
    return (po - pe) / (1 - pe), fn / max(1, tp + fn), fp / max(1, tn + fp)


def test_small_dsm_and_dtm_against_truth(small_survey, tmp_path):
    r = dem(
        small_survey.points,
        tmp_path / "dsm.tif",
        dtm=tmp_path / "dtm.tif",
        classified=tmp_path / "c.laz",
        hillshade=tmp_path / "hs.png",
    )
    cell_m = r.resolution
    assert cell_m == 0.5  # about two points per cell at 12 points/m²
    z, truth = _on_our_grid(small_survey.dsm, r.dsm)
    _, tmax = _on_our_grid(small_survey.dsm, r.dsm, Resampling.max)
    _, tmin = _on_our_grid(small_survey.dsm, r.dsm, Resampling.min)
    ok = np.isfinite(z) & np.isfinite(truth)
    assert ok.mean() > 0.99
    edge = ndimage.maximum_filter(np.nan_to_num(tmax - tmin), 3) > 1.0
    rmse_flat = np.sqrt(np.mean((z - truth)[ok & ~edge] ** 2))
    assert rmse_flat <= 0.5 * cell_m  # measured 0.07 m
    # At building edges a cell holds roof and ground: its value must lie between the two (about
    # three points per cell sometimes miss the roof: measured 90 % within, RMSE 1.7 m vs the true
    # highest point), and nothing may overshoot the true surface (no ringing).
    strict = (tmax - tmin) > 1.0
    inside = (z >= tmin - 0.05) & (z <= tmax + 0.05)
    assert inside[ok & strict].mean() >= 0.85
    # (the points sample the continuous scene, the truth raster is 0.25 m cells: 0.2 % of cells,
    # all on roof edges, differ by more than 0.5 m)
    assert np.mean(z[ok] > tmax[ok] + 0.5) < 0.005
    zt, tdtm = _on_our_grid(small_survey.dtm, r.dtm)
    okt = np.isfinite(zt) & np.isfinite(tdtm)
    assert okt.mean() > 0.99
    assert np.sqrt(np.mean((zt - tdtm)[okt] ** 2)) <= 0.3  # buildings and trees removed (measured 0.08 m)
    with rasterio.open(r.dsm) as ds:
        assert ds.crs.to_epsg() == 32629 and ds.nodata == -9999 and ds.dtypes[0] == "float32"
        assert ds.units[0] == "m"
        assert ds.tags(ns="IMAGE_STRUCTURE") | {"INTERLEAVE": "BAND"} == {
            "LAYOUT": "COG",
            "COMPRESSION": "DEFLATE",
            "INTERLEAVE": "BAND",
            "PREDICTOR": "3",
        }
    # ground classes written back, agreeing with the truth's labels
    truth_cls = laspy.read(small_survey.points).classification == 2
    ours = laspy.read(r.classified)
    assert len(ours.x) == len(truth_cls)
    k, type1, type2 = _kappa(np.asarray(ours.classification) == 2, np.asarray(truth_cls))
    assert k >= 0.85, (k, type1, type2)
    import cv2

    assert cv2.imread(str(r.hillshade), cv2.IMREAD_UNCHANGED).shape[2] == 4


def test_harmonic_fill_has_no_ringing_and_respects_max_gap():
    # a step edge with a hole across it: an IDW + smoothing fill overshoots, a harmonic one cannot
    z = np.where(np.arange(60)[None, :] < 30, 100.0, 110.0) * np.ones((60, 1))
    known = np.ones_like(z, bool)
    known[20:40, 20:40] = False
    known[:, 55:] = False  # outside the cloud
    filled = fill_harmonic(z, known, gap_mask(known, 15))
    hole = filled[20:40, 20:40]
    assert np.isfinite(hole).all()
    assert hole.min() >= 100.0 - 1e-9 and hole.max() <= 110.0 + 1e-9
    assert np.isnan(filled[:, 58]).all()  # the outside stays nodata
    # a smooth (linear) surface is recovered exactly in the hole
    ramp = np.add.outer(np.arange(60) * 0.2, np.arange(60) * 0.1)
    k = np.ones_like(ramp, bool)
    k[10:50, 10:50] = False
    assert np.abs(fill_harmonic(ramp, k)[10:50, 10:50] - ramp[10:50, 10:50]).max() < 0.02
    # a gap wider than twice max_gap stays open
    assert not gap_mask(k, 5)[30, 30] and gap_mask(k, 25)[30, 30]


def test_gridding_methods_by_hand():
    g = Grid.covering(0.0, 0.01, 1.99, 0.99, 1.0)
    assert (g.rows, g.cols) == (1, 2)
    x = np.array([0.2, 0.7, 1.5])
    y = np.array([0.5, 0.5, 0.5])
    z = np.array([1.0, 3.0, 7.0])
    assert grid_points(x, y, z, g, "max").tolist() == [[3.0, 7.0]]
    assert grid_points(x, y, z, g, "min").tolist() == [[1.0, 7.0]]
    assert grid_points(x, y, z, g, "mean").tolist() == [[2.0, 7.0]]
    assert grid_points(x, y, z, g, "count").tolist() == [[2.0, 1.0]]
    idw = grid_points(x, y, z, g, "idw")
    assert 1.0 < idw[0, 0] < 7.0 and idw[0, 1] > idw[0, 0]


def test_autzen_feet_and_ground_filter(tmp_path):
    path = real_data("pdal_las") / "autzen_trim.las"
    r = dem(path, tmp_path / "dsm.tif", dtm=tmp_path / "dtm.tif", classified=tmp_path / "c.las")
    assert r.units == "horizontal foot, vertical foot"
    assert r.resolution == pytest.approx(1 / 0.3048)  # 1 m cells, in feet
    with rasterio.open(r.dsm) as ds:
        assert ds.crs.linear_units in ("foot", "Foot") or "ft" in ds.crs.linear_units.lower()
        assert ds.units[0] == "ft"
        z = ds.read(1, masked=True)
        assert 400 < z.min() and z.max() < 530  # feet, as in the header (406-521)
    # the producer's class 2: the DTM made from them and ours agree where both have ground
    las = laspy.read(path)
    g = np.asarray(las.classification) == 2
    ref = dem(
        path, tmp_path / "ref_dsm.tif", dtm=tmp_path / "ref_dtm.tif", ground_method="classification", max_gap_m=5.0
    )
    with rasterio.open(r.dtm) as a, rasterio.open(ref.dtm) as b:
        da, db = a.read(1, masked=True), b.read(1, masked=True)
    both = ~da.mask & ~db.mask
    rmse_ft = float(np.sqrt(np.mean((da - db)[both] ** 2)))
    assert rmse_ft < 1.0, rmse_ft  # < 0.3 m
    # no producer ground point is called non-ground (type I error); their class 1 holds much bare
    # ground too (kappa against it is low: see the issue note), so type II is not a measure here
    ours = np.asarray(laspy.read(r.classified).classification) == 2
    _, type1, _ = _kappa(ours, g)
    assert type1 < 0.01


def test_4_6_crop_us_feet_kappa(tmp_path):
    path = real_data("pdal_las") / "4_6_crop.las"
    r = dem(path, tmp_path / "dsm.tif", classified=tmp_path / "c.laz")
    assert r.units == "horizontal US survey foot, vertical US survey foot"
    with rasterio.open(r.dsm) as ds:
        assert ds.crs.to_epsg() == 2903
    k, _, _ = _kappa(
        np.asarray(laspy.read(r.classified).classification) == 2, np.asarray(laspy.read(path).classification) == 2
    )
    assert k >= 0.9, k  # measured 0.95


def test_csf_on_a_building_dominated_tile(tmp_path):
    # sample_c: one building covers most of the tile; SMRF's 18 m window cannot remove it, CSF can
    pytest.importorskip("CSF", reason="cloth-simulation-filter is in the dev extra")
    path = real_data("pdal_las") / "sample_c.las"
    r = dem(path, tmp_path / "dsm.tif", crs="EPSG:32610", ground_method="csf", classified=tmp_path / "c.las")
    truth = np.asarray(laspy.read(path).classification) == 2
    k, _, _ = _kappa(np.asarray(laspy.read(r.classified).classification) == 2, truth)
    assert k >= 0.95, k  # measured 0.986 (SMRF: 0.008)


def test_mvk_thin_units_key_wins_over_the_epsg_code(tmp_path):
    path = real_data("pdal_las") / "mvk-thin.las"
    src = open_points(path)
    assert src.horizontal_unit == "US survey foot" and src.vertical_unit == "US survey foot"
    assert any("ProjLinearUnits" in n for n in src.notes)
    from pyproj import CRS

    from geoortho.crs import transformer

    lon, lat = transformer(src.crs, CRS.from_epsg(4326)).transform(2.0475e6, 1.27e6)
    assert -91.7 < lon < -89.3 and 31 < lat < 35.1  # Mississippi, not New Jersey


def test_las_and_laz_give_the_same_dsm(tmp_path):
    d = real_data("pdal_las")
    a = dem(d / "simple.las", tmp_path / "a.tif", crs="EPSG:2992", resolution_m=5.0)
    b = dem(d / "simple.laz", tmp_path / "b.tif", crs="EPSG:2992", resolution_m=5.0)
    with rasterio.open(a.dsm) as x, rasterio.open(b.dsm) as y:
        assert np.array_equal(x.read(1), y.read(1))


def test_array_and_ply_input(tmp_path):
    rng = np.random.default_rng(0)
    xyz = np.c_[rng.uniform(500000, 500050, 5000), rng.uniform(4e6, 4e6 + 50, 5000), np.full(5000, 12.5)]
    r = dem(_write_ply(tmp_path / "p.ply", xyz), tmp_path / "p.tif", crs="EPSG:32629", resolution_m=2.0)
    with rasterio.open(r.dsm) as ds:
        z = ds.read(1, masked=True)
        assert np.allclose(z.compressed(), 12.5)
    from geoortho.elevation import grid_points as gp

    g = Grid.covering(500000, 4e6, 500050, 4e6 + 50, 2.0)
    assert np.nanmax(gp(xyz[:, 0], xyz[:, 1], xyz[:, 2], g)) == 12.5


def _write_ply(path, xyz):
    from plyfile import PlyData, PlyElement

    v = np.array([tuple(p) for p in xyz], dtype=[("x", "f8"), ("y", "f8"), ("z", "f4")])
    PlyData([PlyElement.describe(v, "vertex")]).write(str(path))
    return path


@pytest.mark.parametrize("case", ["empty", "one", "equal", "nan", "nocrs"])
def test_bad_input_clear_errors_no_file(tmp_path, case):
    out = tmp_path / "dsm.tif"
    if case == "nocrs":
        with pytest.raises(InputError, match="no CRS"):
            dem(real_data("pdal_las") / "sample_c.las", out)
    else:
        xyz = {
            "empty": np.zeros((0, 3)),
            "one": np.array([[1.0, 2.0, 3.0]]),
            "equal": np.tile([1.0, 2.0, 3.0], (50, 1)),
            "nan": np.full((10, 3), np.nan),
        }[case]
        with pytest.raises(InputError, match="empty|one .* cell|finite|too few"):
            dem(xyz, out, crs="EPSG:32629")
    assert not out.exists() and not list(tmp_path.glob(".*tmp*"))


def test_some_nan_points_are_skipped_with_a_warning(tmp_path):
    rng = np.random.default_rng(1)
    xyz = np.c_[rng.uniform(0, 20, 2000), rng.uniform(0, 20, 2000), rng.uniform(0, 1, 2000)]
    xyz[[5, 17], 2] = np.nan
    fb = RecordingFeedback()
    r = dem(xyz, tmp_path / "d.tif", crs="EPSG:32629", resolution_m=1.0, feedback=fb)
    assert r.n_points == 1998 and any("2 points" in w and "index 5" in w for w in fb.warnings)


def test_cli_dem_and_bad_parameter(tmp_path):
    path = real_data("pdal_las") / "4_6_crop.las"
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "geoortho",
            "dem",
            "--points",
            str(path),
            "--output",
            str(tmp_path / "d.tif"),
            "--json",
            "--quiet",
        ],
        capture_output=True,
        text=True,
    )
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["units"].startswith("horizontal US survey foot")
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "geoortho",
            "dem",
            "--points",
            str(tmp_path / "none.las"),
            "--output",
            str(tmp_path / "d2.tif"),
        ],
        capture_output=True,
        text=True,
    )
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1 and "none.las" in r.stderr


def test_pdal_engine_or_clear_reason(tmp_path):
    pytest.importorskip(
        "pdal", reason="PDAL cannot be installed on Debian 12 (no libpdal); the native engine is the default"
    )
    path = real_data("pdal_las") / "4_6_crop.las"
    a = dem(path, tmp_path / "a.tif", engine="pdal")
    b = dem(path, tmp_path / "b.tif")
    with rasterio.open(a.dsm) as x, rasterio.open(b.dsm) as y:
        assert np.nanmax(np.abs(x.read(1, masked=True) - y.read(1, masked=True))) < 0.5


def test_unknown_method_is_a_parameter_error(tmp_path):
    with pytest.raises(ParameterError):
        dem(np.zeros((5, 3)), tmp_path / "d.tif", crs="EPSG:32629", method="median")


def test_a_grid_that_cannot_fit_is_refused_before_allocating_with_a_resolution_that_fits(tiny_survey, tmp_path):
    """Issue 23 (5): one outlier point 100 km away with an explicit resolution asked for 74.5 GiB
    (MemoryError); --resolution-m 1e-3 too. Now one line, before any allocation."""
    import laspy

    from geoortho.pointcloud import write_las

    las = laspy.read(tiny_survey.points)
    xyz = np.c_[las.x, las.y, las.z]
    xyz = np.vstack([xyz, xyz[:1] + [100_000.0, 0.0, 0.0]])
    cloud = write_las(tmp_path / "outlier.laz", xyz, las.header.parse_crs())
    with pytest.raises(InputError) as e:
        dem(cloud, tmp_path / "dsm.tif", resolution_m=0.01)
    msg = str(e.value)
    assert "give --resolution-m" in msg and "outlier" in msg and "outlier.laz" in msg, msg
    assert not (tmp_path / "dsm.tif").exists()
    with pytest.raises(InputError, match="give --resolution-m"):
        dem(tiny_survey.points, tmp_path / "dsm.tif", resolution_m=1e-4)
