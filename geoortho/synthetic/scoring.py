"""A DSM and a DTM scored against a synthetic survey's truth, as issue 74 measures them.

The truth is resampled onto the product's grid (bilinear), and the cells scored are those the
survey's true footprints cover at least twice (the ground the product must cover). Objects are
where the true DSM stands more than ``OBJECT_M`` above the true DTM; "near objects" is every
cell within ``NEAR_M`` of one, on either side of its edge; open ground is farther than that.
Where the DTM's source raster lies beside it, the DTM is also scored apart where it says it is a
guess (code 4, under an object with no ground seen) and where it does not.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
from scipy import ndimage

from geoortho.elevation.artefacts import roughness_m
from geoortho.elevation.coverage import UNDER_OBJECT, seen_count

__all__ = ["SurfaceScores", "score_surfaces"]

OBJECT_M = 0.2
NEAR_M = 3.0


@dataclass(frozen=True)
class SurfaceScores:
    """Metres unless the name says GSD."""

    gsd_m: float
    dtm_rmse_m: float
    dtm_p95_near_objects_m: float  # |dZ| within NEAR_M of an object, objects included
    dtm_p95_rim_m: float  # the same, outside the objects only (the rims)
    dtm_roughness_m: float  # open ground: DTM less its 1 m median, RMS
    truth_roughness_m: float  # the true DTM's, measured the same way
    dtm_roughness_excess_gsd: float  # the DTM's beyond the truth's (RMS difference), in GSD
    dsm_p95_near_objects_m: float
    dsm_bias_open_gsd: float  # median DSM - truth on open ground, in GSD
    dsm_rmse_open_m: float
    dtm_rmse_claimed_m: float = math.nan  # the DTM where its source does not call it a guess
    dtm_guess_share: float = math.nan  # of the scored cells, those its source calls a guess (code 4)
    dtm_guess_rmse_m: float = math.nan

    def as_dict(self) -> dict[str, float]:
        return asdict(self)


def _on_grid(path: Path, transform: Any, crs: Any, shape: tuple[int, int]) -> np.ndarray:
    import rasterio
    from rasterio.warp import Resampling, reproject

    out = np.full(shape, np.nan, np.float32)
    with rasterio.open(path) as src:
        reproject(
            rasterio.band(src, 1), out, dst_transform=transform, dst_crs=crs,
            resampling=Resampling.bilinear, dst_nodata=np.nan,
        )  # fmt: skip
    return out.astype(np.float64)


def _read(path: Path) -> tuple[np.ndarray, Any, Any]:
    import rasterio

    with rasterio.open(path) as ds:
        return ds.read(1, masked=True).filled(np.nan).astype(np.float64), ds.transform, ds.crs


def _seen_twice(truth: Path, transform: Any, shape: tuple[int, int]) -> np.ndarray:
    import geopandas as gpd

    fp = gpd.read_file(truth / "footprints.gpkg")
    return seen_count(list(fp.geometry), transform, shape) >= 2


def _p95(a: np.ndarray) -> float:
    return float(np.percentile(np.abs(a), 95)) if a.size else math.nan


def _rms(a: np.ndarray) -> float:
    return float(np.sqrt(np.mean(a**2))) if a.size else math.nan


def score_surfaces(truth: Path, dsm: Path, dtm: Path) -> SurfaceScores:
    """Score ``dsm`` and ``dtm`` (GeoTIFFs on one grid) against the survey's ``truth`` folder."""
    truth = Path(truth)
    info = json.loads((truth / "survey.json").read_text())
    gsd_m = float(info["gsd_cm_at_home_height"]) / 100.0
    z_dsm, t, crs = _read(Path(dsm))
    z_dtm, t2, _ = _read(Path(dtm))
    if t2 != t or z_dtm.shape != z_dsm.shape:
        raise ValueError("the DSM and the DTM are not on one grid")
    true_dsm = _on_grid(truth / "dsm.tif", t, crs, z_dsm.shape)
    true_dtm = _on_grid(truth / "dtm.tif", t, crs, z_dsm.shape)
    seen = _seen_twice(truth, t, z_dsm.shape)
    cell = abs(t.a)
    objects = (true_dsm - true_dtm) > OBJECT_M
    dist_m = np.asarray(ndimage.distance_transform_edt(~objects)) * cell
    near = dist_m <= NEAR_M
    scored = seen & np.isfinite(true_dtm) & np.isfinite(true_dsm)
    d_dtm = z_dtm - true_dtm
    d_dsm = z_dsm - true_dsm
    have_t = scored & np.isfinite(z_dtm)
    have_s = scored & np.isfinite(z_dsm)
    open_ground = scored & ~near
    rough = roughness_m(z_dtm, open_ground & np.isfinite(z_dtm), cell)
    rough_truth = roughness_m(true_dtm, open_ground & np.isfinite(z_dtm), cell)
    excess = math.sqrt(max(rough**2 - rough_truth**2, 0.0)) / gsd_m if math.isfinite(rough) else math.nan
    guess = np.zeros(z_dtm.shape, bool)
    src_path = Path(dtm).with_name(Path(dtm).stem + "_source.tif")
    if src_path.is_file():
        import rasterio

        with rasterio.open(src_path) as ds:
            guess = ds.read(1) == UNDER_OBJECT if ds.shape == z_dtm.shape else guess
    return SurfaceScores(
        dtm_rmse_claimed_m=_rms(d_dtm[have_t & ~guess]),
        dtm_guess_share=float((have_t & guess).sum() / max(1, int(have_t.sum()))),
        dtm_guess_rmse_m=_rms(d_dtm[have_t & guess]),
        gsd_m=gsd_m,
        dtm_rmse_m=_rms(d_dtm[have_t]),
        dtm_p95_near_objects_m=_p95(d_dtm[have_t & near]),
        dtm_p95_rim_m=_p95(d_dtm[have_t & near & ~objects]),
        dtm_roughness_m=rough,
        truth_roughness_m=rough_truth,
        dtm_roughness_excess_gsd=excess,
        dsm_p95_near_objects_m=_p95(d_dsm[have_s & near]),
        dsm_bias_open_gsd=float(np.median(d_dsm[have_s & ~near])) / gsd_m if (have_s & ~near).any() else math.nan,
        dsm_rmse_open_m=_rms(d_dsm[have_s & ~near]),
    )
