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

__all__ = [
    "ChangeScores",
    "GhostScores",
    "OrthoScores",
    "SurfaceScores",
    "score_changes",
    "score_movers",
    "score_ortho",
    "score_surfaces",
]

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


def _band_on_grid(path: Path, transform: Any, crs: Any, shape: tuple[int, int], band: int = 1) -> np.ndarray:
    """One band of a raster resampled (bilinear) onto another grid, float32, NaN where it has none."""
    import rasterio
    from rasterio.warp import Resampling, reproject

    out = np.full(shape, np.nan, np.float32)
    with rasterio.open(path) as src:
        reproject(
            rasterio.band(src, band), out, dst_transform=transform, dst_crs=crs,
            resampling=Resampling.bilinear, dst_nodata=np.nan,
        )  # fmt: skip
    return out


def _on_grid(path: Path, transform: Any, crs: Any, shape: tuple[int, int]) -> np.ndarray:
    return _band_on_grid(path, transform, crs, shape).astype(np.float64)


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


#: An object this high (m) with a roof's colour is a building for the roof-edge measure.
BUILDING_M = 2.0
#: Roof edges are measured this far (m) either side of the true outline, in pieces this long (m).
EDGE_BAND_M = 1.0
EDGE_PIECE_M = 0.5
#: A piece is scored where the true orthophoto's own edge lies this close to the outline (GSD).
#: Where a roof's colour is near the ground's, the strongest line across its outline is the dark
#: rim the scene draws inside the roof: the moving-cars survey (seed 5) has two such buildings,
#: where the truth itself measured 3.7 GSD, and a piece there says nothing of the orthophoto's edge.
EDGE_TRUTH_GSD = 1.0


@dataclass(frozen=True)
class OrthoScores:
    """An orthophoto against the survey's true orthophoto (issue 75's measures)."""

    gsd_m: float
    ssim_open: float  # structural similarity on open ground (grey, the ortho's gain and offset fitted)
    ssim_near_objects: float  # the same within NEAR_M of an object, objects included
    roof_edge_error_gsd: float  # median |offset| of the roof edges from the true outlines, in GSD, on the
    # pieces where the true orthophoto's own edge is found at the outline (within EDGE_TRUTH_GSD)
    roof_edge_error_truth_gsd: float  # the same measure on the true orthophoto, every piece: its own floor
    roof_edge_pieces: int  # outline pieces measured (the first figure's)
    roof_edge_error_all_gsd: float  # the first figure over every piece either measure found an edge on
    holes_inside_m2: float  # transparent area enclosed by the mosaic that the photos saw twice

    def as_dict(self) -> dict[str, float]:
        return asdict(self)


def _ortho_and_truth(truth: Path, ortho: Path) -> tuple[np.ndarray, np.ndarray, Any, Any, np.ndarray]:
    """An orthophoto's RGB (float32) and alpha, its transform and CRS, and the true orthophoto's
    three bands on its grid (bilinear, float32 0..255, NaN where the truth has none)."""
    import rasterio

    with rasterio.open(ortho) as ds:
        rgb = ds.read([1, 2, 3]).astype(np.float32)
        alpha = ds.read(4) if ds.count >= 4 else ds.dataset_mask()
        t, crs = ds.transform, ds.crs
    true_rgb = np.stack([_band_on_grid(truth / "ortho.tif", t, crs, alpha.shape, b) for b in (1, 2, 3)])
    return rgb, alpha, t, crs, true_rgb


def _enclosed(empty: np.ndarray) -> np.ndarray:
    """The ``empty`` cells that do not reach the raster's border through empty cells."""
    labels, _ = ndimage.label(empty)
    border = np.unique(np.r_[labels[0], labels[-1], labels[:, 0], labels[:, -1]])
    return empty & ~np.isin(labels, border[border > 0])


def _grey(rgb: np.ndarray) -> np.ndarray:
    result: np.ndarray = (0.299 * rgb[0] + 0.587 * rgb[1] + 0.114 * rgb[2]).astype(np.float64)
    return result


def _edge_offsets_m(grey: np.ndarray, valid: np.ndarray, buildings: np.ndarray, cell_m: float) -> np.ndarray:
    """Per piece of the buildings' true outline (``EDGE_PIECE_M`` long), how far (m, + outward)
    from it ``grey``'s edge lies: the piece's mean gradient profile across the outline (cells
    binned by their distance from it, within ``EDGE_BAND_M``), its peak refined to a fraction of a
    cell by a parabola through the peak and its neighbours. The outline's cells are the roof's
    last, so the true edge lies half a cell out. NaN where a piece's profile is incomplete or
    peaks at its ends; the pieces are the same for every ``grey`` of the same ``valid``."""
    import cv2

    smooth = cv2.GaussianBlur(np.where(valid, grey, 0.0).astype(np.float32), (0, 0), 1.0)
    grad = np.hypot(cv2.Sobel(smooth, cv2.CV_32F, 1, 0), cv2.Sobel(smooth, cv2.CV_32F, 0, 1))
    outline = buildings & ~ndimage.binary_erosion(buildings)
    if not outline.any():
        return np.zeros(0)
    dist, (ri, ci) = ndimage.distance_transform_edt(~outline, return_indices=True)
    reach = int(round(EDGE_BAND_M / cell_m))
    step = np.rint(np.where(buildings, -dist, dist)).astype(np.int64)  # cells from the outline, + outward
    # the band's cells, and none whose smoothing read past the ortho's edge
    band = (np.abs(step) <= reach) & ndimage.binary_erosion(valid, iterations=3)
    k = max(1, int(round(EDGE_PIECE_M / cell_m)))
    _, piece = np.unique(ri[band] // k * (buildings.shape[1] // k + 1) + ci[band] // k, return_inverse=True)
    n_pieces = int(piece.max()) + 1 if piece.size else 0
    if not n_pieces:
        return np.zeros(0)
    width = 2 * reach + 1
    slot = piece * width + (step[band] + reach)
    n = np.bincount(slot, minlength=n_pieces * width).reshape(n_pieces, width)
    g = np.bincount(slot, grad[band], minlength=n_pieces * width).reshape(n_pieces, width)
    profile = np.where(n > 0, g / np.maximum(n, 1), 0.0)
    peak = np.argmax(profile, axis=1)
    inner = (peak > 0) & (peak < width - 1) & (n.min(axis=1) > 0)
    j = peak[inner]
    rows = np.nonzero(inner)[0]
    lo, mid, hi = profile[rows, j - 1], profile[rows, j], profile[rows, j + 1]
    curve = lo - 2.0 * mid + hi
    delta = np.where(curve < 0, 0.5 * (lo - hi) / np.where(curve < 0, curve, -1.0), 0.0)
    out = np.full(n_pieces, np.nan)
    out[rows] = ((j - reach + np.clip(delta, -0.5, 0.5)) - 0.5) * cell_m
    return out


def score_ortho(truth: Path, ortho: Path) -> OrthoScores:
    """Score the orthophoto ``ortho`` (RGB + alpha) against the survey's ``truth`` folder."""
    from skimage.metrics import structural_similarity

    truth = Path(truth)
    info = json.loads((truth / "survey.json").read_text())
    gsd_m = float(info["gsd_cm_at_home_height"]) / 100.0
    rgb, alpha, t, crs, true_rgb = _ortho_and_truth(truth, Path(ortho))
    shape = alpha.shape
    cell = abs(t.a)
    have = alpha > 0
    true_dsm = _on_grid(truth / "dsm.tif", t, crs, shape)
    true_dtm = _on_grid(truth / "dtm.tif", t, crs, shape)
    seen = _seen_twice(truth, t, shape)
    height = true_dsm - true_dtm
    objects = height > OBJECT_M
    near = np.asarray(ndimage.distance_transform_edt(~objects)) * cell <= NEAR_M
    ok = have & seen & np.isfinite(true_rgb).all(axis=0) & np.isfinite(height)
    grey, true_grey = _grey(rgb), _grey(np.nan_to_num(true_rgb))
    # the photos' exposure and vignetting are not the scene's colours: one gain and offset, fitted
    a, b = np.polyfit(grey[ok & ~near], true_grey[ok & ~near], 1) if (ok & ~near).sum() > 100 else (1.0, 0.0)
    fitted = np.where(have, a * grey + b, true_grey)
    _, ssim_map = structural_similarity(
        fitted, true_grey, data_range=255.0, gaussian_weights=True, sigma=1.5, use_sample_covariance=False, full=True
    )
    # buildings: objects standing BUILDING_M high that are not the trees' green; their outline where
    # the scene's colour turns from ground to roof (0.25 m up its wall)
    labels, n = ndimage.label(objects)
    buildings = np.zeros(shape, bool)
    for i, sl in enumerate(ndimage.find_objects(labels), 1):
        m = labels[sl] == i
        r, g, bl = (float(np.mean(np.nan_to_num(true_rgb[c][sl][m]))) for c in range(3))
        if np.nanmax(height[sl][m]) > BUILDING_M and not (g > 1.25 * r and g > 1.25 * bl):
            buildings[sl] |= m
    ours = _edge_offsets_m(fitted, ok, buildings, cell)
    floor = _edge_offsets_m(true_grey, ok, buildings, cell)
    scored = np.isfinite(ours) & (np.abs(floor) <= EDGE_TRUTH_GSD * gsd_m)
    found, floor = ours[np.isfinite(ours)], floor[np.isfinite(floor)]
    return OrthoScores(
        gsd_m=gsd_m,
        ssim_open=float(np.mean(ssim_map[ok & ~near])) if (ok & ~near).any() else math.nan,
        ssim_near_objects=float(np.mean(ssim_map[ok & near])) if (ok & near).any() else math.nan,
        roof_edge_error_gsd=float(np.median(np.abs(ours[scored]))) / gsd_m if scored.any() else math.nan,
        roof_edge_error_truth_gsd=float(np.median(np.abs(floor))) / gsd_m if floor.size else math.nan,
        roof_edge_pieces=int(scored.sum()),
        roof_edge_error_all_gsd=float(np.median(np.abs(found))) / gsd_m if found.size else math.nan,
        holes_inside_m2=float((_enclosed(~have) & seen).sum()) * cell * cell,
    )


#: A difference from the truth is a mover's where its colour is this far off (0..255, RGB distance,
#: after a 1-pixel smoothing) ...
MOVER_DIFF_DN = 45.0
#: ... over at least this share of the mover's top (less: noise); a whole one covers GHOST_WHOLE of it.
GHOST_MIN_SHARE, GHOST_WHOLE = 0.2, 0.6


@dataclass(frozen=True)
class GhostScores:
    """Moving cars and people in an orthophoto against the static truth: where each one's track
    runs, the car-shaped differences found (issue 75: "0 ghosts", a mover once and whole or not
    at all)."""

    movers: int
    whole: int  # appearances whole (a mover may appear once)
    ghosts: int  # partial appearances, and appearances beyond a mover's first
    per_mover: tuple[tuple[str, int, int], ...]  # (kind, whole, partial)

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


def score_movers(truth: Path, ortho: Path, kinds: tuple[str, ...] = ("car", "person")) -> GhostScores:
    """Count the appearances of the survey's movers (``survey.json``'s movers) in ``ortho``."""
    import cv2

    truth = Path(truth)
    movers = [m for m in json.loads((truth / "survey.json").read_text()).get("movers", []) if m["kind"] in kinds]
    rgb, alpha, t, _, true_rgb = _ortho_and_truth(truth, Path(ortho))
    ok = (alpha > 0) & np.isfinite(true_rgb).all(axis=0)
    fitted = np.empty_like(rgb)
    for c in range(3):  # the photos' exposure is not the scene's colour: a gain and offset per band
        a, b = np.polyfit(rgb[c][ok][::50], true_rgb[c][ok][::50], 1) if ok.sum() > 1000 else (1.0, 0.0)
        fitted[c] = a * rgb[c] + b
    diff = np.sqrt(np.sum((fitted - np.nan_to_num(true_rgb)) ** 2, axis=0))
    diff = cv2.GaussianBlur(np.where(ok, diff, 0.0).astype(np.float32), (0, 0), 1.0)
    cell = abs(t.a)
    per: list[tuple[str, int, int]] = []
    for m in movers:
        h = math.radians(m["heading_deg"])
        fwd = np.array([math.sin(h), math.cos(h)])
        reach = m["length_m"] / 2 + 1.0
        ends = np.array([[m["x0"], m["y0"]], [m["x0"], m["y0"]] + m["track_m"] * fwd]) + [
            [*(-reach * fwd)],
            [*(reach * fwd)],
        ]
        half_w = m["width_m"] / 2 + 1.0
        xs, ys = ends[:, 0], ends[:, 1]
        c0, r0 = ~t * (xs.min() - half_w, ys.max() + half_w)
        c1, r1 = ~t * (xs.max() + half_w, ys.min() - half_w)
        r0, c0 = max(0, int(r0)), max(0, int(c0))
        r1, c1 = min(alpha.shape[0], int(math.ceil(r1))), min(alpha.shape[1], int(math.ceil(c1)))
        if r1 <= r0 or c1 <= c0:
            per.append((m["kind"], 0, 0))
            continue
        cc, rr = np.meshgrid(np.arange(c0, c1) + 0.5, np.arange(r0, r1) + 0.5)
        px, py = t.c + cc * t.a, t.f + rr * t.e
        # distance from the track's segment (its ends widened by half a mover and a metre)
        seg = ends[1] - ends[0]
        u = np.clip(((px - ends[0, 0]) * seg[0] + (py - ends[0, 1]) * seg[1]) / float(seg @ seg), 0.0, 1.0)
        dist = np.hypot(px - (ends[0, 0] + u * seg[0]), py - (ends[0, 1] + u * seg[1]))
        corridor = dist <= half_w
        found = (diff[r0:r1, c0:c1] > MOVER_DIFF_DN) & corridor
        found = cv2.morphologyEx(found.astype(np.uint8), cv2.MORPH_CLOSE, np.ones((3, 3), np.uint8)) > 0
        labels, n = ndimage.label(found & corridor)
        top_m2 = m["length_m"] * m["width_m"]
        areas = np.bincount(labels.ravel())[1:] * cell * cell
        whole = int(sum(max(1, round(a / top_m2)) for a in areas if a >= GHOST_WHOLE * top_m2))
        partial = int(sum(1 for a in areas if GHOST_MIN_SHARE * top_m2 <= a < GHOST_WHOLE * top_m2))
        per.append((m["kind"], whole, partial))
    whole = sum(w for _, w, _ in per)
    ghosts = sum(p + max(0, w - 1) for _, w, p in per)
    return GhostScores(movers=len(movers), whole=whole, ghosts=ghosts, per_mover=tuple(per))


@dataclass(frozen=True)
class ChangeScores:
    """A change's areas against the second epoch's true changes: per change, its name, the volume
    found over it and its true volume (m³); and the areas over no true change (count, m²)."""

    per_change: tuple[tuple[str, float, float], ...]
    n_other: int
    other_m2: float


def score_changes(truth: Path, polygons: Path) -> ChangeScores:
    """``change``'s cut and fill areas (their GeoPackage) against synth's second epoch (``truth``: its
    survey.json): an area counts for the true change whose circle holds a point of it."""
    import geopandas as gpd

    items = json.loads((truth / "survey.json").read_text())["cover"]["second_epoch"]["items"]
    areas = gpd.read_file(polygons, layer="change")
    centre = areas.geometry.representative_point()
    claimed = np.zeros(len(areas), bool)
    per = []
    for i in items:
        mine = np.hypot(centre.x - i["x"], centre.y - i["y"]).to_numpy() <= i["radius_m"]
        claimed |= mine
        per.append((str(i["name"]), float(areas.loc[mine, "volume_m3"].sum()), float(i["volume_m3"])))
    return ChangeScores(tuple(per), int((~claimed).sum()), float(areas.loc[~claimed, "area_m2"].sum()))
