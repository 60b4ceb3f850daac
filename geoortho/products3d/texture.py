"""A mesh's texture: the orthophoto over its extent, and where each vertex falls on it."""

from __future__ import annotations

from pathlib import Path

import numpy as np

#: The orthophoto's colour where it has none (outside the photos): neutral grey.
NO_COLOUR = 128

Bounds = tuple[float, float, float, float]  # west, south, east, north (the CRS's units)


def ortho_texture(ortho: Path, bounds: Bounds, max_px: int, ortho_cell: float) -> tuple[np.ndarray, float]:
    """The orthophoto over ``bounds`` as (h, w, 3) uint8 RGB, no finer than its own pixels and at
    most ``max_px`` a side (averaged down), grey where it has no colour; and its pixel size."""
    import rasterio
    from rasterio.enums import Resampling
    from rasterio.windows import from_bounds

    west, south, east, north = bounds
    cell = max(ortho_cell, (east - west) / max_px, (north - south) / max_px)
    w = max(int(round((east - west) / cell)), 1)
    h = max(int(round((north - south) / cell)), 1)
    with rasterio.open(ortho) as o:
        win = from_bounds(west, south, east, north, o.transform)
        bands = min(o.count, 3)
        rgb = o.read(list(range(1, bands + 1)), window=win, out_shape=(bands, h, w), boundless=True,
                     resampling=Resampling.average, fill_value=0)  # fmt: skip
        mask = o.read_masks(1, window=win, out_shape=(h, w), boundless=True, resampling=Resampling.nearest)
    if bands < 3:
        rgb = np.repeat(rgb[:1], 3, axis=0)
    img = np.moveaxis(rgb, 0, -1).astype(np.uint8)
    img[mask == 0] = NO_COLOUR
    return np.ascontiguousarray(img), cell


def uv_of(xyz: np.ndarray, bounds: Bounds) -> np.ndarray:
    """Each vertex's place on a texture of ``bounds``: (0, 0) its top-left corner, (1, 1) its bottom-right."""
    west, south, east, north = bounds
    return np.stack([(xyz[:, 0] - west) / (east - west), (north - xyz[:, 1]) / (north - south)], axis=1)
