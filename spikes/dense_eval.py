"""dense_eval.py DENSE_LAZ TRUTH_DIR OUT_DIR [method]: DSM from the dense cloud vs the true DSM."""

import json
import sys
from pathlib import Path

import numpy as np
import rasterio
from rasterio.warp import Resampling, reproject

import geoortho

laz, truth, out = map(Path, sys.argv[1:4])
method = sys.argv[4] if len(sys.argv) > 4 else "max"
info = json.loads((truth / "survey.json").read_text())
gsd = info["gsd_cm_at_home_height"] / 100
cell = 2 * gsd
r = geoortho.dem(laz, out / f"dense_dsm_{method}.tif", resolution_m=cell, method=method, max_gap_m=0)
with rasterio.open(r.dsm) as src:
    z = src.read(1, masked=True).filled(np.nan)
    tr, crs = src.transform, src.crs
    shape = z.shape


def onto(path):
    a = np.full(shape, np.nan, np.float32)
    with rasterio.open(path) as s:
        reproject(rasterio.band(s, 1), a, dst_transform=tr, dst_crs=crs, resampling=Resampling.bilinear,
                  dst_nodata=np.nan)
    return a


tdsm, tdtm = onto(truth / "dsm.tif"), onto(truth / "dtm.tif")
fx0, fy0, fx1, fy1 = info["flight_box"]
rows, cols = np.indices(shape)
xs, ys = tr * (cols + 0.5, rows + 0.5)
inside = (xs >= fx0) & (xs <= fx1) & (ys >= fy0) & (ys <= fy1)
dz = z - tdsm
h = tdsm - tdtm
# open ground: flat within 2 cells (no edges)
from scipy import ndimage

open_ground = inside & (ndimage.maximum_filter(h, 5) < 0.2)
roofs = inside & (ndimage.minimum_filter(h, 5) > 3.0)
comp = float(np.isfinite(z[inside]).mean())
og = dz[open_ground & np.isfinite(dz)]
rf = dz[roofs & np.isfinite(dz)]
res = {
    "gsd_m": gsd, "cell_m": cell, "method": method, "completeness": round(comp, 4),
    "open_median_abs_dz_gsd": round(float(np.median(np.abs(og))) / gsd, 2) if og.size else None,
    "open_rmse_gsd": round(float(np.sqrt(np.mean(og ** 2))) / gsd, 2) if og.size else None,
    "open_bias_m": round(float(np.median(og)), 3) if og.size else None,
    "roof_median_dz_m": round(float(np.median(rf)), 3) if rf.size else None,
    "roof_p90_abs_m": round(float(np.percentile(np.abs(rf), 90)), 3) if rf.size else None,
    "n_open": int(og.size), "n_roof": int(rf.size),
}
print(json.dumps(res))
