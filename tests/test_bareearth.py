"""A DTM that is bare earth, on grids whose truth is known exactly: rims taken in, breaklines kept,
spikes dropped, speckle smoothed, fills without cones or sags; the artefact measures; contours."""

from __future__ import annotations

import geopandas as gpd
import numpy as np
import pytest
import rasterio
import shapely
from affine import Affine
from pyproj import CRS
from scipy import ndimage

from geoortho.core.gapfill import fill_harmonic, fill_smooth
from geoortho.elevation.artefacts import footprint_step_m, roughness_m
from geoortho.elevation.bareearth import BRIDGE_M, BRIDGE_TOLERANCE_M, bare_earth, follow_breaklines
from geoortho.elevation.contours import contour_interval_m, write_contours
from geoortho.elevation.ground import bilinear

CELL_M = 0.1


def _terrain(shape=(400, 500), bank=True):
    """A crest with a bank 1.5 m high at 45 deg across it (the ground's own breakline), metres."""
    rows, cols = np.indices(shape)
    x, y = cols * CELL_M, rows * CELL_M
    z = 100.0 + 0.004 * (x - 25.0) ** 2 * -1 + 0.02 * y
    if bank:
        z = z + np.clip(x - 10.0, 0.0, 1.5)  # 1.5 m over 1.5 m of run: 45 deg
    return z


def _building(shape, centre=(200, 330), half=(50, 70)):
    rows, cols = np.indices(shape)
    return (np.abs(rows - centre[0]) <= half[0]) & (np.abs(cols - centre[1]) <= half[1])


def _photogrammetric_dtm(truth, inside, rng):
    """What gridding the ground filter's points gives: the ground with speckle, a plateau under the
    building (the filter's fill), a ring of half-height wall points called ground round it, and
    single-cell mismatches."""
    dtm = truth + rng.normal(0.0, 0.01, truth.shape)
    ring = ndimage.binary_dilation(inside, iterations=8) & ~inside
    dtm[ring] += 0.45  # a rim: within the filter's 0.5 m threshold of its raised surface
    dtm[inside] = np.nan
    spikes = rng.random(truth.shape) < 0.0005
    dtm[spikes & ~inside & ~ring] += rng.choice([-0.4, 0.4], int((spikes & ~inside & ~ring).sum()))
    measured = np.isfinite(dtm)
    dtm = fill_harmonic(dtm, measured)  # the plateau under the roof, as the filter's fill leaves it
    return dtm, measured, ring, spikes


def test_rims_go_spikes_go_speckle_goes_the_bank_stays():
    rng = np.random.default_rng(3)
    truth = _terrain()
    inside = _building(truth.shape)
    dsm = np.where(inside, truth + 8.0, truth) + rng.normal(0.0, 0.01, truth.shape)
    dtm, measured, ring, spikes = _photogrammetric_dtm(truth, inside, rng)
    dsm = np.maximum(dsm, dtm)  # the wall's points are in the DSM too
    clean = bare_earth(dsm, dtm, measured, CELL_M)
    err = clean.z - truth
    near = ndimage.binary_dilation(inside, iterations=30)
    # the rim: 0.45 m before, gone after; under the roof a thin plate through ground of 1 cm
    # speckle (measured: p95 3.9 cm beside the roof, 5.6 cm on the rim, 6.2 cm under the roof)
    assert np.percentile(np.abs(dtm - truth)[ring], 50) > 0.4
    assert np.percentile(np.abs(err)[ring], 95) < 0.07
    assert np.percentile(np.abs(err)[near & ~inside], 95) < 0.05
    assert np.percentile(np.abs(err)[inside], 95) < 0.08
    assert clean.objects[ring].mean() > 0.95 and not clean.ground[ring].any()
    # the mismatches (0.4 m): none left; the worst cell is where one lay on the bank's brow (11 cm)
    assert np.abs(err).max() < 0.15, np.abs(err).max()
    assert np.abs(err[spikes]).max() < 0.15
    # speckle: 1 cm of noise less its 1 m median, smoothed to a third or less
    open_ground = ~near & (np.abs(np.indices(truth.shape)[1] * CELL_M - 10.75) > 2.0)
    before, after = roughness_m(dtm, open_ground, CELL_M), roughness_m(clean.z, open_ground, CELL_M)
    assert after < before / 3, (before, after)
    # the bank: 1.5 m over 1.5 m, still as steep (no bank rounded into a ramp of metres)
    profile = clean.z[100, 80:140] - truth[100, 80:140]
    assert np.abs(profile).max() < 0.06
    # the crest's steady bend: the ring test calls the floor's middle a guess (pessimistic there)
    assert 2.0 <= clean.bridge_m <= 4.0


def test_how_far_a_fill_is_trusted_follows_the_ground_s_own_relief():
    rng = np.random.default_rng(8)
    cell_m = 0.2  # open ground 120 x 80 m beside the wood, to judge 10 m bridges on
    shape = (600, 550)
    rows, cols = np.indices(shape)
    x, y = cols * cell_m, rows * cell_m
    wood = _building(shape, (300, 125), (75, 75))  # 30 m across
    dist_m = ndimage.distance_transform_edt(wood) * cell_m
    for relief_m, wants_guess in ((0.0, False), (0.6, True)):
        # a tilted plane, or rolling ground (hills 25 x 30 m, +-0.6 m)
        truth = 100.0 + 0.03 * x + relief_m * np.sin(2 * np.pi * x / 25.0) * np.sin(2 * np.pi * y / 30.0)
        dsm = np.where(wood, truth + 9.0 + rng.normal(0, 0.3, shape), truth)
        dtm, measured, _, _ = _photogrammetric_dtm(truth, wood, rng)
        clean = bare_earth(dsm, dtm, measured, cell_m)
        err = np.abs(clean.z - truth)
        if not wants_guess:
            # a plane is bridged the whole way (15 m from its edge: more than BRIDGE_M)
            assert clean.bridge_m == BRIDGE_M
            assert not clean.no_ground[dist_m < BRIDGE_M - 2].any()
            assert np.percentile(err[wood], 95) < 0.05
            continue
        assert clean.bridge_m <= 3.0, clean.bridge_m
        # where it says a guess, the fill is off by more than the tolerance; where not, it is within
        guess = clean.no_ground
        bridged = wood & ~guess
        assert guess[dist_m > 5.0].all()
        rms_guess, rms_bridged = (float(np.sqrt(np.mean(err[m] ** 2))) for m in (guess, bridged))
        assert rms_guess > BRIDGE_TOLERANCE_M > 0.75 * rms_bridged, (rms_guess, rms_bridged)


def test_a_wide_object_is_said_to_be_a_guess_and_a_canopy_is_never_ground():
    rng = np.random.default_rng(5)
    truth = _terrain((500, 500), bank=False)
    wood = _building(truth.shape, (250, 250), (170, 170))  # 34 m across
    dsm = np.where(wood, truth + 9.0 + rng.normal(0, 0.3, truth.shape), truth)
    dtm, measured, _, _ = _photogrammetric_dtm(truth, wood, rng)
    clean = bare_earth(dsm, dtm, measured, CELL_M)
    dist_m = ndimage.distance_transform_edt(wood) * CELL_M
    # (measured from the ground kept: the rim and the wood's edge are not, a metre or two)
    assert clean.no_ground[dist_m > BRIDGE_M + 1].all() and not clean.no_ground[dist_m < BRIDGE_M - 3].any()
    # all canopy: the filter's "ground" is the crowns' floor, rough at every scale
    bumps = ndimage.gaussian_filter(rng.normal(0, 30.0, truth.shape), 15)
    crowns = truth + 9.0 + bumps + rng.normal(0, 0.3, truth.shape)
    canopy = bare_earth(crowns + 0.5, crowns, np.ones(truth.shape, bool), CELL_M)
    assert not canopy.ground.any() and canopy.no_ground.all()
    # a plane under the crowns (through each 5 m block's lowest), not on them
    assert np.nanmedian(canopy.z) < np.nanpercentile(crowns, 10)


def test_a_thin_plate_follows_the_ground_s_bend_and_has_no_cone():
    rows, cols = np.indices((300, 400))
    bend = 0.002 * (cols - 200.0) ** 2 - 0.001 * (rows - 150.0) ** 2 + 0.01 * cols
    known = np.ones(bend.shape, bool)
    known[100:200, 150:250] = False  # a roof 10 m across at 0.1 m cells, on a crest
    harmonic = fill_harmonic(np.where(known, bend, np.nan), known)
    smooth = fill_smooth(np.where(known, bend, np.nan), known)
    assert np.abs(harmonic - bend)[~known].max() > 1.0  # the harmonic fill sags
    assert np.abs(smooth - bend)[~known].max() < 0.01
    # pinned to one cell in a wide gap: a harmonic fill is a cone there, a thin plate is round
    z = np.full((200, 200), np.nan)
    pin = np.zeros(z.shape, bool)
    pin[:, :10] = pin[:, -10:] = True
    pin[100, 100] = True
    z[pin] = 0.0
    z[100, 100] = 0.3
    h, t = fill_harmonic(z, pin), fill_smooth(z, pin)
    kink_h = h[100, 100] - 2 * h[100, 101] + h[100, 102]
    kink_t = t[100, 100] - 2 * t[100, 101] + t[100, 102]
    assert kink_h > 0.03 and abs(kink_t) < 0.005, (kink_h, kink_t)


@pytest.mark.parametrize("angle_deg", [35.0, 120.0])
def test_a_bank_under_a_roof_is_carried_across_it_not_rounded(angle_deg):
    """A bank 1.5 m high crossing under a roof 9 m across, at two angles: filled along the bank,
    the step stays a step under the roof; a thin plate alone rounds it (0.3 m and more)."""
    rng = np.random.default_rng(int(angle_deg))
    shape = (360, 360)
    rows, cols = np.indices(shape)
    x, y = cols * CELL_M, rows * CELL_M
    a = np.radians(angle_deg)
    across = (x - 18.0) * np.cos(a) + (y - 18.0) * np.sin(a)  # metres across the bank, 0 mid-roof
    truth = 100.0 + 0.02 * x - 0.01 * y + np.clip(across + 0.75, 0.0, 1.5)
    roof = _building(shape, (180, 180), (45, 45))
    dsm = np.where(roof, truth + 7.0, truth) + rng.normal(0.0, 0.01, shape)
    dtm, measured, _, _ = _photogrammetric_dtm(truth, roof, rng)
    dsm = np.maximum(dsm, dtm)
    clean = bare_earth(dsm, dtm, measured, CELL_M)
    err = np.abs(clean.z - truth)
    plate = fill_smooth(np.where(clean.ground, truth, np.nan), clean.ground, roof)
    assert np.percentile(np.abs(plate - truth)[roof], 95) > 0.3
    assert np.percentile(err[roof], 95) < 0.1, np.percentile(err[roof], 95)
    # the step is where it was: across the bank's line under the roof's middle
    mid = roof & (np.abs(across) < 2.0)
    assert np.abs(clean.z - truth)[mid].max() < 0.25


def test_no_breakline_leaves_the_thin_plate_alone():
    """Rolling ground round a gap (no straight steep ground entering and leaving it): unchanged."""
    rows, cols = np.indices((300, 300))
    hill = 3.0 * np.exp(-((rows - 150.0) ** 2 + (cols - 150.0) ** 2) / (2 * 60.0**2))
    known = np.ones(hill.shape, bool)
    known[120:180, 110:190] = False
    filled = fill_smooth(np.where(known, hill, np.nan), known)
    again = follow_breaklines(filled, known, ~known, CELL_M)
    assert np.array_equal(again, filled)
    # a bank entering from one side only (it ends under the gap): unchanged too
    bank = np.clip((cols - 150.0) * CELL_M, 0.0, 1.5) * (rows < 150)
    filled = fill_smooth(np.where(known, bank, np.nan), known)
    assert np.array_equal(follow_breaklines(filled, known, ~known, CELL_M), filled)


def test_the_step_at_a_footprint_edge_is_measured_and_a_plane_has_none():
    rows, cols = np.indices((400, 400))
    plane = 50.0 + 0.01 * cols - 0.02 * rows
    transform = Affine(0.1, 0, 1000.0, 0, -0.1, 2000.0)
    patch = shapely.box(1010.0, 1965.0, 1030.0, 1985.0)  # a photo's footprint, 20 m a side
    inside = np.zeros(plane.shape, bool)
    inside[150:350, 100:300] = True  # the same box in cells
    grid = np.ones(plane.shape, bool)
    flat, n = footprint_step_m(plane, transform, [patch], grid)
    stepped, n2 = footprint_step_m(plane + 0.05 * inside, transform, [patch], grid)
    assert n == n2 == 4
    assert abs(flat) < 1e-6 and abs(stepped - 0.05) < 0.005, (flat, stepped)
    assert roughness_m(plane, grid, 0.1) < 1e-6
    # a line of nodata just past the east edge, beside the cells the samples fall nearest to: the
    # cell the bilinear sample also weighs is in it and the edge must not count (its nodata read as
    # 0 made a 3.5 m step of the small survey's clean west edge, the quality check's red)
    gap = np.where(cols == 302, np.nan, plane)
    wider = shapely.box(1010.0, 1965.0, 1030.04, 1985.0)  # its east samples 0.4 cell short of the gap
    at_edge, n3 = footprint_step_m(gap, transform, [wider], grid & np.isfinite(gap))
    assert abs(at_edge) < 1e-6 and n3 == 3, (at_edge, n3)
    noisy = plane + np.random.default_rng(1).normal(0.0, 0.01, plane.shape)
    assert 0.008 < roughness_m(noisy, grid, 0.1) < 0.012


def test_contours_lie_at_their_levels_at_an_interval_from_the_accuracy(tmp_path):
    rows, cols = np.indices((300, 300))
    cone = 20.0 - 0.05 * np.hypot(rows - 150.0, cols - 150.0)  # 20 m down to ~12.9 m at the corners
    transform = Affine(0.2, 0, 500000.0, 0, -0.2, 4000000.0)
    assert contour_interval_m(0.03, 7.0) == 0.1  # 3.29 x 3 cm
    assert contour_interval_m(0.2, 7.0) == 1.0  # 0.66 m: the next standard step
    assert contour_interval_m(0.001, 2000.0) == 10.0  # at most 200 levels
    z = np.where(cols > 20, cone, np.nan)  # a strip without values: the lines stop at it
    got = write_contours(tmp_path / "c.gpkg", z, transform, "EPSG:32629", 1.0)
    lines = gpd.read_file(got.path, layer="contours")
    assert lines.crs.to_epsg() == 32629
    assert sorted(set(lines["elevation_m"])) == list(np.arange(np.ceil(np.nanmin(z)), 20.0, 1.0))
    assert set(lines[lines["index"]]["elevation_m"]) == {10.0, 15.0}
    inv = ~transform
    for level, geom in zip(lines["elevation_m"], lines.geometry):
        xy = np.asarray(geom.coords)
        c, r = inv * (xy[:, 0], xy[:, 1])
        assert np.nanmax(np.abs(bilinear(cone, np.asarray(c) - 0.5, np.asarray(r) - 0.5) - level)) < 0.01
        assert (np.asarray(c) >= 20.5).all()


@pytest.mark.parametrize("seed", [0, 1])
def test_synth_draws_the_new_scenes_two_ways(tmp_path, seed):
    """The wide wood, the hall, the hedge and the breaklines in the truth, each drawn as its seed says."""
    import json

    import geoortho

    s = geoortho.synth(
        tmp_path / "s", preset="small", seed=seed, pathology="wide-wood,hall,hedge,breaklines", pixels=False
    )
    info = json.loads((s.truth / "survey.json").read_text())
    cover = info["cover"]
    assert cover["hall"]["pitched"] == (seed % 2 == 1)
    assert cover["breaklines"]["bank_deg"] == (45.0 if seed % 2 == 0 else 30.0)
    assert {"wide_wood", "hedge"} <= set(cover)
    with rasterio.open(s.dsm) as a, rasterio.open(s.dtm) as b:
        dsm, dtm, t = a.read(1), b.read(1), a.transform
    rows, cols = np.indices(dsm.shape)
    x, y = t * (cols + 0.5, rows + 0.5)
    w = cover["wide_wood"]
    in_wood = np.hypot(np.asarray(x) - w["x"], np.asarray(y) - w["y"]) < 0.8 * w["half_w_m"]
    assert w["half_w_m"] >= 20 and np.median((dsm - dtm)[in_wood]) > 6.0
    h = cover["hall"]
    hall = (np.abs(np.asarray(x) - h["x"]) < 5) & (np.abs(np.asarray(y) - h["y"]) < 5)
    assert np.median((dsm - dtm)[hall]) > 6.5
    # the bank: the ground rises by its height across it
    b = cover["breaklines"]
    ang = np.radians(b["normal_deg"])
    lx, ly = np.asarray(x) - np.mean(info["flight_box"][::2]), np.asarray(y) - np.mean(info["flight_box"][1::2])
    d = lx * np.cos(ang) + ly * np.sin(ang)
    gy, gx = np.gradient(dtm.astype(float), t.a)
    steep = np.hypot(gx, gy)[np.abs(d - b["bank_offset_m"]) < 0.3]
    assert np.median(steep) > 0.5  # 45 or 30 deg: 1.0 or 0.58 (the terrain's own slope adds to it)


# --- from the photos: the chain on synthetic surveys with the new scenes ------------------------


def _chain(folder, seed, pathology, gcps=True):
    """synth (tiny) -> gcp-find -> sfm -> dense -> dem --sfm with a DTM and contours (``gcps``
    False: the SfM on the photos' GPS alone)."""
    from conftest import SFM_FAST

    import geoortho

    s = geoortho.synth(folder / "survey", preset="tiny", seed=seed, pathology=pathology)
    found = geoortho.gcp_find(s.images, s.gcp_file, folder / "gcp_list.txt").output if gcps else None
    r_sfm = geoortho.sfm(s.images, folder / "sfm", gcp_list=found, **SFM_FAST)
    r_dense = geoortho.dense(r_sfm.output, s.images, folder / "dense.laz", max_image_size=640)
    r_dem = geoortho.dem(
        r_dense.output, folder / "dsm.tif", dtm=folder / "dtm.tif", sfm=r_sfm.output, contours=folder / "c.gpkg"
    )
    return s, r_sfm, r_dem


@pytest.fixture(scope="module")
def banks(tmp_path_factory):
    """A bank and a road cutting, from the photos (seed 4: a 45 deg bank)."""
    return _chain(tmp_path_factory.mktemp("banks"), 4, "breaklines")


def _truth_on(s, r_dem):
    from geoortho.synthetic.scoring import _on_grid

    with rasterio.open(r_dem.dtm) as ds:
        z = ds.read(1, masked=True).filled(np.nan).astype(float)
        t, crs = ds.transform, ds.crs
    with rasterio.open(r_dem.dtm_source) as ds:
        source = ds.read(1)
    return z, source, t, _on_grid(s.dtm, t, crs, z.shape), _on_grid(s.dsm, t, crs, z.shape)


def test_the_dtm_from_the_photos_keeps_its_bank_and_its_cutting(banks):
    import json

    from geoortho.synthetic.scoring import score_surfaces

    s, _, r_dem = banks
    got = score_surfaces(s.truth, r_dem.dsm, r_dem.dtm)
    z, source, t, tdtm, tdsm = _truth_on(s, r_dem)
    objects = (tdsm - tdtm) > 0.2
    # issue 74's roughness floor on open ground (measured, seed 4: 0.11 GSD beyond the truth's; the
    # rims are not scored here: the dense cloud misses this survey's one building, seed 4)
    assert got.dtm_roughness_excess_gsd <= 0.25, got
    # the bank and the cutting: the ground across them as the truth's, away from the objects
    info = json.loads((s.truth / "survey.json").read_text())
    b = info["cover"]["breaklines"]
    ang = np.radians(b["normal_deg"])
    fx0, fy0, fx1, fy1 = info["flight_box"]
    rows, cols = np.indices(z.shape)
    x, y = (np.asarray(v) for v in t * (cols + 0.5, rows + 0.5))
    d = (x - (fx0 + fx1) / 2) * np.cos(ang) + (y - (fy0 + fy1) / 2) * np.sin(ang)
    clear = ndimage.distance_transform_edt(~objects) * t.a > 5.0
    for at, half in ((b["bank_offset_m"], 3.0), (b["cutting_offset_m"], b["cutting_width_m"] / 2 + 3.0)):
        across = clear & (np.abs(d - at) < half) & np.isfinite(z)
        assert across.sum() > 200
        # measured (seed 4): bank 2.7 / 15 cm (median / 80th percentile), cutting 2.4 / 8 cm; a stretch
        # of the bank the dense cloud holed (0.7 m low) and one beside the tree make the rest
        dz = np.abs(z - tdtm)[across]
        assert np.median(dz) < 0.05 and np.percentile(dz, 80) < 0.2
    lines = gpd.read_file(r_dem.contours, layer="contours")
    assert len(lines) > 10 and r_dem.contour_interval_m in (0.1, 0.2, 0.25, 0.5)


def test_a_survey_all_canopy_gives_a_stated_fallback_never_the_canopy(small_survey, sfm_with_gcps, tmp_path):
    """Bad input: a cloud that is all canopy (crowns 7-12 m over the small survey's ground, rough at
    every scale: no ground seen), carried to the photos' edge. The DTM is not the crowns called
    ground; every cell says it is a guess, and the quality check is red."""
    from geoortho.chain.quality import assess
    from geoortho.core.pointcloud import write_las
    from geoortho.core.surface import read_surface

    r_sfm, _ = sfm_with_gcps
    ground = read_surface(small_survey.dtm)
    rng = np.random.default_rng(8)
    with rasterio.open(small_survey.dtm) as ds:
        left, bottom, right, top = ds.bounds
    n = 400_000
    x, y = rng.uniform(left + 20, right - 20, n), rng.uniform(bottom + 20, top - 20, n)
    # crowns on a jittered 3 m lattice, each 7-12 m high and 2.5 m deep, as synth's wood draws them
    from scipy.spatial import cKDTree

    cx, cy = np.meshgrid(np.arange(left, right, 3.0), np.arange(bottom, top, 3.0))
    centres = np.c_[cx.ravel(), cy.ravel()] + rng.uniform(-1.0, 1.0, (cx.size, 2))
    height, radius = rng.uniform(7.0, 12.0, len(centres)), rng.uniform(1.6, 3.2, len(centres))
    dist, k = cKDTree(centres).query(np.c_[x, y])
    q = np.clip(1.0 - (dist / radius[k]) ** 2, 0.0, 1.0)
    crowns = height[k] - 2.5 + 2.5 * np.sqrt(q) + rng.normal(0.0, 0.12, n)  # leaf clumps
    z = ground.elevation(x, y) + crowns
    ok = np.isfinite(z)
    write_las(tmp_path / "canopy.laz", np.c_[x[ok], y[ok], z[ok]], CRS("EPSG:32629"))
    r_dem = geoortho_dem(tmp_path / "canopy.laz", tmp_path / "dsm.tif", tmp_path / "dtm.tif", r_sfm.output)
    with rasterio.open(r_dem.dtm) as ds:
        dtm = ds.read(1, masked=True).filled(np.nan)
        t = ds.transform
    with rasterio.open(r_dem.dtm_source) as ds:
        source = ds.read(1)
    rows, cols = np.indices(dtm.shape)
    gx, gy = t * (cols + 0.5, rows + 0.5)
    above = dtm - ground.elevation(np.asarray(gx).ravel(), np.asarray(gy).ravel()).reshape(dtm.shape)
    # the crowns stand 7-12 m: the DTM under them is not they (a plane through the lowest)
    assert np.nanmedian(above) < 7.5, np.nanmedian(above)
    assert r_dem.dtm_under_object_share > 0.9 and (source[np.isfinite(dtm)] == 4).mean() > 0.9
    assert any("no ground seen" in n for n in r_dem.notes)
    keys = ("dtm_roughness_m", "dtm_under_object_share", "footprint_step_m", "seen_m2", "measured_share")
    sfm = {"gsd_cm": 1.0}
    checks = {c.item: c.state for c in assess(sfm, None, {k: getattr(r_dem, k) for k in keys}, None, None)}
    assert checks["dtm_no_ground"] == "red"


def geoortho_dem(points, dsm, dtm, sfm):
    import geoortho

    return geoortho.dem(points, dsm, dtm=dtm, sfm=sfm, method="idw", resolution_m=0.5)


def test_a_crown_top_called_ground_inside_a_wood_goes_a_courtyard_stays():
    rng = np.random.default_rng(11)
    shape = (500, 500)
    truth = _terrain(shape, bank=False)
    wood = _building(shape, (250, 150), (100, 100))  # 20 m across
    hall = _building(shape, (250, 390), (80, 80))  # 16 m across, round a courtyard 6 m across
    yard = _building(shape, (250, 390), (30, 30))
    top = _building(shape, (250, 150), (30, 30))  # a smooth crown top 6 m across, 7 m up
    objects = (wood | hall) & ~yard
    dsm = np.where(wood, truth + 7.0 + rng.normal(0, 0.3, shape), truth)
    dsm = np.where(hall & ~yard, truth + 6.0, dsm)
    dtm, measured, _, _ = _photogrammetric_dtm(truth, objects, rng)
    # the filter's DTM kept the crown top (a plateau wider than its window) and the courtyard
    dtm[top] = truth[top] + 7.0 + rng.normal(0, 0.01, (int(top.sum()),))
    measured = measured | top
    dsm[top] = dtm[top]
    clean = bare_earth(dsm, dtm, measured, CELL_M)
    assert not clean.ground[top].any()
    # the DTM under the wood stays with the ground round it, not pinned 7 m up
    # (without the rule: 3 % of the top kept as ground, the DTM 7.0 m up there; with it 0.11 m)
    assert np.abs(clean.z - truth)[wood].max() < 0.5, np.abs(clean.z - truth)[wood].max()
    # the courtyard's middle stays ground (the ring a rim leaves round it is taken out, as beside any wall)
    assert clean.ground[yard].mean() > 0.2
    assert np.percentile(np.abs(clean.z - truth)[yard], 95) < 0.05
