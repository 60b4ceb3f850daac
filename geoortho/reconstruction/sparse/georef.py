"""Georeferencing the model: onto the GPS (levelled by the photos' gravity when recorded), or onto
the GCPs (triangulated, a similarity, then a bundle adjustment with the GCPs fixed), with what
could have gone wrong said."""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
from pyproj import CRS

from geoortho.core.camera import rotation_from_ypr
from geoortho.core.colmap import load_pycolmap
from geoortho.core.crs import (
    ELLIPSOIDAL,
    WGS84,
    crs_to_text,
    geoid_undulation_m,
    heights_label,
    heights_of,
    transformer,
)
from geoortho.feedback import Feedback
from geoortho.gcp.io import GcpSet, heights_are_placeholders
from geoortho.photos.metadata import Photo
from geoortho.reconstruction.sparse.adjust import Mapped, align_to_gps, ba_options, camera_centres
from geoortho.reconstruction.sparse.inputs import Inputs, Priors, Timer
from geoortho.reconstruction.sparse.timelag import refine_time_lag

# A georeferenced model whose vertical is this far from the photos' gravity was bent by bad GPS heights.
MAX_TILT_DEG = 3.0


def _levelling_rotation(rec: Any, photos_by_name: dict[str, Photo]) -> np.ndarray | None:
    """Model → world rotation that makes the cameras look where their recorded attitude says
    (chordal mean over the photos). Gimbals hold pitch and roll to a degree or two, so this
    levels the model from gravity; its heading is only as good as the compass."""
    m = np.zeros((3, 3))
    k = 0
    for iid in rec.reg_image_ids():
        im = rec.image(iid)
        p = photos_by_name.get(im.name)
        if p is None:
            continue
        m += rotation_from_ypr(p.yaw_deg, p.pitch_deg, p.roll_deg) @ im.cam_from_world().rotation.matrix()
        k += 1
    if k < 3:
        return None
    u, _, vt = np.linalg.svd(m)
    r: np.ndarray = u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt
    return r


#: Camera centres farther than this from the flight's plane (take-off, landing, a line flown at
#: another height) do not level the model.
PLANE_OUTLIER_M = 3.0


def _camera_plane_levelling(centres: np.ndarray) -> tuple[np.ndarray, float, int] | None:
    """The rotation that makes the plane through the camera centres level (a drone on a height
    hold flies level lines), its tilt in degrees, and the centres it was fitted to; None for too
    few centres or ones that span no plane (a single line). Centres off the plane by more than
    PLANE_OUTLIER_M of the flight's scale (take-off, landing) are dropped, then it is fitted again."""
    if len(centres) < 6:
        return None
    keep = np.ones(len(centres), bool)
    normal = np.array([0.0, 0.0, 1.0])
    scale = 1.0
    for _ in range(4):
        pts = centres[keep]
        mid = pts.mean(axis=0)
        _, sv, vt = np.linalg.svd(pts - mid)
        if sv[1] < 0.05 * sv[0]:  # one line: no plane to level by
            return None
        normal = vt[2] if vt[2, 2] >= 0 else -vt[2]
        # the model's scale is unknown here: the spread of the centres along the flight sets it
        scale = float(sv[0]) / math.sqrt(len(pts))
        dist = np.abs((centres - mid) @ normal)
        spread = max(1.4826 * float(np.median(dist[keep])), 1e-3 * scale)
        new = dist <= max(4.0 * spread, 0.02 * scale)
        if new.sum() < 6 or (new == keep).all():
            keep = new if new.sum() >= 6 else keep
            break
        keep = new
    up = np.array([0.0, 0.0, 1.0])
    axis = np.cross(normal, up)
    sin_t, cos_t = float(np.linalg.norm(axis)), float(normal @ up)
    tilt = math.degrees(math.atan2(sin_t, cos_t))
    if sin_t < 1e-12:
        return np.eye(3), 0.0, int(keep.sum())
    k = axis / sin_t
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    rot = np.eye(3) + sin_t * kx + (1 - cos_t) * (kx @ kx)
    return rot, tilt, int(keep.sum())


def plane_tilt(rec: Any) -> float | None:
    """Tilt of the plane through the georeferenced model's camera centres, degrees (None: no plane)."""
    plane = _camera_plane_levelling(np.array(list(camera_centres(rec).values())).reshape(-1, 3))
    return None if plane is None else round(plane[1], 3)


def _attitude_recorded(photos: Sequence[Photo]) -> bool:
    """Most photos carry a pitch and roll of their own (not the nadir assumed for none)."""
    assumed = sum(p.attitude_source.startswith("assumed") for p in photos)
    return assumed < 0.5 * max(len(photos), 1)


def _tilt_deg(rec: Any, photos_by_name: dict[str, Photo]) -> float:
    """How far the (georeferenced) model's vertical is from gravity as the photos' attitude gives it."""
    r = _levelling_rotation(rec, photos_by_name)
    return math.nan if r is None else math.degrees(math.acos(float(np.clip(r[2, 2], -1.0, 1.0))))


def _align_horizontal(
    rec: Any, priors: Priors, photos_by_name: dict[str, Photo], sigma_h_m: float, notes: list[str]
) -> tuple[Any, str]:
    """Georeference with untrusted GPS heights: level the model from the photos' attitude (with no
    pitch and roll recorded: on the plane of the camera centres), then a robust 2-D similarity onto
    the GPS positions (scale, heading, east/north); the vertical offset is the median GPS height's
    (GCPs, when given, correct it next). Returns the similarity and how the model was levelled."""
    from skimage.measure import ransac
    from skimage.transform import SimilarityTransform

    pc = load_pycolmap()
    level = _levelling_rotation(rec, photos_by_name)
    centres = camera_centres(rec)
    names = [n for n in centres if n in priors.positions]
    if level is None or len(names) < 3:
        return None, ""
    how = "from the photos' attitude"
    if not _attitude_recorded(list(photos_by_name.values())):
        # No pitch or roll in the metadata: the nadir assumed levels the model only as well as the
        # camera hung plumb (a fixed mount tilted 3.5 deg tilted a real model 3.5 deg). A drone on
        # a height hold flies level lines: the plane of the camera centres is levelled instead.
        plane = _camera_plane_levelling(np.array([level @ centres[n] for n in centres]))
        if plane is not None:
            rot, tilt, used = plane
            level = rot @ level
            how = "on the plane of the camera centres"
            notes.append(
                f"no pitch or roll in the photos and no trusted GPS heights: the model is levelled on the plane "
                f"of {used} camera centres (a flight at one height); the nadir assumed was {tilt:.1f} deg off it"
            )
    src = np.array([level @ centres[n] for n in names])
    tgt = np.array([priors.positions[n] for n in names])
    model, inliers = ransac(
        (src[:, :2], tgt[:, :2]),
        SimilarityTransform,
        min_samples=2,
        residual_threshold=3.0 * sigma_h_m,
        max_trials=500,
        rng=0,
    )
    if model is None or inliers is None or inliers.sum() < 3:
        return None, ""
    scale = float(model.scale)
    c, s_ = math.cos(model.rotation), math.sin(model.rotation)
    rot = np.array([[c, -s_, 0.0], [s_, c, 0.0], [0.0, 0.0, 1.0]]) @ level
    tz = float(np.median(tgt[inliers, 2] - scale * src[inliers, 2]))
    sim = pc.Sim3d(scale, pc.Rotation3d(rot), np.array([*model.translation, tz]))
    rec.transform(sim)
    return sim, how


def _gps_outliers(rec: Any, priors: Priors) -> list[str]:
    """Photos whose GPS position is far off the model's (robust: 4 sigma and 3 m horizontally)."""
    c = camera_centres(rec)
    names = [n for n in c if n in priors.positions]
    if len(names) < 5:
        return []
    d = np.array([np.hypot(*(c[n] - priors.positions[n])[:2]) for n in names])
    sigma = 1.4826 * float(np.median(np.abs(d - np.median(d))))
    limit = max(3.0, float(np.median(d)) + 4.0 * sigma)
    return [n for n, v in zip(names, d) if v > limit]


@dataclass
class GcpState:
    name: str
    surveyed: np.ndarray  # local frame
    observations: list[tuple[str, float, float]]  # (image, x, y) COLMAP pixels (corner origin)
    role: str  # "control" | "checkpoint"
    triangulated: np.ndarray | None = None
    inliers: int = 0
    reprojection_px: float = math.nan


def _gcp_states(
    gcps: GcpSet, crs: CRS, offset: np.ndarray, checkpoints: set[str], registered: set[str], fb: Feedback
) -> list[GcpState]:
    to_local = transformer(gcps.crs, crs)
    by_name = gcps.by_name()
    obs: dict[str, list[tuple[str, float, float]]] = {}
    known = {Path(n).name: n for n in registered}
    unmatched = set()
    for o in gcps.observations:
        image = o.image if o.image in registered else known.get(Path(o.image).name)
        if image is None:
            unmatched.add(o.image)
            continue
        # gcp_list.txt: (0, 0) is the centre of the top-left pixel; COLMAP: its top-left corner.
        obs.setdefault(o.gcp, []).append((image, o.x_px + 0.5, o.y_px + 0.5))
    if unmatched:
        fb.warning(
            f"GCP observations in {len(unmatched)} photo(s) not in the model ignored: "
            + ", ".join(sorted(unmatched)[:5])
            + (" ..." if len(unmatched) > 5 else "")
        )
    states = []
    for name, g in by_name.items():
        x, y = to_local.transform(g.x, g.y)
        local = np.array([x, y, g.z]) - offset
        states.append(GcpState(name, local, obs.get(name, []), "checkpoint" if name in checkpoints else "control"))
    return states


def _triangulate(rec: Any, states: list[GcpState], max_error_px: float = 4.0) -> None:
    """Each GCP from its observations in registered photos (robust; needs two or more)."""
    pc = load_pycolmap()
    by_name = {rec.image(i).name: rec.image(i) for i in rec.reg_image_ids()}
    for s in states:
        s.triangulated, s.inliers, s.reprojection_px = None, 0, math.nan
        ims = [(by_name[n], x, y) for n, x, y in s.observations if n in by_name]
        if len(ims) < 2:
            continue
        opts = pc.EstimateTriangulationOptions()
        opts.residual_type = pc.TriangulationResidualType.REPROJECTION_ERROR
        opts.ransac.max_error = max_error_px
        opts.ransac.random_seed = 0
        out = pc.estimate_triangulation(
            np.array([[x, y] for _, x, y in ims]),
            [im.cam_from_world() for im, _, _ in ims],
            [im.camera for im, _, _ in ims],
            opts,
        )
        if out is None:
            continue
        s.triangulated = np.asarray(out["xyz"], float).reshape(3)
        s.inliers = int(np.sum(out["inliers"]))
        s.reprojection_px = _reprojection_px(ims, s.surveyed)


def _reprojection_px(ims: list[tuple[Any, float, float]], xyz: np.ndarray) -> float:
    """Mean distance (px) between the observations and the surveyed point projected into the photos."""
    errs = []
    for im, x, y in ims:
        p = im.project_point(xyz)
        if p is not None:
            errs.append(math.hypot(p[0] - x, p[1] - y))
    return float(np.mean(errs)) if errs else math.nan


def _align_to_gcps(rec: Any, states: list[GcpState], heights_usable: bool) -> Any:
    """Similarity from the triangulated control GCPs onto their surveyed positions."""
    pc = load_pycolmap()
    use = [s for s in states if s.role == "control" and s.triangulated is not None]
    if len(use) < 3:
        return None
    src = np.array([s.triangulated for s in use])
    tgt = np.array([s.surveyed for s in use])
    if not heights_usable:
        tgt[:, 2] = src[:, 2]  # placeholder heights: control horizontally, keep the GPS heights
    sim = pc.estimate_sim3d(src, tgt)
    if sim is not None:
        rec.transform(sim)
    return sim


def _gcp_bundle_adjust(rec: Any, states: list[GcpState], refine_distortion: bool = True) -> int:
    """Bundle adjustment with the control GCPs as fixed 3D points observed in the photos.

    A COLMAP image cannot take new 2D points once it has some, so each GCP
    observation borrows a keypoint slot that no 3D point uses (its coordinates
    are restored afterwards). The fixed points hold the datum: no gauge is left
    free. Returns the number of GCP observations used.
    """
    pc = load_pycolmap()
    by_name = {rec.image(i).name: i for i in rec.reg_image_ids()}
    borrowed: list[tuple[int, int, np.ndarray]] = []
    gcp_points = []
    free_slots: dict[int, list[int]] = {}
    for s in states:
        if s.role != "control" or s.triangulated is None:
            continue
        track = pc.Track()
        for name, x, y in s.observations:
            iid = by_name.get(name)
            if iid is None:
                continue
            im = rec.image(iid)
            if iid not in free_slots:
                free_slots[iid] = [k for k, p in enumerate(im.points2D) if not p.has_point3D()]
            if not free_slots[iid]:
                continue
            k = free_slots[iid].pop()
            borrowed.append((iid, k, np.array(im.point2D(k).xy)))
            im.points2D[k].xy = np.array([x, y])
            track.add_element(iid, k)
        if track.length() >= 2:
            gcp_points.append(rec.add_point3D(s.surveyed, track, np.zeros(3, np.uint8)))
    n_obs = sum(rec.point3D(p).track.length() for p in gcp_points)
    if len(gcp_points) >= 3:
        cfg = pc.BundleAdjustmentConfig()
        for iid in rec.reg_image_ids():
            cfg.add_image(iid)
        for pid in gcp_points:
            cfg.add_constant_point(pid)
        opts = ba_options(refine_distortion=refine_distortion, robust=True)
        pc.create_default_bundle_adjuster(opts, cfg, rec).solve()
    for pid in gcp_points:
        rec.delete_point3D(pid)
    for iid, k, xy in borrowed:
        rec.image(iid).points2D[k].xy = xy
    return n_obs if len(gcp_points) >= 3 else 0


def georeference(
    mapped: Mapped, inputs: Inputs, gps_sigma_m: float, notes: list[str], timer: Timer, fb: Feedback
) -> tuple[Inputs, Any, Any]:
    """The block's time lag found (and the positions read again at it), then the block put in
    the CRS by the GPS and by the GCPs; the inputs as read again, the lag and the georeference."""
    t0 = time.perf_counter()
    inputs, lag = refine_time_lag(mapped, inputs, notes)
    geo = _georeference_by_gps(mapped.rec, inputs, gps_sigma_m)
    geo = _georeference_by_gcps(
        mapped.rec, inputs, mapped.registered, geo, fb, refine_distortion=not mapped.distortion_held
    )
    notes += geo.notes
    heights, heights_from = _heights_datum(inputs, geo)
    notes.append(
        f"heights' datum: {heights_label(heights)}" + (", from " if heights is not None else ": ") + heights_from
    )
    timer.add("georeferencing", t0)
    return inputs, lag, replace(geo, heights=heights, heights_from=heights_from)


@dataclass(frozen=True)
class Georeference:
    """How the model was put in the CRS, and the GCPs' state after it."""

    how: str
    gps_sim: Any  # the GPS similarity applied, or None
    tilt_deg: float  # the model's vertical against the photos' gravity (NaN: not measured)
    states: tuple[GcpState, ...] = ()
    heights_usable: bool = True  # GCP heights are surveyed, not placeholders
    gcp_obs_used: int = 0  # GCP observations held fixed in the bundle adjustment
    notes: tuple[str, ...] = ()
    gcp_vs_gps: dict[str, Any] | None = None  # what the GCPs changed of the GPS georeference
    heights: Any = None  # the datum of the model's heights (:func:`_heights_datum`), None: not known
    heights_from: str = ""  # where it was learnt, or what to give


def _georeference_by_gps(rec: Any, inputs: Inputs, gps_sigma_m: float) -> Georeference:
    """Similarity onto the GPS positions; levelled from the gimbals when GPS heights are not trusted."""
    priors = inputs.priors
    if not priors.positions:
        return Georeference("none (local frame)", None, math.nan)
    by_name = {inputs.names[p.path]: p for p in inputs.photos}
    notes: list[str] = []
    georef, gps_sim, tilt = "none (local frame)", None, math.nan
    if len(priors.sigmas) >= 0.5 * len(priors.positions):  # most photos state their accuracy (RTK/PPK)
        gps_sigma_m = priors.sigma_h_typical(gps_sigma_m)
    if priors.vertical_trusted:
        gps_sim, n_gps = align_to_gps(rec, priors, gps_sigma_m)
        tilt = _tilt_deg(rec, by_name) if gps_sim is not None else math.nan
        if gps_sim is not None:
            georef = f"GPS of {n_gps} photos"
        # The GPS heights may still be wrong in a way no trend shows: a model they tilt
        # away from the gravity the gimbals saw is put on the GPS horizontally instead.
        # (without a recorded pitch and roll the nadir assumed is no gravity to hold them against)
        if math.isfinite(tilt) and tilt > MAX_TILT_DEG and _attitude_recorded(list(by_name.values())):
            notes.append(
                f"the GPS heights tilt the model {tilt:.1f} deg from the photos' vertical: "
                "GPS heights not trusted, model levelled from the photos' attitude"
            )
            gps_sim = None
    if gps_sim is None and (not priors.vertical_trusted or math.isfinite(tilt)):
        gps_sim, levelled = _align_horizontal(rec, priors, by_name, gps_sigma_m, notes)
        if gps_sim is not None:
            georef = (
                f"GPS of {len(priors.positions)} photos horizontally, levelled {levelled}, "
                "height from the median GPS altitude"
            )
            tilt = _tilt_deg(rec, by_name)
    if gps_sim is None:
        notes.append("the GPS positions did not fit the model (fewer than 3 consistent photos)")
    outliers = _gps_outliers(rec, priors) if gps_sim is not None else []
    if outliers:
        notes.append(
            f"{len(outliers)} photo(s) with GPS positions far off the model: "
            + ", ".join(outliers[:5])
            + ("…" if len(outliers) > 5 else "")
        )
    return Georeference(georef, gps_sim, tilt, notes=tuple(notes))


def _georeference_by_gcps(
    rec: Any,
    inputs: Inputs,
    registered: frozenset[str],
    gps: Georeference,
    fb: Feedback,
    refine_distortion: bool = True,
) -> Georeference:
    """Triangulate the GCPs; with 3 control GCPs, align onto them and bundle-adjust with them fixed."""
    if inputs.gcps is None:
        return gps
    notes = list(gps.notes)
    georef, gcp_obs_used, heights_usable = gps.how, 0, True
    assert inputs.out_crs is not None  # a GCP file always gives the model its grid (_output_crs)
    states = _gcp_states(inputs.gcps, inputs.out_crs, inputs.priors.offset, set(inputs.held_out), set(registered), fb)
    zs = np.array([s.surveyed[2] for s in states])
    if heights_are_placeholders(zs):
        heights_usable = False
        notes.append(
            f"all GCP heights are {zs[0] + inputs.priors.offset[2]:g}: taken as placeholders; "
            "GCPs control the model horizontally only and their Z residuals are not reported"
        )
    _triangulate(rec, states)
    swapped = _swapped_pair(states, heights_usable)
    if swapped is not None:
        # Controlled by a mixed-up pair the model would bend (turned 180 deg on a 4-GCP block):
        # the pair checks instead, and the rest control if they are still 3.
        for st in states:
            if st.name in swapped["names"]:
                st.role = "checkpoint"
    gcp_sim = _align_to_gcps(rec, states, heights_usable)
    effect: dict[str, Any] | None = None
    if gcp_sim is not None and gps.gps_sim is not None:
        effect = _gcp_effect(rec, gcp_sim)
        if abs(effect["scale_change_pct"]) > GCP_SCALE_CHANGE_PCT or effect["rotation_deg"] > GCP_ROTATION_DEG:
            notes.append(
                f"the GCPs rescaled the GPS-georeferenced model by {effect['scale_change_pct']:+.1f} % and turned it "
                f"{effect['rotation_deg']:.2f} deg (moving the site's edge {effect['edge_shift_m']:.2f} m): check the "
                "GCPs' CRS and coordinates, or the photos' GPS"
            )
            fb.warning(notes[-1])
        cause = _shift_cause(effect, inputs, heights_usable and gps.how.startswith("GPS of"))
        if cause:
            effect["likely_cause"] = cause
            notes.append(cause)
            fb.warning(cause)
    if swapped is not None:
        effect = dict(effect or {})
        effect["swapped"] = swapped
        effect["likely_cause"] = (
            f"GCPs {swapped['names'][0]} and {swapped['names'][1]} look swapped: exchanged, their fit's RMSE "
            f"falls from {swapped['rmse_m']:.2f} m to {swapped['rmse_if_exchanged_m']:.2f} m; they are held out "
            "as checkpoints (check their names in the GCP file)"
        )
        notes.append(effect["likely_cause"])
        fb.warning(effect["likely_cause"])
    if gcp_sim is not None:
        georef = (
            f"{sum(s.role == 'control' and s.triangulated is not None for s in states)} GCPs"
            + (" (horizontally; heights from GPS)" if not heights_usable else "")
            + (f" after {georef}" if gps.gps_sim is not None else "")
        )
        if heights_usable:
            _triangulate(rec, states)
            gcp_obs_used = _gcp_bundle_adjust(rec, states, refine_distortion)
            if gcp_obs_used:
                georef += f"; bundle adjustment with {gcp_obs_used} GCP observations fixed"
    else:
        n_ok = sum(s.role == "control" and s.triangulated is not None for s in states)
        notes.append(f"only {n_ok} control GCP(s) triangulated (3 needed): GCPs not used for control")
    _triangulate(rec, states)
    return Georeference(
        georef, gps.gps_sim, gps.tilt_deg, tuple(states), heights_usable, gcp_obs_used, tuple(notes), effect
    )


#: GCPs that change the GPS georeference's scale or rotation more than this are said (issue 48).
GCP_SCALE_CHANGE_PCT = 1.0
GCP_ROTATION_DEG = 0.5
#: A GCP georeference this far (horizontally) from the GPS's is not the GPS's bias (a few metres on
#: consumer drones) but a wrong CRS or datum of the GCP file (issue 48).
GCP_SHIFT_WARN_M = 30.0


def _shift_cause(effect: dict[str, Any], inputs: Inputs, heights_compared: bool) -> str:
    """Name what a large shift between the GPS and the GCP georeference most likely is: the GCP
    file's CRS (horizontal), or heights in another vertical datum (the geoid's undulation here)."""
    h, v = float(effect["shift_horizontal_m"]), float(effect["shift_vertical_m"])
    if h > GCP_SHIFT_WARN_M:
        far = f"{h / 1000:.1f} km" if h >= 1000 else f"{h:.0f} m"
        return (
            f"the GCPs put the block {far} from where its photos' GPS puts it: the GCP file's CRS "
            f"({inputs.gcps.crs.name if inputs.gcps is not None else '?'}) is likely not the one its "
            "coordinates are in"
        )
    if not heights_compared or inputs.out_crs is None or abs(v) < 10.0:
        return ""

    lon, lat = transformer(inputs.out_crs, WGS84).transform(*inputs.priors.offset[:2])
    n = float(geoid_undulation_m(lon, lat))
    if abs(abs(v) - abs(n)) < 5.0 and abs(n) > 10.0:
        return (
            f"the GCPs move the block {v:+.1f} m vertically against the GPS heights, as the geoid's undulation "
            f"here ({n:+.1f} m): the GCP heights are likely in another vertical datum than the CRS says "
            "(orthometric against ellipsoidal)"
        )
    return ""


def _swapped_pair(states: list[GcpState], heights_usable: bool) -> dict[str, Any] | None:
    """Two control GCPs whose surveyed coordinates, exchanged, fit their triangulated positions far
    better: a swapped pair of names in the GCP file (a common field mistake)."""
    pc = load_pycolmap()
    use = [s for s in states if s.role == "control" and s.triangulated is not None]
    if len(use) < 4:  # with 3 a similarity bends to almost any labelling
        return None
    src = np.array([s.triangulated for s in use], dtype=float)
    tgt = np.array([s.surveyed for s in use], dtype=float)
    if not heights_usable:
        src, tgt = src[:, :2], tgt[:, :2]

    def rmse(t: np.ndarray) -> float:
        a, b = (src, t) if src.shape[1] == 3 else (np.c_[src, np.zeros(len(src))], np.c_[t, np.zeros(len(t))])
        sim = pc.estimate_sim3d(a, b)
        if sim is None:
            return math.inf
        m = np.asarray(sim.matrix())
        return float(np.sqrt(np.mean(np.sum((a @ m[:, :3].T + m[:, 3] - b) ** 2, axis=1))))

    base = rmse(tgt)
    if not math.isfinite(base) or base < 0.05:  # GCPs that fit to 5 cm are not mixed up
        return None
    best = (math.inf, -1, -1)
    for i in range(len(use)):
        for j in range(i + 1, len(use)):
            t = tgt.copy()
            t[[i, j]] = t[[j, i]]
            best = min(best, (rmse(t), i, j))
    if best[0] > 0.25 * base:
        return None
    return {
        "names": [use[best[1]].name, use[best[2]].name],
        "rmse_m": round(base, 4),
        "rmse_if_exchanged_m": round(best[0], 4),
    }


def _gcp_effect(rec: Any, sim: Any) -> dict[str, Any]:
    """What the GCPs' similarity did to the GPS-georeferenced model: its scale change, its rotation,
    and how far these two (not the shift, the GPS's own bias) moved the camera farthest from the
    block's middle (the site's edge)."""
    rot = np.asarray(sim.rotation.matrix())
    angle = math.degrees(math.acos(float(np.clip((np.trace(rot) - 1.0) / 2.0, -1.0, 1.0))))
    centres = np.array(list(camera_centres(rec).values())).reshape(-1, 3)  # already moved by ``sim``
    inv = sim.inverse()
    before = np.array([inv * c for c in centres]) if len(centres) else centres
    moved = (centres - centres.mean(axis=0)) - (before - before.mean(axis=0)) if len(centres) else centres
    shift = float(np.linalg.norm(moved, axis=1).max()) if len(centres) else math.nan
    middle = centres.mean(axis=0) - before.mean(axis=0) if len(centres) else np.full(3, math.nan)
    return {
        "scale_change_pct": round((float(sim.scale) - 1.0) * 100.0, 4),
        "rotation_deg": round(angle, 4),
        "edge_shift_m": round(shift, 4),
        # where the GCPs moved the block's middle from the GPS's place (a GPS bias of a few metres,
        # or a wrong CRS/datum of the GCP file)
        "shift_horizontal_m": round(float(np.hypot(middle[0], middle[1])), 3),
        "shift_vertical_m": round(float(middle[2]), 3),
    }


def _heights_datum(inputs: Inputs, geo: Georeference) -> tuple[Any, str]:
    """The datum of the model's heights (a vertical CRS, :data:`ELLIPSOIDAL`, or None: not
    known) and where it was learnt. The model takes its heights from the GCPs when they control
    them, else from the photos' positions."""
    if inputs.out_crs is None:
        return None, "a local frame"
    example = f"e.g. {crs_to_text(inputs.out_crs)}+5773 for EGM96 heights"  # this survey's own grid
    gcps = inputs.gcps
    if gcps is not None and geo.heights_usable and "GCP" in geo.how and any(s.role == "control" for s in geo.states):
        stated = heights_of(gcps.crs)
        if stated is not None:
            return stated, f"the GCP file's CRS ({gcps.crs.name})"
        if inputs.heights_given is not None:
            return inputs.heights_given, "--crs (the GCP heights taken to be in it)"
        return None, (
            f"the GCP file's CRS ({gcps.crs.name}) names no vertical datum: give the GCPs' CRS with "
            f"their heights' datum ({example}), or --crs so"
        )
    if inputs.heights_given is not None:
        return inputs.heights_given, "--crs (the positions' heights taken to be in it, as given)"
    if inputs.positions is not None and inputs.priors.vertical_trusted:
        return ELLIPSOIDAL, f"the positions file {inputs.positions.path.name} (heights above the WGS 84 ellipsoid)"
    return None, (
        "the photos' GNSS heights, whose datum the tags do not state: give GCPs in a compound CRS "
        f"({example}), or --crs with a vertical part"
    )
