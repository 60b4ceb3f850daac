"""The chain's stages: what each runs, what it takes from the project and from the stages before it,
and what it makes.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

from geoortho.gcp.io import read_gcp_file
from geoortho.photos.heights import GpsAltitude

REPORT_NAME = "report.html"

StageName = Literal["gcp-find", "sfm", "dense", "dem", "footprints", "ortho", "mesh", "volume", "change", "report"]


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
    volumes: Path | None = None  # polygons to measure volumes over
    change_from: Path | None = None  # an earlier survey's DSM (a run project's dem/dsm.tif): what changed since

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
    opt_in: bool = False  # asked for (volumes): a run that did not ask does not list it at all


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


def _surface(p: Project) -> Path:
    """The DSM given, else the one the chain's dem makes."""
    return p.dsm if p.dsm is not None else p.folder("dem") / "dsm.tif"


def _given(p: Project, *names: str) -> dict[str, Any]:
    """Project values a stage takes as they were given, under the same names."""
    return {name: getattr(p, name) for name in names}


STAGES: tuple[Stage, ...] = (
    Stage(
        "gcp-find",
        lambda p: p.gcp_file is not None,
        lambda p, d: {
            **_given(p, "images", "gcp_file", "dsm", "crs", "takeoff_elevation_m", "flight_height_m", "workers"),
            "output": p.folder("gcp-find") / "gcp_list.txt",
            "detections": p.folder("gcp-find") / "detections.gpkg",
            "review": p.folder("gcp-find") / "review.png",
        },
        ("images", "gcp_file", "dsm"),
        weight=2,
    ),
    Stage(
        "sfm",
        lambda p: True,
        lambda p, d: {
            **_given(p, "images", "crs", "takeoff_elevation_m", "workers"),
            "output": p.folder("sfm"),
            "gcp_list": _gcp_observations(p, d),
            "checkpoints": _found_checkpoints(p, d),
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
            **_given(p, "images", "workers"),
            "sfm": p.folder("sfm"),
            "output": p.folder("dense") / "dense.laz",
            "copc": p.folder("dense") / "dense.copc.laz",  # what QGIS opens (it reads no plain LAZ here)
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
            **_given(
                p, "images", "crs", "takeoff_elevation_m", "flight_height_m", "ground_elevation_m", "gps_altitude"
            ),
            "output": p.folder("footprints") / "footprints.gpkg",
            "overlap": p.folder("footprints") / "overlap.tif",
            "sfm": p.folder("sfm"),
            "dsm": _surface(p),
        },
        ("images", "sfm", "dsm"),
        weight=1,
    ),
    Stage(
        "ortho",
        lambda p: True,
        lambda p, d: {
            **_given(p, "images", "takeoff_elevation_m", "workers"),
            "output": p.folder("ortho") / "ortho.tif",
            "sfm": p.folder("sfm"),
            "dsm": _surface(p),
            "preview": p.folder("ortho") / "ortho_preview.png",
        },
        ("images", "sfm", "dsm"),
        weight=4,
    ),
    # The 3D products: the surface made (or given) coloured by the orthophoto and its walls by the
    # photos, as glTF, and as 3D Tiles that the QGIS project opens; with an oblique picture for the report.
    Stage(
        "mesh",
        lambda p: True,
        lambda p, d: {
            **_given(p, "images", "workers"),
            "dsm": _surface(p),
            "ortho": p.folder("ortho") / "ortho.tif",
            "output": p.folder("mesh") / "mesh.glb",
            "tileset": p.folder("mesh") / "tileset" / "tileset.json",
            "view": p.folder("mesh") / "mesh_view.png",
            "sfm": p.folder("sfm"),  # its walls coloured from the photos
        },
        ("dsm", "ortho", "images", "sfm"),
        weight=1,
    ),
    # Volumes over the polygons given, on the surface made (or given), with the run's accuracy.
    Stage(
        "volume",
        lambda p: p.volumes is not None,
        lambda p, d: {"dsm": _surface(p), "polygons": p.volumes, "output": p.folder("volume") / "volumes.gpkg"},
        ("dsm", "polygons"),
        weight=0.2,
        opt_in=True,
    ),
    # What changed since an earlier survey of the site: its DSM brought onto this one's, the
    # difference, and the cut and fill areas with their volumes.
    Stage(
        "change",
        lambda p: p.change_from is not None,
        lambda p, d: {
            "reference": p.change_from,
            "compare": _surface(p),
            "output": p.folder("change") / "change.tif",
            "polygons": p.folder("change") / "change.gpkg",
        },
        ("reference", "compare"),
        weight=0.2,
        opt_in=True,
    ),
    Stage(
        "report",
        lambda p: True,
        lambda p, d: {"project": p.output, "output": p.output / REPORT_NAME},
        (),  # reads the ledger: its fingerprint is the other stages' records (see _report_inputs)
        weight=0.5,
    ),
)
