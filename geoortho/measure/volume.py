"""``volume``: the volume of stockpiles and pits over polygons of a DSM, above and below a base,
with an uncertainty drawn from the survey's own measured accuracy and the share that stands on
interpolated cells.

Cut is what stands above the base (material to take away), fill what lies below it (room to fill),
net their difference, as Pix4D and Metashape name them. A cell counts when its centre is inside the
polygon (QGIS's zonal rule).

The uncertainty (1 sigma) is said as three parts:

* **systematic**: a shift of the whole DSM (its datum: the checkpoints' vertical RMSE) moves a
  surface over a fixed base by ``area * sigma``; over a base drawn from the same DSM (its edge, its
  DTM) the shift moves both and cancels;
* **random**: the DSM's noise (the dem stage's ``ground_noise_m``, its spread on open ground),
  correlated over patches of ``NOISE_CORRELATION_M`` a side (a dense matcher's window): the
  patches add in quadrature;
* **base**: a base through the edge inherits the edge samples' noise, weighted by how much of the
  base each sample makes (exactly, from the triangulation), summed over the edge's patches;
* **walls**: where the surface is steeper than 45 degrees (a wall, a cut face) the DSM puts it
  within a cell at best, and a photogrammetric DSM within its dense matcher's reach: its place is
  taken as uncertain by ``WALL_VOXELS`` of the run's dense voxels (a cell over the square root of 12
  where none is known), the same way along the whole of it (a DSM that erodes or fattens objects does
  so on all their sides). The demo survey's buildings came out 0.2-15 % small, within that.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np

from geoortho.core.crs import horizontal_unit_m
from geoortho.errors import InputError, ParameterError
from geoortho.feedback import Feedback, as_feedback
from geoortho.measure.accuracy import (
    NOISE_CORRELATION_M,
    WALL_VOXELS,
    run_noise,
    run_vertical_accuracy,
    run_wall_place_m,
    walls_sigma_m3,
)

__all__ = ["VolumeResult", "volume"]

Base = Literal["edge-triangulated", "edge-lowest", "edge-mean", "fixed", "dtm"]
BASES: tuple[str, ...] = ("edge-triangulated", "edge-lowest", "edge-mean", "fixed", "dtm")
#: A polygon whose area is more than this share interpolated is said to be (its volume there is none).
INTERPOLATED_WARN = 0.2
#: dsm_source.tif's code for a cell interpolated across (geoortho.elevation.coverage).
INTERPOLATED = 2


@dataclass(frozen=True)
class VolumeResult:
    """The volumes measured.

    Attributes
    ----------
    output : Path
        The GeoPackage (layer ``volumes``): per polygon cut_m3, fill_m3, net_m3, sigma_m3 and its
        parts (systematic, random, base, walls), area_m2, base_method, base_m, interpolated_share,
        uncovered_share, note.
    n_polygons : int
        Polygons measured (a polygon wholly off the DSM is listed, with no volume, and not counted).
    cut_m3 : float
        Sum over the polygons of the volume above the base (m³).
    fill_m3 : float
        Sum of the volume below the base (m³).
    net_m3 : float
        Cut minus fill (m³).
    sigma_m3 : float
        The uncertainty (1 sigma) of the net sum, the polygons' systematic parts taken as one.
    accuracy_source : str
        Where the vertical accuracy and the noise came from.
    notes : list[str]
        What was assumed or left out.
    seconds : float
        Time taken.
    """

    output: Path
    n_polygons: int
    cut_m3: float
    fill_m3: float
    net_m3: float
    sigma_m3: float
    accuracy_source: str
    notes: list[str]
    seconds: float


@dataclass(frozen=True)
class _Accuracy:
    systematic_m: float  # NaN: unknown
    noise_m: float
    source: str
    walls_m: float = math.nan  # how far a wall's place is uncertain (NaN: a cell over sqrt(12))


def volume(
    dsm: Path,
    polygons: Path,
    output: Path,
    *,
    base: Base = "edge-triangulated",
    base_elevation_m: float | None = None,
    dtm: Path | None = None,
    vertical_accuracy_m: float | None = None,
    noise_m: float | None = None,
    feedback: Feedback | None = None,
) -> VolumeResult:
    """Cut, fill and net volume over each polygon of a DSM, with its uncertainty.

    Parameters
    ----------
    dsm : Path
        The surface (GeoTIFF); its ``<name>_source.tif`` beside it (dem writes one) gives the share on
        interpolated cells.
    polygons : Path
        The areas (any vector format, any CRS; a ``name`` column names them).
    output : Path
        The GeoPackage written (layer ``volumes``).
    base : str
        The base surface: edge-triangulated (a surface through the polygon's edge: stockpiles),
        edge-lowest (the edge's lowest point), edge-mean (the edge's mean), fixed (base_elevation_m),
        dtm (the DTM given: for what stands on the ground; a stockpile is ground in a DTM made from the
        same survey, so its volume over that DTM is about nothing).
    base_elevation_m : float
        The fixed base's elevation (the DSM's heights' datum and units: metres, or feet for a DSM in
        feet).
    dtm : Path
        The DTM for base dtm.
    vertical_accuracy_m : float
        The DSM's vertical accuracy (1 sigma, metres), a shift of the whole survey. Default: the run's
        checkpoints (vertical RMSE), else its GCPs', read beside a run's DSM.
    noise_m : float
        The DSM's random noise per cell (1 sigma, metres). Default: the run's dem stage's measure.
    """
    import geopandas as gpd
    import rasterio
    from pyproj import CRS

    from geoortho.core.surface import height_unit

    fb = as_feedback(feedback)
    started = time.perf_counter()
    if base not in BASES:
        raise ParameterError("base", f"{base!r}: choose one of {', '.join(BASES)}")
    if base == "fixed" and base_elevation_m is None:
        raise ParameterError("base_elevation_m", "base fixed needs base_elevation_m")
    if base == "dtm" and dtm is None:
        raise ParameterError("dtm", "base dtm needs a dtm")
    with rasterio.open(dsm) as ds:
        if ds.crs is None:
            raise InputError("the DSM has no CRS", path=dsm)
        crs = CRS.from_user_input(ds.crs)
        t = ds.transform
        if t.b != 0 or t.d != 0:
            raise InputError("the DSM is rotated: give it north up", path=dsm)
    frame = _read_polygons(Path(polygons), crs)
    accuracy = _accuracy(Path(dsm), vertical_accuracy_m, noise_m)
    unit = horizontal_unit_m(crs)
    z_unit = height_unit(crs)[1]
    source = Path(dsm).with_name(Path(dsm).stem + "_source.tif")
    notes: list[str] = []
    if not source.is_file():
        notes.append(f"no {source.name} beside the DSM: the share on interpolated cells is not known")
    rows: list[dict[str, Any]] = []
    for i, (geom, name) in enumerate(zip(frame.geometry, frame["__name"])):
        row = _measure(Path(dsm), source if source.is_file() else None, geom, base, base_elevation_m, dtm,
                       accuracy, unit, z_unit)  # fmt: skip
        rows.append({"name": name, **row})
        fb.progress((i + 1) / len(frame))
    measured = [r for r in rows if math.isfinite(r["net_m3"])]
    if not measured:
        raise InputError("no polygon covers the DSM's heights (off the DSM, or its nodata)", path=polygons)
    for r in rows:
        if r["note"]:
            fb.warning(f"polygon {r['name']}: {r['note']}")
    out = frame.drop(columns="__name").copy()
    for key in rows[0]:
        out[key] = [r[key] for r in rows]
    from geoortho.core.outputs import write_vector
    from geoortho.core.styles import product_styles

    write_vector(output, {"volumes": gpd.GeoDataFrame(out, geometry="geometry", crs=crs)},
                 styles=product_styles("volumes"))  # fmt: skip
    cut = float(sum(r["cut_m3"] for r in measured))
    fill = float(sum(r["fill_m3"] for r in measured))
    # one shift for every polygon, and one way of placing walls; the noise is each polygon's own
    systematic = float(np.nansum([r["sigma_systematic_m3"] for r in measured]))
    walls = float(np.nansum([r["sigma_walls_m3"] for r in measured]))
    rest = float(np.nansum([r["sigma_random_m3"] ** 2 + r["sigma_base_m3"] ** 2 for r in measured]))
    sigma = math.sqrt(systematic**2 + walls**2 + rest)
    if not math.isfinite(accuracy.systematic_m):
        notes.append("the vertical accuracy is not known: give vertical_accuracy_m (the systematic part is left out)")
    if not math.isfinite(accuracy.noise_m):
        notes.append("the DSM's noise is not known: give noise_m (the random and base parts are left out)")
    for n in notes:
        fb.warning(n)
    fb.info(f"{len(measured)} polygon(s): cut {cut:,.1f} m³, fill {fill:,.1f} m³, net {cut - fill:,.1f} ± "
            f"{sigma:,.1f} m³ (1 sigma; {accuracy.source})")  # fmt: skip
    return VolumeResult(Path(output), len(measured), cut, fill, cut - fill, sigma, accuracy.source, notes,
                        time.perf_counter() - started)  # fmt: skip


def _read_polygons(path: Path, crs: Any) -> Any:
    """The polygons in the DSM's CRS, each with a name (its ``name`` column, else its number)."""
    import geopandas as gpd

    if not path.exists():
        raise InputError("no such file", path=path)
    try:
        df = gpd.read_file(path, engine="pyogrio")
    except Exception as e:  # pyogrio raises its own DataSourceError and friends
        raise InputError(f"cannot read the polygons: {e}", path=path) from None
    keep = [g is not None and not g.is_empty and g.geom_type in ("Polygon", "MultiPolygon") for g in df.geometry]
    df = df[keep]
    if df.empty:
        raise InputError("the file holds no polygon: draw the stockpiles or pits as polygons", path=path)
    if df.crs is None:
        raise InputError("the polygons have no CRS", path=path)
    df = df.to_crs(crs)
    names = df["name"].astype(str) if "name" in df.columns else [str(i + 1) for i in range(len(df))]
    df = df.assign(__name=list(names))
    df.geometry = df.geometry.make_valid()
    return df


def _accuracy(dsm: Path, vertical_accuracy_m: float | None, noise_m: float | None) -> _Accuracy:
    """The DSM's vertical accuracy and noise: as given, else from the run that made it."""
    said = []
    if vertical_accuracy_m is not None:
        systematic, source = float(vertical_accuracy_m), "vertical accuracy as given"
    else:
        systematic, source = run_vertical_accuracy(dsm)
    said += [source] if source else []
    noise = float(noise_m) if noise_m is not None else run_noise(dsm)
    if noise_m is not None:
        said.append("noise as given")
    elif math.isfinite(noise):
        said.append(f"noise from the run's DSM on open ground ({noise:.3f} m)")
    walls = run_wall_place_m(dsm)
    if math.isfinite(walls):
        said.append(f"walls placed to {walls:.2f} m ({WALL_VOXELS:g} of the dense cloud's voxels)")
    return _Accuracy(systematic, noise, "; ".join(said) or "no accuracy known", walls)


def _measure(
    dsm: Path, source: Path | None, geom: Any, base: str, base_elevation: float | None, dtm: Path | None,
    acc: _Accuracy, unit: float, z_unit: float,
) -> dict[str, Any]:  # fmt: skip
    """One polygon's figures."""
    import rasterio
    from rasterio.features import geometry_mask
    from rasterio.windows import Window

    empty = {"base_method": base, "base_m": math.nan, "area_m2": 0.0, "cut_m3": math.nan, "fill_m3": math.nan,
             "net_m3": math.nan, "sigma_m3": math.nan, "sigma_systematic_m3": math.nan,
             "sigma_random_m3": math.nan, "sigma_base_m3": math.nan, "sigma_walls_m3": math.nan,
             "interpolated_share": math.nan, "interpolated_area_share": math.nan,
             "uncovered_share": 1.0, "note": ""}  # fmt: skip
    with rasterio.open(dsm) as ds:
        t = ds.transform
        west, south, east, north = geom.bounds
        c0, r0 = (int(math.floor(v)) for v in ~t * (west, north))
        c1, r1 = (int(math.ceil(v)) for v in ~t * (east, south))
        c0, r0, c1, r1 = max(c0, 0), max(r0, 0), min(c1, ds.width), min(r1, ds.height)
        if c1 <= c0 or r1 <= r0:
            return {**empty, "note": "off the DSM: not measured"}
        win = Window(c0, r0, c1 - c0, r1 - r0)
        z = ds.read(1, window=win, masked=True).astype(np.float64).filled(np.nan)
        wt = ds.window_transform(win)
    inside = geometry_mask([geom], out_shape=z.shape, transform=wt, invert=True)
    if not inside.any():
        return {**empty, "note": "smaller than a DSM cell: not measured"}
    cell_m2 = abs(wt.a * wt.e) * unit * unit
    covered = inside & np.isfinite(z)
    n_in, n_cov = int(inside.sum()), int(covered.sum())
    # the share without height: its cells on the grid with none, and its part off the grid
    import shapely

    on_grid = geom.intersection(shapely.box(*rasterio.transform.array_bounds(*z.shape, wt)))
    off_share = 1.0 - on_grid.area / geom.area if geom.area > 0 else 0.0
    uncovered = 1.0 - (1.0 - off_share) * n_cov / n_in
    if n_cov == 0:
        return {**empty, "note": "over the DSM's nodata only: not measured"}
    note = ""
    if uncovered > 0.001:
        note = f"{100 * uncovered:.1f} % of it has no DSM height: measured on the covered part"
    rr, cc = np.nonzero(covered)
    xs = wt.c + (cc + 0.5) * wt.a
    ys = wt.f + (rr + 0.5) * wt.e
    b = _base(dsm, geom, base, base_elevation, dtm, xs, ys)
    base_z, base_m = b.z, b.flat_m
    if not np.isfinite(base_z).all():
        ok = np.isfinite(base_z)
        if not ok.any():
            return {**empty, "note": "no base: its edge has no DSM height"}
        note = (note + "; " if note else "") + "the base is not defined under part of it: that part left out"
        rr, cc, base_z = rr[ok], cc[ok], base_z[ok]
    dz = (z[rr, cc] - base_z) * z_unit
    cut = float(dz[dz > 0].sum() * cell_m2)
    fill = float(-dz[dz < 0].sum() * cell_m2)
    area = len(dz) * cell_m2
    interp = interp_area = math.nan
    if source is not None:
        with rasterio.open(source) as s:
            codes = s.read(1, window=win)
        w, filled = np.abs(dz), codes[rr, cc] == INTERPOLATED
        interp = float(w[filled].sum() / w.sum()) if w.sum() > 0 else 0.0
        interp_area = float(filled.mean())
        if interp_area > INTERPOLATED_WARN:
            # a pile the matcher found no point on is filled across from its foot: flat, and as
            # certain-looking as measured ground
            note = (note + "; " if note else "") + (
                f"{100 * interp_area:.0f} % of its area is interpolated (no DSM point there): its volume "
                "there is not measured, and the uncertainty does not cover it"
            )
    sys_m3, rand_m3, base_m3 = _sigmas(acc, base, area, cell_m2, b.weights * cell_m2, b.along_m * unit)
    walls_m3 = walls_sigma_m3(z * z_unit, inside, abs(wt.a) * unit, acc.walls_m)
    return {
        "base_method": base, "base_m": base_m, "area_m2": area, "cut_m3": cut, "fill_m3": fill, "net_m3": cut - fill,
        "sigma_m3": math.sqrt(np.nansum([sys_m3**2, rand_m3**2, base_m3**2, walls_m3**2])),
        "sigma_systematic_m3": sys_m3, "sigma_random_m3": rand_m3, "sigma_base_m3": base_m3,
        "sigma_walls_m3": walls_m3, "interpolated_share": interp, "interpolated_area_share": interp_area,
        "uncovered_share": uncovered, "note": note,
    }  # fmt: skip


@dataclass(frozen=True)
class _Base:
    """The base under each cell (the DSM's units), its one height where it is flat (else NaN), and
    how much each edge sample weighs in its integral (cells of base each sample makes), with the
    samples' place along the edge (metres): what the base's own noise costs the volume."""

    z: np.ndarray
    flat_m: float
    weights: np.ndarray
    along_m: np.ndarray


def _base(
    dsm: Path, geom: Any, base: str, base_elevation: float | None, dtm: Path | None, xs: np.ndarray, ys: np.ndarray
) -> _Base:
    none = np.zeros(0)
    if base == "fixed":
        assert base_elevation is not None
        return _Base(np.full(len(xs), float(base_elevation)), float(base_elevation), none, none)
    if base == "dtm":
        assert dtm is not None
        return _Base(_sample(Path(dtm), xs, ys), math.nan, none, none)
    ex, ey, ez, along = _edge(dsm, geom)
    if len(ez) < 3:
        return _Base(np.full(len(xs), np.nan), math.nan, none, none)
    if base == "edge-lowest":
        w = np.zeros(len(ez))
        w[int(np.argmin(ez))] = len(xs)
        return _Base(np.full(len(xs), float(ez.min())), float(ez.min()), w, along)
    if base == "edge-mean":
        return _Base(np.full(len(xs), float(ez.mean())), float(ez.mean()), np.full(len(ez), len(xs) / len(ez)), along)
    from scipy.spatial import Delaunay, cKDTree

    pts = np.column_stack([ex - ex.mean(), ey - ey.mean()])
    q = np.column_stack([xs - ex.mean(), ys - ey.mean()])
    tri = Delaunay(pts)
    simplex = tri.find_simplex(q)
    inside = simplex >= 0
    # barycentric weights of each cell centre in its triangle: the base is their sum of the samples
    t = tri.transform[simplex[inside]]
    b = np.einsum("nij,nj->ni", t[:, :2], q[inside] - t[:, 2])
    lam = np.column_stack([b, 1.0 - b.sum(axis=1)])
    corners = tri.simplices[simplex[inside]]
    z = np.full(len(xs), np.nan)
    z[inside] = (lam * ez[corners]).sum(axis=1)
    weights = np.zeros(len(ez))
    np.add.at(weights, corners.ravel(), lam.ravel())
    if (~inside).any():  # a cell centre just outside the edge's hull: the nearest edge sample
        _, near = cKDTree(pts).query(q[~inside])
        z[~inside] = ez[near]
        np.add.at(weights, near, 1.0)
    return _Base(z, math.nan, weights, along)


def _edge(dsm: Path, geom: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The DSM along the polygon's rings, a sample a cell (points with no height dropped), and each
    sample's distance along the rings (each ring after the last, a patch apart)."""
    import rasterio
    import shapely

    with rasterio.open(dsm) as ds:
        step = abs(ds.transform.a)
    rings = [geom.exterior, *geom.interiors] if geom.geom_type == "Polygon" else [
        r for p in geom.geoms for r in (p.exterior, *p.interiors)]  # fmt: skip
    parts, along, start = [], [], 0.0
    for r in rings:
        xy = shapely.get_coordinates(shapely.segmentize(r, step))[:-1]
        d = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(xy, axis=0).T))])
        parts.append(xy)
        along.append(start + d)
        start += float(d[-1]) + NOISE_CORRELATION_M * 2
    xy, dist = np.concatenate(parts), np.concatenate(along)
    z = _sample(dsm, xy[:, 0], xy[:, 1])
    ok = np.isfinite(z)
    return xy[ok, 0], xy[ok, 1], z[ok], dist[ok]


def _sample(raster: Path, xs: np.ndarray, ys: np.ndarray) -> np.ndarray:
    """Bilinear heights of a raster at points of its CRS (NaN off it or on its nodata)."""
    import rasterio
    from rasterio.windows import Window

    from geoortho.core.surface import sample_grid

    with rasterio.open(raster) as ds:
        inv = ~ds.transform
        cols, rows = inv * (xs, ys)
        c0 = max(int(np.floor(np.min(cols))) - 2, 0)
        r0 = max(int(np.floor(np.min(rows))) - 2, 0)
        c1 = min(int(np.ceil(np.max(cols))) + 2, ds.width)
        r1 = min(int(np.ceil(np.max(rows))) + 2, ds.height)
        if c1 <= c0 or r1 <= r0:
            return np.full(len(xs), np.nan)
        grid = ds.read(1, window=Window(c0, r0, c1 - c0, r1 - r0), masked=True).astype(np.float32).filled(np.nan)
    return np.asarray(sample_grid(grid, np.asarray(cols) - c0 - 0.5, np.asarray(rows) - r0 - 0.5), np.float64)


def _sigmas(
    acc: _Accuracy, base: str, area_m2: float, cell_m2: float, weights_m2: np.ndarray, along_m: np.ndarray
) -> tuple[float, float, float]:
    """The three parts of the volume's 1 sigma (m³): systematic, random, base. ``weights_m2``: the
    area of base each edge sample makes; samples within a patch of the edge share their noise."""
    patch_m2 = max(cell_m2, NOISE_CORRELATION_M**2)
    noise = acc.noise_m if math.isfinite(acc.noise_m) else math.nan
    random = noise * math.sqrt(area_m2 * patch_m2)
    if base == "fixed":
        return acc.systematic_m * area_m2, random, 0.0
    if base == "dtm":  # made from the same survey: the shift cancels; the DTM's own noise adds
        return 0.0, random * math.sqrt(2.0), 0.0
    patch = np.floor(along_m / max(NOISE_CORRELATION_M, math.sqrt(cell_m2))).astype(np.int64)
    per_patch = np.bincount(patch - patch.min(), weights=weights_m2) if len(patch) else np.zeros(0)
    return 0.0, random, noise * float(np.sqrt(np.sum(per_patch**2)))
