"""The quality verdict: each item graded from what the stages measured, the worst one the verdict."""

from __future__ import annotations

import pytest

from geoortho.chain.quality import THRESHOLDS, assess, verdict


def _clean():
    sfm = {
        "photos": 50,
        "registered": 50,
        "unregistered": [],
        "gsd_cm": 2.0,
        "georeferenced_by": "GCPs (5 control)",
        "gcp_accuracy": {"n": 5, "rmse_3d_m": 0.02, "rmse_horizontal_m": 0.015},
        "checkpoint_accuracy": {"n": 2, "rmse_3d_m": 0.03},
        "gps": {"ce90_m": 30.0},  # not graded: the GCPs georeference the block
        "intrinsics": [{"focal_drift_pct": -0.8}],
        "gcp_vs_gps": {
            "scale_change_pct": 0.2,
            "rotation_deg": 0.1,
            "edge_shift_m": 0.3,
            "shift_horizontal_m": 2.1,
            "shift_vertical_m": -4.0,
        },
    }
    dense = {"photos": 50, "depth_maps": 50, "no_depth_map": {}}
    dem = {
        "seen_m2": 1e4,
        "measured_share": 0.8,
        "dtm_roughness_m": 0.004,
        "dtm_under_object_share": 0.0,
        "footprint_step_m": 0.003,
    }
    ortho = {
        "share_of_seen_2": 0.995, "n_photos": 50, "n_used": 50, "dsm_offset_m": 0.02, "seam_mismatch_balanced": 4,
        "holes_inside_m2": 0.0, "holes_inside_n": 0,
    }  # fmt: skip
    fp = {
        "altitude_m": 60.0, "altitude_metadata_m": 61.0, "height_check": "",
        "n_left_out": 0, "area_left_out_m2": 0.0, "area_seen_m2": 1e4,
    }  # fmt: skip
    return sfm, dense, dem, ortho, fp


def _states(*args):
    return {c.item: c.state for c in assess(*args)}


def test_a_clean_run_is_green_on_every_item():
    states = _states(*_clean())
    assert set(states) == set(THRESHOLDS)
    # GCPs georeference: the GPS fit is not the products'
    assert states["gps_fit"] == states["gps_fits_agree"] == "not measured"
    assert {s for k, s in states.items() if not k.startswith("gps_")} == {"green"}
    assert verdict(assess(*_clean())) == "green" and verdict(assess(*_clean()), failed=True) == "red"


@pytest.mark.parametrize(
    ("change", "item", "state"),
    [
        (lambda s, d, m, o, f: o.update(share_of_seen_2=0.95), "ortho_coverage", "amber"),
        # speckle at 0.9 and 0.5 GSD (the demo DTM before issue 74: 0.48 GSD), a third under objects, steps
        (lambda s, d, m, o, f: m.update(dtm_roughness_m=0.018), "dtm_roughness", "red"),
        (lambda s, d, m, o, f: m.update(dtm_roughness_m=0.01), "dtm_roughness", "amber"),
        (lambda s, d, m, o, f: m.update(dtm_under_object_share=0.3), "dtm_no_ground", "red"),
        (lambda s, d, m, o, f: m.update(footprint_step_m=0.03), "footprint_step", "red"),
        (lambda s, d, m, o, f: m.update(footprint_step_m=0.008), "footprint_step", "amber"),
        (lambda s, d, m, o, f: o.update(share_of_seen_2=0.14), "ortho_coverage", "red"),
        # a real park survey's 25 holes under trees, 88 m² (issue 75); one small hole is not green
        (lambda s, d, m, o, f: o.update(holes_inside_m2=88.0, holes_inside_n=25), "ortho_holes", "red"),
        (lambda s, d, m, o, f: o.update(holes_inside_m2=0.4, holes_inside_n=1), "ortho_holes", "amber"),
        (lambda s, d, m, o, f: s.update(registered=44, unregistered=["A.JPG"]), "photos_registered", "red"),
        (lambda s, d, m, o, f: d.update(depth_maps=37, photos=75), "depth_maps", "red"),
        # a failed submodel's ground (issue 78), a photo lost at a turn
        (lambda s, d, m, o, f: f.update(n_left_out=12, area_left_out_m2=800.0), "ground_left_out", "red"),
        (lambda s, d, m, o, f: f.update(n_left_out=1, area_left_out_m2=250.0), "ground_left_out", "amber"),
        (lambda s, d, m, o, f: s["gcp_accuracy"].update(rmse_3d_m=0.97), "gcp_rmse", "red"),
        (lambda s, d, m, o, f: s["gcp_accuracy"].update(rmse_3d_m=0.05), "gcp_rmse", "amber"),
        (lambda s, d, m, o, f: s["intrinsics"][0].update(focal_drift_pct=12), "focal_drift", "red"),
        (lambda s, d, m, o, f: s["gcp_vs_gps"].update(scale_change_pct=6.7), "gcp_scale", "red"),
        (lambda s, d, m, o, f: s["gcp_vs_gps"].update(rotation_deg=1.2), "gcp_rotation", "amber"),
        (lambda s, d, m, o, f: s["gcp_vs_gps"].update(shift_horizontal_m=237.0), "gcp_shift", "red"),
        (lambda s, d, m, o, f: s["gcp_vs_gps"].update(shift_horizontal_m=15.0), "gcp_shift", "amber"),
        (lambda s, d, m, o, f: o.update(dsm_offset_m=-3.0), "dsm_vs_sfm", "red"),
        (
            lambda s, d, m, o, f: f.update(altitude_metadata_m=87, altitude_m=56, height_check="x"),
            "heights_given",
            "red",
        ),
        (lambda s, d, m, o, f: f.update(altitude_metadata_m=60.5, height_check="2 m off"), "heights_given", "red"),
        (lambda s, d, m, o, f: o.update(seam_mismatch_balanced=25), "seam_mismatch", "red"),
        (lambda s, d, m, o, f: s.update(georeferenced_by="GPS of 75 photos", gcp_accuracy=None), "gps_fit", "red"),
        (
            lambda s, d, m, o, f: s.update(
                georeferenced_by="GPS of 75 photos",
                gcp_accuracy=None,
                gps={"ce90_m": 4.0, "robust_vs_lsq_m": 40.0, "lsq_rotation_deg": 22.0, "inlier_share": 0.25},
            ),
            "gps_fits_agree",
            "red",
        ),
    ],
)
def test_each_item_turns_for_its_own_cause(change, item, state):
    args = _clean()
    change(*args)
    states = _states(*args)
    assert states[item] == state
    assert verdict(assess(*args)) == ("red" if state == "red" else "amber")
    others = {k: s for k, s in states.items() if k != item and s != "not measured"}
    assert set(others.values()) <= {"green"}, others


def test_placeholder_heights_grade_the_horizontal_residual_and_say_so():
    sfm, *rest = _clean()
    sfm["gcp_accuracy"] = {"n": 3, "rmse_3d_m": None, "rmse_horizontal_m": 0.97}
    check = next(c for c in assess(sfm, *rest) if c.item == "gcp_rmse")
    assert check.state == "red" and abs(check.value - 48.5) < 1e-9 and "horizontal" in check.detail


def test_a_stage_not_run_is_not_measured_and_a_missing_measurement_is_never_green():
    """An item a stage that did not run would measure (no GCPs, no dense stage) does not count; one
    every finished run measures (coverage, photos registered) missing is red: its report is
    missing or damaged (issue 76: report was GREEN with every stage report deleted)."""
    from geoortho.chain.quality import REQUIRED

    checks = assess(None, None, None, None, None)
    assert {c.state for c in checks if c.item not in REQUIRED} == {"not measured"}
    assert {c.state for c in checks if c.item in REQUIRED} == {"red"} and verdict(checks) == "red"
    # measured, the required items grade as their values say
    sfm, *rest = _clean()
    assert all(c.state != "red" for c in assess(sfm, *rest) if c.item in REQUIRED)


@pytest.mark.parametrize(
    ("key", "value"),
    [("share_of_seen_2", 1.7), ("share_of_seen_2", True), ("holes_inside_m2", -3.0), ("seam_mismatch_balanced", "5")],
)
def test_an_impossible_or_wrong_typed_value_is_never_graded_as_a_measure(key, value):
    """A share over 100 %, a negative area, a JSON true taken as 1, a number given as text: the
    stage report is damaged, and no item is green on it."""
    sfm, dense, dem, ortho, fp = _clean()
    ortho = {**ortho, key: value}
    item = {"share_of_seen_2": "ortho_coverage", "holes_inside_m2": "ortho_holes",
            "seam_mismatch_balanced": "seam_mismatch"}[key]  # fmt: skip
    check = next(c for c in assess(sfm, dense, dem, ortho, fp) if c.item == item)
    assert check.state != "green", check


@pytest.mark.parametrize("crs", ["EPSG:4979", "EPSG:3763", "EPSG:32629"])
def test_report_plots_gcps_in_the_products_crs_whatever_the_gcp_files(tiny_survey, tmp_path, crs):
    """GCPs given in EPSG:4326/4979 were drawn at (0, 0) of the UTM axes: every plotted GCP is in
    the products' CRS, from a GCP list in geographic, national-grid (PT-TM06) or UTM coordinates."""
    import numpy as np
    from pyproj import Transformer

    from geoortho.chain.report_accuracy import gcp_positions
    from geoortho.chain.report_base import ReportContext
    from geoortho.gcp.io import read_gcp_file

    truth = read_gcp_file(tiny_survey.truth / "gcp_utm.txt")
    to = Transformer.from_crs("EPSG:32629", crs, always_xy=True)
    lines = [crs]
    for p in truth.points:
        x, y = to.transform(p.x, p.y)
        # a geographic gcp list reads latitude first (as ours writes it)
        lines.append(f"{p.name} {y:.10f} {x:.10f} {p.z}" if crs == "EPSG:4979" else f"{p.name} {x:.4f} {y:.4f} {p.z}")
    gcp_list = tmp_path / "gcps.txt"
    gcp_list.write_text("\n".join(lines) + "\n")
    ledger = {
        "stages": {
            "sfm": {"status": "done", "values": {"gcp_list": str(gcp_list)}, "outputs": {}},
            "ortho": {"status": "done", "outputs": {"crs": "EPSG:32629"}},
        }
    }
    got = {n: (x, y) for n, x, y, _ in gcp_positions(ReportContext(tmp_path, ledger))}
    for p in truth.points:
        assert np.hypot(got[p.name][0] - p.x, got[p.name][1] - p.y) < 0.01, (crs, p.name)


def _sfm_quality(survey, out, **kw):
    import json

    from conftest import SFM_FAST

    import geoortho

    r = geoortho.sfm(survey.images, out, **SFM_FAST, **kw)
    report = json.loads(r.report.read_text())
    return report, {c.item: c for c in assess(report, None, None, None, None)}


@pytest.fixture(scope="module")
def found_gcps(tiny_survey, tmp_path_factory):
    """The tiny survey's GCPs found in its photos: a gcp_list.txt with pixel observations."""
    import geoortho

    out = tmp_path_factory.mktemp("found") / "gcp_list.txt"
    geoortho.gcp_find(tiny_survey.images, tiny_survey.gcp_file, out)
    return out


def _rewritten(found, dst, move):
    """``found`` with each line's coordinates passed through ``move(x, y, z, name) -> (x, y, z)``."""
    lines = found.read_text().splitlines()
    out = [lines[0]]
    for line in lines[1:]:
        f = line.split()
        x, y, z = move(float(f[0]), float(f[1]), float(f[2]), f[-1])
        out.append(" ".join([f"{x:.4f}", f"{y:.4f}", f"{z:.4f}", *f[3:]]))
    dst.write_text("\n".join(out) + "\n")
    return dst


def test_gcps_in_the_wrong_crs_are_red_and_the_crs_is_named(tiny_survey, found_gcps, tmp_path):
    """GCPs surveyed in ED50 / UTM 29N, their file saying WGS 84 / UTM 29N: 237 m apart at the site, too
    near to refuse, too far for a GPS bias. The GCPs fit each other perfectly (no residual says it);
    the shift against the GPS does, and names the CRS as the likely cause."""
    from pyproj import Transformer

    assert found_gcps.read_text().splitlines()[0].strip() == "EPSG:32629"
    to_ed50 = Transformer.from_crs("EPSG:32629", "EPSG:23029", always_xy=True)
    wrong = _rewritten(found_gcps, tmp_path / "ed50.txt", lambda x, y, z, _: (*to_ed50.transform(x, y), z))
    report, checks = _sfm_quality(tiny_survey, tmp_path / "sfm", gcp_list=wrong)
    effect = report["gcp_vs_gps"]
    assert 220.0 < effect["shift_horizontal_m"] < 255.0  # 237 m: the two datums' difference at Lisbon
    assert checks["gcp_shift"].state == "red" and "CRS" in checks["gcp_shift"].detail
    assert checks["gcp_rmse"].state == "green"  # the GCPs agree with each other: only the shift tells
    assert any("CRS" in n and "237 m" in n for n in report["notes"]), report["notes"]


def test_a_swapped_pair_of_gcps_is_named(tiny_survey, found_gcps, tmp_path):
    """Two GCPs' names exchanged in the file (4 GCPs): controlled by them the model turned 180 deg.
    The pair is named, held out as checkpoints (red), and the model stays on the GPS."""
    from geoortho.gcp.io import read_gcp_file

    points = read_gcp_file(tiny_survey.gcp_file).points
    a, b = points[0], points[-1]
    found = read_gcp_file(found_gcps)
    where = {p.name: (p.x, p.y, p.z) for p in found.points}
    swap = {a.name: where[b.name], b.name: where[a.name]}
    swapped = _rewritten(found_gcps, tmp_path / "swapped.txt", lambda x, y, z, n: swap.get(n, (x, y, z)))
    report, checks = _sfm_quality(tiny_survey, tmp_path / "sfm", gcp_list=swapped)
    assert sorted(report["gcp_vs_gps"]["swapped"]["names"]) == sorted([a.name, b.name])
    assert checks["checkpoint_rmse"].state == "red"
    assert any("swapped" in n for n in report["notes"]) and "swapped" in checks["gcp_rmse"].detail
    assert report["georeferenced_by"].startswith("GPS")  # 2 control GCPs left: not enough to control


def test_gcps_with_a_5_percent_scale_error_are_red_with_their_effect(tiny_survey, tmp_path):
    """GCP coordinates scaled 5 % about their middle (a wrong unit or CRS): the GCPs rescale the GPS
    georeference by about that, and the quality check says so in red."""
    import numpy as np

    import geoortho
    from geoortho.gcp.io import read_gcp_file

    found = geoortho.gcp_find(tiny_survey.images, tiny_survey.gcp_file, tmp_path / "gcp_list.txt")
    gcps = read_gcp_file(found.output)
    mid = np.mean([[p.x, p.y] for p in gcps.points], axis=0)
    lines = (tmp_path / "gcp_list.txt").read_text().splitlines()
    out = [lines[0]]
    for line in lines[1:]:
        f = line.split()
        x, y = mid + 1.05 * (np.array([float(f[0]), float(f[1])]) - mid)
        out.append(" ".join([f"{x:.4f}", f"{y:.4f}", *f[2:]]))
    scaled = tmp_path / "scaled.txt"
    scaled.write_text("\n".join(out) + "\n")
    report, checks = _sfm_quality(tiny_survey, tmp_path / "sfm", gcp_list=scaled)
    assert 4.0 < report["gcp_vs_gps"]["scale_change_pct"] < 6.0
    assert checks["gcp_scale"].state == "red" and "edge" in checks["gcp_scale"].detail
    assert any("rescaled" in n for n in report["notes"])


def test_a_poor_gps_is_red_when_it_alone_georeferences(tmp_path):
    """A consumer GPS off by 20 m a photo, no GCPs: the products are only as good as the GPS, and the
    check says how good that is (CE90 measured against the photos' geometry)."""
    import geoortho

    s = geoortho.synth(tmp_path / "survey", preset="tiny", seed=6, pathology="poor-gps")
    # on a 32 m block, fixes 20 m off fit no similarity at the GPS's default 2 m: refused, loudly
    with pytest.raises(geoortho.InputError, match="could not be georeferenced"):
        _sfm_quality(s, tmp_path / "refused")
    report, checks = _sfm_quality(s, tmp_path / "sfm", gps_sigma_m=20.0)  # the GPS's sigma given
    assert report["georeferenced_by"].startswith("GPS") and report["gps"]["ce90_m"] > 15
    assert checks["gps_fit"].state == "red" and "rotation ±" in checks["gps_fit"].detail


@pytest.mark.parametrize("seed", [1, 2])
def test_a_dropped_photo_is_red_and_named_with_its_cause(tmp_path, seed):
    """One photo no SfM can register, spoiled one of two ways (smeared by motion, blown out): the
    check names it and why, whichever way it was spoiled."""
    import json

    import geoortho

    s = geoortho.synth(tmp_path / "survey", preset="tiny", seed=seed, pathology="dropped-photo")
    dropped = json.loads((s.truth / "survey.json").read_text())["dropped_photo"]
    assert dropped["how"] == {1: "smeared", 2: "blown out"}[seed]  # both renderings are pinned
    report, checks = _sfm_quality(s, tmp_path / "sfm")
    assert list(report["unregistered"]) == [dropped["image"]]
    assert report["registered"] == report["photos"] - 1
    check = checks["photos_registered"]
    assert check.state == "red" and dropped["image"] in check.detail and "few features" in check.detail


def test_a_failed_submodel_is_named_with_the_ground_it_leaves_out():
    """A split run's failed submodel: its photos are not registered, their ground is in no product,
    and the check says which submodel and how much, whatever share of the photos it held."""
    sfm, dense, dem, ortho, fp = _clean()
    sfm.update(registered=49, unregistered={"A.JPG": "submodel 3 failed: no model could be built"})
    fp.update(n_left_out=1, area_left_out_m2=900.0, area_seen_m2=1.2e4)
    (check,) = [c for c in assess(sfm, dense, dem, ortho, fp) if c.item == "ground_left_out"]
    assert check.state == "red" and check.value == pytest.approx(7.5)
    assert check.detail.startswith("submodel 3 failed") and "900 m² of 12,000 m²" in check.detail
    assert "left_out" in check.detail
    # a damaged footprints record without the count still says the area, and grades it
    del fp["n_left_out"]
    (check,) = [c for c in assess(sfm, dense, dem, ortho, fp) if c.item == "ground_left_out"]
    assert check.state == "red" and "900 m² of 12,000 m², seen by photos left out" in check.detail
