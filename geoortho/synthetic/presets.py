"""What synth draws from: the presets, the camera, the makers' metadata styles, the GPS and attitude
errors, and the pathologies with their sizes."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, get_args

from geoortho.errors import InputError

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
# with each maker family's tags and conventions (geoortho.photos.tags.ATTITUDE_FAMILIES names the documents).
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

#: The error model as survey.json records it.
ERROR_MODEL = {
    "gps_bias_sigma_m": GPS_BIAS_SIGMA_M,
    "gps_noise_sigma_m": GPS_NOISE_SIGMA_M,
    "gps_alt_bias_sigma_m": GPS_ALT_BIAS_SIGMA_M,
    "relative_altitude_sigma_m": REL_ALT_NOISE_SIGMA_M,
    "attitude_sigma_deg": ATTITUDE_NOISE_SIGMA_DEG,
}


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
    "stockpiles": "a graded yard on open ground: a cone of gravel (27 deg), an irregular pile of two heaps run "
    "together (smooth for an even seed, lumpy spoil for an odd one) and a pit dug at the same slope (at most 1.5 m "
    "deep), parts of the ground (DSM and DTM); survey.json: cover.stockpiles.items, each with its centre, a radius "
    "that takes in its foot, and its true volume",
    "second-epoch": "the same site flown again later (the same seed gives the same scene): a pile moved (the "
    "stockpiles' cone carted off, where the yard has one, else a new pile), a trench dug (sides at 27 deg, 1 m deep) "
    "and a new building, on open ground; and the flight's GPS 1.6 m east, 1.2 m south and 0.5 m up of the first's; "
    "survey.json: cover.second_epoch (gps_offset_m, and items, each with its kind, cut or fill, centre, a radius "
    "that takes it in, and its true volume)",
    "breaklines": f"a bank {BANK_M[0]:g} m high across the scene (45 deg for an even seed, 30 for an odd one) and a "
    f"road cutting {CUTTING_M[1]:g} m wide, {CUTTING_M[0]:g} m deep with 45 deg sides: the ground's own sharp edges; "
    "survey.json: cover.breaklines",
    "facades": "the buildings' walls painted as facades, their colours changing with the height above the "
    "ground as no roof's or ground's do: storeys of windows (plaster, windows 1.2 m wide and 1.35 m high, "
    "2.4 m apart, in each 3 m storey) for an even seed, cladding in courses (red and dark brown, each 1 m high, "
    "pale joints) for an odd one; survey.json: facades (the style, and each building's rectangle: centre, length "
    "along its angle, width, eave height); the truth's ortho and DSM are unchanged",
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


def parse_pathologies(text: str) -> tuple[str, ...]:
    """Comma-separated pathology names → a tuple (an error names the unknown ones)."""
    names = tuple(n.strip() for n in (text or "").split(",") if n.strip())
    unknown = [n for n in names if n not in PATHOLOGIES]
    if unknown:
        raise InputError(f"unknown pathology {', '.join(unknown)}; choose from {', '.join(PATHOLOGIES)}")
    return names
