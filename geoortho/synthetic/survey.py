"""A synthetic drone survey with exact ground truth.

The scene lives in a real UTM zone: a DTM (gentle terrain and a ridge), a DSM
(the DTM plus buildings and trees), a procedural ground texture of unlimited
resolution (fields, roads, multi-scale noise) and flat ArUco markers on pads.
A lawnmower flight is rendered by casting every pixel's ray onto the DSM; the
photos carry EXIF and DJI XMP as a real DJI camera writes them, with realistic
GPS and attitude errors, while ``truth/`` keeps the exact values.

Conventions of the truth files (also written to ``truth/survey.json``):

* Heights are ellipsoidal (WGS84), in metres; the scene CRS is the WGS84 UTM
  zone of the scene centre. GCP files give the same points as EPSG:4979
  lat/lon/h and as UTM easting/northing/h.
* Pixels: (0, 0) is the centre of the top-left pixel (OpenCV; what
  OpenDroneMap/OpenSfM read in gcp_list.txt).
* Attitude: yaw clockwise from north, pitch −90 = nadir, roll right-down
  positive (see :mod:`geoortho.core.camera`).
"""

from __future__ import annotations

import datetime as dt
import io
import json
import math
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any, Literal, get_args

import cv2
import numpy as np
from affine import Affine
from pyproj import CRS

from geoortho.core.camera import Intrinsics, Pose, pixel_rays, project_points, rotation_from_ypr, ypr_from_rotation
from geoortho.core.crs import geoid_undulation_m, grid_north, transformer, utm_crs_for
from geoortho.core.outputs import atomic_path, write_cog, write_json, write_text, write_vector
from geoortho.core.parallel import map_ordered
from geoortho.core.pointcloud import write_las
from geoortho.core.surface import GridSurface, RayHits, sample_grid
from geoortho.elevation.grid import NODATA
from geoortho.errors import InputError
from geoortho.feedback import Feedback, as_feedback, split
from geoortho.gcp.markers import (
    TARGETS,
    Dictionary,
    Target,
    get_dictionary,
    marker_cells,
    target_half_extent,
    target_reflectance,
)
from geoortho.gcp.targets import motion_kernel, spread_path
from geoortho.synthetic.cover import CANOPY_STYLES, add_canopy, add_car_park, add_hall, add_hedge, leaf_texture
from geoortho.synthetic.movers import Mover, draw_movers, place_movers

__all__ = ["PRESETS", "PATHOLOGIES", "SynthPreset", "SynthResult", "synth", "build_scene", "plan_flight"]

Preset = Literal["tiny", "small", "medium", "oblique", "hard"]


@dataclass(frozen=True)
class SynthPreset:
    """Everything that differs between presets."""

    name: str
    area_m: tuple[float, float] = (80.0, 60.0)  # flown area, east × north
    altitude_m: float = 40.0  # above the take-off point
    image_px: tuple[int, int] = (1600, 1067)
    front_overlap: float = 0.75
    side_overlap: float = 0.65
    n_buildings: int = 4
    n_trees: int = 6
    n_markers: int = 8
    n_decoys: int = 1  # markers on the ground whose ids are in no GCP file
    n_oblique: int = 0
    cell_m: float = 0.25  # DSM/DTM grid
    ortho_cell_m: float = 0.05
    points_per_m2: float = 12.0
    hard: bool = False
    distortion: tuple[float, ...] = ()


PRESETS: dict[str, SynthPreset] = {
    "tiny": SynthPreset(
        "tiny",
        area_m=(32.0, 24.0),
        altitude_m=30.0,
        image_px=(960, 640),
        front_overlap=0.6,
        side_overlap=0.5,
        n_buildings=1,
        n_trees=1,
        n_markers=4,
        n_decoys=1,
        ortho_cell_m=0.1,
        points_per_m2=4.0,
    ),
    "small": SynthPreset("small"),
    "medium": SynthPreset(
        "medium",
        area_m=(160.0, 120.0),
        altitude_m=50.0,
        image_px=(2400, 1600),
        n_buildings=10,
        n_trees=16,
        n_markers=16,
        n_decoys=2,
        ortho_cell_m=0.1,
    ),
    "oblique": SynthPreset("oblique", n_oblique=12),
    "hard": SynthPreset("hard", hard=True, distortion=(-0.02, 0.01, 0.0, 0.0, 0.0)),
}

# Modelled on the DJI Phantom 4 Pro camera (FC6310): 1" sensor, 8.8 mm lens.
CAMERA_MODEL = "FC6310"
# Whose metadata the photos carry (synth's ``maker``): the same attitude and position written
# with each maker family's tags and conventions (geoortho.photos.metadata._FAMILIES names the documents).
Maker = Literal["dji", "autel", "parrot", "skydio", "pix4d", "sensefly", "exif"]
#: How glare is drawn on a target (``glare``): a small specular spot saturating part of it (spot), a
#: bloom 1.5-3 marker sides across whose core saturates (bloom), or a soft elongated sheen of a few
#: sides that lifts the blacks without clipping (sheen). One renderer's glare is not another's:
#: the detector must hold on the family.
GlareStyle = Literal["spot", "bloom", "sheen"]
#: How motion blur is drawn (``blur_px``): the exact path spread bilinearly (exact), a line drawn by
#: OpenCV's rasteriser at a whole length (line), or a shaken, curved path (shake).
BlurStyle = Literal["exact", "line", "shake"]
#: How the sensor's noise is drawn: the same spread on every pixel, independent (even); photon
#: noise that grows with the light, bright pixels noisier than dark (shot); or the blotches an
#: in-camera denoiser and demosaicing leave, each a couple of pixels across and coloured (grain).
NoiseStyle = Literal["even", "shot", "grain"]
#: How the lens's light falloff (vignetting) is drawn, over rho (the squared radius over the
#: half-diagonal's): 1 - 0.25 rho, 25 % at the corners (quadratic); the cos^4 law of a lens whose
#: diagonal field is 50 degrees, 32 % at the corners (cos4); or flat to half-way and dropping at
#: the corners, 13 % there, as on toledo's DJI photos (flat-drop). The falloff estimate must hold on
#: the family, not on one renderer's curve.
VignettingStyle = Literal["quadratic", "cos4", "flat-drop"]
#: The noise's spread (1.0 = white): even everywhere; shot's photon term (per unit of light) and
#: read term, so white gets about 5 grey levels and black 1.5; grain's, once smoothed.
EVEN_NOISE = 0.008
SHOT_NOISE_PER_LIGHT, READ_NOISE = 0.0004, 0.006
GRAIN_NOISE, GRAIN_PX = 0.012, 1.0
MAKERS: tuple[str, ...] = get_args(Maker)
MAKER_MAKE = {
    "dji": "DJI",
    "autel": "Autel Robotics",
    "parrot": "Parrot",
    "skydio": "Skydio",
    "pix4d": "MicaSense",
    "sensefly": "senseFly",
    "exif": "Wingtra",
}
SENSOR_WIDTH_MM = 13.2
SENSOR_HEIGHT_MM = 8.8
FOCAL_MM = 8.8
FOCAL_35MM = 24

# Error model of the recorded metadata (the truth keeps exact values).
GPS_BIAS_SIGMA_M = 0.5  # per axis, common to the flight
GPS_NOISE_SIGMA_M = 0.2  # per axis, per photo
GPS_ALT_BIAS_SIGMA_M = 3.0  # GPSAltitude is poor on consumer drones
REL_ALT_NOISE_SIGMA_M = 0.1  # barometric height above take-off is good
ATTITUDE_NOISE_SIGMA_DEG = 0.2  # recorded gimbal angles vs the true ones
TRUE_ATTITUDE_JITTER_DEG = 1.5  # how far the real camera wanders from the plan

DEFAULT_LAT = 38.7476  # Lisbon, Monsanto park
DEFAULT_LON = -9.1887

WRONG_CALIBRATION_FACTOR = 1.1
GPS_LAG_S = 1.0
PPK_LAG_S = 0.3  # the camera's time stamp this much before the exposure
GPS_MINUS_UTC_S = 18.0  # leap seconds since 2017: GPS time runs ahead of UTC (the camera's clock)
PPK_EPOCH_S = 0.2
PPK_SIGMA_M = (0.01, 0.02)

WIDE_WOOD_RADIUS_M = 22.0
BANK_M = (2.0,)  # height
CUTTING_M = (1.2, 6.0)  # depth, road width

# What real consumer drones get wrong, each one a survey can be made with (comma-separated).
PATHOLOGIES: dict[str, str] = {
    "no-relative-altitude": "no RelativeAltitude/AbsoluteAltitude; EXIF GPSAltitude orthometric (EGM96), as "
    "most non-DJI cameras write it",
    "ellipsoidal-gps": "no RelativeAltitude/AbsoluteAltitude; EXIF GPSAltitude ellipsoidal",
    "altitude-drift": "no RelativeAltitude; GPSAltitude (orthometric) drifts 30 m over the flight and jumps 12 m",
    "wrong-focal": "EXIF FocalLength 12 % longer than the lens's",
    "dsm-datum": "truth/dsm_other_datum.tif: the DSM in orthometric (EGM96) heights, the photos' ellipsoidal",
    "partial-dsm": "truth/dsm_partial.tif: the DSM cropped to the eastern 60 % of the flight",
    "exposure-steps": "every other flight line exposed 0.7x (ExposureTime says so)",
    "free-heading": "the camera's heading turns freely from photo to photo (a compact camera under a multirotor): "
    "each photo's yaw is drawn at random, and its EXIF/XMP yaw says so",
    "water": "a pond of one flat colour (no texture, as calm water or a fresh tarmac) in the open ground of the "
    "flight: survey.json gives its disc (water: x, y, radius_m)",
    "no-attitude": "a compact camera on a fixed mount: no attitude in the metadata (no XMP, no GPSImgDirection) "
    "and every photo tilted 3.5 deg off nadir towards one fixed direction (survey.json: mount_tilt)",
    "slope": "the terrain tilted 5 deg (rising towards azimuth 30 deg) under a flight at one height",
    "wrong-flight-height": "the user's flight height is 50 % off: survey.json gives it (user_flight_height_m) "
    "beside the true one (flight_height_m, above take-off) for a test to pass it",
    "poor-gps": "a consumer GPS at its worst: every photo's recorded position off by 20 m (sigma, per axis)",
    "canopy": "a wood of closed canopy on open ground of the flight: overlapping crowns 7-12 m high that hide "
    "each other, a leaf texture that repeats from crown to crown (drawn as a regular pattern for an even seed, as "
    "noise blobs for an odd one) and deep shade between them; survey.json gives where (cover.canopy)",
    "cars": "a car park: two rows of bays on tarmac, four in five taken by a car 1.45 m high with its shadow "
    "cast on the tarmac; survey.json gives where (cover.cars)",
    "rtk": "an RTK aircraft: positions and GNSS heights to 2 cm (horizontal) and 3 cm (vertical), fixed "
    "(RtkFlag 50) with their standard deviations in the XMP (Pix4D's Camera:GPSXYAccuracy/GPSZAccuracy for "
    "non-DJI makers); three photos mid-flight in a float solution (0.3 m) and one at a turn with the fix "
    "lost (single point, 1.5 m); survey.json names them (rtk)",
    "ppk": "a PPK flight: truth/trajectory.pos, an RTKLIB solution at 5 Hz (GPS time, fixed, 1 cm H, 2 cm V) "
    f"of the camera's path; the photos' own GPS is a consumer's, and their time stamps (to the millisecond) "
    f"run {PPK_LAG_S:g} s behind the exposures (survey.json: ppk)",
    "factory-calibration": "DJI's factory calibration in the XMP (CalibratedFocalLength, CalibratedOpticalCenterX/Y, "
    "DewarpData, DewarpFlag 0): the camera's true intrinsics",
    "wrong-calibration": f"DJI's factory calibration tags with a focal length {WRONG_CALIBRATION_FACTOR:g} times "
    "the lens's (a calibration of another unit)",
    "gps-lag": f"the photos' GPS fixes {GPS_LAG_S:g} s stale: each photo records where the camera was {GPS_LAG_S:g} s "
    "before its exposure (a consumer camera's lag; survey.json: gps_lag_s)",
    "wide-wood": f"a wood {2 * WIDE_WOOD_RADIUS_M:.0f} m across with no ground seen under it, over whatever stood "
    "there (closed crowns 7-12 m high, leaves drawn as for canopy); survey.json gives where (cover.wide_wood)",
    "hall": "a hall wider than any ground filter's window (40 x 24 m, or half the flight area), 7 m to its eaves: "
    "a flat roof for an even seed, one pitched across its width for an odd one; survey.json: cover.hall",
    "hedge": "a hedge line 1.4 m high and 1.2 m wide across open ground, leaf-textured; survey.json: cover.hedge",
    "breaklines": f"a bank {BANK_M[0]:g} m high across the scene (45 deg for an even seed, 30 for an odd one) and a "
    f"road cutting {CUTTING_M[1]:g} m wide, {CUTTING_M[0]:g} m deep with 45 deg sides: the ground's own sharp edges; "
    "survey.json: cover.breaklines",
    "moving-cars": "four cars (4.4 x 1.8 x 1.45 m, 4 m/s) and two people (1.7 m, 1.4 m/s) going to and fro along "
    "30 m tracks on open ground while the drone flies: each photo shows them where they were then, drawn as a car "
    "with a windscreen (even seed) or a box with a roof stripe (odd); the truth is the static scene without them; "
    "survey.json: movers",
    "dropped-photo": "one photo in the middle of the flight that no SfM can register: smeared by a motion blur of "
    "a tenth of its width, or blown out (25x over-exposed), as the seed draws; survey.json names it "
    "(dropped_photo: image, how)",
}
POOR_GPS_SIGMA_M = 20.0
WRONG_FLIGHT_HEIGHT_FACTOR = 1.5
MOUNT_TILT_DEG = 3.5
MOUNT_TILT_AZIMUTH_DEG = 120.0
SLOPE_DEG = 5.0
SLOPE_AZIMUTH_DEG = 30.0
WRONG_FOCAL_FACTOR = 1.12
WATER_RGB = (0.16, 0.27, 0.33)
WATER_RADIUS_M = 6.0
DRIFT_M = 30.0
JUMP_M = 12.0
EXPOSURE_STEP = 0.7
DROPPED_BLUR_PX = 100.0  # a tenth of a 1000-px photo's width: no feature survives
DROPPED_GAIN = 25.0


# ---------------------------------------------------------------------------------------------
# Scene


@dataclass(frozen=True)
class Marker:
    marker_id: int
    name: str
    x: float
    y: float
    z: float
    angle_deg: float
    decoy: bool = False


@dataclass(eq=False)
class Scene:
    crs: CRS
    transform: Affine  # of the DSM/DTM grids (cell corners)
    dsm: np.ndarray
    dtm: np.ndarray
    landcover: np.ndarray  # (rows, cols, 3) float32 colours on the DSM grid, 0..1
    objects: np.ndarray  # (rows, cols, 3) float32 colours of roofs/trees
    noise: tuple[np.ndarray, ...]
    noise_cells_m: tuple[float, ...]
    markers: tuple[Marker, ...]
    marker_size_m: float
    dictionary: str
    flight_box: tuple[float, float, float, float]  # xmin, ymin, xmax, ymax
    home: tuple[float, float, float]  # take-off point (x, y, ground z)
    marker_cells: dict[int, np.ndarray] = field(default_factory=dict)
    water: tuple[float, float, float] | None = None  # x, y, radius (m): one flat colour there
    target: str = "aruco"  # what the markers look like (markers.TARGETS)
    canopy: np.ndarray | None = None  # (rows, cols) bool on the DSM grid: a wood's crowns, leaf-textured
    canopy_style: str = "pattern"  # how the leaves are drawn (cover.CANOPY_STYLES)
    cover: dict[str, dict[str, Any]] = field(default_factory=dict)  # canopy/cars: where they are
    movers: tuple[Mover, ...] = ()  # moving cars and people (not in the truth's rasters)

    @property
    def surface(self) -> GridSurface:
        return GridSurface(self.dsm, self.transform, self.crs)

    def colrow(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        t = self.transform
        return (x - t.c) / t.a - 0.5, (y - t.f) / t.e - 0.5

    def color(self, x: np.ndarray, y: np.ndarray, z: np.ndarray) -> np.ndarray:
        """Ground colour (N, 3) float 0..1 at world points: the procedural texture."""
        c, r = self.colrow(x, y)
        c32, r32 = c.astype(np.float32), r.astype(np.float32)
        base = _remap3(self.landcover, c32, r32)
        ground = sample_grid(self.dtm, c32, r32)
        above = (z - ground) > 0.25
        if above.any():
            base[above] = _remap3(self.objects, c32[above], r32[above])
        detail = np.ones(len(x), np.float32)
        for grid, cell, amp in zip(self.noise, self.noise_cells_m, (0.22, 0.18, 0.14)):
            detail += amp * _wrap_sample(grid, x / cell, y / cell)
        if self.canopy is not None and above.any():
            leafy = np.zeros(len(x), bool)
            ci = np.clip(np.rint(c[above]).astype(np.int64), 0, self.canopy.shape[1] - 1)
            ri = np.clip(np.rint(r[above]).astype(np.int64), 0, self.canopy.shape[0] - 1)
            leafy[above] = self.canopy[ri, ci]
            if leafy.any():
                base[leafy] *= leaf_texture(self.canopy_style, x[leafy], y[leafy], self.noise[1])[:, None]
        out = base * detail[:, None]
        if self.water is not None:
            wx, wy, wr = self.water
            out[(x - wx) ** 2 + (y - wy) ** 2 <= wr * wr] = WATER_RGB
        self._paint_markers(x, y, z, out)
        return np.clip(out, 0.0, 1.0)

    def _paint_markers(self, x: np.ndarray, y: np.ndarray, z: np.ndarray, out: np.ndarray) -> None:
        s = self.marker_size_m
        reach = s * max(target_half_extent(self.target), target_half_extent("aruco")) * 1.5
        for m in self.markers:
            near = (np.abs(x - m.x) < reach) & (np.abs(y - m.y) < reach) & (np.abs(z - m.z) < 0.2)
            if not near.any():
                continue
            a = math.radians(m.angle_deg)
            dx, dy = x[near] - m.x, y[near] - m.y
            # marker frame: u to the marker's right, v to its top (rotated by angle, clockwise)
            u = dx * math.cos(a) - dy * math.sin(a)
            v = dx * math.sin(a) + dy * math.cos(a)
            refl = target_reflectance(self.target, u / s, v / s, self.marker_cells.get(m.marker_id))
            painted = np.isfinite(refl)
            idx = np.nonzero(near)[0][painted]
            out[idx] = (0.08 + 0.84 * refl[painted]).astype(np.float32)[:, None]


def _remap3(img: np.ndarray, c: np.ndarray, r: np.ndarray) -> np.ndarray:
    out = np.empty((len(c), 3), np.float32)
    for k in range(3):
        v = sample_grid(img[..., k], c, r)
        out[:, k] = np.nan_to_num(v, nan=0.5)
    return out


def _wrap_sample(grid: np.ndarray, fx: np.ndarray, fy: np.ndarray) -> np.ndarray:
    n0, n1 = grid.shape[0] - 1, grid.shape[1] - 1  # the grid carries one wrapped row/column
    c = np.mod(fx, n1).astype(np.float32)
    r = np.mod(-fy, n0).astype(np.float32)
    v = sample_grid(grid, c, r)
    result: np.ndarray = np.nan_to_num(v)
    return result


def _smooth_noise(rng: np.random.Generator, shape: tuple[int, int], blur: float) -> np.ndarray:
    from scipy.ndimage import gaussian_filter

    n = gaussian_filter(rng.standard_normal(shape), blur, mode="wrap").astype(np.float32)
    n /= n.std() + 1e-9
    # One wrapped row/column extra so bilinear sampling never reads past the edge.
    return np.pad(n, ((0, 1), (0, 1)), mode="wrap")


def build_scene(
    preset: SynthPreset,
    rng: np.random.Generator,
    *,
    lat: float,
    lon: float,
    dictionary: str,
    marker_size_m: float,
    slope_deg: float = 0.0,
    bank_deg: float = 0.0,
) -> Scene:
    """The DTM, DSM, texture layers and marker layout for a preset.

    The stages draw from ``rng`` in a fixed order (terrain, landcover, markers, buildings and
    trees, texture noise): the same seed gives the same scene, byte for byte. ``slope_deg``
    tilts the terrain (rising towards SLOPE_AZIMUTH_DEG) and draws nothing."""
    g = _scene_grid(preset, lat, lon)
    dtm = _terrain(g, preset, rng)
    if slope_deg:
        lx, ly = g.local
        az = math.radians(SLOPE_AZIMUTH_DEG)
        dtm = dtm + math.tan(math.radians(slope_deg)) * (lx * math.sin(az) + ly * math.cos(az))
    breaks: dict[str, Any] = {}
    if bank_deg:
        dtm, breaks = _breaklines(g, dtm, bank_deg, np.random.default_rng([int(1000 * bank_deg), 29]))
    landcover, n_fields = _landcover(g, preset, rng)
    taken = _Occupancy()
    markers, pad_r = _place_markers(g, preset, rng, dictionary, marker_size_m, taken)
    objects, height = _buildings_and_trees(g, preset, rng, dtm, taken)
    dtm, markers = _marker_pads(g, dtm, markers, pad_r)
    dsm = (dtm + height).astype(np.float32)
    noise_cells = (0.02, 0.09, 0.45)
    noise = tuple(_smooth_noise(rng, (s, s), 1.0) for s in (1021, 1031, 1009))
    hx, hy = g.flight_box[0] - 5.0, g.flight_box[1] - 5.0
    home_z = float(sample_grid(dtm, *_cr(g.transform, hx, hy))[0])
    scene = Scene(
        g.crs,
        g.transform,
        dsm,
        dtm,
        landcover.astype(np.float32),
        objects.astype(np.float32),
        noise,
        noise_cells,
        tuple(markers),
        marker_size_m,
        dictionary,
        g.flight_box,
        (hx, hy, home_z),
    )
    scene.marker_cells = {m.marker_id: marker_cells(dictionary, m.marker_id) for m in markers}
    if breaks:
        scene.cover["breaklines"] = breaks
    return scene


def _breaklines(
    g: _SceneGrid, dtm: np.ndarray, bank_deg: float, rng: np.random.Generator
) -> tuple[np.ndarray, dict[str, Any]]:
    """A bank across the scene (the ground BANK_M higher on one side, sloping at ``bank_deg``) and a
    road cutting parallel to it on its low side, CUTTING_M deep and wide with 45 deg sides, a third
    of the flight area away: the DTM with them, and where they are (their offsets along one normal)."""
    lx, ly = g.local
    ang = float(rng.uniform(0, np.pi))
    d = lx * math.cos(ang) + ly * math.sin(ang)  # distance along the normal from the centre
    span = min(g.area_m)
    # the cutting on the bank's low side: the ground between them is a terrace below the bank, not
    # a strip standing above the ground on both sides (an embankment, which every ground filter
    # takes for an object); the bank near the middle, its high side wider than SMRF's reach (a
    # terrace 10 m wide at a survey's edge, 2 m up, is an object to it)
    bank_at = -0.05 * span
    cut_at = bank_at - max(0.3 * span, 12.0)  # a shelf of 6 m or more between the bank and the cutting
    run = BANK_M[0] / math.tan(math.radians(bank_deg))
    bank = BANK_M[0] * np.clip((d - bank_at) / run + 0.5, 0.0, 1.0)
    depth, road = CUTTING_M
    cut = np.clip(depth - np.maximum(np.abs(d - cut_at) - road / 2, 0.0), 0.0, depth)  # 45 deg sides
    where = {"normal_deg": math.degrees(ang), "bank_offset_m": bank_at, "bank_deg": bank_deg,
             "bank_height_m": BANK_M[0], "cutting_offset_m": cut_at, "cutting_depth_m": depth,
             "cutting_width_m": road}  # fmt: skip
    return (dtm + bank - cut).astype(np.float64), where


@dataclass(frozen=True)
class _SceneGrid:
    """The scene's raster grid: the survey area with a margin the photos' footprints fit in."""

    crs: CRS
    e0: float  # scene centre, easting and northing (rounded to 10 m)
    n0: float
    area_m: tuple[float, float]
    margin_m: float
    xmin: float
    ymin: float
    cell: float
    rows: int
    cols: int
    transform: Affine
    X: np.ndarray  # cell centres
    Y: np.ndarray

    @property
    def flight_box(self) -> tuple[float, float, float, float]:
        aw, ah = self.area_m
        return self.e0 - aw / 2, self.n0 - ah / 2, self.e0 + aw / 2, self.n0 + ah / 2

    @property
    def local(self) -> tuple[np.ndarray, np.ndarray]:
        return self.X - self.e0, self.Y - self.n0


def _scene_grid(preset: SynthPreset, lat: float, lon: float) -> _SceneGrid:
    crs = utm_crs_for(lon, lat)
    e0, n0 = transformer(CRS.from_epsg(4326), crs).transform(lon, lat)
    e0, n0 = round(e0 / 10) * 10, round(n0 / 10) * 10
    aw, ah = preset.area_m
    fw, fh = _footprint_size_m(preset)
    margin = max(fw, fh) * 0.6 + 25.0
    if preset.n_oblique:
        margin = max(margin, preset.altitude_m / math.tan(math.radians(16.0)) + 20.0)
    cell = preset.cell_m
    xmin, ymin = e0 - aw / 2 - margin, n0 - ah / 2 - margin
    cols = int(math.ceil((aw + 2 * margin) / cell))
    rows = int(math.ceil((ah + 2 * margin) / cell))
    transform = Affine(cell, 0, xmin, 0, -cell, ymin + rows * cell)
    xs = xmin + (np.arange(cols) + 0.5) * cell
    ys = ymin + rows * cell - (np.arange(rows) + 0.5) * cell
    X, Y = np.meshgrid(xs, ys)
    return _SceneGrid(crs, e0, n0, (aw, ah), margin, xmin, ymin, cell, rows, cols, transform, X, Y)


_BASE_Z = 110.0


def _terrain(g: _SceneGrid, preset: SynthPreset, rng: np.random.Generator) -> np.ndarray:
    """Gentle slopes and a ridge (metres, ellipsoidal)."""
    lx, ly = g.local
    ph = rng.uniform(0, 2 * np.pi, 4)
    dtm = (
        _BASE_Z
        + 2.5 * np.sin(lx / 70 + ph[0]) * np.cos(ly / 90 + ph[1])
        + 1.2 * np.sin(lx / 31 + ph[2])
        + 0.02 * lx
        - 0.015 * ly
    )
    ang = rng.uniform(0, np.pi)
    d_ridge = (lx * np.cos(ang) + ly * np.sin(ang)) - rng.uniform(-0.3, 0.3) * g.area_m[0]
    return dtm + 4.0 * np.exp(-0.5 * (d_ridge / 12.0) ** 2)  # type: ignore[no-any-return]


def _landcover(g: _SceneGrid, preset: SynthPreset, rng: np.random.Generator) -> tuple[np.ndarray, int]:
    """Landcover colours: Voronoi fields with stripes, roads, paths and clutter; and the number of fields."""
    from scipy.spatial import cKDTree

    lx, ly = g.local
    rows, cols, cell = g.rows, g.cols, g.cell
    palette = np.array(
        [
            [0.42, 0.55, 0.25],
            [0.55, 0.60, 0.30],
            [0.70, 0.65, 0.38],
            [0.52, 0.40, 0.28],
            [0.35, 0.48, 0.22],
            [0.62, 0.52, 0.35],
            [0.47, 0.58, 0.36],
        ],
        np.float32,
    )
    n_fields = max(6, int((g.area_m[0] + 2 * g.margin_m) * (g.area_m[1] + 2 * g.margin_m) / 700))
    seeds = np.c_[rng.uniform(0, cols, n_fields), rng.uniform(0, rows, n_fields)]
    _, label = cKDTree(seeds).query(
        np.c_[np.repeat(np.arange(cols)[None], rows, 0).ravel(), np.repeat(np.arange(rows)[:, None], cols, 1).ravel()]
    )
    label = label.reshape(rows, cols)
    field_col = palette[rng.integers(0, len(palette), n_fields)]
    landcover = field_col[label].copy()
    stripe_angle = rng.uniform(0, np.pi, n_fields)[label]
    stripe_period = rng.uniform(1.2, 3.5, n_fields)[label]
    stripes = np.sin(2 * np.pi * (lx * np.cos(stripe_angle) + ly * np.sin(stripe_angle)) / stripe_period)
    landcover *= (1.0 + 0.10 * stripes)[..., None].astype(np.float32)
    canvas = np.ascontiguousarray(landcover)
    px_per_m = 1.0 / cell
    aw, ah = g.area_m

    def to_px(x: float, y: float) -> tuple[int, int]:
        return int(round((x - g.xmin) * px_per_m * 16)), int(round((g.ymin + rows * cell - y) * px_per_m * 16))

    for _ in range(2):  # roads through the scene
        a = rng.uniform(0, np.pi)
        off = rng.uniform(-0.4, 0.4) * np.array([aw, ah])
        c = np.array([g.e0, g.n0]) + off
        d = np.array([np.cos(a), np.sin(a)]) * 2000
        p1, p2 = to_px(*(c - d)), to_px(*(c + d))
        cv2.line(canvas, p1, p2, (0.36, 0.36, 0.38), int(5.0 * px_per_m), cv2.LINE_AA, shift=4)
        cv2.line(canvas, p1, p2, (0.85, 0.85, 0.80), max(1, int(0.15 * px_per_m)), cv2.LINE_AA, shift=4)
    for _ in range(int(n_fields * 1.5)):  # clutter: sheds, cars, bushes, patches
        x, y = rng.uniform(g.xmin, g.xmin + cols * cell), rng.uniform(g.ymin, g.ymin + rows * cell)
        colr = tuple(float(v) for v in rng.uniform(0.1, 0.9, 3))
        if rng.random() < 0.5:
            cv2.circle(canvas, to_px(x, y), int(rng.uniform(0.4, 2.0) * px_per_m * 16), colr, -1, cv2.LINE_AA, shift=4)
        else:
            w, h, an = rng.uniform(0.8, 4.0), rng.uniform(0.6, 2.5), rng.uniform(0, 180)
            box = cv2.boxPoints(((x, y), (w, h), an))
            pts = np.array([to_px(*p) for p in box], np.int32)
            cv2.fillPoly(canvas, [pts], colr, cv2.LINE_AA, shift=4)
    return canvas, n_fields


class _Occupancy:
    """Discs already taken by markers, buildings and trees: new objects keep clear of them."""

    def __init__(self) -> None:
        self.discs: list[tuple[float, float, float]] = []

    def free(self, x: float, y: float, r: float) -> bool:
        return all(math.hypot(x - ox, y - oy) > r + orad for ox, oy, orad in self.discs)

    def take(self, x: float, y: float, r: float) -> None:
        self.discs.append((x, y, r))


def _place_markers(
    g: _SceneGrid,
    preset: SynthPreset,
    rng: np.random.Generator,
    dictionary: str,
    marker_size_m: float,
    taken: _Occupancy,
) -> tuple[list[Marker], float]:
    """Markers on flat pads, then decoys (ids never in a GCP file); and the pads' radius."""
    fx0, fy0, fx1, fy1 = g.flight_box
    aw, ah = g.area_m
    n_ids = get_dictionary(dictionary).bytesList.shape[0]
    n_total = preset.n_markers + preset.n_decoys
    if n_total * 2 > n_ids:
        raise InputError(f"dictionary {dictionary} has too few ids for {n_total} markers")
    ids = rng.permutation(np.arange(1, n_ids))[:n_total]  # id 0 is never placed
    markers: list[Marker] = []
    pad_r = marker_size_m * 0.95 + 0.6
    spacing_m = min(8.0, math.sqrt(aw * ah / n_total) * 0.6)
    for k, mid in enumerate(ids):
        for _try in range(500):
            mx = rng.uniform(fx0 + 3, fx1 - 3)
            my = rng.uniform(fy0 + 3, fy1 - 3)
            if taken.free(mx, my, pad_r + 2.0) and all(math.hypot(mx - m.x, my - m.y) > spacing_m for m in markers):
                break
        else:
            raise InputError("could not place all markers; use fewer or a larger area")
        taken.take(mx, my, pad_r)
        decoy = k >= preset.n_markers
        markers.append(
            Marker(int(mid), f"GCP{int(mid):02d}", float(mx), float(my), 0.0, float(rng.uniform(0, 360)), decoy)
        )
    return markers, pad_r


def _buildings_and_trees(
    g: _SceneGrid, preset: SynthPreset, rng: np.random.Generator, dtm: np.ndarray, taken: _Occupancy
) -> tuple[np.ndarray, np.ndarray]:
    """Buildings (gabled or flat) and trees, clear of each other and of the markers: colours and heights."""
    X, Y = g.X, g.Y
    fx0, fy0, fx1, fy1 = g.flight_box
    objects = np.zeros((g.rows, g.cols, 3), np.float32)
    height = np.zeros((g.rows, g.cols), np.float32)
    for _ in range(preset.n_buildings):
        for _try in range(50):
            bx, by = rng.uniform(fx0 - 5, fx1 + 5), rng.uniform(fy0 - 5, fy1 + 5)
            bl, bw = rng.uniform(9, 16), rng.uniform(7, 11)
            if taken.free(bx, by, math.hypot(bl, bw) / 2 + 2):
                break
        else:
            continue
        taken.take(bx, by, math.hypot(bl, bw) / 2)
        ba = rng.uniform(0, np.pi)
        u = (X - bx) * np.cos(ba) + (Y - by) * np.sin(ba)
        v = -(X - bx) * np.sin(ba) + (Y - by) * np.cos(ba)
        inside = (np.abs(u) <= bl / 2) & (np.abs(v) <= bw / 2)
        eave = rng.uniform(4.5, 9.0)
        if rng.random() < 0.6:
            roof = eave + rng.uniform(1.5, 3.0) * (1 - np.abs(v) / (bw / 2))
        else:
            roof = np.full_like(u, eave)
        ground_top = float(dtm[inside].max()) if inside.any() else _BASE_Z
        h = ground_top + roof - dtm
        height = np.where(inside, np.maximum(height, h), height)
        rc = np.array(
            rng.choice([[0.62, 0.30, 0.22], [0.45, 0.45, 0.48], [0.70, 0.68, 0.62], [0.35, 0.30, 0.28]]), np.float32
        )
        shade = np.where(v > 0, 1.0, 0.82)[..., None].astype(np.float32)  # gable sides lit differently
        objects = np.where(inside[..., None], rc * shade, objects)
    for _ in range(preset.n_trees):
        for _try in range(50):
            tx, ty = rng.uniform(fx0 - 10, fx1 + 10), rng.uniform(fy0 - 10, fy1 + 10)
            tr = rng.uniform(2.0, 3.5)
            if taken.free(tx, ty, tr + 1):
                break
        else:
            continue
        taken.take(tx, ty, tr)
        th = rng.uniform(5, 9)
        bump = th * np.exp(-0.5 * ((X - tx) ** 2 + (Y - ty) ** 2) / (tr / 1.6) ** 2)
        crown = bump > 0.3
        height = np.where(crown, np.maximum(height, bump), height)
        objects = np.where(crown[..., None], np.array([0.20, 0.34, 0.14], np.float32), objects)
    return objects, height


def _marker_pads(
    g: _SceneGrid, dtm: np.ndarray, markers: list[Marker], pad_r: float
) -> tuple[np.ndarray, list[Marker]]:
    """Flat pads under the markers, blending into the terrain over 2 m; the markers at their pads' height."""
    placed = []
    for m in markers:
        r = np.hypot(g.X - m.x, g.Y - m.y)
        z_pad = float(sample_grid(dtm.astype(np.float32), *_cr(g.transform, m.x, m.y))[0])
        w = np.clip((r - pad_r) / 2.0, 0.0, 1.0)
        w = w * w * (3 - 2 * w)
        dtm = np.where(r < pad_r + 2.0, z_pad * (1 - w) + dtm * w, dtm)
        placed.append(replace(m, z=z_pad))
    return dtm.astype(np.float32), placed


def _cr(transform: Affine, x: float, y: float) -> tuple[np.ndarray, np.ndarray]:
    return np.array([(x - transform.c) / transform.a - 0.5]), np.array([(y - transform.f) / transform.e - 0.5])


def _footprint_size_m(preset: SynthPreset) -> tuple[float, float]:
    w = preset.altitude_m * SENSOR_WIDTH_MM / FOCAL_MM
    return w, w * preset.image_px[1] / preset.image_px[0]


# ---------------------------------------------------------------------------------------------
# Flight


@dataclass(frozen=True)
class Shot:
    """One planned and flown photo: the true pose and what the drone recorded."""

    name: str
    x: float
    y: float
    z: float
    yaw_deg: float
    pitch_deg: float
    roll_deg: float
    rec_lat: float = float("nan")
    rec_lon: float = float("nan")
    rec_gps_alt_m: float = float("nan")
    rec_rel_alt_m: float = float("nan")
    rec_abs_alt_m: float = float("nan")
    rec_yaw_deg: float = 0.0
    rec_pitch_deg: float = 0.0
    rec_roll_deg: float = 0.0
    flight_yaw_deg: float = 0.0
    flight_pitch_deg: float = 0.0
    flight_roll_deg: float = 0.0
    time: str = ""
    oblique: bool = False
    has_xmp: bool = True
    has_attitude: bool = True  # EXIF GPSImgDirection where there is no XMP
    has_gps: bool = True
    corrupt: bool = False
    blur_px: float = 0.0
    exposure_gain: float = 1.0
    exposure_time_s: float = 1.0 / 800.0
    exif_focal_mm: float = FOCAL_MM  # what EXIF says (the wrong-focal pathology lies)
    maker: str = "dji"  # whose tags carry the metadata (MAKERS)
    dropped: str = ""  # the dropped-photo pathology: how this photo was spoiled
    rtk_flag: int = -1  # the rtk pathology: DJI's RtkFlag (50 fixed, 34 float, 16 single); -1 none
    rtk_sigma_h_m: float = float("nan")  # the stated 1-sigma accuracy (RtkStdLon/Lat, GPSXYAccuracy)
    rtk_sigma_v_m: float = float("nan")
    subsec: str = ""  # EXIF SubSecTimeOriginal (the ppk pathology's stamps fall between seconds)
    # DJI's factory calibration tags (the factory-calibration pathologies): focal length and optical
    # centre (px, corner origin) and DewarpData's distortion; NaN: none written
    cal_focal_px: float = float("nan")
    cal_cx_px: float = float("nan")
    cal_cy_px: float = float("nan")
    cal_distortion: tuple[float, ...] = ()


def plan_flight(preset: SynthPreset, scene: Scene, rng: np.random.Generator) -> list[Shot]:
    """Lawnmower lines north–south across the flown area, yaw alternating; obliques around it."""
    fw, fh = _footprint_size_m(preset)
    along = fh * (1 - preset.front_overlap)
    across = fw * (1 - preset.side_overlap)
    fx0, fy0, fx1, fy1 = scene.flight_box
    n_lines = max(2, int(math.ceil((fx1 - fx0) / across)) + 1)
    n_along = max(2, int(math.ceil((fy1 - fy0) / along)) + 1)
    xs = (fx0 + fx1) / 2 + (np.arange(n_lines) - (n_lines - 1) / 2) * across
    ys = (fy0 + fy1) / 2 + (np.arange(n_along) - (n_along - 1) / 2) * along
    z = scene.home[2] + preset.altitude_m
    j = TRUE_ATTITUDE_JITTER_DEG
    shots: list[Shot] = []
    for li, x in enumerate(xs):
        heading = 0.0 if li % 2 == 0 else 180.0
        line_ys = ys if heading == 0.0 else ys[::-1]
        for y in line_ys:
            shots.append(
                Shot(
                    "",
                    float(x + rng.normal(0, 0.3)),
                    float(y + rng.normal(0, 0.3)),
                    float(z + rng.normal(0, 0.2)),
                    float(heading + rng.normal(0, j)),
                    float(-90.0 + rng.normal(0, j)),
                    float(rng.normal(0, j / 2)),
                )
            )
    for k in range(preset.n_oblique):
        a = 2 * np.pi * k / preset.n_oblique + rng.uniform(-0.2, 0.2)
        r = max(fx1 - fx0, fy1 - fy0) * 0.55
        cx, cy = (fx0 + fx1) / 2 + r * np.sin(a), (fy0 + fy1) / 2 + r * np.cos(a)
        look = (np.degrees(a) + 180.0 + rng.uniform(-40, 40)) % 360.0
        shots.append(
            Shot(
                "",
                float(cx),
                float(cy),
                float(z + rng.normal(0, 0.3)),
                float((look + 180) % 360 - 180),
                float(rng.uniform(-70.0, -45.0)),
                float(rng.normal(0, 1.0)),
                oblique=True,
            )
        )
    return shots


def fly_plan(plan: Path, scene: Scene, rng: np.random.Generator) -> tuple[list[Shot], tuple[int, int]]:
    """The photos of a ``plan`` (plan.gpkg or its folder) as this scene's shots: planned position,
    height and attitude, flown with the same wander as the built-in flight, and the pixel size of the
    plan's camera. Heights: the plan's absolute ones when it was planned on a DTM (the scene's
    truth/dtm.tif), else its altitude above the take-off over the scene's home point. The camera's
    field of view must be the synthetic camera's; its pixel count may differ (a 12 MP plan renders
    12 MP photos)."""
    from geoortho.planning.check import read_plan_photos  # here: 0.9 s (geopandas) in every render worker

    photos, summary = read_plan_photos(plan)
    cam = summary.get("camera", {})
    w, h = int(cam.get("width_px") or 0), int(cam.get("height_px") or 0)
    if (
        min(w, h) < 64
        or abs(cam.get("focal_mm", 0) / max(cam.get("sensor_width_mm", 1e-9), 1e-9) - FOCAL_MM / SENSOR_WIDTH_MM) > 1e-6
    ):
        raise InputError(
            f"the plan's camera ({cam.get('name')}, focal {cam.get('focal_mm')} mm on a "
            f"{cam.get('sensor_width_mm')} mm sensor) has not the synthetic camera's field of view "
            f"({CAMERA_MODEL}, {FOCAL_MM} mm on {SENSOR_WIDTH_MM} mm): plan with --camera {CAMERA_MODEL} "
            "(any --image-width-px/--image-height-px)",
            path=plan,
        )
    t = transformer(CRS.from_user_input(photos.crs), scene.crs)
    x, y = t.transform(photos.geometry.x.to_numpy(), photos.geometry.y.to_numpy())
    on_dtm = str(summary.get("ground", {}).get("model", "")).startswith("DTM")
    z = photos["z_m"].to_numpy() if on_dtm else scene.home[2] + photos["altitude_m"].to_numpy()
    j = TRUE_ATTITUDE_JITTER_DEG
    shots = [
        Shot(
            "",
            float(xi + rng.normal(0, 0.3)),
            float(yi + rng.normal(0, 0.3)),
            float(zi + rng.normal(0, 0.2)),
            float(_wrap180(hd + rng.normal(0, j))),
            float(pt + rng.normal(0, j)),
            float(rng.normal(0, j / 2)),
            oblique=pt > -80.0,
        )
        for xi, yi, zi, hd, pt in zip(x, y, z, photos["grid_heading_deg"], photos["pitch_deg"])
    ]
    return shots, (w, h)


def _record(shots: list[Shot], scene: Scene, preset: SynthPreset, rng: np.random.Generator) -> list[Shot]:
    """Add what the drone writes: noisy GPS, heights, gimbal and aircraft attitude, time."""
    to_ll = transformer(scene.crs, CRS.from_epsg(4326))
    bias = rng.normal(0, GPS_BIAS_SIGMA_M, 2)
    alt_bias = rng.normal(0, GPS_ALT_BIAS_SIGMA_M)
    t0 = dt.datetime(2026, 5, 14, 10, 0, 0)
    # The drone writes yaw from true north; the truth's yaw is from the grid's north.

    lon_t, lat_t = to_ll.transform(np.array([s.x for s in shots]), np.array([s.y for s in shots]))
    convergence, _ = grid_north(scene.crs, lon_t, lat_t)
    out = []
    for i, s in enumerate(shots):
        ex, ey = s.x + bias[0] + rng.normal(0, GPS_NOISE_SIGMA_M), s.y + bias[1] + rng.normal(0, GPS_NOISE_SIGMA_M)
        lon, lat = to_ll.transform(ex, ey)
        n = ATTITUDE_NOISE_SIGMA_DEG
        true_yaw = s.yaw_deg - float(convergence[i])
        fyaw = true_yaw + rng.normal(0, 2.0)  # the aircraft points a little off the gimbal
        out.append(
            replace(
                s,
                name=f"DJI_{i + 1:04d}.JPG",
                rec_lat=lat,
                rec_lon=lon,
                rec_gps_alt_m=s.z + alt_bias + rng.normal(0, 0.3),
                rec_rel_alt_m=s.z - scene.home[2] + rng.normal(0, REL_ALT_NOISE_SIGMA_M),
                rec_abs_alt_m=s.z + alt_bias + rng.normal(0, 0.3),
                rec_yaw_deg=_wrap180(true_yaw + rng.normal(0, n)),
                rec_pitch_deg=s.pitch_deg + rng.normal(0, n),
                rec_roll_deg=s.roll_deg + rng.normal(0, n),
                flight_yaw_deg=_wrap180(fyaw),
                flight_pitch_deg=float(rng.uniform(-8, -3)),
                flight_roll_deg=float(rng.normal(0, 2)),
                time=(t0 + dt.timedelta(seconds=2 * i)).strftime("%Y:%m:%d %H:%M:%S"),
                exposure_gain=float(rng.uniform(0.9, 1.1)),
            )
        )
    if preset.hard:
        idx = rng.permutation(len(out))
        for k in idx[:3]:
            out[k] = replace(out[k], has_xmp=False)
        out[idx[3]] = replace(out[idx[3]], has_gps=False)
        out[idx[4]] = replace(out[idx[4]], corrupt=True)
        for k in idx[5:9]:
            out[k] = replace(out[k], blur_px=float(rng.uniform(3, 6)))
    return out


def _place_water(scene: Scene) -> tuple[float, float, float]:
    """The pond: the open-ground spot of the flight area farthest from buildings, trees and markers
    (no random draw, so the rest of the survey is the one the seed gives without it)."""
    from scipy.ndimage import distance_transform_edt

    t = scene.transform
    cell = t.a
    taken = (scene.dsm - scene.dtm) > 0.05
    for m in scene.markers:
        c, r = scene.colrow(np.array([m.x]), np.array([m.y]))
        taken[int(round(r[0])), int(round(c[0]))] = True
    clear_m = np.asarray(distance_transform_edt(~taken)) * cell
    rows, cols = np.indices(taken.shape)
    xs, ys = (np.asarray(v) for v in t * (cols + 0.5, rows + 0.5))
    fx0, fy0, fx1, fy1 = scene.flight_box
    inside = (xs > fx0 + 0.25 * (fx1 - fx0)) & (xs < fx1 - 0.25 * (fx1 - fx0))
    inside &= (ys > fy0 + 0.25 * (fy1 - fy0)) & (ys < fy1 - 0.25 * (fy1 - fy0))
    best = np.argmax(np.where(inside, clear_m, -1.0))
    radius = min(WATER_RADIUS_M, 0.5 * float(clear_m.flat[best]), 0.15 * min(fx1 - fx0, fy1 - fy0))
    return float(xs.flat[best]), float(ys.flat[best]), radius


RTK_SIGMA_M = {50: (0.02, 0.03), 34: (0.3, 0.45), 16: (1.5, 3.0)}  # RtkFlag -> true 1-sigma H, V


def _stale_fixes(shots: list[Shot], lag_s: float, interval_s: float = 2.0) -> list[Shot]:
    """Each recorded position moved to where the camera was ``lag_s`` before its exposure: back
    along the straight path from the previous photo (the first: from the next), photos
    ``interval_s`` apart."""
    out = []
    for i, s in enumerate(shots):
        j = i - 1 if i > 0 else 1
        dx, dy = shots[j].x - s.x, shots[j].y - s.y
        share = (lag_s / interval_s) * (1.0 if i > 0 else -1.0)
        east, north = dx * share, dy * share
        out.append(
            replace(
                s,
                rec_lat=s.rec_lat + north / 111_320.0,
                rec_lon=s.rec_lon + east / (111_320.0 * math.cos(math.radians(s.rec_lat))),
            )
        )
    return out


def _stamped_early(s: Shot, lag_s: float) -> Shot:
    """The photo's time stamp ``lag_s`` before its exposure, to the millisecond."""
    stamp = dt.datetime.strptime(s.time, "%Y:%m:%d %H:%M:%S") - dt.timedelta(seconds=lag_s)
    return replace(s, time=stamp.strftime("%Y:%m:%d %H:%M:%S"), subsec=f"{stamp.microsecond // 1000:03d}")


def _write_ppk_trajectory(path: Path, scene: Scene, shots: list[Shot], rng: np.random.Generator) -> None:
    """The camera's path as RTKPOST writes it: an epoch every PPK_EPOCH_S in GPS time, the true
    centres (each exposure's, the path straight between them) with a fixed solution's noise."""
    exposures = []
    for s in shots:
        stamp = dt.datetime.strptime(s.time, "%Y:%m:%d %H:%M:%S") + dt.timedelta(milliseconds=int(s.subsec or 0))
        exposures.append((stamp + dt.timedelta(seconds=PPK_LAG_S + GPS_MINUS_UTC_S)).replace(tzinfo=dt.timezone.utc))
    t = np.array([e.timestamp() for e in exposures])
    centres = np.array([[s.x, s.y, s.z] for s in shots])
    order = np.argsort(t)
    t, centres = t[order], centres[order]
    epochs = np.arange(math.floor(t[0]) - 4.0, t[-1] + 4.0, PPK_EPOCH_S)
    xyz = np.c_[[np.interp(epochs, t, centres[:, k]) for k in range(3)]].T
    sh, sv = PPK_SIGMA_M
    xyz += np.c_[rng.normal(0, sh, (len(epochs), 2)), rng.normal(0, sv, len(epochs))]
    lon, lat = transformer(scene.crs, CRS.from_epsg(4326)).transform(xyz[:, 0], xyz[:, 1])
    lines = [
        "% program   : geoortho synth (an RTKPOST solution's layout)",
        "% pos mode  : kinematic",
        "% (lat/lon/height=WGS84/ellipsoidal,Q=1:fix,2:float,3:sbas,4:dgps,5:single,6:ppp,ns=# of satellites)",
        "%  GPST                  latitude(deg) longitude(deg)  height(m)   Q  ns   sdn(m)   sde(m)   sdu(m)  "
        "sdne(m)  sdeu(m)  sdun(m) age(s)  ratio",
    ]
    for k, e in enumerate(epochs):
        when = dt.datetime.fromtimestamp(float(e), dt.timezone.utc)
        lines.append(
            f"{when:%Y/%m/%d %H:%M:%S}.{when.microsecond // 1000:03d}   {lat[k]:.9f}   {lon[k]:.9f}  "
            f"{xyz[k, 2]:9.4f}   1  14   {sh:.4f}   {sh:.4f}   {sv:.4f}   0.0000   0.0000   0.0000   0.00  "
            f"{999.9:6.1f}"
        )
    path.write_text("\n".join(lines) + "\n")


def _rtk_indices(shots: list[Shot]) -> tuple[list[int], int]:
    """The photos of the rtk pathology without a fixed solution: three in a row mid-flight
    (float), and the one where the flight turns most (the fix lost there)."""
    n = len(shots)
    mid = max(0, int(0.4 * n) - 1)
    floats = [i for i in range(mid, min(n, mid + 3))]
    xy = np.array([[s.x, s.y] for s in shots])
    turn = np.zeros(n)
    for i in range(1, n - 1):
        a, b = xy[i] - xy[i - 1], xy[i + 1] - xy[i]
        na, nb = float(np.linalg.norm(a)), float(np.linalg.norm(b))
        if na > 0 and nb > 0:
            turn[i] = math.degrees(math.acos(float(np.clip(a @ b / (na * nb), -1.0, 1.0))))
    turn[floats] = -1.0
    lost = int(np.argmax(turn)) if turn.max() > 0 else (3 * n) // 4
    return floats, lost


def _rtk_positions(shots: list[Shot], scene: Scene, rng: np.random.Generator) -> list[Shot]:
    """Record each photo's position as an RTK receiver gives it: the true camera centre with the
    receiver's own error (its class's sigma), the sigma stated beside it, no common bias."""
    to_ll = transformer(scene.crs, CRS.from_epsg(4326))
    floats, lost = _rtk_indices(shots)
    out = []
    for i, s in enumerate(shots):
        flag = 34 if i in floats else 16 if i == lost else 50
        sh, sv = RTK_SIGMA_M[flag]
        e, n, u = rng.normal(0.0, sh), rng.normal(0.0, sh), rng.normal(0.0, sv)
        lon, lat = to_ll.transform(s.x + e, s.y + n)
        # a receiver states its deviation roughly: within -30 %..+10 % of the true one
        stated_h, stated_v = sh * float(rng.uniform(0.7, 1.1)), sv * float(rng.uniform(0.7, 1.1))
        out.append(
            replace(
                s,
                rec_lat=float(lat),
                rec_lon=float(lon),
                rec_abs_alt_m=s.z + u,
                rec_gps_alt_m=s.z + u,
                rtk_flag=flag,
                rtk_sigma_h_m=stated_h,
                rtk_sigma_v_m=stated_v,
            )
        )
    return out


def _add_cover(
    scene: Scene, pathologies: Sequence[str], rng: np.random.Generator, canopy_style: str, seed: int = 0
) -> None:
    """The wood and the car park, each on the open ground left by what stands there already; a
    wide wood and a hall over it; a hedge on what is left."""
    markers_xy = [(m.x, m.y) for m in scene.markers]
    if "wide-wood" in pathologies:
        scene.dsm, scene.objects, scene.canopy, patch = add_canopy(
            scene.transform, scene.dsm, scene.dtm, scene.objects, scene.flight_box, markers_xy, rng, canopy_style,
            radius_m=WIDE_WOOD_RADIUS_M,
        )  # fmt: skip
        scene.canopy_style = str(patch.detail["style"])
        scene.cover["wide_wood"] = patch.record()
    if "hall" in pathologies:
        scene.dsm, scene.objects, patch = add_hall(
            scene.transform, scene.dsm, scene.dtm, scene.objects, scene.flight_box, markers_xy, rng, seed % 2 == 1,
            avoid=scene.canopy,
        )  # fmt: skip
        scene.cover["hall"] = patch.record()
    if "canopy" in pathologies:
        scene.dsm, scene.objects, wood, patch = add_canopy(
            scene.transform, scene.dsm, scene.dtm, scene.objects, scene.flight_box, markers_xy, rng, canopy_style
        )
        scene.canopy = wood if scene.canopy is None else (scene.canopy | wood)
        scene.canopy_style = str(patch.detail["style"])
        scene.cover["canopy"] = patch.record()
    if "cars" in pathologies:
        scene.dsm, scene.objects, scene.landcover, patch = add_car_park(
            scene.transform, scene.dsm, scene.dtm, scene.objects, scene.landcover, scene.flight_box, markers_xy, rng
        )
        scene.cover["cars"] = patch.record()
    if "hedge" in pathologies:
        scene.dsm, scene.objects, hedge, patch = add_hedge(
            scene.transform, scene.dsm, scene.dtm, scene.objects, scene.flight_box, markers_xy, rng
        )
        scene.canopy = hedge if scene.canopy is None else (scene.canopy | hedge)
        scene.cover["hedge"] = patch.record()


def _wrap180(a: float) -> float:
    return float((a + 180.0) % 360.0 - 180.0)


def parse_pathologies(text: str) -> tuple[str, ...]:
    """Comma-separated pathology names → a tuple (an error names the unknown ones)."""
    names = tuple(n.strip() for n in (text or "").split(",") if n.strip())
    unknown = [n for n in names if n not in PATHOLOGIES]
    if unknown:
        raise InputError(f"unknown pathology {', '.join(unknown)}; choose from {', '.join(PATHOLOGIES)}")
    return names


def _apply_pathologies(
    shots: list[Shot], scene: Scene, pathologies: Sequence[str], undulation_m: float, rng: np.random.Generator
) -> list[Shot]:
    """Make the recorded metadata as wrong as the named consumer-drone pathologies make it."""
    out = list(shots)
    n = len(out)
    # a rotation of MOUNT_TILT_DEG about the horizontal axis square to its azimuth
    az = math.radians(MOUNT_TILT_AZIMUTH_DEG)
    axis = np.array([math.cos(az), -math.sin(az), 0.0])  # east-north: square to (sin az, cos az)
    mount = cv2.Rodrigues(math.radians(MOUNT_TILT_DEG) * axis)[0]
    for i, s in enumerate(out):
        orthometric = s.rec_gps_alt_m - undulation_m  # the recorded GNSS height, made orthometric
        if "no-relative-altitude" in pathologies or "altitude-drift" in pathologies:
            s = replace(s, rec_rel_alt_m=math.nan, rec_abs_alt_m=math.nan, rec_gps_alt_m=orthometric)
        if "ellipsoidal-gps" in pathologies:
            s = replace(s, rec_rel_alt_m=math.nan, rec_abs_alt_m=math.nan)
        if "altitude-drift" in pathologies:
            s = replace(
                s, rec_gps_alt_m=s.rec_gps_alt_m + DRIFT_M * i / max(1, n - 1) + (JUMP_M if i >= int(0.6 * n) else 0.0)
            )
        if "wrong-focal" in pathologies:
            s = replace(s, exif_focal_mm=FOCAL_MM * WRONG_FOCAL_FACTOR)
        if "free-heading" in pathologies and not s.oblique:
            turn = float(rng.uniform(-180.0, 180.0))
            s = replace(
                s,
                yaw_deg=_wrap180(s.yaw_deg + turn),
                rec_yaw_deg=_wrap180(s.rec_yaw_deg + turn),
                flight_yaw_deg=_wrap180(s.flight_yaw_deg + turn),
            )
        if "poor-gps" in pathologies:
            east, north = rng.normal(0.0, POOR_GPS_SIGMA_M, 2)
            s = replace(
                s,
                rec_lat=s.rec_lat + float(north) / 111_320.0,
                rec_lon=s.rec_lon + float(east) / (111_320.0 * math.cos(math.radians(s.rec_lat))),
            )
        if "no-attitude" in pathologies:
            # the true camera tilted towards one fixed direction; nothing of it in the metadata
            yaw, pitch, roll = ypr_from_rotation(mount @ rotation_from_ypr(s.yaw_deg, s.pitch_deg, s.roll_deg))
            s = replace(s, yaw_deg=yaw, pitch_deg=pitch, roll_deg=roll, has_xmp=False, has_attitude=False, maker="exif")
        if "exposure-steps" in pathologies and abs(_wrap180(s.yaw_deg)) > 90.0 and not s.oblique:
            s = replace(
                s, exposure_gain=s.exposure_gain * EXPOSURE_STEP, exposure_time_s=s.exposure_time_s * EXPOSURE_STEP
            )
        out[i] = s
    if "gps-lag" in pathologies:
        out = _stale_fixes(out, GPS_LAG_S)
    if "rtk" in pathologies:
        out = _rtk_positions(out, scene, rng)
    if "ppk" in pathologies:
        out = [_stamped_early(s, PPK_LAG_S) for s in out]
    if "dropped-photo" in pathologies:
        nadir = [i for i, s in enumerate(out) if not s.oblique]
        k = nadir[len(nadir) // 2]
        if rng.random() < 0.5:
            out[k] = replace(out[k], dropped="smeared", blur_px=DROPPED_BLUR_PX)
        else:
            out[k] = replace(out[k], dropped="blown out", exposure_gain=out[k].exposure_gain * DROPPED_GAIN)
    return out


# ---------------------------------------------------------------------------------------------
# Rendering

_SCENE: Scene | None = None


def _init_worker(scene: Scene) -> None:
    global _SCENE
    _SCENE = scene
    cv2.setNumThreads(1)


def _render_task(args: tuple[Shot, Intrinsics, bool, int, str, float, str, str, str, bool, str]) -> dict[str, Any]:
    shot, intr, hard, seed, path, glare, glare_style, blur_style, noise_style, pixels, vignetting_style = args
    assert _SCENE is not None
    return render_photo(
        _SCENE, shot, intr, hard=hard, seed=seed, path=Path(path), glare=glare, glare_style=glare_style,
        blur_style=blur_style, noise_style=noise_style, pixels=pixels, vignetting_style=vignetting_style,
    )  # fmt: skip


def render_photo(
    scene: Scene,
    shot: Shot,
    intr: Intrinsics,
    *,
    hard: bool,
    seed: int,
    path: Path | None,
    glare: float = 0.0,
    glare_style: str = "spot",
    blur_style: str = "exact",
    noise_style: str = "even",
    pixels: bool = True,
    vignetting_style: str = "quadratic",
) -> dict[str, Any]:
    """Render one photo (and write it when ``path`` is given); return its marker truth.

    ``pixels`` False: only the markers' windows are cast and drawn, on flat grey, with no
    camera effects; the marker truth is the same."""
    rng = np.random.default_rng(seed)
    pose = Pose.from_ypr((shot.x, shot.y, shot.z), shot.yaw_deg, shot.pitch_deg, shot.roll_deg)
    w, h = intr.width_px, intr.height_px
    surf = scene.surface

    def cast(cols: np.ndarray, rows: np.ndarray) -> RayHits:
        rays = pixel_rays(np.c_[cols.ravel(), rows.ravel()], intr, pose)
        return surf.intersect(pose.center, rays, max_range_m=2000.0, step_m=0.6)

    if not pixels:
        img = np.full((h, w, 3), 0.5, np.float32)

        def hits_in(y0: int, y1: int, x0: int, x1: int) -> np.ndarray:
            cols, rows = np.meshgrid(np.arange(x0, x1 + 1, dtype=np.float64), np.arange(y0, y1 + 1, dtype=np.float64))
            return cast(cols, rows).points.reshape(y1 - y0 + 1, x1 - x0 + 1, 3)

        markers = _marker_truth_and_antialias(scene, shot, intr, pose, img, hits_in)
        if path is not None:
            _write_jpeg(path, _to_bytes(img), shot, intr)
        return {"image": shot.name, "markers": markers, "blur_px": shot.blur_px, "blur_deg": 0.0}
    uu, vv = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    hits = cast(uu, vv)
    pts = hits.points
    rgb = np.full((len(pts), 3), (0.75, 0.80, 0.88), np.float32)  # sky / off-scene haze
    good = hits.hit
    rgb[good] = scene.color(pts[good, 0], pts[good, 1], pts[good, 2])
    img = rgb.reshape(h, w, 3)
    grid_pts = pts.reshape(h, w, 3)
    if scene.movers:
        depth = np.where(good, (pts - pose.center) @ pose.rotation[:, 2], np.nan).reshape(h, w)
        ground = GridSurface(scene.dtm, scene.transform, scene.crs).elevation
        draw_movers(img, list(scene.movers), _seconds_of_day(shot), intr, pose, ground, depth)
    markers = _marker_truth_and_antialias(
        scene, shot, intr, pose, img, lambda y0, y1, x0, x1: grid_pts[y0 : y1 + 1, x0 : x1 + 1]
    )

    # Camera effects: vignetting, exposure, glare, blur, noise.
    r2 = ((uu - intr.cx_px) ** 2 + (vv - intr.cy_px) ** 2) / (intr.cx_px**2 + intr.cy_px**2)
    img = img * vignetting(r2, vignetting_style)[..., None].astype(np.float32) * shot.exposure_gain
    # effects asked for by option draw from their own stream: the rest of the photo stays as without them
    opt = np.random.default_rng([seed, 1])
    for m in markers:
        if not m["inside"]:
            continue
        if hard and rng.random() < 0.3:  # sun glare on the marker
            gx, gy = m["x_px"] + rng.normal(0, 4), m["y_px"] + rng.normal(0, 4)
            amp, sigma = 0.45, m["size_px"] * 0.35
        elif not hard and glare > 0 and opt.random() < glare:
            img = img + _glare(opt, glare_style, m["x_px"], m["y_px"], m["size_px"], uu, vv)[..., None]
            m["glare"] = True
            continue
        else:
            continue
        g = np.exp(-((uu - gx) ** 2 + (vv - gy) ** 2) / (2 * sigma**2))
        img = img + amp * g[..., None].astype(np.float32)
        m["glare"] = True
    blur_deg = 0.0
    if shot.blur_px > 0:
        blur_deg = float(rng.uniform(0, 180) if hard else opt.uniform(0, 180))
        kernel = (
            motion_kernel(shot.blur_px, blur_deg)
            if hard or blur_style == "exact"
            else _other_motion_kernel(shot.blur_px, blur_deg, blur_style, opt)
        )
        img = np.asarray(cv2.filter2D(img, -1, kernel), np.float32)
    img = img + sensor_noise(rng, noise_style, img)
    if path is not None:
        _write_jpeg(path, _to_bytes(img), shot, intr)
    return {"image": shot.name, "markers": markers, "blur_px": shot.blur_px, "blur_deg": blur_deg}


def vignetting(rho: np.ndarray, style: str = "quadratic") -> np.ndarray:
    """The share of the centre's light a photo keeps at ``rho`` (the squared radius over the
    half-diagonal's), as ``style`` draws it (:data:`VignettingStyle`)."""
    rho = np.asarray(rho, np.float64)
    if style == "cos4":
        return np.asarray(np.cos(np.arctan(np.sqrt(rho) * math.tan(math.radians(25.0)))) ** 4)
    if style == "flat-drop":
        return np.asarray(np.exp(-0.14 * rho**2))
    return 1.0 - 0.25 * rho


def _seconds_of_day(shot: Shot) -> float:
    """The shot's exposure time, seconds after its day's midnight (0 without a time)."""
    if not shot.time:
        return 0.0
    stamp = dt.datetime.strptime(shot.time, "%Y:%m:%d %H:%M:%S")
    return stamp.hour * 3600.0 + stamp.minute * 60.0 + stamp.second + int(shot.subsec or 0) / 1000.0


def _to_bytes(img: np.ndarray) -> np.ndarray:
    return np.clip(img * 255.0 + 0.5, 0, 255).astype(np.uint8)


def sensor_noise(rng: np.random.Generator, style: str, img: np.ndarray) -> np.ndarray:
    """The noise of ``style`` (:data:`NoiseStyle`) to add to a rendered photo (h, w, 3; 1.0 =
    white), drawn from ``rng``."""
    if style == "shot":
        sigma = np.sqrt(SHOT_NOISE_PER_LIGHT * np.clip(img, 0.0, None) + READ_NOISE**2)
        result: np.ndarray = (rng.standard_normal(img.shape) * sigma).astype(np.float32)
        return result
    if style == "grain":
        # white noise smoothed over a couple of pixels, each channel its own (coloured blotches),
        # scaled back to its spread
        raw = rng.standard_normal(img.shape).astype(np.float32)
        smooth = cv2.GaussianBlur(raw, (0, 0), GRAIN_PX, borderType=cv2.BORDER_REFLECT)
        result = smooth * np.float32(GRAIN_NOISE / max(float(smooth.std()), 1e-9))
        return result
    return rng.normal(0, EVEN_NOISE, img.shape).astype(np.float32)


def _glare(
    rng: np.random.Generator, style: str, x_px: float, y_px: float, side_px: float, uu: np.ndarray, vv: np.ndarray
) -> np.ndarray:
    """One glare of ``style`` (:data:`GlareStyle`) near a target of ``side_px`` at (x, y): the light
    it adds to each pixel (1.0 = white)."""
    if style == "bloom":
        # a bloom 1.5-3 sides across, its core saturating, near the target
        gx, gy = x_px + rng.normal(0, 0.4) * side_px, y_px + rng.normal(0, 0.4) * side_px
        amp, sx = float(rng.uniform(0.8, 1.6)), side_px * float(rng.uniform(0.75, 1.5)) / 2.0
        sy, turn = sx, 0.0
    elif style == "sheen":
        # a soft veil, elongated and turned, that lifts the blacks without clipping
        gx, gy = x_px + rng.normal(0, 0.5) * side_px, y_px + rng.normal(0, 0.5) * side_px
        amp, sx = float(rng.uniform(0.25, 0.45)), side_px * float(rng.uniform(1.5, 2.5))
        sy, turn = sx / float(rng.uniform(2.0, 3.0)), float(rng.uniform(0, math.pi))
    else:
        # a specular spot, saturating part of the target
        gx, gy = x_px + rng.normal(0, 0.25) * side_px, y_px + rng.normal(0, 0.25) * side_px
        amp, sx = float(rng.uniform(0.5, 1.0)), side_px * float(rng.uniform(0.15, 0.3))
        sy, turn = sx, 0.0
    # only the pixels within 4 sigma: the photo is large, the glare is not
    reach = 4.0 * max(sx, sy)
    rows = slice(max(0, int(gy - reach)), max(0, int(gy + reach) + 1))
    cols = slice(max(0, int(gx - reach)), max(0, int(gx + reach) + 1))
    out = np.zeros(uu.shape, np.float32)
    du, dv = uu[rows, cols] - gx, vv[rows, cols] - gy
    a = du * math.cos(turn) + dv * math.sin(turn)
    b = -du * math.sin(turn) + dv * math.cos(turn)
    out[rows, cols] = amp * np.exp(-0.5 * ((a / sx) ** 2 + (b / sy) ** 2))
    return out


def _other_motion_kernel(length_px: float, angle_deg: float, style: str, rng: np.random.Generator) -> np.ndarray:
    """Motion blur drawn another way than :func:`motion_kernel`: ``line``, OpenCV's line rasteriser
    between whole-pixel ends (the length rounded); ``shake``, a curved path (a bow of up to a fifth
    of the length to one side) with a shutter that opens and closes gradually, centred on its mean:
    the pose is where the camera was on average over the exposure, which is where the smeared
    marker's image is (the bow's own centre put the markers' truth 0.52 px on average and up to
    1.4 px from any measure of them)."""
    r = int(math.ceil(length_px / 2)) + 2
    a = math.radians(angle_deg)
    if style == "line":
        img = np.zeros((2 * r + 1, 2 * r + 1), np.float32)
        half = max(1, round(length_px)) / 2
        ends = [(round(r + s * half * math.cos(a)), round(r - s * half * math.sin(a))) for s in (-1, 1)]
        cv2.line(img, ends[0], ends[1], 1.0, 1, cv2.LINE_8)
        result: np.ndarray = img / img.sum()
        return result
    n = max(8, int(math.ceil(16 * length_px)))
    t = (np.arange(n) + 0.5) / n - 0.5
    bow = float(rng.uniform(-0.2, 0.2)) * length_px
    along, across = t * length_px, bow * (1 - 4 * t * t)
    x = r + along * math.cos(a) - across * math.sin(a)
    y = r - along * math.sin(a) - across * math.cos(a)
    weight = np.sin(np.pi * (t + 0.5)) ** 0.5  # the shutter's ramp
    # (bilinear spreading keeps a path's mean: the kernel's centroid is then its centre exactly)
    x += r - float(np.average(x, weights=weight))
    y += r - float(np.average(y, weights=weight))
    return spread_path(x, y, weight, 2 * r + 1)


def _marker_truth_and_antialias(
    scene: Scene,
    shot: Shot,
    intr: Intrinsics,
    pose: Pose,
    img: np.ndarray,
    hits_in: Callable[[int, int, int, int], np.ndarray],
) -> list[dict[str, Any]]:
    """Exact projected marker centres, and 4×4 supersampled marker pixels (markers lie on flat pads).

    ``hits_in(y0, y1, x0, x1)``: where the rays of those pixels (inclusive) meet the scene, (rows, cols, 3)."""
    s = scene.marker_size_m
    quiet = s * target_half_extent(scene.target, next(iter(scene.marker_cells.values()), None))
    h, w = img.shape[:2]
    out = []
    sub = (np.arange(4) + 0.5) / 4 - 0.5
    for m in scene.markers:
        a = math.radians(m.angle_deg)
        ca, sa = math.cos(a), math.sin(a)

        def world(u: np.ndarray, v: np.ndarray, m: Marker = m, ca: float = ca, sa: float = sa) -> np.ndarray:
            result: np.ndarray = np.c_[m.x + u * ca + v * sa, m.y - u * sa + v * ca, np.full(len(u), m.z)]
            return result

        centre_px, depth = project_points(np.array([[m.x, m.y, m.z]]), intr, pose)
        if not np.isfinite(centre_px).all() or depth[0] <= 0:
            continue
        cx, cy = centre_px[0]
        corners = world(np.array([-s / 2, s / 2, s / 2, -s / 2]), np.array([s / 2, s / 2, -s / 2, -s / 2]))
        cpx, _ = project_points(corners, intr, pose)
        if not np.isfinite(cpx).all():
            continue
        margin = 2.0 * max(np.ptp(cpx[:, 0]), np.ptp(cpx[:, 1]))
        if not (-margin < cx < w + margin and -margin < cy < h + margin):
            continue
        inside = bool(((cpx[:, 0] >= 0) & (cpx[:, 0] <= w - 1) & (cpx[:, 1] >= 0) & (cpx[:, 1] <= h - 1)).all())
        # Occlusion: the ray to the centre must reach the pad.
        centre_visible = False
        if 0 <= cx <= w - 1 and 0 <= cy <= h - 1:
            p = hits_in(int(round(cy)), int(round(cy)), int(round(cx)), int(round(cx)))[0, 0]
            centre_visible = bool(abs(p[2] - m.z) < 0.1 and math.hypot(p[0] - m.x, p[1] - m.y) < s)
        qc = world(np.array([-quiet, quiet, quiet, -quiet]), np.array([quiet, quiet, -quiet, -quiet]))
        qpx, _ = project_points(qc, intr, pose)
        x0, x1 = int(max(0, np.floor(qpx[:, 0].min()) - 1)), int(min(w - 1, np.ceil(qpx[:, 0].max()) + 1))
        y0, y1 = int(max(0, np.floor(qpx[:, 1].min()) - 1)), int(min(h - 1, np.ceil(qpx[:, 1].max()) + 1))
        if x1 >= x0 and y1 >= y0:
            gu, gv = np.meshgrid(np.arange(x0, x1 + 1, dtype=float), np.arange(y0, y1 + 1, dtype=float))
            on_pad = np.abs(hits_in(y0, y1, x0, x1)[..., 2] - m.z) < 0.15
            su = (gu.ravel()[:, None, None] + sub[None, None, :]).repeat(4, 1)
            sv = (gv.ravel()[:, None, None] + sub[None, :, None]).repeat(4, 2)
            rays = pixel_rays(np.c_[su.ravel(), sv.ravel()], intr, pose)
            t = (m.z - pose.center[2]) / rays[:, 2]
            sp = pose.center + rays * t[:, None]
            col = scene.color(sp[:, 0], sp[:, 1], sp[:, 2]).reshape(-1, 16, 3).mean(axis=1)
            patch = img[y0 : y1 + 1, x0 : x1 + 1].reshape(-1, 3)
            mask = on_pad.ravel()
            patch[mask] = col[mask]
            img[y0 : y1 + 1, x0 : x1 + 1] = patch.reshape(y1 - y0 + 1, x1 - x0 + 1, 3)
        out.append(
            {
                "gcp": m.name,
                "marker_id": m.marker_id,
                "decoy": m.decoy,
                "x_px": float(cx),
                "y_px": float(cy),
                "corners_px": cpx.tolist(),
                "inside": inside and centre_visible,
                "in_frame": inside,
                "occluded": not centre_visible and 0 <= cx <= w - 1 and 0 <= cy <= h - 1,
                "size_px": float(np.sqrt(abs(cv2.contourArea(cpx.astype(np.float32))))),
                "glare": False,
            }
        )
    return out


def _dms(value: float) -> tuple[tuple[int, int], tuple[int, int], tuple[int, int]]:
    v = abs(value)
    d = int(v)
    m = int((v - d) * 60)
    s = (v - d - m / 60) * 3600
    return (d, 1), (m, 1), (int(round(s * 1_000_000)), 1_000_000)


def _xmp(shot: Shot) -> bytes:
    """The photo's XMP packet as its maker writes it (``shot.maker``)."""
    make = MAKER_MAKE[shot.maker]
    ns = {
        "dji": 'xmlns:drone-dji="http://www.dji.com/drone-dji/1.0/"',
        "autel": 'xmlns:drone="http://www.autelrobotics.cn/drone/1.0/"',
        "parrot": 'xmlns:drone-parrot="http://www.parrot.com/drone-parrot/1.0/" '
        'xmlns:Camera="http://pix4d.com/camera/1.0/"',
        "skydio": 'xmlns:drone-skydio="https://www.skydio.com/drone-skydio/1.0/"',
        "pix4d": 'xmlns:Camera="http://pix4d.com/camera/1.0/"',
        "sensefly": 'xmlns:Camera="http://ns.sensefly.com/Camera/1.0/"',
    }[shot.maker]
    attitude, body = _xmp_attitude(shot)
    attrs = _xmp_accuracy(shot) + _xmp_calibration(shot) + attitude
    return (
        '<?xpacket begin="\ufeff" id="W5M0MpCehiHzreSzNTczkc9d"?>\n'
        '<x:xmpmeta xmlns:x="adobe:ns:meta/">\n'
        ' <rdf:RDF xmlns:rdf="http://www.w3.org/1999/02/22-rdf-syntax-ns#">\n'
        f'  <rdf:Description rdf:about="{make} Meta Data"\n'
        f'    xmlns:tiff="http://ns.adobe.com/tiff/1.0/" {ns}\n'
        f'    tiff:Make="{make}" tiff:Model="{CAMERA_MODEL}"\n' + attrs + "  >\n" + body + "  </rdf:Description>\n"
        " </rdf:RDF>\n"
        "</x:xmpmeta>\n"
        '<?xpacket end="w"?>'
    ).encode()


def _xmp_signed(v: float) -> str:
    return f"{v:+.2f}"


def _xmp_optional(name: str, v: float) -> str:
    """An attribute line, or nothing for a value not recorded (NaN)."""
    return f'    {name}="{_xmp_signed(v)}"\n' if math.isfinite(v) else ""


def _xmp_accuracy(shot: Shot) -> str:
    """The position's stated accuracy, as each maker writes it (m, to the millimetre: a receiver's
    centimetres need it); nothing without an RTK flag."""
    if shot.rtk_flag < 0:
        return ""
    if shot.maker in ("dji", "autel"):
        p = "drone-dji" if shot.maker == "dji" else "drone"
        return (
            f'    {p}:RtkFlag="{shot.rtk_flag}"\n'
            f'    {p}:RtkStdLon="{shot.rtk_sigma_h_m:.4f}"\n'
            f'    {p}:RtkStdLat="{shot.rtk_sigma_h_m * 0.9:.4f}"\n'
            f'    {p}:RtkStdHgt="{shot.rtk_sigma_v_m:.4f}"\n'
        )
    if shot.maker in ("pix4d", "sensefly", "parrot"):
        return (
            f'    Camera:GPSXYAccuracy="{shot.rtk_sigma_h_m:.4f}"\n    Camera:GPSZAccuracy="{shot.rtk_sigma_v_m:.4f}"\n'
        )
    return ""


def _xmp_calibration(shot: Shot) -> str:
    """DJI's factory calibration (focal length, optical centre, DewarpData), when the shot has one."""
    if shot.maker != "dji" or not math.isfinite(shot.cal_focal_px):
        return ""
    return (
        f'    drone-dji:CalibratedFocalLength="{shot.cal_focal_px:.6f}"\n'
        f'    drone-dji:CalibratedOpticalCenterX="{shot.cal_cx_px:.6f}"\n'
        f'    drone-dji:CalibratedOpticalCenterY="{shot.cal_cy_px:.6f}"\n'
        f'    drone-dji:DewarpData="2026-05-01;{shot.cal_focal_px:.6f},{shot.cal_focal_px:.6f},0.000000,0.000000,'
        + ",".join(f"{v:.9f}" for v in shot.cal_distortion)
        + '"\n    drone-dji:DewarpFlag="0"\n'
    )


def _xmp_attitude(shot: Shot) -> tuple[str, str]:
    """Heights and angles as each maker writes them: (attribute lines, element lines)."""
    f, opt = _xmp_signed, _xmp_optional
    if shot.maker in ("dji", "autel"):
        p = "drone-dji" if shot.maker == "dji" else "drone"
        absolute = (
            f'    {p}:AbsoluteAltitude="{shot.rec_abs_alt_m:+.3f}"\n'
            if shot.rtk_flag >= 0 and math.isfinite(shot.rec_abs_alt_m)
            else opt(f"{p}:AbsoluteAltitude", shot.rec_abs_alt_m)
        )
        return (
            absolute
            + opt(f"{p}:RelativeAltitude", shot.rec_rel_alt_m)
            + opt(f"{p}:GimbalRollDegree", shot.rec_roll_deg)
            + opt(f"{p}:GimbalYawDegree", shot.rec_yaw_deg)
            + opt(f"{p}:GimbalPitchDegree", shot.rec_pitch_deg)
            + opt(f"{p}:FlightRollDegree", shot.flight_roll_deg)
            + opt(f"{p}:FlightYawDegree", shot.flight_yaw_deg)
            + opt(f"{p}:FlightPitchDegree", shot.flight_pitch_deg)
        ), ""
    if shot.maker == "parrot":
        # Parrot writes its NED angles and the same attitude in Pix4D's Camera: convention.
        return "", (
            f"   <drone-parrot:CameraRollDegree>{f(shot.rec_roll_deg)}</drone-parrot:CameraRollDegree>\n"
            f"   <drone-parrot:CameraPitchDegree>{f(shot.rec_pitch_deg)}</drone-parrot:CameraPitchDegree>\n"
            f"   <drone-parrot:CameraYawDegree>{f(shot.rec_yaw_deg)}</drone-parrot:CameraYawDegree>\n"
            f"   <Camera:Roll>{f(shot.rec_roll_deg)}</Camera:Roll>\n"
            f"   <Camera:Pitch>{f(shot.rec_pitch_deg + 90.0)}</Camera:Pitch>\n"
            f"   <Camera:Yaw>{f(shot.rec_yaw_deg)}</Camera:Yaw>\n"
            + (
                f"   <Camera:AboveGroundAltitude>{f(shot.rec_rel_alt_m)}</Camera:AboveGroundAltitude>\n"
                if math.isfinite(shot.rec_rel_alt_m)
                else ""
            )
        )
    if shot.maker == "skydio":
        # Several frames share the field names: the camera's is CameraOrientationNED (a struct),
        # written after a body-frame struct that must not be taken for it.
        return opt("drone-skydio:AbsoluteAltitude", shot.rec_abs_alt_m) + opt(
            "drone-skydio:RelativeAltitude", shot.rec_rel_alt_m
        ), (
            '   <drone-skydio:CameraOrientationFLU rdf:parseType="Resource">\n'
            "    <drone-skydio:Yaw>+12.00</drone-skydio:Yaw><drone-skydio:Pitch>+3.00</drone-skydio:Pitch>"
            "<drone-skydio:Roll>+1.00</drone-skydio:Roll>\n"
            "   </drone-skydio:CameraOrientationFLU>\n"
            '   <drone-skydio:CameraOrientationNED rdf:parseType="Resource">\n'
            f"    <drone-skydio:Yaw>{f(shot.rec_yaw_deg)}</drone-skydio:Yaw>\n"
            f"    <drone-skydio:Pitch>{f(shot.rec_pitch_deg)}</drone-skydio:Pitch>\n"
            f"    <drone-skydio:Roll>{f(shot.rec_roll_deg)}</drone-skydio:Roll>\n"
            "   </drone-skydio:CameraOrientationNED>\n"
        )
    # pix4d, sensefly
    roll = -shot.rec_roll_deg if shot.maker == "sensefly" else shot.rec_roll_deg
    return (
        opt("Camera:Yaw", shot.rec_yaw_deg)
        + opt("Camera:Pitch", shot.rec_pitch_deg + 90.0)
        + opt("Camera:Roll", roll)
        + opt("Camera:AboveGroundAltitude", shot.rec_rel_alt_m)
    ), ""


def _write_jpeg(path: Path, pixels: np.ndarray, shot: Shot, intr: Intrinsics) -> None:
    import piexif
    from PIL import Image

    zeroth = {
        piexif.ImageIFD.Make: MAKER_MAKE[shot.maker].encode(),
        piexif.ImageIFD.Model: CAMERA_MODEL.encode(),
        piexif.ImageIFD.Orientation: 1,
        piexif.ImageIFD.Software: b"geoortho.synth",
        piexif.ImageIFD.DateTime: shot.time.encode(),
    }
    exif = {
        piexif.ExifIFD.DateTimeOriginal: shot.time.encode(),
        **({piexif.ExifIFD.SubSecTimeOriginal: shot.subsec.encode()} if shot.subsec else {}),
        piexif.ExifIFD.FocalLength: (int(round(shot.exif_focal_mm * 100)), 100),
        piexif.ExifIFD.FocalLengthIn35mmFilm: int(round(FOCAL_35MM * shot.exif_focal_mm / FOCAL_MM)),
        piexif.ExifIFD.PixelXDimension: intr.width_px,
        piexif.ExifIFD.PixelYDimension: intr.height_px,
        piexif.ExifIFD.ExposureTime: (int(round(shot.exposure_time_s * 1e6)), 1_000_000),
        piexif.ExifIFD.FNumber: (28, 10),
        piexif.ExifIFD.ISOSpeedRatings: 100,
    }
    gps: dict[int, Any] = {}
    if shot.has_gps:
        gps = {
            piexif.GPSIFD.GPSVersionID: (2, 3, 0, 0),
            piexif.GPSIFD.GPSLatitudeRef: b"N" if shot.rec_lat >= 0 else b"S",
            piexif.GPSIFD.GPSLatitude: _dms(shot.rec_lat),
            piexif.GPSIFD.GPSLongitudeRef: b"E" if shot.rec_lon >= 0 else b"W",
            piexif.GPSIFD.GPSLongitude: _dms(shot.rec_lon),
            piexif.GPSIFD.GPSAltitudeRef: 0 if shot.rec_gps_alt_m >= 0 else 1,
            piexif.GPSIFD.GPSAltitude: (int(round(abs(shot.rec_gps_alt_m) * 1000)), 1000),
        }
        if shot.maker == "exif" and shot.has_attitude:  # no XMP: where the image top points, true north
            gps[piexif.GPSIFD.GPSImgDirectionRef] = b"T"
            gps[piexif.GPSIFD.GPSImgDirection] = (int(round(shot.rec_yaw_deg % 360.0 * 100)), 100)
    exif_bytes = piexif.dump({"0th": zeroth, "Exif": exif, "GPS": gps})
    buf = io.BytesIO()
    kwargs: dict[str, Any] = {"exif": exif_bytes, "quality": 92}
    if shot.has_xmp and shot.maker != "exif":
        kwargs["xmp"] = _xmp(shot)
    Image.fromarray(pixels).save(buf, format="JPEG", **kwargs)
    data = buf.getvalue()
    if shot.corrupt:
        data = data[: len(data) // 3]  # truncated mid-scan, as an interrupted copy leaves it
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


# ---------------------------------------------------------------------------------------------
# The algorithm


@dataclass(frozen=True)
class SynthResult:
    """Where the synthetic survey was written.

    Attributes
    ----------
    output : Path
        The survey folder.
    images : Path
        The photos (JPEG with EXIF/XMP as a DJI drone writes them).
    truth : Path
        The ground truth: poses, footprints, marker pixels, survey.json.
    gcp_file : Path
        GCP coordinates (UTM, EPSG header).
    dsm : Path
        True DSM.
    dtm : Path
        True DTM.
    ortho : Path
        True orthophoto.
    points : Path
        Point cloud sampled from the DSM.
    n_photos : int
        Number of photos.
    crs : str
        CRS of the scene.
    """

    output: Path
    images: Path
    truth: Path
    gcp_file: Path
    dsm: Path
    dtm: Path
    ortho: Path
    points: Path
    n_photos: int
    crs: str


def synth(
    output: Path,
    preset: Preset = "small",
    seed: int = 0,
    latitude_deg: float = DEFAULT_LAT,
    longitude_deg: float = DEFAULT_LON,
    dictionary: Dictionary = "DICT_4X4_50",
    marker_size_m: float = 1.0,
    workers: int = 0,
    pathology: str = "",
    plan: Path | None = None,
    target: Target = "aruco",
    blur_px: float = 0.0,
    glare: float = 0.0,
    maker: Maker = "dji",
    glare_style: GlareStyle = "spot",
    blur_style: BlurStyle = "exact",
    noise_style: NoiseStyle = "even",
    pixels: bool = True,
    vignetting_style: VignettingStyle = "quadratic",
    *,
    feedback: Feedback | None = None,
) -> SynthResult:
    """Make a synthetic drone survey with its exact ground truth.

    Renders a lawnmower flight over a scene with terrain, buildings, trees and
    coded ground markers; writes DJI-like JPEGs (EXIF GPS, DJI XMP) to
    ``images/`` and the truth (poses, footprints, marker pixels, DSM, DTM, true
    ortho, point cloud, GCP files) to ``truth/``. Deterministic for a seed.

    Parameters
    ----------
    output : Path
        Folder to write the survey into (created; existing files are replaced).
    preset : str
        tiny (a handful of small photos, unit tests), small (the demo), medium
        (benchmarks), oblique (adds oblique photos) or hard (glare, blur, cut
        markers, missing metadata, a corrupt file).
    seed : int
        Random seed; the same seed gives the same survey.
    latitude_deg : float
        Latitude of the scene centre, WGS84 degrees.
    longitude_deg : float
        Longitude of the scene centre, WGS84 degrees.
    dictionary : str
        OpenCV marker dictionary of the ground markers.
    marker_size_m : float
        Side of each marker's black square, metres (a white quiet zone of one
        cell surrounds it).
    workers : int
        Processes for rendering; 0 uses every core.
    pathology : str
        Comma-separated pathologies to build in: no-relative-altitude, ellipsoidal-gps,
        altitude-drift, wrong-focal, dsm-datum, partial-dsm, exposure-steps, free-heading,
        water, no-attitude, slope, wrong-flight-height, poor-gps, canopy, cars, rtk, ppk,
        factory-calibration, wrong-calibration, gps-lag, wide-wood, hall, hedge, breaklines,
        moving-cars, dropped-photo (truth/survey.json says what each did).
    plan : Path
        Fly this plan (a ``plan`` output folder or its plan.gpkg) instead of the preset's
        flight, over the preset's scene: the round trip that checks a plan. The plan's camera
        has the synthetic camera's lens (``--camera FC6310``); its pixel size is rendered (a
        12 MP plan gives 12 MP photos).
    target : str
        What the GCP targets look like: aruco or apriltag (coded markers of the dictionary),
        checkerboard (2 × 2 squares), cross (white bars a fifth of the side wide, painted on
        the ground) or circle (a black disc on a white board).
    blur_px : float
        Motion blur in half of the photos, from a third of this length up to it, pixels, in a
        random direction (poses.json and markers.json say which and how much).
    glare : float
        Share (0–1) of the targets in each photo under a specular glare spot that saturates
        part of them (markers.json marks each).
    glare_style : str
        How the glare is drawn: spot (a small specular spot), bloom (1.5–3 marker sides across,
        its core saturating) or sheen (a soft elongated veil of a few sides, not clipping).
    blur_style : str
        How the motion blur is drawn: exact (the path spread over the pixels it crosses), line
        (OpenCV's line rasteriser at a whole length) or shake (a curved path, the shutter ramping).
    noise_style : str
        How the sensor's noise is drawn: even (the same on every pixel, about 2 grey levels), shot
        (growing with the light: about 5 grey levels on white, 1.5 on black) or grain (blotches a
        couple of pixels across, each colour its own, as an in-camera denoiser leaves).
    vignetting_style : str
        How the lens's light falloff is drawn: quadratic (1 - 0.25 of the squared radius over the
        half-diagonal's: 25 % darker at the corners), cos4 (the cos^4 law of a 50 degree diagonal
        field: 32 %) or flat-drop (flat to half-way, 13 % at the corners, as DJI photos show).
    maker : str
        Whose metadata tags the photos carry: dji (drone-dji:), autel (drone:), parrot
        (drone-parrot: and Camera:), skydio (drone-skydio: structs), pix4d (Camera:, as MicaSense
        writes it), sensefly (Camera:, roll negated) or exif (EXIF GPS and GPSImgDirection only,
        as a fixed-wing geotagger writes it). The same attitude and position in each.
    pixels : bool
        Render the photos. Off: each photo is flat grey with only its markers drawn, and no
        camera effects, in a fraction of the time; every tag and every truth file is the same
        (survey.json says so). For the tools that read only the metadata (footprints, plans).

    Returns
    -------
    SynthResult
        Paths of the images, the truth folder and its main files.
    """
    fb = as_feedback(feedback)
    # every option checked before an earlier survey in the folder is cleared
    _check_options(preset, latitude_deg, longitude_deg, target, dictionary, glare, blur_px, maker)
    _check_styles(
        glare_style=glare_style, blur_style=blur_style, noise_style=noise_style, vignetting_style=vignetting_style
    )
    if not pixels and (blur_px or glare or PRESETS[preset].hard):
        raise InputError("blur, glare and the hard preset are drawn on the pixels: give them without --no-pixels")
    pathologies = parse_pathologies(pathology)
    p = replace(PRESETS[preset])
    output = Path(output)
    images_dir = output / "images"
    truth_dir = output / "truth"
    _clear_earlier_survey(images_dir, truth_dir)
    images_dir.mkdir(parents=True, exist_ok=True)
    truth_dir.mkdir(parents=True, exist_ok=True)
    step_scene, step_render, step_truth = split(fb, [1, 8, 2])
    rng = np.random.default_rng(seed)
    scene = _scene(p, rng, latitude_deg, longitude_deg, dictionary, marker_size_m, target, pathologies, seed)
    step_scene.progress(0.5)
    p, shots, undulation = _flight(
        p, scene, plan, rng, maker, pathologies, seed, blur_px, (latitude_deg, longitude_deg)
    )
    w, h = p.image_px
    intr = Intrinsics.from_sensor(w, h, FOCAL_MM, SENSOR_WIDTH_MM, distortion=p.distortion)
    shots = _with_calibration(shots, intr, p, pathologies)
    fb.info(
        f"synth {preset}: {len(shots)} photos of {w}x{h} px over {p.area_m[0]:.0f}x{p.area_m[1]:.0f} m "
        f"in {scene.crs.name}"
    )
    step_scene.progress(1.0)

    tasks = [
        (s, intr, p.hard, seed * 100003 + i, str(images_dir / s.name), glare, glare_style, blur_style)
        + (noise_style, pixels, vignetting_style)
        for i, s in enumerate(shots)
    ]
    results: list[dict[str, Any]] = map_ordered(
        _render_task, tasks, workers=workers, initializer=_init_worker, initargs=(scene,), feedback=step_render
    )
    # how the degradations were drawn, beside the survey's truth
    degradations = (
        {
            "glare": glare,
            "glare_style": glare_style,
            "blur_px": blur_px,
            "blur_style": blur_style,
            "noise_style": noise_style,
            "vignetting_style": vignetting_style,
        }
        if glare or blur_px or noise_style != "even" or vignetting_style != "quadratic"
        else None
    )
    _write_truth(
        truth_dir, scene, shots, intr, p, results, seed, step_truth, pathologies, undulation, degradations, pixels
    )
    return SynthResult(
        output=output,
        images=images_dir,
        truth=truth_dir,
        gcp_file=truth_dir / "gcp_utm.txt",
        dsm=truth_dir / "dsm.tif",
        dtm=truth_dir / "dtm.tif",
        ortho=truth_dir / "ortho.tif",
        points=truth_dir / "points.laz",
        n_photos=len(shots),
        crs=f"EPSG:{scene.crs.to_epsg()}",
    )


def _scene(
    p: SynthPreset,
    rng: np.random.Generator,
    lat: float,
    lon: float,
    dictionary: str,
    marker_size_m: float,
    target: str,
    pathologies: tuple[str, ...],
    seed: int,
) -> Scene:
    """The preset's scene, with the cover and the water its pathologies ask for."""
    scene = build_scene(
        p,
        rng,
        lat=lat,
        lon=lon,
        dictionary=dictionary,
        marker_size_m=marker_size_m,
        slope_deg=SLOPE_DEG if "slope" in pathologies else 0.0,
        bank_deg=(45.0 if seed % 2 == 0 else 30.0) if "breaklines" in pathologies else 0.0,
    )
    scene.target = target
    if any(k in pathologies for k in ("canopy", "cars", "wide-wood", "hall", "hedge")):
        _add_cover(
            scene, pathologies, np.random.default_rng([seed, 17]), CANOPY_STYLES[seed % len(CANOPY_STYLES)], seed
        )
    if "water" in pathologies:
        scene.water = _place_water(scene)
    if "moving-cars" in pathologies:
        scene.movers = tuple(
            place_movers(
                scene.dsm, scene.dtm, scene.transform, scene.flight_box, [(m.x, m.y) for m in scene.markers],
                np.random.default_rng([seed, 23]), "car" if seed % 2 == 0 else "box",
            )
        )  # fmt: skip
    return scene


def _flight(
    p: SynthPreset,
    scene: Scene,
    plan: Path | None,
    rng: np.random.Generator,
    maker: str,
    pathologies: tuple[str, ...],
    seed: int,
    blur_px: float,
    lat_lon_deg: tuple[float, float],
) -> tuple[SynthPreset, list[Shot], float]:
    """The shots flown (the preset's flight or a plan's, which sets the pixel size) and recorded
    by the drone with the pathologies and the blur; the preset as flown, the shots and the geoid
    undulation the pathologies used (0 without any)."""
    if plan is not None:
        planned, image_px = fly_plan(Path(plan), scene, rng)
        p = replace(p, image_px=image_px)
    else:
        planned = plan_flight(p, scene, rng)
    shots = [replace(s, maker=maker) for s in _record(planned, scene, p, rng)]
    undulation = 0.0
    if pathologies:
        undulation = float(geoid_undulation_m(lat_lon_deg[1], lat_lon_deg[0]))
        shots = _apply_pathologies(shots, scene, pathologies, undulation, np.random.default_rng(seed + 11))
    return p, _with_blur(shots, blur_px, seed), undulation


def _check_options(
    preset: str, lat: float, lon: float, target: str, dictionary: str, glare: float, blur_px: float, maker: str
) -> None:
    if preset not in PRESETS:
        raise InputError(f"unknown preset {preset!r}; choose one of {', '.join(PRESETS)}")
    if not -80 <= lat <= 84 or not -180 <= lon <= 180:
        raise InputError("latitude/longitude outside the UTM domain")
    if target not in TARGETS:
        raise InputError(f"unknown target {target!r}; choose one of {', '.join(TARGETS)}")
    if target == "apriltag" and "APRILTAG" not in str(dictionary).upper():
        raise InputError(f"target apriltag needs an AprilTag dictionary (e.g. DICT_APRILTAG_36H11), not {dictionary}")
    if not 0.0 <= glare <= 1.0 or not 0.0 <= blur_px <= 200.0:
        raise InputError("glare is a share 0–1 and blur_px 0–200 pixels")
    if maker not in MAKERS:
        raise InputError(f"unknown maker {maker!r}; choose one of {', '.join(MAKERS)}")


def _check_styles(**styles: str) -> None:
    """Each degradation's style is one of its kind's (an unknown one would be drawn as the default)."""
    kinds = {
        "glare_style": GlareStyle,
        "blur_style": BlurStyle,
        "noise_style": NoiseStyle,
        "vignetting_style": VignettingStyle,
    }
    for name, style in styles.items():
        if style not in get_args(kinds[name]):
            raise InputError(f"unknown {name} {style!r}; choose one of {', '.join(get_args(kinds[name]))}")


def _with_blur(shots: list[Shot], blur_px: float, seed: int) -> list[Shot]:
    """Half the photos motion-blurred, each by a length drawn between a third of ``blur_px`` and it."""
    if blur_px <= 0:
        return shots
    rng = np.random.default_rng([seed, 13])
    return [replace(s, blur_px=float(rng.uniform(blur_px / 3, blur_px))) if rng.random() < 0.5 else s for s in shots]


def _with_calibration(shots: list[Shot], intr: Intrinsics, p: SynthPreset, pathologies: tuple[str, ...]) -> list[Shot]:
    """The maker's calibration tags, true or (wrong-calibration) with a focal length off."""
    if "factory-calibration" not in pathologies and "wrong-calibration" not in pathologies:
        return shots
    factor = WRONG_CALIBRATION_FACTOR if "wrong-calibration" in pathologies else 1.0
    return [
        replace(
            s,
            cal_focal_px=intr.focal_px * factor,
            cal_cx_px=intr.cx_px + 0.5,  # corner origin, as DJI writes it
            cal_cy_px=intr.cy_px + 0.5,
            cal_distortion=tuple((*p.distortion, 0.0, 0.0, 0.0, 0.0, 0.0)[:5]),
        )
        for s in shots
    ]


def true_footprint(
    scene: Scene, shot: Shot, intr: Intrinsics, per_side: int = 40, max_range_m: float = 1000.0
) -> tuple[np.ndarray, bool]:
    """The image border cast onto the DSM: polygon vertices (N, 2) and whether any ray missed."""
    pose = Pose.from_ypr((shot.x, shot.y, shot.z), shot.yaw_deg, shot.pitch_deg, shot.roll_deg)
    border = intr.border_pixels(per_side)
    hits = scene.surface.intersect(
        pose.center, pixel_rays(border, intr, pose), max_range_m=max_range_m, step_m=scene.transform.a
    )
    return hits.points[:, :2], not bool(hits.hit.all())


def _clear_earlier_survey(images_dir: Path, truth_dir: Path) -> None:
    """Remove the photos of an earlier synth in this folder (its truth/poses.json names them), so
    that none is left over; a file synth did not make is never deleted: refused instead."""
    if not images_dir.is_dir():
        return
    made: set[str] = set()
    try:
        made = {str(p["image"]) for p in json.loads((truth_dir / "poses.json").read_text())}
    except (OSError, ValueError, TypeError, KeyError):
        pass
    present = [f for f in images_dir.iterdir() if not f.name.startswith(".")]
    foreign = sorted(f.name for f in present if f.name not in made)
    if foreign:
        raise InputError(
            f"holds {len(foreign)} file(s) an earlier synth did not make ({', '.join(foreign[:3])}"
            f"{', ...' if len(foreign) > 3 else ''}): give a new or empty output folder",
            path=images_dir,
        )
    for f in present:
        f.unlink()


def _write_truth(
    truth: Path,
    scene: Scene,
    shots: list[Shot],
    intr: Intrinsics,
    p: SynthPreset,
    results: list[dict[str, Any]],
    seed: int,
    fb: Feedback,
    pathologies: Sequence[str] = (),
    undulation_m: float = 0.0,
    degradations: dict[str, Any] | None = None,
    pixels: bool = True,
) -> None:
    """Every truth product: rasters, poses and footprints, GCP files, survey.json, ortho, point cloud."""
    steps = split(fb, [1, 1, 3, 2, 1])
    _write_truth_rasters(truth, scene, pathologies, undulation_m)
    steps[0].progress(1.0)
    _write_poses_and_footprints(truth, scene, shots, intr, results)
    steps[1].progress(1.0)
    _write_gcp_files(truth, scene)
    if "ppk" in pathologies:
        _write_ppk_trajectory(truth / "trajectory.pos", scene, shots, np.random.default_rng([seed, 23]))
    dropped = {"image": s.name, "how": s.dropped} if (s := next((s for s in shots if s.dropped), None)) else None
    rtk = (
        {
            "float": [s.name for s in shots if s.rtk_flag == 34],
            "lost_fix": [s.name for s in shots if s.rtk_flag == 16],
            "true_sigma_m": {"fixed": RTK_SIGMA_M[50], "float": RTK_SIGMA_M[34], "single": RTK_SIGMA_M[16]},
        }
        if any(s.rtk_flag >= 0 for s in shots)
        else None
    )
    _write_survey_json(
        truth, scene, intr, p, seed, pathologies, undulation_m, shots[0].maker if shots else "dji", dropped, rtk,
        degradations, pixels,
    )  # fmt: skip
    steps[2].progress(1.0)
    _write_true_ortho(truth / "ortho.tif", scene, p.ortho_cell_m, steps[3])
    _write_points(truth / "points.laz", scene, p, np.random.default_rng(seed + 7))
    steps[4].progress(1.0)


def _write_truth_rasters(truth: Path, scene: Scene, pathologies: Sequence[str], undulation_m: float) -> None:
    """The true DSM and DTM, and the DSMs the pathologies ask for (another datum, a partial one)."""

    write_cog(truth / "dsm.tif", scene.dsm, transform=scene.transform, crs=scene.crs, nodata=NODATA)
    write_cog(truth / "dtm.tif", scene.dtm, transform=scene.transform, crs=scene.crs, nodata=NODATA)
    if "dsm-datum" in pathologies:
        write_cog(
            truth / "dsm_other_datum.tif",
            scene.dsm - np.float32(undulation_m),
            transform=scene.transform,
            crs=scene.crs,
            nodata=NODATA,
        )
    if "partial-dsm" in pathologies:
        fx0, _, fx1, _ = scene.flight_box
        c0 = int((fx0 + 0.4 * (fx1 - fx0) - scene.transform.c) / scene.transform.a)
        write_cog(
            truth / "dsm_partial.tif",
            scene.dsm[:, c0:],
            transform=scene.transform @ Affine.translation(c0, 0),
            crs=scene.crs,
            nodata=NODATA,
        )


def _pose_record(s: Shot) -> dict[str, Any]:
    R = rotation_from_ypr(s.yaw_deg, s.pitch_deg, s.roll_deg)
    return {
        "image": s.name,
        "x": s.x,
        "y": s.y,
        "z": s.z,
        "yaw_deg": s.yaw_deg,
        "pitch_deg": s.pitch_deg,
        "roll_deg": s.roll_deg,
        "rotation_world_from_camera": R.tolist(),
        "recorded": {
            "latitude_deg": s.rec_lat,
            "longitude_deg": s.rec_lon,
            "gps_altitude_m": s.rec_gps_alt_m,
            "relative_altitude_m": s.rec_rel_alt_m,
            "absolute_altitude_m": s.rec_abs_alt_m,
            "gimbal_yaw_deg": s.rec_yaw_deg,
            "gimbal_pitch_deg": s.rec_pitch_deg,
            "gimbal_roll_deg": s.rec_roll_deg,
            "flight_yaw_deg": s.flight_yaw_deg,
        },
        "oblique": s.oblique,
        "has_xmp": s.has_xmp,
        "has_gps": s.has_gps,
        "corrupt": s.corrupt,
        "blur_px": s.blur_px,
        "exposure_gain": s.exposure_gain,
        "exposure_time_s": s.exposure_time_s,
        "exif_focal_mm": s.exif_focal_mm,
    }


def _write_poses_and_footprints(
    truth: Path, scene: Scene, shots: list[Shot], intr: Intrinsics, results: list[dict[str, Any]]
) -> None:
    import geopandas as gpd
    import shapely

    polys, clipped = [], []
    for s in shots:
        ring, clip = true_footprint(scene, s, intr)
        polys.append(shapely.make_valid(shapely.Polygon(ring)))
        clipped.append(clip)
    gdf = gpd.GeoDataFrame(
        {"image": [s.name for s in shots], "clipped": clipped, "oblique": [s.oblique for s in shots]},
        geometry=polys,
        crs=scene.crs,
    )
    write_vector(truth / "footprints.gpkg", {"footprints": gdf})
    write_json(truth / "poses.json", [_pose_record(s) for s in shots])
    write_json(truth / "markers.json", results)


def _write_gcp_files(truth: Path, scene: Scene) -> None:
    """GCP files as a surveyor hands them over: UTM with an EPSG line, WGS84 text and CSV."""

    gcps = [m for m in scene.markers if not m.decoy]
    to_ll = transformer(scene.crs, CRS.from_epsg(4326))
    utm_lines = [f"EPSG:{scene.crs.to_epsg()}"] + [f"{m.name} {m.x:.4f} {m.y:.4f} {m.z:.4f}" for m in gcps]
    write_text(truth / "gcp_utm.txt", "\n".join(utm_lines) + "\n")
    ll_lines = ["EPSG:4979"]
    csv_lines = ["name,lat,lon,alt"]
    for m in gcps:
        lon, lat = to_ll.transform(m.x, m.y)
        ll_lines.append(f"{m.name} {lat:.9f} {lon:.9f} {m.z:.4f}")
        csv_lines.append(f"{m.name},{lat:.9f},{lon:.9f},{m.z:.4f}")
    write_text(truth / "gcp_wgs84.txt", "\n".join(ll_lines) + "\n")
    write_text(truth / "gcp_wgs84.csv", "\n".join(csv_lines) + "\n")


def renderer_digest() -> str:
    """A digest of the synthetic renderer's source: a survey written by other code is drawn again."""
    import hashlib

    h = hashlib.sha256()
    for f in sorted(Path(__file__).parent.glob("*.py")):
        h.update(f.read_bytes())
    return h.hexdigest()[:16]


def existing_survey(output: Path, preset: str, seed: int) -> SynthResult | None:
    """The survey ``synth(output, preset=preset, seed=seed)`` wrote earlier, complete and drawn by
    this renderer with no pathology; None when there is none. Complete: its point cloud, the last
    file written, is newer than every photo and there is a photo for every pose."""
    output = Path(output)
    truth, images = output / "truth", output / "images"
    try:
        info = json.loads((truth / "survey.json").read_text())
        poses = json.loads((truth / "poses.json").read_text())
        photos = sorted(images.glob("*.JPG"))
        points_time = (truth / "points.laz").stat().st_mtime
        newest_photo = max(f.stat().st_mtime for f in photos) if photos else math.inf
    except (OSError, ValueError):
        return None
    same = (
        info.get("preset", {}).get("name") == preset
        and info.get("seed") == seed
        and not info.get("pathologies")
        and info.get("renderer") == renderer_digest()
    )
    files = [truth / n for n in ("gcp_utm.txt", "dsm.tif", "dtm.tif", "ortho.tif")]
    if not same or len(photos) != len(poses) or newest_photo > points_time or not all(f.is_file() for f in files):
        return None
    return SynthResult(
        output=output, images=images, truth=truth, gcp_file=files[0], dsm=files[1], dtm=files[2], ortho=files[3],
        points=truth / "points.laz", n_photos=len(photos), crs=info["crs"],
    )  # fmt: skip


def _write_survey_json(
    truth: Path,
    scene: Scene,
    intr: Intrinsics,
    p: SynthPreset,
    seed: int,
    pathologies: Sequence[str],
    undulation_m: float,
    maker: str = "dji",
    dropped: dict[str, str] | None = None,
    rtk: dict[str, Any] | None = None,
    degradations: dict[str, Any] | None = None,
    pixels: bool = True,
) -> None:

    write_json(
        truth / "survey.json",
        {
            "preset": asdict(p),
            "seed": seed,
            "crs": f"EPSG:{scene.crs.to_epsg()}",
            "vertical": "WGS84 ellipsoidal height, m",
            "pixel_convention": "(0,0) is the centre of the top-left pixel (OpenCV, OpenDroneMap gcp_list.txt)",
            "attitude_convention": "yaw clockwise from north, pitch -90 nadir, roll right-down positive; "
            "poses.json's yaw_deg from the CRS's grid north, the photos' recorded yaw from true north",
            "camera": {
                "make": MAKER_MAKE[maker],
                "model": CAMERA_MODEL,
                "sensor_width_mm": SENSOR_WIDTH_MM,
                "sensor_height_mm": SENSOR_HEIGHT_MM,
                "focal_mm": FOCAL_MM,
                "focal_35mm": FOCAL_35MM,
                "width_px": intr.width_px,
                "height_px": intr.height_px,
                "focal_px": intr.focal_px,
                "cx_px": intr.cx_px,
                "cy_px": intr.cy_px,
                "distortion": list(p.distortion),
            },
            "pathologies": {k: PATHOLOGIES[k] for k in pathologies},
            **({"water": dict(zip(("x", "y", "radius_m"), scene.water))} if scene.water is not None else {}),
            **({"cover": scene.cover} if scene.cover else {}),
            **({"movers": [m.record() for m in scene.movers]} if scene.movers else {}),
            **(
                {"mount_tilt": {"deg": MOUNT_TILT_DEG, "azimuth_deg": MOUNT_TILT_AZIMUTH_DEG}}
                if "no-attitude" in pathologies
                else {}
            ),
            **({"slope": {"deg": SLOPE_DEG, "azimuth_deg": SLOPE_AZIMUTH_DEG}} if "slope" in pathologies else {}),
            **({"dropped_photo": dropped} if dropped else {}),
            **({"rtk": rtk} if rtk else {}),
            **({"degradations": degradations} if degradations else {}),
            **({"pixels": "markers only, on flat grey, without camera effects"} if not pixels else {}),
            **({"gps_lag_s": GPS_LAG_S} if "gps-lag" in pathologies else {}),
            **(
                {"ppk": {"pos": "trajectory.pos", "lag_s": PPK_LAG_S, "gps_minus_camera_clock_s": GPS_MINUS_UTC_S}}
                if "ppk" in pathologies
                else {}
            ),
            **(
                {"user_flight_height_m": round(p.altitude_m * WRONG_FLIGHT_HEIGHT_FACTOR, 1)}
                if "wrong-flight-height" in pathologies
                else {}
            ),
            "flight_height_m": p.altitude_m,
            "renderer": renderer_digest(),
            "geoid_undulation_m": undulation_m,
            "home": {"x": scene.home[0], "y": scene.home[1], "ground_z": scene.home[2]},
            "flight_box": list(scene.flight_box),
            "gsd_cm_at_home_height": p.altitude_m * SENSOR_WIDTH_MM / FOCAL_MM / intr.width_px * 100,
            "marker_size_m": scene.marker_size_m,
            "dictionary": scene.dictionary,
            "target": scene.target,
            "markers": [asdict(m) for m in scene.markers],
            "error_model": {
                "gps_bias_sigma_m": GPS_BIAS_SIGMA_M,
                "gps_noise_sigma_m": GPS_NOISE_SIGMA_M,
                "gps_alt_bias_sigma_m": GPS_ALT_BIAS_SIGMA_M,
                "relative_altitude_sigma_m": REL_ALT_NOISE_SIGMA_M,
                "attitude_sigma_deg": ATTITUDE_NOISE_SIGMA_DEG,
            },
        },
    )


def _write_true_ortho(path: Path, scene: Scene, cell_m: float, progress: Feedback) -> None:
    """The true orthophoto over the flown area (plus a little), coloured from the scene itself."""

    fx0, fy0, fx1, fy1 = scene.flight_box
    pad = 15.0
    oc = cell_m
    ox0, oy1 = math.floor((fx0 - pad) / oc) * oc, math.ceil((fy1 + pad) / oc) * oc
    ocols = int(round((fx1 + pad - ox0) / oc))
    orows = int(round((oy1 - (fy0 - pad)) / oc))
    ot = Affine(oc, 0, ox0, 0, -oc, oy1)
    ortho = np.empty((3, orows, ocols), np.uint8)
    band = max(1, 2_000_000 // ocols)
    surf = scene.surface
    for r0 in range(0, orows, band):
        r1 = min(orows, r0 + band)
        cc, rr = np.meshgrid(np.arange(ocols) + 0.5, np.arange(r0, r1) + 0.5)
        x = ox0 + cc.ravel() * oc
        y = oy1 - rr.ravel() * oc
        z = surf.elevation(x, y)
        col = scene.color(x, y, z)
        ortho[:, r0:r1] = np.clip(col.T.reshape(3, r1 - r0, ocols) * 255 + 0.5, 0, 255).astype(np.uint8)
        progress.progress(r1 / orows)
    write_cog(path, ortho, transform=ot, crs=scene.crs, compress="DEFLATE", band_names=("red", "green", "blue"))


def _write_points(path: Path, scene: Scene, p: SynthPreset, rng: np.random.Generator) -> None:

    fx0, fy0, fx1, fy1 = scene.flight_box
    pad = 20.0
    area = (fx1 - fx0 + 2 * pad) * (fy1 - fy0 + 2 * pad)
    n = int(area * p.points_per_m2)
    x = rng.uniform(fx0 - pad, fx1 + pad, n)
    y = rng.uniform(fy0 - pad, fy1 + pad, n)
    surf = scene.surface
    z = surf.elevation(x, y)
    ground = scene.dtm
    c, r = scene.colrow(x, y)
    g = sample_grid(ground, c, r)
    hag = z - g
    cls = np.where(hag < 0.15, 2, np.where(hag > 2.0, 6, 1)).astype(np.uint8)
    # Trees are objects with the tree colour: class 5 (high vegetation).
    obj = _remap3(scene.objects, c.astype(np.float32), r.astype(np.float32))
    tree = (cls != 2) & (np.abs(obj[:, 1] - 0.34) < 0.02) & (np.abs(obj[:, 0] - 0.20) < 0.02)
    cls[tree] = 5
    rgb = scene.color(x, y, z)
    write_las(path, np.c_[x, y, z], scene.crs, rgb=rgb, classification=cls)
