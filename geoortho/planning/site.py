"""What a plan is made for: the camera (named, or its sensor and lens), the options, the area of
interest read and checked, and the ground under it."""

from __future__ import annotations

import difflib
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import geopandas as gpd
import numpy as np
import pyogrio
import shapely
from pyproj import CRS, Proj

from geoortho.core.camera import Intrinsics, Pose, PosedCamera, rotation_from_ypr
from geoortho.core.crs import WGS84, crs_to_text, horizontal_unit_m, transformer, utm_crs_for
from geoortho.core.gsd import focal_length_px, gsd_at_height_m, height_for_gsd_m
from geoortho.core.surface import FlatSurface, GridSurface, Surface, read_surface, sample_grid
from geoortho.errors import InputError
from geoortho.gcp.markers import Dictionary
from geoortho.photos.footprint import (
    compute_footprints,
)
from geoortho.photos.metadata import read_photo
from geoortho.photos.sensors import CAMERA_SPECS

DEFAULT_MAX_ALTITUDE_M = 120.0  # the open-category ceiling in the EU and the US


@dataclass(frozen=True)
class CameraSpec:
    """A camera as planning needs it."""

    name: str
    sensor_width_mm: float
    focal_mm: float
    width_px: int
    height_px: int
    source: str

    @property
    def focal_px(self) -> float:
        return focal_length_px(self.focal_mm, self.sensor_width_mm, self.width_px)

    def intrinsics(self) -> Intrinsics:
        return Intrinsics(self.width_px, self.height_px, self.focal_px)


CAMERAS: dict[str, CameraSpec] = {}
for _name, _model, _sw, _sh, _f, _w, _h in CAMERA_SPECS:
    for _key in (_name, _model):
        CAMERAS[_key.lower()] = CameraSpec(_name, _sw, _f, _w, _h, f"table: {_name} ({_model})")


def resolve_camera(
    camera: str = "",
    sensor_width_mm: float | None = None,
    focal_mm: float | None = None,
    image_width_px: int | None = None,
    image_height_px: int | None = None,
) -> CameraSpec:
    """The camera from a model name, a sample photo, or explicit values (which override either)."""
    base: CameraSpec | None = None
    try:
        a_photo = bool(camera) and Path(camera).is_file()
    except OSError:  # a name longer than a file name can be is a model name
        a_photo = False
    if a_photo:
        p = read_photo(camera)
        if not (math.isfinite(p.focal_mm) and math.isfinite(p.sensor_width_mm)):
            raise InputError("the photo gives no focal length or sensor width: give --sensor-width-mm", path=camera)
        base = CameraSpec(
            f"{p.make} {p.model}".strip(),
            p.sensor_width_mm,
            p.focal_mm,
            p.width_px,
            p.height_px,
            f"photo {Path(camera).name} ({p.sensor_source})",
        )
    elif camera:
        words = camera.strip().lower().split()
        # make and model as EXIF writes them ("DJI FC6310", "Hasselblad L1D-20c"): the model alone
        # is the table's key, so the make (one word or more) is tried away
        base = next((CAMERAS[k] for k in (" ".join(words[i:]) for i in range(len(words))) if k in CAMERAS), None)
        if base is None:
            names = sorted({c.name for c in CAMERAS.values()} | {m for _, m, *_ in CAMERA_SPECS})
            close = difflib.get_close_matches(camera, names, n=4, cutoff=0.3)
            hint = (
                f"closest: {', '.join(close)}"
                if close
                else f"known: {', '.join(sorted({c.name for c in CAMERAS.values()}))}"
            )
            named = camera if len(camera) <= 60 else f"{camera[:40]}… ({len(camera)} characters)"
            raise InputError(
                f"unknown camera {named!r} ({hint}); or give a sample photo, or --sensor-width-mm, "
                "--focal-mm, --image-width-px and --image-height-px"
            )
    explicit = (sensor_width_mm, focal_mm, image_width_px, image_height_px)
    if base is None:
        if any(v is None for v in explicit):
            raise InputError(
                "no camera: give --camera MODEL|PHOTO, or all of --sensor-width-mm, --focal-mm, "
                "--image-width-px and --image-height-px"
            )
        base = CameraSpec("camera", 1.0, 1.0, 1, 1, "given")
    spec = CameraSpec(
        base.name,
        float(sensor_width_mm if sensor_width_mm is not None else base.sensor_width_mm),
        float(focal_mm if focal_mm is not None else base.focal_mm),
        int(image_width_px if image_width_px is not None else base.width_px),
        int(image_height_px if image_height_px is not None else base.height_px),
        base.source if not any(v is not None for v in explicit) else base.source + " with given values",
    )
    if not (spec.sensor_width_mm > 0 and spec.focal_mm > 0 and spec.width_px >= 16 and spec.height_px >= 16):
        raise InputError(f"camera values out of range: {spec}")
    return spec


@dataclass(frozen=True)
class PlanOptions:
    """:func:`plan`'s options (all but the AOI and the output folder), as one value."""

    camera: str = ""
    gsd_cm: float | None = None
    altitude_m: float | None = None
    front_overlap: float = 75.0
    side_overlap: float = 65.0
    direction_deg: float | None = None
    dtm: Path | None = None
    terrain: Literal["constant", "follow"] = "constant"
    takeoff_ground_m: float | None = None
    pitch_deg: float = -90.0
    grid: Literal["single", "double"] = "single"
    speed_m_s: float = 8.0
    min_interval_s: float = 2.0
    max_altitude_m: float = DEFAULT_MAX_ALTITUDE_M
    gcps: str = ""
    gcp_crs: CRS | None = None
    marker_dictionary: Dictionary = "DICT_4X4_50"
    marker_size_m: float | None = None
    margin: float = 0.0
    crs: CRS | None = None
    sensor_width_mm: float | None = None
    focal_mm: float | None = None
    image_width_px: int | None = None
    image_height_px: int | None = None


@dataclass(frozen=True)
class Site:
    """What the flight is laid out on: the camera, the area, the ground and the spacing."""

    cam: CameraSpec
    intr: Intrinsics
    area: Any  # shapely geometry in work_crs
    work_crs: CRS
    surface: Surface
    ground: dict[str, float]
    ground_label: str
    z_takeoff: float
    agl: float  # the flight height asked (above the take-off, or the ground when following it)
    spacing_agl: float  # the height the spacing was worked out at
    along_len: float  # footprint along the line, m
    across_w: float  # footprint across, m
    ahead: float
    along: float  # photo spacing, m
    across: float  # line spacing, m


def site_layout(aoi: Path, o: PlanOptions, warnings_: list[str]) -> Site:
    """The camera, the AOI in its working CRS, the ground under it, the flight height and the
    spacings that give the overlaps asked; refuses a plan that cannot be flown."""
    _check_options(
        o.gsd_cm, o.altitude_m, o.front_overlap, o.side_overlap, o.terrain, o.dtm, o.pitch_deg, o.speed_m_s,
        o.min_interval_s, o.max_altitude_m,
    )  # fmt: skip
    cam = resolve_camera(o.camera, o.sensor_width_mm, o.focal_mm, o.image_width_px, o.image_height_px)
    area_geom, work_crs, aoi_notes = _read_aoi(aoi, o.crs)
    warnings_ += aoi_notes
    surface: Surface
    if o.dtm is not None:
        surface = read_surface(o.dtm, work_crs, extend=True)
        ground = _ground_stats(surface, area_geom, o.dtm)
        if ground.get("covered", 1.0) < 1.0:
            warnings_.append(
                f"the DTM covers {100 * ground['covered']:.0f} % of the AOI: the rest is its edge carried on"
            )
        ground_label = f"DTM {Path(o.dtm).name}"
    else:
        surface = FlatSurface(float(o.takeoff_ground_m or 0.0))
        ground = {"min": surface.elevation_m, "median": surface.elevation_m, "max": surface.elevation_m}
        ground_label = "flat ground at the take-off"
    z_takeoff = float(o.takeoff_ground_m) if o.takeoff_ground_m is not None else float(ground["median"])
    if o.dtm is not None and o.takeoff_ground_m is None:
        warnings_.append(
            f"take-off assumed at the AOI's median ground, {z_takeoff:.1f} m on the DTM: "
            "give --takeoff-ground-m for the real one"
        )
    intr = cam.intrinsics()
    tilt = math.radians(90.0 + o.pitch_deg)  # off nadir
    # Height above the ground for the target GSD at the image centre (slant range r = gsd·f·sqrt(cos i)).
    if o.gsd_cm is not None:
        agl = height_for_gsd_m(o.gsd_cm / 100.0, intr.focal_px, tilt)
    else:
        agl = float(o.altitude_m)  # type: ignore[arg-type]
    if agl > o.max_altitude_m:
        best = gsd_at_height_m(o.max_altitude_m, intr.focal_px, tilt) * 100
        raise InputError(
            f"a GSD of {o.gsd_cm:g} cm needs {agl:.0f} m above the ground with {cam.name}, over the "
            f"{o.max_altitude_m:g} m limit (--max-altitude-m); the best possible is {best:.2f} cm"
        )
    # Spacing from the footprint on level ground: at the highest ground of the AOI for a constant
    # altitude, so that the overlaps asked are met everywhere (they grow over lower ground).
    rise = ground["max"] - z_takeoff if o.dtm is not None else 0.0
    spacing_agl = agl if o.terrain == "follow" else agl - rise
    if o.terrain == "constant" and o.dtm is not None and spacing_agl < 0.3 * agl:
        raise InputError(
            f"the ground rises {ground['max'] - z_takeoff:.0f} m above the take-off: a constant "
            f"{agl:.0f} m would pass within {max(spacing_agl, 0):.0f} m of it; use --terrain follow"
        )
    along_len, across_w, ahead = _footprint_shape(intr, o.pitch_deg, spacing_agl)
    along = along_len * (1 - o.front_overlap / 100.0)
    across = across_w * (1 - o.side_overlap / 100.0)
    _refuse_too_many_photos(area_geom, along, across, 2 if o.grid == "double" else 1, cam.name)
    return Site(
        cam, intr, area_geom, work_crs, surface, ground, ground_label, z_takeoff, agl, spacing_agl, along_len,
        across_w, ahead, along, across,
    )  # fmt: skip


def _check_options(
    gsd_cm: float | None,
    altitude_m: float | None,
    front: float,
    side: float,
    terrain: str,
    dtm: Path | None,
    pitch_deg: float,
    speed: float,
    interval: float,
    max_alt: float,
) -> None:
    if (gsd_cm is None) == (altitude_m is None):
        raise InputError("give one of --gsd-cm or --altitude-m")
    if gsd_cm is not None and not 0.05 <= gsd_cm <= 100:
        raise InputError(f"--gsd-cm {gsd_cm:g} is out of range (0.05 to 100 cm)")
    if altitude_m is not None and not 1 <= altitude_m <= 2000:
        raise InputError(f"--altitude-m {altitude_m:g} is out of range (1 to 2000 m)")
    for name, v in (("--front-overlap", front), ("--side-overlap", side)):
        if not 0 <= v < 100:
            raise InputError(f"{name} {v:g} % is not possible: give 0 to 99 % (photos cannot overlap 100 %)")
    if terrain == "follow" and dtm is None:
        raise InputError("--terrain follow needs a --dtm")
    if not -90 <= pitch_deg <= -30:
        raise InputError(f"--pitch-deg {pitch_deg:g}: give -90 (nadir) to -30 (oblique)")
    if speed <= 0 or interval <= 0 or max_alt <= 0:
        raise InputError("--speed-m-s, --min-interval-s and --max-altitude-m must be positive")


def _read_aoi(path: Path, crs: CRS | None) -> tuple[Any, CRS, list[str]]:
    """The AOI as one valid (multi)polygon in the working CRS, with what was repaired."""
    if not path.exists():
        raise InputError("no such file", path=path)
    try:
        if path.is_file() and not len(pyogrio.list_layers(path)):
            raise InputError("the AOI file holds no layer (an empty file?): give an area", path=path)
        df = gpd.read_file(path, engine="pyogrio")
    except InputError:
        raise
    except Exception as e:  # pyogrio raises its own DataSourceError and friends
        raise InputError(f"cannot read the AOI: {e}", path=path) from None
    notes = []
    polys = [g for g in df.geometry if g is not None and not g.is_empty]
    polys = [g for g in polys if g.geom_type in ("Polygon", "MultiPolygon")]
    if not polys:
        kinds = sorted({g.geom_type for g in df.geometry if g is not None})
        raise InputError(f"the AOI holds no polygon ({', '.join(kinds) or 'no geometry'}): give an area", path=path)
    if df.crs is None:
        raise InputError("the AOI has no CRS", path=path)
    xy = shapely.get_coordinates(polys)
    if not np.isfinite(xy).all():
        raise InputError("the AOI has a coordinate that is not a number (NaN or infinite)", path=path)
    src_crs = CRS.from_user_input(df.crs)
    if src_crs.is_geographic and (np.abs(xy[:, 0]).max() > 180 or np.abs(xy[:, 1]).max() > 90):
        raise InputError(
            f"the AOI's coordinates ({xy[0, 0]:.0f}, {xy[0, 1]:.0f}) are not degrees, though its CRS "
            f"({src_crs.name}) says so: projected numbers? give the file its real CRS",
            path=path,
        )
    if src_crs.is_geographic and np.ptp(xy[:, 0]) > 180.0:
        # across the antimeridian: 179.9 and -179.9 are 0.2 degrees apart, not 359.8 (the centre's UTM
        # zone was otherwise 177 degrees away); longitudes unwrapped past 180, as PROJ takes them
        polys = [shapely.transform(g, lambda c: np.c_[np.where(c[:, 0] < 0, c[:, 0] + 360.0, c[:, 0]), c[:, 1]])
                 for g in polys]  # fmt: skip
        notes.append("the AOI crosses the antimeridian: its longitudes read as one area across 180 degrees")
    geom = shapely.union_all(polys)
    if not geom.is_valid:
        reason = shapely.is_valid_reason(geom)
        geom = shapely.make_valid(geom)
        geom = shapely.union_all([g for g in shapely.get_parts(geom) if g.geom_type in ("Polygon", "MultiPolygon")])
        notes.append(
            f"the AOI was not a valid polygon ({reason}): repaired by GEOS make_valid; check it in plan.gpkg, layer aoi"
        )
    if geom.is_empty or geom.area <= 0.0:
        raise InputError("the AOI's polygon has no area (its points lie on a line): give an area", path=path)
    src = src_crs
    if crs is not None:  # a map grid: the faces that parse it say so
        work = crs
        _refuse_untrue_scale(work, _reproject(geom, src, WGS84).centroid)
    elif src.is_projected:
        work = src
    else:  # the UTM zone of the AOI's centre, also when the AOI crosses a zone edge
        c = _reproject(geom, src, WGS84).centroid
        work = utm_crs_for((float(c.x) + 180.0) % 360.0 - 180.0, float(c.y))
    geom = _reproject(geom, src, work)
    if geom.area < 1.0:
        raise InputError(f"the AOI is {geom.area:.2f} m²: too small to plan", path=path)
    _refuse_parts_apart(geom, path)

    if abs(horizontal_unit_m(work) - 1.0) > 1e-9:
        raise InputError(f"plan in a CRS in metres: {crs_to_text(work)} is not (give --crs)")
    return geom, work, notes


#: Parts of an AOI farther apart than this (m) are separate flights: lines across the gap were
#: flown (two fields 8.7 km apart: 2,440 photos, 93 minutes).
MAX_PART_GAP_M = 1000.0


def _refuse_parts_apart(geom: Any, path: Path) -> None:
    """An AOI of parts that lie apart is refused, naming the gap: plan each part on its own."""
    if len(shapely.get_parts(geom)) < 2:
        return
    # parts within the gap of each other are one site: grown by half of it, they join
    sites = list(shapely.get_parts(shapely.union_all(shapely.buffer(shapely.get_parts(geom), MAX_PART_GAP_M / 2))))
    if len(sites) > 1:
        gap = min(float(a.distance(b)) for i, a in enumerate(sites) for b in sites[i + 1 :]) + MAX_PART_GAP_M
        raise InputError(
            f"the AOI has {len(sites)} sites {gap / 1000:,.1f} km apart or more: one flight would cross the gap "
            f"(over {MAX_PART_GAP_M / 1000:g} km); plan each site on its own",
            path=path,
        )


#: A plan's metres are the ground's: a CRS whose scale at the AOI is further from 1 than this
#: (Web Mercator: 1.28 at 38 deg N) would put the photos too close or too far apart.
MAX_SCALE_ERROR = 0.01


def _refuse_untrue_scale(crs: CRS, centre_lonlat: Any) -> None:

    f = Proj(crs).get_factors(float(centre_lonlat.x), float(centre_lonlat.y))
    k = max(abs(f.meridional_scale - 1.0), abs(f.parallel_scale - 1.0))
    if not math.isfinite(k) or k > MAX_SCALE_ERROR:
        raise InputError(
            f"--crs {crs_to_text(crs)}: a metre of it is {1 / f.parallel_scale:.3f} m on the ground here, so "
            "spacings and GSD planned in it would be off: plan in a CRS true to the ground (the default, "
            "the AOI's UTM zone) and reproject the products if that CRS is needed"
        )


def _reproject(geom: Any, src: CRS, dst: CRS) -> Any:

    if src.equals(dst):
        return geom
    t = transformer(src, dst)
    return shapely.transform(geom, lambda c: np.c_[t.transform(c[:, 0], c[:, 1])])


#: More photos than any one flight plan holds (a big mapping job is a few thousand): refused with
#: the count before anything is built (a county at 2 cm would take tens of GB).
MAX_PLAN_PHOTOS = 50_000


def _refuse_too_many_photos(area: Any, along_m: float, across_m: float, grids: int, camera: str) -> None:
    x0, y0, x1, y1 = area.bounds
    lines = (max(x1 - x0, y1 - y0) / across_m + 1) * grids
    n = grids * area.area / (along_m * across_m) + lines
    if n > MAX_PLAN_PHOTOS:
        count = f"{n / 1e6:.1f} M" if n >= 1e6 else f"{n:,.0f}"
        raise InputError(
            f"the plan would take about {count} photos ({area.area / 1e6:,.2f} km² at {along_m:.2f} x {across_m:.2f} m "
            f"spacing with {camera}), over the {MAX_PLAN_PHOTOS:,} a plan holds: split the AOI, or fly higher "
            "(a larger GSD)"
        )


def _ground_stats(surface: Surface, area: Any, dtm: Any = None) -> dict[str, float]:

    x0, y0, x1, y1 = area.bounds
    n = 60
    xs, ys = np.meshgrid(np.linspace(x0, x1, n), np.linspace(y0, y1, n))
    inside = shapely.contains_xy(area, xs, ys)
    if not inside.any():
        inside = np.ones_like(inside)
    covered = 1.0
    if isinstance(surface, GridSurface):
        # the DTM itself, not the ground carried beyond its edge (read with extend)
        c, r = surface.colrow(xs[inside], ys[inside])
        covered = float(np.isfinite(sample_grid(surface.grid, c, r)).mean())
        if covered < 0.5:
            gx0, gy0 = surface.transform @ (0, 0)
            gx1, gy1 = surface.transform @ (surface.grid.shape[1], surface.grid.shape[0])
            far_m = float(np.hypot((x0 + x1 - gx0 - gx1) / 2, (y0 + y1 - gy0 - gy1) / 2))
            raise InputError(
                f"the DTM covers {100 * covered:.0f} % of the AOI (their centres are {far_m / 1000:,.1f} km apart): "
                "give a DTM of this area",
                path=dtm,
            )
    z = surface.elevation(xs[inside], ys[inside])
    z = z[np.isfinite(z)]
    if z.size == 0:
        raise InputError("the DTM does not cover the AOI", path=dtm)
    return {"min": float(z.min()), "median": float(np.median(z)), "max": float(z.max()), "covered": covered}


def _footprint_shape(intr: Intrinsics, pitch_deg: float, agl: float) -> tuple[float, float, float]:
    """A photo's footprint on level ground ``agl`` below: length along the line (through the image
    centre), width across it (at the centre's ground point) and how far ahead of the drone that
    point is."""
    cam = PosedCamera(intr, Pose(np.array([0.0, 0.0, agl]), rotation_from_ypr(0.0, pitch_deg, 0.0)))
    t = compute_footprints([cam], FlatSurface(0.0), per_side=64, max_range_m=50 * agl)
    if t.clipped[0]:
        raise InputError(f"at pitch {pitch_deg:g}° the photo sees the horizon: plan a steeper pitch")
    ring = t.rings[0]
    ahead = agl * math.tan(math.radians(90.0 + pitch_deg))

    poly = shapely.Polygon(ring)
    big = 100 * agl
    along = shapely.intersection(poly, shapely.LineString([(0, -big), (0, big)])).length
    across = shapely.intersection(poly, shapely.LineString([(-big, ahead), (big, ahead)])).length
    return float(along), float(across), float(ahead)
