"""Every metre of ground the photos saw: the DSM, DTM and orthophoto measured against the true
footprints (``truth/footprints.gpkg``: each photo's frame cast on the true surface), not against
the products themselves; and the per-cell source raster that says how each DSM value was made."""

from __future__ import annotations

import json

import geopandas as gpd
import numpy as np
import pytest
import rasterio
from affine import Affine
from conftest import SFM_FAST
from rasterio.warp import Resampling, reproject
from scipy.ndimage import median_filter

import geoortho
from geoortho.elevation.coverage import FALLBACK, INTERPOLATED, MEASURED, complete_grid, extended_grid, seen_count

# --- the completion on its own: exact answers ----------------------------------------------------


def _plane(shape, t, a=100.0, b=0.02, c=-0.01):
    rows, cols = np.indices(shape)
    x, y = t * (cols + 0.5, rows + 0.5)
    return (a + b * (np.asarray(x) - t.c) + c * (np.asarray(y) - t.f)).astype(np.float32)


@pytest.mark.parametrize("max_solve_cells", [10**9, 2000])  # solved whole, and coarse then carried down
def test_a_plane_with_holes_and_a_bare_edge_is_carried_exactly_and_labelled(max_solve_cells):
    t = Affine(0.5, 0, 1000.0, 0, -0.5, 2000.0)
    shape = (120, 160)
    truth = _plane(shape, t)
    z = truth.copy()
    z[40:70, 50:90] = np.nan  # a hole: canopy, water
    z[:, 140:] = np.nan  # the survey's edge, seen by the photos, not measured
    z[:10, :] = np.nan
    measured = np.isfinite(z)
    z[20, 20] = np.nan  # a single cell an earlier gap fill would have made: not measured
    measured[20, 20] = False
    z[20, 20] = truth[20, 20]
    target = np.ones(shape, bool)
    target[:, 155:] = False  # beyond what two photos saw: stays empty
    done = complete_grid(z, measured, target, t, max_solve_cells=max_solve_cells)
    assert np.isnan(done.z[:, 155:]).all() and (done.source[:, 155:] == 0).all()
    inside = target
    assert np.isfinite(done.z[inside]).all()
    assert (done.source[measured] == MEASURED).all()
    assert done.source[20, 20] == INTERPOLATED
    filled = inside & ~np.isfinite(z)
    assert (done.source[filled] == INTERPOLATED).all()
    # a harmonic fill is exact inside an enclosed hole of a plane; beyond the edge it levels off
    hole = np.zeros(shape, bool)
    hole[40:70, 50:90] = True
    assert np.abs(done.z[hole] - truth[hole]).max() < 0.02
    edge = filled & ~hole
    assert np.abs(done.z[edge] - truth[edge]).max() < 0.5
    assert done.fallback_plane is None


def test_nothing_measured_gives_the_tie_points_plane_said_as_fallback():
    t = Affine(1.0, 0, 500.0, 0, -1.0, 800.0)
    shape = (50, 60)
    truth = _plane(shape, t, 40.0, 0.05, 0.03)
    rng = np.random.default_rng(1)
    x, y = rng.uniform(500, 560, 40), rng.uniform(750, 800, 40)
    support = np.c_[x, y, 40.0 + 0.05 * (x - 500) + 0.03 * (y - 800)]
    empty = np.full(shape, np.nan, np.float32)
    none = np.zeros(shape, bool)
    # with tie points in the cells, they are interpolated from (no fallback)
    done = complete_grid(empty, none, np.ones(shape, bool), t, support)
    assert done.fallback_plane is None and (done.source == INTERPOLATED).all()
    assert np.abs(done.z - truth).max() < 1.5 and np.median(np.abs(done.z - truth)) < 0.4  # harmonic: levels off
    # tie points outside the grid only: the plane through them, labelled fallback
    far = support + [1000.0, 0.0, 0.0]
    far[:, 2] = 40.0 + 0.05 * (far[:, 0] - 500) + 0.03 * (far[:, 1] - 800)
    done = complete_grid(empty, none, np.ones(shape, bool), t, far)
    assert (done.source == FALLBACK).all() and done.fallback_plane is not None
    assert np.abs(done.z - truth).max() < 1e-3


def test_the_grid_grows_on_its_own_lattice():
    t = Affine(0.25, 0, 100.0, 0, -0.25, 200.0)
    new, shape, (r0, c0) = extended_grid(t, (40, 40), (98.0, 185.0, 112.6, 203.0))
    assert (new.a, new.e) == (0.25, -0.25) and (new.c, new.f) == (98.0, 203.0)
    assert (r0, c0) == (12, 8)
    assert new.c + shape[1] * 0.25 >= 112.6 and new.f - shape[0] * 0.25 <= 185.0
    # the old cells are the new grid's cells to the last bit
    assert new * (c0, r0) == t * (0, 0)


# --- a survey with freely turning headings, the chain run on it ---------------------------------


def _counts_on(path_polys, transform, shape):
    polys = gpd.read_file(path_polys).geometry.to_numpy()
    return seen_count(polys, transform, shape)


def _on_grid(path, transform, crs, shape):
    out = np.full(shape, np.nan, np.float32)
    with rasterio.open(path) as src:
        reproject(rasterio.band(src, 1), out, dst_transform=transform, dst_crs=crs,
                  resampling=Resampling.bilinear, dst_nodata=np.nan)  # fmt: skip
    return out


def _with_source(path, source_path):
    """A DSM or DTM (NaN where none) and its source raster, on the same grid (checked)."""
    with rasterio.open(path) as ds:
        z = ds.read(1, masked=True).filled(np.nan)
        t, crs = ds.transform, ds.crs
    with rasterio.open(source_path) as ds:
        source = ds.read(1)
        assert ds.transform == t and ds.nodata == 0
    return z, source, t, crs


PRESET = "tiny"


@pytest.fixture(scope="module")
def free_heading(tmp_path_factory):
    """The tiny survey flown with a heading drawn at random for every photo, a pond, a wood and a
    car park in it, and the chain on it as `run` makes it: dense, dem carried to the photos' edge,
    ortho. (Seed 3: the wood's leaves drawn as noise blobs; test_a_wood_drawn_the_other_way has the
    other drawing.)"""
    d = tmp_path_factory.mktemp("free_heading")
    s = geoortho.synth(d / "survey", preset=PRESET, seed=3, pathology="free-heading,water,canopy,cars")
    found = geoortho.gcp_find(s.images, s.gcp_file, d / "gcp_list.txt")
    r_sfm = geoortho.sfm(s.images, d / "sfm", gcp_list=found.output, **SFM_FAST)
    # depth maps at 640 px and a 5 cm orthophoto: coverage is the point here, not detail
    r_dense = geoortho.dense(r_sfm.output, s.images, d / "dense.laz", max_image_size=640)
    r_dem = geoortho.dem(r_dense.output, d / "dsm.tif", dtm=d / "dtm.tif", sfm=r_sfm.output, method="idw")
    r_ortho = geoortho.ortho(s.images, d / "ortho.tif", sfm=r_sfm.output, dsm=r_dem.dsm, workers=2, resolution_m=0.05)
    return s, r_sfm, r_dense, r_dem, r_ortho


def test_free_headings_give_a_depth_map_for_every_photo(free_heading):
    s, r_sfm, r_dense, _, _ = free_heading
    report = json.loads(r_dense.report.read_text())
    yaws = [p["yaw_deg"] for p in json.loads((s.truth / "poses.json").read_text())]
    assert np.ptp(np.unwrap(np.radians(yaws))) > np.radians(180)  # the headings do turn
    assert r_dense.n_depth_maps >= 0.95 * r_sfm.n_registered, report["no_depth_map"]
    # a photo without a depth map is named with its reason
    assert set(report["no_depth_map"]) | set(report["views"]) >= {c for c in report["views"]}


def test_the_dsm_covers_the_ground_two_photos_saw_and_says_how(free_heading):
    s, r_sfm, _, r_dem, _ = free_heading
    # the synthetic camera has no distortion: the SfM holds it at zero (it reprojects no worse)
    (cam,) = json.loads(r_sfm.report.read_text())["intrinsics"]
    assert cam["distortion"]["held_at_zero"], cam
    z, source, t, crs = _with_source(r_dem.dsm, r_dem.dsm_source)
    seen = _counts_on(s.truth / "footprints.gpkg", t, z.shape)
    # grid's own extent: the truth's ground seen by >= 2 beyond it counts as missed
    assert np.isfinite(z[seen >= 2]).mean() >= 0.98
    assert (seen >= 2).sum() * abs(t.a * t.e) >= 0.98 * r_dem.seen_m2 * 0.9
    assert ((source > 0) == np.isfinite(z)).all()
    water = json.loads((s.truth / "survey.json").read_text())["water"]
    rows, cols = np.indices(z.shape)
    x, y = t * (cols + 0.5, rows + 0.5)
    pond = np.hypot(np.asarray(x) - water["x"], np.asarray(y) - water["y"]) < 0.6 * water["radius_m"]
    assert (source[pond] == INTERPOLATED).mean() > 0.9  # no texture to measure: said so
    # a 9-photo block: its wide edge is seen by two photos only, measured by that one pair (41 %
    # measured when a second pair had to agree; 83 % now), the pond and the block's rim interpolated
    assert 0.6 < r_dem.measured_share < 1.0 and r_dem.fallback_share == 0.0
    truth = _on_grid(s.dsm, t, crs, z.shape)
    flat_truth = _on_grid(s.dtm, t, crs, z.shape)
    open_ground = (seen >= 2) & (np.abs(truth - flat_truth) < 0.05) & (source == MEASURED)
    gsd = json.loads((s.truth / "survey.json").read_text())["gsd_cm_at_home_height"] / 100
    dz = (z - truth)[open_ground & np.isfinite(truth)]
    assert np.median(np.abs(dz)) <= 1.5 * gsd
    # depth maps at 640 of 960 px: bias -0.01 GSD (seed 6: +0.02) and RMSE 2.2 GSD measured, its
    # outliers within 0.5 m of the cars and crowns. +0.58 GSD (seed 6: +1.2) while the SfM refined
    # a lens distortion this camera has not (k1 -0.003: the block domed, its tie points +1.6 cm
    # high); +0.96 GSD while the downscaled rows had the columns' scale
    assert abs(np.median(dz)) <= 0.3 * gsd and np.sqrt(np.mean(dz**2)) <= 3 * gsd
    _assert_the_wood_and_the_cars_are_measured(s, z, source, truth, flat_truth, seen, t)
    # the pond, carried across from its shore: a harmonic fill has no curvature, and this pond lies
    # on a crest (the truth rises 0.4 m over its 12 m): measured 0.20 m median, 0.24 m at its centre
    assert np.nanmedian(np.abs((z - truth)[pond])) < 0.3


def test_the_dtm_is_the_bare_earth_to_the_edge(free_heading):
    """The DTM from the photos alone against the true ground, over all the ground two photos saw:
    measured where the ground shows, carried under the wood, the cars and the pond. Before the
    survey's edge was measured (one pair there: no second one can agree) it was interpolated out
    to the rim: RMSE 0.29 m (seed 3) and 0.48 m (seed 6); 0.13 and 0.15 m measured to the edge,
    0.11 and 0.14 m with each axis of a downscaled photo at its own scale, and 0.10 and 0.11 m with
    the lens distortion held at zero and the ground filter's low outliers cut at 1 m."""
    s, _, _, r_dem, _ = free_heading
    z, source, t, crs = _with_source(r_dem.dtm, r_dem.dtm_source)
    seen = _counts_on(s.truth / "footprints.gpkg", t, z.shape)
    truth = _on_grid(s.dtm, t, crs, z.shape)
    both = (seen >= 2) & np.isfinite(truth)
    assert np.isfinite(z[both]).mean() >= 0.98
    dz = (z - truth)[both & np.isfinite(z)]
    assert np.sqrt(np.mean(dz**2)) <= 0.15
    assert (source[both] == MEASURED).mean() >= 0.6
    # bare earth, not speckle: the DTM less its 2 m median, on open ground (0.87 GSD RMS measured)
    open_ground = both & (np.abs(_on_grid(s.dsm, t, crs, z.shape) - truth) < 0.05)
    filled = np.where(np.isfinite(z), z, np.nanmedian(z))
    rough = (z - median_filter(filled, size=int(round(2.0 / t.a)) | 1))[open_ground]
    gsd = json.loads((s.truth / "survey.json").read_text())["gsd_cm_at_home_height"] / 100
    assert np.sqrt(np.nanmean(rough**2)) <= 2 * gsd


def _assert_the_wood_and_the_cars_are_measured(s, z, source, truth, flat_truth, seen, t):
    """The crowns and the cars stand in the DSM, measured: the tie points (which bound each
    pair's search) miss them, and before the near-depth probe the wood was 3-5 % measured and
    9.8 m low (the ground under it), the cars 84 % measured (26 % at a survey's edge)."""
    cover = json.loads((s.truth / "survey.json").read_text())["cover"]
    rows, cols = np.indices(z.shape)
    x, y = (np.asarray(v) for v in t * (cols + 0.5, rows + 0.5))
    # measured here (seeds 3 and 6): wood 80 and 69 % measured, median |dZ| 0.07 and 0.11 m;
    # cars 98 % both, 0.05 and 0.07 m
    for kind, floor, within_m in (("canopy", 0.6, 0.3), ("cars", 0.9, 0.15)):
        c = cover[kind]
        inside = (np.abs(x - c["x"]) < c["half_w_m"]) & (np.abs(y - c["y"]) < c["half_h_m"]) & (seen >= 2)
        standing = inside & (truth - flat_truth > 0.5)
        assert standing.sum() > 500, kind
        assert (source[standing] == MEASURED).mean() >= floor, kind
        assert np.median(np.abs(z - truth)[standing]) <= within_m, kind


def test_a_wood_drawn_the_other_way(tmp_path):
    """The wood's leaves as a regular pattern that repeats exactly from crown to crown (an even
    seed), under freely turning headings: measured as the blobs are."""
    s = geoortho.synth(tmp_path / "survey", preset=PRESET, seed=6, pathology="free-heading,canopy,cars")
    assert json.loads((s.truth / "survey.json").read_text())["cover"]["canopy"]["style"] == "pattern"
    found = geoortho.gcp_find(s.images, s.gcp_file, tmp_path / "gcp_list.txt")
    r_sfm = geoortho.sfm(s.images, tmp_path / "sfm", gcp_list=found.output, **SFM_FAST)
    r_dense = geoortho.dense(r_sfm.output, s.images, tmp_path / "dense.laz", max_image_size=640)
    r_dem = geoortho.dem(r_dense.output, tmp_path / "dsm.tif", sfm=r_sfm.output, method="idw")
    # without a DTM the walls' gaps are not filled from their own side: said, not silent
    assert any("no DTM was asked for" in n for n in r_dem.notes)
    z, source, t, crs = _with_source(r_dem.dsm, r_dem.dsm_source)
    seen = _counts_on(s.truth / "footprints.gpkg", t, z.shape)
    truth, flat_truth = _on_grid(s.dsm, t, crs, z.shape), _on_grid(s.dtm, t, crs, z.shape)
    _assert_the_wood_and_the_cars_are_measured(s, z, source, truth, flat_truth, seen, t)


def test_the_orthophoto_shows_all_the_ground_one_photo_saw(free_heading):
    s, _, _, _, r_ortho = free_heading
    with rasterio.open(r_ortho.output) as ds:
        alpha = ds.read_masks(1) > 0
        t = ds.transform
    seen = _counts_on(s.truth / "footprints.gpkg", t, alpha.shape)
    # measured against the true frames; the edge pixel of each frame is the photos' own margin
    assert alpha[seen >= 1].mean() >= 0.98
    assert r_ortho.share_of_seen_1 >= 0.98 and r_ortho.share_of_seen_2 >= 0.99
    assert r_ortho.seen_2_m2 <= r_ortho.seen_1_m2 and r_ortho.area_m2 > 0.95 * r_ortho.seen_1_m2
    report = json.loads(r_ortho.report.read_text())
    assert report["share_of_seen_1"] == r_ortho.share_of_seen_1
    assert r_ortho.on_interpolated_m2 > 0  # the pond and the edge: on the interpolated surface


@pytest.mark.parametrize(
    ("scene", "bgr"),
    [("snow", (238.0, 240.0, 241.0)), ("water", (70.0, 62.0, 38.0))],
)
def test_textureless_everywhere_gives_a_stated_fallback_surface_and_a_full_orthophoto(
    free_heading, tmp_path, scene, bgr
):
    """Snow or water under every photo (the poses are the SfM's, made before the ground went blank):
    no depth map anywhere. Not an empty product nor a refusal: the cloud is the SfM's tie points,
    said so; the DSM covers the stereo ground, mostly interpolated and labelled; the orthophoto covers
    every photo's ground; and the quality check is red on the depth maps."""
    import cv2

    from geoortho.chain.quality import assess, verdict

    s, r_sfm, *_ = free_heading
    blank = tmp_path / "photos"
    blank.mkdir()
    rng = np.random.default_rng(5)
    for photo in sorted(s.images.glob("*.JPG")):
        h, w = cv2.imread(str(photo)).shape[:2]
        ramp = np.linspace(-3.0, 3.0, w)[None, :, None]  # light falling across the frame, no texture
        img = np.asarray(bgr)[None, None, :] + ramp + rng.normal(0.0, 0.6, (h, w, 3))
        cv2.imwrite(str(blank / photo.name), np.clip(img, 0, 255).astype(np.uint8), [cv2.IMWRITE_JPEG_QUALITY, 95])
    r_dense = geoortho.dense(r_sfm.output, blank, tmp_path / "dense.laz", max_image_size=640)
    report = json.loads(r_dense.report.read_text())
    assert r_dense.n_depth_maps == 0 and "tie points" in report["fallback"]
    assert r_dense.n_points > 100 and any("no depth could be measured" in n for n in r_dense.notes)
    r_dem = geoortho.dem(r_dense.output, tmp_path / "dsm.tif", sfm=r_sfm.output, method="idw")
    with rasterio.open(r_dem.dsm) as ds:
        z = ds.read(1, masked=True).filled(np.nan)
        t, crs = ds.transform, ds.crs
    seen = _counts_on(s.truth / "footprints.gpkg", t, z.shape)
    assert np.isfinite(z[seen >= 2]).mean() >= 0.98
    # (the grid's cell follows the cloud's density: coarse on tie points, most cells hold one)
    truth = _on_grid(s.dsm, t, crs, z.shape)
    # the tie points are true measurements: the surface through them is the ground's to a few decimetres
    assert np.nanmedian(np.abs(z - truth)[seen >= 2]) < 0.3
    r_ortho = geoortho.ortho(blank, tmp_path / "ortho.tif", sfm=r_sfm.output, dsm=r_dem.dsm, resolution_m=0.05)
    assert r_ortho.share_of_seen_1 >= 0.98
    ortho_report = json.loads(r_ortho.report.read_text())
    dem_report = {"seen_m2": r_dem.seen_m2, "measured_share": r_dem.measured_share}
    checks = {c.item: c for c in assess(None, report, dem_report, ortho_report, None)}
    assert checks["depth_maps"].state == "red" and checks["depth_maps"].value == 0.0
    assert checks["ortho_coverage"].state == "green"
    assert verdict(list(checks.values())) == "red"
