"""RTK/PPK photos: each photo's stated position accuracy read, weighed in the bundle adjustment,
and checked against the block; centimetre georeference without GCPs."""

from __future__ import annotations

import json
import math
import shutil

import geopandas as gpd
import numpy as np
import pytest
from conftest import SFM_FAST

import geoortho
from geoortho.photos.metadata import read_photo
from geoortho.photos.tags import DEFAULT_SIGMA_M, position_accuracy

# --- the tags on their own ----------------------------------------------------------------------


@pytest.mark.parametrize(
    ("tags", "expected"),
    [
        # DJI: the larger axis's deviation, the height's, the fix state by its SDK code
        (
            {"drone-dji:RtkFlag": "50", "drone-dji:RtkStdLon": "0.012", "drone-dji:RtkStdLat": "0.017",
             "drone-dji:RtkStdHgt": "0.025"},
            (0.017, 0.025, "fixed"),
        ),
        ({"drone-dji:RtkFlag": "34"}, (*DEFAULT_SIGMA_M["float"], "float")),  # a state, no deviation
        ({"drone-dji:RtkFlag": "16", "drone-dji:RtkStdLon": "1.2"}, (1.2, DEFAULT_SIGMA_M["single"][1], "single")),
        ({"drone-dji:RtkFlag": "0", "drone-dji:RtkStdLon": "9"}, (math.nan, math.nan, "consumer")),  # no RTK
        ({"Camera:GPSXYAccuracy": "0.05", "Camera:GPSZAccuracy": "0.08"}, (0.05, 0.08, "stated")),
        ({"Camera:GPSXYAccuracy": "0.05"}, (0.05, 0.10, "stated")),
        ({"drone-dji:GimbalYawDegree": "12"}, (math.nan, math.nan, "consumer")),
    ],
)  # fmt: skip
def test_position_accuracy_from_the_tags(tags, expected):
    h, v, fix, warning = position_accuracy(tags)
    np.testing.assert_allclose([h, v], expected[:2], equal_nan=True)
    assert fix == expected[2] and warning == ""


def test_a_fixed_solution_stated_at_metres_is_flagged():
    h, v, fix, warning = position_accuracy(
        {"drone-dji:RtkFlag": "50", "drone-dji:RtkStdLon": "5.0", "drone-dji:RtkStdLat": "4.0"}
    )
    assert (h, fix) == (5.0, "fixed")  # the deviation is measured; the state is a label
    assert "RtkFlag 50" in warning and "5 m" in warning


# --- a synthetic RTK survey ---------------------------------------------------------------------


@pytest.fixture(scope="module")
def rtk_tiny(tmp_path_factory):
    d = tmp_path_factory.mktemp("rtk")
    s = geoortho.synth(d / "survey", preset="tiny", seed=2, pathology="rtk")
    found = geoortho.gcp_find(s.images, s.gcp_file, d / "gcp_list.txt")
    names = sorted({line.split()[-1] for line in found.output.read_text().splitlines()[1:] if line.strip()})
    # every GCP a checkpoint: the block stands on the photos' positions alone
    # the tiny block (9 photos: 5 fixed, 3 float, 1 lost fix); bench_rtk measures the small one
    r = geoortho.sfm(s.images, d / "sfm", gcp_list=found.output, checkpoints=",".join(names), **SFM_FAST)
    return s, r


def _camera_errors(s, cameras_path):
    truth = {p["image"]: p for p in json.loads((s.truth / "poses.json").read_text())}
    cams = gpd.read_file(cameras_path)
    cams = cams[cams.registered]
    return cams, np.array([[c.x - truth[c.image]["x"], c.y - truth[c.image]["y"], c.z - truth[c.image]["z"]]
                           for c in cams.itertuples()])  # fmt: skip


def test_an_rtk_block_without_gcps_is_georeferenced_to_centimetres(rtk_tiny):
    s, r = rtk_tiny
    survey = json.loads((s.truth / "survey.json").read_text())
    cams, d = _camera_errors(s, r.cameras)
    assert len(d) == 9
    # measured: 1.8 cm horizontally (per axis) and 3.7 cm vertically; read as consumer GPS (every
    # photo at 2 m, heights from the barometer) 22.5 and 6.8 cm. bench_rtk, the small survey's 35
    # photos: 0.57 and 1.13 cm (8.9 and 1.6 cm as consumer GPS)
    assert np.sqrt((d[:, :2] ** 2).mean()) <= 0.03 and np.sqrt((d[:, 2] ** 2).mean()) <= 0.05
    report = json.loads(r.report.read_text())
    check = report["checkpoint_accuracy"]
    gsd_m = survey["gsd_cm_at_home_height"] / 100
    # measured: 11.0 cm (2.3 GSD) horizontally and 5.6 cm (1.2 GSD) vertically, against 22.3 and
    # 22.7 cm as consumer GPS; on the small survey (bench_rtk) 0.71 and 0.23 GSD (the 2 and 3)
    assert check["n"] >= 3 and report["gcp_accuracy"] is None  # no GCP controls the block
    assert check["rmse_horizontal_m"] <= 3 * gsd_m and check["rmse_z_m"] <= 3 * gsd_m
    # each photo's accuracy class and stated sigma, in the cameras layer and the report
    by_image = {c.image: c for c in cams.itertuples()}
    rtk = survey["rtk"]
    assert {n for n, c in by_image.items() if c.gps_fix == "float"} == set(rtk["float"])
    assert {n for n, c in by_image.items() if c.gps_fix == "single"} == set(rtk["lost_fix"])
    assert all(c.gps_sigma_h_m < 0.05 for c in by_image.values() if c.gps_fix == "fixed")
    classes = report["gps_accuracy"]["classes"]
    assert classes["fixed"]["photos"] == 9 - len(rtk["float"]) - len(rtk["lost_fix"])
    assert classes["fixed"]["rmse_h_m"] < 3 * classes["fixed"]["sigma_h_m"]  # the block agrees with them
    # the float and lost-fix photos are named
    notes = " ".join(report["notes"])
    assert all(n in notes for n in rtk["float"] + rtk["lost_fix"])


def test_a_block_of_rtk_and_consumer_photos_weighs_each_by_its_own(rtk_tiny, tmp_path):
    """The same flight written twice (same seed: the same pixels and poses), once by an RTK
    receiver and once by a consumer GPS; every other photo taken from each."""
    rtk = rtk_tiny[0]
    consumer = geoortho.synth(tmp_path / "consumer", preset="tiny", seed=2)
    mixed = tmp_path / "mixed"
    mixed.mkdir()
    names = sorted(p.name for p in rtk.images.iterdir())
    for i, n in enumerate(names):
        shutil.copy((rtk.images if i % 2 == 0 else consumer.images) / n, mixed / n)
    assert read_photo(mixed / names[0]).gps_fix != "consumer" and read_photo(mixed / names[1]).gps_fix == "consumer"
    r = geoortho.sfm(mixed, tmp_path / "sfm", **SFM_FAST)
    report = json.loads(r.report.read_text())
    assert report["gps_accuracy"]["consumer"] == len(names) // 2
    assert any("consumer GPS at the survey's gps_sigma_m" in n for n in report["notes"])
    cams = gpd.read_file(r.cameras).set_index("image")
    assert cams.loc[names[1], "gps_fix"] == "consumer" and math.isnan(cams.loc[names[1], "gps_sigma_h_m"])
    assert cams.loc[names[0], "gps_sigma_h_m"] < 2.0


# --- factory calibration ------------------------------------------------------------------------


def test_dji_factory_calibration_tags_are_read():
    from geoortho.photos.metadata import factory_calibration

    tags = {
        "drone-dji:CalibratedFocalLength": "3666.666504",
        "drone-dji:CalibratedOpticalCenterX": "2736.000000",
        "drone-dji:CalibratedOpticalCenterY": "1824.000000",
        "drone-dji:DewarpData": "2022-06-08;3713.29,3713.29,7.02,-8.72,-0.11257524,0.01487443,-0.00008572,0.00000076,"
        "-0.02706411",
        "drone-dji:DewarpFlag": "0",
    }
    f, cx, cy, dist, dewarped, warning = factory_calibration(tags, 5472, 3648)
    assert (f, cx, cy, dewarped, warning) == (3666.666504, 2736.0, 1824.0, False, "")
    assert dist == pytest.approx((-0.11257524, 0.01487443, -0.00008572, 0.00000076, -0.02706411))
    # already undistorted in the camera: no distortion to start from
    assert factory_calibration({**tags, "drone-dji:DewarpFlag": "1"}, 5472, 3648)[3:5] == ((), True)
    # a calibration of another image size is not this photo's
    f, *_, warning = factory_calibration(tags, 960, 640)
    assert math.isnan(f) and "cannot be this 960x640 photo's" in warning


@pytest.mark.parametrize(
    "distortion",
    ["nan,0.01,0,0,-0.02", "-0.11,inf,0,0,-0.02", "-0.11,0.01,0,0,NaN", "25.0,0,0,0,0", "-3.0,0,0,0,0", "0,0,0.4,0,0"],
)
def test_a_dewarp_data_no_lens_has_is_ignored_and_said(distortion):
    """NaN or inf in DewarpData stopped sfm with an assertion from COLMAP; an absurd distortion (the
    corner moved by half the frame, a folded lens, a tangential term of 0.4) was used and the
    failure blamed on overlap. Each is dropped with a warning; the focal length and centre stay."""
    from geoortho.photos.metadata import factory_calibration

    tags = {
        "drone-dji:CalibratedFocalLength": "3666.666504",
        "drone-dji:CalibratedOpticalCenterX": "2736.000000",
        "drone-dji:CalibratedOpticalCenterY": "1824.000000",
        "drone-dji:DewarpData": f"2022-06-08;3713.29,3713.29,7.02,-8.72,{distortion}",
    }
    f, cx, cy, dist, _, warning = factory_calibration(tags, 5472, 3648)
    assert (f, cx, cy, dist) == (3666.666504, 2736.0, 1824.0, ())
    assert "is no lens's: ignored" in warning


def test_two_factory_calibrations_of_one_model_are_two_camera_bodies(small_survey):
    """Two drones of one model in one flight carry two calibrations: each is its own body (the first
    photo's was taken for both)."""
    import dataclasses

    from geoortho.photos.metadata import read_photos
    from geoortho.reconstruction.sparse.inputs import camera_bodies

    photos = read_photos(small_survey.images).photos
    half = len(photos) // 2
    mixed = [
        dataclasses.replace(
            p, factory_focal_px=3000.0 if i < half else 3100.0, factory_cx_px=960.0, factory_cy_px=640.0
        )
        for i, p in enumerate(photos)
    ]
    bodies = camera_bodies(mixed)
    assert sorted(len(b.photos) for b in bodies) == sorted([half, len(photos) - half])
    assert {b.photos[0].factory_focal_px for b in bodies} == {3000.0, 3100.0}
    assert all("factory calibration f=" in b.label for b in bodies)
    assert len(camera_bodies(photos)) == 1


@pytest.mark.parametrize(
    ("pathology", "within_pct", "caught"),
    [
        # EXIF's focal length 12 % long, the factory calibration right: the calibration is used
        # (measured: 0.00 %, a free self-calibration would move it -0.14 %); EXIF alone: +12.0 %
        ("wrong-focal,factory-calibration", 0.5, False),
        # a calibration 10 % long (another unit's): held in this nadir block, and said (-9.2 %)
        ("wrong-calibration", 11.0, True),
    ],
)
def test_the_factory_calibration_starts_the_intrinsics_and_a_wrong_one_is_caught(
    tmp_path, pathology, within_pct, caught
):
    s = geoortho.synth(tmp_path / "survey", preset="tiny", seed=2, pathology=pathology)
    truth_px = json.loads((s.truth / "survey.json").read_text())["camera"]["focal_px"]
    r = geoortho.sfm(s.images, tmp_path / "sfm", **SFM_FAST)
    report = json.loads(r.report.read_text())
    (cam,) = report["intrinsics"]
    assert abs(cam["focal_px"] / truth_px - 1.0) * 100.0 <= within_pct
    assert any("factory calibration as the starting intrinsics" in n for n in report["notes"])
    said = [n for n in report["notes"] if "self-calibration would move the focal length" in n]
    assert bool(said) == caught, said
