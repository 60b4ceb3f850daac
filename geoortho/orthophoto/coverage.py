"""What an orthophoto covers: its area against the ground its photos saw, the holes inside it."""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from affine import Affine

from geoortho.core.camera import PosedCamera
from geoortho.core.surface import GridSurface, Surface, sample_grid
from geoortho.elevation.coverage import MEASURED, footprint_polygons, seen_area_m2, seen_count, source_path
from geoortho.orthophoto.provenance import (
    OCCLUDED,
)

#: The orthophoto is said to fall short below this share of the ground the photos saw.
MIN_SHARE_OF_SEEN = 0.95
#: Coverage is measured on a grid of at most this many cells.
COVERAGE_CELLS = 4_000_000


def measure_coverage(
    ortho: Path, cams: Sequence[PosedCamera], surface: Surface, dsm_source: Path | None
) -> dict[str, float]:
    """The orthophoto's opaque area against the ground its photos saw (by >= 1 and >= 2 of them),
    and how much of it lies on interpolated DSM cells, measured on a grid of at most
    :data:`COVERAGE_CELLS` cells over the orthophoto's extent."""
    import rasterio
    from rasterio.enums import Resampling

    with rasterio.open(ortho) as ds:
        crs = ds.crs
        f = max(1, math.ceil(math.sqrt(ds.width * ds.height / COVERAGE_CELLS)))
        shape = (max(1, ds.height // f), max(1, ds.width // f))
        alpha = ds.read_masks(1, out_shape=shape, resampling=Resampling.nearest) > 0
        t = ds.transform @ Affine.scale(ds.width / shape[1], ds.height / shape[0])
    cell_m2 = abs(t.a * t.e)
    polys = footprint_polygons(cams, surface)
    seen = seen_count(polys, t, shape)
    out = {
        "area_m2": float(alpha.sum()) * cell_m2,
        # the areas from the footprints themselves: the dem on the same DSM states the same figures
        "seen_1_m2": seen_area_m2(polys, 1),
        "seen_2_m2": seen_area_m2(polys, 2),
        "share_of_seen_1": float((alpha & (seen >= 1)).sum()) / max(int((seen >= 1).sum()), 1),
        "share_of_seen_2": float((alpha & (seen >= 2)).sum()) / max(int((seen >= 2).sum()), 1),
        "on_interpolated_m2": 0.0,
        **_holes_inside(alpha, cell_m2, ortho, f),
        "occluded_m2": 0.0,
    }
    own_source = source_path(ortho)
    if own_source.is_file():
        with rasterio.open(own_source) as ds:
            how = ds.read(2, out_shape=shape, resampling=Resampling.nearest)
        out["occluded_m2"] = float((alpha & (how == OCCLUDED)).sum()) * cell_m2
    if dsm_source is not None and dsm_source.is_file():
        from rasterio.warp import reproject

        src_grid = np.zeros(shape, np.uint8)
        with rasterio.open(dsm_source) as ds:
            # onto the orthophoto's grid, in its CRS (an ortho made with --crs is in another)
            reproject(rasterio.band(ds, 1), src_grid, dst_transform=t, dst_crs=crs, resampling=Resampling.nearest)
        out["on_interpolated_m2"] = float((alpha & (src_grid != MEASURED)).sum()) * cell_m2
    elif isinstance(surface, GridSurface):
        # the ortho's DSM has its holes filled on reading: what is left off it lies past its grid

        rows, cols = np.nonzero(alpha)
        x, y = t * (cols + 0.5, rows + 0.5)
        c, r = surface.colrow(np.asarray(x), np.asarray(y))
        raw = sample_grid(surface.grid, c, r)
        out["on_interpolated_m2"] = float((~np.isfinite(raw)).sum()) * cell_m2
    return out


def _holes_inside(alpha: np.ndarray, cell_m2: float, ortho: Path | None = None, f: int = 1) -> dict[str, float]:
    """Transparent pixels the mosaic surrounds (not its outer edge): their area, how many holes,
    the largest. ``alpha`` is the mosaic's mask read every ``f`` pixels; each hole found on it is
    measured again on ``ortho``'s own pixels round it: a decimated read pinches a narrow inlet of
    the outer edge shut (toledo: "1 hole, 0.1 m²" where the full mask had none)."""
    from scipy import ndimage

    holes = ndimage.binary_fill_holes(alpha) & ~alpha
    labels, n = ndimage.label(holes, structure=np.ones((3, 3), bool))
    sizes = (np.bincount(labels.ravel())[1:] * cell_m2) if n else np.zeros(0)
    if n and ortho is not None and f > 1:
        import rasterio

        with rasterio.open(ortho) as ds:
            sizes = np.array([_hole_at_full_resolution(ds, box, f) for box in ndimage.find_objects(labels)])
        sizes = sizes[sizes > 0]
        n = len(sizes)
    return {
        "holes_inside_m2": float(sizes.sum()),
        "holes_inside_n": float(n),
        "largest_hole_m2": float(sizes.max()) if n else 0.0,
    }


def _hole_at_full_resolution(ds: Any, box: tuple[slice, slice], f: int) -> float:
    """The area (m²) of the transparent pixels round a hole of the decimated mask (its ``box``) that
    the orthophoto ``ds``'s full mask encloses: none of them reaches the window's edge (two
    decimated cells out)."""
    from rasterio.windows import Window

    r0, c0 = max(0, (box[0].start - 2) * f), max(0, (box[1].start - 2) * f)
    r1, c1 = min(ds.height, (box[0].stop + 2) * f), min(ds.width, (box[1].stop + 2) * f)
    empty = ds.read_masks(1, window=Window(c0, r0, c1 - c0, r1 - r0)) == 0
    result: float = float(enclosed(empty).sum()) * abs(ds.transform.a * ds.transform.e)
    return result


def enclosed(empty: np.ndarray) -> np.ndarray:
    """The ``empty`` pixels not connected to the tile's border."""
    # 4-connected, as the holes are counted (scipy's fill_holes): a diagonal touch does not let one out
    n, comp = cv2.connectedComponents(empty.astype(np.uint8), connectivity=4)
    if n <= 1:
        return np.zeros_like(empty)
    outside = np.zeros(n, bool)
    for edge in (comp[0], comp[-1], comp[:, 0], comp[:, -1]):
        outside[np.unique(edge)] = True
    outside[0] = True  # label 0: the rendered pixels
    result: np.ndarray = ~outside[comp]
    return result
