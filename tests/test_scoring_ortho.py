"""The true-orthophoto scores (issue 75's measures) on the survey's own true orthophoto: a perfect
copy scores perfect, a shifted copy's roof edges are off by the shift, a hole is measured."""

from __future__ import annotations

import numpy as np
import rasterio
from affine import Affine

from geoortho.synthetic.scoring import score_ortho


def _copy_as_ortho(truth, path, shift_cells=0, hole_m=0.0):
    with rasterio.open(truth / "ortho.tif") as ds:
        rgb, t, crs = ds.read(), ds.transform, ds.crs
    alpha = np.full(rgb.shape[1:], 255, np.uint8)
    alpha[:, :2] = alpha[:, -2:] = 0  # a border, as a mosaic's edge
    if hole_m:
        n = int(round(hole_m / t.a))
        r, c = rgb.shape[1] // 2, rgb.shape[2] // 2
        alpha[r : r + n, c : c + n] = 0
    # a shifted copy: the pixels moved east by shift_cells (the grid kept)
    rgb = np.roll(rgb, shift_cells, axis=2)
    with rasterio.open(path, "w", driver="GTiff", width=rgb.shape[2], height=rgb.shape[1], count=4,
                       dtype="uint8", crs=crs, transform=t * Affine.identity()) as out:  # fmt: skip
        out.write(np.concatenate([rgb, alpha[None]]))
    return abs(t.a)


def test_the_truth_scores_perfect_a_shift_and_a_hole_are_measured(small_survey, tmp_path):
    truth = small_survey.truth
    cell = _copy_as_ortho(truth, tmp_path / "same.tif")
    same = score_ortho(truth, tmp_path / "same.tif")
    assert same.ssim_open > 0.99 and same.ssim_near_objects > 0.99, same
    assert same.roof_edge_pieces > 100 and same.roof_edge_error_gsd <= 0.5, same
    assert same.holes_inside_m2 == 0.0
    _copy_as_ortho(truth, tmp_path / "shifted.tif", shift_cells=3, hole_m=1.0)
    shifted = score_ortho(truth, tmp_path / "shifted.tif")
    # east and west walls move by the shift, north and south ones not: the median over pieces
    shift_gsd = 3 * cell / same.gsd_m
    assert 0.3 * shift_gsd < shifted.roof_edge_error_gsd <= shift_gsd + 0.5, (shifted, shift_gsd)
    assert shifted.ssim_near_objects < same.ssim_near_objects - 0.05
    assert abs(shifted.holes_inside_m2 - 1.0) < 0.1, shifted
