"""The run engine (issue 21, in progress): stages re-used or re-done as run.json says, on tiny."""

from __future__ import annotations

import json

import pytest

from geoortho.errors import InputError
from geoortho.pipeline import LEDGER_NAME, Project, run_stages

FAST = {"sfm": {"max_image_size": 1024}, "dense": {"max_image_size": 512}}


def _status(results):
    return {r.name: r.status for r in results}


@pytest.fixture(scope="module")
def first_run(tiny_survey, tmp_path_factory):
    project = Project(
        images=tiny_survey.images,
        output=tmp_path_factory.mktemp("run") / "project",
        gcp_file=tiny_survey.gcp_file,
        options=FAST,
    )
    return project, run_stages(project)


def test_first_run_makes_every_product(first_run):
    project, results = first_run
    assert _status(results) == dict.fromkeys(["footprints", "gcp-find", "sfm", "dense", "dem", "ortho"], "ran")
    ledger = json.loads((project.output / LEDGER_NAME).read_text())
    for name in ("footprints", "gcp-find", "sfm", "dense", "dem", "ortho"):
        rec = ledger["stages"][name]
        assert rec["status"] == "done" and rec["seconds"] > 0 and rec["versions"]["geoortho"]
    assert (project.output / "ortho" / "ortho.tif").is_file() and (project.output / "dem" / "dsm.tif").is_file()
    assert ledger["stages"]["sfm"]["values"]["gcp_list"].endswith("gcp-find/gcp_list.txt")


def test_second_run_reuses_everything_and_reads_no_photo_again(first_run):
    project, _ = first_run
    results = run_stages(project)
    assert set(_status(results).values()) == {"reused"}


def test_an_ortho_option_redoes_only_ortho(first_run):
    project, _ = first_run
    changed = Project(**{**project.__dict__, "options": {**FAST, "ortho": {"resolution_m": 0.2}}})
    status = _status(run_stages(changed))
    assert status["ortho"] == "ran" and all(v == "reused" for k, v in status.items() if k != "ortho")
    # a stage left "running" (the run was killed in it) is re-done, nothing before it
    ledger_path = project.output / LEDGER_NAME
    ledger = json.loads(ledger_path.read_text())
    ledger["stages"]["ortho"]["status"] = "running"
    ledger_path.write_text(json.dumps(ledger))
    status = _status(run_stages(changed))
    assert status["ortho"] == "ran" and all(v == "reused" for k, v in status.items() if k != "ortho")


def test_rerun_from_forces_that_stage_and_the_later_ones(first_run):
    project, _ = first_run
    status = _status(run_stages(project, rerun_from="dem"))
    reused = dict.fromkeys(["footprints", "gcp-find", "sfm", "dense"], "reused")
    assert status == {**reused, "dem": "ran", "ortho": "ran"}
    with pytest.raises(InputError, match="not a stage"):
        run_stages(project, rerun_from="mosaic")


def test_stage_options_are_the_stages_own_parameters(tmp_path):
    from geoortho.pipeline import parse_stage_options

    assert parse_stage_options('{"sfm": {"max_image_size": 2048}}') == {"sfm": {"max_image_size": 2048}}
    f = tmp_path / "opts.json"
    f.write_text('{"ortho": {"resolution_m": 0.05}}')
    assert parse_stage_options(str(f)) == {"ortho": {"resolution_m": 0.05}}
    for bad, why in (
        ('{"mosaic": {}}', "not a stage"),
        ('{"sfm": {"max_size": 1}}', "has no option max_size"),
        ('{"ortho": {"output": "x.tif"}}', "set by the run itself"),
        ("[1, 2]", "give"),
        ("{oops", "not JSON"),
    ):
        with pytest.raises(InputError, match=why):
            parse_stage_options(bad)


def test_a_folder_of_other_files_is_refused_unless_forced(tmp_path):
    from geoortho.pipeline import check_project_folder

    check_project_folder(tmp_path / "new")
    (tmp_path / "thesis.docx").write_text("mine")
    with pytest.raises(InputError, match="not a geoortho project"):
        check_project_folder(tmp_path)
    check_project_folder(tmp_path, force=True)
    (tmp_path / LEDGER_NAME).write_text("{}")
    check_project_folder(tmp_path)


def test_a_moved_project_is_reused(first_run, tmp_path):
    import shutil

    project, _ = first_run
    moved = tmp_path / "moved"
    shutil.copytree(project.output, moved, symlinks=True)
    status = _status(run_stages(Project(**{**project.__dict__, "output": moved})))
    assert set(status.values()) == {"reused"}, status
