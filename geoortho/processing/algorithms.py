"""The specs: one per algorithm.

Defaults, choices and help are the core functions' own (read from their source by
:mod:`.spec`); a spec adds only what a face needs. Parameters several algorithms
share are declared once, below. Nothing heavy is imported here: describing the
registry (``--help``, ``describe --json``, the QGIS provider) stays quick.
"""

from __future__ import annotations

from .spec import Algorithm, Output, Param

# -- shared parameters: one declaration each ---------------------------------
IMAGES = Param("images", "folder")
CRS = Param("crs", "crs")
DSM = Param("dsm", "raster")
GROUND_ELEVATION = Param("ground_elevation_m", "number", unit="m")
TAKEOFF_ELEVATION = Param("takeoff_elevation_m", "number", unit="m")
FLIGHT_HEIGHT = Param("flight_height_m", "number", unit="m", minimum=1.0)
GPS_ALTITUDE = Param("gps_altitude", "enum", advanced=True)
WORKERS = Param("workers", "integer", minimum=0, advanced=True)
SEED = Param("seed", "integer", minimum=0)
PRESET = Param("preset", "enum")
DICTIONARY = Param("dictionary", "enum")
MARKER_SIZE = Param("marker_size_m", "number", unit="m", minimum=0.05, maximum=10.0)
#: Metres on the ground (converted to the CRS's units where that is in feet);
#: ``--resolution`` is still accepted.
RESOLUTION = Param("resolution_m", "number", unit="m", minimum=0.0, aliases=("resolution",))


def _advanced(p: Param) -> Param:
    from dataclasses import replace

    return replace(p, advanced=True)


ALGORITHMS: tuple[Algorithm, ...] = (
    Algorithm(
        id="synth",
        title="Synthetic survey",
        group="Testing",
        function_ref="geoortho.synthetic:synth",
        params=(
            Param("output", "folder", output=True),
            PRESET,
            SEED,
            Param("latitude_deg", "number", unit="deg", minimum=-80, maximum=84, advanced=True),
            Param("longitude_deg", "number", unit="deg", minimum=-180, maximum=180, advanced=True),
            _advanced(DICTIONARY),
            _advanced(MARKER_SIZE),
            WORKERS,
            Param("pathology", "string"),
        ),
        outputs=(
            Output("output", "folder"),
            Output("images", "folder"),
            Output("truth", "folder"),
            Output("gcp_file", "file"),
            Output("dsm", "raster"),
            Output("dtm", "raster"),
            Output("ortho", "raster"),
            Output("points", "pointcloud"),
            Output("n_photos", "integer"),
            Output("crs", "string"),
        ),
    ),
    Algorithm(
        id="footprints",
        title="Photo footprints and GSD",
        group="Photos",
        function_ref="geoortho.footprint:footprints",
        params=(
            IMAGES,
            Param("output", "vector", output=True, extensions=(".gpkg", ".geojson", ".shp", ".fgb")),
            DSM,
            GROUND_ELEVATION,
            TAKEOFF_ELEVATION,
            CRS,
            Param("sensor_width_mm", "number", unit="mm", minimum=0.5, maximum=100.0, advanced=True),
            Param("max_range_m", "number", unit="m", minimum=1.0, advanced=True),
            Param("overlap", "raster", output=True),
            Param("overlap_cell_m", "number", unit="m", minimum=0.01, advanced=True),
            FLIGHT_HEIGHT,
            GPS_ALTITUDE,
        ),
        outputs=(
            Output("output", "vector"),
            Output("overlap", "raster"),
            Output("n_photos", "integer"),
            Output("n_skipped", "integer"),
            Output("median_gsd_cm", "number"),
            Output("crs", "string"),
            Output("height_source", "string"),
            Output("vertical_datum", "string"),
        ),
    ),
    Algorithm(
        id="gcp-find",
        title="Find GCP markers (gcp_list.txt)",
        group="Ground control",
        function_ref="geoortho.gcp.find:gcp_find",
        params=(
            IMAGES,
            Param("gcp_file", "file", extensions=(".txt", ".csv", ".tsv", ".json")),
            Param("output", "file", output=True, extensions=(".txt",)),
            DICTIONARY,
            Param("margin", "number", unit="%", minimum=-50.0, maximum=45.0),
            DSM,
            TAKEOFF_ELEVATION,
            Param("gcp_crs", "crs"),
            CRS,
            Param("detections", "vector", output=True, extensions=(".gpkg", ".csv")),
            Param("review", "file", output=True, extensions=(".png",)),
            MARKER_SIZE,
            Param("position_uncertainty_m", "number", unit="m", minimum=0.0, advanced=True),
            Param("height_uncertainty_m", "number", unit="m", minimum=0.0, advanced=True),
            Param("attitude_uncertainty_deg", "number", unit="deg", minimum=0.0, maximum=45.0, advanced=True),
            WORKERS,
        ),
        outputs=(
            Output("output", "file"),
            Output("detections", "vector"),
            Output("review", "file"),
            Output("n_observations", "integer"),
            Output("n_gcps_found", "integer"),
            Output("n_candidates", "integer"),
            Output("crs", "string"),
        ),
    ),
    Algorithm(
        id="dem",
        title="DSM and DTM from a point cloud",
        group="Elevation",
        function_ref="geoortho.elevation:dem",
        params=(
            Param("points", "pointcloud", extensions=(".las", ".laz", ".ply")),
            Param("output", "raster", output=True, extensions=(".tif",)),
            Param("dtm", "raster", output=True, extensions=(".tif",)),
            RESOLUTION,
            Param("method", "enum"),
            Param("ground_method", "enum"),
            CRS,
            Param("max_gap_m", "number", unit="m", minimum=0.0),
            Param("smooth_px", "integer", minimum=0, maximum=20),
            Param("classified", "pointcloud", output=True, extensions=(".laz", ".las")),
            Param("hillshade", "file", output=True, extensions=(".png",)),
            Param("smrf_cell_m", "number", unit="m", minimum=0.05, advanced=True),
            Param("smrf_slope", "number", minimum=0.0, advanced=True),
            Param("smrf_window_m", "number", unit="m", minimum=0.5, advanced=True),
            Param("smrf_threshold_m", "number", unit="m", minimum=0.0, advanced=True),
            Param("smrf_scalar", "number", minimum=0.0, advanced=True),
            Param("smrf_margin_m", "number", unit="m", minimum=0.0, advanced=True),
            Param("engine", "enum", advanced=True),
        ),
        outputs=(
            Output("dsm", "raster"),
            Output("dtm", "raster"),
            Output("classified", "pointcloud"),
            Output("hillshade", "file"),
            Output("resolution", "number"),
            Output("crs", "string"),
            Output("units", "string"),
            Output("n_points", "integer"),
            Output("n_ground", "integer"),
        ),
    ),
    Algorithm(
        id="sfm",
        title="Structure from Motion (pycolmap), georeferenced",
        group="Photogrammetry",
        function_ref="geoortho.reconstruction:sfm",
        params=(
            IMAGES,
            Param("output", "folder", output=True),
            Param("gcp_list", "file", extensions=(".txt",)),
            Param("checkpoints", "string"),
            CRS,
            Param("matching", "enum"),
            Param("max_image_size", "integer", unit="px", minimum=256, maximum=16384),
            Param("max_features", "integer", minimum=256, maximum=65536, advanced=True),
            Param("camera_model", "enum", advanced=True),
            TAKEOFF_ELEVATION,
            Param("gps_sigma_m", "number", unit="m", minimum=0.01, maximum=100.0, advanced=True),
            Param("local_frame", "bool", advanced=True),
            _advanced(SEED),
            WORKERS,
            Param("mapper", "enum", advanced=True),
        ),
        outputs=(
            Output("output", "folder"),
            Output("model", "folder"),
            Output("points", "pointcloud"),
            Output("cameras", "vector"),
            Output("report", "file"),
            Output("n_photos", "integer"),
            Output("n_registered", "integer"),
            Output("mean_reprojection_error_px", "number"),
            Output("gcp_rmse_m", "number"),
            Output("checkpoint_rmse_m", "number"),
            Output("georeferenced_by", "string"),
            Output("crs", "string"),
        ),
    ),
    Algorithm(
        id="dense",
        title="Dense point cloud from the photos (CPU)",
        group="Photogrammetry",
        function_ref="geoortho.densify:dense",
        params=(
            Param("sfm", "folder"),
            IMAGES,
            Param("output", "pointcloud", output=True, extensions=(".laz", ".las")),
            Param("max_image_size", "integer", unit="px", minimum=256, maximum=16384),
            Param("neighbours", "integer", minimum=1, maximum=10, advanced=True),
            Param("min_views", "integer", minimum=1, maximum=10, advanced=True),
            Param("depth_tolerance", "number", minimum=0.0001, maximum=0.2, advanced=True),
            WORKERS,
        ),
        outputs=(
            Output("output", "pointcloud"),
            Output("report", "file"),
            Output("n_photos", "integer"),
            Output("n_depth_maps", "integer"),
            Output("n_points", "integer"),
            Output("crs", "string"),
        ),
    ),
    Algorithm(
        id="ortho",
        title="Orthophoto mosaic (true ortho on the DSM)",
        group="Photogrammetry",
        function_ref="geoortho.orthophoto.mosaic:ortho",
        params=(
            IMAGES,
            Param("output", "raster", output=True, extensions=(".tif",)),
            Param("sfm", "folder"),
            DSM,
            RESOLUTION,
            CRS,
            GROUND_ELEVATION,
            TAKEOFF_ELEVATION,
            Param("seams", "enum"),
            Param("balance", "enum"),
            Param("blend", "enum"),
            Param("max_hole_px", "integer", unit="px", minimum=0),
            Param("compress", "enum"),
            Param("preview", "file", output=True, extensions=(".png",)),
            Param("interpolation", "enum", advanced=True),
            Param("tile_px", "integer", unit="px", minimum=128, maximum=8192, advanced=True),
            WORKERS,
            FLIGHT_HEIGHT,
            GPS_ALTITUDE,
            Param("dsm_offset", "enum"),
            Param("max_dsm_offset_m", "number", unit="m", minimum=0.0, advanced=True),
        ),
        outputs=(
            Output("output", "raster"),
            Output("preview", "file"),
            Output("report", "file"),
            Output("resolution_m", "number"),
            Output("median_gsd_m", "number"),
            Output("n_used", "integer"),
            Output("seam_mismatch_raw", "number"),
            Output("seam_mismatch_balanced", "number"),
            Output("crs", "string"),
        ),
    ),
    Algorithm(
        id="run",
        title="Run the whole chain (resumable) with a quality report",
        group="Photogrammetry",
        function_ref="geoortho.pipeline:run",
        params=(
            IMAGES,
            Param("output", "folder", output=True),
            Param("gcp_file", "file", extensions=(".txt", ".csv", ".tsv", ".json")),
            Param("gcp_list", "file", extensions=(".txt",)),
            Param("checkpoints", "string"),
            Param("points", "pointcloud", extensions=(".las", ".laz", ".ply")),
            DSM,
            CRS,
            TAKEOFF_ELEVATION,
            Param("stage_options", "string", advanced=True),
            Param("rerun_from", "enum"),
            Param("force", "bool", advanced=True),
            WORKERS,
        ),
        outputs=(
            Output("output", "folder"),
            Output("report", "file"),
            Output("ledger", "file"),
            Output("ortho", "raster"),
            Output("dsm", "raster"),
            Output("dtm", "raster"),
            Output("stages", "json"),
            Output("seconds", "number"),
        ),
    ),
    Algorithm(
        id="report",
        title="Quality report of a run project",
        group="Photogrammetry",
        function_ref="geoortho.reporting:report",
        params=(
            Param("project", "folder"),
            Param("output", "file", output=True, extensions=(".html",)),
        ),
        outputs=(Output("output", "file"), Output("n_sections", "integer"), Output("n_problems", "integer")),
    ),
    Algorithm(
        id="demo",
        title="Demo: the whole chain on a synthetic survey",
        group="Testing",
        function_ref="geoortho.demonstration:demo",
        params=(
            Param("output", "folder", output=True),
            PRESET,
            SEED,
            Param("surface", "enum"),
        ),
        outputs=(Output("output", "folder"), Output("products", "json")),
    ),
)
