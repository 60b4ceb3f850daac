"""SfM against the synthetic survey's true poses, and on real DJI photos (toledo)."""

from __future__ import annotations

import json
import shutil

import geopandas as gpd
import laspy
import numpy as np
import pytest
import rasterio
from conftest import RecordingFeedback
from pyproj import CRS

from geoortho.core.camera import rotation_from_ypr
from geoortho.errors import InputError
from geoortho.photos.metadata import read_photos
from geoortho.reconstruction.sparse import ce90, le90, sfm
from geoortho.reconstruction.sparse.inputs import camera_bodies

FAST = {"max_image_size": 1024, "max_features": 4096}


def _truth(survey):
    poses = {p["image"]: p for p in json.loads((survey.truth / "poses.json").read_text())}
    home = json.loads((survey.truth / "survey.json").read_text())["home"]
    return poses, home


def _centre_errors(result, poses):
    cams = gpd.read_file(result.cameras)
    reg = cams[cams.registered]
    return np.array(
        [[r.x - poses[r.image]["x"], r.y - poses[r.image]["y"], r.z - poses[r.image]["z"]] for r in reg.itertuples()]
    )


NOISE = "ZZ_noise.jpg"


@pytest.fixture(scope="module")
def gps_only(small_survey, tmp_path_factory):
    """The small survey plus one photo of noise (no EXIF, overlaps nothing)."""
    from PIL import Image

    _, home = _truth(small_survey)
    images = tmp_path_factory.mktemp("sfm_gps_images")
    for p in small_survey.images.iterdir():
        shutil.copy(p, images / p.name)
    rng = np.random.default_rng(0)
    Image.fromarray(rng.integers(0, 255, (1067, 1600, 3), dtype=np.uint8)).save(images / NOISE)
    fb = RecordingFeedback()
    r = sfm(images, tmp_path_factory.mktemp("sfm_gps"), takeoff_elevation_m=home["ground_z"], feedback=fb, **FAST)
    return r, fb


@pytest.fixture(scope="module")
def with_gcps(sfm_with_gcps):
    return sfm_with_gcps


def test_gps_only_registers_and_places_cameras(gps_only, small_survey):
    r, fb = gps_only
    poses, _ = _truth(small_survey)
    assert r.n_registered >= 0.95 * len(poses)
    e = _centre_errors(r, poses)
    rmse = np.sqrt((e**2).sum(axis=1).mean())
    assert rmse <= 0.5, rmse  # issue: <= 0.5 m with GPS only
    assert r.mean_reprojection_error_px < 0.5
    assert any("registered" in m for m in fb.infos)
    rep = json.loads(r.report.read_text())
    assert rep["registered"] == r.n_registered and rep["photos"] == len(poses) + 1
    assert set(rep["unregistered"]) == {NOISE}
    # a photo of noise: a fraction of its neighbours' features, none that match (said as such)
    assert "few features" in rep["unregistered"][NOISE]
    assert any(NOISE in w for w in fb.warnings)
    assert rep["georeferenced_by"].startswith("GPS")
    assert 3.0 < rep["gsd_cm"] < 4.5  # the preset flies at 3.75 cm at the take-off height
    assert rep["gps"]["n"] == r.n_registered and rep["gps"]["ce90_m"] < 1.0
    assert rep["offset"][0] % 100 == 0 and rep["offset"][1] % 100 == 0
    assert json.loads((r.model / "georeference.json").read_text())["crs"] == rep["crs"]
    # where mapping spent its time: every photo but the initial pair joined in a step of its own,
    # and the whole-model adjustments fit inside the mapping's time
    prof = rep["mapping_profile"]
    assert prof["registration_steps"] >= r.n_registered - 2, prof
    assert prof["points"] > 0 and 0 < prof["tracks_per_photo_median"] <= prof["tracks_per_photo_max"]
    assert 0 <= prof["adjustment_s"] < rep["seconds"]["mapping"], prof


def test_sparse_points_lie_on_the_true_dsm(gps_only, small_survey):
    r, _ = gps_only
    las = laspy.read(r.points)
    assert las.header.parse_crs().to_epsg() == 32629
    xyz = np.c_[las.x, las.y, las.z]
    with rasterio.open(small_survey.dsm) as ds:
        z_true = np.array([v[0] for v in ds.sample(xyz[:, :2])])
    d = xyz[:, 2] - z_true
    # Points on walls and roof edges differ from the cell's top; the bulk sits on the surface.
    assert np.median(np.abs(d)) < 0.1, np.median(np.abs(d))
    assert np.ptp(las.red) > 0  # coloured


def test_cameras_layer(gps_only, small_survey):
    r, _ = gps_only
    poses, _ = _truth(small_survey)
    cams = gpd.read_file(r.cameras)
    assert cams.crs.to_epsg() == 32629 and len(cams) == len(poses) + 1
    assert not cams[cams.image == NOISE].registered.any()
    reg = cams[cams.registered]
    # Compare rotations, not angles: near pitch -90 yaw and roll trade off (gimbal lock).
    for row in reg.itertuples():
        ours = rotation_from_ypr(row.yaw_deg, row.pitch_deg, row.roll_deg)
        true = np.array(poses[row.image]["rotation_world_from_camera"])
        cos = (np.trace(ours.T @ true) - 1) / 2
        assert np.degrees(np.arccos(np.clip(cos, -1, 1))) < 0.2, row.image
    assert (reg.reprojection_px < 1.0).all() and (reg.tie_points > 100).all()
    assert {"gps_dx_m", "gps_dy_m", "gps_dz_m"} <= set(cams.columns)


def test_gcps_pin_the_cameras_and_checkpoints_are_honest(with_gcps, small_survey):
    r, checkpoints = with_gcps
    poses, _ = _truth(small_survey)
    e = _centre_errors(r, poses)
    rmse = np.sqrt((e**2).sum(axis=1).mean())
    assert rmse <= 0.05, rmse  # issue: <= 0.05 m with GCPs
    rep = json.loads(r.report.read_text())
    rows = {g["name"]: g for g in rep["gcps"]}
    assert {n for n, g in rows.items() if g["role"] == "checkpoint"} == set(checkpoints)
    check = rep["checkpoint_accuracy"]
    assert check["n"] == len(checkpoints)
    assert check["rmse_horizontal_m"] <= 2 * rep["gsd_cm"] / 100  # issue: <= 2 x GSD
    assert check["rmse_z_m"] is not None and check["le90_m"] == pytest.approx(1.6449 * check["rmse_z_m"])
    assert rep["gcp_accuracy"]["n"] >= 3
    assert "GCP" in rep["georeferenced_by"] and "bundle adjustment" in rep["georeferenced_by"]
    assert all(g["reprojection_px"] < 0.5 for g in rows.values())
    assert r.checkpoint_rmse_m == pytest.approx(check["rmse_3d_m"])


def test_ce90_le90_formulas():
    dx, dy, dz = np.array([0.1, -0.1]), np.array([0.0, 0.0]), np.array([0.2, -0.2])
    assert ce90(dx, dy) == pytest.approx(2.1460 * np.sqrt(0.01 / 2))
    assert le90(dz) == pytest.approx(1.6449 * 0.2)
    assert np.isnan(ce90(np.array([]), np.array([])))


def test_toledo_two_bodies_utm17_placeholder_heights(toledo_sfm):
    r = toledo_sfm
    rep = json.loads(r.report.read_text())
    assert r.n_registered >= 0.9 * 57, rep["unregistered"]
    assert "32617" in r.crs
    assert len(rep["camera_bodies"]) == 2 and len(rep["cameras"]) == 2
    # EXIF says 1800 x 2400; the pixels are 2400 x 1800
    assert all(c["width"] == 2400 and c["height"] == 1800 for c in rep["cameras"])
    assert any("placeholders" in n for n in rep["notes"])
    rows = [g for g in rep["gcps"] if g["dx_m"] is not None]
    assert len(rows) >= 3
    assert all(g["dz_m"] is None for g in rep["gcps"])
    # The GCP XY were read off an ODM orthophoto of this flight: metres, not tens of metres.
    assert rep["gcp_accuracy"]["rmse_horizontal_m"] < 3.0
    # Both bodies' lenses distort: held at zero they reproject worse (camera 1: 1.06 -> 1.22 px after
    # the test's ten iterations; the synthetic camera, which has none: within 0.1 %), so the
    # distortion is refined, not held
    for cam in rep["intrinsics"]:
        test = cam["distortion"]
        assert not test["held_at_zero"], cam
        assert test["reprojection_px_held_at_zero"] > 1.05 * test["reprojection_px_refined"], cam
    las = laspy.read(r.points)
    assert las.header.parse_crs().to_epsg() == 32617
    assert abs(np.median(las.x) - 274900) < 300 and abs(np.median(las.y) - 4603300) < 300


def test_camera_bodies_split_by_model_and_size(small_survey, tmp_path):
    from PIL import Image

    src = sorted(small_survey.images.iterdir())[:4]
    for p in src[:2]:
        shutil.copy(p, tmp_path / p.name)
    for p in src[2:]:
        with Image.open(p) as im:
            im.resize((800, 533)).save(tmp_path / p.name, exif=im.info.get("exif", b""))
    bodies = camera_bodies(read_photos(tmp_path, require_gps=False, require_camera=False).photos)
    assert sorted(len(b.photos) for b in bodies) == [2, 2]


def test_bad_input(small_survey, tmp_path):
    from PIL import Image

    two = tmp_path / "two"
    two.mkdir()
    for p in sorted(small_survey.images.iterdir())[:2]:
        shutil.copy(p, two / p.name)
    with pytest.raises(InputError, match="at least 3"):
        sfm(two, tmp_path / "o1")
    noise = tmp_path / "noise"
    noise.mkdir()
    rng = np.random.default_rng(0)
    for i in range(4):
        Image.fromarray(rng.integers(0, 255, (400, 600, 3), dtype=np.uint8)).save(noise / f"n{i}.jpg")
    with pytest.raises(InputError, match="arbitrary"):
        sfm(noise, tmp_path / "o2")
    with pytest.raises(InputError, match="do not overlap"):
        sfm(noise, tmp_path / "o3", local_frame=True, **FAST)
    with pytest.raises(InputError, match="checkpoint"):
        sfm(small_survey.images, tmp_path / "o4", checkpoints="NOPE")
    assert not (tmp_path / "o3" / "report.json").exists()
    assert not list((tmp_path / "o3").glob(".sfm-work*"))


def test_cli_bad_checkpoint_exit_2(small_survey, tmp_path, capsys):
    from geoortho.processing.cli import main

    code = main(
        [
            "sfm",
            "--images",
            str(small_survey.images),
            "--output",
            str(tmp_path / "o"),
            "--gcp-list",
            str(small_survey.gcp_file),
            "--checkpoints",
            "X",
        ]
    )
    assert code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "gcp_list.txt" in err[0] or "observations" in err[0]


# --- split-merge -------------------------------------------------------------------------------


def test_partition_is_balanced_compact_and_overlapping():
    from geoortho.reconstruction.splitmerge import partition

    rng = np.random.default_rng(0)
    xy = np.c_[rng.uniform(0, 400, 100), rng.uniform(0, 100, 100)]
    names = [f"p{i}" for i in range(100)]
    groups, home = partition(names, xy, 25, 40.0)
    homes = [[n for n, h in zip(names, home) if h == k] for k in range(len(groups))]
    assert len(groups) == 4 and sorted(len(h) for h in homes) == [25, 25, 25, 25]
    for g, h in zip(groups, homes):
        assert set(h) <= set(g) and len(g) > len(h)  # its own photos, and neighbours'
        mine = xy[[names.index(n) for n in h]]
        assert np.ptp(mine[:, 0]) < 150  # cut along the long (x) axis: compact strips
        for n in set(g) - set(h):  # an overlap photo is within 40 m of one of the group's own
            assert np.hypot(*(mine - xy[names.index(n)]).T).min() <= 40.0


def test_a_failed_submodel_is_reported_and_the_rest_merged(sfm_with_gcps, small_survey, tmp_path, monkeypatch):
    import geoortho.reconstruction.sparse as rc

    whole, checkpoints = sfm_with_gcps
    real = rc.sfm

    def flaky(images, output, **kw):
        if output.name == "submodel_00":
            raise InputError("no model could be built: the photos do not overlap enough")
        return real(images, output, **kw)

    monkeypatch.setattr(rc, "sfm", flaky)
    fb = RecordingFeedback()
    # the failure's bookkeeping is under test, not accuracy: small images keep the one submodel quick
    r = real(small_survey.images, tmp_path / "s", gcp_list=whole.output.parent / "gcp_list.txt", split=20, feedback=fb,
             max_image_size=640, max_features=2048)  # fmt: skip
    rep = json.loads(r.report.read_text())
    assert any("submodel 0" in w and "failed" in w for w in fb.warnings)
    lost = {n: why for n, why in rep["unregistered"].items() if "submodel 0 failed" in why}
    # its own photos that its neighbour did not share are lost; the shared ones come from the neighbour
    assert 1 <= len(lost) <= 20 and r.n_registered == r.n_photos - len(rep["unregistered"])
    assert r.n_registered >= 15 and [s["submodel"] for s in rep["submodels"]] == [1]

    # its ground is never a silent hole: the photos left out get footprints from their own GPS and
    # attitude, against the true ones, and the ground only they saw is measured
    import shapely

    from geoortho.photos.footprint import footprints

    fp = footprints(small_survey.images, tmp_path / "fp.gpkg", sfm=r.output)
    left = gpd.read_file(fp.output, layer="left_out").set_index("image")
    true = gpd.read_file(small_survey.truth / "footprints.gpkg").set_index("image")
    assert set(left.index) == set(rep["unregistered"]) and fp.n_left_out == len(lost)
    assert all("submodel 0 failed" in why for why in left.why)
    overlap = [
        shapely.intersection(g, true.geometry[n]).area / shapely.union(g, true.geometry[n]).area
        for n, g in left.geometry.items()
    ]
    assert min(overlap) > 0.8, overlap
    assert 0.1 * fp.area_seen_m2 < fp.area_left_out_m2 < 0.6 * fp.area_seen_m2, (fp.area_left_out_m2, fp.area_seen_m2)

    # Run again: the submodel made is reused (it must not be made again), the failed one alone is made
    made = []

    def once(images, output, **kw):
        made.append(output.name)
        assert output.name != "submodel_01", "a finished submodel was made again"
        return real(images, output, **kw)

    monkeypatch.setattr(rc, "sfm", once)
    fb = RecordingFeedback()
    again = real(small_survey.images, tmp_path / "s", gcp_list=whole.output.parent / "gcp_list.txt", split=20,
                 feedback=fb, max_image_size=640, max_features=2048)  # fmt: skip
    rep = json.loads(again.report.read_text())
    assert made == ["submodel_00"] and any("1 of 2 submodels reused" in i for i in fb.infos), fb.infos
    assert sorted((s["submodel"], s["reused"]) for s in rep["submodels"]) == [(0, False), (1, True)]
    assert again.n_registered >= 0.9 * again.n_photos > r.n_registered
    assert not any("failed" in why for why in rep["unregistered"].values())
    # a record is for the photos and options that made it: others, and it is made again
    from geoortho.reconstruction.splitmerge import finished

    sub = tmp_path / "s" / "submodels" / "submodel_01"
    key = json.loads((sub / "submodel.json").read_text())["key"]
    assert finished(sub, 1, key) is not None and key["files"]["gcp_list"]
    assert finished(sub, 1, {**key, "options": {**key["options"], "max_features": "4096"}}) is None
    assert finished(sub, 1, {**key, "photos": key["photos"][1:]}) is None


def test_no_attitude_and_untrusted_heights_level_on_the_camera_plane(tmp_path):
    """A compact camera on a mount tilted 3.5 deg, no pitch or roll in its metadata, GPS heights
    drifting 42 m, over terrain sloping 5 deg: the nadir assumed would tilt the model 3.5 deg (as
    a real survey's was); the level flight lines level it, and the report says how far each prior was."""
    import geoortho

    s = geoortho.synth(tmp_path / "survey", preset="tiny", seed=5, pathology="no-attitude,altitude-drift,slope")
    r = sfm(s.images, tmp_path / "sfm", **FAST)
    report = json.loads(r.report.read_text())
    assert not report["vertical_gps_trusted"] and "plane of the camera centres" in report["georeferenced_by"]
    poses, _ = _truth(s)
    cams = gpd.read_file(r.cameras)
    cams = cams[cams.registered]
    true = np.array([[poses[n][k] for k in "xyz"] for n in cams["image"]])
    dz = cams["z"].to_numpy(float) - true[:, 2]
    # the model's tilt against the truth: the plane of the camera heights' errors
    a = np.c_[true[:, :2] - true[:, :2].mean(axis=0), np.ones(len(true))]
    slope = np.linalg.lstsq(a, dz, rcond=None)[0][:2]
    assert np.degrees(np.arctan(np.hypot(*slope))) < 1.5  # 0.7 measured; 3.5 + jitter when levelled on nadir
    assert 2.0 < report["model_tilt_deg"] < 6.0  # the nadir prior's residual: the mount's tilt
    assert report["camera_plane_tilt_deg"] < 0.1
    assert any("nadir assumed was" in n for n in report["notes"])


def test_colmap_s_rows_move_the_bar_while_it_works(tmp_path, monkeypatch):
    """COLMAP's feature extraction and matching take no callback: the rows it writes to its
    database move the bar, so that a minute of matching does not read as hung."""
    import sqlite3
    import time

    import geoortho.reconstruction.sparse.mapping as sp

    monkeypatch.setattr(sp, "PROGRESS_POLL_S", 0.02)
    db = tmp_path / "database.db"
    con = sqlite3.connect(db)
    con.execute("CREATE TABLE keypoints (image_id INTEGER)")
    con.commit()
    fb = RecordingFeedback()
    with sp._rows_as_progress(db, "keypoints", 4, fb, 0.0, 0.3):
        for i in range(4):
            con.execute("INSERT INTO keypoints VALUES (?)", (i,))
            con.commit()
            time.sleep(0.15)
    assert fb.values and fb.values == sorted(fb.values) and fb.values[-1] == pytest.approx(0.3)
    assert len({round(v, 3) for v in fb.values}) >= 3  # it moved with the rows, not once at the end
    assert sp._pairs_expected("exhaustive", 10) == 45 and sp._pairs_expected("spatial", 100) == 800


def test_the_heights_datum_is_carried_where_known_and_said_where_not(gps_only, with_gcps, tiny_survey, tmp_path):
    """The DEMs carry the datum of their heights when the SfM learnt it (issue 77): a --crs with
    a vertical part reaches the sparse and DEM headers as a compound CRS (which QGIS shows); GCPs
    in a horizontal CRS, or GPS alone, say where the datum would come from."""
    import rasterio

    from geoortho.core.surface import read_surface
    from geoortho.elevation.gridding import dem

    for r, why in ((gps_only[0], "GNSS heights"), (with_gcps[0], "names no vertical datum")):
        rep = json.loads(r.report.read_text())
        assert rep["vertical_crs"] is None and why in rep["vertical_crs_from"], rep["vertical_crs_from"]
        assert CRS(laspy.read(r.points).header.parse_crs()).to_epsg() == 32629  # 2D: nothing claimed
    r = sfm(tiny_survey.images, tmp_path / "sfm", crs=CRS("EPSG:32629+5773"), max_image_size=640, max_features=2048)
    rep = json.loads(r.report.read_text())
    assert r.crs == rep["crs"] == "EPSG:32629"  # the map grid stays horizontal everywhere
    assert rep["vertical_crs"] == "EPSG:5773" and "--crs" in rep["vertical_crs_from"]
    header = CRS(laspy.read(r.points).header.parse_crs())
    assert header.is_compound and header.sub_crs_list[1].to_epsg() == 5773
    d = dem(r.points, tmp_path / "dsm.tif", dtm=tmp_path / "dtm.tif", resolution_m=0.5)
    assert d.vertical_crs == "EPSG:5773" and d.crs == "EPSG:32629"
    for tif in (d.dsm, d.dtm):
        with rasterio.open(tif) as ds:
            crs = CRS(ds.crs.to_wkt())
        assert crs.is_compound and [c.to_epsg() for c in crs.sub_crs_list] == [32629, 5773], tif
    surface = read_surface(d.dsm, CRS.from_epsg(32629))  # read in the map grid: not warped
    with rasterio.open(d.dsm) as ds:
        assert surface.transform == ds.transform and surface.crs.to_epsg() == 32629
