"""The whole chain on a synthetic survey: what ``make demo`` runs."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Literal

from .feedback import Feedback, as_feedback, split

if TYPE_CHECKING:
    from .synthetic import SynthResult

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
    """Make a synthetic survey and run every stage geoortho has on it.

    Prints where each product is. The chain: synth, footprints, GCP finding, SfM,
    the dense cloud, DSM/DTM and the orthophoto.

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
    from .synthetic import synth

    fb = as_feedback(feedback)
    output = Path(output)
    stages = _stages(surface)
    steps = split(fb, [6] + [w for _, w, _ in stages])
    survey = synth(output / "survey", preset=preset, seed=seed, feedback=steps[0])
    products: dict[str, str] = {
        "images": str(survey.images),
        "truth": str(survey.truth),
        "gcp_file": str(survey.gcp_file),
        "true_dsm": str(survey.dsm),
        "true_ortho": str(survey.ortho),
        "points": str(survey.points),
    }
    for (name, _, run), step in zip(stages, steps[1:]):
        products.update(run(survey, output, step))
        fb.info(f"demo: {name} done")
    for k, v in products.items():
        fb.info(f"{k}: {v}")
    return DemoResult(output, products)


def _stages(surface: str = "dense") -> list:
    """(name, weight, run(survey, output, feedback) -> products) for every stage that exists."""
    from functools import partial

    return [
        ("footprints", 1, _footprints),
        ("gcp-find", 2, _gcp_find),
        ("sfm", 4, _sfm),
        *([("dense", 3, _dense)] if surface == "dense" else []),
        ("dem", 1, partial(_dem, lidar=surface == "lidar")),
        ("ortho", 2, _ortho),
    ]


def _takeoff_elevation(survey: SynthResult) -> float:
    """The field crew knows where they took off: the survey's home point elevation."""
    return float(json.loads((survey.truth / "survey.json").read_text())["home"]["ground_z"])


def _footprints(survey: SynthResult, output: Path, fb: Feedback) -> dict[str, str]:
    from .footprint import footprints

    r = footprints(
        survey.images,
        output / "footprints.gpkg",
        dsm=survey.dsm,
        takeoff_elevation_m=_takeoff_elevation(survey),
        overlap=output / "overlap.tif",
        feedback=fb,
    )
    fb.info(f"footprints: {r.n_photos} photos, median GSD {r.median_gsd_cm:.2f} cm")
    return {"footprints": str(r.output), "overlap": str(r.overlap)}


def _gcp_find(survey: SynthResult, output: Path, fb: Feedback) -> dict[str, str]:
    from .gcp.find import gcp_find

    r = gcp_find(
        survey.images,
        survey.gcp_file,
        output / "gcp_list.txt",
        dsm=survey.dsm,
        detections=output / "gcp_detections.gpkg",
        review=output / "gcp_review.png",
        feedback=fb,
    )
    fb.info(f"gcp-find: {r.n_observations} observations of {r.n_gcps_found} GCPs")
    return {"gcp_list": str(r.output), "gcp_detections": str(r.detections), "gcp_review": str(r.review)}


def _sfm(survey: SynthResult, output: Path, fb: Feedback) -> dict[str, str]:
    from .reconstruction import sfm

    gcp_list = output / "gcp_list.txt"
    names = sorted({ln.split()[6] for ln in gcp_list.read_text().splitlines()[1:] if len(ln.split()) >= 7})
    # every third GCP is a checkpoint: held out, measured; 1024 px features keep the demo quick
    r = sfm(
        survey.images,
        output / "sfm",
        gcp_list=gcp_list,
        checkpoints=",".join(names[::3]),
        max_image_size=1024,
        max_features=4096,
        feedback=fb,
    )
    fb.info(
        f"sfm: {r.n_registered}/{r.n_photos} photos, reprojection {r.mean_reprojection_error_px:.2f} px, "
        f"checkpoint RMSE {r.checkpoint_rmse_m * 100:.1f} cm"
    )
    return {
        "sfm_model": str(r.model),
        "sfm_points": str(r.points),
        "sfm_cameras": str(r.cameras),
        "sfm_report": str(r.report),
    }


def _dense(survey: SynthResult, output: Path, fb: Feedback) -> dict[str, str]:
    from .densify import dense

    r = dense(output / "sfm", survey.images, output / "dense.laz", feedback=fb)
    fb.info(f"dense: {r.n_points} points from {r.n_depth_maps} depth maps")
    return {"dense": str(r.output), "dense_report": str(r.report)}


def _dem(survey: SynthResult, output: Path, fb: Feedback, *, lidar: bool = False) -> dict[str, str]:
    from .elevation import dem

    # The cloud the dense stage made from the photos, unless the survey's lidar-like cloud is asked for.
    r = dem(
        survey.points if lidar else output / "dense.laz",
        output / "dsm.tif",
        dtm=output / "dtm.tif",
        hillshade=output / "dtm_hillshade.png",
        feedback=fb,
    )
    fb.info(f"dem: {r.n_points} points, {r.n_ground} ground, cells of {r.resolution:g} ({r.units})")
    return {"dsm": str(r.dsm), "dtm": str(r.dtm), "dtm_hillshade": str(r.hillshade)}


def _ortho(survey: SynthResult, output: Path, fb: Feedback) -> dict[str, str]:
    from .orthophoto import ortho

    # The SfM poses on the DSM the dem stage made: the chain's own products, not the truth.
    r = ortho(
        survey.images,
        output / "ortho.tif",
        sfm=output / "sfm",
        dsm=output / "dsm.tif",
        preview=output / "ortho_preview.png",
        feedback=fb,
    )
    fb.info(
        f"ortho: {r.width_px}x{r.height_px} px at {r.resolution_m * 100:.2f} cm, {r.n_used} photos; "
        f"seam colour mismatch {r.seam_mismatch_raw:.1f} -> {r.seam_mismatch_balanced:.1f} DN"
    )
    return {"ortho": str(r.output), "ortho_preview": str(r.preview), "ortho_report": str(r.report)}
