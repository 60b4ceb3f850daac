"""The Python API as a first-class face: every public name callable, whatever was loaded first."""

from __future__ import annotations

import dataclasses
import inspect
import json
import re
import subprocess
import sys
import typing
from pathlib import Path

import pytest

import geoortho
from geoortho.processing import list_algorithms
from geoortho.processing.spec import parse_docstring
from geoortho.processing.static import StaticReadError, read_function

ALGORITHM_FUNCTIONS = {a.function_ref.split(":")[1] for a in list_algorithms()}

# Loads every face first (the registry, the CLI's parser, describe --json and the QGIS
# provider's reading of it), wraps every public function to record that it was called,
# runs the README's Python example (the whole chain on a tiny survey), then calls the
# public names it does not: a module named like a function would shadow it and fail.
_PRELUDE = r"""
import json, sys, dataclasses, inspect
from pathlib import Path
from geoortho.processing.cli import build_parser
from geoortho.processing.registry import describe, list_algorithms
from geoortho.qgis_provider.interpreter import load_description
build_parser(); describe(); [a.function for a in list_algorithms()]
load_description(sys.executable, Path("describe_cache.json"))
import geoortho

seen = {}
def _recorder(name, fn):
    def wrapped(*args, **kw):
        r = fn(*args, **kw)
        seen[name] = type(r).__name__
        return r
    return wrapped
for _name in geoortho.__all__:
    _value = getattr(geoortho, _name)
    assert not inspect.ismodule(_value), f"geoortho.{_name} is a module"
    if inspect.isfunction(_value):
        setattr(geoortho, _name, _recorder(_name, _value))
"""

_EPILOGUE = r"""
demo = geoortho.demo(Path("demo"), preset="tiny", seed=5, surface="lidar")  # run with dense: test_pipeline
photos = geoortho.read_photos(survey.images)
geoortho.read_photo(photos.photos[0].path)
geoortho.read_gcp_file(survey.gcp_file)
for name in ("TerminalFeedback", "Feedback"):
    getattr(geoortho, name)()
    seen[name] = "feedback"
for name in ("GeoorthoError", "InputError", "CanceledError"):
    assert issubclass(getattr(geoortho, name), Exception)
    seen[name] = "exception"
for name in geoortho.__all__:
    if name.endswith("Result") or name in ("Photo", "GcpSet"):
        assert dataclasses.is_dataclass(getattr(geoortho, name)), name
        seen[name] = "dataclass"
print(json.dumps({"seen": seen, "n_photos": survey.n_photos, "fp": fp.n_photos, "obs": found.n_observations,
                  "registered": model.n_registered, "ortho_used": mosaic.n_used, "demo": sorted(demo.products),
                  "run": result["n_photos"]}))
"""


def _readme_python() -> str:
    readme = (Path(__file__).resolve().parents[1] / "README.md").read_text(encoding="utf-8")
    section = readme[readme.index("## Python") :]
    start = section.index("```python") + len("```python")
    return section[start : section.index("```\n", start)]


@pytest.mark.slow
def test_every_public_name_is_callable_after_every_face_is_loaded_and_the_readme_runs(tmp_path):
    code = _PRELUDE + _readme_python() + _EPILOGUE
    proc = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, proc.stderr[-3000:]
    got = json.loads(proc.stdout.strip().splitlines()[-1])
    assert set(got["seen"]) == set(geoortho.__all__)
    # each algorithm returned its own result dataclass, and a real one
    assert got["seen"]["synth"] == "SynthResult" and got["seen"]["ortho"] == "OrthoResult"
    assert got["seen"]["gcp_find"] == "GcpFindResult" and got["seen"]["dem"] == "DemResult"
    assert got["seen"]["sfm"] == "SfmResult" and got["seen"]["demo"] == "DemoResult"
    assert got["seen"]["run"] == "RunResult" and got["seen"]["report"] == "ReportResult"
    assert got["fp"] == got["n_photos"] == got["run"]
    assert got["obs"] > 0 and got["registered"] >= got["n_photos"] - 1 and got["ortho_used"] >= 2
    assert {"footprints", "gcp_list", "dsm", "ortho"} <= set(got["demo"])
    assert (tmp_path / "ortho.tif").is_file() and "m pixels" in proc.stdout
    assert (tmp_path / "project" / "report.html").is_file() and (tmp_path / "report_copy.html").is_file()


def test_public_names_resolve_to_functions_and_dataclasses_not_modules():
    # loading the registry, the CLI and every core module first must not shadow an export
    import geoortho.processing.cli  # noqa: F401

    for alg in list_algorithms():
        alg.function  # noqa: B018 (imports the module the spec names)
    for name in geoortho.__all__:
        value = getattr(geoortho, name)
        assert not inspect.ismodule(value), f"geoortho.{name} is a module"
    for name in ALGORITHM_FUNCTIONS:
        assert name in geoortho.__all__, f"algorithm function {name} is not exported"
        assert inspect.isfunction(getattr(geoortho, name))


@pytest.mark.parametrize("alg", list_algorithms(), ids=lambda a: a.id)
def test_result_dataclass_documents_every_field(alg):
    fn = alg.function
    result_type = typing.get_type_hints(fn)["return"]
    assert dataclasses.is_dataclass(result_type)
    assert getattr(geoortho, result_type.__name__) is result_type, f"{result_type.__name__} is not exported"
    documented = parse_docstring(result_type.__doc__ or "")["attributes"]
    fields = {f.name for f in dataclasses.fields(result_type)}
    assert fields == set(documented), f"{result_type.__name__}: undocumented {fields - set(documented)}"
    assert all(documented.values())


@pytest.mark.parametrize("alg", list_algorithms(), ids=lambda a: a.id)
def test_static_reading_equals_the_imported_signature(alg):
    """Defaults and choices read from the source are what Python sees when it runs it."""
    fn = alg.function
    sig = inspect.signature(fn)
    hints = typing.get_type_hints(fn)
    for p in alg.params:
        fp = sig.parameters[p.name]
        assert p.required == (fp.default is inspect.Parameter.empty), p.name
        if not p.required:
            assert p.default == fp.default, f"{alg.id}.{p.name}: {p.default!r} != {fp.default!r}"
        hint = hints[p.name]
        options = (hint,) if typing.get_origin(hint) is typing.Literal else typing.get_args(hint)
        literal = [a for a in options if typing.get_origin(a) is typing.Literal]
        if p.type == "enum":
            assert literal and tuple(typing.get_args(literal[0])) == p.choices, p.name
        else:
            assert not literal, f"{alg.id}.{p.name} is a Literal but not an enum"
    assert inspect.getdoc(fn) == read_function(alg.function_ref).doc


def test_shared_parameters_mean_the_same_everywhere():
    helps: dict[str, set[str]] = {}
    for alg in list_algorithms():
        for p in alg.params:
            helps.setdefault(p.name, set()).add(p.help)
    assert len(helps["takeoff_elevation_m"]) == 1, helps["takeoff_elevation_m"]
    resolution = [(a.id, p.name, p.unit) for a in list_algorithms() for p in a.params if "resolution" in p.name]
    assert resolution == [("dem", "resolution_m", "m"), ("ortho", "resolution_m", "m")]


def test_marker_dictionaries_are_opencvs():
    import cv2

    from geoortho.gcp.markers import DICTIONARIES

    assert set(DICTIONARIES) == {n for n in dir(cv2.aruco) if n.startswith("DICT_") and n == n.upper()}


def test_presets_are_the_literal():
    from geoortho.synthetic.presets import PRESETS, Preset

    assert set(typing.get_args(Preset)) == set(PRESETS)


def test_the_ready_made_description_is_fresh_and_read_back_exactly():
    """``--help`` reads the registry's functions ready-made; they must be what the sources say."""
    from geoortho.processing import static
    from geoortho.processing.algorithms import ALGORITHMS

    fresh = static.ready_made_text([a.function_ref for a in ALGORITHMS])
    assert static.READY_MADE.read_text() == fresh, "stale: run `python tools/write_described.py` and commit it"
    for alg in list_algorithms():
        assert static.read_function(alg.function_ref) == static._read_source(alg.function_ref), alg.id


def test_static_reader_refuses_what_it_cannot_read(tmp_path, monkeypatch):
    import geoortho.processing.static as static

    pkg = tmp_path / "geoortho"
    pkg.mkdir()
    (pkg / "odd.py").write_text(
        "import os\n\ndef f(a: int = os.cpu_count(), *, feedback=None) -> None:\n    '''Doc.'''\n"
    )
    monkeypatch.setattr(static, "_PACKAGE_DIR", pkg)
    with pytest.raises(StaticReadError, match="parameter a"):
        static.read_function.__wrapped__("geoortho.odd:f")


def test_cli_help_imports_no_heavy_stack():
    code = (
        "import sys\nfrom geoortho.processing.cli import build_parser\nfrom geoortho.processing.registry "
        "import describe\nbuild_parser(); describe()\n"
        "heavy = [m for m in ('cv2', 'pycolmap', 'rasterio', 'scipy', 'numpy', 'pyproj', 'geopandas') "
        "if m in sys.modules]\nprint(','.join(heavy))"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == ""


def test_resolution_alias_still_accepted(tmp_path):
    from geoortho.processing.cli import build_parser

    args = build_parser().parse_args(["ortho", "--images", str(tmp_path), "--output", "o.tif", "--resolution", "0.05"])
    assert args.resolution_m == "0.05"


def test_ortho_refuses_a_crs_in_feet(tiny_survey, tmp_path):
    with pytest.raises(geoortho.InputError, match="metres"):
        geoortho.ortho(tiny_survey.images, tmp_path / "o.tif", crs="EPSG:2227")
    assert not list(Path(tmp_path).iterdir())


@pytest.mark.parametrize(
    ("call", "message"),
    [
        (lambda g: g.footprints(123, 456), "images: 123 is int, not a path"),
        (lambda g: g.dem("a.laz", "b.tif", resolution_m="0.5"), "resolution_m: '0.5' is str, not a number"),
        (lambda g: g.gcp_find("i", "g.txt", "o.txt", workers="2"), "workers: '2' is str, not an integer"),
        (lambda g: g.ortho("i", "o.tif", blend=True), "blend: True is bool, not one of the choices"),
        (lambda g: g.dem(), "missing a required argument: 'points'"),
    ],
)
def test_the_api_checks_argument_types_at_the_door(call, message):
    """A wrong type is refused with the parameter's name (as the CLI refuses it), before any work,
    never a bare TypeError from deep inside."""
    import geoortho

    with pytest.raises(geoortho.InputError, match=re.escape(message)):
        call(geoortho)


@pytest.mark.parametrize(
    ("call", "message"),
    [
        (lambda g: g.sfm("i", "o", crs="EPSG:4326"), "crs: WGS 84 is not projected: sfm needs a map grid"),
        (lambda g: g.dem("a.laz", "b.tif", crs="EPSG:4978"), "crs: WGS 84 is geocentric"),
        (lambda g: g.plan("a.gpkg", "o", crs="not a crs"), "crs: "),
        (lambda g: g.gcp_find("i", "g.txt", "o.txt", gcp_crs="EPSG:5773"), "gcp_crs: EGM96 height is a vertical CRS"),
    ],
)
def test_the_api_parses_and_checks_a_crs_at_the_door(call, message):
    """A CRS given to the API as text is parsed and held to the command line's rules at the door,
    before any file is read (the inputs here do not exist): the core never parses one."""
    with pytest.raises(geoortho.InputError, match=re.escape(message)):
        call(geoortho)


def test_the_core_takes_a_crs_never_a_string():
    """Every algorithm's CRS parameter is a pyproj CRS in the core function's signature: the faces
    (CLI, API door, QGIS) parse it once; the core neither parses nor re-checks it."""
    from pyproj import CRS

    for alg in list_algorithms():
        hints = typing.get_type_hints(alg.function)
        for p in alg.params:
            if p.type == "crs":
                assert hints[p.name] == CRS | None, (alg.id, p.name, hints[p.name])


def test_a_crs_given_as_text_reaches_the_core_parsed(tmp_path):
    """The door hands the core function the parsed CRS (legacy ODM words included), not the text."""
    import pyproj

    got = {}

    def footprints(images, output, *args, crs=None, **kwargs):
        got["crs"] = crs

    door = geoortho._checked(footprints, "geoortho.photos.footprint:footprints")
    door(tmp_path, tmp_path / "f.gpkg", crs="WGS84 UTM 29N")
    assert isinstance(got["crs"], pyproj.CRS) and got["crs"].to_epsg() == 32629


def _out_of_spec(p):
    """Values the spec rules out for ``p`` (an enum's stranger, a number past its bounds)."""
    if p.type == "enum":
        return [p.choices[0].upper() + "x", ""]
    bad = []
    if p.minimum is not None:
        bad.append(p.minimum - (1 if p.type == "integer" else 0.5 + abs(p.minimum)))
    if p.maximum is not None:
        bad.append(p.maximum + (1 if p.type == "integer" else 0.5 + abs(p.maximum)))
    return [int(v) if p.type == "integer" else float(v) for v in bad]


_DUMMY = {"number": 1.0, "integer": 1, "bool": True, "string": "x", "crs": "EPSG:4326"}


@pytest.mark.parametrize("alg", list_algorithms(), ids=lambda a: a.id)
def test_the_api_refuses_what_the_spec_rules_out_before_any_work(alg, tmp_path):
    """Every choice and bound the CLI and QGIS enforce, the Python API does too, in the same
    words: synth(glare_style="foo") once drew the default and went on."""
    import geoortho

    fn = getattr(geoortho, alg.function_ref.split(":")[1])
    required = {p.name: _DUMMY.get(p.type, str(tmp_path / "in")) for p in alg.params if p.required}
    checked = 0
    for p in alg.params:
        for value in _out_of_spec(p):
            with pytest.raises(geoortho.InputError, match=f"^{p.name}: .*(not one of|minimum|maximum)"):
                fn(**{**required, p.name: value})
            checked += 1
    assert not list(tmp_path.iterdir())
    assert checked > 0 or alg.id in ("report", "copc")  # their only parameters are paths (and a CRS)
