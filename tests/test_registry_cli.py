"""The registry, the generated CLI and describe --json."""

from __future__ import annotations

import inspect
import json
import subprocess
import sys
from pathlib import Path

import pytest

from geoortho.errors import ParameterError
from geoortho.processing import PARAM_TYPES, list_algorithms, run_algorithm
from geoortho.processing.cli import ARGPARSE_OPTIONS, main
from geoortho.processing.registry import CONVERTERS, convert_value
from geoortho.processing.spec import Param, parse_docstring


def cli(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "geoortho", *args], capture_output=True, text=True, timeout=120)


def test_every_param_type_has_cli_and_converter_mapping():
    assert set(ARGPARSE_OPTIONS) == set(PARAM_TYPES)
    assert set(CONVERTERS) == set(PARAM_TYPES)


def test_unknown_param_type_is_refused():
    with pytest.raises(ValueError, match="unknown type"):
        Param("x", "colour")  # type: ignore[arg-type]


@pytest.mark.parametrize("alg", list_algorithms(), ids=lambda a: a.id)
def test_spec_matches_function_signature(alg):
    sig = inspect.signature(alg.function)
    assert "feedback" in sig.parameters and sig.parameters["feedback"].kind is inspect.Parameter.KEYWORD_ONLY
    spec_names = {p.name for p in alg.params}
    fn_names = {n for n in sig.parameters if n != "feedback"}
    assert spec_names == fn_names, f"{alg.id}: spec {spec_names ^ fn_names} differ from the function"
    for p in alg.params:
        fp = sig.parameters[p.name]
        if p.required:
            assert fp.default is inspect.Parameter.empty, f"{alg.id}.{p.name}: required in spec only"
        else:
            assert fp.default is not inspect.Parameter.empty, f"{alg.id}.{p.name}: required in function only"
            assert fp.default == p.default or (p.type == "folder" and str(fp.default) == str(p.default)), (
                f"{alg.id}.{p.name}: default {p.default!r} != {fp.default!r}"
            )
        assert p.help, f"{alg.id}.{p.name} has no help (docstring Parameters section)"
    assert alg.short_help and alg.title


def test_outputs_are_attributes_of_the_result_type():
    for alg in list_algorithms():
        ret = inspect.signature(alg.function).return_annotation
        hints = __import__("typing").get_type_hints(alg.function)
        result_type = hints.get("return", ret)
        fields = set(getattr(result_type, "__dataclass_fields__", {}))
        assert {o.name for o in alg.outputs} <= fields, alg.id


def test_converters_validate_ranges_and_types(tmp_path):
    assert convert_value(Param("n", "integer", default=0, minimum=0), "3") == 3
    with pytest.raises(ParameterError, match="n: 3.5"):
        convert_value(Param("n", "number", default=0, minimum=0, maximum=2, unit="m"), "3.5")
    with pytest.raises(ParameterError, match="expected an integer"):
        convert_value(Param("n", "integer", default=0), "2.5")
    with pytest.raises(ParameterError, match="not one of"):
        convert_value(Param("e", "enum", default="a", choices=("a", "b")), "c")
    assert convert_value(Param("b", "bool", default=False), "yes") is True
    with pytest.raises(ParameterError, match="no such file"):
        convert_value(Param("f", "file"), tmp_path / "missing.txt")
    assert convert_value(Param("f", "file", output=True), tmp_path / "new.txt") == tmp_path / "new.txt"
    assert convert_value(Param("c", "crs", default=None), "WGS84 UTM 29N").to_epsg() == 32629
    with pytest.raises(ParameterError, match="unknown CRS"):
        convert_value(Param("c", "crs", default=None), "EPSG:999999")


def test_parse_docstring_reads_numpydoc():
    d = parse_docstring(run_algorithm.__doc__ or "")
    assert d["summary"].startswith("Validate")


def test_help_lists_every_algorithm():
    r = cli("--help")
    assert r.returncode == 0
    for alg in list_algorithms():
        assert alg.id in r.stdout


def test_algorithm_help_shows_units_defaults_and_choices():
    r = cli("synth", "--help")
    assert r.returncode == 0
    assert "--marker-size-m" in r.stdout and "unit: m" in r.stdout
    assert "tiny,small,medium,oblique,hard" in r.stdout
    assert "default: 0" in r.stdout


def test_describe_json_round_trips():
    r = cli("describe", "--json")
    assert r.returncode == 0
    d = json.loads(r.stdout)
    assert json.loads(json.dumps(d)) == d
    ids = [a["id"] for a in d["algorithms"]]
    assert ids == [a.id for a in list_algorithms()]
    synth = next(a for a in d["algorithms"] if a["id"] == "synth")
    preset = next(p for p in synth["parameters"] if p["name"] == "preset")
    assert preset["type"] == "enum" and "tiny" in preset["choices"] and preset["qgis_name"] == "PRESET"
    assert preset["cli"] == "--preset"
    assert set(d["param_types"]) == set(PARAM_TYPES)


def test_made_up_option_exits_2_with_one_line():
    r = cli("synth", "--output", "x", "--no-such-option", "1")
    assert r.returncode == 2
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "--no-such-option" in lines[0]


def test_bad_value_exits_2_naming_the_option(tmp_path):
    r = cli("synth", "--output", str(tmp_path / "s"), "--seed", "-3")
    assert r.returncode == 2
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "seed" in lines[0] and "minimum" in lines[0]
    r = cli("synth", "--output", str(tmp_path / "s"), "--marker-size-m", "big")
    assert (
        r.returncode == 2 and "--marker-size-m" in r.stderr and "marker_size_m" not in r.stderr and "number" in r.stderr
    )


def test_missing_required_option_exits_2():
    r = cli("synth")
    assert r.returncode == 2 and "--output" in r.stderr and len(r.stderr.strip().splitlines()) == 1


def test_main_json_output(tmp_path, capsys):
    rc = main(
        [
            "synth",
            "--output",
            str(tmp_path / "t"),
            "--preset",
            "tiny",
            "--seed",
            "5",
            "--json",
            "--quiet",
            "--workers",
            "1",
        ]
    )
    assert rc == 0
    out = json.loads(capsys.readouterr().out)
    assert out["n_photos"] == len(list(Path(out["images"]).glob("*.JPG")))
    assert out["crs"] == "EPSG:32629"


def test_json_outputs_have_no_nan():
    # JSON has no NaN; "not measured" (e.g. no checkpoints) must reach QGIS and scripts as null.
    import numpy as np

    from geoortho.processing.registry import _jsonable

    assert _jsonable({"rmse": float("nan"), "n": np.int64(3), "inf": np.float32("inf")}) == {
        "rmse": None,
        "n": 3,
        "inf": None,
    }


@pytest.mark.parametrize(
    "args, what",
    [
        (["dem", "--points", "{d}/in.laz", "--output", "{d}/in.laz"], "points"),
        (["dem", "--points", "{d}/in.laz", "--output", "{d}/dsm.tif", "--dtm", "{d}/dsm.tif"], "output dsm"),
        (["dem", "--points", "{d}/in.laz", "--output", "{d}/dsm.tif", "--hillshade", "{d}/link.laz"], "points"),
        (["gcp-find", "--images", "{d}", "--gcp-file", "{d}/g.txt", "--output", "{d}/./g.txt"], "gcp-file"),
        (["ortho", "--images", "{d}", "--dsm", "{d}/d.tif", "--output", "{d}/d.tif"], "dsm"),
        (["footprints", "--images", "{d}", "--output", "{d}/fp.gpkg", "--overlap", "{d}/fp.gpkg"], "output output"),
    ],
)
def test_an_output_that_is_an_input_or_another_output_is_refused_untouched(tmp_path, capsys, args, what):
    """Issue 23 (1): writing an output onto an input destroyed it, exit 0. Refused before any work,
    the input byte for byte as it was; symlinks and '..' paths are the same file too."""
    import os

    for name, data in (
        ("in.laz", b"LASF" + bytes(range(200))),
        ("g.txt", b"EPSG:32629\nGCP1 1 2 3\n"),
        ("d.tif", b"II*\x00" + bytes(100)),
    ):
        (tmp_path / name).write_bytes(data)
    os.symlink(tmp_path / "in.laz", tmp_path / "link.laz")
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir() if p.is_file()}
    code = main([a.format(d=tmp_path) for a in args] + ["--quiet"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1, err
    assert "destroy" in err[0] or "also the output" in err[0], err[0]
    label = what.split()[-1]
    assert label in err[0], err[0]
    after = {p.name: p.read_bytes() for p in tmp_path.iterdir() if p.is_file()}
    assert after == before  # nothing touched, nothing written


@pytest.mark.parametrize(
    "alg, crs, message",
    [
        ("ortho", "EPSG:4326", "is not projected"),
        ("footprints", "EPSG:4978", "geocentric"),
        ("footprints", "EPSG:5773", "vertical"),
        ("footprints", "x" * 100_000, "unknown CRS"),
    ],
)
def test_a_crs_that_cannot_be_a_map_is_refused(tmp_path, capsys, alg, crs, message):
    """Issue 23 (7, 10): ortho --crs EPSG:4326 was ignored, footprints --crs EPSG:4978 wrote ECEF
    geometry, a 100 kB --crs was echoed back whole."""
    code = main([alg, "--images", str(tmp_path), "--output", str(tmp_path / "o.tif"), "--crs", crs, "--quiet"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and message in err[0] and len(err[0]) < 300, err


def test_progress_json_ends_with_a_json_error_line(tmp_path):
    """Issue 23 (10): with --progress-json every stderr line is JSON, the final error too."""
    r = cli("footprints", "--images", str(tmp_path / "none"), "--output", str(tmp_path / "f.gpkg"), "--progress-json")
    last = json.loads(r.stderr.strip().splitlines()[-1])
    assert r.returncode == 2 and last["type"] == "error" and last["exit_code"] == 2
    assert "no such folder" in last["message"] and last["message"].startswith("geoortho footprints: error:")


def test_no_room_for_the_output_is_said_before_any_work(tmp_path, capsys, monkeypatch):
    """Issue 23 (9): a full disk was found only after the computing, under a temporary's name."""
    import geoortho.processing.registry as registry

    monkeypatch.setattr(registry, "MIN_FREE_MB", 1e15)
    code = main(["synth", "--output", str(tmp_path / "s"), "--preset", "tiny", "--quiet"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and f"cannot write {tmp_path / 's'}" in err[0] and "MB free" in err[0]
    assert not (tmp_path / "s").exists()


def _ctrl_c_wrapped_by_a_c_extension() -> RuntimeError:
    """What pycolmap raises when Ctrl-C lands while its C++ backend starts: the KeyboardInterrupt,
    turned into ImportError by pybind11, turned into RuntimeError by pycolmap (seen in CI)."""
    try:
        try:
            try:
                raise KeyboardInterrupt
            except KeyboardInterrupt as e:
                raise ImportError("initialization failed") from e
        except ImportError as e:
            raise RuntimeError("Cannot import the C++ backend pycolmap._core.") from e
    except RuntimeError as e:
        return e


def test_a_ctrl_c_a_library_wrapped_is_still_canceled_with_130(tmp_path, capsys, monkeypatch):
    """A Ctrl-C 1.5 s into `ortho` reported 'unexpected error: RuntimeError: Cannot import the
    C++ backend' and exit 1: it had landed during pycolmap's import."""
    import geoortho.processing.cli as cli_module

    def interrupted_run(*args, **kwargs):
        raise _ctrl_c_wrapped_by_a_c_extension()

    monkeypatch.setattr(cli_module, "run_algorithm", interrupted_run)
    code = main(["synth", "--output", str(tmp_path / "s"), "--preset", "tiny", "--quiet"])
    assert code == 130 and capsys.readouterr().err.strip().splitlines() == ["geoortho synth: canceled"]

    def broken_run(*args, **kwargs):
        raise RuntimeError("Cannot import the C++ backend pycolmap._core.") from ImportError("no such file")

    monkeypatch.setattr(cli_module, "run_algorithm", broken_run)
    code = main(["synth", "--output", str(tmp_path / "s"), "--preset", "tiny", "--quiet"])
    assert code == 1 and "unexpected error: RuntimeError" in capsys.readouterr().err


def test_pycolmap_interrupted_while_loading_raises_keyboard_interrupt(monkeypatch):
    """The Python API's caller gets the Ctrl-C back as itself, not as a broken install."""
    import builtins

    from geoortho.core.colmap import load_pycolmap

    real_import = builtins.__import__

    def importing(name, *args, **kwargs):
        if name == "pycolmap":
            raise _ctrl_c_wrapped_by_a_c_extension()
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", importing)
    with pytest.raises(KeyboardInterrupt):
        load_pycolmap()


def test_a_ctrl_c_a_library_swallows_still_cancels_the_run(tmp_path, capsys, monkeypatch):
    """A Ctrl-C that landed while an optional library loaded, caught there as its ImportError,
    was lost: the command ran to the end and exited 0. The run stops at its next progress call."""
    import os
    import signal

    import geoortho.processing.cli as cli_module

    def run_whose_library_swallows_the_interrupt(alg, values, feedback, **kwargs):
        try:
            os.kill(os.getpid(), signal.SIGINT)
            signal.sigtimedwait([], 1.0)  # the handler runs here, at the latest
        except KeyboardInterrupt:
            pass  # as `try: import optional except ImportError:` does with pybind11's wrapping
        feedback.progress(0.5)
        return {}

    monkeypatch.setattr(cli_module, "run_algorithm", run_whose_library_swallows_the_interrupt)
    # a command's process: SIGINT has Python's own handler and is not blocked (the test worker may
    # have been left otherwise by an earlier test's library: CI once saw this run end with 0)
    handler = signal.signal(signal.SIGINT, signal.default_int_handler)
    mask = signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})
    try:
        before = signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)
        code = main(["synth", "--output", str(tmp_path / "s"), "--preset", "tiny", "--quiet"])
        assert code == 130 and capsys.readouterr().err.strip().splitlines() == ["geoortho synth: canceled"]
        assert (signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)) == before
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, mask)
        signal.signal(signal.SIGINT, handler)


def test_a_ctrl_c_caught_inside_an_exec_still_exits_130(tmp_path, capsys, monkeypatch):
    """`ortho` printed 'canceled' and then died by SIGINT (-2, not 130) when the Ctrl-C landed as
    a dataclass built its methods: CPython 3.11 kept the interrupt marked unhandled, and under
    `python -m` ends so at exit. The mark is read where the interpreter exports it."""
    import ctypes

    import geoortho.processing.cli as cli_module

    try:
        mark = ctypes.c_int.in_dll(ctypes.pythonapi, "_Py_UnhandledKeyboardInterrupt")
    except ValueError:
        pytest.skip("this interpreter does not export the mark")

    def run_interrupted_inside_an_exec(*args, **kwargs):
        exec("raise KeyboardInterrupt")

    def run_whose_library_caught_it_inside_an_exec(*args, **kwargs):
        try:
            exec("raise KeyboardInterrupt")
        except KeyboardInterrupt:
            pass  # and the run ends without another progress call
        return {}

    try:
        monkeypatch.setattr(cli_module, "run_algorithm", run_interrupted_inside_an_exec)
        code = main(["synth", "--output", str(tmp_path / "s"), "--preset", "tiny", "--quiet"])
        assert code == 130 and capsys.readouterr().err.strip().splitlines() == ["geoortho synth: canceled"]
        assert mark.value == 0
        monkeypatch.setattr(cli_module, "run_algorithm", run_whose_library_caught_it_inside_an_exec)
        assert main(["synth", "--output", str(tmp_path / "s"), "--preset", "tiny", "--quiet"]) == 0
        assert mark.value == 0
    finally:
        mark.value = 0  # this test process itself runs under `python -m pytest`


@pytest.mark.parametrize("alg", list_algorithms(), ids=lambda a: a.id)
def test_help_is_for_people(alg, capsys):
    """One options heading, no reStructuredText, each option by its flag (not its Python name),
    no module path, no empty default, a long choice list once."""
    import re

    with pytest.raises(SystemExit):
        main([alg.id, "--help"])
    text = capsys.readouterr().out
    assert text.count("options:") == 1 and "required" in text or not any(p.required for p in alg.params)
    assert "``" not in text and not re.search(r":(mod|func|class|meth):`", text)
    assert "(default: )" not in text and "default: ;" not in text
    assert not re.search(r"\bgeoortho\.[a-z]", text), re.search(r".{30}\bgeoortho\.[a-z].{20}", text)
    python_names = {p.name for p in alg.params if "_" in p.name}
    for name in python_names:
        assert not re.search(rf"(?<![\w./-]){name}(?![\w]|\.\w)", text), name
    flat = " ".join(text.split())
    for p in alg.params:
        if p.type == "enum" and len(p.choices) > 8:  # a long list: once, in its help, not in the usage too
            assert "{" + ",".join(p.choices) + "}" not in text and flat.count(", ".join(p.choices)) == 1, p.name


def test_an_error_names_the_option_by_its_flag(tmp_path):
    r = cli("dem", "--points", str(tmp_path / "x.laz"), "--output", str(tmp_path / "d.tif"))
    assert r.returncode == 2 and "error: --points: no such file" in r.stderr, r.stderr
    r = cli("dem", "--points", __file__, "--output", str(tmp_path / "d.tif"), "--resolution-m", "-1")
    assert r.returncode == 2 and "--resolution-m" in r.stderr and "resolution_m" not in r.stderr, r.stderr
