"""The specs: one per algorithm. Help texts come from the core functions' docstrings."""

from __future__ import annotations

from ..dem import GROUND_METHODS, METHODS, dem
from ..demo import demo
from ..footprint import footprints
from ..gcp.find import gcp_find
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
        id="footprints", title="Photo footprints and GSD", group="Photos", function=footprints,
        params=(
            Param("images", "folder"),
            Param("output", "vector", output=True, extensions=(".gpkg", ".geojson", ".shp", ".fgb")),
            Param("dsm", "raster", None),
            Param("ground_elevation_m", "number", None, unit="m"),
            Param("takeoff_elevation_m", "number", None, unit="m"),
            Param("crs", "crs", None),
            Param("sensor_width_mm", "number", None, unit="mm", minimum=0.5, maximum=100.0, advanced=True),
            Param("max_range_m", "number", 500.0, unit="m", minimum=1.0, advanced=True),
            Param("overlap", "raster", None, output=True),
            Param("overlap_cell_m", "number", 1.0, unit="m", minimum=0.01, advanced=True),
        ),
        outputs=(
            Output("output", "vector", "footprints (layer footprints) and camera positions (layer cameras)"),
            Output("overlap", "raster", "photos seeing each ground cell"),
            Output("n_photos", "integer", "photos with a footprint"),
            Output("n_skipped", "integer", "photos skipped"),
            Output("median_gsd_cm", "number", "median GSD at the image centres, cm"),
            Output("crs", "string", "CRS of the output"),
            Output("height_source", "string", "how camera heights were found"),
        ),
    ),
    Algorithm(
        id="gcp-find", title="Find GCP markers (gcp_list.txt)", group="Ground control", function=gcp_find,
        params=(
            Param("images", "folder"),
            Param("gcp_file", "file", extensions=(".txt", ".csv", ".tsv", ".json")),
            Param("output", "file", output=True, extensions=(".txt",)),
            Param("dictionary", "enum", "DICT_4X4_50", choices=DICTIONARIES),
            Param("margin", "number", 0.0, unit="%", minimum=-50.0, maximum=45.0),
            Param("dsm", "raster", None),
            Param("takeoff_elevation_m", "number", None, unit="m"),
            Param("gcp_crs", "crs", None),
            Param("crs", "crs", None),
            Param("detections", "vector", None, output=True, extensions=(".gpkg", ".csv")),
            Param("review", "file", None, output=True, extensions=(".png",)),
            Param("marker_size_m", "number", 1.0, unit="m", minimum=0.05, maximum=10.0),
            Param("position_uncertainty_m", "number", 5.0, unit="m", minimum=0.0, advanced=True),
            Param("height_uncertainty_m", "number", 5.0, unit="m", minimum=0.0, advanced=True),
            Param("attitude_uncertainty_deg", "number", 3.0, unit="deg", minimum=0.0, maximum=45.0,
                  advanced=True),
            Param("workers", "integer", 0, minimum=0, advanced=True),
        ),
        outputs=(
            Output("output", "file", "OpenDroneMap gcp_list.txt"),
            Output("detections", "vector", "every candidate and what became of it"),
            Output("review", "file", "PNG contact sheet of the detections"),
            Output("n_observations", "integer", "observations written"),
            Output("n_gcps_found", "integer", "GCPs seen at least once"),
            Output("n_candidates", "integer", "(photo, GCP) pairs searched"),
            Output("crs", "string", "CRS of gcp_list.txt"),
        ),
    ),
    Algorithm(
        id="dem", title="DSM and DTM from a point cloud", group="Elevation", function=dem,
        params=(
            Param("points", "pointcloud", extensions=(".las", ".laz", ".ply")),
            Param("output", "raster", output=True, extensions=(".tif",)),
            Param("dtm", "raster", None, output=True, extensions=(".tif",)),
            Param("resolution_m", "number", 0.0, unit="m", minimum=0.0),
            Param("method", "enum", "max", choices=METHODS),
            Param("ground_method", "enum", "smrf", choices=GROUND_METHODS),
            Param("crs", "crs", None),
            Param("max_gap_m", "number", 25.0, unit="m", minimum=0.0),
            Param("smooth_px", "integer", 0, minimum=0, maximum=20),
            Param("classified", "pointcloud", None, output=True, extensions=(".laz", ".las")),
            Param("hillshade", "file", None, output=True, extensions=(".png",)),
            Param("smrf_cell_m", "number", 1.0, unit="m", minimum=0.05, advanced=True),
            Param("smrf_slope", "number", 0.15, minimum=0.0, advanced=True),
            Param("smrf_window_m", "number", 18.0, unit="m", minimum=0.5, advanced=True),
            Param("smrf_threshold_m", "number", 0.5, unit="m", minimum=0.0, advanced=True),
            Param("smrf_scalar", "number", 1.25, minimum=0.0, advanced=True),
            Param("smrf_margin_m", "number", 1.0, unit="m", minimum=0.0, advanced=True),
            Param("engine", "enum", "native", choices=("native", "pdal"), advanced=True),
        ),
        outputs=(
            Output("dsm", "raster", "DSM (COG, float32, nodata -9999)"),
            Output("dtm", "raster", "DTM from ground points"),
            Output("classified", "pointcloud", "the cloud with ground as class 2"),
            Output("hillshade", "file", "hillshade preview"),
            Output("resolution", "number", "cell size in the CRS units"),
            Output("crs", "string", "CRS of the rasters"),
            Output("units", "string", "horizontal and vertical units"),
            Output("n_points", "integer", "points used"),
            Output("n_ground", "integer", "ground points"),
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
