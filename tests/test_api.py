"""The Python API as a first-class face: every public name callable, whatever was loaded first."""

from __future__ import annotations

import dataclasses
import inspect
import json
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
# provider's reading of it), then calls every public name on a tiny survey: a module
# named like a function would shadow it here and the call would fail.
_SCRIPT = r"""
import json, sys, dataclasses
from pathlib import Path
from geoortho.processing.cli import build_parser
from geoortho.processing.registry import describe, list_algorithms, run_algorithm as _run
from geoortho.qgis_provider.interpreter import load_description
build_parser(); describe(); [a.function for a in list_algorithms()]
load_description(sys.executable, Path(sys.argv[1]) / "describe_cache.json")
import geoortho

out = Path(sys.argv[1]); seen = {}
def call(name, *args, **kw):
    value = getattr(geoortho, name)
    assert callable(value), f"geoortho.{name} is {type(value).__name__}, not callable"
    r = value(*args, **kw)
    seen[name] = type(r).__name__
    return r

s = call("synth", out / "survey", preset="tiny", seed=5)
f = call("footprints", s.images, out / "fp.gpkg", dsm=s.dsm)
g = call("gcp_find", s.images, s.gcp_file, out / "gcp_list.txt", dsm=s.dsm)
d = call("dem", s.points, out / "dsm.tif", dtm=out / "dtm.tif")
m = call("sfm", s.images, out / "sfm", gcp_list=g.output, max_image_size=640, max_features=2048)
o = call("ortho", s.images, out / "ortho.tif", sfm=m.output, dsm=d.dsm)
demo = call("demo", out / "demo", preset="tiny", seed=5)
photos = call("read_photos", s.images)
call("read_photo", photos.photos[0].path)
call("read_gcp_file", s.gcp_file)
r = call("run_algorithm", "footprints", {"images": str(s.images), "output": str(out / "fp2.gpkg")})
for name in ("TerminalFeedback", "Feedback"):
    call(name)
for name in ("GeoorthoError", "InputError", "CanceledError"):
    assert issubclass(getattr(geoortho, name), Exception)
    seen[name] = "exception"
for name in geoortho.__all__:
    if name.endswith("Result") or name in ("Photo", "GcpSet"):
        assert dataclasses.is_dataclass(getattr(geoortho, name)), name
        seen[name] = "dataclass"
print(json.dumps({"seen": seen, "n_photos": s.n_photos, "fp": f.n_photos, "obs": g.n_observations,
                  "registered": m.n_registered, "ortho_used": o.n_used, "demo": sorted(demo.products),
                  "run": r["n_photos"]}))
"""


@pytest.mark.slow
def test_every_public_name_is_callable_after_every_face_is_loaded(tmp_path):
    proc = subprocess.run([sys.executable, "-c", _SCRIPT, str(tmp_path)], capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, proc.stderr[-3000:]
    got = json.loads(proc.stdout.strip().splitlines()[-1])
    assert set(got["seen"]) == set(geoortho.__all__)
    # each algorithm returned its own result dataclass, and a real one
    assert got["seen"]["synth"] == "SynthResult" and got["seen"]["ortho"] == "OrthoResult"
    assert got["seen"]["gcp_find"] == "GcpFindResult" and got["seen"]["dem"] == "DemResult"
    assert got["fp"] == got["n_photos"] == got["run"]
    assert got["obs"] > 0 and got["registered"] >= got["n_photos"] - 1 and got["ortho_used"] >= 2
    assert {"footprints", "gcp_list", "dsm", "ortho"} <= set(got["demo"])


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

    from geoortho.markers import DICTIONARIES

    assert set(DICTIONARIES) == {n for n in dir(cv2.aruco) if n.startswith("DICT_") and n == n.upper()}


def test_presets_are_the_literal():
    from geoortho.synthetic import PRESETS, Preset

    assert set(typing.get_args(Preset)) == set(PRESETS)


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


@pytest.mark.slow
def test_readme_python_example_runs(tmp_path):
    """The README's Python section is code that works, not a sketch."""
    readme = (Path(__file__).resolve().parents[1] / "README.md").read_text(encoding="utf-8")
    section = readme[readme.index("## Python") :]
    code = section[
        section.index("```python") + len("```python") : section.index("```\n", section.index("```python") + 9)
    ]
    proc = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert (tmp_path / "ortho.tif").is_file() and (tmp_path / "gcp_list.txt").is_file()
    assert "m pixels" in proc.stdout
