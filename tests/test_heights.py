"""Heights you can trust: the consumer-drone pathologies of synth, each handled against the truth or refused.

The clean tiny survey sets the bar; each pathology must come within 1.5x of its figures
(footprint IoU shortfall, SfM camera RMSE, ortho geolocation) or be refused with a line
naming what to give.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import geopandas as gpd
import numpy as np
import pytest
import rasterio
from conftest import RecordingFeedback, real_data

from geoortho.core.crs import geoid_undulation_m
from geoortho.core.surface import FlatSurface
from geoortho.errors import InputError
from geoortho.photos.footprint import footprints
from geoortho.photos.heights import check_altitudes, flight_height_range_m, resolve_heights
from geoortho.photos.metadata import Photo


def _survey(tmp_path_factory, name, pathology):
    from geoortho.synthetic.survey import synth

    return synth(tmp_path_factory.mktemp(name), preset="tiny", seed=3, workers=os.cpu_count() or 1, pathology=pathology)


@pytest.fixture(scope="module")
def no_rel(tmp_path_factory):
    return _survey(tmp_path_factory, "no_rel", "no-relative-altitude,dsm-datum,partial-dsm")


@pytest.fixture(scope="module")
def drift(tmp_path_factory):
    return _survey(tmp_path_factory, "drift", "altitude-drift")


def _info(survey):
    return json.loads((survey.truth / "survey.json").read_text())


def _iou_shortfall(out: Path, survey) -> float:
    """1 − mean IoU of the footprints against the true ones."""
    fp = gpd.read_file(out, layer="footprints").set_index("image")
    truth = gpd.read_file(survey.truth / "footprints.gpkg").set_index("image")
    ious = [
        g.intersection(truth.loc[n].geometry).area / g.union(truth.loc[n].geometry).area for n, g in fp.geometry.items()
    ]
    return 1.0 - float(np.mean(ious))


@pytest.fixture(scope="module")
def clean_shortfall(tiny_survey, tmp_path_factory):
    """The clean survey's footprint IoU shortfall on its DSM, the bar for every pathology."""
    out = tmp_path_factory.mktemp("clean_fp") / "fp.gpkg"
    footprints(tiny_survey.images, out, dsm=tiny_survey.dsm)
    return _iou_shortfall(out, tiny_survey)


# --- the geoid and the altitude checks --------------------------------------------------------


def test_geoid_undulation_is_egm96():
    # EGM96 geoid heights published for these places: Lisbon about +54 m, north-west Ohio about −35 m
    assert geoid_undulation_m(-9.1887, 38.7476) == pytest.approx(54.0, abs=1.5)
    assert geoid_undulation_m(-83.699, 41.549) == pytest.approx(-35.0, abs=2.0)
    both = geoid_undulation_m(np.array([-9.1887, -83.699]), np.array([38.7476, 41.549]))
    assert both.shape == (2,) and both[0] > 50 > -30 > both[1]


def _photo(i: int, **kw) -> Photo:
    t = f"2026-05-14T10:{i // 30:02d}:{(2 * i) % 60:02d}"
    base = dict(
        path=Path(f"P{i:03d}.JPG"),
        width_px=4000,
        height_px=3000,
        make="ACME",
        model="Cam",
        latitude_deg=38.0,
        longitude_deg=-9.0,
        focal_mm=8.8,
        sensor_width_mm=13.2,
        taken_at=t,
        has_xmp=True,
    )
    base.update(kw)
    return Photo(**base)


def test_altitude_check_finds_drift_jump_and_outlier():
    flat = [_photo(i) for i in range(40)]
    rng = np.random.default_rng(0)
    z = 100 + rng.normal(0, 0.3, 40)
    c = check_altitudes(flat, z, "GPS altitude")
    assert c.trusted and abs(c.drift_m) < 2 and not c.steps and not c.outliers
    d = check_altitudes(flat, z + np.linspace(0, 30, 40), "GPS altitude")
    assert not d.trusted and d.drift_m == pytest.approx(30, abs=2)
    j = z.copy()
    j[25:] += 12
    cj = check_altitudes(flat, j, "GPS altitude")
    assert not cj.trusted and cj.steps[0] == "P025.JPG" and abs(cj.drift_m) < 3
    o = z.copy()
    o[10] += 40
    co = check_altitudes(flat, o, "GPS altitude")
    assert co.trusted and co.outliers == ("P010.JPG",)


def _line(n: int, spacing_m: float, **kw) -> tuple[list[Photo], np.ndarray, np.ndarray]:
    photos = [_photo(i, yaw_deg=0.0, **kw) for i in range(n)]
    xy = np.c_[np.zeros(n), np.arange(n) * spacing_m]
    return photos, xy, np.tile([-9.0, 38.0], (n, 1))


def test_spacing_bounds_the_flight_height():
    # 4000x3000 px, f = 8.8 mm on 13.2 mm → 2667 px; image top along the course: the 3000 px side
    # spans 3000/2667·H. At 75 % front overlap and H = 60 m consecutive photos are 16.9 m apart.
    photos, xy, _ = _line(10, 0.25 * 3000 / 2666.67 * 60)
    lo, hi = flight_height_range_m(photos, xy)
    assert lo < 60 < hi and hi / lo < 3.5


def test_sea_level_altitude_is_refused_without_a_ground_model():
    photos, xy, ll = _line(12, 16.9, gps_altitude_m=412.0)
    with pytest.raises(InputError, match="flight_height_m"):
        resolve_heights(photos, xy, ll, None)
    # given the flight height, it is used and said
    h = resolve_heights(photos, xy, ll, None, flight_height_m=60.0)
    assert np.allclose(h.z_m, 60.0) and "flight height given" in h.method


def test_gps_altitude_read_against_the_ground_and_the_geoid():
    photos, xy, ll = _line(12, 16.9, gps_altitude_m=412.0)
    n = float(geoid_undulation_m(-9.0, 38.0))
    # Orthometric GPS over ellipsoidal ground 60 m below the camera: only +N makes it fit.
    ground = FlatSurface(412.0 + n - 60.0)
    h = resolve_heights(photos, xy, ll, ground)
    assert np.allclose(h.z_m - ground.elevation_m, 60.0, atol=0.01)
    assert "made ellipsoidal" in h.method
    # Ground in the GPS's own datum: as is.
    h2 = resolve_heights(photos, xy, ll, FlatSurface(352.0))
    assert np.allclose(h2.z_m, 412.0) and "as" in h2.method
    # Old DJI firmware (no XMP) writes the height above take-off there.
    old, xy, ll = _line(12, 16.9, gps_altitude_m=60.0, make="DJI", has_xmp=False)
    h3 = resolve_heights(old, xy, ll, None)
    assert np.allclose(h3.z_m, 60.0) and "above take-off" in h3.method and h3.notes


def test_drifting_gps_altitude_is_refused_and_named():
    photos, xy, ll = _line(30, 16.9)
    photos = [Photo(**{**p.__dict__, "gps_altitude_m": 400.0 + 2.0 * i}) for i, p in enumerate(photos)]
    with pytest.raises(InputError, match="drift"):
        resolve_heights(photos, xy, ll, FlatSurface(340.0))


# --- footprints on the pathologies ----------------------------------------------------------


def test_no_relative_altitude_refused_without_ground_then_right_on_the_dsm(no_rel, clean_shortfall, tmp_path):
    with pytest.raises(InputError, match="flight_height_m"):
        footprints(no_rel.images, tmp_path / "a.gpkg")
    fb = RecordingFeedback()
    r = footprints(no_rel.images, tmp_path / "b.gpkg", dsm=no_rel.dsm, feedback=fb)
    # GPSAltitude orthometric, the DSM ellipsoidal: the geoid puts them together
    assert "made ellipsoidal" in r.height_source and "EGM96" in r.height_source
    assert _iou_shortfall(tmp_path / "b.gpkg", no_rel) <= 1.5 * clean_shortfall + 0.005
    layer = gpd.read_file(tmp_path / "b.gpkg", layer="footprints")
    assert (layer.vertical_datum == "the DSM's datum").all() and layer.height_source.str.contains("GPS altitude").all()
    # with the flight height given instead, on flat ground
    info = _info(no_rel)
    r2 = footprints(no_rel.images, tmp_path / "c.gpkg", flight_height_m=info["preset"]["altitude_m"])
    assert r2.median_gsd_cm == pytest.approx(info["gsd_cm_at_home_height"], rel=0.1)


def test_no_relative_altitude_cli_refuses_in_one_line(no_rel, tmp_path):
    p = subprocess.run(
        [
            sys.executable,
            "-m",
            "geoortho",
            "footprints",
            "--images",
            str(no_rel.images),
            "--output",
            str(tmp_path / "x.gpkg"),
        ],
        capture_output=True,
        text=True,
    )
    assert p.returncode == 2
    lines = [x for x in p.stderr.splitlines() if x.strip()]
    assert len(lines) == 1 and "--flight-height-m" in lines[0] and "GPS altitude" in lines[0]
    assert "flight_height_m" not in lines[0]  # the command line names its options by their flags


def test_drifting_altitude_refused_unless_flight_height_given(drift, clean_shortfall, tmp_path):
    with pytest.raises(InputError, match="not trustworthy.*drift"):
        footprints(drift.images, tmp_path / "a.gpkg", dsm=drift.dsm)
    info = _info(drift)
    footprints(
        drift.images,
        tmp_path / "b.gpkg",
        dsm=drift.dsm,
        flight_height_m=info["preset"]["altitude_m"],
        takeoff_elevation_m=info["home"]["ground_z"],
    )
    assert _iou_shortfall(tmp_path / "b.gpkg", drift) <= 1.5 * clean_shortfall + 0.005


def test_dsm_in_another_datum_is_caught_for_relative_altitudes(tiny_survey, tmp_path):
    """RelativeAltitude + GNSS take-off on a DSM 54 m off: said, and the take-off taken from the DSM."""
    with rasterio.open(tiny_survey.dsm) as src:
        prof, z = src.profile, src.read(1)
    n = float(geoid_undulation_m(-9.1887, 38.7476))
    other = tmp_path / "dsm_orthometric.tif"
    with rasterio.open(other, "w", **prof) as dst:
        dst.write(np.where(z == prof["nodata"], z, z - n).astype(z.dtype), 1)
    fb = RecordingFeedback()
    r = footprints(tiny_survey.images, tmp_path / "fp.gpkg", dsm=other, feedback=fb)
    assert any("one is ellipsoidal, the other orthometric" in w for w in fb.warnings)
    assert "moved by the EGM96 geoid" in r.height_source
    # the same heights above ground as on the DSM in the photos' datum
    same = footprints(tiny_survey.images, tmp_path / "same.gpkg", dsm=tiny_survey.dsm)
    assert r.median_gsd_cm == pytest.approx(same.median_gsd_cm, rel=0.01)


def test_partial_dsm_falls_back_to_a_plane_not_to_the_range_limit(no_rel, tiny_survey, tmp_path):
    fb = RecordingFeedback()
    out = tmp_path / "fp.gpkg"
    footprints(no_rel.images, out, dsm=no_rel.truth / "dsm_partial.tif", feedback=fb)
    layer = gpd.read_file(out, layer="footprints")
    assert layer.outside_dsm.any() and not layer.clipped.any()
    assert np.isfinite(layer.gsd_cm).all()
    full = gpd.read_file(tiny_survey.truth / "footprints.gpkg")
    assert layer.area_m2.max() < 1.3 * full.geometry.area.max()
    assert any("beyond the DSM" in w for w in fb.warnings)


# --- SfM ------------------------------------------------------------------------------------

SFM_FAST = {"max_image_size": 960, "max_features": 4096}


def _gcp_list(survey, tmp_path):
    from geoortho.gcp.find import gcp_find

    return gcp_find(survey.images, survey.gcp_file, tmp_path / "gcp_list.txt").output


def _camera_rmse(result, survey) -> float:
    poses = {p["image"]: p for p in json.loads((survey.truth / "poses.json").read_text())}
    cams = gpd.read_file(result.cameras)
    reg = cams[cams.registered]
    e = np.array(
        [[r.x - poses[r.image]["x"], r.y - poses[r.image]["y"], r.z - poses[r.image]["z"]] for r in reg.itertuples()]
    )
    return float(np.sqrt((e**2).sum(axis=1).mean()))


@pytest.fixture(scope="module")
def clean_sfm(tiny_survey, tmp_path_factory):
    from geoortho.reconstruction.sparse import sfm

    d = tmp_path_factory.mktemp("clean_sfm")
    return sfm(tiny_survey.images, d / "out", gcp_list=_gcp_list(tiny_survey, d), **SFM_FAST)


@pytest.fixture(scope="module")
def clean_sfm_rmse(clean_sfm, tiny_survey):
    return _camera_rmse(clean_sfm, tiny_survey)


def _shifted(dsm: Path, out: Path, dz_m: float, keep_east_of: float | None = None) -> Path:
    """The DSM moved by dz_m (another vertical datum), optionally cut west of an easting."""
    with rasterio.open(dsm) as src:
        prof, z = src.profile, src.read(1)
        t = src.transform
    z = np.where(z == prof["nodata"], z, z + dz_m).astype(z.dtype)
    if keep_east_of is not None:
        c0 = int((keep_east_of - t.c) / t.a)
        z, t = z[:, c0:], t @ rasterio.Affine.translation(c0, 0)
        prof.update(width=z.shape[1], transform=t)
    with rasterio.open(out, "w", **prof) as dst:
        dst.write(z, 1)
    return out


def test_ortho_dsm_in_another_datum_measured_corrected_or_refused(clean_sfm, tiny_survey, tmp_path):
    from geoortho.orthophoto import ortho
    from geoortho.orthophoto.quality import geolocation_shifts

    n = float(geoid_undulation_m(-9.1887, 38.7476))
    good = ortho(tiny_survey.images, tmp_path / "good.tif", sfm=clean_sfm.output, dsm=tiny_survey.dsm, workers=1)
    other = _shifted(tiny_survey.dsm, tmp_path / "orthometric.tif", -n)
    fb = RecordingFeedback()
    r = ortho(tiny_survey.images, tmp_path / "o.tif", sfm=clean_sfm.output, dsm=other, workers=1, feedback=fb)
    note = next(x for x in r.notes if x.startswith("DSM vs SfM points"))
    assert "corrected" in note
    moved = float(note.split("DSM moved ")[1].split(" m")[0])
    assert moved == pytest.approx(n, abs=0.3)
    g0 = np.median([s.distance for s in geolocation_shifts(good.output, tiny_survey.ortho, tile_px=128)])
    g1 = np.median([s.distance for s in geolocation_shifts(r.output, tiny_survey.ortho, tile_px=128)])
    assert g1 <= 1.5 * g0 + 0.5 * r.resolution_m
    with pytest.raises(InputError, match="another vertical datum"):
        ortho(tiny_survey.images, tmp_path / "x.tif", sfm=clean_sfm.output, dsm=other, dsm_offset="refuse")
    assert not (tmp_path / "x.tif").exists()
    # the right DSM is measured too, and left alone
    assert any("DSM vs SfM points" in x and "corrected" not in x for x in good.notes)


def test_ortho_partial_dsm_keeps_every_photo(clean_sfm, tiny_survey, tmp_path):
    from geoortho.orthophoto import ortho

    info = _info(tiny_survey)
    fx0, _, fx1, _ = info["flight_box"]
    cut = fx0 + 0.6 * (fx1 - fx0)
    part = _shifted(tiny_survey.dsm, tmp_path / "part.tif", 0.0, keep_east_of=cut)
    full = ortho(tiny_survey.images, tmp_path / "full.tif", sfm=clean_sfm.output, dsm=tiny_survey.dsm, workers=1)
    r = ortho(tiny_survey.images, tmp_path / "part.tif", sfm=clean_sfm.output, dsm=part, workers=1)
    assert not r.skipped and r.n_used == full.n_used
    with rasterio.open(r.output) as a, rasterio.open(full.output) as b:
        # not clipped to the DSM's extent: west of the cut as far as the full DSM's, give or take the
        # plane standing in for the missing terrain
        assert a.bounds.left < cut - 20.0 and abs(a.bounds.left - b.bounds.left) < 5.0


def test_sfm_drifting_altitude_levelled_then_on_the_gcps(drift, clean_sfm_rmse, tmp_path):
    from geoortho.reconstruction.sparse import sfm

    r0 = sfm(drift.images, tmp_path / "gps", **SFM_FAST)
    rep0 = json.loads(r0.report.read_text())
    assert rep0["vertical_gps_trusted"] is False
    assert any("GPS altitude not trusted" in n and "drift" in n for n in rep0["notes"])
    assert "horizontally" in rep0["georeferenced_by"] and rep0["model_tilt_deg"] < 1.5
    r = sfm(drift.images, tmp_path / "gcp", gcp_list=_gcp_list(drift, tmp_path), **SFM_FAST)
    assert _camera_rmse(r, drift) <= 1.5 * clean_sfm_rmse + 0.01


def test_sfm_wrong_exif_focal_held_reported_then_fixed_by_gcps(tmp_path_factory, clean_sfm_rmse):
    import pycolmap  # as it is (geoortho's loader sets the level it checks)

    from geoortho.reconstruction.sparse import sfm
    from geoortho.reconstruction.sparse.lens import probe_free_focal

    survey = _survey(tmp_path_factory, "wrong_focal", "wrong-focal")
    d = tmp_path_factory.mktemp("wf")
    r0 = sfm(survey.images, d / "gps", **SFM_FAST)
    rep0 = json.loads(r0.report.read_text())
    assert any("focal length held" in n for n in rep0["notes"])
    cam0 = rep0["intrinsics"][0]
    assert cam0["focal_drift_pct"] == pytest.approx(0.0, abs=0.01) and "free_focal_drift_pct" in cam0
    # the free-focal probe leaves COLMAP's log level as geoortho set it (pycolmap.bundle_adjustment
    # reset it to INFO: every sfm after it printed COLMAP's lines to stderr)
    free = probe_free_focal(pycolmap.Reconstruction(str(r0.output / "model")))
    assert free and pycolmap.logging.minloglevel == int(pycolmap.logging.ERROR)
    r = sfm(survey.images, d / "gcp", gcp_list=_gcp_list(survey, d), **SFM_FAST)
    rep = json.loads(r.report.read_text())
    true_px = _info(survey)["camera"]["focal_px"]
    assert rep["intrinsics"][0]["focal_px"] == pytest.approx(true_px, rel=0.02)
    assert any("focal length" in n and "off the EXIF" in n for n in rep["notes"])
    assert _camera_rmse(r, survey) <= 1.5 * clean_sfm_rmse + 0.01


def test_toledo_height_source_gsd_and_focal(toledo_sfm, tmp_path):
    """EXIF GPS only (old DJI firmware): height above take-off, said; GSD by physics; focal near EXIF."""
    base = real_data("toledo_dji")
    r = footprints(base / "images", tmp_path / "fp.gpkg")
    assert "above take-off" in r.height_source
    layer = gpd.read_file(tmp_path / "fp.gpkg", layer="footprints")
    assert (layer.height_source.str.count("flat take-off ground") == 1).all(), layer.height_source[0]
    from geoortho.photos.metadata import read_photos

    photos = read_photos(base / "images").photos
    # physics at the flown height: GSD = height · sensor width / (focal · image width)
    physics = np.median(
        [p.gps_altitude_m * p.sensor_width_mm / (p.focal_mm * max(p.width_px, p.height_px)) * 100 for p in photos]
    )
    assert r.median_gsd_cm == pytest.approx(physics, rel=0.05)
    rep = json.loads(toledo_sfm.report.read_text())
    for cam in rep["intrinsics"]:
        assert abs(cam["focal_px"] / cam["focal_exif_px"] - 1) < 0.03, cam
    assert any(n.startswith("heights:") for n in rep["notes"])


def test_exposure_steps_balanced_from_exif_and_the_overlaps(tmp_path_factory):
    from geoortho.orthophoto import ortho

    survey = _survey(tmp_path_factory, "exposure", "exposure-steps")
    d = tmp_path_factory.mktemp("exp")
    info = _info(survey)
    r = ortho(survey.images, d / "o.tif", dsm=survey.dsm, takeoff_elevation_m=info["home"]["ground_z"], workers=1)
    rep = json.loads(r.report.read_text())
    poses = {p["image"]: p for p in json.loads((survey.truth / "poses.json").read_text())}
    # gain × exposure should be flat: the product's spread is far smaller than the step
    prod = np.array([np.mean(g) * poses[n]["exposure_gain"] for n, g in rep["gains_bgr"].items()])
    assert np.ptp(np.log(prod)) < 0.5 * abs(math.log(0.7))
    assert any("EXIF exposure" in n for n in rep["notes"])
    assert r.seam_mismatch_balanced < r.seam_mismatch_raw


def test_warnings_grouped_and_quiet(hard_survey, tmp_path):
    from geoortho.photos.metadata import read_photos

    fb = RecordingFeedback()
    read_photos(hard_survey.images, feedback=fb)
    assert len(fb.warnings) <= 5, fb.warnings  # one line per kind, not per photo
    assert all(": " in w and "photo" in w for w in fb.warnings)
    p = subprocess.run(
        [
            sys.executable,
            "-m",
            "geoortho",
            "footprints",
            "--images",
            str(hard_survey.images),
            "--output",
            str(tmp_path / "q.gpkg"),
            "--quiet",
        ],
        capture_output=True,
        text=True,
    )
    assert p.returncode == 0 and p.stderr.strip() == ""


def test_real_mini4pro_sea_level_altitudes_refused(tmp_path):
    """Real DJI Mini 4 Pro frames whose XMP keeps only AbsoluteAltitude (348 and 1190 m over Bali):
    no height above ground, so no footprint — a line naming what to give instead of 1 km-wide garbage."""
    images = real_data("dji_mini4pro_defects") / "images"
    with pytest.raises(InputError, match="flight_height_m") as e:
        footprints(images, tmp_path / "fp.gpkg")
    assert "348–1190 m" in str(e.value)
    r = footprints(images, tmp_path / "fp.gpkg", flight_height_m=100.0)
    assert r.n_photos == 3 and "flight height given" in r.height_source
