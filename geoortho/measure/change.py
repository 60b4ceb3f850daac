"""``change``: what changed between two surveys of one site (their DSMs):
the second brought onto the first on the ground that did not change, their difference, a level of
detection per cell from both surveys' noise and the fit's, and the cut and fill areas beyond it as
polygons with their volumes.

Fill is where the second survey is higher (material added), cut where it is lower (removed).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from geoortho.core.folders import project_dsm
from geoortho.errors import InputError
from geoortho.feedback import Feedback, as_feedback
from geoortho.measure.accuracy import NOISE_CORRELATION_M, run_noise, wall_place_m, walls_sigma_m3
from geoortho.measure.coregister import Grid, cells_of, coregister, moved

__all__ = ["ChangeResult", "change"]

#: 95 % of a normal error lies within this many sigma: the level of detection's factor.
LOD_SIGMAS = 1.96


@dataclass(frozen=True)
class ChangeResult:
    """What changed.

    Attributes
    ----------
    output : Path
        The difference (second minus first, after the fit), a GeoTIFF on the first's grid.
    polygons : Path
        The GeoPackage (layer ``change``): each area beyond the level of detection, its kind (cut or
        fill), area_m2, volume_m3 (positive for fill, negative for cut), sigma_m3 (1 sigma: the
        surveys' noise over its patches, the fit's vertical sigma over its area and its walls') and
        sigma_walls_m3 (the walls' part: where each survey put the walls of what was built or dug).
    shift_x_m : float
        How far the second survey was moved east to sit on the first.
    shift_y_m : float
        North.
    shift_z_m : float
        Up.
    rotation_deg : float
        The turn about the vertical (counter-clockwise).
    tilt_deg : float
        The tilt taken out (the steepest of the two slopes).
    residual_m : float
        The difference's robust spread (NMAD) on the ground that did not change, after the fit.
    stable_share : float
        The share of the common cells that agreed (did not change).
    lod_m : float
        The level of detection on flat ground (95 %): a difference smaller than this is not called
        change; on a slope it grows with the slope times how well the fit placed the surveys (at
        least a cell over the square root of 12).
    area_lod_m : float
        The level of detection of an area's mean difference: how far the mean of a patch a metre
        wide strays on the ground that did not change (the largest of them): two photogrammetric
        surfaces differ by such patches, not by independent cells.
    n_interpolated : int
        Areas beyond the levels of detection left out because they stand mostly on a surface
        interpolated in either survey (its run's dsm_source): no measured change.
    n_cut : int
        Cut areas found (at least ``min_area_m2``).
    n_fill : int
        Fill areas found.
    cut_m3 : float
        Volume removed (positive, m³).
    fill_m3 : float
        Volume added (m³).
    seconds : float
        Time taken.
    """

    output: Path
    polygons: Path
    shift_x_m: float
    shift_y_m: float
    shift_z_m: float
    rotation_deg: float
    tilt_deg: float
    residual_m: float
    stable_share: float
    lod_m: float
    area_lod_m: float
    n_interpolated: int
    n_cut: int
    n_fill: int
    cut_m3: float
    fill_m3: float
    seconds: float


def change(
    reference: Path,
    compare: Path,
    output: Path,
    polygons: Path,
    *,
    noise_m: float | None = None,
    min_area_m2: float = 1.0,
    feedback: Feedback | None = None,
) -> ChangeResult:
    """The change between two surveys of one site, the second brought onto the first.

    Parameters
    ----------
    reference : Path
        The first survey's DSM, or its run project's folder (its dem/dsm.tif; a run's noise is read
        beside its DSM).
    compare : Path
        The second survey's DSM, or its run project's folder. It may start metres away from the
        first and turned (two flights on GPS alone; found to 2 cm from 13 m and 1 degree apart on
        an 80 m site): the fit runs coarse to fine, and needs relief in more than one direction to
        fix the horizontal shift (a flat field fixes only the height).
    output : Path
        The difference raster (GeoTIFF).
    polygons : Path
        The cut and fill areas (GeoPackage).
    noise_m : float
        Each survey's noise (1 sigma, metres). Default: the runs' dem measure where both are runs,
        else the fit's residual on stable ground split between the two.
    min_area_m2 : float
        A cut or fill area smaller than this is left out (m²).
    """
    import rasterio
    from pyproj import CRS

    fb = as_feedback(feedback)
    started = time.perf_counter()
    a_path, b_path = _dsm_of(Path(reference)), _dsm_of(Path(compare))
    with rasterio.open(a_path) as ds:
        if ds.crs is None:
            raise InputError("the DSM has no CRS", path=a_path)
        crs = CRS.from_user_input(ds.crs)
        ta = ds.transform
        az = ds.read(1, masked=True).astype(np.float64).filled(np.nan)
    with rasterio.open(b_path) as ds:
        if ds.crs is None or CRS.from_user_input(ds.crs) != crs:
            raise InputError(f"not in the first survey's CRS ({crs.to_string()}): give both in one CRS", path=b_path)
        tb = ds.transform
        bz = ds.read(1, masked=True).astype(np.float64).filled(np.nan)
    from geoortho.core.surface import refuse_unless_north_up

    for t, p in ((ta, a_path), (tb, b_path)):
        refuse_unless_north_up(t, p)
    a = Grid.of(az, ta.c + ta.a / 2, ta.f + ta.e / 2, ta.a)
    b = Grid.of(bz, tb.c + tb.a / 2, tb.f + tb.e / 2, tb.a)
    fb.info("bringing the second survey onto the first on the ground that did not change ...")
    fit = coregister(a, b)
    fb.progress(0.6)
    xs, ys, za = a.centres()
    zb, _, _ = moved(b, xs, ys, fit.params, fit.centre)
    diff = np.full(az.shape, np.nan)
    rr, cc = np.nonzero(np.isfinite(az))
    diff[rr, cc] = zb - za
    common = np.isfinite(diff)
    if common.sum() < 100:
        raise InputError("the two surveys share almost no ground: not the same site?", path=b_path)
    stable_share = float(fit.inliers[common].mean())
    sigma_a, sigma_b, said = _noise(a_path, b_path, noise_m, fit.residual)
    sigma_d = math.sqrt(sigma_a**2 + sigma_b**2 + fit.sigma[2] ** 2)
    # where the ground is steep, a place known to a fraction of a cell is a height known to that
    # times the slope: a wall's cells differ by metres for a millimetre's shift, and are no change
    sigma_h = max(float(np.max(fit.sigma[:2])), ta.a / math.sqrt(12.0))
    slope = np.hypot(a.slope_x, a.slope_y).astype(np.float64)
    lod_cells = LOD_SIGMAS * np.sqrt(sigma_d**2 + (np.nan_to_num(slope) * sigma_h) ** 2)
    lod = LOD_SIGMAS * sigma_d
    cell_m2 = ta.a * ta.a
    guessed = np.zeros(az.shape, bool)
    guessed[rr, cc] = _interpolated(a_path, None, xs, ys) | _interpolated(b_path, (b, fit.params, fit.centre), xs, ys)
    # a new or removed object's walls stand where each survey's dense cloud put them
    place_m = math.hypot(wall_place_m(a_path, ta.a), wall_place_m(b_path, ta.a))
    frame, cut, fill, area_lod, (n_guessed, n_within) = _areas(
        diff, lod_cells, guessed, ta, crs, min_area_m2, cell_m2, (sigma_d, fit.sigma[2], place_m)
    )
    from geoortho.core.outputs import write_cog, write_vector
    from geoortho.core.styles import difference, product_styles, write_raster_style

    write_cog(output, diff.astype(np.float32), transform=ta, crs=crs, nodata=float("nan"),
              band_names=("second minus first",), units="metre")  # fmt: skip
    write_raster_style(output, difference(Path(output)))
    write_vector(polygons, {"change": frame}, styles=product_styles("change"), empty_as={"change": "Polygon"})
    dx, dy, dz, turn, tx, ty = fit.params
    tilt = math.degrees(math.atan(math.hypot(tx, ty)))
    fb.info(
        f"moved {dx:+.2f} m east, {dy:+.2f} m north, {dz:+.2f} m up, turned {math.degrees(turn):+.3f}°; "
        f"stable ground {100 * stable_share:.0f} %, residual {fit.residual:.3f} m; level of detection "
        f"{lod:.3f} m ({said}), of an area's mean {area_lod:.3f} m; {int((frame['kind'] == 'cut').sum())} cut, "
        f"{int((frame['kind'] == 'fill').sum())} fill areas: cut {cut:,.1f} m³, fill {fill:,.1f} m³"
        + (f"; {n_within} area(s) left out, their volume within {LOD_SIGMAS} sigma of its own" if n_within else "")
    )
    if n_guessed:
        fb.warning(
            f"{n_guessed} area(s) beyond the level of detection stand mostly on surface interpolated in one "
            "survey or both (dsm_source): left out, they are no measured change"
        )
    if max(abs(fit.sigma[0]), abs(fit.sigma[1])) > fit.residual * 10 or not np.isfinite(fit.sigma[:2]).all():
        fb.warning("the horizontal shift is poorly fixed (too little relief in some direction): check the fit")
    return ChangeResult(
        Path(output), Path(polygons), float(dx), float(dy), float(dz), math.degrees(turn), tilt, fit.residual,
        stable_share, lod, area_lod, n_guessed, int((frame["kind"] == "cut").sum()),
        int((frame["kind"] == "fill").sum()), cut, fill,
        time.perf_counter() - started,
    )  # fmt: skip


def _dsm_of(path: Path) -> Path:
    """A DSM that is there: the file, or a run project's."""
    path = project_dsm(path)
    if not path.is_file():
        raise InputError("no such file", path=path)
    return path


def _noise(a: Path, b: Path, noise_m: float | None, residual: float) -> tuple[float, float, str]:
    """Each survey's noise: as given, the runs' own, else the fit's residual split between them."""
    if noise_m is not None:
        return float(noise_m), float(noise_m), "noise as given"
    found = [run_noise(p) for p in (a, b)]
    if all(math.isfinite(f) for f in found):
        return found[0], found[1], "each run's noise on open ground"
    half = residual / math.sqrt(2.0)
    return half, half, "the residual on stable ground, shared between the surveys"


#: An area more than this share of which stands on a surface interpolated in either survey (its
#: ``dsm_source``) is no measured change: its difference is two guesses' (left out, and counted).
MAX_INTERPOLATED_SHARE = 0.5


def _interpolated(
    dsm: Path, moved_by: tuple[Grid, np.ndarray, tuple[float, float]] | None, xs: np.ndarray, ys: np.ndarray
) -> np.ndarray:
    """Which of the first survey's cells (xs, ys) stand on a surface this survey interpolated (its
    run's ``dsm_source.tif`` beside the DSM; none known without one). ``moved_by``: the second
    survey's grid and the fit that moved it."""
    import rasterio

    from geoortho.core.surface import sample_grid
    from geoortho.elevation.coverage import MEASURED

    source = dsm.with_name("dsm_source.tif")
    if not source.is_file():
        return np.zeros(xs.size, bool)
    with rasterio.open(source) as ds:
        code, t = ds.read(1), ds.transform
    guess = ((code != MEASURED) & (code != 0)).astype(np.float32)
    if moved_by is None:
        cols, rows = (xs - t.c) / t.a - 0.5, (ys - t.f) / t.e - 0.5
    else:
        cols, rows = cells_of(moved_by[0], xs, ys, moved_by[1], moved_by[2])
    on_guess: np.ndarray = np.nan_to_num(sample_grid(guess, cols, rows, nearest=True), nan=0.0).ravel() > 0.5
    return on_guess


def _areas(
    diff: np.ndarray, lod: np.ndarray, guessed: np.ndarray, transform: Any, crs: Any, min_area_m2: float,
    cell_m2: float, sigmas: tuple[float, float, float],
) -> tuple[Any, float, float, float, tuple[int, int]]:  # fmt: skip
    """The cut and fill areas beyond each cell's level of detection, as polygons with their volumes;
    the level of detection of an area's mean; how many areas stood on interpolated surface, and how
    many had a volume within their own level of detection (LOD_SIGMAS of their sigma_m3: on the
    tiny survey flown twice, the edge of a building each survey placed otherwise, 4.8 m³ ± 13.5).

    ``sigmas``: the difference's noise per cell (m), the fit's vertical sigma (m), and how far the
    two surveys may each have put a wall, together (m). An area's sigma_m3 joins the noise over its
    patches, the vertical fit over its area, and its walls (sigma_walls_m3: the steep cells of the
    difference around it, each as far off as that)."""
    import geopandas as gpd
    import shapely
    from rasterio.features import shapes
    from scipy import ndimage

    rows: list[dict[str, Any]] = []
    geoms = []
    patch_m2 = max(cell_m2, NOISE_CORRELATION_M**2)
    cell_m = math.sqrt(cell_m2)
    area_lod = _area_lod(diff, lod, cell_m)
    n_guessed = n_within = 0
    sigma_d, sigma_z, place_m = sigmas
    for kind, mask in (("fill", diff > lod), ("cut", diff < -lod)):
        mask = ndimage.binary_opening(np.nan_to_num(mask, nan=0).astype(bool))  # a lone cell is noise
        labels, n = ndimage.label(mask)
        if n == 0:
            continue
        counts = np.bincount(labels.ravel())
        sums = ndimage.sum(np.nan_to_num(diff), labels, np.arange(1, n + 1))
        # an area as large as asked, whose mean stands out of how the surveys differ where nothing changed
        big = counts[1:] * cell_m2 >= min_area_m2
        stands_out = big & (np.abs(sums) >= area_lod * counts[1:])
        on_guess = ndimage.sum(guessed, labels, np.arange(1, n + 1)) > MAX_INTERPOLATED_SHARE * counts[1:]
        n_guessed += int((stands_out & on_guess).sum())
        keep = np.flatnonzero(stands_out & ~on_guess) + 1
        kept = np.isin(labels, keep) & (labels > 0)
        by_label: dict[int, list[Any]] = {}
        for geom, value in shapes(labels.astype(np.int32), mask=kept, transform=transform):
            by_label.setdefault(int(value), []).append(shapely.geometry.shape(geom))
        boxes = ndimage.find_objects(labels)
        for lab in keep:
            area = float(counts[lab] * cell_m2)
            vol = float(sums[lab - 1] * cell_m2)
            walls = _walls_sigma(diff, labels, int(lab), boxes[lab - 1], cell_m, place_m)
            sigma = math.sqrt((sigma_d * math.sqrt(area * patch_m2)) ** 2 + (sigma_z * area) ** 2 + walls**2)
            if abs(vol) < LOD_SIGMAS * sigma:  # within its own uncertainty (an edge placed otherwise)
                n_within += 1
                continue
            geoms.append(shapely.union_all(by_label.get(int(lab), [])))
            rows.append({"kind": kind, "area_m2": area, "volume_m3": vol, "sigma_m3": sigma, "sigma_walls_m3": walls})
    columns: dict[str, list[Any]] = {"kind": [], "area_m2": [], "volume_m3": [], "sigma_m3": [], "sigma_walls_m3": []}
    frame = gpd.GeoDataFrame(rows or columns, geometry=geoms, crs=crs)
    cut = float(-frame.loc[frame["kind"] == "cut", "volume_m3"].sum()) if len(frame) else 0.0
    fill = float(frame.loc[frame["kind"] == "fill", "volume_m3"].sum()) if len(frame) else 0.0
    return frame, cut, fill, area_lod, (n_guessed, n_within)


def _walls_sigma(
    diff: np.ndarray, labels: np.ndarray, label: int, box: tuple[slice, slice], cell_m: float, place_m: float
) -> float:
    """An area's volume uncertainty from its walls (m³): the difference's steep cells over the area
    and a cell around it (a new building's wall stands on its edge), each wall as far off as
    ``place_m``."""
    from scipy import ndimage

    rows = slice(max(box[0].start - 2, 0), box[0].stop + 2)
    cols = slice(max(box[1].start - 2, 0), box[1].stop + 2)
    region = ndimage.binary_dilation(labels[rows, cols] == label)
    return walls_sigma_m3(diff[rows, cols], region, cell_m, place_m)


#: Ground is flat for the area's level of detection where its cell's level is within this factor of
#: the flattest cell's (the slope's part is then under the noise's).
FLAT_LOD_FACTOR = 1.5


def _area_lod(diff: np.ndarray, lod: np.ndarray, cell_m: float) -> float:
    """How far the mean of a patch (NOISE_CORRELATION_M wide) of the stable ground strays: the
    largest magnitude of any. Two photogrammetric surfaces differ there by patches a matching
    window wide, not by independent cells: on the tiny survey flown twice (512 px depth maps) the
    cells' NMAD was 0.015 m but 1 % of the 1 m patches stood 0.13 m off, and the per-cell level of
    detection (0.05 m) called 33 such areas of 1-25 m² change. A quantile of the patches is no
    bound: its 99.9th percentile (0.091 m) still let through the thousandth of some 5,000 patches
    that lies beyond it by chance, 7 areas of 1-4 m² whose means were 0.09-0.12 m; the largest is
    what the site's stable ground itself shows (a change whose mean is below it is not told
    from how the surveys differ)."""
    from scipy.ndimage import binary_dilation, uniform_filter

    ok = np.isfinite(diff)
    k = max(1, int(round(NOISE_CORRELATION_M / cell_m)))
    # the stable ground: away from what plainly changed (five levels of detection: a pile, a wall),
    # its own strays kept, since they are what is measured
    changed = ok & (np.abs(np.nan_to_num(diff)) > 5.0 * np.nan_to_num(lod, nan=np.inf))
    # and flat: on a slope or a wall a place known to a fraction of a cell is a height known to
    # metres (the cell's level of detection says so), and its patches are no measure of the noise
    flat = np.nan_to_num(lod, nan=np.inf) <= FLAT_LOD_FACTOR * float(np.nanmin(lod))
    stable = ok & flat & ~binary_dilation(changed | ~flat, np.ones((2 * k + 1, 2 * k + 1), bool))
    num = uniform_filter(np.where(stable, diff, 0.0), k, mode="constant")
    den = uniform_filter(stable.astype(np.float64), k, mode="constant")
    full = stable & (den > 0.99)
    if full.sum() < 100:
        return 0.0
    return float(np.max(np.abs(num[full] / den[full])))
