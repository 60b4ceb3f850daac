"""Shared fixtures: synthetic surveys are made once per session."""

from __future__ import annotations

import os

import pytest
from realdata import real_data  # noqa: F401 (tests import it from here)

from geoortho.feedback import Feedback


@pytest.fixture(scope="session")
def tiny_survey(tmp_path_factory: pytest.TempPathFactory):
    from geoortho.synthetic.survey import synth

    return synth(tmp_path_factory.mktemp("tiny"), preset="tiny", seed=3, workers=os.cpu_count() or 1)


@pytest.fixture(scope="session")
def small_survey(tmp_path_factory: pytest.TempPathFactory):
    from geoortho.synthetic.survey import synth

    return synth(tmp_path_factory.mktemp("small"), preset="small", seed=1)


@pytest.fixture(scope="session")
def oblique_survey(tmp_path_factory: pytest.TempPathFactory):
    from geoortho.synthetic.survey import synth

    return synth(tmp_path_factory.mktemp("oblique"), preset="oblique", seed=2)


@pytest.fixture(scope="session")
def hard_survey(tmp_path_factory: pytest.TempPathFactory):
    from geoortho.synthetic.survey import synth

    return synth(tmp_path_factory.mktemp("hard"), preset="hard", seed=4)


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
    from geoortho.gcp.find import gcp_find
    from geoortho.reconstruction.sparse import sfm

    d = tmp_path_factory.mktemp("sfm_gcp")
    found = gcp_find(small_survey.images, small_survey.gcp_file, d / "gcp_list.txt")
    seen = sorted({line.split()[6] for line in (d / "gcp_list.txt").read_text().splitlines()[1:]})
    checkpoints = seen[::3]
    r = sfm(small_survey.images, d / "out", gcp_list=found.output, checkpoints=",".join(checkpoints), **SFM_FAST)
    return r, checkpoints


@pytest.fixture(scope="session")
def toledo_sfm(tmp_path_factory):
    """SfM of the real toledo_dji photos with their gcp_list.txt."""
    from geoortho.reconstruction.sparse import sfm

    base = real_data("toledo_dji")
    return sfm(
        base / "images", tmp_path_factory.mktemp("toledo_sfm"), gcp_list=base / "gcp" / "gcp_list.txt", **SFM_FAST
    )
