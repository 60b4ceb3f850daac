"""The quality verdict of a run: each item measured, graded green, amber or red against one table.

Pix4D's quality check is the model: per item the measured value, the thresholds beside it, and a
state; the verdict is the worst item's (a stage that failed is red whatever was measured). The
thresholds are here and nowhere else, each with the reason for its value (the README lists them).
An item the run did not measure (no GCPs, no dense stage) is said so and does not count.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any, Literal

__all__ = ["THRESHOLDS", "Check", "Threshold", "as_number", "assess", "verdict"]

State = Literal["green", "amber", "red", "not measured"]
_ORDER = {"not measured": 0, "green": 1, "amber": 2, "red": 3}


@dataclass(frozen=True)
class Threshold:
    """Green up to ``green``, red past ``red``, amber between; ``higher_is_better`` turns it round."""

    label: str
    unit: str
    green: float
    red: float
    higher_is_better: bool
    reason: str

    def grade(self, value: float) -> State:
        if not math.isfinite(value):
            return "not measured"
        if self.higher_is_better:
            return "green" if value >= self.green else ("red" if value < self.red else "amber")
        return "green" if value <= self.green else ("red" if value > self.red else "amber")

    def limits(self) -> tuple[str, str]:
        sign_good, sign_bad = (">=", "<") if self.higher_is_better else ("<=", ">")
        return f"{sign_good} {_fmt(self.green, self.unit)}", f"{sign_bad} {_fmt(self.red, self.unit)}"


#: Every item's thresholds, and why.
THRESHOLDS: dict[str, Threshold] = {
    "ortho_coverage": Threshold(
        "Orthophoto coverage of the ground seen by >= 2 photos",
        "%",
        98.0,
        90.0,
        True,
        "OpenDroneMap, Pix4D and Metashape map all the stereo ground; under 90 % a user sees holes",
    ),
    "ortho_holes": Threshold(
        "Holes inside the orthophoto (transparent ground it surrounds)",
        "m²",
        0.0,
        10.0,
        False,
        "every metre a photo's frame holds is drawn (a true occlusion from the nearest view, marked in "
        "ortho_source.tif); a hole inside the map is what users of every anchor report first (a real park "
        "survey: 25 holes under trees, 88 m²)",
    ),
    "dsm_measured": Threshold(
        "DSM cells measured by the dense cloud",
        "%",
        30.0,
        10.0,
        True,
        "the rest is interpolated (water, canopy, the edge); ground seen by only two photos at a block's edge "
        "has one stereo pair and is interpolated, which on a 9-photo block is most of it (a clean one: 38 %); "
        "under 10 % the DSM is a guess",
    ),
    "dtm_roughness": Threshold(
        "DTM roughness on open ground (less its 1 m median, RMS)",
        "GSD",
        0.35,
        0.7,
        False,
        "bare ground is smooth at a metre (a synthetic survey's true ground: 0.01 GSD); a photogrammetric "
        "DTM's speckle shows in the hillshade from about a third of a GSD (the demo's DTM before issue 74: "
        "0.48 GSD, visibly dotted)",
    ),
    "dtm_no_ground": Threshold(
        "DTM under objects with no ground seen (its source code 4)",
        "%",
        5.0,
        25.0,
        False,
        "under a wood or a hall the DTM is bridged from its edge, as far as the ground's own relief says a "
        "fill stays within 0.1 m (2-10 m); beyond that it is a guess; a quarter of the survey guessed is not a "
        "terrain model",
    ),
    "footprint_step": Threshold(
        "DTM step at the photos' footprint edges (RMS over the edges)",
        "GSD",
        0.25,
        1.0,
        False,
        "a depth map off its neighbours leaves a patch with straight edges, one per photo (the demo's DTM before "
        "issue 74: 0.41 GSD, its edges a line of dots in the hillshade; after: 0.04 GSD); a GSD shows in contours",
    ),
    "photos_registered": Threshold(
        "Photos registered by the SfM",
        "%",
        98.0,
        90.0,
        True,
        "a mapping flight loses at most a photo or two (take-off, a turn); more is a gap in the block",
    ),
    "ground_left_out": Threshold(
        "Ground seen only by photos the SfM left out",
        "%",
        1.0,
        5.0,
        False,
        "a photo lost at a turn costs a sliver; a failed submodel or a lost strip leaves ground the photos saw "
        "out of every product, and the map must not end there silently (issue 78)",
    ),
    "photos_in_ortho": Threshold(
        "Registered photos used in the orthophoto",
        "%",
        95.0,
        80.0,
        True,
        "photos left out (oblique, off the surface) leave their ground to fewer views",
    ),
    "depth_maps": Threshold(
        "Registered photos with a depth map",
        "%",
        95.0,
        80.0,
        True,
        "every photo with stereo partners gives one; missing ones leave their ground interpolated",
    ),
    "gcp_rmse": Threshold(
        "GCP residuals (control, RMSE)",
        "GSD",
        2.0,
        3.0,
        False,
        "control points fit to about a pixel; over 3 GSD a coordinate, its CRS or its datum is wrong",
    ),
    "checkpoint_rmse": Threshold(
        "Checkpoint residuals (RMSE)",
        "GSD",
        2.0,
        4.0,
        False,
        "1-3 GSD is what a survey-grade block reaches (ASPRS 2014, Pix4D's guide); 4 GSD is not mapping grade",
    ),
    "gcp_scale": Threshold(
        "Scale change the GCPs imposed on the GPS georeference",
        "%",
        1.0,
        3.0,
        False,
        "GPS over a block fixes its scale to a few tenths of a percent; GCPs that change it more hold a wrong "
        "coordinate, CRS or datum (a real case: 3 GCPs rescaled a model by 6.7 %)",
    ),
    "gcp_rotation": Threshold(
        "Rotation the GCPs imposed on the GPS georeference",
        "deg",
        0.5,
        2.0,
        False,
        "the GPS fixes the block's heading and level to a fraction of a degree; more is a GCP mix-up",
    ),
    "gcp_shift": Threshold(
        "Shift the GCPs imposed on the GPS georeference (horizontal)",
        "m",
        10.0,
        30.0,
        False,
        "a consumer GPS is biased by a few metres over a block; GCPs that move it by tens to hundreds of metres "
        "are in another CRS or datum than their file says (ED50 read as WGS 84 moves Lisbon 237 m)",
    ),
    "gps_fit": Threshold(
        "GPS against the photos' geometry (CE90)",
        "m",
        5.0,
        15.0,
        False,
        "consumer GNSS fixes scatter 2-5 m; past 15 m the GPS georeference (no GCPs) is not to be trusted",
    ),
    "gps_fits_agree": Threshold(
        "GPS georeference: least squares against the robust fit, at the site's edge",
        "x CE90",
        0.5,
        2.0,
        False,
        "two fits of one GPS agree within its scatter; a least-squares fit that moves the edge by more than the "
        "GPS's CE90 is dragged by bad fixes, and the rotation is not determined (a real case: 22 deg)",
    ),
    "focal_drift": Threshold(
        "Focal length refined against the EXIF's",
        "%",
        2.0,
        5.0,
        False,
        "a lens differs from its label by 1-2 %; more means a wrong EXIF focal or a weak block",
    ),
    "dsm_vs_sfm": Threshold(
        "DSM against the SfM points (median offset)",
        "m",
        0.10,
        1.0,
        False,
        "a DSM of the same photos lies on their points; past 1 m it is in another datum or another place",
    ),
    "heights_given": Threshold(
        "Heights given or read against the measured (height above ground)",
        "%",
        10.0,
        10.0,
        False,
        "a wrong flight height or take-off scales every figure computed from it (issue 47's 87 m for 56 m)",
    ),
    "seam_mismatch": Threshold(
        "Colour step across seams after balancing",
        "DN",
        8.0,
        20.0,
        False,
        "a step under 8 grey levels is hard to see; over 20 every seam shows",
    ),
}


@dataclass(frozen=True)
class Check:
    """One graded item."""

    item: str
    label: str
    state: State
    value: float
    shown: str  # the value as the report prints it
    green: str  # the green and red limits, in words
    red: str
    detail: str = ""


def _fmt(v: float, unit: str) -> str:
    if unit == "%":
        return f"{v:.1f} %"
    if unit == "GSD":
        return f"{v:.2f} GSD"
    if unit == "m":
        return f"{v:.2f} m"
    if unit == "deg":
        return f"{v:.2f}°"
    return f"{v:.1f} {unit}"


#: Items every finished run measures: one missing means its stage's report is missing or damaged,
#: and a missing measurement is never green.
REQUIRED = ("ortho_coverage", "dsm_measured", "photos_registered", "photos_in_ortho")


def _check(item: str, value: float, detail: str = "") -> Check:
    t = THRESHOLDS[item]
    green, red = t.limits()
    shown = _fmt(value, t.unit) if math.isfinite(value) else "–"
    if math.isfinite(value) and (value < 0 or (t.unit == "%" and value > 100.0 + 1e-6)):
        # a share over 100 % or a negative size: the stage report is damaged, not a measurement
        return Check(item, t.label, "red", math.nan, shown, green, red, "impossible value: the stage report is damaged")
    if not math.isfinite(value) and item in REQUIRED:
        why = "not measured: its stage's report is missing or damaged"
        return Check(item, t.label, "red", value, shown, green, red, f"{why}; {detail}" if detail else why)
    return Check(item, t.label, t.grade(value), value, shown, green, red, detail)


def _share(n: Any, of: Any) -> float:
    n_, of_ = as_number(n), as_number(of)
    return 100.0 * n_ / of_ if of_ > 0 else math.nan


def as_number(v: Any) -> float:
    """A measured value as a float; NaN (not measured) for anything that is not a number (JSON's
    true and false, and numbers written as text, included)."""
    if isinstance(v, (bool, str, bytes)):  # a number written as text is no report's: damaged
        return math.nan
    try:
        return float(v)
    except (TypeError, ValueError, OverflowError):
        return math.nan


def assess(
    sfm: dict[str, Any] | None,
    dense: dict[str, Any] | None,
    dem: dict[str, Any] | None,
    ortho: dict[str, Any] | None,
    footprints: dict[str, Any] | None,
) -> list[Check]:
    """Grade what the stages measured (their reports and outputs; None for a stage not run)."""
    sfm, dense, dem, ortho, fp = sfm or {}, dense or {}, dem or {}, ortho or {}, footprints or {}
    return [
        *_coverage_checks(dem, ortho),
        *_terrain_checks(sfm, dem),
        *_photo_checks(sfm, dense, ortho),
        _left_out_check(sfm, fp),
        *_control_checks(sfm),
        *_gps_checks(sfm),
        *_surface_checks(sfm, ortho, fp),
    ]


def _coverage_checks(dem: dict[str, Any], ortho: dict[str, Any]) -> list[Check]:
    return [
        _check("ortho_coverage", 100.0 * as_number(ortho.get("share_of_seen_2", math.nan))),
        _check(
            "ortho_holes",
            as_number(ortho.get("holes_inside_m2", math.nan)),
            f"{as_number(ortho.get('holes_inside_n', math.nan)):.0f} holes, the largest "
            f"{as_number(ortho.get('largest_hole_m2', math.nan)):.1f} m²"
            if as_number(ortho.get("holes_inside_n", 0)) > 0
            else "",
        ),
        _check(
            "dsm_measured",
            100.0 * as_number(dem.get("measured_share", math.nan)) if dem.get("seen_m2") else math.nan,
        ),
    ]


def _terrain_checks(sfm: dict[str, Any], dem: dict[str, Any]) -> list[Check]:
    """The DTM as a hillshade shows it: its roughness on open ground and its steps at the photos'
    footprint edges (in GSDs), and how much of it lies under objects with no ground seen."""
    gsd_m = as_number(sfm.get("gsd_cm")) / 100.0
    rough_m, step_m = as_number(dem.get("dtm_roughness_m", math.nan)), as_number(dem.get("footprint_step_m", math.nan))
    return [
        _check(
            "dtm_roughness",
            rough_m / gsd_m if gsd_m > 0 else math.nan,
            f"{100 * rough_m:.1f} cm" if math.isfinite(rough_m) else "",
        ),
        _check("dtm_no_ground", 100.0 * as_number(dem.get("dtm_under_object_share", math.nan))),
        _check(
            "footprint_step",
            step_m / gsd_m if gsd_m > 0 else math.nan,
            f"{100 * step_m:.1f} cm" if math.isfinite(step_m) else "",
        ),
    ]


def _photo_checks(sfm: dict[str, Any], dense: dict[str, Any], ortho: dict[str, Any]) -> list[Check]:
    """Photos registered, in the orthophoto, with a depth map; the ones left out named."""
    dropped = sfm.get("unregistered") or []
    if isinstance(dropped, dict):  # image -> why, as sfm's report gives it
        unregistered = [f"{k} ({v})" if len(dropped) <= 3 else str(k) for k, v in dropped.items()]
    else:
        unregistered = [str(u.get("image", u)) if isinstance(u, dict) else str(u) for u in dropped]
    no_map = dense.get("no_depth_map") or {}
    return [
        _check(
            "photos_registered",
            _share(sfm.get("registered"), sfm.get("photos")),
            ("not registered: " + ", ".join(unregistered[:8]) + (" …" if len(unregistered) > 8 else ""))
            if unregistered
            else "",
        ),
        _check("photos_in_ortho", _share(ortho.get("n_used"), ortho.get("n_photos"))),
        _check(
            "depth_maps",
            _share(dense.get("depth_maps"), dense.get("photos")),
            ("none for: " + ", ".join(list(no_map)[:8])) if no_map else "",
        ),
    ]


def _control_checks(sfm: dict[str, Any]) -> list[Check]:
    """The GCPs' and checkpoints' RMSE (in GSDs), and how far the GCPs moved the GPS georeference."""
    gsd_m = as_number(sfm.get("gsd_cm")) / 100.0
    checks = []
    for item, key in (("gcp_rmse", "gcp_accuracy"), ("checkpoint_rmse", "checkpoint_accuracy")):
        acc = sfm.get(key) or {}
        if not acc:
            checks.append(_check(item, math.nan))
            continue
        # 3D when the heights are controlled; placeholder heights: horizontal only
        three_d = acc.get("rmse_3d_m") is not None
        rmse = as_number(acc.get("rmse_3d_m") if three_d else acc.get("rmse_horizontal_m"))
        what = "3D" if three_d else "horizontal (heights not controlled)"
        checks.append(_check(item, rmse / gsd_m, f"{100 * rmse:.1f} cm {what} over {acc.get('n')}"))
    effect = sfm.get("gcp_vs_gps") or {}
    cause = str(effect.get("likely_cause") or "")
    if cause and checks[0].state != "not measured":  # the control residuals: what most likely made them
        checks[0] = Check(**{**asdict(checks[0]), "detail": f"{checks[0].detail}; likely cause: {cause}"})
    edge = f"moves the site's edge {as_number(effect.get('edge_shift_m')):.2f} m" if "edge_shift_m" in effect else ""
    checks.append(_check("gcp_scale", abs(as_number(effect.get("scale_change_pct", math.nan))), edge))
    checks.append(_check("gcp_rotation", as_number(effect.get("rotation_deg", math.nan)), edge))
    checks.append(
        _check(
            "gcp_shift",
            as_number(effect.get("shift_horizontal_m", math.nan)),
            f"{as_number(effect.get('shift_vertical_m')):+.2f} m vertically" + (f"; {cause}" if cause else "")
            if "shift_horizontal_m" in effect
            else "",
        )
    )
    return checks


def _gps_checks(sfm: dict[str, Any]) -> list[Check]:
    """A block georeferenced by its GPS: how well the GPS fits it, and whether the two fits agree."""
    by_gps = str(sfm.get("georeferenced_by", "")).startswith("GPS")
    gps = sfm.get("gps") or {}
    spread = (
        f"; {100 * as_number(gps.get('inlier_share')):.0f} % of the photos fit it, rotation ± "
        f"{as_number(gps.get('rotation_sd_deg')):.2f}°, scale ± {as_number(gps.get('scale_sd_pct')):.2f} %"
        if "inlier_share" in gps
        else ""
    )
    ce90_m = as_number(gps.get("ce90_m"))
    return [
        _check(
            "gps_fit",
            ce90_m if by_gps else math.nan,
            "the products' absolute accuracy is the GPS's" + spread if by_gps else "",
        ),
        _check(
            "gps_fits_agree",
            as_number(gps.get("robust_vs_lsq_m")) / ce90_m if by_gps and ce90_m > 0 else math.nan,
            f"{as_number(gps.get('robust_vs_lsq_m')):.2f} m; least squares turns it "
            f"{as_number(gps.get('lsq_rotation_deg')):+.2f}°"
            if by_gps
            else "",
        ),
    ]


def _left_out_check(sfm: dict[str, Any], fp: dict[str, Any]) -> Check:
    """The ground that only the photos the SfM did not place saw (footprints from their GPS), as a
    share of all the ground seen; the submodels that failed named."""
    area, seen = as_number(fp.get("area_left_out_m2", math.nan)), as_number(fp.get("area_seen_m2", math.nan))
    dropped = sfm.get("unregistered")
    reasons = [str(why) for why in dropped.values()] if isinstance(dropped, dict) else []
    failed = sorted({why.split(":")[0] for why in reasons if why.startswith("submodel ")})
    detail = ""
    if math.isfinite(area) and area > 0:
        n = as_number(fp.get("n_left_out"))
        detail = (
            f"{area:,.0f} m² of {seen:,.0f} m², seen by {f'{n:.0f} ' if math.isfinite(n) else ''}photos "
            "left out (footprints layer left_out)"
        )
    if failed:
        detail = "; ".join([", ".join(failed) + " failed", *([detail] if detail else [])])
    return _check("ground_left_out", _share(area, seen) if seen > 0 else math.nan, detail)


def _surface_checks(sfm: dict[str, Any], ortho: dict[str, Any], fp: dict[str, Any]) -> list[Check]:
    """The camera's focal drift, the DSM against the SfM, the heights given against those measured,
    and the colour step across the seams."""
    drifts = [abs(as_number(i.get("focal_drift_pct"))) for i in sfm.get("intrinsics") or []]
    drifts = [d for d in drifts if math.isfinite(d)]
    measured, meta = as_number(fp.get("altitude_m")), as_number(fp.get("altitude_metadata_m"))
    off = 100.0 * abs(meta - measured) / measured if measured > 0 else math.nan
    heights = _check("heights_given", off, str(fp.get("height_check") or ""))
    if fp.get("height_check") and heights.state != "red":  # an elevation 2 m off is red at any share
        heights = Check(**{**asdict(heights), "state": "red"})
    return [
        _check("focal_drift", max(drifts) if drifts else math.nan),
        _check("dsm_vs_sfm", abs(as_number(ortho.get("dsm_offset_m", math.nan)))),
        heights,
        _check("seam_mismatch", as_number(ortho.get("seam_mismatch_balanced", math.nan))),
    ]


def verdict(checks: list[Check], failed: bool = False) -> State:
    """The worst item's state; red when a stage failed."""
    if failed:
        return "red"
    worst: State = max((c.state for c in checks), key=_ORDER.__getitem__, default="not measured")
    return "green" if worst == "not measured" else worst
