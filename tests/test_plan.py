"""The plan algorithm: checked by flying the plan in the synthetic survey, and on terrain."""

from __future__ import annotations

import json
import math
import re
from collections import Counter

import cv2
import geopandas as gpd
import numpy as np
import pytest
import shapely
from conftest import RecordingFeedback, real_data
from rasterio.transform import from_origin

import geoortho
from geoortho.errors import InputError
from geoortho.planning.exports import LITCHI_HEADER
from geoortho.planning.plan import (
    default_gcp_count,
    line_overlaps,
    min_module_px,
    resolve_camera,
)

E0, N0, UTM29 = 487000.0, 4290000.0, "EPSG:32629"


def _aoi(path, geom, crs=UTM29):
    gpd.GeoDataFrame(geometry=[geom], crs=crs).to_file(path)
    return path


@pytest.fixture(scope="module")
def flown(small_survey, tmp_path_factory):
    """A plan over the small survey's flight box (truth DTM, its GCP file), flown by synth."""
    d = tmp_path_factory.mktemp("plan_flown")
    survey = json.loads((small_survey.truth / "survey.json").read_text())
    x0, y0, x1, y1 = survey["flight_box"]
    aoi = _aoi(d / "aoi.gpkg", shapely.box(x0 + 5, y0 + 5, x1 - 5, y1 - 5), survey["crs"])
    photo = sorted(small_survey.images.iterdir())[0]
    p = geoortho.plan(
        aoi,
        d / "plan",
        camera=str(photo),
        altitude_m=40.0,
        front_overlap=70.0,  # the preset flies 75/65: fewer photos keep the test quick
        side_overlap=60.0,
        dtm=small_survey.dtm,
        gcps=str(small_survey.gcp_file),
        marker_size_m=survey["marker_size_m"],
    )
    # markers only (no scene rendered): what is checked is metadata, footprints and marker sightings
    s = geoortho.synth(d / "flown", preset="small", seed=1, plan=p.plan, pixels=False)
    return p, s, survey


def test_flying_the_plan_gives_the_planned_overlap_gsd_and_gcp_sightings(flown, tmp_path):
    p, s, survey = flown
    summary = json.loads(p.summary.read_text())
    photos = gpd.read_file(p.plan, layer="photos")
    assert s.n_photos == p.n_photos == len(photos)
    # the overlaps asked are met on the plan's own footprints (spaced at the highest ground)
    planned = summary["overlap_on_footprints_pct"]
    assert planned["front"] >= 70 - 0.5 and planned["side"] >= 60 - 0.5
    fp = geoortho.footprints(s.images, tmp_path / "fp.gpkg", dsm=s.dtm, takeoff_elevation_m=survey["home"]["ground_z"])
    got = gpd.read_file(fp.output, layer="footprints").sort_values("image")
    front, side = line_overlaps(list(got.geometry), photos["line"].tolist())
    # measured: front 76.8 vs 76.8, side 64.4 vs 66.6 (the flown attitude wanders 1.5 degrees)
    assert abs(front - planned["front"]) <= 3.0 and abs(side - planned["side"]) <= 3.0
    assert abs(np.median(got["gsd_cm"]) / summary["gsd_cm"]["median"] - 1) <= 0.03
    # every GCP found in as many photos as planned (the expected count given how far a flown pose
    # wanders), +-1; measured on two flown plans: 9 of 16 exact, the rest +-1
    r = geoortho.gcp_find(s.images, s.gcp_file, tmp_path / "gcp_list.txt")
    rows = r.output.read_text().splitlines()[1:]
    found = Counter(ln.split()[6] for ln in rows if ln.strip())
    for g in summary["gcps"]:
        assert abs(found.get(g["name"], 0) - g["n_photos"]) <= 1, g


def test_synth_flies_a_plan_at_its_camera_pixel_size_and_refuses_another_lens(tiny_survey, tmp_path):
    """A plan for the synthetic lens at another pixel count (as a 12 MP benchmark plans it) is
    rendered at that count; a plan for another lens is refused before anything is rendered."""
    survey = json.loads((tiny_survey.truth / "survey.json").read_text())
    x0, y0, x1, y1 = survey["flight_box"]
    aoi = _aoi(tmp_path / "aoi.gpkg", shapely.box(x0 + 4, y0 + 4, x1 - 4, y1 - 4), survey["crs"])
    size = dict(image_width_px=480, image_height_px=360)  # 4:3, where the preset renders 3:2
    p = geoortho.plan(aoi, tmp_path / "plan", camera="FC6310", altitude_m=30.0, **size)
    s = geoortho.synth(tmp_path / "flown", preset="tiny", plan=p.plan)
    info = json.loads((s.truth / "survey.json").read_text())
    assert (info["camera"]["width_px"], info["camera"]["height_px"]) == (480, 360)
    shapes = {cv2.imread(str(f)).shape[:2] for f in s.images.iterdir()}
    assert shapes == {(360, 480)} and s.n_photos == p.n_photos
    other = geoortho.plan(aoi, tmp_path / "plan330", camera="DJI FC330", altitude_m=30.0)
    with pytest.raises(InputError, match="field of view"):
        geoortho.synth(tmp_path / "flown330", preset="tiny", plan=other.plan)


def test_plan_layers_and_exports(flown):
    p, _, _ = flown
    layers = set(gpd.list_layers(p.plan)["name"])
    assert {"photos", "lines", "footprints", "gcps", "aoi"} <= layers
    photos = gpd.read_file(p.plan, layer="photos")
    assert {"altitude_m", "heading_deg", "pitch_deg", "line", "gsd_cm"} <= set(photos.columns)
    assert photos["line"].nunique() == p.n_lines
    # KML 2.2 as GDAL reads it: the photo placemarks with their lon/lat
    kml = gpd.read_file(p.kml, layer="Photos")
    assert len(kml) == p.n_photos
    ll = photos.to_crs("EPSG:4326")
    assert np.allclose(kml.geometry.x, ll.geometry.x, atol=1e-7) and np.allclose(
        kml.geometry.y, ll.geometry.y, atol=1e-7
    )
    # Litchi: its 46 columns, one take-photo waypoint per photo (<= 99), altitude above take-off
    lines = p.litchi.read_text().splitlines()
    assert lines[0].split(",") == LITCHI_HEADER and len(LITCHI_HEADER) == 46
    rows = [ln.split(",") for ln in lines[1:]]
    assert len(rows) == p.n_photos and all(len(r) == 46 and r[8] == "1" for r in rows)
    assert np.allclose([float(r[2]) for r in rows], photos["altitude_m"], atol=0.06)
    # marker sheets: one PDF per GCP at the real size (page = square + white border + 2 cm + label)
    summary = json.loads(p.summary.read_text())
    side = summary["marker"]["size_m"]
    for g in summary["gcps"]:
        pdf = (p.output / "markers" / f"{g['name']}.pdf").read_bytes()
        w_pt = float(re.search(rb"/MediaBox \[\s*0 0 ([\d.]+) ([\d.]+)", pdf).group(1))
        module = side / summary["marker"]["cells"]
        assert abs(w_pt / 72 * 0.0254 - (side + 2 * module + 0.04)) < 1e-3


def test_terrain_following_keeps_the_gsd_and_constant_altitude_reports_the_spread(tmp_path):
    cell = 5.0
    x = E0 - 300 + (np.arange(300) + 0.5) * cell
    y = N0 + 900 - (np.arange(300) + 0.5) * cell
    X, Y = np.meshgrid(x, y)
    hill_m = 60.0
    z = 200 + hill_m * np.exp(-(((X - E0 - 300) / 180) ** 2 + ((Y - N0 - 300) / 180) ** 2))
    from geoortho.core.outputs import write_cog

    dtm = write_cog(
        tmp_path / "hill.tif",
        z.astype(np.float32),
        transform=from_origin(E0 - 300, N0 + 900, cell, cell),
        crs=UTM29,
        nodata=-9999.0,
    )
    aoi = _aoi(tmp_path / "aoi.geojson", shapely.box(E0, N0, E0 + 600, N0 + 600))
    follow = geoortho.plan(
        aoi,
        tmp_path / "follow",
        camera="DJI Phantom 4 Pro",
        gsd_cm=2.0,
        dtm=dtm,
        terrain="follow",
        takeoff_ground_m=200.0,
    )
    fp = gpd.read_file(follow.plan, layer="footprints")
    assert np.abs(fp["gsd_cm"] / 2.0 - 1).max() <= 0.05
    ph = gpd.read_file(follow.plan, layer="photos")
    assert ph["altitude_m"].max() - ph["altitude_m"].min() > 0.8 * hill_m  # it climbs over the hill
    const = geoortho.plan(
        aoi, tmp_path / "const", camera="DJI Phantom 4 Pro", gsd_cm=3.0, dtm=dtm, takeoff_ground_m=200.0
    )
    s = json.loads(const.summary.read_text())
    agl = s["altitude_m"]  # over the take-off ground: the hilltop is 60 m nearer
    assert s["gsd_cm"]["max"] == pytest.approx(3.0, rel=0.03)
    assert s["gsd_cm"]["min"] == pytest.approx(3.0 * (agl - hill_m) / agl, rel=0.06)
    # too low for the hill: refused with what to do
    with pytest.raises(InputError, match="terrain follow"):
        geoortho.plan(aoi, tmp_path / "low", camera="DJI Phantom 4 Pro", gsd_cm=2.0, dtm=dtm, takeoff_ground_m=200.0)
    # spaced at the hilltop: the overlaps asked hold over it too
    assert s["coverage"]["aoi_share_at_required_pct"] > 95
    assert s["spacing"]["planned_at_agl_m"] == pytest.approx(agl - hill_m, abs=1.0)


def test_gcp_proposal_spread_and_seen(tmp_path):
    aoi = _aoi(
        tmp_path / "aoi.gpkg",
        shapely.Polygon([(E0, N0), (E0 + 700, N0), (E0 + 700, N0 + 400), (E0 + 300, N0 + 600), (E0, N0 + 400)]),
    )
    r = geoortho.plan(aoi, tmp_path / "p", camera="FC6310", gsd_cm=2.5)
    g = gpd.read_file(r.plan, layer="gcps")
    area_ha = shapely.area(gpd.read_file(aoi).geometry.iloc[0]) / 1e4
    assert len(g) == default_gcp_count(area_ha) == 5 + math.ceil((area_ha - 5) / 10)
    poly = gpd.read_file(aoi).geometry.iloc[0]
    assert poly.contains(shapely.MultiPoint(list(zip(g.geometry.x, g.geometry.y))))
    d = np.hypot(*(np.c_[g.geometry.x, g.geometry.y][:, None] - np.c_[g.geometry.x, g.geometry.y][None]).T)
    np.fill_diagonal(d, np.inf)
    assert d.min() > 0.25 * math.sqrt(poly.area / len(g))  # evenly spread, no two bunched
    roles = Counter(g["role"])
    assert roles["perimeter"] >= 4 and roles["interior"] >= 1
    assert (g["n_photos"] >= 3).all() and (g["marker_size_m"] > 0).all()
    # the print size: the dictionary's measured module size, 1.5x, at the worst GSD seen at a GCP
    s = json.loads(r.summary.read_text())
    need = s["marker"]["cells"] * s["marker"]["min_module_px"] * 1.5 * max(x["gsd_max_cm"] for x in s["gcps"]) / 100
    assert need <= s["marker"]["size_m"] < need + 0.05


def test_min_module_px_is_what_the_detector_decodes():
    from geoortho.gcp.detect import SearchWindow, detect_in_image
    from geoortho.gcp.markers import marker_cells
    from geoortho.planning.control import _render_marker

    m = min_module_px("DICT_4X4_50")
    assert 1.25 <= m <= 4.0  # measured: 2.25 px
    rng = np.random.default_rng(123)

    def decoded(module, angle, mid):
        cells = marker_cells("DICT_4X4_50", mid)
        img = _render_marker(cells, module, angle, rng)
        c = (img.shape[1] - 1) / 2
        win = SearchWindow("m", mid, c, c, 40.0, cells.shape[0] * module)
        return any(d.marker_id == mid for d in detect_in_image(img, [win], "DICT_4X4_50"))

    # fresh rotations and ids: at 1.5x the measured size (what plans print) every one decodes;
    # at half of it almost none does
    assert all(decoded(1.5 * m, a, i) for a, i in zip((5, 17, 29, 41, 8), (1, 9, 17, 25, 33)))
    assert sum(decoded(0.5 * m, a, i) for a, i in zip((5, 17, 29, 41, 8), (1, 9, 17, 25, 33))) <= 1


def test_geographic_aoi_across_a_utm_zone_edge(tmp_path):
    # 6 W is the edge of zones 29 and 30: the plan is made in the zone of the AOI's centre and the
    # headings the drone flies are from true north (convergence about 2 degrees there)
    aoi = _aoi(tmp_path / "aoi.geojson", shapely.box(-6.004, 40.0, -5.992, 40.006), "EPSG:4326")
    r = geoortho.plan(aoi, tmp_path / "p", camera="DJI Mavic 3 Enterprise", gsd_cm=3.0, direction_deg=0.0)
    assert r.crs == "EPSG:32630"
    ph = gpd.read_file(r.plan, layer="photos")
    from pyproj import Proj

    conv = Proj("EPSG:32630").get_factors(-6.0, 40.003).meridian_convergence
    d = ((ph["heading_deg"] - ph["grid_heading_deg"] + 180) % 360 - 180).abs()
    assert np.allclose(d, abs(conv), atol=0.05) and abs(conv) > 1.5
    area = gpd.read_file(r.plan, layer="aoi").to_crs("EPSG:32629").area.iloc[0]
    assert area == pytest.approx(gpd.read_file(aoi).to_crs("EPSG:32629").area.iloc[0], rel=1e-3)


@pytest.mark.parametrize(
    "args, message",
    [
        (["--front-overlap", "100"], "above the maximum 99"),
        (["--gsd-cm", "9"], "the best possible is"),
        (["--camera", "Phantom 4 Pr0"], "closest: DJI Phantom 4 Pro"),
        (["--terrain", "follow"], "needs a --dtm"),
    ],
)
def test_bad_input_exit_2(tmp_path, capsys, args, message):
    from geoortho.processing.cli import main

    aoi = _aoi(tmp_path / "aoi.gpkg", shapely.box(E0, N0, E0 + 200, N0 + 200))
    base = {"--aoi": str(aoi), "--output": str(tmp_path / "p"), "--camera": "FC6310", "--gsd-cm": "2"}
    for k, v in zip(args[::2], args[1::2]):
        base[k] = v
    code = main(["plan", *[x for kv in base.items() for x in kv], "--quiet"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and message in err[0], err


def test_aoi_not_a_polygon_refused_self_intersecting_repaired(tmp_path, capsys):
    from geoortho.processing.cli import main

    line = _aoi(tmp_path / "line.gpkg", shapely.LineString([(E0, N0), (E0 + 300, N0 + 200)]))
    code = main(
        ["plan", "--aoi", str(line), "--output", str(tmp_path / "a"), "--camera", "FC6310", "--gsd-cm", "2", "--quiet"]
    )
    err = capsys.readouterr().err
    assert code == 2 and "no polygon" in err and "line.gpkg" in err
    bowtie = shapely.Polygon([(E0, N0), (E0 + 300, N0 + 300), (E0 + 300, N0), (E0, N0 + 300)])
    assert not bowtie.is_valid
    r = geoortho.plan(_aoi(tmp_path / "bow.gpkg", bowtie), tmp_path / "b", camera="FC6310", gsd_cm=2.0)
    assert any("repaired" in w for w in r.warnings)
    fixed = gpd.read_file(r.plan, layer="aoi").geometry.iloc[0]
    assert fixed.is_valid and fixed.area == pytest.approx(2 * 0.25 * 300 * 300, rel=1e-6)


def test_camera_from_table_photo_or_values(small_survey):
    assert resolve_camera("fc6310").name == "DJI Phantom 4 Pro"
    assert resolve_camera("DJI FC6310").name == resolve_camera("Hasselblad DJI FC6310").name == "DJI Phantom 4 Pro"
    photo = resolve_camera(str(sorted(small_survey.images.iterdir())[0]))
    assert (photo.width_px, photo.height_px) == (1600, 1067) and photo.focal_mm == pytest.approx(8.8)
    given = resolve_camera("", 13.2, 8.8, 4000, 3000)
    assert given.focal_px == pytest.approx(8.8 / 13.2 * 4000)


def test_check_a_plan_and_the_flown_photos(flown, tmp_path):
    p, s, survey = flown
    planned = {g["name"]: g for g in json.loads(p.summary.read_text())["gcps"]}
    # an extra GCP far outside the block: seen by no photo, listed
    far = tmp_path / "gcps.txt"
    far.write_text(s.gcp_file.read_text().rstrip("\n") + "\nGCP49 483300.0 4288600.0 110.0\n")
    c = geoortho.check_plan(far, tmp_path / "c_plan", plan=p.plan, marker_size_m=1.0)
    rep = json.loads(c.report.read_text())
    assert c.short_gcps == "GCP49" and c.n_short_gcps == 1
    for g in rep["gcps"]:
        if g["name"] in planned:
            assert g["n_expected"] == planned[g["name"]]["n_photos"]  # the same count as plan gave
    assert rep["under_overlap_pct"] < 1.0  # the plan covers its AOI at the overlap it asked
    # the plan's folder, as the help says, through the CLI (its one .gpkg is the plan)
    from geoortho.processing.cli import main

    argv = ["plan-check", "--plan", str(p.plan.parent), "--gcp-file", str(far), "--output", str(tmp_path / "c_dir")]
    assert main([*argv, "--marker-size-m", "1", "--quiet"]) == 0
    assert json.loads((tmp_path / "c_dir" / "check.json").read_text())["gcps"] == rep["gcps"]
    # the flown photos, from their metadata and the take-off height (GPS off by a bias of ~1 m: a
    # GCP near the edge of a line is in or out of all its photos together): what gcp-find found lies between the sure
    # and the most sightings, +-1
    c2 = geoortho.check_plan(
        far, tmp_path / "c_photos", images=s.images, dsm=s.dtm, takeoff_elevation_m=survey["home"]["ground_z"]
    )
    rows = {g["name"]: g for g in json.loads(c2.report.read_text())["gcps"]}
    got = {n: g["n_photos"] for n, g in rows.items()}
    r = geoortho.gcp_find(s.images, s.gcp_file, tmp_path / "gcp_list.txt")
    found = Counter(ln.split()[6] for ln in r.output.read_text().splitlines()[1:] if ln.strip())
    assert got["GCP49"] == 0
    for n, k in found.items():
        assert rows[n]["n_sure"] - 1 <= k <= rows[n]["n_max"] + 1, (n, k, rows[n])
    under = gpd.read_file(c2.check, layer="under_overlap")
    assert len(under) > 0 and (under["photos_needed"] == 5).all()  # the block's edge


def test_real_toledo_photos_checked_and_used_as_the_camera(tmp_path):
    """Toledo's gcp_list has placeholder heights (all 400 m, above the drone): taken from the ground,
    said; every GCP is then in at least as many photos as someone marked it in, by hand."""
    folder = real_data("toledo_dji")
    gcp_list = folder / "gcp" / "gcp_list.txt"
    fb = RecordingFeedback()
    c = geoortho.check_plan(gcp_list, tmp_path / "c", images=folder / "images", feedback=fb)
    assert any("placeholders" in w for w in fb.warnings)
    marked = Counter(
        ln.split()[-1]
        for ln in gcp_list.read_text().splitlines()[1:]
        if ln.strip() and not ln.startswith("#") and len(ln.split()) >= 7
    )
    got = {g["name"]: g["n_photos"] for g in json.loads(c.report.read_text())["gcps"]}
    assert marked and all(got[n] >= k for n, k in marked.items()) and c.n_short_gcps == 0
    photo = sorted((folder / "images").iterdir())[0]
    cam = resolve_camera(str(photo))
    import cv2

    h, w = cv2.imread(str(photo)).shape[:2]  # the size as decoded (these files were downscaled)
    assert "FC3" in cam.name and (cam.width_px, cam.height_px) == (w, h) and 6.0 < cam.sensor_width_mm < 6.4


def test_double_grid_oblique_and_speed(tmp_path):
    aoi = _aoi(tmp_path / "aoi.gpkg", shapely.box(E0, N0, E0 + 300, N0 + 200))
    single = geoortho.plan(aoi, tmp_path / "s", camera="FC6310", gsd_cm=2.0, min_interval_s=2.0, speed_m_s=12.0)
    double = geoortho.plan(aoi, tmp_path / "d", camera="FC6310", gsd_cm=2.0, grid="double")
    lines = gpd.read_file(double.plan, layer="lines")
    assert len(set((lines["grid_heading_deg"] % 180).round())) == 2 and double.n_photos > 1.6 * single.n_photos
    s = json.loads(single.summary.read_text())
    # one photo every spacing at the speed flown: never faster than the camera's interval
    assert s["photo_interval_s"] >= 2.0 - 1e-9 and s["speed_m_s"] <= 12.0
    assert s["speed_m_s"] == pytest.approx(min(12.0, s["spacing"]["along_m"] / 2.0))
    oblique = geoortho.plan(aoi, tmp_path / "o", camera="FC6310", gsd_cm=2.0, pitch_deg=-60.0)
    ph = gpd.read_file(oblique.plan, layer="photos")
    fp = gpd.read_file(oblique.plan, layer="footprints")
    # the footprints lie ahead of the drone along its heading, by about the height x tan(30 deg)
    a = np.radians(ph["grid_heading_deg"])
    ahead = (fp.centroid.x - ph.geometry.x) * np.sin(a) + (fp.centroid.y - ph.geometry.y) * np.cos(a)
    agl = json.loads(oblique.summary.read_text())["altitude_m"]
    assert np.median(ahead) > 0.4 * agl * math.tan(math.radians(30))
    assert json.loads(oblique.summary.read_text())["gsd_cm"]["median"] == pytest.approx(2.0, rel=0.03)


def test_a_plan_canceled_while_it_is_written_leaves_no_half_plan(tmp_path, monkeypatch):
    """Issue 76: a cancel while plan wrote its files left plan.gpkg and overlap.tif without the KML,
    the Litchi mission or the summary; now nothing of it is left to be flown."""
    import geoortho.planning.exports as planning

    aoi = _aoi(tmp_path / "aoi.gpkg", shapely.box(E0, N0, E0 + 120, N0 + 80))

    def canceled(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(planning, "_write_kml", canceled)
    with pytest.raises(KeyboardInterrupt):
        geoortho.plan(aoi, tmp_path / "plan", camera="DJI FC6310", gsd_cm=2.0)
    left = sorted(p.name for p in (tmp_path / "plan").iterdir()) if (tmp_path / "plan").exists() else []
    assert not [n for n in left if n in planning.PLAN_PRODUCTS], left
    monkeypatch.undo()
    r = geoortho.plan(aoi, tmp_path / "plan", camera="DJI FC6310", gsd_cm=2.0)
    assert all((tmp_path / "plan" / n).exists() for n in ("plan.gpkg", "plan.kml", "litchi.csv", "summary.json"))
    assert r.n_photos > 0
