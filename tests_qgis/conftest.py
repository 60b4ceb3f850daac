"""Real headless QGIS for the provider tests (run by ``make test-qgis`` in .venv-qgis).

The environment is set before anything imports qgis: no display, a throwaway
QGIS profile, Debian's bindings and Processing plugin on the path.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest

os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")
os.environ.setdefault("XDG_RUNTIME_DIR", tempfile.mkdtemp(prefix="geoortho-xdg-"))
PROFILE = Path(os.environ.setdefault("QGIS_CUSTOM_CONFIG_PATH", tempfile.mkdtemp(prefix="geoortho-qgis-")))
# The interpreter geoortho runs in: this test environment's (it has geoortho).
PYTHON = os.environ.setdefault("GEOORTHO_PYTHON", sys.executable)
if "/usr/lib/python3/dist-packages" not in sys.path:
    sys.path.append("/usr/lib/python3/dist-packages")
sys.path.insert(0, "/usr/share/qgis/python/plugins")  # Processing

PROJECT = Path(__file__).resolve().parents[1]
sys.path.append(str(PROJECT / "tests"))  # realdata: where ../shared/data/real is


def geoortho_cli(*args: str, check: bool = True) -> subprocess.CompletedProcess[str]:
    """``python -m geoortho ...`` as a user would run it."""
    r = subprocess.run([PYTHON, "-m", "geoortho", *args], capture_output=True, text=True)
    if check and r.returncode != 0:
        raise AssertionError(f"geoortho {' '.join(args)} failed ({r.returncode}): {r.stderr[-2000:]}")
    return r


def qgis_run(alg_id: str, params: dict, feedback=None, context=None) -> dict:
    """``processing.run("geoortho:<alg_id>", ...)`` as a script in QGIS would call it."""
    import processing
    from qgis.core import QgsProcessingContext, QgsProcessingFeedback

    return processing.run(
        f"geoortho:{alg_id}",
        params,
        feedback=feedback or QgsProcessingFeedback(),
        context=context or QgsProcessingContext(),
    )


@pytest.fixture(scope="session")
def qgis_app():
    from qgis.core import QgsApplication

    QgsApplication.setPrefixPath("/usr", True)
    app = QgsApplication([], False)
    app.initQgis()
    from processing.core.Processing import Processing

    Processing.initialize()
    yield app
    app.exitQgis()


@pytest.fixture(scope="session")
def provider(qgis_app):
    """geoortho's provider, registered (and kept referenced: pitfall 2 of the recipe)."""
    from qgis.core import QgsApplication

    from geoortho.qgis_provider.provider import GeoorthoProvider

    p = GeoorthoProvider()
    assert QgsApplication.processingRegistry().addProvider(p)
    yield p
    QgsApplication.processingRegistry().removeProvider(p)


@pytest.fixture(scope="session")
def description() -> dict:
    """The registry as the CLI describes it (what the provider must mirror)."""
    return json.loads(geoortho_cli("describe", "--json").stdout)


@pytest.fixture(scope="session")
def tiny(tmp_path_factory) -> Path:
    """The synthetic ``tiny`` survey, made by the CLI."""
    out = tmp_path_factory.mktemp("tiny")
    geoortho_cli("synth", "--preset", "tiny", "--seed", "3", "--output", str(out), "--quiet")
    return out
