"""GCP coordinate files: every sample format reads to the same points; errors name file and line."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from pyproj import Transformer

from geoortho.errors import InputError
from geoortho.gcp import marker_id_of, read_gcp_file

SAMPLES = Path(__file__).resolve().parents[1] / "sample_gcps"


def _utm(gcps) -> dict[str, np.ndarray]:
    if gcps.crs.is_geographic:
        t = Transformer.from_crs(gcps.crs, "EPSG:32629", always_xy=True)
        return {p.name: np.array([*t.transform(p.x, p.y)[:2], p.z]) for p in gcps.points}
    return {p.name: np.array([p.x, p.y, p.z]) for p in gcps.points}


@pytest.mark.parametrize(
    "name, crs",
    [
        ("gcp_utm.txt", None),
        ("gcp_wgs84.txt", None),
        ("gcp_legacy_odm_header.txt", None),
        ("gcp_named_columns.csv", None),
        ("gcp_easting_northing.tsv", "EPSG:32629"),
        ("gcp_list.txt", None),
        ("ground_control_points.json", None),
    ],
)
def test_every_sample_format_gives_the_same_points(name, crs):
    ref = _utm(read_gcp_file(SAMPLES / "gcp_utm.txt"))
    got = _utm(read_gcp_file(SAMPLES / name, crs))
    assert set(got) == {"GCP03", "GCP07", "GCP12"}
    for k in ref:
        assert np.allclose(got[k], ref[k], atol=0.002), (name, k)


def test_synth_gcp_files_agree(tiny_survey):
    a = _utm(read_gcp_file(tiny_survey.truth / "gcp_utm.txt"))
    b = _utm(read_gcp_file(tiny_survey.truth / "gcp_wgs84.txt"))
    c = _utm(read_gcp_file(tiny_survey.truth / "gcp_wgs84.csv"))
    assert set(a) == set(b) == set(c) and all(np.allclose(a[k], b[k], atol=2e-3) for k in a)
    assert all(np.allclose(a[k], c[k], atol=2e-3) for k in a)


def test_real_odm_gcp_list_with_comments_and_missing_names():
    from conftest import real_data

    g = read_gcp_file(real_data("toledo_dji") / "gcp" / "gcp_list.txt")
    assert g.crs.to_epsg() == 32617 and len(g.points) == 5
    assert {"HV01", "HV03", "HV04", "HV05"} <= set(g.by_name())


@pytest.mark.parametrize(
    "text, match, line",
    [
        ("GCP1 1 2 3\n", "no CRS", 1),
        ("EPSG:32629\nGCP1 483580.1 4288804.6 112.2\nGCP2 48358x.1 4288804.6 112.2\n", "not a number", 3),
        ("EPSG:32629\nGCP1 483580.1\n", "expected 'name x y z'", 2),
        ("EPSG:4979\nGCP1 -9.18 38.74 100\nGCP2 38.74 -9.18 100\nGCP3 -120.5 38.7 1\n", "look swapped", 4),
        ("EPSG:32629\nA 1 2 3\nA 1 2 4\n", "appears again", 3),
        ("EPSG:99999999\nA 1 2 3\n", "unknown CRS", 1),
        ("name,lat,lon,alt\nA,38.7,-9.1\n", "expected 4 columns", 2),
    ],
)
def test_errors_name_file_and_line(tmp_path, text, match, line):
    f = tmp_path / "gcp.txt"
    f.write_text(text)
    with pytest.raises(InputError, match=match) as e:
        read_gcp_file(f)
    assert str(e.value).startswith(str(f))
    assert f"{f}:{line}:" in str(e.value)


def test_duplicate_with_same_coordinates_is_fine(tmp_path):
    f = tmp_path / "g.txt"
    f.write_text("EPSG:32629\nA 1 2 3\nA 1 2 3\n")
    assert len(read_gcp_file(f).points) == 1


def test_marker_id_of():
    assert [marker_id_of(n) for n in ("GCP07", "12", "HV01", "base")] == [7, 12, 1, None]


def test_semicolon_rows_with_decimal_commas(tmp_path):
    """Issue 23 (6): 'GCP33;483601,6247;4288786,6576;113,8976' was split into 7 fields and read as
    x=483601, y=6247, z=4288786 — silently wrong. Semicolons separate, commas are decimals."""
    p = tmp_path / "g.txt"
    p.write_text("EPSG:32629\nGCP33;483601,6247;4288786,6576;113,8976\nGCP34 ; 483602,5 ; 4288787 ; 114\n")
    g = read_gcp_file(p)
    assert [(q.name, q.x, q.y, q.z) for q in g.points] == [
        ("GCP33", 483601.6247, 4288786.6576, 113.8976),
        ("GCP34", 483602.5, 4288787.0, 114.0),
    ]
