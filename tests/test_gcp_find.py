"""GCP finder against the synthetic truth (markers.json) and on real ArUco photos."""

from __future__ import annotations

import csv
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import real_data
from pyproj import CRS

from geoortho.gcp import read_gcp_file
from geoortho.gcp.detect import diagonal_intersection, marker_centre
from geoortho.gcp.find import gcp_find


def _score(survey, gcp_list) -> dict:
    truth = {
        m["image"]: {mm["gcp"]: mm for mm in m["markers"]}
        for m in json.loads((survey.truth / "markers.json").read_text())
    }
    rows = [ln.split() for ln in gcp_list.read_text().splitlines()[1:]]
    errors, wrong, found = [], 0, set()
    for r in rows:
        t = truth[r[5]].get(r[6])
        if t is None or t["decoy"]:
            wrong += 1
            continue
        e = float(np.hypot(float(r[3]) - t["x_px"], float(r[4]) - t["y_px"]))
        errors.append(e)
        wrong += e > 3.0
        found.add((r[5], r[6]))
    visible = {
        (i, g) for i, ms in truth.items() for g, m in ms.items() if m["inside"] and not m["decoy"] and not m["occluded"]
    }
    return {
        "written": len(rows),
        "precision": (len(rows) - wrong) / max(1, len(rows)),
        "recall": len(found & visible) / max(1, len(visible)),
        "n_visible": len(visible),
        "mean_error_px": float(np.mean(errors)) if errors else np.nan,
    }


def test_small_precision_recall_and_centre_error(small_survey, tmp_path):
    out = tmp_path / "gcp_list.txt"
    r = gcp_find(
        small_survey.images, small_survey.gcp_file, out, detections=tmp_path / "det.csv", review=tmp_path / "review.png"
    )
    s = _score(small_survey, out)
    assert s["n_visible"] >= 40
    assert s["precision"] == 1.0
    assert s["recall"] >= 0.98
    assert s["mean_error_px"] <= 0.1  # issue target 0.3; measured 0.03 with contour-refined corners
    assert r.n_observations == s["written"]
    # gcp_list.txt reads back as ODM's format with the file's coordinates
    lines = out.read_text().splitlines()
    assert lines[0] == "EPSG:32629"
    back = read_gcp_file(out).by_name()
    src = read_gcp_file(small_survey.gcp_file).by_name()
    for name, p in back.items():
        assert (p.x, p.y, p.z) == pytest.approx((src[name].x, src[name].y, src[name].z), abs=1e-4)
    assert all(len(ln.split()) == 7 for ln in lines[1:])
    # the detections table accounts for every candidate
    rows = list(csv.DictReader((tmp_path / "det.csv").open()))
    assert sum(r_["status"] == "detected" for r_ in rows) == r.n_observations
    import cv2

    sheet = cv2.imread(str(r.review))
    assert sheet is not None and sheet.shape[1] == 8 * 128
    assert sheet.shape[0] == -(-r.n_observations // 8) * (128 + 18)


def test_flight_offset_is_measured_and_windows_follow_it(small_survey, tmp_path):
    """GCP coordinates 3 m east and 2 m south of the markers look to the finder like a GPS bias
    of (−3, +2) m on top of the real one: the pilot photos must measure it, and the narrow
    windows placed with it must still find everything."""
    from pyproj import Transformer

    poses = json.loads((small_survey.truth / "poses.json").read_text())
    to_utm = Transformer.from_crs("EPSG:4326", "EPSG:32629", always_xy=True)
    gps_bias_m = np.mean(
        [
            np.subtract(
                to_utm.transform(p["recorded"]["longitude_deg"], p["recorded"]["latitude_deg"]), (p["x"], p["y"])
            )
            for p in poses
            if p["has_gps"]
        ],
        axis=0,
    )
    lines = small_survey.gcp_file.read_text().splitlines()
    moved = [lines[0]]
    for ln in lines[1:]:
        name, x, y, z = ln.split()
        moved.append(f"{name} {float(x) + 3.0:.4f} {float(y) - 2.0:.4f} {z}")
    gcps = tmp_path / "moved.txt"
    gcps.write_text("\n".join(moved) + "\n")
    out = tmp_path / "gcp_list.txt"
    r = gcp_find(small_survey.images, gcps, out)
    assert r.flight_offset_m is not None
    assert np.hypot(*(np.array(r.flight_offset_m) - (gps_bias_m - [3.0, -2.0]))) < 0.75
    s = _score(small_survey, out)
    assert s["precision"] == 1.0 and s["recall"] >= 0.98


def test_the_pilot_reads_by_the_fast_attempt_alone_where_that_measures_the_offset(small_survey, tmp_path, monkeypatch):
    """The flight's offset needs a few markers in more than one photo: the detector's cheapest read
    ("fast") in twice the pilot photos gives them on a clean survey, so no other attempt runs in
    a window sized for the stated uncertainty (a blurred photo's blur undone there cost a
    degraded flight's pilot four times as much); everything is still found."""
    from geoortho.gcp import detect, pilot

    tried: list[str] = []
    run = detect._run
    monkeypatch.setattr(
        detect, "_run", lambda gray, attempt, *a, **kw: tried.append(attempt) or run(gray, attempt, *a, **kw)
    )
    before_offset: list[list[str]] = []
    offset = pilot._flight_offset

    def measured(*a, **kw):
        got = offset(*a, **kw)
        if got is not None and not before_offset:
            before_offset.append(list(tried))
        return got

    monkeypatch.setattr(pilot, "_flight_offset", measured)
    r = gcp_find(small_survey.images, small_survey.gcp_file, tmp_path / "gcp_list.txt", workers=1)
    assert before_offset and before_offset[0] and set(before_offset[0]) == {"fast"}
    assert set(tried) - {"fast"}  # the other attempts still run, later, in the narrowed windows
    s = _score(small_survey, r.output)
    assert s["precision"] == 1.0 and s["recall"] >= 0.98, s


def test_where_the_fast_attempt_reads_nothing_the_pilot_tries_every_attempt(tiny_survey, tmp_path, monkeypatch):
    """No marker read by the fast attempt (a blurred flight): the pilot photos are searched with
    every attempt, and the offset is measured from those."""
    from geoortho.gcp import detect

    run = detect._run
    monkeypatch.setattr(
        detect, "_run", lambda gray, attempt, *a, **kw: [] if attempt == "fast" else run(gray, attempt, *a, **kw)
    )
    r = gcp_find(tiny_survey.images, tiny_survey.truth / "gcp_wgs84.csv", tmp_path / "gcp_list.txt", workers=1)
    assert r.flight_offset_m is not None
    s = _score(tiny_survey, r.output)
    assert s["precision"] == 1.0 and s["recall"] >= 0.98, s


def test_hard_preset(hard_survey, tmp_path):
    out = tmp_path / "gcp_list.txt"
    gcp_find(hard_survey.images, hard_survey.truth / "gcp_wgs84.txt", out)
    s = _score(hard_survey, out)
    assert s["precision"] == 1.0
    assert s["recall"] >= 0.90
    # a geographic GCP file is written in the photos' UTM zone
    assert out.read_text().splitlines()[0] == "EPSG:32629"


def test_swapped_coordinates_are_never_written(tiny_survey, tmp_path):
    """Two GCPs with each other's coordinates: the markers are where the other is predicted.
    Nothing wrong may be written; the rest is unaffected."""
    lines = (tiny_survey.gcp_file).read_text().splitlines()
    rows = [ln.split() for ln in lines[1:]]
    a, b = rows[0], rows[1]
    a[1:], b[1:] = b[1:], a[1:]
    bad = tmp_path / "swapped.txt"
    bad.write_text("\n".join([lines[0]] + [" ".join(r) for r in rows]) + "\n")
    out = tmp_path / "gcp_list.txt"
    gcp_find(
        tiny_survey.images, bad, out, position_uncertainty_m=1.0, height_uncertainty_m=1.0, attitude_uncertainty_deg=1.0
    )
    written = [ln.split() for ln in out.read_text().splitlines()[1:]]
    assert not [w for w in written if w[6] in (a[0], b[0])]
    assert written  # the others are still found


def test_tiny_everything_found(tiny_survey, tmp_path):
    out = tmp_path / "gcp_list.txt"
    gcp_find(tiny_survey.images, tiny_survey.truth / "gcp_wgs84.csv", out, workers=1)
    s = _score(tiny_survey, out)
    assert s["precision"] == 1.0 and s["recall"] >= 0.98


def test_a_wrong_dictionary_is_answered_by_the_photos(tiny_survey, tmp_path):
    """No marker decodes as the dictionary given (5x5; these are 4x4): the one they decode in
    where predicted is searched instead, said with the option to give; before, nothing was
    found and the warning was only that."""
    from conftest import RecordingFeedback

    fb = RecordingFeedback()
    r = gcp_find(
        tiny_survey.images, tiny_survey.gcp_file, tmp_path / "gcp_list.txt", dictionary="DICT_5X5_50", feedback=fb
    )
    assert r.dictionary == "DICT_4X4_50"
    assert any("no marker decodes as DICT_5X5_50" in w and "--dictionary DICT_4X4_50" in w for w in fb.warnings)
    s = _score(tiny_survey, r.output)
    assert s["precision"] == 1.0 and s["recall"] >= 0.98, s


def test_real_findgcp_photos_without_gps_match_upstream(tmp_path):
    folder = real_data("findgcp_aruco")
    out = tmp_path / "gcp_list.txt"
    # a local frame: any projected CRS carries it through unchanged
    gcp_find(
        folder / "images", folder / "coords" / "aruco.txt", out, dictionary="DICT_4X4_100", gcp_crs=CRS("EPSG:3857")
    )
    ours = {(r[5], r[6]): (float(r[3]), float(r[4])) for r in (ln.split() for ln in out.read_text().splitlines()[1:])}
    coords = {p.name: (p.x, p.y, p.z) for p in read_gcp_file(folder / "coords" / "aruco.txt", "EPSG:3857").points}
    name_of = {v: k for k, v in coords.items()}
    upstream = {}
    for ln in (folder / "coords" / "expected_gcp_find_output_from_upstream_README.txt").read_text().splitlines():
        if ln.startswith("#") or not ln.strip():
            continue
        f = ln.split()
        upstream[(f[5], name_of[(float(f[0]), float(f[1]), float(f[2]))])] = (float(f[3]), float(f[4]))
    assert set(ours) == set(upstream)  # the same 11 observations, no more
    # upstream truncates the mean of whole-pixel corners; ours is the diagonal intersection of
    # sub-pixel corners, up to 1 px apart on these strongly tilted 47 px markers
    for k, (x, y) in upstream.items():
        assert abs(ours[k][0] - x) <= 2.5 and abs(ours[k][1] - y) <= 2.5, k


def test_marker_centre_follows_the_diagonals_under_perspective():
    # a square seen in perspective: the projected centre is not the mean of the corners
    from geoortho.core.camera import Intrinsics, Pose, project_points

    intr = Intrinsics(1000, 800, 800.0)
    square = np.array([[-1, 1, 0], [1, 1, 0], [1, -1, 0], [-1, -1, 0], [0, 0, 0]], float)
    strong = Pose.from_ypr((0, -8, 6), 0, -30, 0)
    px, _ = project_points(square, intr, strong)
    assert np.allclose(diagonal_intersection(px[:4]), px[4], atol=1e-9)
    assert np.hypot(*(px[:4].mean(axis=0) - px[4])) > 0.8
    assert np.allclose(marker_centre(px[:4]), px[4], atol=1e-9)  # strong perspective: diagonals
    nadir = Pose.from_ypr((0.3, 0.2, 40), 0, -90, 0)
    px, _ = project_points(square, intr, nadir)
    assert np.allclose(marker_centre(px[:4]), px[:4].mean(axis=0))  # no perspective: the mean


def test_cli_bad_gcp_file_exit_2(tmp_path, tiny_survey):
    bad = tmp_path / "g.txt"
    bad.write_text("EPSG:32629\nGCP1 1 2 x\n")
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "geoortho",
            "gcp-find",
            "--images",
            str(tiny_survey.images),
            "--gcp-file",
            str(bad),
            "--output",
            str(tmp_path / "o.txt"),
        ],
        capture_output=True,
        text=True,
    )
    assert r.returncode == 2
    assert r.stderr.strip().splitlines() == [r.stderr.strip()] and f"{bad}:2:" in r.stderr


@pytest.mark.parametrize(
    "how, hint",
    [
        ("zone", "the file's CRS looks wrong"),
        ("swapped", "the columns look swapped"),
        ("far", "the nearest is 0.3 km from the flight"),
    ],
)
def test_no_gcp_in_any_photo_says_why(tiny_survey, tmp_path, how, hint):
    """Issue 23 (6): a GCP file with no GCP in any photo ended in 'weights must sum to a positive
    number'. Now one line: how far the nearest is, both CRSs, and the likely cause when found."""
    from geoortho.errors import InputError

    lines = tiny_survey.gcp_file.read_text().splitlines()
    rows = [ln.split() for ln in lines[1:] if ln.strip()]
    if how == "zone":
        text = ["EPSG:32617"] + [" ".join(r) for r in rows]
    elif how == "swapped":
        text = [lines[0]] + [f"{r[0]} {r[2]} {r[1]} {r[3]}" for r in rows]
    else:
        text = [lines[0]] + [f"{r[0]} {float(r[1]) + 300:.3f} {r[2]} {r[3]}" for r in rows]
    bad = tmp_path / "gcps.txt"
    bad.write_text("\n".join(text) + "\n")
    with pytest.raises(InputError) as e:
        gcp_find(tiny_survey.images, bad, tmp_path / "gcp_list.txt")
    msg = str(e.value)
    assert "none of the" in msg and "gcps.txt" in msg and hint in msg and "EPSG:32629" in msg, msg
    assert not (tmp_path / "gcp_list.txt").exists()


def test_opencv_refinement_assertion_does_not_end_the_run():
    """A window of the real toledo DJI_0091.JPG on which OpenCV's contour corner refinement
    asserts ("nContours.size() >= 2") in the glare attempt: it used to end gcp-find with an
    unexpected error; now the attempt falls back to sub-pixel corner refinement."""
    from geoortho.gcp.detect import _run
    from geoortho.photos.metadata import decode_photo

    gray = decode_photo(str(real_data("toledo_dji") / "images" / "DJI_0091.JPG"), grey=True)
    crop = gray[1251 : 1251 + 362, 800 : 800 + 361]
    hits = _run(crop, "glare", "DICT_4X4_50", 11.72)
    assert all(c.shape == (4, 2) for _, c in hits)


@pytest.mark.parametrize("dictionary", ["DICT_APRILTAG_36H11", "DICT_APRILTAG_16H5"])
def test_apriltag_dictionaries_like_aruco(tmp_path, dictionary):
    """Issue 26: AprilTag surveys found as exactly as ArUco ones. 16h5 (ids 5 bits apart) decoded
    texture beside a real tag as a skewed quad 200 px off (precision 0.92): decodes must be shaped
    like the marker the window expects. Measured: 36h11 17/17 at 0.035 px, 16h5 12/12 at 0.047 px."""
    from geoortho.synthetic.survey import synth

    s = synth(tmp_path / "s", preset="tiny", seed=3, target="apriltag", dictionary=dictionary, workers=2)
    out = tmp_path / "gcp_list.txt"
    gcp_find(s.images, s.truth / "gcp_wgs84.csv", out, dictionary=dictionary, target="apriltag", workers=2)
    score = _score(s, out)
    assert score["n_visible"] >= 10
    assert score["precision"] == 1.0 and score["recall"] >= 0.98, score
    assert score["mean_error_px"] <= 0.1, score


def test_id_scores_without_rendering_every_id_equal_the_rendered_ones():
    """The id margin's correlations by dot products equal those of every id rendered (2,320 ids x 4
    turns for AprilTag 36h10: 8 s per fit rendered)."""
    from geoortho.gcp.look import Renderer, coded_patterns, masked_ncc_score
    from geoortho.gcp.markers import coded_cells_at, marker_cells

    cells = marker_cells("DICT_APRILTAG_25H9", 7)
    ys, xs = np.mgrid[0:40, 0:40]
    rend = Renderer("apriltag", cells, xs, ys)
    rng = np.random.default_rng(0)
    A = np.array([[22.0, 3.0], [-2.0, -21.0]])
    img = rng.uniform(0, 255, xs.size)
    w = rng.uniform(0, 1, xs.size)
    pats = coded_patterns("DICT_APRILTAG_25H9")
    fast = rend.ncc_ids(img, w, 19.3, 20.1, A, 4.0, 30.0, 0.5, pats)
    # every id rendered: a pixel is the mean of its samples, white in the quiet zone, 0 off the board
    u, v = rend.uv(19.3, 20.1, A, 4.0, 30.0, 0.5)
    board, inside, idx = coded_cells_at(u, v, pats.shape[1])
    flat = pats.reshape(len(pats), -1).astype(float)
    rendered = np.where(board[None], np.where(inside[None], flat[:, idx], 1.0), 0.0).sum(axis=2)
    rendered /= np.maximum(board.sum(axis=1), 1)[None]
    plain = [masked_ncc_score(img, t, w) for t in rendered]
    np.testing.assert_allclose(fast, plain, atol=1e-9)


def _photo_with_markers(placed: dict[int, tuple[int, int]], side_px: int = 24) -> np.ndarray:
    """A grey 600 x 400 photo with DICT_4X4_50 markers (id -> top-left pixel) on white boards."""
    import cv2

    from geoortho.gcp.markers import get_dictionary

    gray = np.full((400, 600), 110, np.uint8)
    for marker_id, (x, y) in placed.items():
        board = np.full((side_px * 2, side_px * 2), 255, np.uint8)
        marker = cv2.aruco.generateImageMarker(get_dictionary("DICT_4X4_50"), marker_id, side_px)
        board[side_px // 2 : side_px // 2 + side_px, side_px // 2 : side_px // 2 + side_px] = marker
        gray[y - side_px // 2 : y + side_px + side_px // 2, x - side_px // 2 : x + side_px + side_px // 2] = board
    return gray


def test_the_wide_window_is_searched_last_and_only_where_the_photo_does_not_place_the_marker(monkeypatch):
    """A marker 60 px from its prediction (a pose off by more than the measured residual) is found
    in the wide window, searched by the detector after the fit in the marker's own window (in the
    first pass, which does not fit, not at all: the second look fits, then searches it). Where two
    markers of the photo place it inside its window, the wide one is not searched (on degraded
    surveys 122 wide searches decoded nothing). A coded marker's wide window is the detector's, in
    a smeared photo too: never fitted."""
    import cv2

    from geoortho.gcp import detect
    from geoortho.gcp.blur import motion_kernel

    def window(gcp: str, marker_id: int, x: float, y: float) -> detect.SearchWindow:
        return detect.SearchWindow(
            gcp, marker_id, x, y, radius_px=30.0, side_px=24.0, wide_radius_px=120.0, ground_px=(24.0, 0.0, 0.0, -24.0)
        )

    done: list[tuple[str, int, int]] = []  # (what, marker id, square's width), in order
    search, fit = detect._search, detect._fit

    def counting(gray, box, win, *args, **kwargs):
        done.append(("search", win.marker_id, box[2] - box[0]))
        return search(gray, box, win, *args, **kwargs)

    def counting_fits(gray, win, k, box, *args, **kwargs):
        done.append(("fit", win.marker_id, box[2] - box[0]))
        return fit(gray, win, k, box, *args, **kwargs)

    monkeypatch.setattr(detect, "_search", counting)
    monkeypatch.setattr(detect, "_fit", counting_fits)
    # one marker, predicted 60 px off (both ways): not in the first pass's squares
    gray = _photo_with_markers({7: (300, 200)})
    wins = [window("G7", 7, 372.0, 212.0)]
    dets = detect.detect_in_image(gray, wins, "DICT_4X4_50", fit=False)
    assert not [d for d in dets if d.marker_id == 7] and done == [("search", 7, 61)]
    # fitted in its own window first (nothing there), then found by the detector in the wide one
    done.clear()
    dets = detect.detect_in_image(gray, wins, "DICT_4X4_50")
    found = [d for d in dets if d.marker_id == 7 and not d.reason]
    assert found and abs(found[0].x_px - 312) < 1 and abs(found[0].y_px - 212) < 1
    assert done == [("search", 7, 61), ("fit", 7, 61), ("search", 7, 241)]  # the wide square: 2 x 120 px
    # the second look's order is the same: the fits, then the wide window
    done.clear()
    dets = detect.search_wide(
        gray, wins, detect.fit_missed(gray, wins, [], [0], "aruco", "DICT_4X4_50", None), [0], "DICT_4X4_50", None
    )
    assert [d.marker_id for d in dets if not d.reason] == [7] and done == [("fit", 7, 61), ("search", 7, 241)]
    # two markers found where predicted place the third where predicted: it is not in its window
    # (its paint is elsewhere: a GCP whose coordinates are off), and the wide window is not searched
    done.clear()
    gray = _photo_with_markers({1: (100, 100), 2: (450, 300), 7: (300, 100)})
    wins = [window("G1", 1, 112.0, 112.0), window("G2", 2, 462.0, 312.0), window("G7", 7, 312.0, 300.0)]
    dets = detect.detect_in_image(gray, wins, "DICT_4X4_50")
    assert {d.marker_id for d in dets if not d.reason} == {1, 2}
    assert ("search", 7, 61) in done and ("search", 7, 241) not in done
    # a smeared photo: its wide window too is searched by the detector (its attempts there: the
    # fast one and the blur undone), never fitted
    done.clear()
    gray = _photo_with_markers({7: (300, 200)})
    blurred = cv2.filter2D(gray, -1, motion_kernel(12.0, 0.0))
    wins = [window("G7", 7, 372.0, 212.0), window("G9", 9, 200.0, 300.0)]  # G9: not in the photo
    dets = detect.detect_in_image(blurred, wins, "DICT_4X4_50", blur=(12.0, 0.0))
    assert ("search", 7, 241) in done and ("search", 9, 241) in done
    assert [d.attempt for d in dets if d.marker_id == 7 and not d.reason] == ["deblur"]
    assert [(mid, width) for what, mid, width in done if what == "fit"] == [(7, 61), (9, 61)]  # own windows only


def test_a_marker_missed_at_the_edge_of_a_sharp_photo_is_fitted_only_under_glare(monkeypatch):
    """A coded marker the detector missed, predicted within half a side of a sharp photo's edge, is
    a marker cut by the frame unless glare hid it: fitted only where saturated pixels cover a tenth
    of a marker's area in its window, not for a few clipped ones (a clean flight's one such fit held
    a worker 0.6 s to refuse it as cut). In a blurred photo it is fitted whatever the glare."""
    from geoortho.gcp import detect

    fitted: list[int] = []
    monkeypatch.setattr(detect, "_fit_model", lambda gray, win, k, *a, **kw: fitted.append(win.marker_id))
    gray = np.full((400, 600), 110, np.uint8)
    win = detect.SearchWindow("G7", 7, 300.0, 4.0, radius_px=30.0, side_px=24.0, ground_px=(24.0, 0.0, 0.0, -24.0))
    gray[10:12, 300:303] = 255  # six clipped pixels
    detect.fit_missed(gray, [win], [], [0], "aruco", "DICT_4X4_50", (0.0, 0.0))
    assert fitted == []
    gray[10:20, 280:290] = 255  # a glare spot of 100 pixels: a sixth of the marker's area
    detect.fit_missed(gray, [win], [], [0], "aruco", "DICT_4X4_50", (0.0, 0.0))
    assert fitted == [7]
    fitted.clear()
    gray[:] = 110
    detect.fit_missed(gray, [win], [], [0], "aruco", "DICT_4X4_50", (6.0, 0.0))
    assert fitted == [7]


def test_a_photo_is_looked_at_again_for_a_marker_predicted_just_beyond_its_edge(monkeypatch):
    """The second look fits a photo's missed markers once every photo is searched. A photo whose
    markers in the frame were all decoded, and whose missed one is predicted just beyond its edge
    (within two marker sides: the prediction errs by that much), is looked at again; where the
    missed one is predicted further out, or every marker was decoded, it is not. Ground is carried
    from another photo only to a marker predicted in the frame."""
    from types import SimpleNamespace

    from geoortho.gcp import pilot
    from geoortho.gcp.detect import Detection, SearchWindow

    cam = SimpleNamespace(
        photo=SimpleNamespace(width_px=1600, height_px=1067), pose=SimpleNamespace(center=np.zeros(3))
    )
    ground = (16.0, 0.0, 0.0, -16.0)

    def window(gcp: str, marker_id: int, x: float, y: float) -> SearchWindow:
        return SearchWindow(gcp, marker_id, x, y, 40.0, side_px=16.0, ground_px=ground)

    def looked_at(y_missed: float) -> list[tuple[str, list]]:
        windows = {
            "a.JPG": [window("GCP01", 1, 400.0, 600.0), window("GCP02", 2, 300.0, y_missed)],
            "b.JPG": [window("GCP02", 2, 500.0, 500.0)],
        }
        results = [
            ("/x/a.JPG", [Detection(1, 401.0, 601.0, (), "deblur", 0, 16.0)], "", (4.0, 0.0)),
            ("/x/b.JPG", [Detection(2, 502.0, 499.0, ((494.0, 491.0),) * 4, "fast", 0, 16.0)], "", (0.0, 0.0)),
        ]
        asked: list[tuple[str, list]] = []

        def second_looks(task, items, **kwargs):
            asked.extend((Path(item[0]).name, item[3]) for item in items)
            return [(item[0], item[2]) for item in items]

        monkeypatch.setattr(pilot, "map_ordered", second_looks)
        pilot.second_look(
            results, windows, SimpleNamespace(cams={"a.JPG": cam, "b.JPG": cam}), "DICT_4X4_50", "aruco", None, 1
        )
        return asked

    assert looked_at(1080.0) == [("a.JPG", [])]  # 13 px beyond the edge: fitted, nothing carried
    assert looked_at(1120.0) == []  # 53 px beyond: out of view
    ((image, jobs),) = looked_at(1000.0)  # in the frame: ground carried from b.JPG
    assert image == "a.JPG" and [(k, Path(donor).name) for k, donor, *_ in jobs] == [(1, "b.JPG")]
