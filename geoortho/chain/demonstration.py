"""The whole chain on a synthetic survey: what ``make demo`` runs."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Literal

from geoortho.chain.pipeline import run
from geoortho.feedback import Feedback, as_feedback, split
from geoortho.gcp.io import read_gcp_file
from geoortho.planning.check import check_plan
from geoortho.planning.plan import plan
from geoortho.synthetic.survey import existing_survey, synth

if TYPE_CHECKING:
    from geoortho.synthetic.survey import SynthResult

__all__ = ["DemoResult", "demo"]

#: Where the DSM comes from: the dense cloud made from the photos, or the survey's lidar-like cloud.
Surface = Literal["dense", "lidar"]


@dataclass(frozen=True)
class DemoResult:
    """Where each product of the demo is.

    Attributes
    ----------
    output : Path
        The demo folder.
    products : dict of str to str
        Product paths by name.
    """

    output: Path
    products: dict[str, str] = field(default_factory=dict)


def demo(
    output: Path = Path("demo_output"),
    preset: Literal["tiny", "small", "medium", "oblique", "hard"] = "small",
    seed: int = 0,
    surface: Surface = "dense",
    *,
    feedback: Feedback | None = None,
) -> DemoResult:
    """Make a synthetic survey and run the whole chain on it with ``run``.

    Prints where each product and the quality report are. Before the flight, a plan over the
    survey's area with its GCPs (``OUTPUT/plan``); after it, the photos checked against the GCPs
    (``OUTPUT/plan/check``). The chain: footprints, GCP finding,
    SfM (every third GCP held out as a checkpoint), the dense cloud, DSM/DTM, the orthophoto, the
    3D mesh, the volumes of the survey's buildings (and stockpiles, where it has them), what the
    photos' surface shows otherwise than the survey's lidar-like DSM (a change) and the report,
    in ``OUTPUT/project``; the survey and its truth are in ``OUTPUT/survey``. Run it again on the
    same folder and only what changed is re-done: the survey too is kept when it is
    complete and of the same preset and seed.

    Parameters
    ----------
    output : Path
        Folder for the survey and all products.
    preset : str
        Synthetic survey preset (see the synth algorithm).
    seed : int
        Random seed of the synthetic survey.
    surface : str
        The cloud the DSM and DTM are made from: dense (from the photos, as a survey without
        lidar) or lidar (the survey's own lidar-like cloud; the dense stage is skipped).
    """

    fb = as_feedback(feedback)
    output = Path(output).absolute()  # every path it prints the same way
    weights = (1.0, 0.1, 4.0)
    synth_step, plan_step, run_step = split(fb, weights)
    starts = [sum(weights[:i]) / sum(weights) for i in range(3)]
    fb.stage("survey", 1, 3, starts[0], starts[1] - starts[0])
    survey = existing_survey(output / "survey", preset, seed)
    if survey is not None:
        fb.info(f"demo: the {preset} survey of seed {seed} in {survey.output} is complete: not drawn again")
    else:
        survey = synth(output / "survey", preset=preset, seed=seed, feedback=synth_step)
    names = sorted(read_gcp_file(survey.gcp_file).by_name())
    fb.stage("plan and check", 2, 3, starts[1], starts[2] - starts[1])
    planned = _plan_and_check(survey, output / "plan", plan_step)
    volumes = _volume_polygons(survey, output / "volumes.gpkg")
    fb.stage("run", 3, 3, starts[2], 1.0 - starts[2])
    result = run(
        survey.images,
        output / "project",
        gcp_file=survey.gcp_file,
        checkpoints=",".join(names[::3]),
        points=survey.points if surface == "lidar" else None,
        takeoff_elevation_m=_takeoff_elevation(survey),
        # 1024 px features keep the demo quick
        stage_options=json.dumps({"sfm": {"max_image_size": 1024, "max_features": 4096}}),
        volumes=volumes,
        # the site as its lidar measured it: what the photos' surface shows otherwise, beyond the
        # level of detection (crowns, walls), in the report's change section and the QGIS project
        change_from=survey.dsm if surface == "dense" else None,
        feedback=run_step,
    )
    products: dict[str, str] = {
        "images": str(survey.images),
        "truth": str(survey.truth),
        "gcp_file": str(survey.gcp_file),
        "true_dsm": str(survey.dsm),
        "true_ortho": str(survey.ortho),
        "points": str(survey.points),
        **planned,
        **_products(result.output),
        "report": str(result.report),
    }
    for k, v in products.items():
        fb.info(f"{k}: {v}")
    fb.info(f"demo: the quality report is {result.report}")
    if "qgis_project" in products:
        fb.info(f"demo: open {products['qgis_project']} in QGIS for every product, styled")
    return DemoResult(output, products)


def _plan_and_check(survey: SynthResult, folder: Path, fb: Feedback) -> dict[str, str]:
    """Before the flight: the plan over the survey's area with its GCPs; after it: the photos
    checked against the GCPs and the overlap needed."""
    import geopandas as gpd
    import shapely

    info = json.loads((survey.truth / "survey.json").read_text())
    aoi = folder / "aoi.gpkg"
    folder.mkdir(parents=True, exist_ok=True)
    gpd.GeoDataFrame(geometry=[shapely.box(*info["flight_box"])], crs=info["crs"]).to_file(aoi)
    before, after = split(fb, [1, 1])
    p = plan(
        aoi,
        folder,
        camera=str(sorted(survey.images.iterdir())[0]),
        altitude_m=info["preset"]["altitude_m"],
        front_overlap=100 * info["preset"]["front_overlap"],
        side_overlap=100 * info["preset"]["side_overlap"],
        dtm=survey.dtm,
        takeoff_ground_m=_takeoff_elevation(survey),
        gcps=str(survey.gcp_file),
        marker_size_m=info["marker_size_m"],
        feedback=before,
    )
    c = check_plan(
        survey.gcp_file,
        folder / "check",
        images=survey.images,
        dsm=survey.dtm,
        takeoff_elevation_m=_takeoff_elevation(survey),
        feedback=after,
    )
    return {"plan": str(p.plan), "plan_summary": str(p.summary), "plan_kml": str(p.kml), "check": str(c.report)}


#: A standing object larger than this (m²) is a building whose volume the demo measures.
BUILDING_MIN_M2 = 30.0


def _volume_polygons(survey: SynthResult, target: Path) -> Path | None:
    """Polygons to measure volumes over: the survey's stockpiles and pit where it has them, and its
    buildings (from its truth: what stands 2 m over the ground on 30 m² or more), each with 2 m of
    ground round it; None when there is neither."""
    import geopandas as gpd
    import numpy as np
    import rasterio
    import shapely
    from rasterio.features import shapes
    from scipy import ndimage

    info = json.loads((survey.truth / "survey.json").read_text())
    names, geoms = [], []
    for item in (info.get("cover") or {}).get("stockpiles", {}).get("items", []):
        names.append(str(item["name"]))
        geoms.append(shapely.Point(item["x"], item["y"]).buffer(float(item["radius_m"]), 64))
    with rasterio.open(survey.dsm) as d, rasterio.open(survey.dtm) as t:
        height, transform = d.read(1) - t.read(1), d.transform
    labels, n = ndimage.label(height > 2.0)
    cell_m2 = abs(transform.a * transform.e)
    sizes = np.bincount(labels.ravel())
    big = [k for k in range(1, n + 1) if sizes[k] * cell_m2 >= BUILDING_MIN_M2]
    for geom, _ in shapes(labels.astype(np.int32), mask=np.isin(labels, big), transform=transform):
        names.append(f"building {len([x for x in names if x.startswith('building')]) + 1}")
        geoms.append(shapely.geometry.shape(geom).envelope.buffer(2.0, join_style="mitre"))
    if not geoms:
        return None
    gpd.GeoDataFrame({"name": names}, geometry=geoms, crs=info["crs"]).to_file(target)
    return target


def _takeoff_elevation(survey: SynthResult) -> float:
    """The field crew knows where they took off: the survey's home point elevation."""
    return float(json.loads((survey.truth / "survey.json").read_text())["home"]["ground_z"])


#: The project's products by name, at the stable paths ``run`` gives them.
PRODUCTS = {
    "footprints": "footprints/footprints.gpkg",
    "overlap": "footprints/overlap.tif",
    "gcp_list": "gcp-find/gcp_list.txt",
    "gcp_detections": "gcp-find/detections.gpkg",
    "gcp_review": "gcp-find/review.png",
    "sfm_model": "sfm/model",
    "sfm_points": "sfm/points.laz",
    "sfm_cameras": "sfm/cameras.gpkg",
    "sfm_report": "sfm/report.json",
    "dense": "dense/dense.laz",
    "dense_copc": "dense/dense.copc.laz",
    "dense_report": "dense/dense_report.json",
    "dsm": "dem/dsm.tif",
    "dtm": "dem/dtm.tif",
    "dtm_hillshade": "dem/dtm_hillshade.png",
    "dsm_source": "dem/dsm_source.tif",
    "dtm_source": "dem/dtm_source.tif",
    "contours": "dem/contours.gpkg",
    "ortho": "ortho/ortho.tif",
    "ortho_preview": "ortho/ortho_preview.png",
    "ortho_report": "ortho/ortho_report.json",
    "ortho_source": "ortho/ortho_source.tif",
    "ortho_seamlines": "ortho/ortho_seamlines.gpkg",
    "volumes": "volume/volumes.gpkg",
    "change": "change/change.tif",
    "change_areas": "change/change.gpkg",
    "mesh": "mesh/mesh.glb",
    "mesh_tileset": "mesh/tileset/tileset.json",
    "mesh_view": "mesh/mesh_view.png",
    "ledger": "run.json",
    "qgis_project": "project.qgz",
}


def _products(project: Path) -> dict[str, str]:
    return {k: str(project / v) for k, v in PRODUCTS.items() if (project / v).exists()}
