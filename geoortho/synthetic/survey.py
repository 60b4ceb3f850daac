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

import json
import math
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, get_args

import numpy as np

from geoortho.core.camera import Intrinsics
from geoortho.core.crs import geoid_undulation_m
from geoortho.core.parallel import map_ordered
from geoortho.errors import InputError
from geoortho.feedback import Feedback, as_feedback, split
from geoortho.gcp.markers import (
    TARGETS,
    Dictionary,
    Target,
)
from geoortho.synthetic.cover import CANOPY_STYLES
from geoortho.synthetic.flight import (
    Shot,
    apply_pathologies,
    drone_records,
    fly_plan,
    plan_flight,
    with_blur,
    with_calibration,
)
from geoortho.synthetic.movers import place_movers
from geoortho.synthetic.presets import (
    DEFAULT_LAT,
    DEFAULT_LON,
    FOCAL_MM,
    MAKERS,
    PATHOLOGIES,
    PRESETS,
    SENSOR_WIDTH_MM,
    SLOPE_DEG,
    BlurStyle,
    GlareStyle,
    Maker,
    NoiseStyle,
    Preset,
    SynthPreset,
    VignettingStyle,
    parse_pathologies,
)
from geoortho.synthetic.render import init_render_worker, render_task
from geoortho.synthetic.scene import FACADE_STYLES, Scene, add_cover, build_scene, place_water
from geoortho.synthetic.truth import renderer_digest, write_truth

__all__ = ["PRESETS", "PATHOLOGIES", "SynthPreset", "SynthResult", "synth", "build_scene", "plan_flight"]


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
        factory-calibration, wrong-calibration, gps-lag, wide-wood, hall, hedge, stockpiles, breaklines,
        moving-cars, dropped-photo, second-epoch, facades (truth/survey.json says what each did).
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
    shots = with_calibration(shots, intr, p, pathologies)
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
        render_task, tasks, workers=workers, initializer=init_render_worker, initargs=(scene,), feedback=step_render
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
    write_truth(
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
    if any(k in pathologies for k in ("canopy", "cars", "wide-wood", "hall", "hedge", "stockpiles", "second-epoch")):
        add_cover(scene, pathologies, np.random.default_rng([seed, 17]), CANOPY_STYLES[seed % len(CANOPY_STYLES)], seed)
    if "facades" in pathologies:
        scene.facade_style = FACADE_STYLES[seed % len(FACADE_STYLES)]
    if "water" in pathologies:
        scene.water = place_water(scene)
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
    shots = [replace(s, maker=maker) for s in drone_records(planned, scene, p, rng)]
    undulation = 0.0
    if pathologies:
        undulation = float(geoid_undulation_m(lat_lon_deg[1], lat_lon_deg[0]))
        shots = apply_pathologies(shots, scene, pathologies, undulation, np.random.default_rng(seed + 11))
    return p, with_blur(shots, blur_px, seed), undulation


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
