"""The dense stage against the synthetic truth: a DSM from the photos alone."""

from __future__ import annotations

import json

import numpy as np
import pytest
import rasterio
from rasterio.warp import Resampling, reproject
from scipy import ndimage

import geoortho


def _on_grid(path, transform, crs, shape):
    out = np.full(shape, np.nan, np.float32)
    with rasterio.open(path) as src:
        reproject(
            rasterio.band(src, 1),
            out,
            dst_transform=transform,
            dst_crs=crs,
            resampling=Resampling.bilinear,
            dst_nodata=np.nan,
        )
    return out


@pytest.fixture(scope="module")
def dense_small(sfm_with_gcps, small_survey, tmp_path_factory):
    r_sfm, _ = sfm_with_gcps
    d = tmp_path_factory.mktemp("dense")
    return geoortho.dense(r_sfm.output, small_survey.images, d / "dense.laz"), d


def test_dense_dsm_against_the_true_dsm(dense_small, small_survey):
    r, d = dense_small
    info = json.loads((small_survey.truth / "survey.json").read_text())
    gsd = info["gsd_cm_at_home_height"] / 100
    report = json.loads(r.report.read_text())
    assert r.n_depth_maps == report["depth_maps"] >= 0.9 * small_survey.n_photos
    assert report["points_written"] == r.n_points > 0 and r.crs == small_survey.crs
    dsm = geoortho.dem(r.output, d / "dsm.tif", resolution_m=2 * gsd, max_gap_m=0)
    with rasterio.open(dsm.dsm) as src:
        z = src.read(1, masked=True).filled(np.nan)
        transform, crs = src.transform, src.crs
    true_dsm = _on_grid(small_survey.dsm, transform, crs, z.shape)
    true_dtm = _on_grid(small_survey.dtm, transform, crs, z.shape)
    rows, cols = np.indices(z.shape)
    xs, ys = transform * (cols + 0.5, rows + 0.5)
    fx0, fy0, fx1, fy1 = info["flight_box"]
    flown = (xs >= fx0) & (xs <= fx1) & (ys >= fy0) & (ys <= fy1)
    height = true_dsm - true_dtm
    open_ground = flown & (ndimage.maximum_filter(height, 5) < 0.2)
    roofs = flown & (ndimage.minimum_filter(height, 5) > 3.0)
    dz = z - true_dsm
    assert np.isfinite(z[flown]).mean() >= 0.95  # completeness before any gap fill
    ground = dz[open_ground & np.isfinite(dz)]
    assert np.median(np.abs(ground)) <= 1.5 * gsd
    assert np.sqrt(np.mean(ground**2)) <= 3 * gsd
    roof = dz[roofs & np.isfinite(dz)]
    assert roof.size > 1000 and abs(np.median(roof)) <= 0.3


def test_dense_refuses_a_model_of_one_photo(sfm_with_gcps, small_survey, tmp_path):
    r_sfm, _ = sfm_with_gcps
    images = tmp_path / "images"
    images.mkdir()
    one = sorted(small_survey.images.iterdir())[0]
    (images / one.name).symlink_to(one)
    with pytest.raises(geoortho.InputError, match="registered photo"):
        geoortho.dense(r_sfm.output, images, tmp_path / "dense.laz")
    assert not (tmp_path / "dense.laz").exists()
