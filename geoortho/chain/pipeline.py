"""The whole chain in one resumable command: ``run``, its stages, the project folder and ``run.json``.

A project folder holds one subfolder per stage with products at stable names, ``run.json`` (the
ledger) and ``report.html``. A stage is *done* only when the ledger says so with the fingerprint
of what it was run with: its options, the content hashes of its inputs (photos, GCP file,
earlier stages' products) and the software versions. Every product is written atomically by its
stage and a stage is marked ``running`` before it starts, so a run killed mid-stage leaves that
stage not done: the next run re-does it and keeps every finished one. A stage whose fingerprint
changed is re-done; stages after it are re-done when the products they read changed (content,
not time). Paths inside the project are kept as ``PROJECT/...``, so a moved project resumes.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

from pyproj import CRS

from geoortho.core.outputs import write_json
from geoortho.core.pointcloud import check_las_header
from geoortho.core.surface import refuse_image
from geoortho.errors import GeoorthoError, InputError, interrupted
from geoortho.feedback import Feedback, as_feedback, split
from geoortho.gcp.io import read_gcp_file
from geoortho.photos.heights import GpsAltitude
from geoortho.photos.metadata import list_images
from geoortho.processing.registry import (
    check_in_context,
    convert_value,
    get_algorithm,
    refuse_overwrites,
    run_algorithm,
)

__all__ = [
    "STAGES",
    "Ledger",
    "Project",
    "RunResult",
    "Stage",
    "StageRun",
    "check_project_folder",
    "parse_stage_options",
    "run",
    "run_stages",
]

LEDGER_NAME = "run.json"
LEDGER_VERSION = 2
REPORT_NAME = "report.html"
#: Prefix of a path inside the project, as the ledger keeps it.
PROJECT_PREFIX = "PROJECT/"

StageName = Literal["gcp-find", "sfm", "dense", "dem", "footprints", "ortho", "report"]


@dataclass(frozen=True)
class Project:
    """What the user gave, and where the products go."""

    images: Path
    output: Path
    gcp_file: Path | None = None
    gcp_list: Path | None = None  # observations already made (clicked, or an earlier gcp-find)
    checkpoints: str = ""
    points: Path | None = None
    dsm: Path | None = None
    crs: str | None = None
    takeoff_elevation_m: float | None = None
    flight_height_m: float | None = None
    ground_elevation_m: float | None = None
    gps_altitude: GpsAltitude = "auto"
    workers: int = 0
    options: dict[str, dict[str, Any]] = field(default_factory=dict)  # stage -> its own options
    positions: Path | None = None  # PPK/surveyed camera positions for the SfM
    split: int = 0  # split-merge SfM: submodels of at most this many photos (0: one block)
    split_overlap_m: float | None = None  # the submodels' overlap (None: sfm's default)

    def folder(self, stage: str) -> Path:
        return self.output / stage


#: What earlier stages of this run produced (their outputs), by stage name.
Done = dict[str, dict[str, Any]]


@dataclass(frozen=True)
class Stage:
    """One step of the chain: the algorithm it runs, when it applies, its values (from the project
    and earlier stages' outputs; products at stable paths) and which values are files it reads."""

    name: str  # the algorithm id
    applies: Callable[[Project], bool]
    values: Callable[[Project, Done], dict[str, Any]]
    inputs: tuple[str, ...]  # the value names that are files or folders read (hashed)
    weight: float = 1.0  # share of a typical run's time, for the overall progress bar


def _gcp_observations(p: Project, done: Done) -> Path | None:
    """The gcp_list.txt given, or the one found, when gcp-find found any marker (else SfM runs on
    GPS alone)."""
    if p.gcp_list is not None:
        return p.gcp_list
    found = done.get("gcp-find") or {}
    return Path(found["output"]) if found.get("n_observations") else None


def _found_checkpoints(p: Project, done: Done) -> str | None:
    """The named checkpoints that gcp-find found (one not found is reported, not fatal)."""
    gcp_list = _gcp_observations(p, done)
    if not p.checkpoints or gcp_list is None:
        return None

    if p.checkpoints.strip().lower() in ("all", "none"):
        return p.checkpoints.strip().lower()
    found = set(read_gcp_file(gcp_list).by_name())
    names = [c.strip() for c in p.checkpoints.split(",") if c.strip() in found]
    return ",".join(names) or None


def _cloud(p: Project) -> Path:
    return p.points if p.points is not None else p.folder("dense") / "dense.laz"


STAGES: tuple[Stage, ...] = (
    Stage(
        "gcp-find",
        lambda p: p.gcp_file is not None,
        lambda p, d: {
            "images": p.images,
            "gcp_file": p.gcp_file,
            "output": p.folder("gcp-find") / "gcp_list.txt",
            "detections": p.folder("gcp-find") / "detections.gpkg",
            "review": p.folder("gcp-find") / "review.png",
            "dsm": p.dsm,
            "crs": p.crs,
            "takeoff_elevation_m": p.takeoff_elevation_m,
            "flight_height_m": p.flight_height_m,
            "workers": p.workers,
        },
        ("images", "gcp_file", "dsm"),
        weight=2,
    ),
    Stage(
        "sfm",
        lambda p: True,
        lambda p, d: {
            "images": p.images,
            "output": p.folder("sfm"),
            "gcp_list": _gcp_observations(p, d),
            "checkpoints": _found_checkpoints(p, d),
            "crs": p.crs,
            "takeoff_elevation_m": p.takeoff_elevation_m,
            "workers": p.workers,
            **({"positions": p.positions} if p.positions is not None else {}),
            # only when splitting: a one-block project's ledger (and so its resume) is unchanged
            **({"split": p.split} if p.split else {}),
            **({"split_overlap_m": p.split_overlap_m} if p.split and p.split_overlap_m is not None else {}),
        },
        ("images", "gcp_list", "positions"),
        weight=6,
    ),
    Stage(
        "dense",
        lambda p: p.points is None,
        lambda p, d: {
            "sfm": p.folder("sfm"),
            "images": p.images,
            "output": p.folder("dense") / "dense.laz",
            "workers": p.workers,
        },
        ("sfm", "images"),
        weight=5,
    ),
    Stage(
        "dem",
        lambda p: True,
        lambda p, d: {
            "points": _cloud(p),
            "output": p.folder("dem") / "dsm.tif",
            "dtm": p.folder("dem") / "dtm.tif",
            "hillshade": p.folder("dem") / "dtm_hillshade.png",
            "contours": p.folder("dem") / "contours.gpkg",
            "crs": p.crs if p.points is not None else None,
            # the photos' cloud is carried to the edge of what they saw; a lidar cloud is what it is
            "sfm": p.folder("sfm") if p.points is None else None,
            # the photos' cloud is one noisy surface: idw, as dem's auto chooses, named in the ledger
            # (only when it applies: a stage option may still choose)
            **({"method": "idw"} if p.points is None else {}),
        },
        ("points", "sfm"),
        weight=1,
    ),
    # The footprints of the cameras the SfM measured, on the surface made (or given): the report's
    # GSD and area are measured, not read from a flight height; the heights the metadata and the
    # options give are checked against them (a disagreement is a red problem).
    Stage(
        "footprints",
        lambda p: True,
        lambda p, d: {
            "images": p.images,
            "output": p.folder("footprints") / "footprints.gpkg",
            "overlap": p.folder("footprints") / "overlap.tif",
            "sfm": p.folder("sfm"),
            "dsm": p.dsm if p.dsm is not None else p.folder("dem") / "dsm.tif",
            "crs": p.crs,
            "takeoff_elevation_m": p.takeoff_elevation_m,
            "flight_height_m": p.flight_height_m,
            "ground_elevation_m": p.ground_elevation_m,
            "gps_altitude": p.gps_altitude,
        },
        ("images", "sfm", "dsm"),
        weight=1,
    ),
    Stage(
        "ortho",
        lambda p: True,
        lambda p, d: {
            "images": p.images,
            "output": p.folder("ortho") / "ortho.tif",
            "sfm": p.folder("sfm"),
            "dsm": p.dsm if p.dsm is not None else p.folder("dem") / "dsm.tif",
            "preview": p.folder("ortho") / "ortho_preview.png",
            "takeoff_elevation_m": p.takeoff_elevation_m,
            "workers": p.workers,
        },
        ("images", "sfm", "dsm"),
        weight=4,
    ),
    Stage(
        "report",
        lambda p: True,
        lambda p, d: {"project": p.output, "output": p.output / REPORT_NAME},
        (),  # reads the ledger: its fingerprint is the other stages' records (see _report_inputs)
        weight=0.5,
    ),
)


# --- content hashes ------------------------------------------------------------------------------


#: How much of a file's head is read on every run to trust its cached hash: a photo's EXIF/XMP
#: lies in it, and a geotagger writing it in place may keep the size and the time stamp
#: (``exiftool -P``).
HEAD_BYTES = 1 << 16


class Hasher:
    """SHA-256 of files and folders (sorted relative names + contents), cached by size, mtime and
    the file's head (its first 64 KiB, where a photo's metadata is), so that a second run over
    unchanged photos reads 64 KiB of each and no more."""

    def __init__(self, cache: dict[str, list[Any]] | None = None) -> None:
        self.cache: dict[str, list[Any]] = dict(cache) if isinstance(cache, dict) else {}
        self.bytes_read = 0
        # files checked in this run, by their stat: the photos are inputs of four stages and the
        # products are checked again when reused; a file rewritten since has another stat
        self._checked: dict[tuple[str, int, int, int], str] = {}

    def file(self, path: Path) -> str:
        st = path.stat()
        key = str(path.resolve())
        seen = (key, st.st_size, st.st_mtime_ns, st.st_ino)
        if seen in self._checked:
            return self._checked[seen]
        with open(path, "rb") as f:
            first = f.read(HEAD_BYTES)
            head = hashlib.sha256(first).hexdigest()
            hit = self.cache.get(key)
            if isinstance(hit, list) and hit[:2] == [st.st_size, st.st_mtime_ns] and hit[3:4] == [head]:
                self.bytes_read += len(first)
                digest = str(hit[2])
            else:
                h = hashlib.sha256(first)
                for block in iter(lambda: f.read(1 << 20), b""):
                    h.update(block)
                self.bytes_read += st.st_size
                digest = h.hexdigest()
                self.cache[key] = [st.st_size, st.st_mtime_ns, digest, head]
        self._checked[seen] = digest
        return digest

    def photos(self, folder: Path) -> str:
        """The photos of a folder as the stages read them (its image files, not below it): notes or
        a project folder beside them change nothing."""

        h = hashlib.sha256()
        for f in list_images(folder):
            h.update(f.name.encode() + b"\0" + self.file(f).encode() + b"\n")
        return h.hexdigest()

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


# --- paths as the ledger keeps them --------------------------------------------------------------


def to_ledger(v: Any, root: Path) -> Any:
    """Paths (and path strings) inside the project as ``PROJECT/...``; the rest as JSON values."""
    if isinstance(v, dict):
        return {k: to_ledger(x, root) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [to_ledger(x, root) for x in v]
    if isinstance(v, Path) or (isinstance(v, str) and os.path.isabs(v)):
        try:
            return PROJECT_PREFIX + Path(v).resolve().relative_to(root.resolve()).as_posix()
        except ValueError:
            return str(v)
    return v


def from_ledger(v: Any, root: Path) -> Any:
    """The inverse of :func:`to_ledger`: ``PROJECT/...`` back to a path string under ``root``."""
    if isinstance(v, dict):
        return {k: from_ledger(x, root) for k, x in v.items()}
    if isinstance(v, list):
        return [from_ledger(x, root) for x in v]
    if isinstance(v, str) and v.startswith(PROJECT_PREFIX):
        return str(root / v[len(PROJECT_PREFIX) :])
    return v


# --- the ledger ----------------------------------------------------------------------------------


class Ledger:
    """``PROJECT/run.json``: per stage its status, fingerprint, options, input hashes, outputs,
    seconds, peak memory and warnings; the runs; written atomically after every change of status."""

    def __init__(self, path: Path, force: bool = False) -> None:
        self.path = path
        self.data: dict[str, Any] = {"version": LEDGER_VERSION, "stages": {}, "runs": [], "hash_cache": {}}
        if path.is_file():
            try:
                loaded = json.loads(path.read_text())
                why = ledger_problem(loaded)
            except (ValueError, UnicodeDecodeError) as e:
                why = f"not JSON ({' '.join(str(e).split())})"
            if why and not force:
                raise InputError(
                    f"not a run ledger this version reads: {why}; give --force to start the project again",
                    path=path,
                )
            if not why:
                self.data = {**self.data, **loaded}

    def stage(self, name: str) -> dict[str, Any]:
        return dict(self.data["stages"].get(name, {}))

    def set_stage(self, name: str, record: dict[str, Any]) -> None:
        self.data["stages"][name] = record
        self.save()

    def save(self) -> None:

        write_json(self.path, self.data)


def ledger_problem(data: Any) -> str:
    """What is wrong with a ``run.json`` (a hand edit, another version); "" when nothing."""
    if not isinstance(data, dict):
        return f"it holds a {type(data).__name__}, not an object"
    if data.get("version") != LEDGER_VERSION:
        return f"version {data.get('version')!r}, not {LEDGER_VERSION}"
    kinds = {"stages": dict, "runs": list, "hash_cache": dict}
    for key, kind in kinds.items():
        if key in data and not isinstance(data[key], kind):
            return f"'{key}' is a {type(data[key]).__name__}, not {'an object' if kind is dict else 'a list'}"
    bad = [k for k, v in (data.get("stages") or {}).items() if not isinstance(v, dict)]
    if bad:
        return f"stage '{bad[0]}' is not an object"
    fields: dict[str, tuple[type, ...]] = {
        "status": (str,), "fingerprint": (str,), "outputs": (dict,), "values": (dict,), "inputs": (dict,),
        "seconds": (int, float), "started": (int, float), "warnings": (list,), "products": (dict,),
        "versions": (dict,),
    }  # fmt: skip
    for name, record in (data.get("stages") or {}).items():
        for key, allowed in fields.items():
            value = record.get(key)
            if value is not None and (not isinstance(value, allowed) or isinstance(value, bool)):
                return f"stage '{name}': '{key}' is a {type(value).__name__}"
    if any(not isinstance(r, dict) for r in data.get("runs") or []):
        return "a run record is not an object"
    if not isinstance(data.get("problems", []), list) or not isinstance(data.get("current_run", {}), dict):
        return "'problems' or 'current_run' is of the wrong type"
    return ""


@dataclass(frozen=True)
class StageRun:
    """What happened to one stage in this run."""

    name: str
    status: str  # "ran", "reused", "skipped" (does not apply), "failed", "not run" (after a failure)
    seconds: float
    outputs: dict[str, Any]


def _fingerprint(
    stage: Stage, values: dict[str, Any], hashes: dict[str, str], versions: dict[str, str], root: Path
) -> str:
    # files read count by content only: a photo folder moved or given by another path is the same input
    record = {
        "stage": stage.name,
        "values": to_ledger({k: v for k, v in sorted(values.items()) if k not in hashes}, root),
        "inputs": hashes,
        "versions": versions,
    }
    return hashlib.sha256(json.dumps(record, sort_keys=True, default=str).encode()).hexdigest()


def _report_inputs(ledger: Ledger, names: Sequence[str], problems: list[dict[str, str]]) -> dict[str, str]:
    """What the report is made from: every other stage's record as this run leaves it."""
    records = {n: {k: ledger.stage(n).get(k) for k in ("status", "fingerprint", "started")} for n in names}
    blob = json.dumps({"stages": records, "problems": problems}, sort_keys=True, default=str)
    return {"stages": hashlib.sha256(blob.encode()).hexdigest()}


class _PeakMemory:
    """Peak resident memory while a stage runs, sampled every 0.25 s: this process, and this
    process with its children (the stages' worker pools; shared pages are counted per process)."""

    def __init__(self, interval_s: float = 0.25) -> None:
        self.interval_s = interval_s
        self.main_mb = 0.0
        self.total_mb = 0.0
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def _sample(self) -> None:
        import psutil

        me = psutil.Process()
        while True:
            try:
                main = me.memory_info().rss
                total = main
                for child in me.children(recursive=True):
                    try:
                        total += child.memory_info().rss
                    except psutil.Error:
                        continue
            except psutil.Error:
                main = total = 0
            self.main_mb = max(self.main_mb, main / 2**20)
            self.total_mb = max(self.total_mb, total / 2**20)
            if self._stop.wait(self.interval_s):
                return

    def __enter__(self) -> _PeakMemory:
        self._thread = threading.Thread(target=self._sample, name="geoortho-peak-memory", daemon=True)
        self._thread.start()
        return self

    def __exit__(self, *exc: Any) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join()


class _Recorder(Feedback):
    """Passes everything on to the run's feedback and keeps the stage's warnings for the report."""

    def __init__(self, parent: Feedback) -> None:
        super().__init__()
        self._parent = parent
        self.warnings: list[str] = []

    def set_progress(self, fraction: float) -> None:
        self._parent.progress(fraction)

    def info(self, message: str) -> None:
        self._parent.info(message)

    def warning(self, message: str) -> None:
        self.warnings.append(message)
        self._parent.warning(message)

    def is_canceled(self) -> bool:
        return self._parent.is_canceled() or super().is_canceled()

    def cancel(self) -> None:
        self._parent.cancel()


def _stage_problems(stage: str, outputs: dict[str, Any], project: Project) -> list[dict[str, str]]:
    """What a finished stage's outputs say the client must be told (shown in red in the report)."""
    out: list[dict[str, str]] = []
    if stage == "gcp-find" and not outputs.get("n_observations"):
        out.append(
            {
                "stage": stage,
                "level": "error",
                "message": "no GCP marker was found in any photo: SfM ran without GCPs (GPS only); "
                "the products' absolute accuracy is the GPS's, not the survey's",
            }
        )
    if stage == "dense" and outputs.get("n_depth_maps") == 0:
        out.append(
            {
                "stage": stage,
                "level": "error",
                "message": "no depth could be measured in any photo (water, snow, or poses that do not fit): the "
                "surface is interpolated from the SfM's tie points",
            }
        )
    if stage == "footprints" and outputs.get("height_check"):
        out.append({"stage": stage, "level": "error", "message": str(outputs["height_check"])})
    observed = Path(outputs["output"]) if stage == "gcp-find" and outputs.get("n_observations") else None
    if stage == "footprints" and project.gcp_list is not None:
        observed = project.gcp_list
    if observed is not None and project.checkpoints:
        found = set(read_gcp_file(observed).by_name())
        missing = [c.strip() for c in project.checkpoints.split(",") if c.strip() and c.strip() not in found]
        if missing:
            out.append(
                {
                    "stage": stage,
                    "level": "error",
                    "message": f"checkpoint(s) not found in any photo, so not measured: {', '.join(missing)}",
                }
            )
    return out


def run_stages(
    project: Project,
    *,
    rerun_from: str | None = None,
    stages: Sequence[Stage] = STAGES,
    runner: Callable[[str, dict[str, Any], Feedback], dict[str, Any]] | None = None,
    feedback: Feedback | None = None,
    force: bool = False,
) -> list[StageRun]:
    """Run the stages that apply, re-using every one whose fingerprint is unchanged and whose
    outputs are still there; ``rerun_from`` forces that stage and every later one.

    A stage that fails is marked so in the ledger, the report is still written (it says which
    stage failed and keeps every earlier product), and the error is raised again, naming the stage.
    ``force``: a ledger that cannot be read is started afresh instead of refused.
    """
    fb = as_feedback(feedback)
    names = [s.name for s in stages]
    if rerun_from is not None and rerun_from not in names:
        raise InputError(f"--rerun-from {rerun_from}: not a stage; choose from {', '.join(names)}")
    unknown = set(project.options) - set(names)
    if unknown:
        raise InputError(f"options for {sorted(unknown)[0]}: not a stage; choose from {', '.join(names)}")
    project.output.mkdir(parents=True, exist_ok=True)
    root = project.output
    with _project_lock(root):
        return _run_stages(project, root, rerun_from, stages, runner, fb, force)


LOCK_NAME = ".run.lock"


@contextlib.contextmanager
def _project_lock(root: Path) -> Iterator[None]:
    """One run at a time on a project: a second would redo the same stages and lose a run record.
    An advisory lock the system drops with its process (a killed run leaves none behind); the file
    is removed when the run ends. Never through a link: a lock that is a symlink would truncate
    what it points to."""
    import fcntl

    path = root / LOCK_NAME
    while True:
        try:
            fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW, 0o644)
        except OSError:
            raise InputError(f"{LOCK_NAME} is a link or a folder, not a run's lock: remove it", path=root) from None
        f = os.fdopen(fd, "r+")
        try:
            fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            f.seek(0)
            pid = f.read(32).strip() or "?"
            f.close()
            raise InputError(
                f"another run is working on this project (process {pid}): wait for it", path=root
            ) from None
        # a run that ended between our open and our lock removed the file we hold: take the new one
        try:
            same = os.path.samestat(os.fstat(fd), os.stat(path, follow_symlinks=False))
        except OSError:
            same = False
        if same:
            break
        f.close()
    with f:
        f.seek(0)
        f.truncate()
        f.write(str(os.getpid()))
        f.flush()
        try:
            yield
        finally:
            with contextlib.suppress(OSError):
                path.unlink()
            fcntl.flock(f, fcntl.LOCK_UN)


@dataclass
class _RunState:
    """What one run of the stages carries from stage to stage."""

    ledger: Ledger
    hasher: Hasher
    versions: dict[str, str]
    t_run: float
    results: list[StageRun] = field(default_factory=list)
    done: Done = field(default_factory=dict)
    problems: list[dict[str, str]] = field(default_factory=list)
    failure: BaseException | None = None


def _run_stages(
    project: Project,
    root: Path,
    rerun_from: str | None,
    stages: Sequence[Stage],
    runner: Callable[[str, dict[str, Any], Feedback], dict[str, Any]] | None,
    fb: Feedback,
    force: bool,
) -> list[StageRun]:
    """Each stage in turn: skipped when it does not apply, reused when its fingerprint and products
    are unchanged, else run and recorded in the ledger; then the run itself is recorded."""

    ledger = Ledger(root / LEDGER_NAME, force=force)
    state = _RunState(ledger, Hasher(ledger.data.get("hash_cache")), _versions(), time.perf_counter())
    run_one = runner or (lambda name, values, f: run_algorithm(name, values, feedback=f))
    names = [s.name for s in stages]
    forced = False
    weights = [s.weight if s.applies(project) else 0.01 for s in stages]
    steps = split(fb, weights)
    total = sum(weights)
    start = 0.0
    for index, (stage, step, weight) in enumerate(zip(stages, steps, weights), 1):
        fb.stage(stage.name, index, len(stages), start / total, weight / total)
        start += weight
        forced = forced or stage.name == rerun_from
        if state.failure is not None and stage.name != "report":
            state.results.append(StageRun(stage.name, "not run", 0.0, {}))
            continue
        if not stage.applies(project):
            ledger.data["stages"].pop(stage.name, None)
            state.results.append(StageRun(stage.name, "skipped", 0.0, {}))
            step.progress(1.0)
            continue
        values, hashes = _stage_inputs(stage, project, state, names)
        fp = _fingerprint(stage, values, hashes, state.versions, root)
        if not forced and _reuse(stage, fp, project, state, root):
            fb.info(f"run: {stage.name}: unchanged, reused")
            step.progress(1.0)
            continue
        seconds = _execute(stage, values, hashes, fp, project, state, root, run_one, step)
        if seconds is not None:
            fb.info(f"run: {stage.name}: done in {seconds:.1f} s")
    _record_run(state)
    if state.failure is not None:
        _raise_failure(state, root)
    return state.results


def _stage_inputs(
    stage: Stage, project: Project, state: _RunState, names: list[str]
) -> tuple[dict[str, Any], dict[str, Any]]:
    """The stage's values (from the stages before it and the project's options) and the digests of
    its inputs; the report's also say what this run did (its hook into the ledger)."""
    values = {k: v for k, v in stage.values(project, state.done).items() if v is not None}
    values.update(project.options.get(stage.name, {}))
    hasher = state.hasher
    hashes = {
        k: hasher.photos(Path(values[k])) if k == "images" else hasher.path(Path(values[k]))
        for k in stage.inputs
        if k in values
    }
    if stage.name == "report":
        ledger = state.ledger
        hashes.update(_report_inputs(ledger, [n for n in names if n != "report"], state.problems))
        # what the report shows of this run (not part of its fingerprint: a run that changed
        # nothing keeps the report the last change made)
        ledger.data["problems"] = state.problems
        elapsed = time.perf_counter() - state.t_run
        ledger.data["current_run"] = {
            "started": time.time() - elapsed,
            "seconds_before_report": round(elapsed, 3),
            "overhead_seconds": round(max(0.0, elapsed - sum(r.seconds for r in state.results)), 3),
            "stages": {r.name: r.status for r in state.results},
        }
        ledger.save()
    return values, hashes


def _reuse(stage: Stage, fp: str, project: Project, state: _RunState, root: Path) -> bool:
    """The stage's last run, taken as it is when its fingerprint is the same and its products are
    there and untouched."""
    before = state.ledger.stage(stage.name)
    if not (
        before.get("status") == "done"
        and before.get("fingerprint") == fp
        and _outputs_there(from_ledger(before.get("outputs", {}), root))
        and _products_intact(before, root, state.hasher)
    ):
        return False
    outputs = from_ledger(before.get("outputs", {}), root)
    state.done[stage.name] = outputs
    state.problems.extend(_stage_problems(stage.name, outputs, project))
    state.results.append(StageRun(stage.name, "reused", 0.0, outputs))
    return True


def _execute(
    stage: Stage,
    values: dict[str, Any],
    hashes: dict[str, Any],
    fp: str,
    project: Project,
    state: _RunState,
    root: Path,
    run_one: Callable[[str, dict[str, Any], Feedback], dict[str, Any]],
    step: Feedback,
) -> float | None:
    """Run the stage and record it in the ledger, done or failed; its seconds (None: it failed,
    and the run goes on to the report; a cancel, or a failed report, is raised)."""
    ledger = state.ledger
    if stage.name != "report":
        project.folder(stage.name).mkdir(parents=True, exist_ok=True)
        _remove_leftovers(project.folder(stage.name))
    started = time.time()
    ledger.set_stage(stage.name, {"status": "running", "started": started, "fingerprint": fp})
    recorder = _Recorder(step)
    t0 = time.perf_counter()
    try:
        with _PeakMemory() as memory:
            outputs = run_one(stage.name, dict(values), recorder)
    except BaseException as e:
        seconds = time.perf_counter() - t0
        status = "canceled" if interrupted(e) else "failed"
        ledger.set_stage(
            stage.name,
            {
                "status": status,
                "fingerprint": fp,
                "started": started,
                "seconds": seconds,
                "error": " ".join(str(e).split()) or type(e).__name__,
                "error_type": type(e).__name__,
                "values": to_ledger(values, root),
                "warnings": recorder.warnings,
            },
        )
        state.results.append(StageRun(stage.name, status, seconds, {}))
        if status == "canceled" or stage.name == "report":
            raise
        state.failure = e
        state.problems.append({"stage": stage.name, "level": "error", "message": f"stage failed: {e}"})
        return None
    seconds = time.perf_counter() - t0
    ledger.data["hash_cache"] = state.hasher.cache
    ledger.set_stage(
        stage.name,
        {
            "status": "done",
            "fingerprint": fp,
            "values": to_ledger(values, root),
            "inputs": hashes,
            "versions": state.versions,
            "started": started,
            "seconds": seconds,
            "peak_memory_mb": {"main": round(memory.main_mb, 1), "with_workers": round(memory.total_mb, 1)},
            "warnings": recorder.warnings,
            "outputs": to_ledger(outputs, root),
            "products": _product_digests(outputs, state.hasher),
        },
    )
    state.done[stage.name] = outputs
    state.problems.extend(_stage_problems(stage.name, outputs, project))
    state.results.append(StageRun(stage.name, "ran", seconds, outputs))
    return seconds


def _record_run(state: _RunState) -> None:
    """The run in the ledger: its time, its overhead and what each stage did (the last 20 runs)."""
    ledger = state.ledger
    total_seconds = time.perf_counter() - state.t_run
    ledger.data["hash_cache"] = state.hasher.cache
    ledger.data["problems"] = state.problems
    ledger.data["runs"] = [
        *ledger.data.get("runs", [])[-19:],
        {
            "finished": time.time(),
            "seconds": round(total_seconds, 3),
            # everything but the stages themselves: hashing, fingerprints, the ledger
            "overhead_seconds": round(max(0.0, total_seconds - sum(r.seconds for r in state.results)), 3),
            "stages": {r.name: r.status for r in state.results},
        },
    ]
    ledger.save()


def _raise_failure(state: _RunState, root: Path) -> None:
    """The failed stage's error, raised again naming the stage (earlier products kept)."""
    failure = state.failure
    assert failure is not None
    name = next(r.name for r in state.results if r.status == "failed")
    tail = f"earlier products kept; see {root / REPORT_NAME}"
    if isinstance(failure, InputError):
        raise InputError(f"stage {name}: {' '.join(str(failure).split())} ({tail})") from failure
    raise GeoorthoError(
        f"stage {name} failed: {type(failure).__name__}: {' '.join(str(failure).split())} ({tail})"
    ) from failure


def _remove_leftovers(folder: Path) -> None:
    """Temporary files of a run killed in this stage (outputs.atomic_path's ``.name.tmp-*``): never
    a product, and the stage is about to be re-done."""
    for tmp in folder.rglob(".*.tmp-*"):
        if tmp.is_file():
            tmp.unlink(missing_ok=True)


def _outputs_there(outputs: dict[str, Any]) -> bool:
    """Every path the stage reported still exists (a product removed by hand is made again)."""
    for v in outputs.values():
        if isinstance(v, str) and os.path.isabs(v) and not Path(v).exists():
            return False
    return True


def _product_digests(outputs: dict[str, Any], hasher: Hasher) -> dict[str, str]:
    """Each product file or folder a stage made, by its output name: its digest when made."""
    return {
        k: hasher.path(Path(v))
        for k, v in outputs.items()
        if isinstance(v, str) and os.path.isabs(v) and Path(v).exists()
    }


def _products_intact(record: dict[str, Any], root: Path, hasher: Hasher) -> bool:
    """Every product is as its stage left it: one truncated, replaced or edited by hand is made again
    (and what reads it after it)."""
    outputs = from_ledger(record.get("outputs", {}), root)
    for k, digest in (record.get("products") or {}).items():
        path = outputs.get(k)
        if not isinstance(path, str) or not Path(path).exists() or hasher.path(Path(path)) != digest:
            return False
    return True


def _check_given(project: Project) -> None:
    """The files given are read now, not when their stage comes minutes into the run: a DSM that
    is no elevation raster, a cloud that is no point cloud, a GCP file that does not parse."""
    import rasterio
    from rasterio.errors import RasterioIOError

    list_images(project.images)
    if project.dsm is not None:
        try:
            with rasterio.open(project.dsm) as ds:
                if ds.crs is None:
                    raise InputError("the DSM has no CRS", path=project.dsm)
                refuse_image(ds, project.dsm)
        except RasterioIOError as e:
            raise InputError(f"not an elevation raster ({e})", path=project.dsm) from None
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
            ("dsm", project.dsm), ("positions", project.positions),
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


# --- the algorithm -------------------------------------------------------------------------------


@dataclass(frozen=True)
class RunResult:
    """What ``run`` made.

    Attributes
    ----------
    output : Path
        The project folder.
    report : Path
        The quality report (report.html): self-contained, printable to PDF from a browser.
    ledger : Path
        run.json: each stage's options, input hashes, versions, status, seconds, outputs.
    ortho : Path
        The orthophoto (COG GeoTIFF).
    dsm : Path
        The DSM (COG GeoTIFF); the one given when ``dsm`` was given.
    dtm : Path
        The DTM (COG GeoTIFF).
    stages : dict of str to str
        What happened to each stage: ran, reused or skipped.
    seconds : float
        Wall time of this run.
    """

    output: Path
    report: Path
    ledger: Path
    ortho: Path
    dsm: Path
    dtm: Path
    stages: dict[str, str]
    seconds: float


def run(
    images: Path,
    output: Path,
    gcp_file: Path | None = None,
    gcp_list: Path | None = None,
    checkpoints: str = "",
    points: Path | None = None,
    dsm: Path | None = None,
    crs: CRS | None = None,
    takeoff_elevation_m: float | None = None,
    flight_height_m: float | None = None,
    ground_elevation_m: float | None = None,
    gps_altitude: GpsAltitude = "auto",
    stage_options: str = "",
    rerun_from: StageName | None = None,
    force: bool = False,
    workers: int = 0,
    positions: Path | None = None,
    split: int = 0,
    split_overlap_m: float | None = None,
    *,
    feedback: Feedback | None = None,
) -> RunResult:
    """Run the whole chain on a folder of photos, resumably, and write a quality report.

    The stages that apply, in order: gcp-find (with a GCP file), sfm (on the found GCPs), dense
    (unless a lidar cloud is given), dem (DSM and DTM), footprints (of the SfM's cameras on the
    DSM, with the heights given checked against them), ortho (on the DSM), report. No flight
    height is needed: the SfM measures it.
    Each writes into its own subfolder of the project at stable names; ``run.json`` records
    what each was run with. Run again and only the stages whose inputs or options changed are
    re-done, with everything after them; a run that was killed resumes at the stage it was in.

    Parameters
    ----------
    images : Path
        Folder of photos.
    output : Path
        Project folder (new, empty, or an earlier run's).
    gcp_file : Path
        Surveyed GCP coordinates (any format gcp-find reads): markers are found in the photos
        and SfM is put on them. When none is found the run goes on without GCPs and says so.
    gcp_list : Path
        An OpenDroneMap gcp_list.txt whose image observations are already made (clicked by hand,
        or by an earlier gcp-find): SfM is put on it directly, with no gcp-find stage.
    checkpoints : str
        GCP names held out of the adjustment and measured, comma-separated.
    points : Path
        A lidar point cloud: the DSM and DTM are made from it and the dense stage is skipped.
    dsm : Path
        A DSM to use for footprints, GCP prediction and the orthophoto instead of the one made.
    crs : CRS
        Output CRS (default: the UTM zone of the photos).
    takeoff_elevation_m : float
        Ground elevation of the take-off point, in the vertical datum of the ground
        model (the DSM, the ground elevation or the GCPs). Default: worked out from the
        photos (absolute − relative altitude, checked against the
        ground model; else the ground under the flight), and said.
    flight_height_m : float
        Flight height above the take-off ground, for photos whose altitudes give none: used to
        predict the GCPs in the photos. Never needed: the SfM measures the heights, and a
        flight height more than 10 % off what it measured is reported in red.
    ground_elevation_m : float
        Ground elevation under the flight (datum of the GCPs), checked against the surface made.
    gps_altitude : str
        What GPSAltitude holds when the photos have no RelativeAltitude: auto, above-takeoff,
        orthometric or ellipsoidal (see footprints).
    stage_options : str
        Options of each stage as JSON, or a JSON file: {"sfm": {"max_image_size": 2048},
        "ortho": {"resolution_m": 0.05}}; names and values are the stages' own parameters.
    rerun_from : str
        Re-do this stage and every later one even when unchanged.
    force : bool
        Use an output folder that holds other files (not an earlier run's project).
    workers : int
        Worker processes for the per-photo stages (0 = every core).
    positions : Path
        Post-processed (PPK) or surveyed camera positions for the SfM (see sfm): an RTKLIB .pos,
        a DJI Timestamp.MRK or a CSV. With RTK/PPK-grade positions the GCPs are checkpoints
        unless checkpoints says otherwise ('none': they control the block).
    split : int
        Split-merge for large surveys (see sfm): the SfM reconstructs submodels of at most this
        many photos, by position (as tasks on the Dask cluster when one is given), and merges them
        into one model, from which the dense cloud, DSM, DTM and orthophoto are made whole (0 = one
        block). A submodel that fails is named and its photos' ground is shown as left out; a run
        killed mid-way reuses the submodels already made.
    split_overlap_m : float
        Each submodel also takes its neighbours' photos within this distance (m; default: sfm's 30).
    """
    fb = as_feedback(feedback)
    t0 = time.perf_counter()
    # Every path absolute from here: the ledger keeps the project's own as PROJECT/..., the rest as
    # they are, so a project resumes from any working folder and under any path naming it.
    output = Path(output).absolute()
    check_project_folder(output, force)
    options = parse_stage_options(stage_options)

    def given(path: Path | None) -> Path | None:
        return Path(path).absolute() if path is not None else None

    project = Project(
        images=Path(images).absolute(),
        output=output,
        gcp_file=given(gcp_file),
        gcp_list=given(gcp_list),
        checkpoints=checkpoints or "",
        points=given(points),
        dsm=given(dsm),
        crs=str(crs) if crs is not None else None,  # its srs text: what the ledger has always recorded
        takeoff_elevation_m=takeoff_elevation_m,
        flight_height_m=flight_height_m,
        ground_elevation_m=ground_elevation_m,
        gps_altitude=gps_altitude,
        workers=workers,
        options=options,
        positions=given(positions),
        split=int(split or 0),
        split_overlap_m=split_overlap_m,
    )
    if project.gcp_file is not None and project.gcp_list is not None:
        raise InputError("give --gcp-file (markers to find) or --gcp-list (observations made), not both")
    if project.checkpoints and project.gcp_file is None and project.gcp_list is None:
        raise InputError("checkpoints are named but no GCP file is given (--gcp-file or --gcp-list)")
    check_stage_options(project, fb)
    check_run_paths(project)
    _check_given(project)
    results = run_stages(project, rerun_from=rerun_from, feedback=fb, force=force)
    by_name = {r.name: r for r in results}
    ran = [r.name for r in results if r.status == "ran"]
    reused = [r.name for r in results if r.status == "reused"]
    fb.info(f"run: {len(ran)} stage(s) run ({', '.join(ran) or 'none'}), {len(reused)} reused")
    report = output / REPORT_NAME
    fb.info(f"report: {report}")
    dem_out = by_name["dem"].outputs
    return RunResult(
        output=output,
        report=report,
        ledger=output / LEDGER_NAME,
        ortho=Path(by_name["ortho"].outputs["output"]),
        dsm=Path(dsm) if dsm is not None else Path(dem_out["dsm"]),
        dtm=Path(dem_out["dtm"]),
        stages={r.name: r.status for r in results},
        seconds=time.perf_counter() - t0,
    )
