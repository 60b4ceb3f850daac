"""The catalogue of hostile inputs (issue 23): every command, as a new user would break it.

Each case runs the CLI in-process and asserts what a surveyor needs of it:

* the exit code: 0 with a product, 2 with one stderr line for bad input, never 1 ("unexpected");
* the line names the file, the line or the value, and what to give instead;
* every input is byte for byte as it was;
* nothing is left under a final name that is not a complete product, and no temporary file.

``python tests/test_bad_input.py`` runs the catalogue outside pytest and prints the counts
the issue asks for (cases, products, named errors, unexpected errors, inputs destroyed,
temporaries left).
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import json
import re
import shutil
import struct
import sys
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest

from geoortho.processing.cli import main

# ---------------------------------------------------------------------------------------------
# hostile inputs, made from a clean tiny survey

CENTRE = "DJI_0005.JPG"  # a photo in the middle of the tiny flight


def _exif_edit(path: Path, edit: Callable[[dict], None]) -> None:
    import piexif

    ex = piexif.load(str(path))
    edit(ex)
    piexif.insert(piexif.dump(ex), str(path))


def _xmp_edit(path: Path, pattern: bytes, value: bytes) -> None:
    """Replace an XMP attribute's value keeping the segment's length (the JPEG stays valid)."""
    data = path.read_bytes()

    def same_length(m: re.Match[bytes]) -> bytes:
        return m.group(1) + value.rjust(len(m.group(2))) + m.group(3)

    new = re.sub(pattern, same_length, data)
    assert new != data and len(new) == len(data)
    path.write_bytes(new)


def _dms(v: float) -> tuple:
    d = int(abs(v))
    m = int((abs(v) - d) * 60)
    return (d, 1), (m, 1), (int(round(((abs(v) - d) * 60 - m) * 60 * 1000)), 1000)


def _pitch_0(p: Path) -> None:
    _xmp_edit(p, rb'(GimbalPitchDegree=")([^"]*)(")', b"+0.00")


def _no_altitude(p: Path) -> None:
    _exif_edit(p, lambda ex: [ex["GPS"].pop(k, None) for k in (5, 6)])
    _xmp_edit(p, rb'(drone-dji:AbsoluteAltitude=")([^"]*)(")', b"")
    _xmp_edit(p, rb'(drone-dji:RelativeAltitude=")([^"]*)(")', b"")


def _corrupt_scan(p: Path) -> None:
    data = bytearray(p.read_bytes())
    sos = data.find(b"\xff\xda")
    rng = np.random.default_rng(1)
    for k in rng.integers(sos + 600, len(data) - 100, 200):
        if data[k - 1] != 0xFF and data[k] != 0xFF:
            data[k] = int(rng.integers(0, 255))
    p.write_bytes(bytes(data))


def _latitude_95(p: Path) -> None:
    _exif_edit(p, lambda ex: ex["GPS"].update({2: ((95, 1), (0, 1), (0, 1))}))


def _12000_km_away(p: Path) -> None:
    _exif_edit(p, lambda ex: ex["GPS"].update({1: b"S", 2: _dms(45.0), 3: b"E", 4: _dms(170.0)}))


def _focal_0(p: Path) -> None:
    _exif_edit(p, lambda ex: ex["Exif"].update({0x920A: (0, 1), 0xA405: 0}))


def _header_30000_px(p: Path) -> None:
    data = bytearray(p.read_bytes())
    sof = data.find(b"\xff\xc0")
    data[sof + 5 : sof + 9] = struct.pack(">HH", 30000, 30000)
    p.write_bytes(bytes(data))


def _header_100_mp(p: Path) -> None:
    """The SOF claims 10000 x 10000 px (under PIL's bomb limit), EXIF and the data say 960 x 640."""
    data = bytearray(p.read_bytes())
    sof = data.find(b"\xff\xc0")
    data[sof + 5 : sof + 9] = struct.pack(">HH", 10000, 10000)
    p.write_bytes(bytes(data))


def _truncated(p: Path) -> None:
    p.write_bytes(p.read_bytes()[: p.stat().st_size // 2])


def _text(p: Path) -> None:
    p.write_bytes(b"this is not a photo\n")


def _empty(p: Path) -> None:
    p.write_bytes(b"")


#: Bad photo -> (how it is made, what the skip reason must say). Each is a copy of the centre
#: photo with one defect, so it would land in the products if it were not refused.
BAD_PHOTOS: dict[str, tuple[Callable[[Path], None], str]] = {
    "pitch_0": (_pitch_0, "looks at the horizon"),
    "no_altitude": (_no_altitude, "no altitude"),
    "corrupt_scan": (_corrupt_scan, "corrupt"),
    "latitude_95": (_latitude_95, "out of range"),
    "far_away": (_12000_km_away, "km from"),
    "focal_0": (_focal_0, "no focal length"),  # placeholders ignored: the camera is then unknown
    "bomb": (_header_30000_px, "M pixels"),
    "header_lies": (_header_100_mp, "damaged header"),
    "truncated": (_truncated, "truncated"),
    "text": (_text, "not a readable image"),
    "empty": (_empty, "not a readable image"),
}


def hostile_photos(clean: Path, folder: Path) -> Path:
    """The clean photos plus one copy of the centre photo per defect, named after it."""
    folder.mkdir(parents=True, exist_ok=True)
    for p in sorted(clean.iterdir()):
        shutil.copy(p, folder / p.name)
    for name, (make, _) in BAD_PHOTOS.items():
        target = folder / f"BAD_{name}.JPG"
        shutil.copy(clean / CENTRE, target)
        make(target)
    return folder


def hostile_gcp_files(truth: Path, folder: Path) -> dict[str, Path]:
    """GCP files that cannot place any GCP in the photos, or cannot be read."""
    folder.mkdir(parents=True, exist_ok=True)
    rows = [ln.split() for ln in (truth / "gcp_utm.txt").read_text().splitlines()[1:] if ln.strip()]
    files = {
        "wrong_zone": "EPSG:32617\n" + "".join(f"{n} {x} {y} {z}\n" for n, x, y, z in rows),
        "swapped": "EPSG:32629\n" + "".join(f"{n} {y} {x} {z}\n" for n, x, y, z in rows),
        "300m_off": "EPSG:32629\n" + "".join(f"{n} {float(x) + 300} {y} {z}\n" for n, x, y, z in rows),
        "geocentric": "EPSG:4978\n" + "".join(f"{n} {x} {y} {z}\n" for n, x, y, z in rows),
        "vertical": "EPSG:5773\n" + "".join(f"{n} {x} {y} {z}\n" for n, x, y, z in rows),
        "json_points_5": '{"points": 5}',
        "json_nan": '{"points": [{"id": "A", "position": {"latitude": "nan", "longitude": 1}}]}',
        "json_list": "[1, 2, 3]",
        "not_a_number": "EPSG:32629\nGCP1 483600 abc 110\n",
        "binary": "\x00\x01\x02\xff" * 50,
        "empty": "",
    }
    out = {}
    for name, text in files.items():
        out[name] = folder / f"{name}.txt"
        out[name].write_bytes(text.encode("utf-8", "surrogateescape") if name != "binary" else bytes(range(256)))
    return out


# ---------------------------------------------------------------------------------------------
# running a case


@dataclass
class Outcome:
    code: int
    stderr: list[str]
    stdout: str
    changed_inputs: list[str] = field(default_factory=list)
    temporaries: list[str] = field(default_factory=list)


def _digest(paths: list[Path]) -> dict[str, str]:
    out = {}
    for root in paths:
        files = [root] if root.is_file() else sorted(p for p in root.rglob("*") if p.is_file())
        for p in files:
            out[str(p)] = hashlib.sha1(p.read_bytes()).hexdigest()
    return out


def run_cli(argv: list[str], inputs: list[Path], workdir: Path, quiet: bool = True) -> Outcome:
    before = _digest(inputs)
    err, out = io.StringIO(), io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(out), warnings.catch_warnings(record=True) as w:
        warnings.simplefilter("default")  # as python -m geoortho runs: shown once, on stderr
        try:
            code = main([*argv, "--quiet"] if quiet else argv)
        except SystemExit as e:  # argparse's own refusals (unknown choice, made-up option)
            code = int(e.code or 0)
    after = _digest(inputs)
    shown = [f"{x.filename}:{x.lineno}: {x.category.__name__}: {x.message}" for x in w]
    return Outcome(
        code,
        shown + [ln for ln in err.getvalue().splitlines() if ln.strip()],
        out.getvalue(),
        sorted(k for k in before if before[k] != after.get(k)),
        sorted(str(p) for p in workdir.rglob(".*.tmp*")),
    )


@dataclass(frozen=True)
class Case:
    """One hostile input: the arguments ({s}: the tiny survey, {h}: the hostile inputs, {o}: an empty
    output folder), the exit code, and a pattern the last stderr line (code 2) must match."""

    id: str
    argv: tuple[str, ...]
    code: int
    message: str = ""
    outputs: tuple[str, ...] = ()  # final output paths: present with code 0, absent otherwise


PLAN = ("plan", "--camera", "DJI FC6310", "--gsd-cm", "2")

CASES_ROUND3 = [
    # outputs that would change a file inside an input folder, or add a photo to it
    Case(
        "dense/output-in-sfm",
        ("dense", "--sfm", "{h}/sfm", "--images", "{s}/images", "--output", "{h}/sfm/points.laz"),
        2,
        "a file of the input folder",
    ),
    Case(
        "gcp-find/review-over-a-photo",
        (
            "gcp-find",
            "--images",
            "{s}/images",
            "--gcp-file",
            "{s}/truth/gcp_utm.txt",
            "--output",
            "{o}/g.txt",
            "--review",
            "{s}/images/DJI_0001.JPG",
        ),  # fmt: skip
        2,
        "review: .* a file of the input folder",
    ),
    Case(
        "ortho/preview-over-a-photo",
        ("ortho", "--images", "{s}/images", "--output", "{o}/o.tif", "--preview", "{s}/images/DJI_0002.JPG"),
        2,
        "preview: .* a file of the input folder",
    ),
    Case("ortho/output-among-photos", ("ortho", "--images", "{s}/images", "--output", "{s}/images/o.tif"), 2, "photo"),
    Case("synth/a-folder-not-its-own", ("synth", "--output", "{h}/synth", "--preset", "tiny"), 2, "did not make"),
    # silently wrong before
    Case(
        "footprints/rgba-dsm",
        ("footprints", "--images", "{s}/images", "--output", "{o}/fp.gpkg", "--dsm", "{s}/truth/ortho.tif"),
        2,
        "an image .*not an elevation raster",
    ),
    Case(
        "plan/web-mercator",
        (*PLAN, "--aoi", "{h}/aoi_good.geojson", "--output", "{o}/p", "--crs", "EPSG:3857"),
        2,
        "0.780 m on the ground",
    ),  # fmt: skip
    Case(
        "plan/dtm-20-km-away",
        (*PLAN, "--aoi", "{h}/aoi_good.geojson", "--output", "{o}/p", "--dtm", "{h}/dtm_far.tif"),
        2,
        "covers 0 % of the AOI .*20.5 km",
    ),  # fmt: skip
    # runaway memory
    Case("plan/county-at-2-cm", (*PLAN, "--aoi", "{h}/aoi_county.geojson", "--output", "{o}/p"), 2, "M photos"),
    Case(
        "plan/16-px-camera",
        (
            "plan",
            "--aoi",
            "{h}/aoi_good.geojson",
            "--output",
            "{o}/p",
            "--sensor-width-mm",
            "6",
            "--focal-mm",
            "8",
            "--image-width-px",
            "16",
            "--image-height-px",
            "16",
            "--gsd-cm",
            "2",
        ),  # fmt: skip
        2,
        "M photos",
    ),
    # "unexpected error" before
    Case("plan/zero-area", (*PLAN, "--aoi", "{h}/aoi_zero.geojson", "--output", "{o}/p"), 2, "no area"),
    Case("plan/nan", (*PLAN, "--aoi", "{h}/aoi_nan.geojson", "--output", "{o}/p"), 2, "not a number"),
    Case(
        "plan/utm-as-degrees", (*PLAN, "--aoi", "{h}/aoi_utm_as_degrees.geojson", "--output", "{o}/p"), 2, "not degrees"
    ),  # fmt: skip
    Case("plan/empty-kml", (*PLAN, "--aoi", "{h}/aoi_empty.kml", "--output", "{o}/p"), 2, "holds no layer"),
    Case("plan/output-a-file", (*PLAN, "--aoi", "{h}/aoi_good.geojson", "--output", "{h}/a_file"), 2, "is a file"),
    Case(
        "plan-check/output-a-file",
        ("plan-check", "--images", "{s}/images", "--gcp-file", "{s}/truth/gcp_utm.txt", "--output", "{h}/a_file"),
        2,
        "is a file",
    ),
    Case(
        "run/stage-options-300-characters",
        (
            "run",
            "--images",
            "{s}/images",
            "--output",
            "{o}/p",
            "--stage-options",
            "[" + ",".join(["1234567"] * 37) + "]",
        ),
        2,
        "stage options",
    ),
    # validated before the first stage, not minutes into the run
    Case(
        "run/ortho-crs-geographic",
        (
            "run",
            "--images",
            "{s}/images",
            "--output",
            "{o}/p",
            "--stage-options",
            '{{"ortho": {{"crs": "EPSG:4326"}}}}',
        ),  # braces: str.format
        2,
        "not projected",
    ),
    Case(
        "run/dsm-not-a-raster",
        ("run", "--images", "{s}/images", "--output", "{o}/p", "--dsm", "{h}/dsm.tif"),
        2,
        "not an elevation raster",
    ),  # fmt: skip
    # misleading before
    Case(
        "gcp-find/degrees-under-utm",
        ("gcp-find", "--images", "{s}/images", "--gcp-file", "{h}/gcp/degrees_row.txt", "--output", "{o}/g.txt"),
        2,
        r"degrees_row.txt:6: .*latitude and longitude",
    ),
]

CASES = [
    *CASES_ROUND3,
    # 3-4: photos, one bad photo never aborts a batch
    Case(
        "footprints/bad-photos",
        ("footprints", "--images", "{h}/photos", "--output", "{o}/fp.gpkg"),
        0,
        outputs=("{o}/fp.gpkg",),
    ),
    Case(
        "gcp-find/bad-photos",
        ("gcp-find", "--images", "{h}/photos", "--gcp-file", "{s}/truth/gcp_utm.txt", "--output", "{o}/gcp_list.txt"),
        0,
        outputs=("{o}/gcp_list.txt",),
    ),
    Case("ortho/bad-photos", ("ortho", "--images", "{h}/photos", "--output", "{o}/o.tif"), 0, outputs=("{o}/o.tif",)),
    Case(
        "footprints/no-photo",
        ("footprints", "--images", "{h}/gcp", "--output", "{o}/fp.gpkg"),
        2,
        "no images .* in the folder",
    ),
    # 1: outputs onto inputs
    Case("dem/output=points", ("dem", "--points", "{h}/points.laz", "--output", "{h}/points.laz"), 2, "points"),
    Case(
        "gcp-find/output=gcp-file",
        ("gcp-find", "--images", "{s}/images", "--gcp-file", "{h}/gcp/swapped.txt", "--output", "{h}/gcp/swapped.txt"),
        2,
        "--gcp-file",
    ),
    Case(
        "ortho/output=dsm",
        ("ortho", "--images", "{s}/images", "--dsm", "{s}/truth/dsm.tif", "--output", "{s}/truth/dsm.tif"),
        2,
        "dsm",
    ),
    # 2: every offered vector format whole under its final name
    Case(
        "footprints/shapefile",
        ("footprints", "--images", "{s}/images", "--output", "{o}/fp.shp"),
        0,
        outputs=("{o}/fp.shp", "{o}/fp.dbf", "{o}/fp.shx", "{o}/fp.prj"),
    ),
    Case(
        "footprints/csv", ("footprints", "--images", "{s}/images", "--output", "{o}/fp.csv"), 0, outputs=("{o}/fp.csv",)
    ),
    Case(
        "footprints/kml", ("footprints", "--images", "{s}/images", "--output", "{o}/fp.kml"), 0, outputs=("{o}/fp.kml",)
    ),
    # 5: point clouds and grids
    Case(
        "dem/far-outliers",
        ("dem", "--points", "{h}/outliers.laz", "--output", "{o}/dsm.tif"),
        0,
        outputs=("{o}/dsm.tif",),
    ),
    Case("dem/line", ("dem", "--points", "{h}/line.laz", "--output", "{o}/dsm.tif"), 2, "a line or a spot"),
    Case("dem/x-scale-0", ("dem", "--points", "{h}/x0.laz", "--output", "{o}/dsm.tif"), 2, "a line or a spot"),
    Case(
        "dem/resolution-0.01",
        ("dem", "--points", "{s}/truth/points.laz", "--output", "{o}/dsm.tif", "--resolution-m", "0.01"),
        2,
        r"give \S+ m or coarser",
    ),
    Case(
        "dem/resolution-1e-3",
        ("dem", "--points", "{s}/truth/points.laz", "--output", "{o}/dsm.tif", "--resolution-m", "1e-3"),
        2,
        r"give \S+ m or coarser",
    ),
    Case(
        "dem/smrf-cell-0.05",
        (
            "dem",
            "--points",
            "{s}/truth/points.laz",
            "--output",
            "{o}/dsm.tif",
            "--dtm",
            "{o}/dtm.tif",
            "--smrf-cell-m",
            "0.05",
        ),
        2,
        r"--smrf-cell-m: .* give \S+ m or coarser",
    ),
    Case(
        "dem/smrf-window-1e6",
        (
            "dem",
            "--points",
            "{s}/truth/points.laz",
            "--output",
            "{o}/dsm.tif",
            "--dtm",
            "{o}/dtm.tif",
            "--smrf-window-m",
            "1e6",
        ),
        0,
        outputs=("{o}/dsm.tif", "{o}/dtm.tif"),
    ),
    Case(
        "dem/max-gap-1e9",
        ("dem", "--points", "{s}/truth/points.laz", "--output", "{o}/dsm.tif", "--max-gap-m", "1e9"),
        0,
        outputs=("{o}/dsm.tif",),
    ),
    Case(
        "dem/count-lies",
        ("dem", "--points", "{h}/count_lies.laz", "--output", "{o}/dsm.tif"),
        2,
        "cannot read points|points",
    ),
    Case(
        "dem/not-a-cloud", ("dem", "--points", "{h}/gcp/binary.txt", "--output", "{o}/dsm.tif"), 2, "point cloud format"
    ),
    Case("dem/text-as-laz", ("dem", "--points", "{h}/text.laz", "--output", "{o}/dsm.tif"), 2, "not a LAS/LAZ file"),
    Case(
        "dem/nan-z", ("dem", "--points", "{h}/nan.ply", "--output", "{o}/dsm.tif", "--crs", "EPSG:32629"), 2, "finite"
    ),
    # 6: GCP files
    *[
        Case(
            f"gcp-find/{name}",
            (
                "gcp-find",
                "--images",
                "{s}/images",
                "--gcp-file",
                f"{{h}}/gcp/{name}.txt",
                "--output",
                "{o}/gcp_list.txt",
            ),
            2,
            message,
        )
        for name, message in (
            ("wrong_zone", r"none of the \d+ GCPs falls inside any photo.*CRS"),
            ("swapped", "swapped"),
            ("300m_off", r"none of the \d+ GCPs falls inside any photo; the nearest is 0.3 km from the flight"),
            ("geocentric", "EPSG:4978 is geocentric"),
            ("vertical", "EPSG:5773 is vertical only"),
            ("json_points_5", "expected OpenSfM"),
            ("json_nan", "must be numbers|not finite"),
            ("json_list", "expected OpenSfM"),
            ("not_a_number", r"not_a_number.txt:2: y is not a number"),
            ("binary", "cannot read GCP file|no CRS"),
            ("empty", "empty GCP file"),
        )
    ],
    Case(
        "sfm/gcps-10-km-off",
        ("sfm", "--images", "{s}/images", "--gcp-list", "{h}/gcp_list_far.txt", "--output", "{o}/sfm"),
        2,
        r"nearest GCP is 10.0 km from the photos",
    ),
    # 7: options that produce nothing
    Case(
        "ortho/resolution-1e6",
        ("ortho", "--images", "{s}/images", "--output", "{o}/o.tif", "--resolution-m", "1e6"),
        2,
        r"not within 0.1 to 100 x",
    ),
    Case(
        "ortho/crs-4326",
        ("ortho", "--images", "{s}/images", "--output", "{o}/o.tif", "--crs", "EPSG:4326"),
        2,
        "not projected",
    ),
    Case(
        "footprints/crs-4978",
        ("footprints", "--images", "{s}/images", "--output", "{o}/fp.gpkg", "--crs", "EPSG:4978"),
        2,
        "geocentric",
    ),
    Case(
        "footprints/crs-5773",
        ("footprints", "--images", "{s}/images", "--output", "{o}/fp.gpkg", "--crs", "EPSG:5773"),
        2,
        "vertical",
    ),
    Case(
        "footprints/crs-100kB",
        ("footprints", "--images", "{s}/images", "--output", "{o}/fp.gpkg", "--crs", "x" * 100_000),
        2,
        "unknown CRS",
    ),
    Case("synth/preset", ("synth", "--output", "{o}/s", "--preset", "huge"), 2, "invalid choice: 'huge'"),
    Case("plan/no-aoi", ("plan", "--aoi", "{h}/missing.gpkg", "--output", "{o}/plan"), 2, "no such file"),
]


def make_hostile(survey: Path, folder: Path) -> None:
    """Every hostile input the cases name under {h}."""
    import laspy

    from geoortho.core.pointcloud import write_las

    hostile_photos(survey / "images", folder / "photos")
    hostile_gcp_files(survey / "truth", folder / "gcp")
    las = laspy.read(survey / "truth" / "points.laz")
    xyz = np.c_[las.x, las.y, las.z]
    crs = las.header.parse_crs()
    write_las(folder / "points.laz", xyz, crs)
    far = np.vstack([xyz[:10] + [100_000.0, 0, 0], xyz[10:11] + [0, 0, 10_000.0]])
    write_las(folder / "outliers.laz", np.vstack([xyz, far]), crs)
    t = np.linspace(0, 30, 500)
    write_las(folder / "line.laz", np.c_[xyz[0, 0] + t, xyz[0, 1] + 0 * t, xyz[0, 2] + 0 * t], crs)
    data = bytearray((survey / "truth" / "points.laz").read_bytes())
    data[131:139] = struct.pack("<d", 0.0)  # LAS 1.2-1.4 header: X scale factor
    (folder / "x0.laz").write_bytes(bytes(data))
    lies = bytearray((folder / "points.laz").read_bytes())
    lies[107:111] = struct.pack("<I", 10 * len(xyz))  # legacy point count: ten times the truth
    lies[247:255] = struct.pack("<Q", 10 * len(xyz))  # LAS 1.4 point count
    (folder / "count_lies.laz").write_bytes(bytes(lies))
    (folder / "text.laz").write_text("not a point cloud\n")
    # headers whose counts cannot be true: laspy read them for minutes, lazrs allocated 45 GB and
    # aborted the process (found by tests/test_fuzz.py)
    good = (folder / "points.laz").read_bytes()
    header_size, to_points = struct.unpack_from("<HI", good, 94)
    vlr = good.find(b"laszip encoded")
    for name, at, value in (
        ("vlr_count", 100, struct.pack("<I", 2**31)),
        ("chunk_size", vlr - 2 + 54 + 12, struct.pack("<I", 2**30)),
        ("chunk_table", struct.unpack_from("<q", good, to_points)[0] + 4, struct.pack("<I", 2**31)),
    ):
        bad = bytearray(good)
        bad[at : at + len(value)] = value
        (folder / f"{name}.laz").write_bytes(bytes(bad))
    from plyfile import PlyData, PlyElement

    v = np.zeros(50, dtype=[("x", "f8"), ("y", "f8"), ("z", "f8")])
    v["x"], v["y"], v["z"] = np.arange(50.0), np.arange(50.0) % 7, np.nan
    PlyData([PlyElement.describe(v, "vertex")]).write(str(folder / "nan.ply"))
    rows = [ln.split() for ln in (survey / "truth" / "gcp_utm.txt").read_text().splitlines()[1:] if ln.strip()]
    (folder / "gcp_list_far.txt").write_text(
        "EPSG:32629\n" + "".join(f"{float(x) + 10_000} {y} {z} 100 100 DJI_0001.JPG {n}\n" for n, x, y, z in rows)
    )


def make_hostile_round3(survey: Path, folder: Path) -> None:
    """Issue 49's inputs: an sfm-like folder with its cloud, AOIs no plan can fly, a DTM 20 km away,
    a folder synth did not make, a GCP row in degrees under a UTM header, a text file as a DSM."""
    import rasterio
    from rasterio.transform import from_origin

    (folder / "sfm").mkdir()
    shutil.copy(folder / "points.laz", folder / "sfm" / "points.laz")
    (folder / "synth" / "images").mkdir(parents=True)
    (folder / "synth" / "images" / "mine.txt").write_text("my notes")
    ring = [[-9.19, 38.747], [-9.187, 38.747], [-9.187, 38.749], [-9.19, 38.749], [-9.19, 38.747]]
    aois = {
        "good": ring,
        "zero": [[-9.19, 38.747], [-9.187, 38.747], [-9.19, 38.747]],
        "nan": [[-9.19, 38.747], [-9.187, float("nan")], [-9.187, 38.749], [-9.19, 38.747]],
        "utm_as_degrees": [[483600, 4288700], [483800, 4288700], [483800, 4288900], [483600, 4288700]],
        "county": [[-9.5, 38.5], [-8.3, 38.5], [-8.3, 39.4], [-9.5, 39.4], [-9.5, 38.5]],
    }
    for name, coords in aois.items():
        geo = {"type": "Polygon", "coordinates": [coords]}
        fc = {"type": "FeatureCollection", "features": [{"type": "Feature", "properties": {}, "geometry": geo}]}
        (folder / f"aoi_{name}.geojson").write_text(json.dumps(fc).replace("NaN", "NaN"))
    (folder / "aoi_empty.kml").write_text(
        '<?xml version="1.0"?><kml xmlns="http://www.opengis.net/kml/2.2"><Document></Document></kml>'
    )
    with rasterio.open(
        folder / "dtm_far.tif", "w", driver="GTiff", width=100, height=100, count=1, dtype="float32",
        crs="EPSG:32629", transform=from_origin(503600, 4288900, 10, 10),
    ) as dst:  # fmt: skip
        dst.write(np.full((100, 100), 50, np.float32), 1)
    (folder / "a_file").write_text("not a folder")
    (folder / "dsm.tif").write_text("not a raster")
    rows = (survey / "truth" / "gcp_utm.txt").read_text().splitlines()
    (folder / "gcp" / "degrees_row.txt").write_text("\n".join([*rows, "GCP99 38.7476 -9.1887 100.0"]) + "\n")


def make_hostile_round4(survey: Path, folder: Path) -> None:
    """Issue 76's inputs: positions files that cannot be right, stage options that name a photo as an
    output or cannot be read, a positions file inside sfm's output named like its report, a DSM's
    source codes given as heights."""
    import rasterio

    poses = json.loads((survey / "truth" / "poses.json").read_text())
    crs = json.loads((survey / "truth" / "survey.json").read_text())["crs"]
    zone = int(crs.split(":")[1])

    def csv(name: str, head: str, dy: float = 0.0, twice: bool = False) -> None:
        rows = [f"{p['image']},{p['x']:.3f},{p['y'] + dy:.3f},{p['z']:.3f}" for p in poses]
        if twice:
            rows.insert(1, rows[0])
        (folder / name).write_text("\n".join([head, "image,easting,northing,z", *rows]) + "\n")

    csv("positions_55km.csv", f"# {crs}", dy=55_000.0)
    csv("positions_wrong_zone.csv", f"# EPSG:{zone + 1}")
    csv("positions_twice.csv", f"# {crs}", twice=True)
    (folder / "week_overflow.pos").write_text("% header\n99999999999999 1.0 38.7 -9.1 100 1 10 0.01 0.01 0.02\n")

    def aoi(name: str, *rings: list[list[float]]) -> None:
        geo = {"type": "MultiPolygon", "coordinates": [[r] for r in rings]}
        fc = {"type": "FeatureCollection", "features": [{"type": "Feature", "properties": {}, "geometry": geo}]}
        (folder / f"aoi_{name}.geojson").write_text(json.dumps(fc))

    def square(lon: float, lat: float, d: float = 0.0015) -> list[list[float]]:
        return [[lon, lat], [lon + d, lat], [lon + d, lat + d], [lon, lat + d], [lon, lat]]

    aoi("two_sites", square(-9.19, 38.747), square(-9.09, 38.747))  # 8.7 km apart
    aoi("antimeridian", [[179.9985, -17.0], [-179.9985, -17.0], [-179.9985, -16.9985], [179.9985, -16.9985],
                         [179.9985, -17.0]])  # fmt: skip
    far = [ln.split() for ln in (survey / "truth" / "gcp_wgs84.txt").read_text().splitlines()[1:] if ln.strip()]
    (folder / "gcp_far.txt").write_text(
        "EPSG:4979\n" + "".join(f"{n} {float(lat) + 20:.9f} {lon} {h}\n" for n, lat, lon, h in far)
    )
    (folder / "linked").mkdir()
    for photo_path in sorted((survey / "images").glob("*.JPG")):
        (folder / "linked" / photo_path.name).symlink_to(photo_path)
    (folder / "sfm_out").mkdir()
    (folder / "sfm_out" / "report.json").write_text("image,lat,lon,height\n")
    photo = survey / "images" / "DJI_0001.JPG"
    (folder / "options_classified_photo.json").write_text(json.dumps({"dem": {"classified": str(photo)}}))
    (folder / "options_positions.json").write_text(
        json.dumps({"sfm": {"positions": str(folder / "positions_twice.csv")}})
    )
    (folder / "options_deep.json").write_text("[" * 200_000 + "]" * 200_000)
    (folder / "options_folder").mkdir()
    with rasterio.open(survey / "truth" / "dsm.tif") as ds:
        prof = dict(ds.profile, dtype="uint8", nodata=0, driver="GTiff")
        codes = (ds.read(1) > 0).astype("uint8")
    with rasterio.open(folder / "dsm_source.tif", "w", **prof) as dst:
        dst.write(codes, 1)
        dst.set_band_description(1, "0 no data, 1 measured, 2 interpolated, 3 fallback plane")


SFM = ("sfm", "--images", "{s}/images", "--output", "{o}/sfm")
RUN = ("run", "--images", "{s}/images", "--output", "{o}/p")

CASES_ROUND4 = [
    # nothing destroyed
    Case(
        "run/stage-option-output-over-a-photo",
        (*RUN, "--stage-options", "{h}/options_classified_photo.json"),
        2,
        r"dem\.classified \(a stage option\).* a file of the input folder",
    ),
    Case(
        "sfm/positions-named-like-its-report",
        ("sfm", "--images", "{s}/images", "--output", "{h}/sfm_out", "--positions", "{h}/sfm_out/report.json"),
        2,
        "lies in the output folder",
    ),
    Case(
        "sfm/a-folder-of-linked-photos",
        ("sfm", "--images", "{h}/linked", "--output", "{o}/sfm", "--max-image-size", "640"),
        0,
        outputs=("{o}/sfm/report.json",),
    ),
    # never silently wrong
    Case("sfm/positions-55-km-away", (*SFM, "--positions", "{h}/positions_55km.csv"), 2, r"55\.\d km from the photos"),
    Case(
        "sfm/positions-crs-of-another-zone",
        (*SFM, "--positions", "{h}/positions_wrong_zone.csv"),
        2,
        "km from the photos' own GPS .*a wrong CRS",
    ),
    Case("sfm/positions-a-photo-twice", (*SFM, "--positions", "{h}/positions_twice.csv"), 2, "has a position on line"),
    Case(
        "ortho/dsm-source-codes",
        ("ortho", "--images", "{s}/images", "--output", "{o}/o.tif", "--dsm", "{h}/dsm_source.tif"),
        2,
        "source codes",
    ),
    Case(
        "plan/two-sites-8-km-apart",
        (*PLAN, "--aoi", "{h}/aoi_two_sites.geojson", "--output", "{o}/p"),
        2,
        r"2 sites 8\.\d km apart .*plan each site on its own",
    ),  # fmt: skip
    Case(
        "plan/gcps-2000-km-away",
        (*PLAN, "--aoi", "{h}/aoi_good.geojson", "--output", "{o}/p", "--gcps", "{h}/gcp_far.txt"),
        2,
        r"GCPs lie [\d,]+\.\d km or more from the area flown",
    ),  # fmt: skip
    Case(
        "plan-check/gcps-2000-km-away",
        ("plan-check", "--gcp-file", "{h}/gcp_far.txt", "--output", "{o}/c", "--images", "{s}/images"),
        2,
        r"GCPs lie [\d,]+\.\d km or more from the area flown",
    ),  # fmt: skip
    Case(
        "run/positions-55-km-away-before-any-stage",
        (*RUN, "--positions", "{h}/positions_55km.csv"),
        2,
        r"55\.\d km from the photos",
    ),
    Case(
        "run/a-checkpoint-not-in-the-gcp-file",
        (*RUN, "--gcp-file", "{s}/truth/gcp_utm.txt", "--checkpoints", "GCP_NOPE"),
        2,
        "checkpoint GCP_NOPE not in the GCP file",
    ),  # fmt: skip
    Case(
        "run/positions-twice",
        (*RUN, "--positions", "{h}/positions_55km.csv", "--stage-options", "{h}/options_positions.json"),
        2,
        "sfm.positions is also given to the run itself",
    ),  # fmt: skip
    Case(
        "run/split-twice",
        (*RUN, "--split", "20", "--stage-options", '{{"sfm": {{"split": 10}}}}'),
        2,
        "sfm.split is also given to the run itself",
    ),  # fmt: skip
    # one clear line, never a traceback
    Case(
        "plan/a-camera-name-of-300-characters",
        (*PLAN[:1], "--camera", "A" * 300, "--gsd-cm", "2", "--aoi", "{h}/aoi_good.geojson", "--output", "{o}/p"),
        2,
        r"unknown camera 'A+… \(300 characters\)",
    ),  # fmt: skip
    Case("sfm/rtklib-week-overflow", (*SFM, "--positions", "{h}/week_overflow.pos"), 2, "line 2: not an RTKLIB"),
    Case("run/stage-options-nested-deep", (*RUN, "--stage-options", "{h}/options_deep.json"), 2, "nested too deeply"),
    # messages that send the user the right way
    Case("run/stage-options-missing", (*RUN, "--stage-options", "{h}/no_such.json"), 2, "no such file"),
    Case("run/stage-options-a-folder", (*RUN, "--stage-options", "{h}/options_folder"), 2, "a folder"),
]
CASES = [*CASES, *CASES_ROUND4]


def run_case(case: Case, survey: Path, hostile: Path, out: Path, quiet: bool = True) -> Outcome:
    out.mkdir(parents=True, exist_ok=True)
    fill = {"s": str(survey), "h": str(hostile), "o": str(out)}
    argv = [a.format(**fill) if len(a) < 1000 else a for a in case.argv]
    return run_cli(argv, [survey, hostile], out, quiet)


def judge(case: Case, got: Outcome, survey: Path, hostile: Path, out: Path) -> list[str]:
    """What is wrong with the outcome (empty: the case passes)."""
    fill = {"s": str(survey), "h": str(hostile), "o": str(out)}
    problems = []
    if got.code != case.code:
        problems.append(f"exit {got.code}, expected {case.code}: {got.stderr[-1:]}")
    if got.code == 2:
        if len(got.stderr) != 1:
            problems.append(f"{len(got.stderr)} stderr lines, expected one: {got.stderr}")
        elif not re.search(case.message, got.stderr[0]):
            problems.append(f"message {got.stderr[0]!r} does not match {case.message!r}")
        elif len(got.stderr[0]) > 600:
            problems.append(f"message of {len(got.stderr[0])} characters")
    if got.stderr and "unexpected error" in got.stderr[-1]:
        problems.append(got.stderr[-1])
    for o in case.outputs:
        path = Path(o.format(**fill))
        if got.code == 0 and not path.is_file():
            problems.append(f"no product {path.name}")
    if got.code != 0:
        left = [p for p in out.rglob("*") if p.is_file()]
        if left:
            problems.append(f"a failed run left {[p.name for p in left]}")
    if got.changed_inputs:
        problems.append(f"inputs changed: {got.changed_inputs}")
    if got.temporaries:
        problems.append(f"temporaries left: {got.temporaries}")
    return problems


# ---------------------------------------------------------------------------------------------
# the tests


@pytest.fixture(scope="module")
def hostile(tiny_survey, tmp_path_factory):
    folder = tmp_path_factory.mktemp("hostile")
    make_hostile(tiny_survey.output, folder)
    make_hostile_round3(tiny_survey.output, folder)
    make_hostile_round4(tiny_survey.output, folder)
    return folder


@pytest.mark.parametrize("case", CASES, ids=lambda c: c.id)
def test_hostile_input(case, tiny_survey, hostile, tmp_path):
    got = run_case(case, tiny_survey.output, hostile, tmp_path / "out")
    assert not judge(case, got, tiny_survey.output, hostile, tmp_path / "out")


@pytest.mark.parametrize("command", ["footprints", "gcp-find", "ortho"])
def test_each_bad_photo_is_skipped_with_its_reason_by_every_command(command, tiny_survey, hostile, tmp_path):
    """Issue 23 (3-4): garbage photos entered the mosaic, exit 0; one bad photo aborted the batch."""
    out = tmp_path / "out"
    case = next(c for c in CASES if c.id == f"{command}/bad-photos")
    got = run_case(case, tiny_survey.output, hostile, out, quiet=False)
    assert got.code == 0, got.stderr
    said = list(got.stderr)
    if command == "ortho":
        report = json.loads((out / "o_report.json").read_text())["skipped"]
        said += [f"skipped {s['image']}: {s['reason']}" for s in report]
    skipped = {}
    for name in BAD_PHOTOS:
        image = f"BAD_{name}.JPG"
        lines = [line for line in said if image in line]
        if lines:
            skipped[image] = " | ".join(lines)
    for name, (_, reason) in BAD_PHOTOS.items():
        image = f"BAD_{name}.JPG"
        if reason is None:
            assert image not in skipped, skipped.get(image)
        elif name == "pitch_0" and command != "ortho":
            continue  # a horizon view has a footprint (clipped) and can hold a GCP: only the mosaic refuses it
        elif name in ("no_altitude", "focal_0") and command == "gcp-find":
            continue  # searched whole / detected or not: neither can put a wrong GCP in the list
        elif name == "corrupt_scan" and command == "footprints":
            continue  # footprints read headers only
        else:
            assert image in skipped and re.search(reason, skipped[image]), (image, skipped.get(image))
    if command == "ortho":
        import rasterio

        with rasterio.open(out / "o.tif") as ds:
            assert ds.count == 4 and ds.crs.is_projected  # RGBA, georeferenced


@pytest.mark.parametrize(
    "argv",
    [
        ["gcp-find", "--images", "{h}/photos", "--gcp-file", "{s}/truth/gcp_utm.txt", "--output", "{o}/g.txt"],
        ["ortho", "--images", "{h}/photos", "--output", "{o}/o.tif"],
        ["footprints", "--images", "{h}/photos", "--output", "{o}/fp.shp"],
        ["dem", "--points", "{h}/outliers.laz", "--output", "{o}/d.tif", "--dtm", "{o}/t.tif"],
        ["sfm", "--images", "{s}/images", "--output", "{o}/sfm", "--max-image-size", "640"],  # COLMAP's own log
    ],
    ids=lambda a: a[0],
)
def test_stderr_holds_only_geoortho_lines(argv, tiny_survey, hostile, tmp_path):
    """Issue 23 (10): libjpeg's "Corrupt JPEG data", pyogrio's and geopandas' Shapefile warnings
    and others leaked to stderr between geoortho's own lines (C libraries write to fd 2)."""
    import subprocess

    fill = {"s": str(tiny_survey.output), "h": str(hostile), "o": str(tmp_path)}
    args = [a.format(**fill) for a in argv]
    r = subprocess.run([sys.executable, "-m", "geoortho", *args, "--quiet"], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    foreign = [ln for ln in r.stderr.splitlines() if ln.strip() and not ln.startswith(("warning: ", "geoortho "))]
    assert not foreign, foreign


def test_sigterm_stops_dem_before_writing_anything(tiny_survey, tmp_path):
    """Issue 23 (8): SIGTERM during dem wrote both rasters and then said "canceled"."""
    import signal
    import subprocess

    src = tmp_path / "big.laz"
    make_big = (
        "import numpy as np, laspy; from geoortho.core.pointcloud import write_las;"
        f"las = laspy.read({str(tiny_survey.points)!r}); xyz = np.c_[las.x, las.y, las.z];"
        "rng = np.random.default_rng(0); k = 60;"
        "big = np.vstack([xyz + [0, 0, rng.normal(0, 0.01)] for _ in range(k)]);"
        f"write_las({str(src)!r}, big, las.header.parse_crs())"
    )
    subprocess.run([sys.executable, "-c", make_big], check=True)
    p = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "geoortho",
            "dem",
            "--points",
            str(src),
            "--output",
            str(tmp_path / "dsm.tif"),
            "--dtm",
            str(tmp_path / "dtm.tif"),
            "--resolution-m",
            "0.1",
            "--progress-json",
        ],
        stderr=subprocess.PIPE,
        stdout=subprocess.DEVNULL,
        text=True,
    )
    assert p.stderr is not None
    lines = []
    for line in p.stderr:  # the handler is in place once the run reports anything
        lines.append(line)
        if "grid " in line:
            break
    p.send_signal(signal.SIGTERM)
    err = "".join(lines) + p.stderr.read()
    p.wait(timeout=120)
    if p.returncode == 0:
        pytest.skip("dem finished before the signal")
    assert p.returncode == 130 and json.loads(err.strip().splitlines()[-1])["type"] == "canceled", err
    assert not (tmp_path / "dsm.tif").exists() and not (tmp_path / "dtm.tif").exists()
    assert not list(tmp_path.glob(".*tmp*"))


def test_gcp_list_with_spaces_in_image_names_round_trips(tiny_survey, tmp_path):
    """Issue 23 (6): photo names with spaces broke the gcp_list.txt round trip into sfm."""
    from geoortho.gcp.find import gcp_find
    from geoortho.gcp.io import read_gcp_file

    images = tmp_path / "my photos"
    images.mkdir()
    for p in tiny_survey.images.iterdir():
        shutil.copy(p, images / p.name.replace("_", " "))
    found = gcp_find(images, tiny_survey.gcp_file, tmp_path / "gcp_list.txt")
    gl = read_gcp_file(found.output)
    names = {o.image for o in gl.observations}
    assert names and names <= {p.name for p in images.iterdir()}, names
    assert {o.gcp for o in gl.observations} <= {p.name for p in read_gcp_file(tiny_survey.gcp_file).points}


# ---------------------------------------------------------------------------------------------
# the counts, outside pytest


def _counts() -> None:
    import tempfile

    from geoortho.synthetic.survey import synth

    with tempfile.TemporaryDirectory() as d:
        root = Path(d)
        survey = synth(root / "tiny", preset="tiny", seed=3).output
        make_hostile(survey, root / "hostile")
        tally = {
            "cases": 0,
            "passed": 0,
            "products": 0,
            "named errors": 0,
            "unexpected errors": 0,
            "inputs destroyed": 0,
            "temporaries left": 0,
        }
        for k, case in enumerate(CASES):
            out = root / "out" / str(k)
            got = run_case(case, survey, root / "hostile", out)
            problems = judge(case, got, survey, root / "hostile", out)
            tally["cases"] += 1
            tally["passed"] += not problems
            tally["products"] += got.code == 0
            tally["named errors"] += got.code == 2
            tally["unexpected errors"] += got.code == 1
            tally["inputs destroyed"] += bool(got.changed_inputs)
            tally["temporaries left"] += bool(got.temporaries)
            print(f"{'ok ' if not problems else 'BAD'} {case.id}: exit {got.code}", *problems, sep="\n    ")
        print(json.dumps(tally, indent=1))


if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).parent))
    _counts()


@pytest.mark.parametrize("delay_s", [0.8, 1.2, 1.5, 1.7, 1.9, 2.2, 2.6])
def test_sigterm_to_the_process_group_as_ortho_starts_its_pool_ends_the_run(tiny_survey, tmp_path, delay_s):
    """Issue 76: a batch scheduler's SIGTERM to the process group just as ortho started its worker
    pool hung the run for ever (2 of 4 tries): the main process blocked writing to a worker that
    died while starting; later, shutting the pool down waited for ever on a result half written by a
    worker killed mid-write (1 of 14). At every moment of the start it ends: "canceled" and exit 130 (or done,
    when the signal came after the end), no process left in the group, no partial product."""
    import os
    import signal
    import subprocess
    import time

    out = tmp_path / "o.tif"
    p = subprocess.Popen(
        [sys.executable, "-m", "geoortho", "ortho", "--images", str(tiny_survey.images), "--output", str(out),
         "--workers", "2", "--resolution-m", "0.05"],
        stderr=subprocess.PIPE, stdout=subprocess.DEVNULL, text=True, start_new_session=True,
    )  # fmt: skip
    time.sleep(delay_s)
    os.killpg(p.pid, signal.SIGTERM)
    try:
        _, err = p.communicate(timeout=90)
    except subprocess.TimeoutExpired:
        os.killpg(p.pid, signal.SIGKILL)
        pytest.fail(f"ortho did not end within 90 s of SIGTERM sent {delay_s} s after its start")
    # 130 canceled; 0, or killed by the signal once the command had handed back (-15), with the product done
    assert p.returncode in (0, 130, -signal.SIGTERM), err
    if p.returncode == 130:
        assert "canceled" in err.strip().splitlines()[-1] and not out.exists()
    else:
        assert out.is_file() and "ortho:" in err
    deadline = time.monotonic() + 10
    while True:  # the workers go with the run
        try:
            os.killpg(p.pid, 0)
        except ProcessLookupError:
            break
        assert time.monotonic() < deadline, "a process of the run is left"
        time.sleep(0.1)
    assert not list(tmp_path.glob(".*tmp*"))


def test_an_aoi_across_the_antimeridian_is_planned_in_its_own_utm_zone(hostile, tmp_path):
    """Issue 76: an AOI from 179.9985 E to 179.9985 W was planned in the UTM zone of its naive centre,
    177 degrees away; it is 320 m wide, in zone 60 or 1."""
    import geoortho

    r = geoortho.plan(hostile / "aoi_antimeridian.geojson", tmp_path / "p", camera="DJI FC6310", gsd_cm=2.0)
    assert r.crs in ("EPSG:32760", "EPSG:32701"), r.crs
    import geopandas as gpd

    area = gpd.read_file(tmp_path / "p" / "plan.gpkg", layer="aoi").to_crs(r.crs).area.sum()
    assert 0.9 * 320 * 166 < area < 1.1 * 320 * 166, area
