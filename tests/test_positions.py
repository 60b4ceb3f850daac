"""Camera positions from a file (PPK trajectories, DJI event files, CSV), matched to the photos,
and the camera-to-GPS time lag a block shows."""

from __future__ import annotations

import json
import math
import subprocess
import sys

import geopandas as gpd
import numpy as np
import pytest
from conftest import SFM_FAST

import geoortho
from geoortho.errors import InputError
from geoortho.photos.metadata import read_photos
from geoortho.photos.positions import read_positions


@pytest.fixture(scope="module")
def ppk(tmp_path_factory):
    d = tmp_path_factory.mktemp("ppk")
    s = geoortho.synth(d / "survey", preset="tiny", seed=2, pathology="ppk")
    return s, read_photos(s.images).photos


def _truth(s):
    return {p["image"]: p for p in json.loads((s.truth / "poses.json").read_text())}


def test_a_trajectory_is_matched_by_time_with_the_offset_found_from_the_photos_gps(ppk):
    s, photos = ppk
    pf = read_positions(s.truth / "trajectory.pos", photos)
    assert pf.source == "RTKLIB .pos" and len(pf.by_image) == len(photos) and pf.offset_found
    # GPS time runs 18 s ahead of the camera's UTC clock, and the stamps 0.3 s behind the exposures:
    # the photos' own GPS (a consumer's, 0.5 m off) lays them on the path to a few hundredths
    assert pf.time_offset_s == pytest.approx(18.3, abs=0.05)
    assert all(q.fix == "fixed" and q.sigma_h_m == pytest.approx(0.01) for q in pf.by_image.values())


def test_a_trajectory_of_another_day_is_refused_in_one_line(ppk, tmp_path):
    s, photos = ppk
    text = (s.truth / "trajectory.pos").read_text().replace("2026/05/14", "2026/05/15")
    other = tmp_path / "other_day.pos"
    other.write_text(text)
    with pytest.raises(InputError, match=r"\+1\.00 days .* another day"):
        read_positions(other, photos)
    # the CLI: exit 2, one line naming the file
    done = subprocess.run(
        [sys.executable, "-m", "geoortho", "sfm", "--images", str(s.images), "--output", str(tmp_path / "sfm"),
         "--positions", str(other)],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert done.returncode == 2
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and "other_day.pos" in lines[0] and "another day" in lines[0]


def test_a_lag_the_block_shows_is_found_and_the_positions_read_again(ppk, tmp_path):
    """The offset given as GPS time against UTC (18 s): the stamps' 0.3 s lag is left, 1.5 m along
    each flight line, for the block to find."""
    s, _ = ppk
    r = geoortho.sfm(
        s.images, tmp_path / "sfm", positions=s.truth / "trajectory.pos", positions_time_offset_s=18.0, **SFM_FAST
    )
    report = json.loads(r.report.read_text())
    lag = report["positions"]["time_lag"]
    # measured: +0.296 s (small survey: +0.299 s)
    assert lag["applied"] and lag["lag_s"] == pytest.approx(0.3, abs=0.05)
    truth = _truth(s)
    cams = gpd.read_file(r.cameras)
    d = np.array([[c.x - truth[c.image]["x"], c.y - truth[c.image]["y"], c.z - truth[c.image]["z"]]
                  for c in cams.itertuples() if c.registered])  # fmt: skip
    # measured: 1.8 cm H and 1.2 cm V (0.4 and 1.0 cm on the small survey); before the lag, 1.5 m
    assert np.sqrt((d[:, :2] ** 2).mean()) <= 0.03 and np.sqrt((d[:, 2] ** 2).mean()) <= 0.05
    assert any("time lag +0.3" in n or "time lag +0.2" in n for n in report["notes"])


def test_csv_positions_in_latitude_longitude_and_in_a_projected_crs(ppk, tmp_path):
    s, photos = ppk
    truth = _truth(s)
    names = sorted(truth)
    from pyproj import Transformer

    to_ll = Transformer.from_crs(json.loads((s.truth / "survey.json").read_text())["crs"], "EPSG:4326", always_xy=True)
    rows = ["image,lat,lon,height,sigma_h,sigma_v"]
    for n in names[:-1]:
        lon, lat = to_ll.transform(truth[n]["x"], truth[n]["y"])
        rows.append(f"{n},{lat:.9f},{lon:.9f},{truth[n]['z']:.3f},0.02,0.04")
    rows.append("IMG_9999.JPG,38.7,-9.1,100,0.02,0.04")  # no such photo
    (tmp_path / "ll.csv").write_text("\n".join(rows) + "\n")
    pf = read_positions(tmp_path / "ll.csv", photos)
    assert pf.source == "CSV" and len(pf.by_image) == len(names) - 1
    assert pf.photos_without == (names[-1],) and pf.lines_without == ("IMG_9999.JPG (line 10)",)
    q = pf.by_image[names[0]]
    assert (q.sigma_h_m, q.sigma_v_m, q.fix) == (0.02, 0.04, "stated")
    assert q.height_m == pytest.approx(truth[names[0]]["z"], abs=1e-3)
    # the same in the survey's UTM zone, semicolons, no sigma: weighed as consumer GPS
    crs = json.loads((s.truth / "survey.json").read_text())["crs"]
    rows = [f"# {crs}", "name;easting;northing;z"] + [
        f"{n};{truth[n]['x']:.4f};{truth[n]['y']:.4f};{truth[n]['z']:.3f}" for n in names
    ]
    (tmp_path / "utm.csv").write_text("\n".join(rows) + "\n")
    pf2 = read_positions(tmp_path / "utm.csv", photos)
    assert pf2.by_image[names[0]].latitude_deg == pytest.approx(q.latitude_deg, abs=1e-8)
    assert pf2.by_image[names[0]].fix == "consumer" and math.isnan(pf2.by_image[names[0]].sigma_h_m)


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("image,x,y,z\nDJI_0001.JPG,483600,4288780,150\n", r"line 2: x/y without a CRS"),
        ("image,lat,lon,z\nDJI_0001.JPG,38.7,abc,150\n", r"line 2: 'abc' is not a number in column lon"),
        ("image,lat,lon\nDJI_0001.JPG,38.7,-9.1\n", r"line 1: the header names no z column"),
        ("# EPSG:4326\nimage,x,y,z\nDJI_0001.JPG,-9.1,138.7,150\n", r"line 3: .* no position"),
    ],
)
def test_a_bad_csv_names_its_line(ppk, tmp_path, text, message):
    _, photos = ppk
    path = tmp_path / "bad.csv"
    path.write_text(text)
    with pytest.raises(InputError, match=message):
        read_positions(path, photos)


def test_dji_event_file_in_shooting_order(ppk, tmp_path):
    _, photos = ppk
    mrk = tmp_path / "Timestamp.MRK"
    mrk.write_text(
        "1\t295413.651488\t[2058]\t    22,N\t    -4,E\t   188,V\t38.74729100,Lat\t-9.18920600,Lon\t150.123,Ellh"
        "\t0.012725, 0.011567, 0.028096\t50,Q\n"
        "2\t295415.651488\t[2058]\t    21,N\t    -3,E\t   187,V\t38.74738100,Lat\t-9.18920700,Lon\t150.211,Ellh"
        "\t0.310000, 0.290000, 0.450000\t34,Q\n"
    )
    pf = read_positions(mrk, photos)
    first, second = sorted(photos, key=lambda p: p.taken_at)[:2]
    assert pf.source == "DJI MRK" and len(pf.by_image) == 2
    a, b = pf.by_image[first.image], pf.by_image[second.image]
    assert (a.fix, a.sigma_h_m, a.sigma_v_m, a.height_m) == ("fixed", 0.012725, 0.028096, 150.123)
    assert (b.fix, b.sigma_h_m) == ("float", 0.31)
    assert len(pf.photos_without) == len(photos) - 2


def test_an_rtklib_event_file_matches_each_photo_to_its_event(ppk, tmp_path):
    """RTKPOST's solution at the camera events only: one epoch a photo, 2 s apart."""
    import datetime as dt

    s, photos = ppk
    pf = read_positions(s.truth / "trajectory.pos", photos)
    lines = ["%  GPST                  latitude(deg) longitude(deg)  height(m)   Q  ns   sdn(m)   sde(m)   sdu(m)"]
    for p in sorted(photos, key=lambda p: p.taken_at)[:-1]:  # the last photo's event is missing
        q = pf.by_image[p.image]
        t = dt.datetime.fromtimestamp(pf.photo_times_s[p.image], dt.timezone.utc)
        lines.append(
            f"{t:%Y/%m/%d %H:%M:%S}.{t.microsecond // 1000:03d} {q.latitude_deg:.9f} {q.longitude_deg:.9f} "
            f"{q.height_m:.4f} 2 12 0.2000 0.2500 0.4000"
        )
    (tmp_path / "events.pos").write_text("\n".join(lines) + "\n")
    events = read_positions(tmp_path / "events.pos", photos)
    assert events.trajectory is not None and events.trajectory.is_events
    assert len(events.by_image) == len(photos) - 1 and len(events.photos_without) == 1
    q = next(iter(events.by_image.values()))
    assert (q.fix, q.sigma_h_m, q.sigma_v_m) == ("float", 0.25, 0.4)


def _stale_copy(survey, dst, lag_s: float, interval_s: float = 2.0):
    """The survey's photos with each GPS fix moved to where the camera was ``lag_s`` before the
    exposure (back along the straight path from the previous photo): synth's gps-lag pathology
    written into copies of an existing survey's photos (no rendering again)."""
    import shutil

    import piexif

    truth = _truth(survey)
    names = sorted(truth)
    dst.mkdir()
    for i, name in enumerate(names):
        j = i - 1 if i > 0 else 1
        share = (lag_s / interval_s) * (1.0 if i > 0 else -1.0)
        east = (truth[names[j]]["x"] - truth[name]["x"]) * share
        north = (truth[names[j]]["y"] - truth[name]["y"]) * share
        shutil.copy(survey.images / name, dst / name)
        exif = piexif.load(str(dst / name))
        gps = exif["GPS"]

        def deg(value):
            (d, dd), (m, md), (sec, sd) = value
            return d / dd + m / md / 60 + sec / sd / 3600

        def dms(v):
            v = abs(v)
            d, m = int(v), int((abs(v) - int(v)) * 60)
            return (d, 1), (m, 1), (int(round((v - d - m / 60) * 3600 * 1_000_000)), 1_000_000)

        sign_lat = -1 if gps[piexif.GPSIFD.GPSLatitudeRef] in (b"S", "S") else 1
        sign_lon = -1 if gps[piexif.GPSIFD.GPSLongitudeRef] in (b"W", "W") else 1
        lat = sign_lat * deg(gps[piexif.GPSIFD.GPSLatitude]) + north / 111_320.0
        lon = sign_lon * deg(gps[piexif.GPSIFD.GPSLongitude]) + east / (111_320.0 * math.cos(math.radians(lat)))
        gps[piexif.GPSIFD.GPSLatitude], gps[piexif.GPSIFD.GPSLongitude] = dms(lat), dms(lon)
        piexif.insert(piexif.dump(exif), str(dst / name))
    return dst


def test_a_consumer_gps_that_lags_the_exposures_is_found_and_undone(small_survey, tmp_path):
    """Each photo's own GPS fix a second stale (5 m back along its line, alternating with the
    lines' direction): the block adjusted on its photos alone lies ahead of the fixes along the
    lines; the lag is said and the positions moved by it."""
    images = _stale_copy(small_survey, tmp_path / "images", 1.0)
    r = geoortho.sfm(images, tmp_path / "sfm", max_image_size=640, max_features=2048)
    report = json.loads(r.report.read_text())
    lag = report["gps_time_lag"]
    # measured: +0.88 s (±0.02) against the 1.0 s built in (+0.89 s at 1024 px)
    assert lag["applied"] and lag["lag_s"] == pytest.approx(1.0, abs=0.2)
    assert any("GPS fixes lag their exposures" in n for n in report["notes"])
    truth = _truth(small_survey)
    cams = gpd.read_file(r.cameras)
    d = np.array([[c.x - truth[c.image]["x"], c.y - truth[c.image]["y"]] for c in cams.itertuples() if c.registered])
    # measured: 0.24 m per axis (1.57 m with the fixes as they were)
    assert np.sqrt((d**2).mean()) < 0.6


# -- positions files that disagree with the photos, state another datum, or are malformed (issue 76) --


def _pos_lines(pf, photos, fmt="deg", header_height="WGS84/ellipsoidal", sigma="0.0100   0.0100   0.0200"):
    """An RTKLIB event file (one epoch a photo) of ``pf``'s positions, in degrees or in RTKPOST's
    degrees-minutes-seconds."""
    import datetime as dt

    def dms(v):
        a = abs(v)
        d, m = int(a), int((a - int(a)) * 60)
        s = (a - d - m / 60) * 3600
        return f"{'-' if v < 0 else ''}{d} {m:02d} {s:08.5f}"

    cols = "latitude(d'\")   longitude(d'\")" if fmt == "dms" else "latitude(deg) longitude(deg)"
    lines = [
        f"% (lat/lon/height={header_height},Q=1:fix,2:float)",
        f"%  GPST  {cols}  height(m)   Q  ns   sdn(m)   sde(m)   sdu(m)",
    ]
    for p in sorted(photos, key=lambda p: p.taken_at):
        q = pf.by_image[p.image]
        t = dt.datetime.fromtimestamp(pf.photo_times_s[p.image], dt.timezone.utc)
        ll = (
            f"{dms(q.latitude_deg)} {dms(q.longitude_deg)}"
            if fmt == "dms"
            else f"{q.latitude_deg:.9f} {q.longitude_deg:.9f}"
        )
        lines.append(f"{t:%Y/%m/%d %H:%M:%S}.{t.microsecond // 1000:03d} {ll} {q.height_m:.4f} 1 12 {sigma}")
    return "\n".join(lines) + "\n"


def test_rtkpost_degrees_minutes_seconds_and_geoid_heights_are_read_as_they_are_meant(ppk, tmp_path):
    """RTKPOST's ddd mm ss output is the same place as its degrees; its 'geodetic' heights are above
    the geoid (EGM96 here), turned ellipsoidal; a deviation of zero is "not stated", as in a CSV."""
    from geoortho.core.crs import geoid_undulation_m

    s, photos = ppk
    pf = read_positions(s.truth / "trajectory.pos", photos)
    (tmp_path / "dms.pos").write_text(_pos_lines(pf, photos, "dms"))
    dms = read_positions(tmp_path / "dms.pos", photos)
    for name, q in pf.by_image.items():
        assert dms.by_image[name].latitude_deg == pytest.approx(q.latitude_deg, abs=1e-8)
        assert dms.by_image[name].longitude_deg == pytest.approx(q.longitude_deg, abs=1e-8)
    assert dms.gps_distance_m < 5.0
    (tmp_path / "geoid.pos").write_text(_pos_lines(pf, photos, header_height="WGS84/geodetic", sigma="0 0 -1"))
    geo = read_positions(tmp_path / "geoid.pos", photos)
    name, q = next(iter(pf.by_image.items()))
    n = float(geoid_undulation_m(q.longitude_deg, q.latitude_deg))
    assert abs(n) > 40  # Lisbon: the datum matters by tens of metres
    assert geo.by_image[name].height_m == pytest.approx(q.height_m + n, abs=0.01)
    assert "geodetic" in geo.heights
    assert (geo.by_image[name].sigma_h_m, geo.by_image[name].sigma_v_m) == (0.02, 0.03)  # the fixed class's


def _csv_of(pf, names, crs="", header="image,lat,lon,height", move_deg=0.0):
    rows = ([f"# {crs}"] if crs else []) + [header]
    for n in names:
        q = pf.by_image[n]
        rows.append(f"{n},{q.latitude_deg + move_deg:.9f},{q.longitude_deg:.9f},{q.height_m:.3f}")
    return "\n".join(rows) + "\n"


@pytest.mark.parametrize(
    ("case", "message"),
    [
        ("another-site", r"lie 55\.\d km from the photos' own GPS"),
        ("wrong-crs", r"km from the photos' own GPS .* a wrong CRS"),
        ("twice", r"line 3: .* has a position on line 2 too"),
        ("absurd-height", r"height 1e\+06 m is no camera's height"),
        ("week-overflow", r"line 3: not an RTKLIB solution line"),
    ],
)
def test_a_positions_file_that_cannot_be_right_is_refused_naming_why(ppk, tmp_path, case, message):
    s, photos = ppk
    pf = read_positions(s.truth / "trajectory.pos", photos)
    names = sorted(pf.by_image)
    truth = json.loads((s.truth / "survey.json").read_text())
    path = tmp_path / ("bad.pos" if case == "week-overflow" else "bad.csv")
    if case == "another-site":  # half a degree of latitude away
        path.write_text(_csv_of(pf, names, move_deg=0.5))
    elif case == "wrong-crs":  # the easting/northing of the photos' zone, labelled with the next zone
        t = _truth(s)
        zone = int(truth["crs"].split(":")[1])
        rows = [f"# EPSG:{zone + 1}", "name,easting,northing,z"] + [
            f"{n},{t[n]['x']:.3f},{t[n]['y']:.3f},{t[n]['z']:.3f}" for n in names
        ]
        path.write_text("\n".join(rows) + "\n")
    elif case == "twice":
        path.write_text(_csv_of(pf, [names[0], names[0], *names[1:]]))
    elif case == "absurd-height":
        path.write_text(_csv_of(pf, names).replace(f"{pf.by_image[names[2]].height_m:.3f}", "1000000", 1))
    else:
        path.write_text("% header\n% more\n99999999999999 1.0 38.7 -9.1 100 1 10 0.01 0.01 0.02\n")
    with pytest.raises(InputError, match=message):
        read_positions(path, photos)
    if case == "another-site":  # the CLI: exit 2, one line naming the file, the file untouched
        before = path.read_bytes()
        done = subprocess.run(
            [sys.executable, "-m", "geoortho", "sfm", "--images", str(s.images), "--output", str(tmp_path / "sfm"),
             "--positions", str(path)],
            capture_output=True, text=True, timeout=120,
        )  # fmt: skip
        lines = done.stderr.strip().splitlines()
        assert done.returncode == 2 and len(lines) == 1 and "bad.csv" in lines[0] and "55." in lines[0], done.stderr
        assert path.read_bytes() == before and not (tmp_path / "sfm" / "report.json").exists()


def test_csv_heights_said_to_be_orthometric_or_in_a_compound_crs_are_turned_ellipsoidal(ppk, tmp_path):
    from geoortho.core.crs import geoid_undulation_m

    s, photos = ppk
    pf = read_positions(s.truth / "trajectory.pos", photos)
    names = sorted(pf.by_image)
    q = pf.by_image[names[0]]
    n = float(geoid_undulation_m(q.longitude_deg, q.latitude_deg))
    # the heights written are orthometric (ellipsoidal less N), and the file says so in three ways
    ortho = {k: v for k, v in pf.by_image.items()}
    lines = _csv_of(pf, names).splitlines()
    shifted = [lines[0]] + [",".join([*row.split(",")[:3], f"{float(row.split(',')[3]) - n:.3f}"]) for row in lines[1:]]
    for text in (
        "# heights: orthometric (EGM96)\n" + "\n".join(shifted),
        "\n".join([shifted[0].replace("height", "h_msl"), *shifted[1:]]),
        "# EPSG:4326+5773\n" + "\n".join([shifted[0].replace("lat,lon", "lat,lon"), *shifted[1:]]),
    ):
        (tmp_path / "o.csv").write_text(text + "\n")
        got = read_positions(tmp_path / "o.csv", photos)
        assert got.by_image[names[0]].height_m == pytest.approx(ortho[names[0]].height_m, abs=0.02), text[:40]
        assert "ellipsoidal" in got.heights and "as read" not in got.heights
    (tmp_path / "e.csv").write_text(_csv_of(pf, names))
    plain = read_positions(tmp_path / "e.csv", photos)
    assert "as read" in plain.heights  # said: taken as ellipsoidal
    assert any("heights ellipsoidal (WGS 84) as read" in note for note in plain.notes())


def test_an_mrk_one_event_short_names_the_photo_that_has_none(ppk, tmp_path):
    """An event missing in the middle of the flight: the photos after it are not shifted onto
    their neighbours' positions; the photo named is the one whose event is missing."""
    s, photos = ppk
    pf = read_positions(s.truth / "trajectory.pos", photos)
    ordered = sorted(photos, key=lambda p: p.taken_at)
    missing = ordered[len(ordered) // 2].image
    lines = []
    for k, p in enumerate((p for p in ordered if p.image != missing), 1):
        q = pf.by_image[p.image]
        lines.append(
            f"{k}\t{295413.65 + 2 * k:.6f}\t[2058]\t    22,N\t    -4,E\t   188,V\t{q.latitude_deg:.8f},Lat\t"
            f"{q.longitude_deg:.8f},Lon\t{q.height_m:.3f},Ellh\t0.012725, 0.011567, 0.028096\t50,Q"
        )
    (tmp_path / "Timestamp.MRK").write_text("\n".join(lines) + "\n")
    got = read_positions(tmp_path / "Timestamp.MRK", photos)
    assert got.photos_without == (missing,)
    for name, q in got.by_image.items():
        assert q.latitude_deg == pytest.approx(pf.by_image[name].latitude_deg, abs=1e-7)
    assert not got.far_from_gps


def test_a_csv_of_a_million_rows_keeps_the_photos_and_counts_the_rest(ppk, tmp_path):
    s, photos = ppk
    pf = read_positions(s.truth / "trajectory.pos", photos)
    names = sorted(pf.by_image)
    text = _csv_of(pf, names)
    q = pf.by_image[names[0]]
    extra = "".join(f"OTHER_{k}.JPG,{q.latitude_deg:.9f},{q.longitude_deg:.9f},100\n" for k in range(1_000_000))
    (tmp_path / "big.csv").write_text(text + extra)
    got = read_positions(tmp_path / "big.csv", photos)
    assert len(got.by_image) == len(names)
    assert got.n_lines_without == 1_000_000 and len(got.lines_without) == 20
    assert any("1,000,000 position(s)" in note for note in got.notes())
