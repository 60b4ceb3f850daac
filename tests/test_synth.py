"""The synthetic survey checked against itself and against independent readers."""

from __future__ import annotations

import dataclasses
import json
import re
import xml.etree.ElementTree as ET
from pathlib import Path

import cv2
import numpy as np
import pytest
from pyproj import Transformer

from geoortho.core.camera import Intrinsics, Pose, project_points


def _poses(survey) -> list[dict]:
    return json.loads((survey.truth / "poses.json").read_text())


def _markers(survey) -> dict[str, list[dict]]:
    return {m["image"]: m["markers"] for m in json.loads((survey.truth / "markers.json").read_text())}


def _info(survey) -> dict:
    return json.loads((survey.truth / "survey.json").read_text())


def _intrinsics(info: dict) -> Intrinsics:
    c = info["camera"]
    return Intrinsics(c["width_px"], c["height_px"], c["focal_px"], c["cx_px"], c["cy_px"], tuple(c["distortion"]))


def _ratio(v) -> float:
    return float(v.num) / float(v.den)


def _dms(tag) -> float:
    d, m, s = (_ratio(v) for v in tag.values)
    return d + m / 60 + s / 3600


def test_exif_read_back_by_exifread(tiny_survey):
    """exifread (not our code) reads GPS, camera and time as written; GPS is the recorded value."""
    import exifread

    info = _info(tiny_survey)
    for pose in _poses(tiny_survey):
        with open(tiny_survey.images / pose["image"], "rb") as f:
            tags = exifread.process_file(f, details=False)
        assert str(tags["Image Make"]) == "DJI"
        assert str(tags["Image Model"]) == info["camera"]["model"]
        assert _ratio(tags["EXIF FocalLength"].values[0]) == pytest.approx(info["camera"]["focal_mm"])
        assert int(str(tags["EXIF FocalLengthIn35mmFilm"])) == info["camera"]["focal_35mm"]
        assert int(str(tags["EXIF ExifImageWidth"])) == info["camera"]["width_px"]
        assert re.fullmatch(r"\d{4}:\d\d:\d\d \d\d:\d\d:\d\d", str(tags["EXIF DateTimeOriginal"]))
        lat = _dms(tags["GPS GPSLatitude"]) * (-1 if str(tags["GPS GPSLatitudeRef"]) == "S" else 1)
        lon = _dms(tags["GPS GPSLongitude"]) * (-1 if str(tags["GPS GPSLongitudeRef"]) == "W" else 1)
        rec = pose["recorded"]
        assert lat == pytest.approx(rec["latitude_deg"], abs=1e-7)
        assert lon == pytest.approx(rec["longitude_deg"], abs=1e-7)
        assert _ratio(tags["GPS GPSAltitude"].values[0]) == pytest.approx(rec["gps_altitude_m"], abs=0.01)


def test_xmp_read_back_by_elementtree(tiny_survey):
    """The DJI XMP packet is well-formed XML and carries the recorded attitude and altitudes."""
    ns = "http://www.dji.com/drone-dji/1.0/"
    for pose in _poses(tiny_survey):
        data = (tiny_survey.images / pose["image"]).read_bytes()
        start, end = data.find(b"<x:xmpmeta"), data.find(b"</x:xmpmeta>")
        assert start > 0 and end > start
        root = ET.fromstring(data[start : end + len(b"</x:xmpmeta>")])
        desc = root.find(".//{http://www.w3.org/1999/02/22-rdf-syntax-ns#}Description")
        assert desc is not None
        rec = pose["recorded"]
        values = {k.split("}")[1]: float(v) for k, v in desc.attrib.items() if k.startswith("{" + ns)}
        assert values["RelativeAltitude"] == pytest.approx(rec["relative_altitude_m"], abs=0.01)
        assert values["AbsoluteAltitude"] == pytest.approx(rec["absolute_altitude_m"], abs=0.01)
        assert values["GimbalPitchDegree"] == pytest.approx(rec["gimbal_pitch_deg"], abs=0.01)
        assert values["GimbalYawDegree"] == pytest.approx(rec["gimbal_yaw_deg"], abs=0.01)
        assert values["GimbalRollDegree"] == pytest.approx(rec["gimbal_roll_deg"], abs=0.01)
        for key in ("FlightYawDegree", "FlightPitchDegree", "FlightRollDegree"):
            assert key in values


def test_recorded_gps_is_truth_plus_bounded_noise(tiny_survey):
    info = _info(tiny_survey)
    to_utm = Transformer.from_crs("EPSG:4326", info["crs"], always_xy=True)
    err = []
    for pose in _poses(tiny_survey):
        rec = pose["recorded"]
        x, y = to_utm.transform(rec["longitude_deg"], rec["latitude_deg"])
        err.append(np.hypot(x - pose["x"], y - pose["y"]))
    em = info["error_model"]
    bound = 5 * np.hypot(em["gps_bias_sigma_m"], em["gps_noise_sigma_m"])
    assert 0 < max(err) < bound  # noisy, but not absurdly


def test_gcp_files_agree(tiny_survey):
    """The WGS84 and the UTM GCP files describe the same points; decoys are not in them."""
    info = _info(tiny_survey)
    utm_lines = (tiny_survey.truth / "gcp_utm.txt").read_text().splitlines()
    wgs_lines = (tiny_survey.truth / "gcp_wgs84.txt").read_text().splitlines()
    assert utm_lines[0] == info["crs"] and wgs_lines[0] == "EPSG:4979"
    to_utm = Transformer.from_crs("EPSG:4979", info["crs"], always_xy=True)
    utm = {ln.split()[0]: np.array(ln.split()[1:], float) for ln in utm_lines[1:]}
    wgs = {ln.split()[0]: np.array(ln.split()[1:], float) for ln in wgs_lines[1:]}
    real = {m["name"]: m for m in info["markers"] if not m["decoy"]}
    assert set(utm) == set(wgs) == set(real)
    for name, (lat, lon, h) in wgs.items():
        x, y = to_utm.transform(lon, lat)
        assert np.allclose([x, y, h], utm[name], atol=2e-3)
        assert np.allclose(utm[name], [real[name]["x"], real[name]["y"], real[name]["z"]], atol=1e-3)


def test_marker_truth_matches_projection(tiny_survey):
    """markers.json centres are the projection of the GCP positions with the true poses."""
    info = _info(tiny_survey)
    intr = _intrinsics(info)
    by_name = {m["name"]: m for m in info["markers"]}
    markers = _markers(tiny_survey)
    n = 0
    for pose in _poses(tiny_survey):
        p = Pose(np.array([pose["x"], pose["y"], pose["z"]]), np.array(pose["rotation_world_from_camera"]))
        for m in markers[pose["image"]]:
            g = by_name[m["gcp"]]
            px, _ = project_points(np.array([[g["x"], g["y"], g["z"]]]), intr, p)
            assert np.allclose(px[0], [m["x_px"], m["y_px"]], atol=1e-6)
            n += 1
    assert n > 0


def _detect(path: Path, dictionary: str) -> dict[int, np.ndarray]:
    from geoortho.gcp.markers import get_dictionary

    gray = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    det = cv2.aruco.ArucoDetector(get_dictionary(dictionary), params)
    corners, ids, _ = det.detectMarkers(gray)
    if ids is None:
        return {}
    return {int(i): c.reshape(4, 2).mean(axis=0) for i, c in zip(ids.ravel(), corners)}


def test_opencv_finds_visible_markers_at_their_true_pixels(tiny_survey):
    """OpenCV's ArUco detector (independent) finds nearly every fully visible marker near truth."""
    info = _info(tiny_survey)
    markers = _markers(tiny_survey)
    expected = found = 0
    errors = []
    for image, ms in markers.items():
        detections = _detect(tiny_survey.images / image, info["dictionary"])
        for m in ms:
            if not (m["inside"] and not m["occluded"]):
                continue
            expected += 1
            if m["marker_id"] in detections:
                found += 1
                errors.append(np.hypot(*(detections[m["marker_id"]] - [m["x_px"], m["y_px"]])))
        # nothing detected that is not there
        placed = {m["marker_id"] for m in ms if m["in_frame"]}
        assert set(detections) <= placed
    assert expected >= 10
    assert found >= 0.9 * expected
    # The mean of the four corners is not exactly the projected centre under perspective,
    # but at nadir it is within a fraction of a pixel.
    assert np.median(errors) < 0.5 and max(errors) < 1.5


def test_true_footprints_contain_projected_markers(tiny_survey):
    """A marker whose true projection is inside the frame lies inside the true footprint, and back."""
    import geopandas as gpd
    import shapely

    info = _info(tiny_survey)
    fp = gpd.read_file(tiny_survey.truth / "footprints.gpkg").set_index("image")
    assert fp.crs.to_epsg() == int(info["crs"].split(":")[1])
    by_name = {m["name"]: m for m in info["markers"]}
    inside = outside = 0
    for image, ms in _markers(tiny_survey).items():
        poly = fp.loc[image].geometry
        # the footprint is roughly the image's ground size at this altitude
        ground_w = info["preset"]["altitude_m"] * info["camera"]["width_px"] / info["camera"]["focal_px"]
        assert 0.7 * ground_w < np.sqrt(poly.area * 1.5) < 1.4 * ground_w
        for m in ms:
            g = by_name[m["gcp"]]
            pt = shapely.Point(g["x"], g["y"])
            w, h = info["camera"]["width_px"], info["camera"]["height_px"]
            if 2 < m["x_px"] < w - 3 and 2 < m["y_px"] < h - 3:
                assert poly.buffer(0.05).contains(pt), (image, m["gcp"])
                inside += 1
            elif not (-3 < m["x_px"] < w + 2 and -3 < m["y_px"] < h + 2):
                assert not poly.buffer(-0.05).contains(pt), (image, m["gcp"])
                outside += 1
    assert inside > 5


def test_rasters_and_points(tiny_survey):
    import laspy
    import rasterio

    info = _info(tiny_survey)
    with rasterio.open(tiny_survey.dsm) as dsm, rasterio.open(tiny_survey.dtm) as dtm:
        assert dsm.crs.to_string() == info["crs"] and dsm.profile["tiled"]
        a, b = dsm.read(1), dtm.read(1)
        assert (a >= b - 1e-4).all()  # DSM never below DTM
        assert (a - b).max() > 3  # a building or tree stands up
        transform = dsm.transform
    with rasterio.open(tiny_survey.ortho) as ortho:
        assert ortho.count >= 3 and ortho.crs.to_string() == info["crs"]
    las = laspy.read(tiny_survey.points)
    assert las.header.parse_crs().to_epsg() == int(info["crs"].split(":")[1])
    cls = np.asarray(las.classification)
    assert {2, 1}.issubset(set(np.unique(cls).tolist()))
    col = ((np.asarray(las.x) - transform.c) / transform.a).astype(int)
    row = ((np.asarray(las.y) - transform.f) / transform.e).astype(int)
    ok = (col >= 0) & (row >= 0) & (col < a.shape[1]) & (row < a.shape[0])
    ground = ok & (cls == 2)
    # ground points sit on the DTM (within a cell's slope)
    assert np.median(np.abs(np.asarray(las.z)[ground] - b[row[ground], col[ground]])) < 0.1


def test_deterministic_for_a_seed(tmp_path, tiny_survey):
    from geoortho.synthetic.survey import synth

    again = synth(tmp_path / "again", preset="tiny", seed=3, workers=1)
    for name in ("poses.json", "markers.json", "gcp_utm.txt"):
        assert (again.truth / name).read_text() == (tiny_survey.truth / name).read_text()
    first = sorted(p.name for p in tiny_survey.images.iterdir())
    assert first == sorted(p.name for p in again.images.iterdir())
    a = cv2.imread(str(tiny_survey.images / first[0]))
    b = cv2.imread(str(again.images / first[0]))
    assert np.array_equal(a, b)


@pytest.mark.parametrize("style", ["cos4", "flat-drop"])
def test_the_lens_falloff_is_drawn_as_its_style_says(tmp_path, tiny_survey, style):
    """The same survey drawn with another vignetting: photo by photo, ring by ring out from the
    centre, the brightness over the default's is the ratio of the two profiles (to JPEG's rounding)."""
    from geoortho.errors import InputError
    from geoortho.synthetic.render import vignetting
    from geoortho.synthetic.survey import synth

    other = synth(tmp_path / style, preset="tiny", seed=3, workers=1, vignetting_style=style)
    assert json.loads((other.truth / "survey.json").read_text())["degradations"]["vignetting_style"] == style
    name = sorted(p.name for p in tiny_survey.images.iterdir())[1]
    a = cv2.imread(str(tiny_survey.images / name)).astype(float).mean(axis=2)
    b = cv2.imread(str(other.images / name)).astype(float).mean(axis=2)
    h, w = a.shape
    yy, xx = np.indices(a.shape)
    rho = ((xx - (w - 1) / 2) ** 2 + (yy - (h - 1) / 2) ** 2) / (((w - 1) / 2) ** 2 + ((h - 1) / 2) ** 2)
    unclipped = (a > 30) & (a < 225) & (b < 225)
    for lo in np.arange(0.0, 0.9, 0.1):
        ring = unclipped & (rho >= lo) & (rho < lo + 0.1)
        want = float(vignetting(np.array(lo + 0.05), style) / vignetting(np.array(lo + 0.05)))
        assert b[ring].sum() / a[ring].sum() == pytest.approx(want, abs=0.005), lo
    with pytest.raises(InputError, match="vignetting_style"):
        synth(tmp_path / "bad", preset="tiny", seed=3, vignetting_style="fisheye")


def test_hard_preset_has_its_defects(hard_survey):
    from PIL import Image

    poses = _poses(hard_survey)
    assert sum(not p["has_xmp"] for p in poses) >= 2
    assert sum(not p["has_gps"] for p in poses) == 1
    corrupt = [p for p in poses if p["corrupt"]]
    assert len(corrupt) == 1
    with pytest.raises((OSError, SyntaxError)):
        Image.open(hard_survey.images / corrupt[0]["image"]).load()
    markers = [m for ms in _markers(hard_survey).values() for m in ms]
    assert any(m["glare"] for m in markers)
    w, h = _info(hard_survey)["camera"]["width_px"], _info(hard_survey)["camera"]["height_px"]

    def cut(m: dict) -> bool:  # centre in the frame, a corner outside it
        c = np.array(m["corners_px"])
        centre_in = 0 <= m["x_px"] <= w - 1 and 0 <= m["y_px"] <= h - 1
        return centre_in and not ((c >= 0).all() and (c[:, 0] <= w - 1).all() and (c[:, 1] <= h - 1).all())

    assert any(cut(m) and not m["inside"] for m in markers)  # cut by the frame edge
    assert any(p["blur_px"] > 0 for p in poses)
    for p in poses:
        if not p["has_xmp"] and not p["corrupt"]:
            assert b"drone-dji" not in (hard_survey.images / p["image"]).read_bytes()


def test_oblique_plan_and_footprints():
    """The oblique preset adds photos at pitch -45..-70 with free yaw; their true footprints reach
    far from the drone on the side it looks at (checked on the plan, to keep the suite fast)."""
    from geoortho.core.camera import Intrinsics
    from geoortho.synthetic.presets import FOCAL_MM, PRESETS, SENSOR_WIDTH_MM
    from geoortho.synthetic.survey import build_scene, plan_flight
    from geoortho.synthetic.truth import true_footprint

    p = PRESETS["oblique"]
    rng = np.random.default_rng(5)
    scene = build_scene(p, rng, lat=38.7476, lon=-9.1887, dictionary="DICT_4X4_50", marker_size_m=1.0)
    shots = plan_flight(p, scene, rng)
    obl = [s for s in shots if s.oblique]
    assert len(obl) == p.n_oblique >= 8
    assert all(-70.0 <= s.pitch_deg <= -45.0 for s in obl)
    assert np.ptp([s.yaw_deg for s in obl]) > 180  # free yaw, all round
    intr = Intrinsics.from_sensor(320, 213, FOCAL_MM, SENSOR_WIDTH_MM)
    for s in obl[:3]:
        xy, missed = true_footprint(scene, s, intr, per_side=8)
        d = xy - [s.x, s.y]
        centroid_dir = d.mean(axis=0) / np.linalg.norm(d.mean(axis=0))
        look = np.array([np.sin(np.radians(s.yaw_deg)), np.cos(np.radians(s.yaw_deg))])
        assert centroid_dir @ look > 0.9  # the footprint lies ahead, where the camera looks
        # the far edge is wider than the near edge (a trapezoid, not a rectangle)
        along = d @ look
        far, near = xy[along > np.quantile(along, 0.8)], xy[along < np.quantile(along, 0.2)]
        assert np.ptp(far @ [look[1], -look[0]]) > 1.3 * np.ptp(near @ [look[1], -look[0]])


def test_bad_preset_is_an_input_error(tmp_path):
    from geoortho.errors import InputError
    from geoortho.synthetic.survey import synth

    with pytest.raises(InputError, match="unknown preset"):
        synth(tmp_path, preset="huge")  # type: ignore[arg-type]


@pytest.mark.parametrize("length_px, angle_deg", [(7.6, 72.0), (4.0, 0.0), (3.3, 135.0)])
def test_motion_kernel_is_the_blur_it_is_said_to_be(length_px, angle_deg):
    """The truth's blur_px is the kernel's: a path of exactly that length (an odd whole-pixel line
    made 7.6 px a 9 px blur), centred, along its angle (anticlockwise from x, y down): its
    spread along the path is a box's, L / sqrt(12), plus the bilinear spread's 1/6 px²."""
    import math

    import numpy as np

    from geoortho.gcp.blur import motion_kernel

    k = motion_kernel(length_px, angle_deg).astype(float)
    c = k.shape[0] // 2
    ys, xs = np.mgrid[: k.shape[0], : k.shape[1]] - c
    a = math.radians(angle_deg)
    along = xs * math.cos(a) - ys * math.sin(a)
    across = xs * math.sin(a) + ys * math.cos(a)
    assert abs(k.sum() - 1) < 1e-5
    assert abs((k * xs).sum()) < 1e-4 and abs((k * ys).sum()) < 1e-4
    assert math.sqrt((k * along**2).sum()) == pytest.approx(math.sqrt(length_px**2 / 12 + 1 / 6), abs=0.02)
    assert (k * across**2).sum() < 0.2


def test_a_survey_without_pixels_has_the_same_tags_and_truth(tmp_path, tiny_survey):
    """--no-pixels: flat grey photos with only their markers drawn, every tag and truth file the
    same, in a fraction of the time; survey.json says so, and what is drawn on pixels is refused."""
    from geoortho.errors import InputError
    from geoortho.photos.metadata import read_photos
    from geoortho.synthetic.survey import synth

    bare = synth(tmp_path / "bare", preset="tiny", seed=3, workers=1, pixels=False)
    for name in ("poses.json", "markers.json", "gcp_utm.txt"):
        assert (bare.truth / name).read_text() == (tiny_survey.truth / name).read_text(), name
    assert json.loads((bare.truth / "survey.json").read_text())["pixels"].startswith("markers only")
    assert "pixels" not in _info(tiny_survey)
    rendered = {p.path.name: dataclasses.asdict(p) for p in read_photos(tiny_survey.images).photos}
    bare_photos = read_photos(bare.images).photos
    assert len(bare_photos) == len(rendered) == tiny_survey.n_photos
    for photo in bare_photos:
        tags, want = dataclasses.asdict(photo), rendered[photo.path.name]
        assert {k: v for k, v in tags.items() if k != "path"}.__repr__() == {
            k: v for k, v in want.items() if k != "path"
        }.__repr__()  # repr: NaN (a tag the photo lacks) is equal to itself there
    # the markers are drawn where the truth says, on grey: OpenCV finds them there
    info, markers = _info(bare), _markers(bare)
    found = 0
    for image, ms in markers.items():
        pixels = cv2.imread(str(bare.images / image))
        assert np.median(pixels) == 128  # the rest is flat grey
        detections = _detect(bare.images / image, info["dictionary"])
        for m in ms:
            if m["inside"] and m["marker_id"] in detections:
                found += 1
                assert np.hypot(*(detections[m["marker_id"]] - [m["x_px"], m["y_px"]])) < 1.5
    assert found >= 10
    with pytest.raises(InputError, match="without --no-pixels"):
        synth(tmp_path / "blurred", preset="tiny", seed=3, blur_px=5.0, pixels=False)
    assert not (tmp_path / "blurred").exists()


def test_synth_help_names_every_pathology():
    """Issue 76: synth --help listed 13 of its 21 pathologies; every one it builds is named."""
    import subprocess
    import sys

    from geoortho.synthetic.presets import PATHOLOGIES

    out = subprocess.run([sys.executable, "-m", "geoortho", "synth", "--help"], capture_output=True, text=True).stdout
    flat = " ".join(out.split()).replace("- ", "-")  # argparse wraps at hyphens
    missing = [name for name in PATHOLOGIES if name not in flat]
    assert not missing, missing


def test_a_complete_survey_of_the_same_preset_and_seed_is_found_again(tmp_path, tiny_survey):
    """What lets a second `demo` keep its survey: found when complete, of this preset and seed and
    renderer; not when a photo is newer than the truth's last file (drawing stopped part-way)."""
    import os
    import shutil

    from geoortho.synthetic.survey import existing_survey

    found = existing_survey(tiny_survey.output, "tiny", 3)
    assert found is not None and dataclasses.asdict(found) == dataclasses.asdict(tiny_survey)
    assert existing_survey(tiny_survey.output, "tiny", 4) is None
    assert existing_survey(tiny_survey.output, "small", 3) is None
    copy = Path(shutil.copytree(tiny_survey.output, tmp_path / "survey"))
    assert existing_survey(copy, "tiny", 3) is not None
    photo = sorted((copy / "images").iterdir())[0]
    later = (copy / "truth" / "points.laz").stat().st_mtime + 5
    os.utime(photo, (later, later))
    assert existing_survey(copy, "tiny", 3) is None
    photo.unlink()
    (copy / "truth" / "points.laz").touch()
    assert existing_survey(copy, "tiny", 3) is None  # a photo short of the poses
