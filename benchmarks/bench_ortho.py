"""Benchmark: geoortho ortho against a plain GDAL mosaic of the same photos, same grid, same run.

Both sides get the survey's true poses and DSM (this measures the ortho stage, not SfM), and
each runs in its own child process so that its peak memory is its own:

* plain baseline: every photo warped by GDAL (``rasterio.warp.reproject``) from 25 ground
  control points — its pixel grid cast onto the DSM, i.e. the footprint's homography — then
  ``rasterio.merge.merge`` of all of them: no occlusion, no seams, no balance, no blending;
* geoortho: :func:`geoortho.orthophoto.mosaic` (rectification on the DSM with occlusion, graph-cut
  seams, gains, multi-band blending, hole fill, COG with overviews) on ``--workers`` processes.

Prints output megapixels per second, time per stage, peak RSS (main process and largest worker)
and the time ratio geoortho / baseline (target <= 2 while doing seams, balance and blending),
and peak memory against the 2 GB target for ``medium``.

    python benchmarks/bench_ortho.py [--preset small|medium] [--survey DIR] [--workers 2]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

COMMON = r"""
import json, resource, sys, time
import numpy as np
from pathlib import Path
from geoortho.core.camera import Intrinsics, Pose
from geoortho.core.camera import PosedCamera
from geoortho.core.surface import read_surface

def true_cameras(survey):
    c = json.loads((survey / "truth/survey.json").read_text())["camera"]
    intr = Intrinsics(c["width_px"], c["height_px"], c["focal_px"], c["cx_px"], c["cy_px"], tuple(c["distortion"]))
    return [PosedCamera(intr, Pose(np.array([p["x"], p["y"], p["z"]]), np.array(p["rotation_world_from_camera"])),
                        p["image"], survey / "images" / p["image"])
            for p in json.loads((survey / "truth/poses.json").read_text()) if not p["corrupt"]]

def peak():
    own = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    kids = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    print("peak_rss_kb", own, kids, file=sys.stderr)
"""

OURS = (
    COMMON
    + r"""
from geoortho.orthophoto import MosaicOptions, mosaic
survey, out, resolution, workers = json.loads(sys.argv[1])
survey, out = Path(survey), Path(out)
surf = read_surface(survey / "truth/dsm.tif")
t0 = time.perf_counter()
r = mosaic(true_cameras(survey), surf, surf.crs, out / "ours.tif", resolution, MosaicOptions(workers=workers))
wall = time.perf_counter() - t0
print(json.dumps({"wall": wall, "width": r.width_px, "height": r.height_px, "resolution": r.resolution_m,
                  "seconds": r.seconds, "seam_raw": r.seam_mismatch_raw, "seam_bal": r.seam_mismatch_balanced}))
peak()
"""
)

BASELINE = (
    COMMON
    + r"""
import rasterio
from rasterio.control import GroundControlPoint
from rasterio.merge import merge
from rasterio.warp import reproject, Resampling
from geoortho.core.camera import pixel_rays
survey, out, resolution, workers = json.loads(sys.argv[1])
survey, out = Path(survey), Path(out)
surf = read_surface(survey / "truth/dsm.tif")
t0 = time.perf_counter()
files = []
for cam in true_cameras(survey):
    intr = cam.intrinsics
    u, v = np.meshgrid(np.linspace(0, intr.width_px - 1, 5), np.linspace(0, intr.height_px - 1, 5))
    pix = np.c_[u.ravel(), v.ravel()]
    hit = surf.intersect(cam.pose.center, pixel_rays(pix, intr, cam.pose), max_range_m=1000.0)
    gcps = [GroundControlPoint(row=float(p[1]) + 0.5, col=float(p[0]) + 0.5, x=float(q[0]), y=float(q[1]),
                               z=float(q[2])) for p, q, h in zip(pix, hit.points, hit.hit) if h]
    with rasterio.open(cam.path) as src:
        img = src.read()
    xs, ys = hit.points[hit.hit, 0], hit.points[hit.hit, 1]
    x0, y1 = np.floor(xs.min() / resolution) * resolution, np.ceil(ys.max() / resolution) * resolution
    w = int(np.ceil((xs.max() - x0) / resolution)); h = int(np.ceil((y1 - ys.min()) / resolution))
    dst_t = rasterio.transform.from_origin(x0, y1, resolution, resolution)
    dst = np.zeros((3, h, w), np.uint8)
    reproject(img, dst, gcps=gcps, src_crs=surf.crs, dst_transform=dst_t, dst_crs=surf.crs,
              resampling=Resampling.bilinear, src_nodata=None, dst_nodata=0)
    f = out / f"base_{cam.name}.tif"
    with rasterio.open(f, "w", driver="GTiff", width=w, height=h, count=3, dtype="uint8", crs=surf.crs,
                       transform=dst_t, nodata=0) as d:
        d.write(dst)
    files.append(f)
t_warp = time.perf_counter() - t0
mosaic_arr, tr = merge([str(f) for f in files], res=resolution, nodata=0)
with rasterio.open(out / "baseline.tif", "w", driver="GTiff", width=mosaic_arr.shape[2], height=mosaic_arr.shape[1],
                   count=3, dtype="uint8", crs=surf.crs, transform=tr, nodata=0, tiled=True,
                   compress="DEFLATE") as d:
    d.write(mosaic_arr)
wall = time.perf_counter() - t0
print(json.dumps({"wall": wall, "warp": t_warp, "width": mosaic_arr.shape[2], "height": mosaic_arr.shape[1]}))
peak()
"""
)


def _child(code: str, args: list) -> tuple[dict, int, int]:
    r = subprocess.run([sys.executable, "-c", code, json.dumps(args)], capture_output=True, text=True)
    if r.returncode:
        sys.stderr.write(r.stderr[-3000:])
        raise SystemExit(1)
    own, kids = (int(v) for v in r.stderr.strip().splitlines()[-1].split()[-2:])
    return json.loads(r.stdout.strip().splitlines()[-1]), own, kids


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--preset", default="small")
    ap.add_argument("--survey", type=Path, help="an existing synth folder (skips making one)")
    ap.add_argument("--workers", type=int, default=2)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as d:
        survey = args.survey
        if survey is None:
            from geoortho.synthetic.survey import synth

            survey = synth(Path(d) / "survey", preset=args.preset).output
        res = json.loads((survey / "truth" / "survey.json").read_text())["gsd_cm_at_home_height"] / 100.0
        res = float(f"{res:.3g}")
        t = time.perf_counter()
        ours, own_o, kids_o = _child(OURS, [str(survey), d, res, args.workers])
        base, own_b, kids_b = _child(BASELINE, [str(survey), d, res, args.workers])
        mp_o = ours["width"] * ours["height"] / 1e6
        mp_b = base["width"] * base["height"] / 1e6
        print(
            f"survey {survey.name}: grid {ours['width']}x{ours['height']} px at {res * 100:.2f} cm "
            f"({mp_o:.1f} Mpx); {args.workers} workers; benchmark {time.perf_counter() - t:.0f} s"
        )
        print(
            f"geoortho: {ours['wall']:.1f} s = {mp_o / ours['wall']:.2f} Mpx/s; stages "
            + ", ".join(f"{k} {v:.1f} s" for k, v in ours["seconds"].items())
            + f"; seam mismatch {ours['seam_raw']:.1f} -> {ours['seam_bal']:.1f} DN"
        )
        print(
            f"baseline (GDAL warp + merge): {base['wall']:.1f} s = {mp_b / base['wall']:.2f} Mpx/s "
            f"(warping {base['warp']:.1f} s)"
        )
        peak_o = max(own_o, kids_o) / 1024
        print(
            f"peak RSS: geoortho main {own_o / 1024:.0f} MB, largest worker {kids_o / 1024:.0f} MB; "
            f"baseline {max(own_b, kids_b) / 1024:.0f} MB (target < 2048 MB for medium: "
            f"{'met' if peak_o < 2048 else 'NOT met'})"
        )
        ratio = ours["wall"] / base["wall"]
        print(f"time ratio geoortho / baseline: {ratio:.2f} (target <= 2: {'met' if ratio <= 2 else 'NOT met'})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
