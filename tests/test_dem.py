"""DSM/DTM against the synthetic truth, the ground filter against producers' labels, units, bad input."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import laspy
import numpy as np
import pytest
import rasterio
from conftest import RecordingFeedback, real_data
from pyproj import CRS
from rasterio.warp import Resampling, reproject
from scipy import ndimage

from geoortho.core.gapfill import fill_harmonic, gap_mask
from geoortho.core.pointcloud import open_points
from geoortho.elevation.gridding import Grid, dem, grid_points
from geoortho.errors import InputError, ParameterError


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
    cell_m = r.resolution_m
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


def test_gaps_filled_by_windows_are_the_whole_grids_gaps():
    """ortho's DSM hole fill, window by window: the same gap cells as gap_mask on the whole grid
    (tiles of 32 cells, so most gaps and the outline cross tile edges), a plane recovered in them,
    the outside and a gap wider than the limit left open."""
    from scipy import ndimage

    from geoortho.core.gapfill import fill_gaps_by_windows

    rng = np.random.default_rng(4)
    rows, cols = np.mgrid[0:300, 0:400]
    plane = (50.0 + 0.03 * cols - 0.02 * rows).astype(np.float32)
    inside = (rows - 150) ** 2 / 140**2 + (cols - 200) ** 2 / 190**2 < 1  # the cloud's outline
    z = np.where(inside, plane, np.nan).astype(np.float32)
    for r, c in rng.integers([20, 20], [280, 380], size=(40, 2)):
        z[r : r + rng.integers(1, 9), c : c + rng.integers(1, 9)] = np.nan  # holes, some on the outline
    z[58:72, 40:130] = np.nan  # 14 cells wide, across tile edges: closed only with the halo's data
    z[180:270, 250:263] = np.nan
    z[140:160, 100:300] = np.nan  # 20 cells wide: wider than 2 x 8, stays open
    filled, n = fill_gaps_by_windows(z, max_gap_cells=8, tile_cells=32)
    known = np.isfinite(z)
    whole = gap_mask(known, 8)
    assert n == int(whole.sum()) > 500
    assert np.array_equal(np.isfinite(filled), known | whole)
    # a plane is harmonic: recovered in gaps enclosed by data; a gap open to the outside is solved
    # with part of the outside free (the whole grid's fill: 0.018 m off the plane there, here 0.023)
    err = np.abs(filled - plane)
    outside = ndimage.binary_dilation(~known & ~whole, structure=np.ones((3, 3), bool))
    labels, _ = ndimage.label(whole, structure=np.ones((3, 3), bool))
    enclosed = whole & ~np.isin(labels, labels[outside & whole])
    assert enclosed.sum() > 400 and err[enclosed].max() < 1e-3
    assert err[whole].max() < 0.03
    assert np.isnan(filled[150, 200]) and np.isnan(filled[0, 0])
    assert np.array_equal(filled[known], z[known])


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
    assert r.resolution_crs_units == pytest.approx(1 / 0.3048)  # 1 m cells, in feet
    assert r.resolution_m == pytest.approx(1.0)
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
    r = dem(
        path, tmp_path / "dsm.tif", points_crs=CRS("EPSG:32610"), ground_method="csf", classified=tmp_path / "c.las"
    )
    truth = np.asarray(laspy.read(path).classification) == 2
    k, _, _ = _kappa(np.asarray(laspy.read(r.classified).classification) == 2, truth)
    assert k >= 0.95, k  # measured 0.986 (SMRF: 0.008)


def test_mvk_thin_units_key_wins_over_the_epsg_code(tmp_path):
    path = real_data("pdal_las") / "mvk-thin.las"
    src = open_points(path)
    assert src.horizontal_unit == "US survey foot" and src.vertical_unit == "US survey foot"
    assert any("ProjLinearUnits" in n for n in src.notes)
    from pyproj import CRS

    from geoortho.core.crs import transformer

    lon, lat = transformer(src.crs, CRS.from_epsg(4326)).transform(2.0475e6, 1.27e6)
    assert -91.7 < lon < -89.3 and 31 < lat < 35.1  # Mississippi, not New Jersey


def test_las_and_laz_give_the_same_dsm(tmp_path):
    d = real_data("pdal_las")
    a = dem(d / "simple.las", tmp_path / "a.tif", points_crs=CRS("EPSG:2992"), resolution_m=5.0)
    b = dem(d / "simple.laz", tmp_path / "b.tif", points_crs=CRS("EPSG:2992"), resolution_m=5.0)
    with rasterio.open(a.dsm) as x, rasterio.open(b.dsm) as y:
        assert np.array_equal(x.read(1), y.read(1))


def test_array_and_ply_input(tmp_path):
    rng = np.random.default_rng(0)
    xyz = np.c_[rng.uniform(500000, 500050, 5000), rng.uniform(4e6, 4e6 + 50, 5000), np.full(5000, 12.5)]
    r = dem(_write_ply(tmp_path / "p.ply", xyz), tmp_path / "p.tif", crs=CRS("EPSG:32629"), resolution_m=2.0)
    with rasterio.open(r.dsm) as ds:
        z = ds.read(1, masked=True)
        assert np.allclose(z.compressed(), 12.5)
    from geoortho.elevation.gridding import grid_points as gp

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
        with pytest.raises(InputError, match="empty|a line or a spot|finite|too few"):
            dem(xyz, out, crs=CRS("EPSG:32629"))
    assert not out.exists() and not list(tmp_path.glob(".*tmp*"))


def test_some_nan_points_are_skipped_with_a_warning(tmp_path):
    rng = np.random.default_rng(1)
    xyz = np.c_[rng.uniform(0, 20, 2000), rng.uniform(0, 20, 2000), rng.uniform(0, 1, 2000)]
    xyz[[5, 17], 2] = np.nan
    fb = RecordingFeedback()
    r = dem(xyz, tmp_path / "d.tif", crs=CRS("EPSG:32629"), resolution_m=1.0, feedback=fb)
    assert r.n_points == 1998 and any("2 points" in w and "index 5" in w for w in fb.warnings)


def test_a_cloud_s_heights_datum_reaches_its_dems_and_a_2d_one_claims_none(tmp_path):
    """A LAS in a compound CRS (lidar delivered in EPSG:xxxx+vvvv) gives DEMs in it; a cloud in a
    2D CRS gives 2D DEMs and says the datum is not stated (issue 77)."""
    import laspy
    import rasterio
    from pyproj import CRS

    from geoortho.core.pointcloud import write_las

    rng = np.random.default_rng(2)
    xyz = np.c_[rng.uniform(0, 30, 6000) + 5e5, rng.uniform(0, 30, 6000) + 4.3e6, rng.uniform(0, 1, 6000)]
    for crs, heights in (("EPSG:32629+5773", [32629, 5773]), ("EPSG:32629", None)):
        las = write_las(tmp_path / f"{heights is None}.laz", xyz, CRS(crs))
        assert CRS(laspy.read(las).header.parse_crs()) == CRS(crs)
        r = dem(las, tmp_path / f"{heights is None}.tif", resolution_m=1.0)
        with rasterio.open(r.dsm) as ds:
            got = CRS(ds.crs.to_wkt())
        assert r.crs == "EPSG:32629" and (r.vertical_crs == "EPSG:5773") == (heights is not None)
        assert [c.to_epsg() for c in got.sub_crs_list] == heights if heights else got.to_epsg() == 32629
        assert any("heights' datum: " + ("EGM96 height" if heights else "not stated") in n for n in r.notes)


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
        dem(np.zeros((5, 3)), tmp_path / "d.tif", crs=CRS("EPSG:32629"), method="median")


@pytest.mark.parametrize("option", [{"resolution_m": -0.1}, {"max_gap_m": -1.0}, {"smooth_px": -2}])
def test_a_negative_option_is_named_for_itself(tmp_path, option):
    # it was named resolution_m whichever of the three was negative
    ((name, value),) = option.items()
    with pytest.raises(ParameterError, match=rf"^{name}: {name} must not be negative") as e:
        dem(np.zeros((5, 3)), tmp_path / "d.tif", crs=CRS("EPSG:32629"), **option)
    assert e.value.name == name and not (tmp_path / "d.tif").exists()


def test_far_outliers_are_dropped_and_the_dsm_is_the_clean_one(tiny_survey, tmp_path):
    """Issue 23 (5): outlier points 100 km away (and one 10 km up) made a 74.5 GiB grid, or with
    the automatic resolution a silent 200 m-cell DSM. Now they are dropped with a warning."""
    import laspy
    import rasterio

    from geoortho.core.pointcloud import write_las

    las = laspy.read(tiny_survey.points)
    xyz = np.c_[las.x, las.y, las.z]
    far = np.vstack([xyz[:10] + [100_000.0, 0.0, 0.0], xyz[10:11] + [0.0, 0.0, 10_000.0]])
    cloud = write_las(tmp_path / "outlier.laz", np.vstack([xyz, far]), las.header.parse_crs())
    fb = RecordingFeedback()
    for name, src in (("clean", tiny_survey.points), ("outliers", cloud)):
        r = dem(src, tmp_path / f"{name}.tif", dtm=tmp_path / f"{name}_dtm.tif", feedback=fb)
    assert any("11 far outlier point(s) dropped" in w and "100.0 km" in w for w in fb.warnings), fb.warnings
    assert any("11 far outlier" in n for n in r.notes)
    for kind in ("", "_dtm"):
        with rasterio.open(tmp_path / f"clean{kind}.tif") as a, rasterio.open(tmp_path / f"outliers{kind}.tif") as b:
            assert a.transform == b.transform and a.shape == b.shape
            assert np.array_equal(a.read(1), b.read(1))


def test_many_points_far_apart_are_data_not_outliers():
    from geoortho.core.pointcloud import open_points
    from geoortho.elevation.extent import scan_extent
    from geoortho.feedback import Feedback

    rng = np.random.default_rng(0)
    a = np.c_[rng.uniform(0, 50, (10_000, 2)), rng.uniform(0, 2, 10_000)]
    block = a[:900] + [20_000.0, 0.0, 0.0]  # a second block 20 km away: 8 % of the points
    scan = scan_extent(open_points(np.vstack([a, block]), CRS("EPSG:32629")), Feedback())
    assert scan.keep is None and scan.src.bounds[3] > 20_000
    # 18 points in two far groups: too rare for the core, too many (> 0.1 %) to be strays
    strays = np.vstack([a[:9] + [20_000.0, 0.0, 0.0], a[9:18] + [0.0, 20_000.0, 0.0]])
    scan = scan_extent(open_points(np.vstack([a, strays]), CRS("EPSG:32629")), Feedback())
    assert scan.keep is None and scan.src.bounds[4] > 20_000 and "kept as data" in scan.notes[-1], scan.notes
    scan = scan_extent(open_points(np.vstack([a, strays[:9]]), CRS("EPSG:32629")), Feedback())
    assert scan.keep is not None and scan.src.bounds[3] < 51 and "9 far outlier" in scan.notes[-1]


def test_grids_that_cannot_fit_or_are_mostly_interpolation_are_refused_first(tiny_survey, tmp_path, monkeypatch):
    """--resolution-m 0.01 on a 72 x 64 m cloud took 7 GB and 9 minutes; 1e-3 asked for 238 GB."""
    import collections

    import psutil

    with pytest.raises(ParameterError, match=r"one point per 2,500 cells.*give 0.052 m or coarser"):
        dem(tiny_survey.points, tmp_path / "dsm.tif", resolution_m=0.01)
    mem = collections.namedtuple("mem", "available")
    monkeypatch.setattr(psutil, "virtual_memory", lambda: mem(2_000_000))
    with pytest.raises(InputError, match=r"more than this machine has free.*give --resolution-m \S+ or coarser"):
        dem(tiny_survey.points, tmp_path / "dsm.tif", resolution_m=0.5)
    assert not (tmp_path / "dsm.tif").exists()


@pytest.mark.parametrize(
    "option, message",
    [
        ({"smrf_cell_m": 0.05}, r"smrf_cell_m: .*would take ~2.4 h: give 0.085 m or coarser"),
        ({"max_gap_m": 1e9}, None),
        ({"smrf_window_m": 1e6}, None),
    ],
)
def test_parameters_at_their_extremes_finish_or_are_refused_at_once(tiny_survey, tmp_path, option, message):
    """--smrf-cell-m 0.05 ran 15 minutes, --smrf-window-m 1e6 over 3, --max-gap-m 1e9 ran out of memory."""
    import time

    t = time.perf_counter()
    if message:
        with pytest.raises(ParameterError, match=message):
            dem(tiny_survey.points, tmp_path / "dsm.tif", dtm=tmp_path / "dtm.tif", **option)
    else:
        r = dem(tiny_survey.points, tmp_path / "dsm.tif", dtm=tmp_path / "dtm.tif", **option)
        assert r.dtm is not None and r.dtm.exists()
    assert time.perf_counter() - t < 60


@pytest.mark.parametrize("case", ["line", "x_scale_0"])
def test_points_without_an_area_are_refused(tiny_survey, tmp_path, case):
    """Points on a line gave an np.gradient error; a header X scale of 0 a one-column DSM, exit 0."""
    import struct

    import laspy

    from geoortho.core.pointcloud import write_las

    if case == "line":
        t = np.linspace(0, 30, 500)
        cloud = write_las(tmp_path / "line.laz", np.c_[483600 + t, 4288780 + 0 * t, 110 + 0 * t], CRS("EPSG:32629"))
    else:
        data = bytearray(Path(tiny_survey.points).read_bytes())
        assert laspy.open(tiny_survey.points).header.version.minor >= 2
        data[131:139] = struct.pack("<d", 0.0)  # the X scale factor of a LAS 1.2-1.4 header
        cloud = tmp_path / "x0.laz"
        cloud.write_bytes(data)
    with pytest.raises(InputError, match="a line or a spot, not an area"):
        dem(cloud, tmp_path / "dsm.tif")
    assert not (tmp_path / "dsm.tif").exists()


def test_a_grid_made_in_tiles_is_the_whole_grid(small_survey, tmp_path, monkeypatch):
    """Tiles (here forced small: 6 of them, halo and all) give the DSM, DTM and ground classes of
    the whole grid; only where the harmonic fill's iterations meet a tile's halo may a filled
    cell differ, by its convergence (millimetres)."""
    import geoortho.elevation.tiles as demtiles

    whole = dem(small_survey.points, tmp_path / "w.tif", dtm=tmp_path / "w_dtm.tif", classified=tmp_path / "w.laz")
    monkeypatch.setattr(demtiles, "WHOLE_GRID_MAX_CELLS", 0)
    monkeypatch.setattr(demtiles, "TILE_CELLS", 64)
    fb = RecordingFeedback()
    tiled = dem(
        small_survey.points,
        tmp_path / "t.tif",
        dtm=tmp_path / "t_dtm.tif",
        classified=tmp_path / "t.laz",
        hillshade=tmp_path / "t.png",
        feedback=fb,
    )
    assert any("tiles" in n for n in tiled.notes) and any("made in" in m for m in fb.infos)
    assert (tiled.n_points, tiled.n_ground) == (whole.n_points, whole.n_ground)
    for w, t in (("w.tif", "t.tif"), ("w_dtm.tif", "t_dtm.tif")):
        with rasterio.open(tmp_path / w) as a, rasterio.open(tmp_path / t) as b:
            assert a.profile == b.profile and a.descriptions == b.descriptions and a.units == b.units
            za, zb = a.read(1).astype(float), b.read(1).astype(float)
        assert np.array_equal(za == -9999, zb == -9999)
        assert np.abs(za - zb).max() <= 0.005, w
    ca = np.asarray(laspy.read(tmp_path / "w.laz").classification)
    cb = np.asarray(laspy.read(tmp_path / "t.laz").classification)
    assert np.array_equal(ca, cb)
    assert (tmp_path / "t.png").stat().st_size > 1000


@pytest.mark.parametrize("coarse_max_cells", [10**9, 16_000])  # the coarse grid the whole grid's cells; 4x coarser
def test_gaps_wider_than_a_tiles_halo_are_filled_as_in_the_whole_grid(tmp_path, monkeypatch, coarse_max_cells):
    """Holes of 6-64 m, a bay and a long 3 m slot in a cloud at 0.25 m cells, made in tiles of 16 m
    whose gap-fill halo (4 m) is far short of what a 25 m gap reaches (50 m): tiles wholly inside a
    hole, gaps crossing tile edges, a hole too wide to fill whole. The gaps filled are the whole
    grid's (to a coarse cell at the outline) and their values are the whole grid's within the
    harmonic fill's convergence."""
    from scipy import ndimage

    import geoortho.elevation.tiles as demtiles

    rng = np.random.default_rng(5)
    x, y = rng.uniform(0, 160, 500_000), rng.uniform(0, 100, 500_000)
    keep = ~((x < 10) & (np.abs(y - 70) < 12))  # a bay 24 m wide: closed by a 25 m disc
    keep &= ~((np.abs(x - 60) < 1.5) & (y > 10) & (y < 90))
    for cx, cy, r in ((20, 20, 3), (35, 50, 9), (110, 50, 32)):
        keep &= np.hypot(x - cx, y - cy) > r
    x, y = x[keep], y[keep]
    xyz = np.c_[x + 483_000, y + 4_288_000, 100 + 0.05 * x + 2 * np.sin(y / 15) + 0.5 * np.cos(x / 9)]
    kw = dict(points_crs=CRS("EPSG:32629"), resolution_m=0.25, method="mean")
    dem(xyz, tmp_path / "w.tif", dtm=tmp_path / "w_dtm.tif", **kw)
    monkeypatch.setattr(demtiles, "WHOLE_GRID_MAX_CELLS", 0)
    monkeypatch.setattr(demtiles, "TILE_CELLS", 64)
    monkeypatch.setattr(demtiles, "HALO_MAX_CELLS", 16)
    monkeypatch.setattr(demtiles, "COARSE_MAX_CELLS", coarse_max_cells)
    fb = RecordingFeedback()
    dem(xyz, tmp_path / "t.tif", dtm=tmp_path / "t_dtm.tif", feedback=fb, **kw)
    f = 1 if coarse_max_cells > 10**6 else 4
    assert any(f"held at a {f}x coarser grid's fill" in m for m in fb.infos), fb.infos
    for w, t in (("w.tif", "t.tif"), ("w_dtm.tif", "t_dtm.tif")):
        with rasterio.open(tmp_path / w) as a, rasterio.open(tmp_path / t) as b:
            za, zb = a.read(1).astype(float), b.read(1).astype(float)
        ka, kb = za != -9999, zb != -9999
        assert (~ka[100:300, 400:480]).sum() > 1000  # the premise: the 64 m hole's centre is left...
        # ...outline cells may differ within a coarse cell (two at least) of the whole grid's outline
        differ = ka != kb
        # measured: 1 % at 4x (under-filled by up to 0.25 m at the edge of the 64 m hole's centre)
        assert differ.sum() <= 0.02 * ka.sum(), differ.sum()
        near_outline = ndimage.binary_dilation(ka, iterations=2 * f) & ~ndimage.binary_erosion(ka, iterations=2 * f)
        assert not (differ & ~near_outline).any()
        both = ka & kb
        err = np.abs(za - zb)[both]
        assert err.max() < 0.1 and np.sqrt(np.mean(err**2)) < 0.005, (err.max(), np.sqrt(np.mean(err**2)))


def test_output_crs_reprojects_and_points_crs_overrides(tmp_path):
    """Issue 26: dem --crs is the output CRS (points reprojected before gridding, heights unchanged);
    --points-crs says what the points are in. A smooth surface in UTM 29N made in PT-TM06 matches
    the surface evaluated at each cell centre."""
    from pyproj import CRS

    from geoortho.core.crs import transformer

    rng = np.random.default_rng(3)
    x = rng.uniform(483_000, 483_200, 400_000)
    y = rng.uniform(4_288_000, 4_288_150, 400_000)

    def surface(x, y):
        return 100.0 + 0.05 * (x - 483_000) + 3.0 * np.sin((y - 4_288_000) / 20.0)

    xyz = np.c_[x, y, surface(x, y)]
    r = dem(
        xyz, tmp_path / "pt.tif", points_crs=CRS("EPSG:32629"), crs=CRS("EPSG:3763"), resolution_m=1.0, method="mean"
    )
    with rasterio.open(r.dsm) as src:
        assert CRS(src.crs).to_epsg() == 3763
        z = src.read(1, masked=True)
        rows, cols = np.nonzero(~np.ma.getmaskarray(z))
        cx, cy = rasterio.transform.xy(src.transform, rows, cols)
    ux, uy = transformer(CRS.from_epsg(3763), CRS.from_epsg(32629)).transform(np.asarray(cx), np.asarray(cy))
    err = z.compressed() - surface(ux, uy)
    inner = (ux > 483_005) & (ux < 483_195) & (uy > 4_288_005) & (uy < 4_288_145)
    assert np.sqrt(np.mean(err[inner] ** 2)) < 0.05  # a placement error of 1 m would be ~0.1 m RMS
    assert any("reprojected" in n for n in r.notes)
    # The old meaning (--crs naming a wrong CRS of the points) is caught: they lie outside it.
    with pytest.raises(InputError, match="--points-crs"):
        dem(xyz, tmp_path / "x.tif", points_crs=CRS("EPSG:3763"), crs=CRS("EPSG:32629"), resolution_m=1.0)
    # Points without a CRS: --crs alone is theirs, as before.
    r2 = dem(xyz[:50_000], tmp_path / "same.tif", crs=CRS("EPSG:32629"), resolution_m=2.0)
    assert "32629" in r2.crs and not any("reprojected" in n for n in r2.notes)


def test_auto_method_is_idw_for_a_cloud_from_photos_and_max_for_lidar(tmp_path):
    """A photo cloud is one noisy surface: a cell's highest point stands above it (the free-heading
    survey: +1.1 GSD gridded by max). dem's default grids a cloud dense made (its report beside it)
    by the distance-weighted mean, any other cloud by max, and says which."""
    rng = np.random.default_rng(5)
    n = 40_000
    xyz = np.c_[rng.uniform(500000, 500040, n), rng.uniform(4e6, 4e6 + 40, n), 10 + rng.normal(0, 0.05, n)]
    ply = _write_ply(tmp_path / "cloud.ply", xyz)
    lidar = dem(ply, tmp_path / "lidar.tif", crs=CRS("EPSG:32629"), resolution_m=0.5)
    (tmp_path / "cloud_report.json").write_text(json.dumps({"photos": 3, "depth_maps": 3}))  # dense's
    photos = dem(ply, tmp_path / "photos.tif", crs=CRS("EPSG:32629"), resolution_m=0.5)
    assert any("method auto: max" in n for n in lidar.notes) and any("method auto: idw" in n for n in photos.notes)
    with rasterio.open(lidar.dsm) as a, rasterio.open(photos.dsm) as b:
        high, mean = a.read(1, masked=True).mean(), b.read(1, masked=True).mean()
    assert high - 10 > 0.04 and abs(mean - 10) < 0.01  # max of ~6 points: 1.3 sigma high; idw: on the surface
    explicit = dem(ply, tmp_path / "max.tif", crs=CRS("EPSG:32629"), resolution_m=0.5, method="max")
    assert not any("method auto" in n for n in explicit.notes)


def test_the_compiled_fills_and_sums_are_the_numpy_paths(monkeypatch):
    """The gap fill's sweeps and the distance-weighted gridding, compiled, give what their numpy
    paths give: the same cells, the same heights to rounding (sums in another order)."""
    from geoortho.core import gapfill
    from geoortho.core import kernels as loader
    from geoortho.elevation import grid as gridding

    rng = np.random.default_rng(7)
    h, w = 300, 420  # over COMPILED_MIN_CELLS
    yy, xx = np.mgrid[0:h, 0:w]
    z = 0.02 * xx - 0.01 * yy + np.sin(xx / 17.0)
    known = rng.random((h, w)) > 0.4
    known[60:200, 100:300] = False  # a gap the pyramid must cross
    known[:, :3] = False  # and the border
    x, y = rng.uniform(0.0, 40.0, (2, gridding.COMPILED_MIN_POINTS + 7))
    pz = np.sin(x) + y / 10.0
    g = gridding.Grid.covering(0.0, 0.0, 40.0, 40.0, 0.3)
    got = {}
    for switch in ("1", "0"):
        monkeypatch.setenv(loader.ENV_SWITCH, switch)
        got[switch] = (gapfill.fill_harmonic(z, known), gridding.grid_points(x, y, pz, g, "idw"))
    assert loader.compiled(gapfill._sor_sweeps) is None  # switched off: the numpy paths ran
    monkeypatch.setenv(loader.ENV_SWITCH, "1")
    if loader.compiled(gapfill._sor_sweeps) is None:
        pytest.skip("numba is not importable here: only the numpy paths")
    for a, b in zip(got["1"], got["0"]):
        assert np.array_equal(np.isnan(a), np.isnan(b))
        assert np.nanmax(np.abs(a - b)) < 1e-9
    filled = got["0"][0][~known]
    assert np.isfinite(filled).all() and np.nanstd(filled) > 0.1  # a real fill, not a constant
