"""Benchmark: ``run`` on a 12 MP block, as a user starts it (issue 47's goal: ``sfm`` <= 10 min and
the whole ``run`` <= 20 min for 75 photos of 12 MP on 2 cores).

No 12 MP survey is in ``../shared``, so one is made: a ``plan`` over the ``medium`` preset's flight
box for the synthetic camera's lens at 4000 x 3000 px (FC6310's field of view), 50 m up, 75 % front
and 70 % side overlap (84 photos), flown by ``synth --plan``. Then ``geoortho run`` with the GCP file
and no height option, in a fresh process. Prints each stage's and sfm's steps' seconds, the peak
memory, registration, the cameras' error against the truth, and the two ratios against the goal.

    python benchmarks/bench_12mp.py [--survey DIR]   # DIR: an earlier run's survey, kept with --keep
"""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

import cv2
import geopandas as gpd
import numpy as np
import shapely
from bench_sfm import OURS, _child

import geoortho

SFM_GOAL_S, RUN_GOAL_S = 600.0, 1200.0


def make_survey(folder: Path) -> Path:
    """The 12 MP plan over the medium preset's scene, flown by synth (about 30 min on 2 cores)."""
    e0, n0 = 483600.0, 4288780.0  # the medium preset's flight box centre at synth's default place
    aoi = folder / "aoi.gpkg"
    gpd.GeoDataFrame(geometry=[shapely.box(e0 - 57, n0 - 50, e0 + 57, n0 + 50)], crs="EPSG:32629").to_file(aoi)
    p = geoortho.plan(
        aoi, folder / "plan", camera="FC6310", image_width_px=4000, image_height_px=3000,
        altitude_m=50.0, front_overlap=75.0, side_overlap=70.0,
    )  # fmt: skip
    return geoortho.synth(folder / "survey", preset="medium", plan=p.plan).output


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--survey", type=Path, help="a survey made before (its images/ and truth/)")
    ap.add_argument("--keep", type=Path, help="make the survey in this folder and keep it")
    a = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        survey = a.survey or make_survey(a.keep or Path(tmp))
        photos = sorted((survey / "images").glob("*.JPG"))
        n_photos, size = len(photos), "x".join(map(str, cv2.imread(str(photos[0])).shape[1::-1]))
        project = Path(tmp) / "run"
        argv = ["geoortho", "run", "--images", str(survey / "images"), "--gcp-file", str(survey / "truth/gcp_utm.txt")]
        wall_s, _, peak_kb = _child(OURS, [*argv, "--output", str(project), "--quiet"])
        stages = {k: v.get("seconds") for k, v in json.loads((project / "run.json").read_text())["stages"].items()}
        report = json.loads((project / "sfm" / "report.json").read_text())
        truth = {p["image"]: p for p in json.loads((survey / "truth" / "poses.json").read_text())}
        cams = gpd.read_file(project / "sfm" / "cameras.gpkg")
        cams = cams[cams["registered"].astype(bool)]
        d = np.array(
            [
                [c.x - truth[c.image]["x"], c.y - truth[c.image]["y"], c.z - truth[c.image]["z"]]
                for c in cams.itertuples()
            ]
        )
    print(f"{n_photos} photos of {size}; run as a fresh process: {wall_s:.0f} s, peak {peak_kb / 1024**2:.2f} GB")
    print("stages (s): " + ", ".join(f"{k} {v:.0f}" for k, v in stages.items() if v is not None))
    print("sfm steps (s): " + ", ".join(f"{k} {v:.0f}" for k, v in report["seconds"].items()))
    h_cm, v_cm = 100 * np.sqrt((d[:, :2] ** 2).sum(1).mean()), 100 * np.sqrt((d[:, 2] ** 2).mean())
    print(
        f"registered {len(cams)}/{n_photos}, reprojection {report['mean_reprojection_error_px']:.2f} px; "
        f"cameras against the truth (RMSE): {h_cm:.2f} cm H, {v_cm:.2f} cm V"
    )
    print(
        f"goal ratios (goal / measured, >= 1 meets it): sfm {SFM_GOAL_S / stages['sfm']:.2f} "
        f"(goal {SFM_GOAL_S:.0f} s), run {RUN_GOAL_S / wall_s:.2f} (goal {RUN_GOAL_S:.0f} s)"
    )


if __name__ == "__main__":
    main()
