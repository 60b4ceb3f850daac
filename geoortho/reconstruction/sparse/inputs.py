"""What sfm reads and decides before any photogrammetry: the photos and their camera bodies, the
GPS priors, the GCPs and checkpoints, the output CRS, and the options' choices."""

from __future__ import annotations

import math
import os
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, get_args

import numpy as np
from pyproj import CRS

from geoortho.core.crs import (
    WGS84,
    crs_to_text,
    heights_of,
    horizontal_of,
    transformer,
    utm_crs_for,
)
from geoortho.errors import InputError
from geoortho.feedback import Feedback
from geoortho.gcp.io import GcpSet, read_gcp_file
from geoortho.photos.footprint import photo_cameras, working_crs
from geoortho.photos.heights import absolute_altitude, check_altitudes
from geoortho.photos.metadata import Photo, list_images, read_photos
from geoortho.photos.positions import PositionFile, apply_positions, read_positions

Matching = Literal["auto", "exhaustive", "spatial", "sequential"]
Mapper = Literal["incremental", "global"]
CameraModel = Literal["RADIAL", "SIMPLE_RADIAL", "OPENCV", "SIMPLE_PINHOLE", "PINHOLE"]
MATCHING: tuple[str, ...] = get_args(Matching)
MAPPERS: tuple[str, ...] = get_args(Mapper)
CAMERA_MODELS: tuple[str, ...] = get_args(CameraModel)
# Up to this many photos every pair is matched; above, pairs come from the GPS positions.
EXHAUSTIVE_MAX_PHOTOS = 40


@dataclass(frozen=True)
class Body:
    """Photos sharing one camera: same make, model, decoded size and focal length."""

    key: tuple[str, str, int, int, float]
    photos: tuple[Photo, ...]
    calibration: str = ""  # the factory calibration, named when bodies of one model differ by it

    @property
    def label(self) -> str:
        make, model, w, h, f = self.key
        return (
            f"{make} {model} {w}x{h}"
            + (f" f={f:g} mm" if math.isfinite(f) else "")
            + (f" ({self.calibration})" if self.calibration else "")
        )


def _factory_key(p: Photo) -> tuple[float, float, float]:
    if not math.isfinite(p.factory_focal_px):
        return (math.nan, math.nan, math.nan)
    return (round(p.factory_focal_px, 1), round(p.factory_cx_px, 1), round(p.factory_cy_px, 1))


def camera_bodies(photos: Sequence[Photo]) -> list[Body]:
    """The photos grouped by camera; two drones of one model carry two factory calibrations, and
    each is its own body (the first photo's calibration was taken for both)."""
    groups: dict[tuple[str, str, int, int, float], list[Photo]] = {}
    for p in photos:
        f = round(p.focal_mm, 2) if math.isfinite(p.focal_mm) else math.nan
        groups.setdefault((p.make, p.model, p.width_px, p.height_px, f), []).append(p)
    out = []
    for k, v in groups.items():
        by_cal: dict[str, list[Photo]] = {}
        for p in v:
            by_cal.setdefault(repr(_factory_key(p)), []).append(p)
        if len(by_cal) == 1:
            out.append(Body(k, tuple(v)))
            continue
        for ps in by_cal.values():
            fk = _factory_key(ps[0])
            said = f"factory calibration f={fk[0]:g} px" if math.isfinite(fk[0]) else "no factory calibration"
            out.append(Body(k, tuple(ps), said))
    return out


def colmap_camera_params(body: Body, model: str) -> str:
    """Initial intrinsics for COLMAP: the maker's factory calibration where the photos carry one
    (focal length, optical centre, distortion), else the focal length from EXIF, the principal
    point at the centre and no distortion."""
    p = body.photos[0]
    factory = math.isfinite(p.factory_focal_px)
    f = p.factory_focal_px if factory else p.focal_px
    if not math.isfinite(f):
        return ""  # COLMAP then guesses 1.2 × the larger side and refines it
    # COLMAP: pixel (0, 0) is the top-left corner, as DJI's optical centre
    cx, cy = (p.factory_cx_px, p.factory_cy_px) if factory else (p.width_px / 2.0, p.height_px / 2.0)
    k1, k2, p1, p2, _k3 = (*p.factory_distortion, 0.0, 0.0, 0.0, 0.0, 0.0)[:5] if factory else (0.0,) * 5
    base = {
        "SIMPLE_PINHOLE": [f, cx, cy],
        "PINHOLE": [f, f, cx, cy],
        "SIMPLE_RADIAL": [f, cx, cy, k1],
        "RADIAL": [f, cx, cy, k1, k2],
        "OPENCV": [f, f, cx, cy, k1, k2, p1, p2],
    }[model]
    return ",".join(f"{v:.6f}" for v in base)


@dataclass(frozen=True)
class Priors:
    """GPS camera positions in the local frame (CRS minus ``offset``), by image name."""

    crs: CRS | None
    offset: np.ndarray  # (3,) added back to local coordinates
    positions: dict[str, np.ndarray]
    heights: str
    vertical_trusted: bool = True
    notes: tuple[str, ...] = ()
    # the 1-sigma horizontal and vertical accuracy (m) each photo states (RTK/PPK); the photos
    # not here are weighed at the survey's gps_sigma_m
    sigmas: dict[str, tuple[float, float]] = field(default_factory=dict)
    fixes: dict[str, str] = field(default_factory=dict)  # photo -> Photo.gps_fix

    def sigma_h_typical(self, default_m: float) -> float:
        """The median horizontal sigma of the positions (``default_m`` with none stated)."""
        values = [h for h, _ in self.sigmas.values() if math.isfinite(h)]
        return float(np.median(values)) if values else default_m


def gps_priors(photos: Sequence[Photo], names: dict[Path, str], crs: CRS, takeoff_elevation_m: float | None) -> Priors:
    """Camera positions from the metadata, heights per :mod:`geoortho.photos.heights`.

    SfM needs no height above ground, only camera elevations in one datum: a flight without
    RelativeAltitude keeps its GPS altitude as recorded (EXIF: orthometric) when no reading of it
    as a height above ground holds, and its trend over time decides whether it is trusted."""
    with_gps = [p for p in photos if p.has_gps and p.has_altitude]
    if not with_gps:
        return Priors(crs, np.zeros(3), {}, "no GPS")
    notes: list[str] = []
    try:
        cams, heights = photo_cameras(with_gps, crs, takeoff_elevation_m=takeoff_elevation_m, gnss_takeoff=True)
        centres = np.array([c.pose.center for c in cams])
        trusted = heights.vertical_gps_trusted or heights.method.startswith("relative")
        label = heights.method
        notes += [n for n in heights.notes if "not trusted" in n or "drift" in n]
    except InputError as e:
        # No height above ground to be had: keep the recorded GNSS altitude (its own datum).
        xy = np.array(
            transformer(WGS84, crs).transform([p.longitude_deg for p in with_gps], [p.latitude_deg for p in with_gps])
        ).T
        z = np.array([absolute_altitude(p) for p in with_gps])
        centres = np.c_[xy, z]
        check = check_altitudes(with_gps, z, "GPS altitude")
        trusted = check is None or check.trusted
        label = "GPS altitude as recorded (EXIF says orthometric; not converted)"
        if not trusted:
            notes.append(f"GPS altitude not trusted ({check.describe()})")  # type: ignore[union-attr]
        elif "sea-level" not in str(e):
            notes.append(f"heights: {e}")
    centres, n_rtk_heights = _rtk_heights(with_gps, centres, notes)
    trusted = trusted or n_rtk_heights >= 3
    offset = np.array([*np.round(np.median(centres[:, :2], axis=0), -2), 0.0])
    positions = {names[p.path]: c - offset for p, c in zip(with_gps, centres)}
    sigmas = {names[p.path]: (p.gps_sigma_h_m, p.gps_sigma_v_m) for p in with_gps if math.isfinite(p.gps_sigma_h_m)}
    fixes = {names[p.path]: p.gps_fix for p in with_gps}
    return Priors(crs, offset, positions, label, trusted, tuple(notes), sigmas, fixes)


#: A photo whose stated vertical accuracy is this good (m) is placed at its GNSS altitude.
RTK_HEIGHT_SIGMA_M = 0.5


def _rtk_heights(photos: Sequence[Photo], centres: np.ndarray, notes: list[str]) -> tuple[np.ndarray, int]:
    """The camera heights of photos with an RTK/PPK-grade vertical accuracy from their own GNSS
    altitude, not from the barometric RelativeAltitude plus take-off (0.1-0.5 m of noise where the
    receiver gives centimetres). Kept in the datum of the other heights: a user's take-off
    elevation in another datum moves them all by the median difference."""
    z = np.array([absolute_altitude(p) for p in photos])
    sigma_v = np.array([p.gps_sigma_v_m for p in photos])
    with np.errstate(invalid="ignore"):
        rtk = np.isfinite(z) & (sigma_v <= RTK_HEIGHT_SIGMA_M)
    if rtk.sum() < 3:
        return centres, 0
    shift = float(np.median(z[rtk] - centres[rtk, 2]))
    datum = 0.0 if abs(shift) < 1.0 else shift  # the same datum (metres of noise) or another
    out = centres.copy()
    out[rtk, 2] = z[rtk] - datum
    notes.append(
        f"heights of {int(rtk.sum())} photos from their GNSS altitude (stated vertical accuracy "
        f"{RTK_HEIGHT_SIGMA_M:g} m or better)"
        + (f", moved {-datum:+.2f} m onto the other heights' datum" if datum else "")
    )
    return out, int(rtk.sum())


def _image_names(photos: Sequence[Photo]) -> tuple[Path, dict[Path, str]]:
    """The photos' common folder and each photo's COLMAP image name (its path relative to that).
    A photo that is a link keeps its own name (its folder resolved, not the link): a folder of links
    picks photos for a run, and the link's target may lie anywhere."""
    root = Path(os.path.commonpath([str(p.path.parent.resolve()) for p in photos]))
    return root, {p.path: str((p.path.parent.resolve() / p.path.name).relative_to(root)) for p in photos}


@dataclass
class Timer:
    stages: dict[str, float] = field(default_factory=dict)

    def add(self, stage: str, t0: float) -> None:
        self.stages[stage] = self.stages.get(stage, 0.0) + time.perf_counter() - t0


def check_choice(what: str, value: str, choices: tuple[str, ...]) -> None:
    if value not in choices:
        raise InputError(f"{what} {value!r} is not one of {', '.join(choices)}")


@dataclass(frozen=True)
class Inputs:
    """What sfm works from: the photos, the GCPs and the GPS priors, checked."""

    photos: tuple[Photo, ...]
    skipped: tuple[tuple[str, str], ...]
    root: Path  # the folder image names are relative to
    names: dict[Path, str]  # photo path -> COLMAP image name
    gcps: GcpSet | None
    held_out: frozenset[str]  # checkpoint names
    out_crs: CRS | None
    priors: Priors
    bodies: tuple[Body, ...]
    notes: tuple[str, ...]
    positions: PositionFile | None = None  # a positions file's, applied to the photos
    photos_as_read: tuple[Photo, ...] = ()  # before the positions file (a time lag reads it again)
    takeoff_elevation_m: float | None = None
    heights_given: Any = None  # the heights' datum --crs states (its vertical part), or None

    @property
    def crs_text(self) -> str:
        return crs_to_text(self.out_crs) if self.out_crs is not None else ""


def _read_gcps(gcp_list: Path | None, checkpoints: str, photos: list[Photo], notes: list[str]) -> tuple[Any, set[str]]:
    """The GCP file (None without one) and the GCPs held out as checkpoints."""
    gcps = read_gcp_file(gcp_list) if gcp_list else None
    if gcps is not None and not gcps.observations:
        raise InputError(
            "the GCP file has no image observations: SfM needs a gcp_list.txt "
            "(x y z px py image name rows), e.g. from gcp-find",
            path=gcp_list,
        )
    held_out = _checkpoint_names(checkpoints, gcps, photos, notes)
    if gcps is not None and held_out - set(gcps.by_name()):
        raise InputError(
            f"checkpoint(s) not in the GCP file: {', '.join(sorted(held_out - set(gcps.by_name())))}", path=gcp_list
        )
    return gcps, held_out


def _priors_for(
    photos: list[Photo],
    names: dict[Path, str],
    out_crs: CRS | None,
    takeoff_elevation_m: float | None,
    gcps: GcpSet | None,
) -> tuple[Priors, list[str]]:
    """The photos' GPS as pose priors in the output CRS (its local frame's origin: the GCPs'
    median where no photo has GPS), and what their heights are, in words."""
    priors = (
        gps_priors(photos, names, out_crs, takeoff_elevation_m)
        if out_crs is not None
        else Priors(None, np.zeros(3), {}, "no GPS")
    )
    notes = [f"heights: {priors.heights}", *priors.notes]
    if gcps is not None and priors.positions and out_crs is not None:
        _check_gcps_near_photos(gcps, priors, out_crs)
    if gcps is not None and not priors.positions and out_crs is not None:
        to_local = transformer(gcps.crs, out_crs)
        xy = np.array([to_local.transform(g.x, g.y) for g in gcps.points])
        priors = Priors(out_crs, np.array([*np.round(np.median(xy, axis=0), -2), 0.0]), {}, "no GPS")
    return priors, notes


def read_inputs(
    images: Path,
    gcp_list: Path | None,
    checkpoints: str,
    crs: CRS | None,
    takeoff_elevation_m: float | None,
    local_frame: bool,
    timer: Timer,
    fb: Feedback,
    *,
    positions: Path | None = None,
    positions_time_offset_s: float | None = None,
) -> Inputs:
    t0 = time.perf_counter()
    paths = list_images(images) if isinstance(images, (str, os.PathLike)) else [Path(p) for p in images]
    # No feedback: SfM does not use the attitude, so its per-photo warnings would be noise here.
    photoset = read_photos(paths, require_gps=False, require_camera=False)
    photos = photoset.photos
    as_read = tuple(photos)
    contradicted = [p.image for p in photos if any(w.startswith("RtkFlag") for w in p.warnings)]
    position_file = None
    if positions is not None:
        position_file = read_positions(positions, photos, time_offset_s=positions_time_offset_s)
        photos = apply_positions(photos, position_file)
    for name, reason in photoset.skipped:
        fb.warning(f"skipped {name}: {reason}")
    timer.add("metadata", t0)
    if len(photos) < 3:
        raise InputError(f"SfM needs at least 3 readable photos, found {len(photos)}", path=images)
    root, names = _image_names(photos)
    early: list[str] = []
    if contradicted:
        early.append(
            f"{len(contradicted)} photo(s) state a fixed RTK solution with deviations of metres (weighed by the "
            "deviations): " + ", ".join(contradicted[:8]) + ("…" if len(contradicted) > 8 else "")
        )
    gcps, held_out = _read_gcps(gcp_list, checkpoints, photos, early)
    has_gps = sum(p.has_gps for p in photos)
    if has_gps < 3 and gcps is None and not local_frame:
        raise InputError(
            "fewer than 3 photos with GPS and no GCPs: the model would be arbitrary in scale, "
            "position and orientation; give a gcp_list.txt, or local_frame to accept that",
            path=images,
        )
    out_crs = _output_crs(crs, photos, gcps)
    priors, notes = _priors_for(photos, names, out_crs, takeoff_elevation_m, gcps)
    bodies = camera_bodies(photos)
    notes += _factory_calibration_notes(bodies)
    fb.info(
        f"{len(photos)} photos, {len(bodies)} camera bod{'y' if len(bodies) == 1 else 'ies'}: "
        + "; ".join(f"{b.label} ({len(b.photos)})" for b in bodies)
    )
    if len({(b.key[2], b.key[3]) for b in bodies}) > 1:
        notes.append("photos of several image sizes: each size is its own camera")
    return Inputs(
        tuple(photos),
        tuple(photoset.skipped),
        root,
        names,
        gcps,
        frozenset(held_out),
        out_crs,
        priors,
        tuple(bodies),
        tuple([*(position_file.notes() if position_file is not None else []), *early, *notes]),
        position_file,
        as_read,
        takeoff_elevation_m,
        heights_of(crs) if crs is not None else None,
    )


#: The factory calibration's focal length and EXIF's may differ by this (%) before it is said.
FACTORY_VS_EXIF_PCT = 3.0


def _factory_calibration_notes(bodies: Sequence[Body]) -> list[str]:
    """What each camera body starts from when its photos carry the maker's factory calibration."""
    out = []
    for b in bodies:
        p = b.photos[0]
        if not math.isfinite(p.factory_focal_px):
            continue
        line = (
            f"{b.label}: factory calibration as the starting intrinsics (focal length {p.factory_focal_px:.1f} px, "
            f"optical centre {p.factory_cx_px:.1f}, {p.factory_cy_px:.1f} px"
            + (", JPEG already undistorted" if p.dewarped else f", distortion {len(p.factory_distortion)} terms")
            + ")"
        )
        exif = p.exif_focal_px
        if math.isfinite(exif) and abs(p.factory_focal_px / exif - 1.0) * 100.0 > FACTORY_VS_EXIF_PCT:
            line += f"; EXIF's focal length gives {exif:.1f} px ({100.0 * (exif / p.factory_focal_px - 1.0):+.1f} %)"
        out.append(line)
    return out


#: Most photos stating a horizontal accuracy this good (m) make an RTK/PPK block: its GCPs check it.
RTK_BLOCK_SIGMA_M = 0.1


def _checkpoint_names(checkpoints: str, gcps: GcpSet | None, photos: Sequence[Photo], notes: list[str]) -> set[str]:
    """The GCPs held out as checkpoints: those named, ``all``, or ``none``; by default none, except
    in an RTK/PPK block (most photos to a decimetre or better), where every GCP checks the
    block the positions georeference."""
    text = checkpoints.strip()
    if text.lower() == "none":
        return set()
    if text.lower() == "all" or (not text and gcps is not None and _rtk_block(photos)):
        if gcps is None:
            raise InputError("checkpoints 'all' but no gcp_list is given")
        if not text:
            notes.append(
                "an RTK/PPK block: its GCPs are checkpoints, checking the georeference the photos' positions "
                "give (checkpoints 'none' to control the block with them)"
            )
        return set(gcps.by_name())
    held_out = {c.strip() for c in text.split(",") if c.strip()}
    if held_out and gcps is None:
        raise InputError("checkpoints are named but no gcp_list is given")
    return held_out


def _rtk_block(photos: Sequence[Photo]) -> bool:
    good = sum(math.isfinite(p.gps_sigma_h_m) and p.gps_sigma_h_m <= RTK_BLOCK_SIGMA_M for p in photos)
    return good >= 0.5 * max(len(photos), 1)


#: GCPs farther than this from every photo's GPS (and than the flight's size) are not of this flight.
GCP_FAR_M = 1000.0


def _check_gcps_near_photos(gcps: GcpSet, priors: Priors, crs: CRS) -> None:
    """Refuse GCPs that lie kilometres from the photos' GPS positions: the model would follow
    them there (a wrong CRS line, a wrong UTM zone, another site's file), silently."""
    pos = np.array(list(priors.positions.values()))[:, :2] + priors.offset[:2]
    t = transformer(gcps.crs, crs)
    gxy = np.array(t.transform([g.x for g in gcps.points], [g.y for g in gcps.points])).T
    if not np.isfinite(gxy).all():
        raise InputError(f"the GCPs cannot be placed in {crs_to_text(crs)}: is the file's CRS right?", path=gcps.path)
    nearest = np.min(np.linalg.norm(gxy[:, None, :] - pos[None, :, :], axis=2), axis=1)
    size = float(np.linalg.norm(pos.max(axis=0) - pos.min(axis=0)))
    if nearest.min() > max(GCP_FAR_M, size):
        raise InputError(
            f"the nearest GCP is {nearest.min() / 1000:,.1f} km from the photos' GPS positions (the flight is "
            f"{size:,.0f} m across): is the GCP file's CRS right ({crs_to_text(gcps.crs)})? is it this site's file?",
            path=gcps.path,
        )


def _output_crs(crs: CRS | None, photos: Sequence[Photo], gcps: GcpSet | None) -> CRS | None:
    """The model's map grid: horizontal (a compound CRS's vertical part is the heights' datum,
    :func:`_heights_datum`). A given CRS is a map grid: the faces that parse it say so."""
    if crs is not None:
        return horizontal_of(crs)
    if gcps is not None and gcps.crs.is_projected:
        return horizontal_of(gcps.crs)
    if any(p.has_gps for p in photos):
        return working_crs([p for p in photos if p.has_gps])
    if gcps is not None:
        g = gcps.points[0]
        lon, lat = transformer(gcps.crs, WGS84).transform(g.x, g.y)

        return utm_crs_for(lon, lat)
    return None
