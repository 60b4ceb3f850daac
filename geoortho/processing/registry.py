"""Validate and convert parameter values, run algorithms, describe the registry."""

from __future__ import annotations

import dataclasses
import json
import math
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

from geoortho.core.folders import path_inside, refuse_writing_into
from geoortho.errors import ParameterError, shortened
from geoortho.feedback import Feedback, as_feedback
from geoortho.processing.algorithms import ALGORITHMS
from geoortho.processing.spec import PARAM_TYPES, PATH_TYPES, Algorithm, Param
from geoortho.version import __version__

__all__ = [
    "CONVERTERS",
    "convert_value",
    "convert_values",
    "get_algorithm",
    "list_algorithms",
    "run_algorithm",
    "describe",
]


def _path_in(p: Param, v: Any, *, want_dir: bool) -> Path:
    path = Path(v).expanduser()
    if p.output:
        return path
    if not path.exists():
        raise ParameterError(p.name, f"no such {'folder' if want_dir else 'file'}: {path}")
    if want_dir and not path.is_dir():
        raise ParameterError(p.name, f"not a folder: {path}")
    if not want_dir and path.is_dir() and p.project_file:
        if not (path / p.project_file).is_file():
            raise ParameterError(p.name, f"is a folder without {p.project_file} (a run project's): {path}")
        return path / p.project_file
    if not want_dir and path.is_dir():
        # a product's folder for its one file of the kind (plan's folder for its plan.gpkg)
        inside = sorted(f for f in path.iterdir() if f.is_file() and f.suffix.lower() in p.extensions)
        if len(inside) == 1:
            return inside[0]
        raise ParameterError(p.name, f"is a folder, expected a file: {path}")
    return path


def _number(p: Param, v: Any) -> float:
    try:
        x = float(v)
    except (TypeError, ValueError):
        raise ParameterError(p.name, f"expected a number, got {_shown(v)}") from None
    if not math.isfinite(x):
        raise ParameterError(p.name, f"expected a finite number, got {_shown(v)}")
    _check_range(p, x)
    return x


def _integer(p: Param, v: Any) -> int:
    if isinstance(v, bool):
        raise ParameterError(p.name, f"expected an integer, got {v!r}")
    try:
        x = int(v) if not isinstance(v, float) or v.is_integer() else None
    except (TypeError, ValueError):  # 3.11 refuses to read an integer of over 4,300 digits: ValueError
        x = None
    if x is None:
        raise ParameterError(p.name, f"expected an integer, got {_shown(v)}")
    _check_range(p, x)
    return x


def _shown(v: Any) -> str:
    """A value as a message shows it (:func:`~geoortho.errors.shortened`)."""
    return shortened(repr(v) if isinstance(v, str) else str(v))


def _check_range(p: Param, x: float) -> None:
    unit = f" {p.unit}" if p.unit else ""
    try:
        shown = f"{float(x):g}"
    except OverflowError:  # an integer past any float
        shown = f"a number of {len(str(abs(int(x))))} digits"
    if p.minimum is not None and x < p.minimum:
        raise ParameterError(p.name, f"{shown}{unit} is below the minimum {p.minimum:g}{unit}")
    if p.maximum is not None and x > p.maximum:
        raise ParameterError(p.name, f"{shown}{unit} is above the maximum {p.maximum:g}{unit}")


def _enum(p: Param, v: Any) -> str:
    s = str(v)
    if s not in p.choices:
        raise ParameterError(p.name, f"{_shown(s)} is not one of {', '.join(p.choices)}")
    return s


_TRUE = {"1", "true", "yes", "on"}
_FALSE = {"0", "false", "no", "off"}


def _bool(p: Param, v: Any) -> bool:
    if isinstance(v, bool):
        return v
    s = str(v).strip().lower()
    if s in _TRUE:
        return True
    if s in _FALSE:
        return False
    raise ParameterError(p.name, f"expected true or false, got {_shown(v)}")


def _crs(p: Param, v: Any) -> Any:
    from geoortho.core.crs import parse_crs  # here: pyproj is no part of --help

    try:
        crs = parse_crs(v)
    except ValueError as e:
        raise ParameterError(p.name, str(e)) from None
    if crs.is_geocentric:
        raise ParameterError(p.name, f"{crs.name} is geocentric (ECEF x, y, z): give a projected CRS or lon/lat")
    if crs.is_vertical and not (crs.is_projected or crs.is_geographic):
        raise ParameterError(p.name, f"{crs.name} is a vertical CRS only: give a horizontal one")
    return crs


#: Algorithms whose ``crs`` may be geographic (lon/lat vectors); every other ``crs`` is a map grid.
_GEOGRAPHIC_CRS_OK = frozenset({"footprints"})


#: One converter per parameter type (a test checks that every type has one).
CONVERTERS: dict[str, Callable[[Param, Any], Any]] = {
    "folder": lambda p, v: _path_in(p, v, want_dir=True),
    "file": lambda p, v: _path_in(p, v, want_dir=False),
    "raster": lambda p, v: _path_in(p, v, want_dir=False),
    "vector": lambda p, v: _path_in(p, v, want_dir=False),
    "pointcloud": lambda p, v: _path_in(p, v, want_dir=False),
    "number": _number,
    "integer": _integer,
    "enum": _enum,
    "bool": _bool,
    "crs": _crs,
    "string": lambda p, v: str(v),
}
assert set(CONVERTERS) == set(PARAM_TYPES)


def convert_value(p: Param, value: Any) -> Any:
    """Convert one value to the param's Python type, or raise ParameterError."""
    if value is None:
        if p.required:
            raise ParameterError(p.name, "is required")
        return None
    return CONVERTERS[p.type](p, value)


def list_algorithms() -> list[Algorithm]:
    """Every registered algorithm, in registry order."""
    return list(ALGORITHMS)


def get_algorithm(algorithm_id: str) -> Algorithm:
    for alg in list_algorithms():
        if alg.id == algorithm_id:
            return alg
    raise ParameterError("algorithm", f"unknown algorithm {algorithm_id!r}")


def convert_values(alg: Algorithm, values: dict[str, Any]) -> dict[str, Any]:
    """Validate a dict of raw values (strings, numbers) against the spec."""
    unknown = set(values) - {p.name for p in alg.params}
    if unknown:
        raise ParameterError(sorted(unknown)[0], f"not a parameter of {alg.id}")
    kwargs: dict[str, Any] = {}
    for p in alg.params:
        if p.name in values and values[p.name] is not None:
            kwargs[p.name] = convert_value(p, values[p.name])
        elif p.required:
            raise ParameterError(p.name, "is required")
        else:
            kwargs[p.name] = p.default
    if kwargs.get("crs") is not None:
        check_in_context(alg.id, "crs", kwargs["crs"])
    _refuse_overwriting_inputs(alg, kwargs)
    return kwargs


def check_in_context(algorithm_id: str, name: str, value: Any) -> None:
    """What a value's type alone does not say of it: a CRS must be projected for the algorithms
    that grid in it."""
    if name == "crs" and value is not None and algorithm_id not in _GEOGRAPHIC_CRS_OK and not value.is_projected:
        raise ParameterError(
            "crs",
            f"{value.name} is not projected: {algorithm_id} needs a map grid in metres or feet (e.g. the photos' "
            "UTM zone)",
        )


def same_file(a: Path, b: Path) -> bool:
    """The same file, through symlinks and ``..`` too (an output need not exist yet)."""
    try:
        if a.exists() and b.exists():
            return os.path.samefile(a, b)
    except OSError:
        pass
    return a.resolve() == b.resolve()


def _refuse_overwriting_inputs(alg: Algorithm, kwargs: dict[str, Any]) -> None:
    """An algorithm's path parameters through :func:`refuse_overwrites`. run checks its products
    one by one (run_checks.check_run_paths): a project holds what it was made from."""

    def named(output: bool) -> list[tuple[str, Path, bool]]:
        return [
            (p.name, Path(kwargs[p.name]), p.type == "folder")
            for p in alg.params
            if p.type in PATH_TYPES and p.output == output and kwargs.get(p.name) is not None
        ]

    refuse_overwrites(named(True), named(False), writer=alg.id if alg.id != "run" else "")


def refuse_overwrites(
    writes: list[tuple[str, Path, bool]], reads: list[tuple[str, Path, bool]], writer: str = ""
) -> None:
    """Outputs (name, path, is a folder) that would destroy an input (name, path, is a folder):
    refused before any work. An output that is an input file or another output; a file written
    into an input folder (:func:`refuse_writing_into`); and, when ``writer`` (the algorithm) is
    given, an input file inside an output folder (a positions file called report.json in sfm's
    output: read, then overwritten). Folders given as outputs are checked against input files
    only (a project folder may hold the photos' folder beside it)."""
    for i, (out_name, out_path, out_dir) in enumerate(writes):
        for in_name, in_path, in_dir in reads:
            if (not in_dir or not out_dir) and same_file(out_path, in_path):
                raise ParameterError(
                    out_name, f"{out_path} is also the input {in_name}: writing it would destroy it; give another path"
                )
        for other_name, other_path, _ in writes[:i]:
            if same_file(out_path, other_path):
                raise ParameterError(out_name, f"{out_path} is also the output {other_name}; give another path")
        for in_name, in_path, in_dir in reads:  # after the inputs themselves: the message names the input file
            if in_dir and not out_dir:
                refuse_writing_into(out_name, out_path, in_name, in_path)
            elif writer and not in_dir and out_dir and path_inside(in_path, out_path) is not None:
                raise ParameterError(
                    in_name,
                    f"{in_path} lies in the output folder {out_path}, where {writer} writes its products: "
                    "move it out, or give another output",
                )


def outputs_of(alg: Algorithm, result: Any) -> dict[str, Any]:
    """The outputs dict of a core function's result, JSON-ready."""
    out: dict[str, Any] = {}
    for o in alg.outputs:
        v = result[o.name] if isinstance(result, dict) else getattr(result, o.name)
        out[o.name] = _jsonable(v)
    return out


def _jsonable(v: Any) -> Any:
    if isinstance(v, Path):
        return str(v)
    if dataclasses.is_dataclass(v) and not isinstance(v, type):
        return _jsonable(dataclasses.asdict(v))
    if isinstance(v, dict):
        return {str(k): _jsonable(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_jsonable(x) for x in v]
    if hasattr(v, "item") and callable(v.item):  # numpy scalars
        v = v.item()
    if isinstance(v, float) and not math.isfinite(v):
        return None  # JSON has no NaN: "not measured" is null
    return v


def run_algorithm(
    algorithm_id: str | Algorithm,
    values: dict[str, Any],
    feedback: Feedback | None = None,
    *,
    scheduler: str | None = None,
) -> dict[str, Any]:
    """Validate ``values``, call the core function with a feedback, return its outputs.

    ``scheduler``: a Dask scheduler's address (default ``$GEOORTHO_SCHEDULER``) to run the
    per-photo and per-tile work on; its workers must see every input and output path."""
    from geoortho.core.parallel import use_scheduler  # here: the pool's imports are no part of --help

    alg = algorithm_id if isinstance(algorithm_id, Algorithm) else get_algorithm(algorithm_id)
    kwargs = convert_values(alg, values)
    _clean_beside_outputs(alg, kwargs)
    fb = as_feedback(feedback)
    paths = [kwargs[p.name] for p in alg.params if p.type in PATH_TYPES and kwargs.get(p.name) is not None]
    with use_scheduler(scheduler, must_see=paths) as client:
        if client is not None:
            fb.info(f"per-photo and per-tile work on the Dask cluster at {client.scheduler.address}")
        result = alg.function(**kwargs, feedback=fb)
    fb.set_progress(1.0)  # the work is done: a cancel that comes now has nothing left to stop
    return outputs_of(alg, result)


def _clean_beside_outputs(alg: Algorithm, kwargs: dict[str, Any]) -> None:
    """Each output can be written (refused now, not after the computing); temporaries of killed
    runs beside (or in) it are removed before this run starts."""
    from geoortho.core.outputs import remove_stale_temporaries  # here: numpy is no part of --help

    for p in alg.params:
        if p.output and kwargs.get(p.name) is not None:
            path = Path(kwargs[p.name])
            _check_writable(p, path)
            remove_stale_temporaries(path.parent)
            if p.type == "folder":
                remove_stale_temporaries(path)


MIN_FREE_MB = 50  # below this a product cannot be written whole; said before any computing


def _check_writable(p: Param, path: Path) -> None:
    """Before the work, not after it: the output's folder can be written and has room."""
    import shutil

    if p.type == "folder" and path.exists() and not path.is_dir():
        raise ParameterError(p.name, f"{path} exists and is a file: give a folder")
    if p.type != "folder" and path.is_dir():
        raise ParameterError(p.name, f"{path} is a folder: give a file's path")
    where = path if p.type == "folder" and path.is_dir() else path.parent
    while not where.exists() and where != where.parent:  # folders still to be made
        where = where.parent
    if not os.access(where, os.W_OK | os.X_OK) or (
        path.exists() and not path.is_dir() and not os.access(path, os.W_OK)
    ):
        raise ParameterError(p.name, f"cannot write {path}: {where} is read-only")
    free_mb = shutil.disk_usage(where).free / 1e6
    if free_mb < MIN_FREE_MB:
        raise ParameterError(p.name, f"cannot write {path}: only {free_mb:.0f} MB free on its disk")


def _param_json(p: Param) -> dict[str, Any]:
    default = None if p.required else _jsonable(p.default)
    if default is not None and p.type == "crs":
        default = str(default)
    return {
        "name": p.name,
        "cli": p.cli_flag,
        "qgis_name": p.qgis_name,
        "type": p.type,
        "help": p.help,
        "required": p.required,
        "default": default,
        "unit": p.unit,
        "minimum": p.minimum,
        "maximum": p.maximum,
        "choices": list(p.choices),
        "extensions": list(p.extensions),
        "output": p.output,
        "advanced": p.advanced,
    }


def describe() -> dict[str, Any]:
    """The whole registry as a JSON-ready dict (the contract other faces build on)."""
    return {
        "name": "geoortho",
        "version": __version__,
        # Where this geoortho lives: the QGIS provider keys its cache of this
        # description on the files there, so an upgrade is noticed.
        "package_dir": str(Path(__file__).resolve().parents[1]),
        "param_types": list(PARAM_TYPES),
        "algorithms": [
            {
                "id": a.id,
                "title": a.title,
                "group": a.group,
                "short_help": a.short_help,
                "help": a.help,
                "parameters": [_param_json(p) for p in a.params],
                "outputs": [{"name": o.name, "type": o.type, "help": o.help} for o in a.outputs],
            }
            for a in list_algorithms()
        ],
    }


def describe_json(indent: int | None = 2) -> str:
    return json.dumps(describe(), indent=indent)


_PYTHON_TYPES: dict[str, tuple[tuple[type, ...], str]] = {
    "folder": ((str, os.PathLike), "a path"),
    "file": ((str, os.PathLike), "a path"),
    "raster": ((str, os.PathLike), "a path"),
    "vector": ((str, os.PathLike), "a path"),
    "pointcloud": ((str, os.PathLike), "a path"),
    "number": ((int, float), "a number"),
    "integer": ((int,), "an integer"),
    "enum": ((str,), "one of the choices (a string)"),
    "bool": ((bool,), "True or False"),
    "string": ((str,), "a string"),
}


def check_call(function_ref: str, bound: dict[str, Any]) -> dict[str, Any]:
    """The Python API's door: each argument of a core function is of its declared type, one of
    its choices and within its declared range, refused with the parameter's name (a
    ParameterError, in the CLI's words) rather than a TypeError from deep inside, or a value
    nobody checked taken silently for the default. What depends on more than one value is
    checked by the function itself.

    Returns the arguments it converted, as the core function takes them: each CRS parsed (a
    pyproj ``CRS`` from anything a user writes) and held to the same rules as on the command line,
    here once (the core functions take a ``CRS`` and never parse one)."""
    alg = next((a for a in list_algorithms() if a.function_ref == function_ref), None)
    if alg is None:
        return {}
    import numpy as np

    converted: dict[str, Any] = {}
    for p in alg.params:
        value = bound.get(p.name)
        if value is None or value is p.default:
            continue
        if p.type == "crs":
            converted[p.name] = convert_value(p, value)
            check_in_context(alg.id, p.name, converted[p.name])
            continue
        kinds, said = _PYTHON_TYPES[p.type]
        ok = isinstance(value, kinds) and not (p.type in ("number", "integer") and isinstance(value, bool))
        if p.type in ("number", "integer") and isinstance(value, (np.integer, np.floating)):
            ok = p.type == "number" or isinstance(value, np.integer)
        if not ok:
            raise ParameterError(p.name, f"{value!r} is {type(value).__name__}, not {said}")
        if p.type == "enum":
            _enum(p, value)
        elif p.type in ("number", "integer"):
            _check_range(p, float(value))
    return converted
