"""Benchmark: RTK and PPK georeference without GCPs, against the same photos read as consumer GPS.

Three synthetic surveys of one flight (``small`` by default), every GCP a checkpoint:

* **RTK**: the photos' positions fixed to 2 cm (RtkFlag 50 with their deviations), three float
  and one lost fix. Read with their stated accuracy (geoortho now) and as consumer GPS (every
  photo at gps_sigma_m, heights from the barometer: the tags ignored, as before);
* **PPK**: a consumer GPS in the photos and an RTKLIB trajectory at 5 Hz, the photos' time
  stamps 0.3 s behind the exposures. With ``--positions`` (offset found from the photos' GPS;
  offset given as 18 s, the lag left for the block to find) and without (the photos' own GPS);
* **factory calibration**: EXIF's focal length 12 % long, DJI's calibration tags right; with
  and without the tags read.

Prints, per run: cameras against the truth (RMSE per horizontal axis and vertical), checkpoint
RMSE (horizontal, vertical, in GSD), the time lag found, the focal length's error, and the
wall time of the sfm stage. Each run is a fresh process (``python -m geoortho sfm``).

    python benchmarks/bench_rtk.py [--preset small] [--seed 1]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

IGNORE_TAGS = r"""
import sys
import geoortho.photos.metadata as m
# the tags unread: positions as a consumer GPS's, no factory calibration
m.position_accuracy = lambda tags: (float("nan"), float("nan"), "consumer", "")
m.factory_calibration = lambda tags, w, h: (float("nan"),) * 3 + ((), False, "")
from geoortho.processing.cli import main
sys.exit(main(sys.argv[1:]))
"""


def _sfm(images: Path, out: Path, extra: list[str], ignore_tags: bool = False) -> float:
    cmd = [sys.executable, "-c", IGNORE_TAGS] if ignore_tags else [sys.executable, "-m", "geoortho"]
    t0 = time.perf_counter()
    subprocess.run(
        [*cmd, "sfm", "--images", str(images), "--output", str(out), "--max-image-size", "1024", "--quiet", *extra],
        check=True,
        capture_output=True,
    )
    return time.perf_counter() - t0


def _figures(survey: Path, out: Path) -> dict[str, float]:
    import geopandas as gpd

    truth = {p["image"]: p for p in json.loads((survey / "truth" / "poses.json").read_text())}
    gsd_m = json.loads((survey / "truth" / "survey.json").read_text())["gsd_cm_at_home_height"] / 100
    cams = gpd.read_file(out / "cameras.gpkg")
    cams = cams[cams.registered]
    d = np.array([[c.x - truth[c.image]["x"], c.y - truth[c.image]["y"], c.z - truth[c.image]["z"]]
                  for c in cams.itertuples()])  # fmt: skip
    report = json.loads((out / "report.json").read_text())
    check = report.get("checkpoint_accuracy") or {}
    lag = ((report.get("positions") or {}).get("time_lag") or {}).get("lag_s", float("nan"))
    truth_f = json.loads((survey / "truth" / "survey.json").read_text())["camera"]["focal_px"]
    focal = report["intrinsics"][0]["focal_px"]
    return {
        "cam_h_cm": 100 * float(np.sqrt((d[:, :2] ** 2).mean())),
        "cam_v_cm": 100 * float(np.sqrt((d[:, 2] ** 2).mean())),
        "chk_h_gsd": float(check.get("rmse_horizontal_m", float("nan"))) / gsd_m,
        "chk_v_gsd": float(check.get("rmse_z_m", float("nan"))) / gsd_m,
        "lag_s": float(lag),
        "focal_err_pct": 100 * (focal / truth_f - 1),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--preset", default="small")
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args()
    import geoortho

    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp)
        runs = []
        for name, pathology in (("rtk", "rtk"), ("ppk", "ppk"), ("cal", "wrong-focal,factory-calibration")):
            s = geoortho.synth(d / name, preset=args.preset, seed=args.seed, pathology=pathology)
            found = geoortho.gcp_find(s.images, s.gcp_file, d / f"{name}_gcp.txt")
            names = sorted({ln.split()[-1] for ln in found.output.read_text().splitlines()[1:] if ln.strip()})
            gcp = ["--gcp-list", str(found.output), "--checkpoints", ",".join(names)]
            pos = str(s.truth / "trajectory.pos")
            cases = {
                "rtk": [
                    ("RTK, stated accuracy", gcp, False),
                    ("RTK read as consumer GPS", gcp, True),
                ],
                "ppk": [
                    ("PPK .pos, offset found", [*gcp, "--positions", pos], False),
                    ("PPK .pos, offset 18 s (lag left)", [*gcp, "--positions", pos, "--positions-time-offset-s", "18"],
                     False),
                    ("photos' own GPS (no .pos)", gcp, False),
                ],
                "cal": [
                    ("factory calibration read", gcp, False),
                    ("EXIF focal only (tags ignored)", gcp, True),
                ],
            }[name]  # fmt: skip
            for k, (label, extra, ignore) in enumerate(cases):
                out = d / f"{name}_sfm{k}"
                seconds = _sfm(s.images, out, extra, ignore)
                runs.append((label, seconds, _figures(s.output, out)))
    print(f"preset {args.preset}, seed {args.seed}; every GCP a checkpoint")
    print(f"{'run':36s} {'cam H cm':>9s} {'cam V cm':>9s} {'chk H GSD':>10s} {'chk V GSD':>10s} {'lag s':>7s} "
          f"{'focal %':>8s} {'sfm s':>7s}")  # fmt: skip
    for label, seconds, f in runs:
        print(f"{label:36s} {f['cam_h_cm']:9.2f} {f['cam_v_cm']:9.2f} {f['chk_h_gsd']:10.2f} {f['chk_v_gsd']:10.2f} "
              f"{f['lag_s']:7.3f} {f['focal_err_pct']:8.2f} {seconds:7.1f}")  # fmt: skip


if __name__ == "__main__":
    main()
