"""The specs: one per algorithm. Help texts come from the core functions' docstrings."""

from __future__ import annotations

from ..demo import demo
from ..markers import DICTIONARIES
from ..synth import PRESETS, synth
from .spec import Algorithm, Output, Param

PRESET_CHOICES = tuple(PRESETS)

ALGORITHMS: tuple[Algorithm, ...] = (
    Algorithm(
        id="synth", title="Synthetic survey", group="Testing", function=synth,
        params=(
            Param("output", "folder", output=True),
            Param("preset", "enum", "small", choices=PRESET_CHOICES),
            Param("seed", "integer", 0, minimum=0),
            Param("latitude_deg", "number", synth.__defaults__[2], unit="deg", minimum=-80, maximum=84,
                  advanced=True),
            Param("longitude_deg", "number", synth.__defaults__[3], unit="deg", minimum=-180, maximum=180,
                  advanced=True),
            Param("dictionary", "enum", "DICT_4X4_50", choices=DICTIONARIES, advanced=True),
            Param("marker_size_m", "number", 1.0, unit="m", minimum=0.2, maximum=5.0, advanced=True),
            Param("workers", "integer", 0, minimum=0, advanced=True),
        ),
        outputs=(
            Output("output", "folder", "the survey folder"),
            Output("images", "folder", "the photos"),
            Output("truth", "folder", "the ground truth"),
            Output("gcp_file", "file", "GCP coordinates (UTM, EPSG header)"),
            Output("dsm", "raster", "true DSM"),
            Output("dtm", "raster", "true DTM"),
            Output("ortho", "raster", "true orthophoto"),
            Output("points", "pointcloud", "point cloud sampled from the DSM"),
            Output("n_photos", "integer", "number of photos"),
            Output("crs", "string", "CRS of the scene"),
        ),
    ),
    Algorithm(
        id="demo", title="Demo: the whole chain on a synthetic survey", group="Testing", function=demo,
        params=(
            Param("output", "folder", "demo_output", output=True),
            Param("preset", "enum", "small", choices=PRESET_CHOICES),
            Param("seed", "integer", 0, minimum=0),
        ),
        outputs=(Output("output", "folder", "the demo folder"), Output("products", "json", "product paths")),
    ),
)
