"""Photo metadata and footprints, against the synthetic truth and on real photos."""

from __future__ import annotations

import json
import math
import subprocess
import sys

import geopandas as gpd
import numpy as np
import pytest
from conftest import RecordingFeedback, real_data
from pyproj import CRS

from geoortho.errors import InputError
from geoortho.photos.footprint import compute_footprints, footprints, photo_cameras
from geoortho.photos.metadata import parse_xmp, read_photo, read_photos


def _truth(survey):
    poses = {p["image"]: p for p in json.loads((survey.truth / "poses.json").read_text())}
    info = json.loads((survey.truth / "survey.json").read_text())
    return poses, info


def _iou(a, b) -> float:
    return a.intersection(b).area / a.union(b).area


# --- metadata ------------------------------------------------------------------------------


def test_read_photo_matches_what_was_recorded(tiny_survey):
    poses, info = _truth(tiny_survey)
    for name, t in poses.items():
        p = read_photo(tiny_survey.images / name)
        rec = t["recorded"]
        assert (p.width_px, p.height_px) == (info["camera"]["width_px"], info["camera"]["height_px"])
        assert (p.make, p.model) == ("DJI", info["camera"]["model"])
        assert p.latitude_deg == pytest.approx(rec["latitude_deg"], abs=1e-7)
        assert p.longitude_deg == pytest.approx(rec["longitude_deg"], abs=1e-7)
        assert p.relative_altitude_m == pytest.approx(rec["relative_altitude_m"], abs=0.01)
        assert p.absolute_altitude_m == pytest.approx(rec["absolute_altitude_m"], abs=0.01)
        assert p.gps_altitude_m == pytest.approx(rec["gps_altitude_m"], abs=0.01)
        assert (p.yaw_deg, p.pitch_deg, p.roll_deg) == pytest.approx(
            (rec["gimbal_yaw_deg"], rec["gimbal_pitch_deg"], rec["gimbal_roll_deg"]), abs=0.01
        )
        assert p.attitude_source == "gimbal" and p.sensor_source == "database"
        assert p.focal_px == pytest.approx(info["camera"]["focal_px"])
        assert p.taken_at.startswith("2026-")


def test_parse_xmp_attribute_and_element_forms():
    attr = b"<rdf:Description drone-dji:GimbalYawDegree=\"+12.50\" drone-dji:RelativeAltitude='+40.1'/>"
    elem = b"<drone-dji:GimbalPitchDegree>-80.00</drone-dji:GimbalPitchDegree><Camera:Yaw>33</Camera:Yaw>"
    tags = parse_xmp(attr + elem)
    assert tags["drone-dji:GimbalYawDegree"] == "+12.50"
    assert tags["drone-dji:RelativeAltitude"] == "+40.1"
    assert tags["drone-dji:GimbalPitchDegree"] == "-80.00"
    assert tags["Camera:Yaw"] == "33"
    assert parse_xmp(None) == {}


def test_camera_namespace_pitch_is_converted(tmp_path, tiny_survey):
    """MicaSense/Sentera-style Camera:Pitch 0 = nadir becomes our -90."""
    from PIL import Image

    src = next(tiny_survey.images.iterdir())
    xmp = (
        b'<x:xmpmeta xmlns:x="adobe:ns:meta/"><rdf:RDF><rdf:Description Camera:Yaw="30" '
        b'Camera:Pitch="10" Camera:Roll="2"/></rdf:RDF></x:xmpmeta>'
    )
    with Image.open(src) as im:
        im.save(tmp_path / "m.jpg", exif=im.getexif(), xmp=xmp)
    p = read_photo(tmp_path / "m.jpg")
    assert (p.yaw_deg, p.pitch_deg, p.roll_deg, p.attitude_source) == (30.0, -80.0, 2.0, "camera")


def test_bad_photos_are_named_and_skipped(hard_survey):
    poses, _ = _truth(hard_survey)
    ps = read_photos(hard_survey.images)
    skipped = dict(ps.skipped)
    corrupt = next(n for n, p in poses.items() if p["corrupt"])
    no_gps = next(n for n, p in poses.items() if not p["has_gps"])
    assert "truncated" in skipped[corrupt] or "readable" in skipped[corrupt]
    assert "GPS" in skipped[no_gps]
    assert len(ps.photos) == len(poses) - 2
    # No XMP: attitude unknown, yaw from the flight course, close to the truth.
    for p in ps.photos:
        if not poses[p.image]["has_xmp"]:
            assert "course" in p.attitude_source and p.warnings
            assert abs((p.yaw_deg - poses[p.image]["yaw_deg"] + 180) % 360 - 180) < 10


def test_not_a_folder_and_empty_folder(tmp_path):
    with pytest.raises(InputError, match="no images"):
        read_photos(tmp_path)
    with pytest.raises(InputError, match="not a folder"):
        read_photos(tmp_path / "missing")


def test_real_brighton_dji_xmp():
    folder = real_data("brighton_dji_xmp_pair") / "images"
    p = read_photo(folder / "DJI_0018.JPG")
    assert (p.model, p.width_px, p.height_px) == ("FC300S", 4000, 2250)  # 16:9 crop
    assert (p.relative_altitude_m, p.yaw_deg, p.pitch_deg) == (39.8, 45.0, -89.9)
    assert p.sensor_width_mm == 6.17 and p.attitude_source == "gimbal"
    assert p.latitude_deg == pytest.approx(46.8426, abs=1e-4) and p.longitude_deg < 0


def test_real_toledo_sizes_that_lie_and_no_xmp():
    folder = real_data("toledo_dji") / "images"
    ps = read_photos(folder)
    assert len(ps.photos) == 57 and not ps.skipped
    assert {p.model for p in ps.photos} == {"FC300X", "FC350"}
    # EXIF says 1800 x 2400; the pixels are 2400 x 1800
    assert all((p.width_px, p.height_px) == (2400, 1800) for p in ps.photos)
    assert all(not p.has_xmp and "course" in p.attitude_source for p in ps.photos)
    table = ps.to_geodataframe("EPSG:32617")
    assert len(table) == 57 and table.crs.to_epsg() == 32617
    # ODM's own image-location file for this set agrees with our GPS reading and projection
    listed = {}
    for line in (folder.parent / "gcp" / "cameras_32617.txt").read_text().splitlines()[1:]:
        x, y, name = line.split()
        listed[name] = (float(x), float(y))
    d = [math.hypot(g.x - listed[n][0], g.y - listed[n][1]) for n, g in zip(table["image"], table.geometry)]
    assert max(d) < 0.5


def test_real_mini4pro_partial_xmp():
    folder = real_data("dji_mini4pro_defects") / "images"
    ps = read_photos(folder)
    by = {p.image: p for p in ps.photos}
    cap = by["DJI_20251027143608_0008_D_LENS_CAP.JPG"]
    assert cap.pitch_deg == -80.0 and cap.yaw_deg == pytest.approx(89.6)
    assert "aircraft" in " ".join(cap.warnings)
    sharp = by["DJI_20251001132715_0396_D_POOR_SHARPNESS.JPG"]
    assert sharp.attitude_source.startswith("assumed nadir") and sharp.sensor_width_mm == 9.7


def test_real_phone_photo_with_trailer_is_not_truncated():
    folder = real_data("findgcp_aruco") / "images"
    ps = read_photos(folder, require_gps=False)
    assert len(ps.photos) == 2 and ps.photos[0].sensor_source == "35mm equivalent (diagonal)"


# --- footprints ----------------------------------------------------------------------------


def test_footprints_with_true_poses_reproduce_the_truth(tiny_survey):
    """With the exact poses and the DSM, our footprints are the true ones (geometry check)."""
    from geoortho.core.camera import Intrinsics, Pose, PosedCamera
    from geoortho.core.surface import read_surface

    poses, info = _truth(tiny_survey)
    c = info["camera"]
    intr = Intrinsics(c["width_px"], c["height_px"], c["focal_px"], c["cx_px"], c["cy_px"])
    cams = [
        PosedCamera(intr, Pose(np.array([t["x"], t["y"], t["z"]]), np.array(t["rotation_world_from_camera"])), n)
        for n, t in poses.items()
    ]
    surface = read_surface(tiny_survey.dsm)
    table = compute_footprints(cams, surface, per_side=40)
    truth = gpd.read_file(tiny_survey.truth / "footprints.gpkg").set_index("image")
    import shapely

    ious = [_iou(shapely.Polygon(r), truth.loc[n].geometry) for n, r in zip(poses, table.rings)]
    # 1.0 but where a border ray grazes a roof edge (our march steps 2 cells, the truth 1)
    assert min(ious) > 0.99 and np.median(ious) > 0.9999
    # nadir GSD at the centre is range / focal
    assert np.allclose(table.gsd_m, table.altitude_m / c["focal_px"], rtol=0.05)


def test_footprints_iou_on_dsm(tiny_survey, tmp_path):
    poses, info = _truth(tiny_survey)
    out = tmp_path / "fp.gpkg"
    r = footprints(
        tiny_survey.images,
        out,
        dsm=tiny_survey.dsm,
        takeoff_elevation_m=info["home"]["ground_z"],
        overlap=tmp_path / "overlap.tif",
        overlap_cell_m=0.5,
    )
    fp = gpd.read_file(out, layer="footprints").set_index("image")
    truth = gpd.read_file(tiny_survey.truth / "footprints.gpkg").set_index("image")
    ious = [_iou(g, truth.loc[n].geometry) for n, g in fp.geometry.items()]
    assert np.mean(ious) >= 0.93 and min(ious) >= 0.85
    assert r.n_photos == len(poses) and fp.crs.to_epsg() == 32629
    # GSD near the true one at the nadir
    assert r.median_gsd_cm == pytest.approx(info["gsd_cm_at_home_height"], rel=0.1)
    cams = gpd.read_file(out, layer="cameras").set_index("image")
    for n, t in poses.items():
        assert math.hypot(cams.loc[n].geometry.x - t["x"], cams.loc[n].geometry.y - t["y"]) < 3.0
    import rasterio

    with rasterio.open(r.overlap) as ov:
        counts = ov.read(1)
        assert counts.max() >= 4 and ov.nodata == 0
        # a cell's count equals the number of footprints containing its centre
        row, col = np.unravel_index(np.argmax(counts), counts.shape)
        x, y = ov.xy(row, col)
        import shapely

        assert counts[row, col] == int(shapely.contains_xy(fp.geometry.values, x, y).sum())


def test_flat_ground_worse_than_dsm_but_sane(tiny_survey, tmp_path):
    out = tmp_path / "flat.gpkg"
    footprints(tiny_survey.images, out)
    fp = gpd.read_file(out, layer="footprints").set_index("image")
    truth = gpd.read_file(tiny_survey.truth / "footprints.gpkg").set_index("image")
    ious = [_iou(g, truth.loc[n].geometry) for n, g in fp.geometry.items()]
    assert np.mean(ious) > 0.75
    assert set(fp["height_source"].str.contains("relative altitude")) == {True}


def test_oblique_footprints_iou(oblique_survey, tmp_path):
    poses, info = _truth(oblique_survey)
    out = tmp_path / "obl.gpkg"
    footprints(oblique_survey.images, out, dsm=oblique_survey.dsm, takeoff_elevation_m=info["home"]["ground_z"])
    fp = gpd.read_file(out, layer="footprints").set_index("image")
    truth = gpd.read_file(oblique_survey.truth / "footprints.gpkg").set_index("image")
    obl = [_iou(g, truth.loc[n].geometry) for n, g in fp.geometry.items() if poses[n]["oblique"]]
    nadir = [_iou(g, truth.loc[n].geometry) for n, g in fp.geometry.items() if not poses[n]["oblique"]]
    assert len(obl) >= 8
    assert np.mean(obl) >= 0.85 and np.mean(nadir) >= 0.93
    # oblique footprints are bigger and their GSD varies across the frame
    o = fp[[poses[n]["oblique"] for n in fp.index]]
    assert (o["gsd_max_cm"] / o["gsd_min_cm"]).min() > 1.5


def test_rays_above_horizon_are_clipped():
    from geoortho.core.camera import Intrinsics, Pose, PosedCamera
    from geoortho.core.surface import FlatSurface

    intr = Intrinsics(400, 300, 300.0)
    cams = [
        PosedCamera(intr, Pose.from_ypr((0, 0, 50), 0, -10, 0)),
        PosedCamera(intr, Pose.from_ypr((0, 0, 50), 0, -90, 0)),
    ]
    t = compute_footprints(cams, FlatSurface(0.0), max_range_m=300.0)
    assert t.clipped.tolist() == [True, False]
    assert np.hypot(*t.rings[0].T).max() == pytest.approx(300.0, rel=0.01)


def test_real_toledo_footprints_predict_annotated_gcp_pixels(tmp_path):
    """Camera model + course yaw predict where the GCPs of ODM's toledo gcp_list.txt were clicked."""
    folder = real_data("toledo_dji")
    ps = read_photos(folder / "images")
    cams, _ = photo_cameras(ps.photos, CRS.from_epsg(32617))
    by = {c.photo.image: c for c in cams}
    errors = []
    for line in (folder / "gcp" / "gcp_list.txt").read_text().splitlines()[1:]:
        f = line.split()
        if len(f) < 6 or line.startswith("#"):
            continue
        x, y, _, px, py = map(float, f[:5])
        pred = by[f[5]].project(np.array([[x, y, 0.0]]))[0][0]  # ground at the take-off height
        if f[5] != "DJI_0068.JPG":
            errors.append(math.hypot(pred[0] - px, pred[1] - py))
    # GPS and the take-off height assumption bound this: metres, i.e. tens of pixels at 8 cm GSD.
    # DJI_0068 is left out: the Inspire 1 turned its camera north-up there while flying east, and
    # without XMP nothing in the file says so (its annotated GCPs show it).
    assert len(errors) == 14
    assert np.median(errors) < 100 and max(errors) < 200
    out = tmp_path / "toledo.gpkg"
    r = footprints(folder / "images", out)
    fp = gpd.read_file(out, layer="footprints").sort_values("taken_at")
    assert 5 < r.median_gsd_cm < 12  # published 6.17 mm sensor, 3.61 mm lens, ~110-120 m
    # consecutive photos of a flight line overlap, as a survey plan implies
    geoms = fp.geometry.values
    overl = [_iou(a, b) for a, b in zip(geoms, geoms[1:])]
    assert np.median(overl) > 0.4


def test_footprints_cli_bad_input_exit_2(tmp_path):
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "geoortho",
            "footprints",
            "--images",
            str(tmp_path),
            "--output",
            str(tmp_path / "x.gpkg"),
        ],
        capture_output=True,
        text=True,
    )
    assert r.returncode == 2
    assert len(r.stderr.strip().splitlines()) == 1 and "no images" in r.stderr


def _with_exif(src, dst, gps=None, exif=None):
    """A copy of ``src`` with some EXIF GPS/Exif tags replaced (piexif), its XMP kept."""
    import piexif

    data = piexif.load(str(src))
    for k, v in (gps or {}).items():
        data["GPS"][k] = v
    for k, v in (exif or {}).items():
        data["Exif"][k] = v
    piexif.insert(piexif.dump(data), str(src), str(dst))
    return dst


def test_garbage_photos_are_skipped_with_their_reason_the_batch_goes_on(tiny_survey, tmp_path):
    """Issue 23 (3, 4): lat 95 gave POINT(inf inf); a photo 12,000 km away was kept; a header of
    30000 x 30000 px killed every command; focal length 0 killed footprints."""
    import piexif

    folder = tmp_path / "images"
    folder.mkdir()
    srcs = sorted(tiny_survey.images.iterdir())
    for s in srcs[1:]:
        (folder / s.name).write_bytes(s.read_bytes())
    _with_exif(srcs[0], folder / "lat95.jpg", gps={piexif.GPSIFD.GPSLatitude: ((95, 1), (0, 1), (0, 1))})
    _with_exif(
        srcs[0],
        folder / "far.jpg",
        gps={piexif.GPSIFD.GPSLatitudeRef: b"S", piexif.GPSIFD.GPSLongitude: ((170, 1), (0, 1), (0, 1))},
    )
    _with_exif(srcs[0], folder / "focal0.jpg", exif={piexif.ExifIFD.FocalLength: (0, 1)})
    # a JPEG whose frame header claims 30000 x 30000 pixels
    raw = bytearray(srcs[0].read_bytes())
    sof = raw.find(b"\xff\xc0")
    raw[sof + 5 : sof + 9] = (30000).to_bytes(2, "big") * 2
    (folder / "bomb.jpg").write_bytes(bytes(raw))
    ps = read_photos(folder)
    skipped = dict(ps.skipped)
    assert "out of range" in skipped["lat95.jpg"]
    assert "km from the other photos" in skipped["far.jpg"]
    assert "M pixels" in skipped["bomb.jpg"]
    focal0 = next(p for p in ps.photos if p.image == "focal0.jpg")  # the 35 mm equivalent stands in
    assert any("not a lens" in w for w in focal0.warnings) and focal0.focal_px > 0
    assert {p.image for p in ps.photos} == {s.name for s in srcs[1:]} | {"focal0.jpg"}
    r = footprints(folder, tmp_path / "fp.gpkg")
    assert r.n_photos == len(srcs) and r.n_skipped == 3


def test_a_dsm_far_larger_than_the_flight_is_read_only_under_it(tiny_survey, tmp_path, monkeypatch):
    """The tiny survey's DSM set in a 40 km square of nodata (a county's DSM, 1.6 G cells at 1 m
    if read whole): footprints read the window under the flight (out to the longest ray), and
    give the footprints of the DSM alone; a window over the cell budget is read decimated."""
    import rasterio
    from rasterio.transform import from_origin

    import geoortho.photos.footprint as fpmod
    import geoortho.photos.photo_cameras as cameras
    from geoortho.core import surface as surf

    home = json.loads((tiny_survey.truth / "survey.json").read_text())["home"]
    with rasterio.open(tiny_survey.dsm) as src:
        z, tr, prof = src.read(1), src.transform, src.profile
    side = round(40_000 / tr.a)
    big = tmp_path / "county.tif"
    x0, y0 = tr.c - 20_000, tr.f + 20_000
    prof.update(width=side, height=side, transform=from_origin(x0, y0, tr.a, -tr.e), tiled=True, compress="deflate")
    prof.update(blockxsize=512, blockysize=512, BIGTIFF="YES")
    with rasterio.open(big, "w", **prof) as dst:  # sparse: only the DSM's blocks are written
        col, row = round((tr.c - x0) / tr.a), round((y0 - tr.f) / -tr.e)
        dst.write(z, 1, window=rasterio.windows.Window(col, row, z.shape[1], z.shape[0]))
    shapes = []
    real = surf.read_surface

    def spy(*a, **k):
        s = real(*a, **k)
        shapes.append(s.grid.shape)
        return s

    monkeypatch.setattr(cameras, "read_surface", spy)
    args = dict(takeoff_elevation_m=home["ground_z"])
    a = footprints(tiny_survey.images, tmp_path / "a.gpkg", dsm=tiny_survey.dsm, **args)
    b = footprints(tiny_survey.images, tmp_path / "b.gpkg", dsm=big, **args)
    rows, cols = shapes[-1]
    assert rows * cols < 0.001 * side * side  # the window, not the county
    ga = gpd.read_file(tmp_path / "a.gpkg", layer="footprints").set_index("image")
    gb = gpd.read_file(tmp_path / "b.gpkg", layer="footprints").set_index("image")
    assert a.n_photos == b.n_photos and list(ga.index) == list(gb.index)
    ious = [_iou(ga.geometry[n], gb.geometry[n]) for n in ga.index]
    assert min(ious) > 0.999, (ious, ga.outside_dsm.tolist(), gb.outside_dsm.tolist())
    for module in (cameras, fpmod):  # the read under the flight, and what footprints says of it
        monkeypatch.setattr(module, "DSM_MAX_CELLS", 10_000)
    fb = RecordingFeedback()
    c = footprints(tiny_survey.images, tmp_path / "c.gpkg", dsm=big, feedback=fb, **args)
    assert shapes[-1][0] * shapes[-1][1] <= 10_000
    assert any(m.startswith("DSM read at") for m in fb.infos), fb.infos
    gc = gpd.read_file(tmp_path / "c.gpkg", layer="footprints").set_index("image")
    assert c.n_photos == a.n_photos and np.mean([_iou(ga.geometry[n], gc.geometry[n]) for n in ga.index]) > 0.95


def _retag(survey, folder, maker: str, absolute: bool = True):
    """The survey's photos with the same recorded metadata written in ``maker``'s tags
    (``absolute``: with the AbsoluteAltitude where the family has one)."""
    from PIL import Image

    from geoortho.core.camera import Intrinsics
    from geoortho.synthetic import flight, render

    folder.mkdir()
    cam = json.loads((survey.truth / "survey.json").read_text())["camera"]
    intr = Intrinsics(cam["width_px"], cam["height_px"], cam["focal_px"])
    for t in json.loads((survey.truth / "poses.json").read_text()):
        if not t["has_xmp"] or t["corrupt"]:
            continue
        rec = t["recorded"]
        shot = flight.Shot(
            t["image"],
            t["x"],
            t["y"],
            t["z"],
            t["yaw_deg"],
            t["pitch_deg"],
            t["roll_deg"],
            rec_lat=rec["latitude_deg"],
            rec_lon=rec["longitude_deg"],
            rec_gps_alt_m=rec["gps_altitude_m"],
            rec_rel_alt_m=rec["relative_altitude_m"],
            rec_abs_alt_m=rec["absolute_altitude_m"] if absolute else math.nan,
            rec_yaw_deg=rec["gimbal_yaw_deg"],
            rec_pitch_deg=rec["gimbal_pitch_deg"],
            rec_roll_deg=rec["gimbal_roll_deg"],
            flight_yaw_deg=rec["flight_yaw_deg"],
            time="2026:05:01 10:00:00",
            maker=maker,
        )
        with Image.open(survey.images / t["image"]) as im:
            render._write_jpeg(folder / t["image"], np.asarray(im.convert("RGB")), shot, intr)
    return folder


@pytest.mark.parametrize("maker", ["autel", "parrot", "skydio", "pix4d", "sensefly", "exif"])
def test_every_maker_family_reads_back_and_gives_the_dji_footprint(tiny_survey, tmp_path, maker):
    """Issue 26: attitude read back from each maker's tags as the header states it; the footprint
    of a photo written with that family's tags is the DJI-tagged one."""
    folder = _retag(tiny_survey, tmp_path / maker, maker)
    dji = {p.image: p for p in read_photos(tiny_survey.images).photos}
    theirs = read_photos(folder).photos
    assert len(theirs) >= 8
    for p in theirs:
        d = dji[p.image]
        assert p.latitude_deg == pytest.approx(d.latitude_deg, abs=1e-7)
        assert p.longitude_deg == pytest.approx(d.longitude_deg, abs=1e-7)
        if maker == "exif":  # no XMP: GPSImgDirection is the yaw, the rest assumed and said
            assert p.attitude_source == "exif direction" and (p.pitch_deg, p.roll_deg) == (-90.0, 0.0)
            assert p.yaw_deg == pytest.approx(d.yaw_deg, abs=0.01)
            assert any("GPSImgDirection" in w for w in p.warnings)
            continue
        assert (p.yaw_deg, p.pitch_deg, p.roll_deg) == pytest.approx((d.yaw_deg, d.pitch_deg, d.roll_deg), abs=0.006)
        assert p.relative_altitude_m == pytest.approx(d.relative_altitude_m, abs=0.006)
        assert p.attitude_source == {"pix4d": "camera", "sensefly": "camera"}.get(maker, f"gimbal ({maker.title()})")
    if maker == "exif":
        return
    # against DJI tags carrying what this family carries (Parrot, MicaSense, senseFly: no AbsoluteAltitude)
    dji_tags = _retag(tiny_survey, tmp_path / "dji", "dji", absolute=maker in ("autel", "skydio"))
    ours = footprints(folder, tmp_path / "f.gpkg", dsm=tiny_survey.dsm)
    ref = footprints(dji_tags, tmp_path / "ref.gpkg", dsm=tiny_survey.dsm)
    a = gpd.read_file(ours.output, layer="footprints").set_index("image")
    b = gpd.read_file(ref.output, layer="footprints").set_index("image")
    assert set(a["attitude_source"]) == {theirs[0].attitude_source}
    ious = [_iou(a.loc[n].geometry, b.loc[n].geometry) for n in a.index]
    assert len(ious) >= 8 and min(ious) > 0.999, ious


def test_skydio_struct_in_attribute_form_and_other_frames():
    """Skydio's older firmware writes the struct's fields as attributes; its other frames (FLU,
    the body's) share the field names and must not be read as the camera's."""
    xmp = (
        b'<rdf:Description><drone-skydio:CameraOrientationFLU drone-skydio:Roll="1.0" drone-skydio:Pitch="5.0" '
        b'drone-skydio:Yaw="44.0"/><drone-skydio:CameraOrientationNED drone-skydio:Roll="0.2" '
        b'drone-skydio:Pitch="-84.0" drone-skydio:Yaw="146.5"/></rdf:Description>'
    )
    tags = parse_xmp(xmp)
    assert tags["drone-skydio:CameraOrientationNED:Pitch"] == "-84.0"
    assert tags["drone-skydio:CameraOrientationNED:Yaw"] == "146.5"
    assert tags["drone-skydio:CameraOrientationFLU:Yaw"] == "44.0"


def test_sensor_table_of_thousands_of_cameras():
    """Issue 26: OpenSfM's public table ships with the package; our DJI entries win where more precise."""
    from geoortho.photos.sensors import opensfm_sensor_table as _sensor_table
    from geoortho.photos.sensors import sensor_width_from_table

    assert len(_sensor_table()) > 3600
    assert sensor_width_from_table("Canon", "PowerShot S110") == 7.53  # the eBee's old camera
    assert sensor_width_from_table("NIKON CORPORATION", "NIKON D800") == 35.9  # make's first word
    assert sensor_width_from_table("DJI", "FC330") == 6.17  # ours (OpenSfM: 6.25)
    assert sensor_width_from_table("SONY", "DSC-RX1RM2") == 35.9  # WingtraOne, ours
    assert math.isnan(sensor_width_from_table("Nobody", "X-1"))


@pytest.mark.parametrize(
    ("folder", "model", "width_mm", "tol"),
    [
        # Mini 4 Pro, 4:3: the width rule gave 10.08 mm (4 % off); the diagonal 9.69
        ("dji_mini4pro_defects", "fc8482", 9.7, 0.002),
        # Phantom 3 in 16:9 (4000 x 2250) on its 4:3 sensor: f35 stays the whole sensor's (20 mm)
        ("brighton_dji_xmp_pair", "fc300s", 6.17, 0.015),
        # Phantom 3, 4:3 photos downscaled to 2400 x 1800
        ("toledo_dji", "fc300x", 6.17, 0.015),
    ],
)
def test_35mm_fallback_by_the_diagonal_on_real_photos(monkeypatch, folder, model, width_mm, tol):
    """A camera missing from every table: its width from the 35 mm equivalent by the diagonal,
    crop modes included, and the GSD this gives against physics (pixel pitch x height / focal)."""
    import geoortho.photos.metadata as photos

    monkeypatch.delitem(photos.SENSOR_WIDTHS_MM, model)
    monkeypatch.setattr(photos, "sensor_width_from_table", lambda make, model: math.nan)
    p = read_photos(real_data(folder) / "images", require_gps=False).photos[0]
    assert p.sensor_source.startswith("35mm equivalent (diagonal")
    assert p.sensor_width_mm == pytest.approx(width_mm, rel=tol)
    # GSD at 100 m: the fallback's against the published sensor's, within 2 %
    gsd = 100.0 / p.focal_px
    true_gsd = 100.0 * width_mm / p.focal_mm / max(p.width_px, p.height_px)
    assert gsd == pytest.approx(true_gsd, rel=0.02)


def test_footprints_agree_across_projected_crs(tiny_survey, tmp_path):
    """Issue 26: yaw is from true north; in a projected CRS the footprint turns by the meridian
    convergence and grows by the point scale. Written in PT-TM06 (EPSG:3763), UTM 29N and UTM 30N
    (photos 6° west of its central meridian: convergence 3.9°, scale 1.0036) and reprojected to one CRS,
    they agree (before: 1.03 % of the area apart between 3763 and UTM 29N, 0.10 % with the rotation alone)."""
    layers = {}
    for crs in ("EPSG:3763", "EPSG:32629", "EPSG:32630"):
        r = footprints(tiny_survey.images, tmp_path / f"{crs[5:]}.gpkg", crs=CRS(crs), ground_elevation_m=0)
        layers[crs] = gpd.read_file(r.output, layer="footprints").set_index("image")
    ref = layers["EPSG:3763"]
    assert abs(ref["grid_convergence_deg"].mean() - 0.66) < 0.01  # Lisbon: 0.66° in PT-TM06
    for crs in ("EPSG:32629", "EPSG:32630"):
        other = layers[crs].to_crs("EPSG:3763")
        for name, row in ref.iterrows():
            a, b = row.geometry, other.loc[name].geometry
            assert a.symmetric_difference(b).area / a.area < 1e-4, (crs, name)
    assert layers["EPSG:32630"]["grid_convergence_deg"].mean() > 3.5  # west of its meridian


def test_a_photo_named_in_other_than_utf8_is_skipped_and_named(tiny_survey, tmp_path, capsys):
    """A file name of raw bytes (a camera card from another locale): that photo is skipped with its
    reason, the batch goes on (it killed footprints when the name reached the GeoPackage)."""
    import os

    from geoortho.processing.cli import main

    folder = tmp_path / "photos"
    folder.mkdir()
    for p in sorted(tiny_survey.images.glob("*.JPG")):
        (folder / p.name).symlink_to(p)
    odd = os.path.join(os.fsencode(folder), b"caf\xe9.JPG")
    os.symlink(os.fsencode(sorted(tiny_survey.images.glob("*.JPG"))[0]), odd)
    import geoortho

    r = geoortho.footprints(folder, tmp_path / "fp.gpkg")
    assert r.n_photos == 9 and r.n_skipped == 1
    capsys.readouterr()
    assert main(["footprints", "--images", str(folder), "--output", str(tmp_path / "fp2.gpkg")]) == 0
    assert "not UTF-8" in capsys.readouterr().err
