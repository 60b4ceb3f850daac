"""Benchmark: each consumer-drone pathology of synth against the clean survey, in one run.

For the clean survey and each pathology (same preset and seed), prints what the chain made of it:
footprint IoU shortfall on the true DSM (1 − mean IoU), SfM camera RMSE with the GCPs gcp-find
found, the ortho's median geolocation error against the true ortho, or the refusal line — and the
ratio to the clean figure (target <= 1.5), plus the time each took.

    python benchmarks/bench_heights.py [--preset tiny|small] [--seed 1] [--pathologies a,b]
"""

from __future__ import annotations

import argparse
import json
import resource
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ALL = (
    "no-relative-altitude",
    "ellipsoidal-gps",
    "altitude-drift",
    "wrong-focal",
    "dsm-datum",
    "partial-dsm",
    "exposure-steps",
)


def _iou_shortfall(fp: Path, truth: Path) -> float:
    import geopandas as gpd

    a = gpd.read_file(fp, layer="footprints").set_index("image")
    t = gpd.read_file(truth / "footprints.gpkg").set_index("image")
    return 1.0 - float(
        np.mean(
            [g.intersection(t.loc[n].geometry).area / g.union(t.loc[n].geometry).area for n, g in a.geometry.items()]
        )
    )


def _camera_rmse(cameras: Path, truth: Path) -> float:
    import geopandas as gpd

    poses = {p["image"]: p for p in json.loads((truth / "poses.json").read_text())}
    c = gpd.read_file(cameras)
    c = c[c.registered]
    e = np.array(
        [[r.x - poses[r.image]["x"], r.y - poses[r.image]["y"], r.z - poses[r.image]["z"]] for r in c.itertuples()]
    )
    return float(np.sqrt((e**2).sum(axis=1).mean()))


def measure(name: str, preset: str, seed: int, work: Path) -> dict[str, object]:
    from geoortho.errors import GeoorthoError
    from geoortho.gcp.find import gcp_find
    from geoortho.orthophoto import ortho
    from geoortho.orthophoto.quality import geolocation_shifts
    from geoortho.photos.footprint import footprints
    from geoortho.reconstruction.sparse import sfm
    from geoortho.synthetic.survey import synth

    out: dict[str, object] = {"pathology": name}
    t0 = time.perf_counter()
    s = synth(work / "survey", preset=preset, seed=seed, pathology="" if name == "clean" else name)
    info = json.loads((s.truth / "survey.json").read_text())
    dsm = s.dsm
    if name == "dsm-datum":
        dsm = s.truth / "dsm_other_datum.tif"
    elif name == "partial-dsm":
        dsm = s.truth / "dsm_partial.tif"
    try:
        footprints(s.images, work / "fp.gpkg", dsm=dsm)
        out["footprint_iou_shortfall"] = _iou_shortfall(work / "fp.gpkg", s.truth)
    except GeoorthoError as e:
        out["footprint_iou_shortfall"] = f"refused: {e}"
    found = gcp_find(s.images, s.gcp_file, work / "gcp_list.txt")
    r = sfm(s.images, work / "sfm", gcp_list=found.output, max_image_size=1024, max_features=4096)
    out["sfm_camera_rmse_m"] = _camera_rmse(r.cameras, s.truth)
    rep = json.loads(r.report.read_text())
    out["sfm_notes"] = rep["notes"]
    o = ortho(s.images, work / "ortho.tif", sfm=r.output, dsm=dsm, resolution_m=info["preset"]["ortho_cell_m"])
    d = [x.distance for x in geolocation_shifts(o.output, s.ortho)]
    out["ortho_geolocation_m"] = float(np.median(d)) if d else float("nan")
    out["ortho_seam_mismatch_dn"] = [o.seam_mismatch_raw, o.seam_mismatch_balanced]
    out["ortho_notes"] = list(o.notes)
    out["seconds"] = time.perf_counter() - t0
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--preset", default="small")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--pathologies", default=",".join(ALL))
    args = ap.parse_args()
    rows = []
    for name in ("clean", *[p for p in args.pathologies.split(",") if p]):
        with tempfile.TemporaryDirectory() as d:
            rows.append(measure(name, args.preset, args.seed, Path(d)))
            print(json.dumps(rows[-1], default=float), flush=True)
    clean = rows[0]
    print(
        f"\n{'pathology':<22}{'fp IoU short':>13}{'ratio':>7}{'cam RMSE m':>12}{'ratio':>7}"
        f"{'ortho geo m':>12}{'ratio':>7}{'s':>7}"
    )
    for r in rows:
        cells = []
        for k in ("footprint_iou_shortfall", "sfm_camera_rmse_m", "ortho_geolocation_m"):
            v, c = r[k], clean[k]
            if isinstance(v, str):
                cells.append(f"{'refused':>13}{'':>7}" if k.startswith("foot") else f"{'refused':>12}{'':>7}")
            else:
                ratio = v / c if isinstance(c, float) and c > 0 else float("nan")
                w = 13 if k.startswith("foot") else 12
                cells.append(f"{v:>{w}.4f}{ratio:>7.2f}")
        print(f"{r['pathology']:<22}" + "".join(cells) + f"{r['seconds']:>7.0f}")
    print(f"peak RSS {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MB")
    return 0


if __name__ == "__main__":
    sys.exit(main())
