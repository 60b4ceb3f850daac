"""What ``run`` checks before any stage starts: the given inputs, each stage's options (parsed from
``--stage-options``), the paths inside and outside the project, the project folder itself.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from geoortho.chain.ledger import LEDGER_NAME
from geoortho.chain.stages import STAGES, Project, Stage
from geoortho.core.folders import path_inside
from geoortho.core.pointcloud import check_las_header
from geoortho.core.surface import refuse_image
from geoortho.errors import InputError
from geoortho.feedback import Feedback
from geoortho.gcp.io import read_gcp_file
from geoortho.photos.metadata import list_images
from geoortho.processing.registry import (
    check_in_context,
    convert_value,
    get_algorithm,
    refuse_overwrites,
)

LOCK_NAME = ".run.lock"


def check_given(project: Project) -> None:
    """The files given are read now, not when their stage comes minutes into the run: a DSM that
    is no elevation raster, a cloud that is no point cloud, a GCP file that does not parse."""
    import rasterio
    from rasterio.errors import RasterioIOError

    list_images(project.images)
    for dsm in (project.dsm, project.change_from):
        if dsm is None:
            continue
        try:
            with rasterio.open(dsm) as ds:
                if ds.crs is None:
                    raise InputError("the DSM has no CRS", path=dsm)
                refuse_image(ds, dsm)
        except RasterioIOError as e:
            raise InputError(f"not an elevation raster ({e})", path=dsm) from None
    if project.change_from is not None and path_inside(project.change_from, project.output) is not None:
        raise InputError(
            "the earlier survey is this project's own: give another run's folder or DSM", path=project.change_from
        )
    if project.points is not None and project.points.suffix.lower() in (".las", ".laz"):
        if not project.points.is_file():
            raise InputError("no such file", path=project.points)
        check_las_header(project.points)
    for gcps in (project.gcp_file, project.gcp_list):
        if gcps is not None:
            names = read_gcp_file(gcps).by_name()
            wanted = [c.strip() for c in project.checkpoints.split(",") if c.strip()]
            unknown = [c for c in wanted if c.lower() not in ("all", "none") and c not in names]
            if unknown:
                raise InputError(
                    f"checkpoint{'s' if len(unknown) > 1 else ''} {', '.join(unknown)} not in the GCP file (it "
                    f"names {', '.join(sorted(names)[:12])}{'…' if len(names) > 12 else ''})",
                    path=gcps,
                )
    if project.positions is not None:
        if not project.positions.is_file():
            raise InputError("no such positions file", path=project.positions)
        # read now against the photos (minutes before sfm would: another site's file, a wrong CRS)
        from geoortho.photos.metadata import read_photos
        from geoortho.photos.positions import read_positions

        offset = (project.options.get("sfm") or {}).get("positions_time_offset_s")
        read_positions(project.positions, read_photos(project.images).photos, time_offset_s=offset)


def check_stage_options(project: Project, fb: Feedback) -> None:
    """Stage options that would do nothing or override what the run was given: options of a stage
    that does not run (dense beside a given cloud) are said, not taken silently (an options file
    kept for every run may hold them); an option the run already sets from its own (sfm's positions
    beside --positions; the stage option used to win, silently) is refused. The others the run sets
    are refused by :func:`parse_stage_options`."""
    for stage in STAGES:
        own = project.options.get(stage.name) or {}
        if own and not stage.applies(project):
            fb.warning(
                f"run: stage options for {stage.name} ({', '.join(sorted(own))}) do nothing: the stage does not "
                "run in this project"
            )
    sfm_options = project.options.get("sfm") or {}
    if project.positions is not None and "positions" in sfm_options:
        raise InputError("stage options: sfm.positions is also given to the run itself (--positions): give it once")
    for name in ("split", "split_overlap_m"):
        if name in sfm_options and project.split:
            raise InputError(f"stage options: sfm.{name} is also given to the run itself (--split): give it once")
    if project.split_overlap_m is not None and not project.split:
        fb.warning("run: --split-overlap-m does nothing without --split (the SfM runs as one block)")


def check_run_paths(project: Project) -> None:
    """Every file a stage of the run will write, chained or given in a stage option, checked before
    the first stage (:func:`~geoortho.processing.registry.refuse_overwrites`) against every file the
    run reads (given, or in a stage option) and against the photos' folder: a stage option naming a
    photo as the classified cloud replaced the photo with a point cloud, with exit 0. Paths are
    compared through links and ``..``."""
    from geoortho.processing.spec import PATH_TYPES

    reads: list[tuple[str, Path, bool]] = [
        (name, Path(path), False)
        for name, path in (
            ("gcp_file", project.gcp_file), ("gcp_list", project.gcp_list), ("points", project.points),
            ("dsm", project.dsm), ("positions", project.positions), ("change_from", project.change_from),
        )
        if path is not None
    ]  # fmt: skip
    reads.append(("images", project.images, True))
    writes: list[tuple[str, Path, bool]] = []
    for stage in STAGES:
        if not stage.applies(project):
            continue
        params = {p.name: p for p in get_algorithm(stage.name).params}
        chained = {k: v for k, v in stage.values(project, {}).items() if v is not None}
        own = project.options.get(stage.name, {})
        for key, value in {**chained, **own}.items():
            p = params.get(key)
            if p is None or p.type not in PATH_TYPES or value is None:
                continue
            where = f"{stage.name}.{key}" + (" (a stage option)" if key in own else "")
            if p.output:
                writes.append((where, Path(value).absolute(), p.type == "folder"))
            elif key in own and p.type != "folder":
                reads.append((where, Path(value).absolute(), False))
    refuse_overwrites(writes, reads)


def check_project_folder(output: Path, force: bool = False) -> None:
    """Refuse a folder that holds something other than a geoortho project (no run.json), unless
    ``force``: a mistyped --output must not mix products into, or overwrite, someone's files."""
    if output.exists() and not output.is_dir():
        raise InputError("exists and is not a folder", path=output)
    if (
        output.is_dir()
        and not (output / LEDGER_NAME).is_file()
        and any(p.name != LOCK_NAME for p in output.iterdir())
        and not force
    ):
        raise InputError(
            f"holds files but no {LEDGER_NAME}: not a geoortho project (give an empty or new folder, or --force)",
            path=output,
        )


def parse_stage_options(text: str, stages: Sequence[Stage] = STAGES) -> dict[str, dict[str, Any]]:
    """Stage options from JSON text or a JSON file: ``{"sfm": {"max_image_size": 2048}, ...}``.
    Each stage's options are its own algorithm's parameters (one declaration per parameter);
    the ones the chain sets itself (inputs, outputs) cannot be given."""

    if not text:
        return {}
    path = Path(text)
    # JSON text starts with a bracket, a quote or a digit; anything else names a file
    is_file = text.lstrip()[:1] not in set('{["0123456789-')
    if is_file:
        try:
            if path.is_dir():
                raise InputError("stage options: a folder, not a JSON file or JSON text", path=path)
            if not path.is_file():
                raise InputError("stage options: no such file (give JSON text or a JSON file)", path=path)
            text = path.read_text(encoding="utf-8")
        except (OSError, UnicodeDecodeError) as e:
            raise InputError(
                f"stage options: cannot be read ({getattr(e, 'strerror', None) or e})", path=path
            ) from None
    try:
        raw = json.loads(text)
    except ValueError as e:
        raise InputError(f"stage options: not JSON ({e})", path=path if is_file else None) from None
    except RecursionError:
        raise InputError(
            "stage options: nested too deeply to be stage options", path=path if is_file else None
        ) from None
    if not isinstance(raw, dict) or not all(isinstance(v, dict) for v in raw.values()):
        raise InputError('stage options: give {"stage": {"option": value, ...}, ...}')
    by_name = {s.name: s for s in stages}
    probe = Project(images=Path("."), output=Path("."), gcp_file=Path("."), points=Path("."), dsm=Path("."))
    for name, opts in raw.items():
        if name not in by_name:
            raise InputError(f"stage options: {name} is not a stage; choose from {', '.join(by_name)}")
        params = {p.name: p for p in get_algorithm(name).params}
        chained = set(by_name[name].values(probe, {}))
        for key, value in opts.items():
            if key not in params:
                raise InputError(f"stage options: {name} has no option {key}")
            if key in chained:
                raise InputError(f"stage options: {name}.{key} is set by the run itself")
            # a bad value is refused now, not an hour into the run
            check_in_context(name, key, convert_value(params[key], value))
    return raw
