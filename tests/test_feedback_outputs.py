from __future__ import annotations

import io
import json

import numpy as np
import pytest
from conftest import RecordingFeedback

from geoortho.core.outputs import atomic_path, write_cog, write_json
from geoortho.errors import CanceledError, InputError
from geoortho.feedback import JsonLinesFeedback, split, track


def test_split_maps_substeps_onto_weighted_ranges():
    fb = RecordingFeedback()
    a, b = split(fb, [1, 3])
    a.progress(1.0)
    b.progress(0.5)
    b.progress(1.0)
    assert fb.values == pytest.approx([0.25, 0.625, 1.0])


def test_cancel_raises_from_progress_even_in_substeps():
    fb = RecordingFeedback()
    (a,) = split(fb, [1])
    fb.cancel()
    with pytest.raises(CanceledError):
        a.progress(0.1)
    with pytest.raises(CanceledError):
        list(track(range(3), fb))


def test_json_lines_feedback():
    s = io.StringIO()
    fb = JsonLinesFeedback(s)
    fb.progress(0.5)
    fb.warning("careful")
    lines = [json.loads(x) for x in s.getvalue().splitlines()]
    assert lines == [{"progress": 0.5}, {"warning": "careful"}]


def test_input_error_names_file_and_line():
    e = InputError("too few columns", path="gcps.txt", line=7)
    assert str(e) == "gcps.txt:7: too few columns" and isinstance(e, ValueError)


def test_atomic_path_leaves_nothing_on_failure(tmp_path):
    target = tmp_path / "out.txt"
    with pytest.raises(RuntimeError):
        with atomic_path(target) as tmp:
            tmp.write_text("half")
            raise RuntimeError("interrupted")
    assert list(tmp_path.iterdir()) == []
    with atomic_path(target) as tmp:
        tmp.write_text("whole")
    assert target.read_text() == "whole" and len(list(tmp_path.iterdir())) == 1


def test_write_cog_is_a_cog_with_crs_and_nodata(tmp_path):
    import rasterio
    from affine import Affine

    arr = np.arange(1500 * 1300, dtype=np.float32).reshape(1300, 1500)  # > one 512 block: overviews
    arr[:10, :10] = -9999
    path = write_cog(
        tmp_path / "a.tif", arr, transform=Affine(0.5, 0, 1000, 0, -0.5, 2000), crs="EPSG:32629", nodata=-9999.0
    )
    with rasterio.open(path) as ds:
        assert ds.crs.to_epsg() == 32629 and ds.nodata == -9999.0
        assert ds.tags(ns="IMAGE_STRUCTURE").get("LAYOUT") == "COG"
        assert ds.overviews(1)
        np.testing.assert_array_equal(ds.read(1), arr)


@pytest.mark.parametrize("ext", [".gpkg", ".geojson", ".shp", ".fgb", ".csv", ".kml", ".gml"])
def test_every_offered_vector_format_is_whole_under_its_final_name(tmp_path, ext):
    """Issue 23 (2): a Shapefile's .dbf/.shx/.prj/.cpg stayed under the temporary name (GDAL could
    not open the result), CSV failed, KML layers were named after the temporary file."""
    import geopandas as gpd
    import pyogrio
    import shapely

    from geoortho.core.outputs import write_vector
    from geoortho.core.styles import product_styles

    g = gpd.GeoDataFrame(
        {"image": ["a", "b"]}, geometry=[shapely.box(0, 0, 1, 1), shapely.box(1, 1, 2, 3)], crs="EPSG:32629"
    )
    styles = product_styles("footprints", "cameras")
    p = write_vector(tmp_path / f"fp{ext}", {"footprints": g, "cameras": g}, styles=styles)
    back = gpd.read_file(p, layer=0).sort_values("image")
    back = back.set_crs("EPSG:32629") if back.crs is None else back.to_crs("EPSG:32629")  # CSV: no CRS; KML: lon/lat
    assert list(back["image"]) == ["a", "b"] and back.geometry.area.round(3).tolist() == [1.0, 2.0]
    assert not [x.name for x in tmp_path.iterdir() if ".tmp-" in x.name]
    names = pyogrio.list_layers(p)[:, 0].tolist()
    assert names[0] in ("footprints", "fp")
    if ext == ".gpkg":  # each layer's QGIS style as its default, where QGIS reads it (issue 77)
        rows = pyogrio.read_dataframe(p, layer="layer_styles")
        assert dict(zip(rows["f_table_name"], rows["styleQML"])) == styles and rows["useAsDefault"].all()
        assert "#377eb8"[1:] not in styles["cameras"] and "55,126,184" in styles["footprints"]


def test_a_dead_runs_temporaries_are_removed_at_the_next_start_a_live_runs_kept(tiny_survey, tmp_path):
    """Issue 23 (8): a SIGKILLed ortho left .o.tif-*/mosaic.tif (12 MB) that reruns never cleaned."""
    import os

    from geoortho.processing import run_algorithm

    dead = 2**22 + 12345  # above Linux's default pid_max: no such process
    stale_dir = tmp_path / f".o.tif.tmp-{dead}-abc"
    stale_dir.mkdir()
    (stale_dir / "mosaic.tif").write_bytes(b"\0" * 1000)
    stale_file = tmp_path / f".fp.tmp-{dead}-xyz.gpkg"
    stale_file.write_bytes(b"half")
    live = tmp_path / f".other.tmp-{os.getpid()}-q.tif"  # a run still going (here: this one)
    live.write_bytes(b"busy")
    run_algorithm("footprints", {"images": tiny_survey.images, "output": tmp_path / "fp.gpkg"})
    assert not stale_dir.exists() and not stale_file.exists() and live.exists()
    assert (tmp_path / "fp.gpkg").is_file()


def test_without_a_terminal_each_stage_is_a_line_and_a_long_one_a_heartbeat(monkeypatch):
    """stderr to a log file: no bar, but a line as each stage starts and one a minute while it runs
    (a 30-minute SfM said nothing); --quiet: none."""
    import io

    from geoortho.feedback import TerminalFeedback

    log = io.StringIO()
    fb = TerminalFeedback("run", stream=log)
    fb.stage("sfm", 3, 7, 0.2, 0.5)
    fb.progress(0.3)  # within the minute: nothing more
    monkeypatch.setattr(TerminalFeedback, "HEARTBEAT_S", 0.0)
    fb.progress(0.45)
    lines = log.getvalue().splitlines()
    assert lines[0].startswith("run [3/7] sfm: started ") and lines[1] == "  sfm: 50% after 0.0 min"
    assert len(lines) == 2
    quiet = io.StringIO()
    q = TerminalFeedback("run", stream=quiet, quiet=True)
    q.stage("sfm", 3, 7, 0.2, 0.5)
    q.progress(0.45)
    assert quiet.getvalue() == ""


def test_json_written_is_strict_not_measured_is_null(tmp_path):
    value = {"rmse_m": float("nan"), "max": np.float32(np.inf), "n": np.int64(3), "xy": np.array([1.5, np.nan]),
             "path": tmp_path, "ok": np.bool_(True)}  # fmt: skip
    path = write_json(tmp_path / "q.json", value)

    def refuse(name):
        raise ValueError(name)

    got = json.loads(path.read_text(), parse_constant=refuse)
    assert got == {"rmse_m": None, "max": None, "n": 3, "xy": [1.5, None], "path": str(tmp_path), "ok": True}
    with pytest.raises(TypeError):
        write_json(tmp_path / "bad.json", {"x": object()})
    assert not (tmp_path / "bad.json").exists()
