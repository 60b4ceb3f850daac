"""Orthophoto against the synthetic survey's true ortho; occlusion, seams, balance, holes, COG; bad input."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
import rasterio
from conftest import RecordingFeedback, real_data
from scipy import ndimage

from geoortho.core.camera import Intrinsics, Pose, PosedCamera
from geoortho.core.surface import read_surface
from geoortho.errors import InputError
from geoortho.orthophoto import MosaicOptions, mosaic, ortho
from geoortho.orthophoto.quality import geolocation_shifts, share_off_beside_objects

TRUE_CELL_M = 0.05  # the small preset's true ortho: our grid lands on its pixels


def _true_cameras(survey):
    c = json.loads((survey.truth / "survey.json").read_text())["camera"]
    intr = Intrinsics(c["width_px"], c["height_px"], c["focal_px"], c["cx_px"], c["cy_px"], tuple(c["distortion"]))
    return [
        PosedCamera(
            intr,
            Pose(np.array([p["x"], p["y"], p["z"]]), np.array(p["rotation_world_from_camera"])),
            p["image"],
            survey.images / p["image"],
        )
        for p in json.loads((survey.truth / "poses.json").read_text())
        if not p["corrupt"]
    ]


def test_project_grid_is_the_camera_model():
    """The tiles' float32 per-component projection agrees with camera.project_points (distortion too)."""
    from geoortho.orthophoto.rectify import project_grid

    intr = Intrinsics(1600, 1067, 1066.7, 800.3, 533.1, (-0.02, 0.01, 0.001, -0.002, 0.003))
    cam = PosedCamera(intr, Pose.from_ypr((500000.0, 4300000.0, 140.0), 30, -80, 2), "a")
    rng = np.random.default_rng(0)
    x = 500000 + rng.uniform(-20, 20, (50, 40))
    y = 4300000 + rng.uniform(-20, 20, (50, 40))
    z = rng.uniform(90, 110, (50, 40))
    mx, my, depth = project_grid(cam, x, y, z)
    ref, ref_depth = cam.project(np.c_[x.ravel(), y.ravel(), z.ravel()])
    assert np.nanmax(np.abs(mx.ravel() - ref[:, 0])) < 0.01
    assert np.nanmax(np.abs(my.ravel() - ref[:, 1])) < 0.01
    assert np.allclose(depth.ravel(), ref_depth, atol=1e-3)


def _gsd_m(survey):
    return json.loads((survey.truth / "survey.json").read_text())["gsd_cm_at_home_height"] / 100.0


@pytest.fixture(scope="module")
def true_ortho(small_survey, tmp_path_factory):
    d = tmp_path_factory.mktemp("ortho_true")
    surf = read_surface(small_survey.dsm)
    fb = RecordingFeedback()
    r = mosaic(
        _true_cameras(small_survey),
        surf,
        surf.crs,
        d / "ortho.tif",
        TRUE_CELL_M,
        MosaicOptions(workers=2),
        preview=d / "ortho.png",
        feedback=fb,
    )
    return r, fb


def _ring_errors(ortho_path, survey):
    return share_off_beside_objects(ortho_path, survey.ortho, survey.dsm, survey.dtm)


@pytest.mark.parametrize("extend", [False, True], ids=["holes", "holes-extended"])
def test_visibility_march_skipping_clear_blocks_and_compiled_is_the_plain_march(
    small_survey, tmp_path, monkeypatch, extend
):
    """The march jumps over DSM blocks a ray clears (rectify.BlockTops), and runs compiled (numba)
    where it can: every grid must be the plain numpy cell-by-cell march's, bit for bit, with real
    occlusion in them (buildings, trees), on a DSM with holes (rays through them: no data, or the
    ground continued under them) and past its edge."""
    import dataclasses

    from geoortho.core import kernels
    from geoortho.orthophoto import rectify

    surf = read_surface(small_survey.dsm)
    grid = surf.grid.copy()
    rng = np.random.default_rng(0)
    grid[rng.random(grid.shape) < 0.01] = np.nan
    grid[grid.shape[0] // 3 : grid.shape[0] // 3 + 80, :] = np.nan  # a band across the block
    surf = dataclasses.replace(surf, grid=grid, extend=extend)
    tops = rectify.block_tops(surf)
    monkeypatch.setattr(rectify, "COMPILED_MIN_RAYS", 0)
    hidden = 0
    for i, cam in enumerate(_true_cameras(small_survey)[::7]):
        x, y = cam.pose.center[:2]
        box = (x - 40.0, y - 30.0, x + 40.0, y + 30.0)
        grids = {}
        for compiled in ("0", "1"):
            monkeypatch.setenv(kernels.ENV_SWITCH, compiled)
            for skip in (False, True):
                path = tmp_path / f"{i}_{compiled}_{skip}.npy"
                grids[compiled, skip] = np.load(
                    rectify.visibility_grid(cam, surf, box, path, tops=tops if skip else ()).path
                )
        plain = grids["0", False]
        for key, other in grids.items():
            assert np.array_equal(plain, other), (cam.name, key, int((plain != other).sum()))
        hidden += int((plain == 0).sum())
    assert kernels.compiled(rectify._march_rays) is not None  # numba is here: both paths were taken
    assert hidden > 1000  # the grids do hide cells: the comparison is not of empty grids


def test_occlusion_keeps_roofs_off_the_ground_beside_buildings(true_ortho, small_survey, tmp_path):
    r, _ = true_ortho
    surf = read_surface(small_survey.dsm)
    plain = mosaic(
        _true_cameras(small_survey),
        surf,
        surf.crs,
        tmp_path / "plain.tif",
        TRUE_CELL_M,
        MosaicOptions(occlusion=False, workers=2),
    )
    ours = _ring_errors(r.output, small_survey)
    theirs = _ring_errors(plain.output, small_survey)
    # measured: 0.45 % of the ring off with occlusion, 7.4 % without; open ground 0.06 % either way
    assert ours["ring"] < 0.02
    assert theirs["ring"] > 3 * ours["ring"]
    assert ours["open"] < 0.01


def test_sfm_poses_with_gcps_jpeg_cog(sfm_with_gcps, small_survey, tmp_path):
    r_sfm, _ = sfm_with_gcps
    r = ortho(
        small_survey.images,
        tmp_path / "o.tif",
        sfm=r_sfm.output,
        dsm=small_survey.dsm,
        resolution_m=TRUE_CELL_M,
        compress="JPEG",
        workers=2,
    )
    d = np.array([s.distance for s in geolocation_shifts(r.output, small_survey.ortho)])
    assert len(d) >= 30
    assert np.median(d) <= 2 * _gsd_m(small_survey)  # measured 0.9 mm
    assert r.poses.startswith("sfm")
    with rasterio.open(r.output) as src:
        assert src.count == 3 and src.compression.name == "jpeg"
        mask = src.dataset_mask()
        assert rasterio.enums.MaskFlags.per_dataset in src.mask_flag_enums[0]
    assert 0.5 < (mask > 0).mean() < 1.0


def test_direct_georeferencing_from_metadata(tiny_survey, tmp_path):
    home = json.loads((tiny_survey.truth / "survey.json").read_text())["home"]
    r = ortho(
        tiny_survey.images,
        tmp_path / "o.tif",
        dsm=tiny_survey.dsm,
        takeoff_elevation_m=home["ground_z"],
        preview=tmp_path / "o.png",
        workers=1,
    )
    assert r.poses.startswith("photo metadata")
    # default resolution: the median GSD, rounded to 3 digits
    assert r.resolution_m == pytest.approx(r.median_gsd_m, rel=0.01)
    d = np.array([s.distance for s in geolocation_shifts(r.output, tiny_survey.ortho, tile_px=128)])
    assert len(d) >= 3
    # GPS bias 0.5 m and attitude noise 0.2° per axis: a field-check mosaic, within a metre
    assert np.median(d) < 1.0
    assert r.preview.exists()


def test_bad_photos_are_reported_and_skipped(small_survey, tmp_path):
    cams = _true_cameras(small_survey)[:8]
    broken = tmp_path / "broken.JPG"
    broken.write_bytes(b"\xff\xd8\xff\xe0 not really a jpeg")
    far = cams[1].pose.center + np.array([5000.0, 0.0, 0.0])
    cams = cams + [
        PosedCamera(cams[0].intrinsics, cams[0].pose, "broken.JPG", broken),
        PosedCamera(cams[1].intrinsics, Pose(far, cams[1].pose.rotation), "far.JPG", cams[1].path),
    ]
    surf = read_surface(small_survey.dsm)
    fb = RecordingFeedback()
    r = mosaic(cams, surf, surf.crs, tmp_path / "o.tif", 0.2, MosaicOptions(workers=1), feedback=fb)
    why = dict(r.skipped)
    assert "corrupt" in why["broken.JPG"]  # the strict decoder refuses it (was: "cannot be decoded")
    assert "outside the DSM" in why["far.JPG"]
    assert r.n_used == 8
    assert any("broken.JPG" in w for w in fb.warnings)


def test_dsm_holes_are_filled_and_said(tiny_survey, tmp_path):
    with rasterio.open(tiny_survey.dsm) as src:
        prof, z = src.profile, src.read(1)
    z[20:26, 30:36] = prof["nodata"]
    holed = tmp_path / "dsm_holes.tif"
    with rasterio.open(holed, "w", **prof) as dst:
        dst.write(z, 1)
    home = json.loads((tiny_survey.truth / "survey.json").read_text())["home"]
    r = ortho(
        tiny_survey.images,
        tmp_path / "o.tif",
        dsm=holed,
        takeoff_elevation_m=home["ground_z"],
        resolution_m=0.03,
        workers=1,
    )
    assert any("36 nodata cells" in n for n in r.notes)
    assert any("finer than the photos' median GSD" in n for n in r.notes)  # 3 cm asked, GSD 4.7 cm
    assert r.holes_left_px == 0


def test_bad_input_exit_2(tmp_path):
    (tmp_path / "empty").mkdir()
    p = subprocess.run(
        [
            sys.executable,
            "-m",
            "geoortho",
            "ortho",
            "--images",
            str(tmp_path / "empty"),
            "--output",
            str(tmp_path / "o.tif"),
        ],
        capture_output=True,
        text=True,
    )
    assert p.returncode == 2
    assert len(p.stderr.strip().splitlines()) == 1
    with pytest.raises(InputError, match="not an sfm output"):
        ortho(tmp_path / "empty", tmp_path / "o.tif", sfm=tmp_path / "empty")
    assert not (tmp_path / "o.tif").exists()


def test_toledo_mosaic_from_sfm(toledo_sfm, tmp_path):
    """Real photos: two camera bodies, downscaled photos with lying EXIF sizes, UTM 17N."""
    base = real_data("toledo_dji")
    r = ortho(
        base / "images",
        tmp_path / "toledo.tif",
        sfm=toledo_sfm.output,
        resolution_m=0.3,
        preview=tmp_path / "toledo.png",
        workers=2,
    )
    assert r.n_used >= 50 and "32617" in r.crs
    assert r.holes_left_px == 0
    assert r.seam_mismatch_balanced < r.seam_mismatch_raw
    with rasterio.open(r.output) as src:
        alpha = src.read(4)
    # a complete mosaic: one solid block of coverage without holes inside it
    filled = ndimage.binary_fill_holes(alpha > 0)
    assert (alpha[filled] > 0).mean() > 0.999
    assert r.preview.exists()


@pytest.mark.parametrize("resolution", ["1e6", "1e-5"])
def test_a_resolution_that_makes_no_product_is_refused(tiny_survey, tmp_path, capsys, resolution):
    """Issue 23 (7): --resolution 1e6 wrote a 1 x 1 px mosaic with 0 photos used, exit 0."""
    from geoortho.processing.cli import main

    code = main(
        [
            "ortho",
            "--images",
            str(tiny_survey.images),
            "--output",
            str(tmp_path / "o.tif"),
            "--resolution-m",
            resolution,
            "--takeoff-elevation-m",
            "110",
            "--quiet",
        ]
    )
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "median GSD" in err[0] and not (tmp_path / "o.tif").exists(), err


def test_seam_pass_streams_photos_and_loses_no_overlap(small_survey):
    """Issue 25: the coarse seam/gain pass holds only the views a later photo can still overlap,
    and gets the same gains as every pair solved with every view held."""
    import math

    from affine import Affine

    from geoortho.feedback import as_feedback
    from geoortho.orthophoto.placing import place_photos
    from geoortho.orthophoto.rectify import bounds_window
    from geoortho.orthophoto.seams import (
        _coarse_view,
        _falloff_blocks,
        _pair_stat,
        _without_falloff,
        plan_seams,
        solve_gains,
    )

    surf = read_surface(small_survey.dsm)
    placed = place_photos(_true_cameras(small_survey), surf, as_feedback(None))
    cams, boxes = list(placed.cams), list(placed.boxes)
    n = len(cams)
    res = 0.5
    xmin, ymin, xmax, ymax = surf.bounds
    transform = Affine(res, 0, xmin, 0, -res, ymax)
    shape = (math.ceil((ymax - ymin) / res), math.ceil((xmax - xmin) / res))
    plan = plan_seams(cams, boxes, list(placed.gsds), surf, [None] * n, transform, shape, 2, seams="voronoi")
    views = [
        _coarse_view(i, c, surf, None, plan.transform, w, g)
        for i, (c, b, g) in enumerate(zip(cams, boxes, placed.gsds))
        if (w := bounds_window(plan.transform, plan.labels.shape, b)) is not None
    ]
    # held at once: the most windows that cross one sweep line, along the grid's longer axis
    rows_first = plan.labels.shape[0] >= plan.labels.shape[1]
    spans = [
        (v.win.row_off, v.win.row_off + v.win.height) if rows_first else (v.win.col_off, v.win.col_off + v.win.width)
        for v in views
    ]
    crossing = max(sum(a <= s0 < b for a, b in spans) for s0, _ in spans)
    assert plan.views_held_max == crossing < n  # not the survey: photos stream through
    rows = [s for a in range(len(views)) for b in range(a + 1, len(views)) if (s := _pair_stat(views[a], views[b]))]
    assert len(rows) > n
    # the lens's falloff, measured on the overlaps, is the renderer's (1 - 0.25 rho: 6.25 % half-way
    # out, 25 % at the corners), and the gains are solved with it taken out
    by_index = {v.index: v for v in views}
    blocks = {(r[0], r[1]): _falloff_blocks(by_index[r[0]], by_index[r[1]]) for r in rows}
    assert plan.falloff is not None
    assert plan.falloff.loss_at(0.25) == pytest.approx(0.0625, abs=0.01)
    assert plan.falloff.loss_at(1.0) == pytest.approx(0.25, abs=0.02)
    rows = _without_falloff(rows, blocks, plan.falloff)
    held = solve_gains(rows, n, exposure=[math.nan] * n)
    np.testing.assert_allclose(plan.gains, held.gains, rtol=1e-6)
    assert not np.allclose(plan.gains, 1.0)


def test_graph_cut_seams_beat_voronoi_on_toledo(toledo_sfm, tmp_path):
    """Issue 26: the seam cost rewards agreement of the balanced photos. Measured on toledo at
    0.3 m: colour mismatch across seams 10.64 DN (Voronoi 12.88; the old edge-seeking cost 12.23),
    seam pixels where the photos differ by > 10 DN 6077 (Voronoi 6692)."""
    base = real_data("toledo_dji") / "images"
    figures = {}
    for seams in ("graphcut", "voronoi"):
        r = ortho(base, tmp_path / f"{seams}.tif", sfm=toledo_sfm.output, resolution_m=0.3, seams=seams, workers=2)
        rep = json.loads(r.report.read_text())
        figures[seams] = (r.seam_mismatch_balanced, rep["seam_visible_pixels"])
    (gc, gc_visible), (vo, vo_visible) = figures["graphcut"], figures["voronoi"]
    assert gc < 0.95 * vo, figures
    assert gc_visible < vo_visible, figures


def test_blending_lowers_the_step_across_seams(tiny_survey, tmp_path):
    """Issue 26: the output's colour step across seams (tiny, direct georeferencing): no blending
    27.9 DN, multiband 16.5, feather 11.0 (feather fed OpenCV the seam masks, which do not overlap,
    and blended nothing: 27.8)."""
    home = json.loads((tiny_survey.truth / "survey.json").read_text())["home"]
    steps = {}
    for blend in ("none", "multiband", "feather"):
        r = ortho(
            tiny_survey.images,
            tmp_path / f"{blend}.tif",
            dsm=tiny_survey.dsm,
            takeoff_elevation_m=home["ground_z"],
            blend=blend,
            workers=1,
        )
        rep = json.loads(r.report.read_text())
        steps[blend] = rep["seam_step_dn"]
    assert steps["multiband"] < 0.8 * steps["none"], steps
    assert steps["feather"] < 0.8 * steps["none"], steps


def test_holes_up_to_max_hole_px_are_filled_wider_ones_stay_transparent():
    """Issue 26: hole fill by width: a 6 px hole is inpainted (close to the smooth ground around
    it), a 30 px one is left alone, with max_hole_px 10."""
    from geoortho.orthophoto.tile import _fill_holes

    yy, xx = np.mgrid[0:120, 0:200].astype(np.float32)
    truth = np.dstack([60 + 0.5 * xx, 80 + 0.4 * yy, 100 + 0.2 * (xx + yy)]).astype(np.uint8)
    img = truth.copy()
    holes = np.zeros((120, 200), bool)
    holes[40:46, 30:60] = True  # 6 px wide
    holes[40:70, 120:150] = True  # 30 px wide
    img[holes] = 0
    filled = _fill_holes(img, holes, max_hole_px=10)
    assert filled[40:46, 30:60].all() and not filled[40:70, 120:150].any()
    err = np.abs(img[40:46, 30:60].astype(int) - truth[40:46, 30:60].astype(int))
    assert err.max() <= 4, err.max()
    assert (img[40:70, 120:150] == 0).all()  # the wide hole stays as it was: the caller keeps it transparent


def test_a_hole_filling_a_whole_tile_is_left_and_warns_nothing():
    """A tile that is one hole (no edge inside it): the distance transform's huge value made the
    width test overflow (a RuntimeWarning on real data); the hole is wider than any limit."""
    import warnings

    from geoortho.orthophoto.tile import _fill_holes

    bgr = np.zeros((40, 40, 3), np.uint8)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert not _fill_holes(bgr, np.ones((40, 40), bool), 10).any()
        small = np.zeros((40, 40), bool)
        small[10:13, 10:13] = True
        assert _fill_holes(bgr, small, 10).sum() == 9


# --- where each pixel came from (issue 75) ------------------------------------------------------


def test_each_pixel_names_the_photo_that_sees_it_and_the_seamlines_tile_the_mosaic(true_ortho, small_survey):
    import xml.etree.ElementTree as ET

    import geopandas as gpd

    from geoortho.orthophoto.provenance import INPAINTED, OCCLUDED, SEEN

    r, _ = true_ortho
    cams = {c.name: c for c in _true_cameras(small_survey)}
    with rasterio.open(r.source) as ds:
        photo, how = ds.read(1), ds.read(2)
        t = ds.transform
        assert ds.descriptions == ("photo", "how") and ds.nodata == 0
    with rasterio.open(r.output) as ds:
        alpha = ds.read(4) > 0
        assert ds.transform == t
    # every opaque pixel has its photo, every transparent one none
    assert (photo[alpha] > 0).all() and (photo[~alpha] == 0).all()
    assert set(np.unique(how[alpha])) <= {SEEN, OCCLUDED, INPAINTED}
    # the attribute table names the photos by number
    table = ET.parse(str(r.source) + ".aux.xml").getroot().find(".//GDALRasterAttributeTable")
    names = {int(row[0].text): row[1].text for row in table.findall("Row")}
    assert set(names.values()) <= set(cams) and set(np.unique(photo[alpha])) <= set(names)
    # a pixel said seen by a photo lies in that photo's frame (its ground point projected on the DSM)
    surf = read_surface(small_survey.dsm)
    rng = np.random.default_rng(1)
    rows, cols = np.nonzero(how == SEEN)
    pick = rng.choice(len(rows), 400, replace=False)
    x, y = t * (cols[pick] + 0.5, rows[pick] + 0.5)
    z = surf.elevation(np.asarray(x), np.asarray(y))
    for k in range(len(pick)):
        cam = cams[names[int(photo[rows[pick[k]], cols[pick[k]]])]]
        (u, v), depth = (a[0] for a in cam.project(np.array([[x[k], y[k], z[k]]])))
        assert depth > 0 and 0 <= u < cam.intrinsics.width_px and 0 <= v < cam.intrinsics.height_px
    # the seamlines: one region per photo used, not overlapping, together the mosaic
    lines = gpd.read_file(r.seamlines, layer="seamlines")
    assert len(lines) == len(np.unique(photo[alpha])) and lines["photo"].is_unique
    union = lines.geometry.union_all().area
    assert abs(lines.geometry.area.sum() - union) < 0.01 * union
    assert abs(union - r.area_m2) < 0.03 * r.area_m2
    assert (lines["view_angle_deg"] < 10).all() and (lines["gsd_cm"] > 0).all()
    assert (lines["taken_at"].str.len() > 0).all()
    assert r.holes_inside_m2 == 0.0


def test_hidden_ground_is_drawn_from_the_ground_round_it_not_from_what_hides_it():
    """Moving-cars survey, seed 5: ground north of a roof at the survey's edge is hidden from every
    photo. Drawn from the photo that had it in frame most directly, it showed the roof: the roof ran
    on 0.6-0.8 m past its wall, a second edge beside it. Drawn from the ground round it, the roof ends
    at its wall; the roof itself, what lies beyond the mosaic and the seen ground are untouched."""
    from geoortho.orthophoto.tile import _ground_behind

    rng = np.random.default_rng(3)
    bgr = np.zeros((120, 160, 3), np.uint8)
    z = np.full((120, 160), 100.0)
    ground = np.array([60, 160, 120], float)  # BGR: a green field with texture
    bgr[:] = np.clip(ground + rng.normal(0, 12, (120, 160, 3)), 0, 255).astype(np.uint8)
    roof = (slice(40, 120), slice(60, 160))
    bgr[roof] = (90, 100, 110)  # a grey-brown roof 6 m up
    z[roof] = 106.0
    hidden = np.zeros((120, 160), bool)
    hidden[24:40, 10:160] = True  # the strip north of its wall no photo sees...
    bgr[hidden] = (90, 100, 110)  # ...drawn from a photo that sees the roof there
    labelled = np.ones((120, 160), bool)
    labelled[:, :8] = False  # beyond the mosaic: black, never a source
    bgr[~labelled] = 0
    before = bgr.copy()
    _ground_behind(bgr, hidden, labelled, z)
    got = bgr[hidden].astype(float)
    assert np.abs(got.mean(axis=0) - ground).max() < 8  # the field's colour, not the roof's
    assert got.std(axis=0).max() < 12  # softened, no streaks of single pixels
    assert (bgr[~hidden] == before[~hidden]).all()
    _ground_behind(bgr, np.zeros_like(hidden), labelled, z)  # nothing hidden: nothing done
    assert (bgr[~hidden] == before[~hidden]).all()


def test_a_wrong_spike_in_the_dsm_leaves_no_hole_and_is_marked(tiny_survey, tmp_path):
    """Issue 75's bad input: a DSM with a 20 m spike under a roof hides the ground round it from every
    photo. The orthophoto stays whole (each hidden pixel drawn from the ground round it) and the
    source raster marks those pixels."""
    from geoortho.orthophoto.provenance import OCCLUDED

    with rasterio.open(tiny_survey.dsm) as src:
        prof, z = src.profile, src.read(1)
    rows, cols = z.shape
    z[rows // 2 - 4 : rows // 2 + 4, cols // 2 - 4 : cols // 2 + 4] += 20.0  # 2 x 2 m, 20 m up
    spiked = tmp_path / "dsm_spike.tif"
    with rasterio.open(spiked, "w", **prof) as dst:
        dst.write(z, 1)
    home = json.loads((tiny_survey.truth / "survey.json").read_text())["home"]
    r = ortho(tiny_survey.images, tmp_path / "o.tif", dsm=spiked, takeoff_elevation_m=home["ground_z"],
              max_hole_px=0, workers=1)  # fmt: skip
    assert r.holes_inside_m2 == 0.0 and r.holes_left_px == 0
    assert r.occluded_m2 > 1.0
    with rasterio.open(r.source) as ds:
        assert (ds.read(2) == OCCLUDED).sum() * abs(ds.transform.a * ds.transform.e) > 1.0


def test_seams_keep_off_roofs_and_crowns(true_ortho, small_survey):
    """The graph cut pays for the parallax between two photos where relief stands (issue 75): a roof
    agrees in colour with itself and was crossed more than open ground (measured, small survey: 12.9 %
    of the seam pixels on objects that cover 5.4 % of the mosaic; with the parallax cost 8.6 %)."""
    from geoortho.synthetic.scoring import _on_grid

    r, _ = true_ortho
    with rasterio.open(r.source) as ds:
        photo, t, crs = ds.read(1), ds.transform, ds.crs
    relief = _on_grid(small_survey.dsm, t, crs, photo.shape) - _on_grid(small_survey.dtm, t, crs, photo.shape)
    objects = relief > 0.5
    seam = np.zeros(photo.shape, bool)
    seam[:, :-1] |= (photo[:, :-1] > 0) & (photo[:, 1:] > 0) & (photo[:, :-1] != photo[:, 1:])
    seam[:-1, :] |= (photo[:-1, :] > 0) & (photo[1:, :] > 0) & (photo[:-1, :] != photo[1:, :])
    on_objects = (seam & objects).sum() / seam.sum()
    assert seam.sum() > 1000 and objects[photo > 0].mean() > 0.03
    assert on_objects < 0.11, on_objects


def test_a_photo_of_another_flight_is_named_and_left_out(tiny_survey, tmp_path):
    """Issue 75's bad input: one photo in the folder is of another flight over the same site (three
    days before, by its clock): it is named, with why, and no pixel of the mosaic is drawn from it."""
    import shutil

    import geopandas as gpd
    import piexif

    images = tmp_path / "images"
    shutil.copytree(tiny_survey.images, images)
    stray = sorted(images.glob("*.JPG"))[3]
    exif = piexif.load(str(stray))
    taken = exif["Exif"][piexif.ExifIFD.DateTimeOriginal].decode()
    day = int(taken[8:10])
    earlier = f"{taken[:8]}{day - 3 if day > 3 else day + 3:02d}{taken[10:]}"
    exif["Exif"][piexif.ExifIFD.DateTimeOriginal] = earlier.encode()
    piexif.insert(piexif.dump(exif), str(stray))
    home = json.loads((tiny_survey.truth / "survey.json").read_text())["home"]
    r = ortho(images, tmp_path / "o.tif", dsm=tiny_survey.dsm, takeoff_elevation_m=home["ground_z"], workers=1)
    reasons = dict(r.skipped)
    assert "another flight" in reasons.get(stray.name, ""), r.skipped
    assert len(r.skipped) == 1  # the survey's own photos are all used
    assert stray.name not in set(gpd.read_file(r.seamlines, layer="seamlines")["photo"])


@pytest.mark.parametrize(
    ("profile", "expect"),
    [
        ("cos4", True),  # the natural cos^4 law over a 50 degree diagonal field (32 % at the corners)
        ("flat-then-drop", True),  # toledo's shape: flat to half-way, a drop at the corners
        ("none", False),  # no falloff: nothing applied
        ("brighter-outwards", False),  # content, not a lens: refused
    ],
)
def test_the_falloff_fit_finds_each_lens_profile_and_refuses_what_no_lens_does(profile, expect):
    """The falloff estimator on overlaps drawn from several profiles (not the renderer's one): each
    overlap's blocks at random radii in both photos, a random exposure ratio per overlap, noise and
    a tenth of the blocks disagreeing as parallax or a moved car would."""
    import math

    from geoortho.orthophoto.falloff import estimate_falloff

    half_diag = math.tan(math.radians(25.0))

    def log_v(rho):
        if profile == "cos4":
            return 4.0 * np.log(np.cos(np.arctan(np.sqrt(rho) * half_diag)))
        if profile == "flat-then-drop":
            return -0.14 * rho**2
        if profile == "brighter-outwards":
            return 0.1 * rho
        return 0.0 * rho

    rng = np.random.default_rng(7)
    pairs = []
    for _ in range(60):
        ra, rb = rng.uniform(0, 1, 36), rng.uniform(0, 1, 36)
        d = log_v(ra) - log_v(rb) + rng.normal(0, 0.3) + rng.normal(0, 0.01, 36)
        d[rng.random(36) < 0.1] += rng.normal(0, 0.3, 1)
        pairs.append(np.c_[rng.uniform(5, 10, 36), d, ra, rb])
    f = estimate_falloff(pairs)
    if not expect:
        assert f is None
        return
    assert f is not None
    for rho in (0.25, 0.5, 1.0):
        assert f.loss_at(rho) == pytest.approx(1.0 - math.exp(float(log_v(np.array(rho)))), abs=0.015), rho


def test_holes_are_counted_on_the_full_mask_not_on_its_decimated_read(tmp_path):
    """A mosaic too big for one read is measured every f pixels: a one-pixel inlet of its outer edge
    reads as shut there, and the transparent bay behind it as a hole. Each hole found so is measured
    again on the full mask: the bay is no hole, a true hole keeps its area."""
    import math

    from affine import Affine
    from rasterio.enums import Resampling

    from geoortho.orthophoto.coverage import COVERAGE_CELLS, _holes_inside

    side = int(math.sqrt(COVERAGE_CELLS)) + 1000
    alpha = np.full((side, side), 255, np.uint8)
    alpha[100:200, 0:2] = 0  # the outer edge's own transparent strip ...
    for row in (117, 168):  # ... two inlets one pixel wide from it, on rows of either parity (a
        alpha[row, 2:301] = 0  # decimated read skips one of them) ...
        alpha[row - 10 : row + 10, 300:340] = 0  # ... each with a bay behind it
    alpha[1000:1010, 1000:1020] = 0  # a hole: 200 px
    path = tmp_path / "mask.tif"
    with rasterio.open(path, "w", driver="GTiff", width=side, height=side, count=1, dtype="uint8",
                       crs="EPSG:32630", transform=Affine(0.1, 0, 0, 0, -0.1, 0), tiled=True) as ds:  # fmt: skip
        ds.write(alpha, 1)
        ds.write_mask(alpha)
    f = max(1, math.ceil(math.sqrt(side * side / COVERAGE_CELLS)))
    with rasterio.open(path) as ds:
        shape = (side // f, side // f)
        read = ds.read_masks(1, out_shape=shape, resampling=Resampling.nearest) > 0
    cell_m2 = 0.01 * f * f
    assert f >= 2 and _holes_inside(read, cell_m2)["holes_inside_n"] == 2  # the bay reads as a hole
    got = _holes_inside(read, cell_m2, path, f)
    assert got["holes_inside_n"] == 1 and got["holes_inside_m2"] == pytest.approx(200 * 0.01)
