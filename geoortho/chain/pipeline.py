"""The whole chain in one resumable command: ``run``, its stages, the project folder and ``run.json``.

A project folder holds one subfolder per stage with products at stable names, ``run.json`` (the
ledger) and ``report.html``. A stage is *done* only when the ledger says so with the fingerprint
of what it was run with: its options, the content hashes of its inputs (photos, GCP file,
earlier stages' products) and the software versions. Every product is written atomically by its
stage and a stage is marked ``running`` before it starts, so a run killed mid-stage leaves that
stage not done: the next run re-does it and keeps every finished one. A stage whose fingerprint
changed is re-done; stages after it are re-done when the products they read changed (content,
not time). Paths inside the project are kept as ``PROJECT/...``, so a moved project resumes.

Here: :func:`run` and the running of its stages (the lock, reuse, execution, memory, problems).
Beside it: :mod:`.stages` (what each stage takes and makes), :mod:`.ledger` (``run.json``, the
fingerprints, content hashes) and :mod:`.run_checks` (what is checked before a stage starts).
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
from typing import Any

from pyproj import CRS

from geoortho.chain.ledger import (
    LEDGER_NAME,
    Hasher,
    Ledger,
    StageRun,
    fingerprint_of,
    from_ledger,
    outputs_there,
    product_digests,
    products_intact,
    software_versions,
    to_ledger,
)
from geoortho.chain.run_checks import (
    LOCK_NAME,
    check_given,
    check_project_folder,
    check_run_paths,
    check_stage_options,
    parse_stage_options,
)
from geoortho.chain.stages import REPORT_NAME, STAGES, Done, Project, Stage, StageName
from geoortho.core.folders import project_dsm
from geoortho.errors import GeoorthoError, InputError, interrupted
from geoortho.feedback import Feedback, as_feedback, split
from geoortho.gcp.io import read_gcp_file
from geoortho.photos.heights import GpsAltitude
from geoortho.processing.registry import (
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
    for s in stages:  # a stage asked for before and not now: its record goes as a skipped one's does
        if s.opt_in and not s.applies(project):
            ledger.data["stages"].pop(s.name, None)
    stages = [s for s in stages if s.applies(project) or not s.opt_in]
    state = _RunState(ledger, Hasher(ledger.data.get("hash_cache")), software_versions(), time.perf_counter())
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
        fp = fingerprint_of(stage, values, hashes, state.versions, root)
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
        and outputs_there(from_ledger(before.get("outputs", {}), root))
        and products_intact(before, root, state.hasher)
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
            "products": product_digests(outputs, state.hasher),
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
    volumes: Path | None = None,
    change_from: Path | None = None,
    *,
    feedback: Feedback | None = None,
) -> RunResult:
    """Run the whole chain on a folder of photos, resumably, and write a quality report.

    The stages that apply, in order: gcp-find (with a GCP file), sfm (on the found GCPs), dense
    (unless a lidar cloud is given), dem (DSM and DTM), footprints (of the SfM's cameras on the
    DSM, with the heights given checked against them), ortho (on the DSM), mesh (3D), volume
    (with volumes), change (with an earlier survey), report. No flight
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
    volumes : Path
        Polygons (stockpiles, pits; any vector format): their volumes on the DSM (see volume), with
        the run's own vertical accuracy, in the report and the QGIS project.
    change_from : Path
        An earlier survey of the site: its run project's folder or its DSM. What changed since (see
        change): its surface brought onto this one's on the ground that did not change, the
        difference, and the cut and fill areas beyond the level of detection with their volumes, in
        the report and the QGIS project.
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
        volumes=given(volumes),
        change_from=given(project_dsm(Path(change_from)) if change_from is not None else None),
    )
    if project.gcp_file is not None and project.gcp_list is not None:
        raise InputError("give --gcp-file (markers to find) or --gcp-list (observations made), not both")
    if project.checkpoints and project.gcp_file is None and project.gcp_list is None:
        raise InputError("checkpoints are named but no GCP file is given (--gcp-file or --gcp-list)")
    check_stage_options(project, fb)
    check_run_paths(project)
    check_given(project)
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
