"""The whole chain in one resumable command: the stages, the project folder and ``run.json``.

Work in progress (issue 21): the engine — which stages apply, where each writes, what makes a
stage's result still valid, and the ledger that says so. The ``run`` algorithm, its report and
its progress display are built on it.

A stage is *done* only when ``run.json`` says so with the fingerprint of what it was run with:
its options, the content hashes of its inputs (photos, GCP file, earlier stages' products) and
the software versions. Every product is written atomically by its stage, and a stage is marked
``running`` before it starts, so a run killed mid-stage leaves that stage not done: the next
run re-does it and keeps every finished one. A stage whose fingerprint changed is re-done;
stages after it are re-done when the products they read changed (content, not time).
"""

from __future__ import annotations

import hashlib
import json
import os
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from .errors import InputError
from .feedback import Feedback, as_feedback, split

__all__ = [
    "STAGES",
    "Ledger",
    "Project",
    "Stage",
    "StageRun",
    "check_project_folder",
    "parse_stage_options",
    "run_stages",
]

LEDGER_NAME = "run.json"
LEDGER_VERSION = 1


@dataclass(frozen=True)
class Project:
    """What the user gave, and where the products go."""

    images: Path
    output: Path
    gcp_file: Path | None = None
    checkpoints: str = ""
    points: Path | None = None
    dsm: Path | None = None
    crs: str | None = None
    options: dict[str, dict[str, Any]] = field(default_factory=dict)  # stage -> its own options

    def folder(self, stage: str) -> Path:
        return self.output / stage


@dataclass(frozen=True)
class Stage:
    """One step of the chain: the algorithm it runs, when it applies, and its values (inputs from the
    project and from earlier stages' products at stable paths; outputs at stable paths)."""

    name: str  # the algorithm id
    applies: Callable[[Project], bool]
    values: Callable[[Project], dict[str, Any]]
    inputs: tuple[str, ...]  # the value names that are files or folders read (hashed)


def _gcp_list(p: Project) -> Path | None:
    return p.folder("gcp-find") / "gcp_list.txt" if p.gcp_file is not None else None


def _cloud(p: Project) -> Path:
    if p.points is not None:
        return p.points
    return p.folder("dense") / "dense.laz"


STAGES: tuple[Stage, ...] = (
    Stage(
        "footprints",
        lambda p: True,
        lambda p: {
            "images": p.images,
            "output": p.folder("footprints") / "footprints.gpkg",
            "overlap": p.folder("footprints") / "overlap.tif",
            "dsm": p.dsm,
            "crs": p.crs,
        },
        ("images", "dsm"),
    ),
    Stage(
        "gcp-find",
        lambda p: p.gcp_file is not None,
        lambda p: {
            "images": p.images,
            "gcp_file": p.gcp_file,
            "output": p.folder("gcp-find") / "gcp_list.txt",
            "detections": p.folder("gcp-find") / "detections.gpkg",
            "review": p.folder("gcp-find") / "review.png",
            "dsm": p.dsm,
            "crs": p.crs,
        },
        ("images", "gcp_file", "dsm"),
    ),
    Stage(
        "sfm",
        lambda p: True,
        lambda p: {
            "images": p.images,
            "output": p.folder("sfm"),
            "gcp_list": _gcp_list(p),
            "checkpoints": p.checkpoints or None,
            "crs": p.crs,
        },
        ("images", "gcp_list"),
    ),
    Stage(
        "dense",
        lambda p: p.points is None,
        lambda p: {"sfm": p.folder("sfm"), "images": p.images, "output": p.folder("dense") / "dense.laz"},
        ("sfm", "images"),
    ),
    Stage(
        "dem",
        lambda p: True,
        lambda p: {
            "points": _cloud(p),
            "output": p.folder("dem") / "dsm.tif",
            "dtm": p.folder("dem") / "dtm.tif",
            "hillshade": p.folder("dem") / "dtm_hillshade.png",
        },
        ("points",),
    ),
    Stage(
        "ortho",
        lambda p: True,
        lambda p: {
            "images": p.images,
            "output": p.folder("ortho") / "ortho.tif",
            "sfm": p.folder("sfm"),
            "dsm": p.dsm if p.dsm is not None else p.folder("dem") / "dsm.tif",
            "preview": p.folder("ortho") / "ortho_preview.png",
        },
        ("images", "sfm", "dsm"),
    ),
)


# --- content hashes ------------------------------------------------------------------------------


class Hasher:
    """SHA-256 of files and folders (sorted relative names + contents), cached by size and mtime so
    that a second run over unchanged photos reads nothing."""

    def __init__(self, cache: dict[str, list[Any]] | None = None) -> None:
        self.cache: dict[str, list[Any]] = dict(cache or {})
        self.bytes_read = 0

    def file(self, path: Path) -> str:
        st = path.stat()
        key = str(path.resolve())
        hit = self.cache.get(key)
        if hit is not None and hit[0] == st.st_size and hit[1] == st.st_mtime_ns:
            return str(hit[2])
        h = hashlib.sha256()
        with open(path, "rb") as f:
            for block in iter(lambda: f.read(1 << 20), b""):
                h.update(block)
        self.bytes_read += st.st_size
        digest = h.hexdigest()
        self.cache[key] = [st.st_size, st.st_mtime_ns, digest]
        return digest

    def path(self, path: Path) -> str:
        if path.is_file():
            return self.file(path)
        if not path.is_dir():
            raise InputError("no such file or folder", path=path)
        h = hashlib.sha256()
        for f in sorted(p for p in path.rglob("*") if p.is_file() and not p.name.startswith(".")):
            h.update(f.relative_to(path).as_posix().encode() + b"\0" + self.file(f).encode() + b"\n")
        return h.hexdigest()


def _versions() -> dict[str, str]:
    from importlib.metadata import PackageNotFoundError, version

    out = {}
    for name in ("geoortho", "pycolmap", "opencv-contrib-python-headless", "rasterio", "numpy"):
        try:
            out[name] = version(name)
        except PackageNotFoundError:
            continue
    return out


# --- the ledger ----------------------------------------------------------------------------------


class Ledger:
    """``PROJECT/run.json``: per stage its status, fingerprint, options, input hashes, outputs,
    seconds; written atomically after every change of status."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.data: dict[str, Any] = {"version": LEDGER_VERSION, "stages": {}, "hash_cache": {}}
        if path.is_file():
            try:
                loaded = json.loads(path.read_text())
            except ValueError as e:
                raise InputError(f"unreadable run ledger ({e}): remove it to start afresh", path=path) from None
            if loaded.get("version") == LEDGER_VERSION:
                self.data = loaded

    def stage(self, name: str) -> dict[str, Any]:
        return dict(self.data["stages"].get(name, {}))

    def set_stage(self, name: str, record: dict[str, Any]) -> None:
        self.data["stages"][name] = record
        self.save()

    def save(self) -> None:
        from .outputs import write_json

        write_json(self.path, self.data)


@dataclass(frozen=True)
class StageRun:
    """What happened to one stage in this run."""

    name: str
    status: str  # "ran", "reused", "skipped" (does not apply)
    seconds: float
    outputs: dict[str, Any]


def _relative(v: Any, root: Path) -> Any:
    """A path inside the project as ``PROJECT/...``: a moved project keeps its fingerprints."""
    if isinstance(v, Path):
        try:
            return "PROJECT/" + v.resolve().relative_to(root.resolve()).as_posix()
        except ValueError:
            return str(v)
    return v


def _fingerprint(
    stage: Stage, values: dict[str, Any], hashes: dict[str, str], versions: dict[str, str], root: Path
) -> str:
    record = {
        "stage": stage.name,
        "values": {k: _relative(v, root) for k, v in sorted(values.items())},
        "inputs": hashes,
        "versions": versions,
    }
    return hashlib.sha256(json.dumps(record, sort_keys=True, default=str).encode()).hexdigest()


def run_stages(
    project: Project,
    *,
    rerun_from: str | None = None,
    stages: Sequence[Stage] = STAGES,
    runner: Callable[[str, dict[str, Any], Feedback], dict[str, Any]] | None = None,
    feedback: Feedback | None = None,
) -> list[StageRun]:
    """Run the stages that apply, re-using every one whose fingerprint is unchanged and whose
    outputs are still there; ``rerun_from`` forces that stage and every later one."""
    from .processing.registry import run_algorithm

    fb = as_feedback(feedback)
    names = [s.name for s in stages]
    if rerun_from is not None and rerun_from not in names:
        raise InputError(f"--rerun-from {rerun_from}: not a stage; choose from {', '.join(names)}")
    unknown = set(project.options) - set(names)
    if unknown:
        raise InputError(f"options for {sorted(unknown)[0]}: not a stage; choose from {', '.join(names)}")
    project.output.mkdir(parents=True, exist_ok=True)
    ledger = Ledger(project.output / LEDGER_NAME)
    hasher = Hasher(ledger.data.get("hash_cache"))
    versions = _versions()
    run = runner or (lambda name, values, f: run_algorithm(name, values, feedback=f))
    forced = False
    results: list[StageRun] = []
    steps = split(fb, [1.0] * len(stages))
    for stage, step in zip(stages, steps):
        forced = forced or stage.name == rerun_from
        if not stage.applies(project):
            results.append(StageRun(stage.name, "skipped", 0.0, {}))
            step.progress(1.0)
            continue
        values = {k: v for k, v in stage.values(project).items() if v is not None}
        values.update(project.options.get(stage.name, {}))
        hashes = {k: hasher.path(Path(values[k])) for k in stage.inputs if k in values}
        fp = _fingerprint(stage, values, hashes, versions, project.output)
        before = ledger.stage(stage.name)
        if not forced and before.get("status") == "done" and before.get("fingerprint") == fp and _outputs_there(before):
            results.append(StageRun(stage.name, "reused", 0.0, before.get("outputs", {})))
            fb.info(f"run: {stage.name}: unchanged, reused")
            step.progress(1.0)
            continue
        project.folder(stage.name).mkdir(parents=True, exist_ok=True)
        started = time.time()
        ledger.set_stage(stage.name, {"status": "running", "started": started, "fingerprint": fp})
        t0 = time.perf_counter()
        try:
            outputs = run(stage.name, dict(values), step)
        except BaseException as e:
            ledger.set_stage(stage.name, {"status": "failed", "error": str(e), "fingerprint": fp})
            raise
        seconds = time.perf_counter() - t0
        ledger.data["hash_cache"] = hasher.cache
        ledger.set_stage(
            stage.name,
            {
                "status": "done",
                "fingerprint": fp,
                "values": {k: (str(v) if isinstance(v, Path) else v) for k, v in values.items()},
                "inputs": hashes,
                "versions": versions,
                "started": started,
                "seconds": seconds,
                "outputs": outputs,
            },
        )
        results.append(StageRun(stage.name, "ran", seconds, outputs))
        fb.info(f"run: {stage.name}: done in {seconds:.1f} s")
    ledger.data["hash_cache"] = hasher.cache
    ledger.save()
    return results


def _outputs_there(record: dict[str, Any]) -> bool:
    """Every path the stage reported still exists (a product removed by hand is made again)."""
    for v in record.get("outputs", {}).values():
        if isinstance(v, str) and (os.sep in v) and not Path(v).exists():
            return False
    return True


def check_project_folder(output: Path, force: bool = False) -> None:
    """Refuse a folder that holds something other than a geoortho project (no run.json), unless
    ``force``: a mistyped --output must not mix products into, or overwrite, someone's files."""
    if output.exists() and not output.is_dir():
        raise InputError("exists and is not a folder", path=output)
    if output.is_dir() and not (output / LEDGER_NAME).is_file() and any(output.iterdir()) and not force:
        raise InputError(
            f"holds files but no {LEDGER_NAME}: not a geoortho project (give an empty or new folder, or --force)",
            path=output,
        )


def parse_stage_options(text: str, stages: Sequence[Stage] = STAGES) -> dict[str, dict[str, Any]]:
    """Stage options from JSON text or a JSON file: ``{"sfm": {"max_image_size": 2048}, ...}``.
    Each stage's options are its own algorithm's parameters (one declaration per parameter);
    the ones the chain sets itself (inputs, outputs) cannot be given."""
    from .processing.registry import get_algorithm

    if not text:
        return {}
    path = Path(text)
    try:
        raw = json.loads(path.read_text() if not text.lstrip().startswith("{") and path.is_file() else text)
    except ValueError as e:
        raise InputError(f"stage options: not JSON ({e})") from None
    if not isinstance(raw, dict) or not all(isinstance(v, dict) for v in raw.values()):
        raise InputError('stage options: give {"stage": {"option": value, ...}, ...}')
    by_name = {s.name: s for s in stages}
    probe = Project(images=Path("."), output=Path("."), gcp_file=Path("."))
    for name, opts in raw.items():
        if name not in by_name:
            raise InputError(f"stage options: {name} is not a stage; choose from {', '.join(by_name)}")
        params = {p.name for p in get_algorithm(name).params}
        chained = set(by_name[name].values(probe))
        for key in opts:
            if key not in params:
                raise InputError(f"stage options: {name} has no option {key}")
            if key in chained:
                raise InputError(f"stage options: {name}.{key} is set by the run itself")
    return raw
