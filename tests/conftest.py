"""Shared fixtures: synthetic surveys are made once per session.

``make test`` runs the files on several pytest-xdist workers; a session fixture here is then made
once for the whole run, by the first worker that needs it, and read back by the others.
"""

from __future__ import annotations

import fcntl
import os
import pickle
import shutil
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from realdata import real_data  # noqa: F401 (tests import it from here)

from geoortho.core.parallel import WORKERS_ENV
from geoortho.feedback import Feedback

# Under pytest-xdist the test files already run side by side, a process a core: each algorithm's
# default pool (a process a core again) is then start-up and contention, not speed (a tiny run:
# 47 s of CPU on pools, 37 s in-process). Tests of the pools themselves give their workers.
if int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1")) > 1:
    os.environ.setdefault(WORKERS_ENV, "1")


def made_once(tmp_path_factory: pytest.TempPathFactory, name: str, make: Callable[[Path], Any]) -> Any:
    """``make(folder)``, once per test run: under pytest-xdist every worker would otherwise make its own.

    The first worker to ask makes it in the run's shared temporary folder, under a file lock, and
    leaves the result pickled beside it; the others wait on the lock and read that. A make that
    raises leaves nothing behind, so the next worker to ask tries again (and fails the same way).
    """
    if os.environ.get("PYTEST_XDIST_WORKER") is None:
        return make(tmp_path_factory.mktemp(name))
    shared = tmp_path_factory.getbasetemp().parent  # the workers' own folders are inside it
    made = shared / f"{name}.pickle"
    with open(shared / f"{name}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # released when the file closes
        if made.exists():
            return pickle.loads(made.read_bytes())
        folder = shared / name
        if folder.exists():  # a make that failed on another worker
            shutil.rmtree(folder)
        folder.mkdir()
        value = make(folder)
        made.write_bytes(pickle.dumps(value))
        return value


def _synth(preset: str, seed: int, **options: Any) -> Callable[[Path], Any]:
    def make(folder: Path) -> Any:
        from geoortho.synthetic.survey import synth

        return synth(folder, preset=preset, seed=seed, **options)

    return make


@pytest.fixture(scope="session")
def tiny_survey(tmp_path_factory: pytest.TempPathFactory):
    return made_once(tmp_path_factory, "tiny", _synth("tiny", 3, workers=os.cpu_count() or 1))


@pytest.fixture(scope="session")
def small_survey(tmp_path_factory: pytest.TempPathFactory):
    return made_once(tmp_path_factory, "small", _synth("small", 1))


@pytest.fixture(scope="session")
def oblique_survey(tmp_path_factory: pytest.TempPathFactory):
    # only its tags and truth are read (footprints): its photos are not rendered
    return made_once(tmp_path_factory, "oblique", _synth("oblique", 2, pixels=False))


@pytest.fixture(scope="session")
def hard_survey(tmp_path_factory: pytest.TempPathFactory):
    return made_once(tmp_path_factory, "hard", _synth("hard", 4))


class RecordingFeedback(Feedback):
    """A Feedback that keeps what it is told: progress fractions, infos, warnings."""

    def __init__(self):
        super().__init__()
        self.values: list[float] = []
        self.infos: list[str] = []
        self.warnings: list[str] = []

    def set_progress(self, fraction):
        self.values.append(fraction)

    def info(self, message):
        self.infos.append(message)

    def warning(self, message):
        self.warnings.append(message)


SFM_FAST = {"max_image_size": 1024, "max_features": 4096}


@pytest.fixture(scope="session")
def sfm_with_gcps(small_survey, tmp_path_factory):
    """SfM of the small survey with the GCPs gcp-find located; every third GCP is a checkpoint."""

    def make(d: Path):
        from geoortho.gcp.find import gcp_find
        from geoortho.reconstruction.sparse import sfm

        found = gcp_find(small_survey.images, small_survey.gcp_file, d / "gcp_list.txt")
        seen = sorted({line.split()[6] for line in (d / "gcp_list.txt").read_text().splitlines()[1:]})
        checkpoints = seen[::3]
        r = sfm(small_survey.images, d / "out", gcp_list=found.output, checkpoints=",".join(checkpoints), **SFM_FAST)
        return r, checkpoints

    return made_once(tmp_path_factory, "sfm_gcp", make)


@pytest.fixture(scope="session")
def toledo_sfm(tmp_path_factory):
    """SfM of the real toledo_dji photos with their gcp_list.txt."""
    base = real_data("toledo_dji")

    def make(d: Path):
        from geoortho.reconstruction.sparse import sfm

        return sfm(base / "images", d, gcp_list=base / "gcp" / "gcp_list.txt", **SFM_FAST)

    return made_once(tmp_path_factory, "toledo_sfm", make)


#: The test files by their time in a full run (measured, longest first: 590, 270, 210, ... s). Under
#: pytest-xdist a file stays on one worker (--dist loadfile), and files are handed out in this order
#: (--no-loadscope-reorder): the longest first, so that no worker is left alone with a long file at
#: the end. Files not listed follow in their own order.
LONGEST_FIRST = (
    "test_pipeline", "test_ortho", "test_dense", "test_gcp_targets", "test_api", "test_cluster", "test_quality",
    "test_heights", "test_bad_input", "test_sfm", "test_volume", "test_coverage", "test_photos_footprints",
    "test_dem", "test_rtk", "test_movers", "test_gcp_find", "test_positions", "test_bareearth",
)  # fmt: skip


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    rank = {name: i for i, name in enumerate(LONGEST_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.stem, len(rank)))  # stable: a file's own order kept
