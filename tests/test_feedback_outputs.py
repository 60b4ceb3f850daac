from __future__ import annotations

import io
import json

import numpy as np
import pytest
from conftest import RecordingFeedback

from geoortho.errors import CanceledError, InputError
from geoortho.feedback import JsonLinesFeedback, split, track
from geoortho.outputs import atomic_path, write_cog


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
