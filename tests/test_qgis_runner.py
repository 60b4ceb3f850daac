"""The QGIS provider's qgis-free half: finding geoortho's Python, the cached
registry description, and running the CLI with progress and Cancel.

The provider itself is tested in a real QGIS by ``make test-qgis`` (tests_qgis/).
"""

from __future__ import annotations

import configparser
import json
import os
import sys
import time
from pathlib import Path

import pytest

import geoortho
from geoortho.qgis_provider import interpreter as interp
from geoortho.qgis_provider.runner import (
    RunCanceled,
    RunFailed,
    remove_partial_outputs,
    run_geoortho,
)

PROVIDER_DIR = Path(interp.__file__).parent


class Recorder:
    """QgsProcessingFeedback's interface, recording what it is told."""

    def __init__(self, cancel_at_percent: float | None = None) -> None:
        self.progress: list[float] = []
        self.info: list[str] = []
        self.warnings: list[str] = []
        self.console: list[str] = []
        self.progress_text: list[str] = []
        self._cancel_at = cancel_at_percent

    def setProgress(self, percent: float) -> None:  # noqa: N802
        self.progress.append(percent)

    def pushInfo(self, text: str) -> None:  # noqa: N802
        self.info.append(text)

    def pushWarning(self, text: str) -> None:  # noqa: N802
        self.warnings.append(text)

    def pushConsoleInfo(self, text: str) -> None:  # noqa: N802
        self.console.append(text)

    def setProgressText(self, text: str) -> None:  # noqa: N802
        self.progress_text.append(text)

    def isCanceled(self) -> bool:  # noqa: N802
        return self._cancel_at is not None and any(p >= self._cancel_at for p in self.progress)


def test_plugin_metadata_is_geoortho_s():
    meta = configparser.ConfigParser()
    meta.read(PROVIDER_DIR / "metadata.txt")
    general = meta["general"]
    assert general["version"] == geoortho.__version__
    assert general["hasProcessingProvider"] == "yes"  # qgis_process loads nothing else
    assert (PROVIDER_DIR / general["icon"]).is_file()


def test_interpreter_setting_then_environment(monkeypatch, tmp_path):
    monkeypatch.setenv(interp.ENV_VAR, sys.executable)
    assert interp.find_interpreter("") == sys.executable
    with pytest.raises(interp.InterpreterError, match="Processing > Options > Providers > geoortho"):
        interp.find_interpreter(str(tmp_path / "python"))  # a wrong setting is said, not skipped
    monkeypatch.setenv(interp.ENV_VAR, str(tmp_path / "python"))
    with pytest.raises(interp.InterpreterError, match=interp.ENV_VAR):
        interp.find_interpreter("")


def test_interpreter_found_from_the_importable_package(monkeypatch):
    monkeypatch.delenv(interp.ENV_VAR, raising=False)
    python = interp.find_interpreter("")
    # It runs the very geoortho this process imports.
    import subprocess

    out = subprocess.run(
        [python, "-c", "import geoortho; print(geoortho.__file__)"],
        capture_output=True,
        text=True,
        check=True,
        env=interp.clean_environment(),
    ).stdout.strip()
    assert Path(out).resolve() == Path(geoortho.__file__).resolve()


def test_interpreter_from_the_console_script_shebang(monkeypatch, tmp_path):
    script = tmp_path / "geoortho"
    script.write_text(f"#!{sys.executable}\nimport sys\n")
    script.chmod(0o755)
    monkeypatch.setenv("PATH", str(tmp_path))
    assert interp._from_console_script() == Path(sys.executable)
    script.write_text("no shebang\n")
    assert interp._from_console_script() is None


def test_qgis_variables_do_not_reach_geoortho(monkeypatch):
    monkeypatch.setenv("PROJ_LIB", "/qgis/share/proj")
    monkeypatch.setenv("PYTHONHOME", "/qgis/apps/python")
    env = interp.clean_environment()
    assert "PROJ_LIB" not in env and "PYTHONHOME" not in env and env["PYTHONUNBUFFERED"] == "1"


def test_description_is_cached_until_geoortho_changes(tmp_path):
    cache = tmp_path / "description.json"
    fresh = interp.load_description(sys.executable, cache)
    assert {a["id"] for a in fresh["algorithms"]} >= {"footprints", "synth", "ortho"}
    assert Path(fresh["package_dir"]).resolve() == Path(geoortho.__file__).resolve().parent
    # A cache hit returns the cached record: mark it and read it back.
    record = json.loads(cache.read_text())
    record["description"]["version"] = "cached-marker"
    cache.write_text(json.dumps(record))
    assert interp.load_description(sys.executable, cache)["version"] == "cached-marker"
    # Another geoortho (here: a changed package signature) is asked again.
    record["package"] = "something else"
    cache.write_text(json.dumps(record))
    assert interp.load_description(sys.executable, cache)["version"] == geoortho.__version__


def test_package_signature_sees_an_edit(tmp_path):
    (tmp_path / "a.py").write_text("x = 1\n")
    before = interp._package_signature(str(tmp_path))
    (tmp_path / "a.py").write_text("x = 22\n")
    assert interp._package_signature(str(tmp_path)) != before


def test_describe_failure_says_how_to_set_the_interpreter(tmp_path):
    fake = tmp_path / "python"
    fake.write_text("#!/bin/sh\necho 'No module named geoortho' >&2\nexit 1\n")
    fake.chmod(0o755)
    with pytest.raises(interp.InterpreterError, match="cannot run geoortho .No module named geoortho"):
        interp.load_description(str(fake))


def test_run_reports_progress_and_returns_the_outputs(tiny_survey, tmp_path):
    fb = Recorder()
    out = tmp_path / "f.gpkg"
    outputs = run_geoortho(sys.executable, "footprints", [f"--images={tiny_survey.images}", f"--output={out}"], fb)
    assert outputs["output"] == str(out) and out.is_file()
    assert outputs["n_photos"] == len(list(tiny_survey.images.glob("*.JPG")))
    assert fb.progress[-1] == pytest.approx(100.0) and fb.progress == sorted(fb.progress)
    assert any("footprints" in m for m in fb.info)


def test_bad_input_raises_with_geoortho_s_line(tmp_path):
    with pytest.raises(RunFailed, match="geoortho footprints: error: images: no such folder") as e:
        run_geoortho(
            sys.executable, "footprints", [f"--images={tmp_path / 'x'}", f"--output={tmp_path / 'f.gpkg'}"], Recorder()
        )
    assert e.value.returncode == 2


def test_cancel_stops_the_process_and_leaves_no_temporary(tmp_path):
    fb = Recorder(cancel_at_percent=1.0)
    t0 = time.monotonic()
    with pytest.raises(RunCanceled):
        run_geoortho(
            sys.executable, "synth", [f"--output={tmp_path / 's'}", "--preset=tiny"], fb, destinations=[tmp_path / "s"]
        )
    assert time.monotonic() - t0 < 60
    assert max(fb.progress) < 100.0
    assert not [p for p in tmp_path.rglob("*") if ".tmp-" in p.name]


def test_remove_partial_outputs_touches_only_temporaries(tmp_path):
    # The runner cannot import geoortho (it runs in QGIS), so it knows the
    # temporary name by convention: check it against the writer's own.
    from geoortho.core.outputs import atomic_path

    (tmp_path / "dsm.tif").write_bytes(b"whole")
    (tmp_path / ".other.tmp-1.tif").write_bytes(b"someone else's")
    with pytest.raises(RuntimeError, match="writer produced no file"):
        with atomic_path(tmp_path / "dsm.tif") as half:
            half.write_bytes(b"half")  # a run killed mid-write leaves this
            removed = remove_partial_outputs([tmp_path / "dsm.tif"])
            assert removed == [half]
    assert sorted(os.listdir(tmp_path)) == [".other.tmp-1.tif", "dsm.tif"]
