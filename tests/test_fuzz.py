"""Property-based fuzzing of every parser (issue 23): whatever the bytes, a parser returns or
raises geoortho's InputError (a named file, line and reason); never another exception.

Seeds are real files from ../shared/data/real and the synthetic survey's own, mutated byte by
byte; CI replays the same 150 examples per parser; ``GEOORTHO_FUZZ_EXAMPLES=5000`` explores new ones.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from pyproj import CRS
from realdata import REAL_DATA

from geoortho.errors import InputError

# CI replays a fixed sequence (a red CI must be reproducible); GEOORTHO_FUZZ_EXAMPLES=N explores anew.
_EXPLORE = int(os.environ.get("GEOORTHO_FUZZ_EXAMPLES", "0"))
FUZZ = settings(
    max_examples=_EXPLORE or 150,
    derandomize=not _EXPLORE,
    deadline=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture],
)


def _mutate(data: bytes, edits: list[tuple[int, int]], cut: int | None, region: int) -> bytes:
    b = bytearray(data)
    span = max(1, min(region, len(b)))
    for pos, value in edits:
        b[pos % span] = value
    if cut is not None:
        b = b[: cut % max(1, len(b))]
    return bytes(b)


EDITS = st.lists(st.tuples(st.integers(0, 2**31), st.integers(0, 255)), min_size=1, max_size=24)
CUTS = st.one_of(st.none(), st.integers(0, 2**31))


def _jpeg_headers() -> list[bytes]:
    """Real JPEG headers (everything before the scan data) with a minimal scan and end marker."""
    out = []
    for folder in ("toledo_dji/images", "brighton_dji_xmp_pair", "dji_mini4pro_defects/images"):
        for p in sorted((REAL_DATA / folder).rglob("*.[jJ][pP][gG]"))[:2]:
            data = p.read_bytes()
            sos = data.find(b"\xff\xda")
            out.append(data[:sos] + b"\xff\xda\x00\x02" + b"\x00" * 64 + b"\xff\xd9")
    return out


HEADERS = _jpeg_headers() if REAL_DATA.exists() else []


def _read_photo_only_input_errors(data: bytes) -> None:
    from geoortho.photos.metadata import read_photo

    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "fuzz.JPG"
        path.write_bytes(data)
        try:
            read_photo(path).intrinsics()
        except InputError:
            pass


@pytest.mark.skipif(not HEADERS, reason="../shared/data/real is absent")
@FUZZ
@given(which=st.integers(0, 100), edits=EDITS, cut=CUTS)
def test_mutated_real_exif_and_xmp_headers_raise_only_input_errors(which, edits, cut):
    header = HEADERS[which % len(HEADERS)]
    _read_photo_only_input_errors(_mutate(header, edits, cut, region=len(header) - 70))


@FUZZ
@given(data=st.binary(max_size=4096))
def test_random_bytes_as_a_photo_raise_only_input_errors(data):
    _read_photo_only_input_errors(data)


@FUZZ
@given(text=st.one_of(st.text(max_size=2000), st.binary(max_size=2000).map(lambda b: b.decode("latin-1"))))
def test_random_xmp_parses_to_a_dict_of_strings(text):
    from geoortho.photos.metadata import parse_xmp

    tags = parse_xmp(text)
    assert isinstance(tags, dict) and all(isinstance(k, str) and isinstance(v, str) for k, v in tags.items())


# GCP files: rows built of the pieces real files are made of, in any order and number.
TOKENS = st.sampled_from(
    [
        "EPSG:32629", "EPSG:4326", "EPSG:4978", "EPSG:5773", "+proj=utm +zone=29", "WGS84 UTM 29N",
        "GCP1", "name", "lat", "lon", "alt", "x", "y", "z", "easting", "northing", "elevation",
        "483601.62", "4288786.66", "113.9", "-9.18", "38.75", "95", "-200", "nan", "inf", "1e308", "0",
        "483601,6247", "DJI_0001.JPG", "DJI 0002.JPG", "1024", "768", "#", "", " ", "\t", ",", ";", '"',
        '{"points": [', '{"id": "A", "position": {"latitude": 38.7, "longitude": -9.1}}', "]}", "{", "}", "[",
    ]
)  # fmt: skip
ROWS = st.lists(st.lists(TOKENS, max_size=9).map(" ".join), max_size=12).map("\n".join)


@FUZZ
@given(text=st.one_of(ROWS, st.text(max_size=600)), suffix=st.sampled_from([".txt", ".csv", ".json"]))
def test_gcp_files_raise_only_input_errors(text, suffix):
    from geoortho.gcp.io import read_gcp_file

    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / f"gcp{suffix}"
        path.write_text(text, encoding="utf-8", errors="surrogateescape")
        for crs in (None, "EPSG:32629"):
            try:
                gcps = read_gcp_file(path, crs)
            except InputError:
                continue
            assert gcps.points and all(p.name for p in gcps.points)


@FUZZ
@given(data=st.binary(max_size=3000), suffix=st.sampled_from([".txt", ".json", ".csv"]))
def test_random_bytes_as_a_gcp_file_raise_only_input_errors(data, suffix):
    from geoortho.gcp.io import read_gcp_file

    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / f"gcp{suffix}"
        path.write_bytes(data)
        try:
            read_gcp_file(path, "EPSG:32629")
        except InputError:
            pass


def _las_seeds() -> list[bytes]:
    folder = REAL_DATA / "pdal_las"
    return [(folder / n).read_bytes() for n in ("simple.las", "simple.laz") if (folder / n).exists()]


LAS = _las_seeds() if REAL_DATA.exists() else []


@pytest.mark.skipif(not LAS, reason="../shared/data/real is absent")
@FUZZ
@given(which=st.integers(0, 10), edits=EDITS, cut=CUTS, suffix=st.sampled_from([".las", ".laz"]))
def test_mutated_las_headers_raise_only_input_errors(which, edits, cut, suffix):
    from geoortho.core.pointcloud import open_points

    data = _mutate(LAS[which % len(LAS)], edits, cut, region=375)  # the LAS 1.4 public header
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / f"cloud{suffix}"
        path.write_bytes(data)
        try:
            src = open_points(path, CRS("EPSG:32629"))
            for _ in src.chunks(200_000):
                pass
        except InputError:
            pass
