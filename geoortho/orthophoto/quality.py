"""How well an orthophoto sits on a reference one: per-tile shifts by phase correlation, and colour
errors beside buildings (where a wrong surface shows)."""

from __future__ import annotations

import os
from dataclasses import dataclass

import cv2
import numpy as np

__all__ = ["TileShift", "geolocation_shifts", "read_on_grid", "share_off_beside_objects"]


@dataclass(frozen=True)
class TileShift:
    """Shift of the orthophoto against the reference over one tile (reference CRS units; +x east, +y north)."""

    row: int
    col: int
    dx: float
    dy: float
    response: float

    @property
    def distance(self) -> float:
        return float(np.hypot(self.dx, self.dy))


def read_on_grid(path: str | os.PathLike[str], like: str | os.PathLike[str]) -> tuple[np.ndarray, np.ndarray]:
    """Raster ``path`` resampled (bilinear) onto the grid of ``like``: RGB (3, rows, cols) uint8 and a
    validity mask (from alpha/mask)."""
    import rasterio
    from rasterio.enums import Resampling
    from rasterio.vrt import WarpedVRT

    with rasterio.open(like) as ref, rasterio.open(path) as src:
        with WarpedVRT(
            src,
            crs=ref.crs,
            transform=ref.transform,
            width=ref.width,
            height=ref.height,
            resampling=Resampling.bilinear,
        ) as vrt:
            rgb = vrt.read((1, 2, 3))
            mask = vrt.dataset_mask() > 0
    return rgb, mask


def geolocation_shifts(
    ortho: str | os.PathLike[str], reference: str | os.PathLike[str], tile_px: int = 256, min_response: float = 0.05
) -> list[TileShift]:
    """Phase-correlate the orthophoto with the reference tile by tile (tiles fully covered by both
    and with texture); a positive dx means the orthophoto shows things east of where the reference does."""
    import rasterio

    with rasterio.open(reference) as ref:
        ref_rgb = ref.read((1, 2, 3))
        ref_mask = ref.dataset_mask() > 0
        res_x, res_y = ref.transform.a, -ref.transform.e
    rgb, mask = read_on_grid(ortho, reference)
    gray_ref = cv2.cvtColor(np.ascontiguousarray(ref_rgb.transpose(1, 2, 0)), cv2.COLOR_RGB2GRAY).astype(np.float32)
    gray = cv2.cvtColor(np.ascontiguousarray(rgb.transpose(1, 2, 0)), cv2.COLOR_RGB2GRAY).astype(np.float32)
    window = cv2.createHanningWindow((tile_px, tile_px), cv2.CV_32F)
    out = []
    rows, cols = gray.shape
    for r in range(0, rows - tile_px + 1, tile_px):
        for c in range(0, cols - tile_px + 1, tile_px):
            if not (mask[r : r + tile_px, c : c + tile_px].all() and ref_mask[r : r + tile_px, c : c + tile_px].all()):
                continue
            a = gray_ref[r : r + tile_px, c : c + tile_px]
            b = gray[r : r + tile_px, c : c + tile_px]
            if a.std() < 2.0:
                continue
            (sx, sy), resp = cv2.phaseCorrelate(a, b, window)
            if resp < min_response:
                continue
            out.append(TileShift(r, c, float(sx * res_x), float(-sy * res_y), float(resp)))
    return out


def share_off_beside_objects(
    ortho: str | os.PathLike[str],
    reference: str | os.PathLike[str],
    dsm: str | os.PathLike[str],
    dtm: str | os.PathLike[str],
    off_dn: float = 25.0,
) -> dict[str, float]:
    """Share of pixels whose colour is off the reference ortho by more than ``off_dn`` (mean of RGB,
    lightly smoothed), on the ground 0.3–2.5 m beside buildings and trees (``ring``: where roofs
    lean or ghost when the surface or the occlusion test is wrong) and on open ground > 6 m from
    them (``open``). ``dsm`` and ``dtm`` are the true surfaces (same grid) that say where objects are."""
    import rasterio
    from scipy import ndimage

    with rasterio.open(dsm) as a, rasterio.open(dtm) as b:
        hag, cell, dsm_tr = a.read(1) - b.read(1), a.transform.a, a.transform
    near = ndimage.distance_transform_edt(~(hag > 2.0)) * cell
    ground = hag < 0.1
    masks = {"ring": ground & (near > 0.3) & (near < 2.5), "open": ground & (near > 6.0)}
    with rasterio.open(reference) as t:
        truth, ttr = t.read((1, 2, 3)).astype(np.float32), t.transform
    rgb, valid = read_on_grid(ortho, reference)
    rows, cols = np.indices(valid.shape)
    x, y = ttr.c + (cols + 0.5) * ttr.a, ttr.f + (rows + 0.5) * ttr.e
    c = np.clip(((x - dsm_tr.c) / dsm_tr.a).astype(int), 0, hag.shape[1] - 1)
    r = np.clip(((y - dsm_tr.f) / dsm_tr.e).astype(int), 0, hag.shape[0] - 1)
    diff = cv2.GaussianBlur(np.abs(rgb.astype(np.float32) - truth).mean(axis=0), (0, 0), 1.0)
    out = {}
    for name, m in masks.items():
        sel = m[r, c] & valid
        out[name] = float((diff[sel] > off_dn).mean()) if sel.any() else float("nan")
    return out
