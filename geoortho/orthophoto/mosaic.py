"""The orthophoto: photos rectified on the DSM tile by tile, seams, balance, blending, hole fill, COG.

:func:`mosaic` works from posed cameras and a surface (tests give it the true
poses); :func:`ortho` is the algorithm: poses from an ``sfm`` folder or from
the photo metadata, surface from a DSM or flat ground. Beside it: :mod:`.placing` (the photos on the
surface, the resolution), :mod:`.tile` (one tile, in a worker), :mod:`.given_dsm` (the DSM read and
checked against the SfM points) and :mod:`.coverage` (the ground the orthophoto covers).
"""

from __future__ import annotations

import contextlib
import math
import os
import tempfile
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, get_args

import cv2
import numpy as np
from affine import Affine
from pyproj import CRS
from rasterio.windows import Window

from geoortho.core.camera import PosedCamera
from geoortho.core.crs import crs_to_text, horizontal_unit_m
from geoortho.core.outputs import atomic_path, temp_prefix, write_json, write_png
from geoortho.core.parallel import imap_ordered, map_ordered
from geoortho.core.sfm_model import cameras_from_sfm
from geoortho.core.surface import FlatSurface, GridSurface, Surface
from geoortho.elevation.coverage import source_path
from geoortho.errors import InputError
from geoortho.feedback import Feedback, as_feedback, split
from geoortho.orthophoto.coverage import MIN_SHARE_OF_SEEN, measure_coverage
from geoortho.orthophoto.given_dsm import DSM_OFFSET, DsmOffset, check_dsm_against_points, given_surface
from geoortho.orthophoto.placing import mosaic_resolution, place_photos, without_other_flights
from geoortho.orthophoto.provenance import (
    SourceWriter,
    seamlines_path,
    write_seamlines,
)
from geoortho.orthophoto.rectify import (
    VisibilityGrid,
    block_tops,
    bounds_window,
)
from geoortho.orthophoto.seams import BALANCE, SEAMS, Balance, SeamMethod, plan_seams
from geoortho.orthophoto.tile import BANDS, TileContext, init_visibility, init_worker, render_tile, visibility_task
from geoortho.photos.footprint import photo_cameras, photos_with_altitude, working_crs
from geoortho.photos.heights import GpsAltitude

__all__ = ["OrthoResult", "ortho", "mosaic", "BLEND", "BALANCE", "SEAMS", "COMPRESS", "INTERPOLATION"]

Blend = Literal["multiband", "feather", "none"]
Compression = Literal["DEFLATE", "JPEG"]
Interpolation = Literal["bilinear", "bicubic", "lanczos", "nearest"]
BLEND: tuple[str, ...] = get_args(Blend)
COMPRESS: tuple[str, ...] = get_args(Compression)
_INTERPOLATION = {
    "bilinear": cv2.INTER_LINEAR,
    "bicubic": cv2.INTER_CUBIC,
    "lanczos": cv2.INTER_LANCZOS4,
    "nearest": cv2.INTER_NEAREST,
}
INTERPOLATION: tuple[str, ...] = get_args(Interpolation)


@dataclass(frozen=True)
class OrthoResult:
    """The orthophoto and what was measured while making it.

    Attributes
    ----------
    output : Path
        Orthophoto (COG, RGB + alpha).
    preview : Path
        PNG preview (None when not asked for).
    report : Path
        Report JSON: resolution, GSD, coverage, holes, seam colour mismatch, gains.
    crs : str
        CRS of the orthophoto.
    resolution_m : float
        Pixel size, metres.
    median_gsd_m : float
        Median GSD of the photos, metres.
    width_px : int
        Width of the orthophoto.
    height_px : int
        Height of the orthophoto.
    n_photos : int
        Photos given.
    n_used : int
        Photos in the mosaic.
    coverage_px : int
        Pixels with data.
    holes_filled_px : int
        Pixels inpainted inside the coverage.
    holes_left_px : int
        Holes left transparent (wider than max_hole_px).
    seam_mismatch_raw : float
        Colour difference across seams before balancing, DN.
    seam_mismatch_balanced : float
        Colour difference across seams after balancing, DN.
    poses : str
        Where the poses came from.
    surface : str
        What the photos were rectified on.
    skipped : tuple of (str, str)
        Photos left out, and why.
    notes : tuple of str
        What was assumed or checked, in words.
    seconds : dict of str to float
        Time spent in each step.
    area_m2 : float
        Ground the orthophoto shows (opaque pixels).
    seen_1_m2 : float
        Ground seen by at least one of the photos used (their frames cast on the surface).
    seen_2_m2 : float
        Ground seen by at least two of them.
    share_of_seen_1 : float
        Share of ``seen_1_m2`` the orthophoto shows.
    share_of_seen_2 : float
        Share of ``seen_2_m2`` the orthophoto shows.
    on_interpolated_m2 : float
        Ground the orthophoto shows on DSM cells that were interpolated or a fallback plane (from the
        DSM's ``_source.tif`` when it has one; otherwise the ground past the DSM's grid, on its plane).
    dsm_offset_m : float
        The DSM's height above the SfM's points (median), as measured before any correction (NaN:
        not measured: no SfM, or too few points over the DSM).
    holes_inside_m2 : float
        Transparent ground the mosaic surrounds (holes inside it, not its outer edge).
    holes_inside_n : float
        How many such holes.
    largest_hole_m2 : float
        The largest of them.
    occluded_m2 : float
        Ground no photo sees (a true occlusion on the DSM), drawn from the seen ground round it
        (not from what hides it), marked 2 in the source raster; band 1 names the photo that has
        it in frame most directly.
    source : Path
        ``<name>_source.tif``: each pixel's photo (band 1, 1-based, named in its attribute table)
        and how it was drawn (band 2: 1 seen, 2 occluded, 3 inpainted).
    seamlines : Path
        ``<name>_seamlines.gpkg``: one polygon per photo region, with the photo's name, GSD, view
        angle, capture time and area.
    """

    output: Path
    preview: Path | None
    report: Path
    crs: str
    resolution_m: float
    median_gsd_m: float
    width_px: int
    height_px: int
    n_photos: int
    n_used: int
    coverage_px: int
    holes_filled_px: int
    holes_left_px: int
    seam_mismatch_raw: float
    seam_mismatch_balanced: float
    poses: str
    surface: str
    skipped: tuple[tuple[str, str], ...] = ()
    notes: tuple[str, ...] = ()
    seconds: dict[str, float] = field(default_factory=dict)
    area_m2: float = 0.0
    seen_1_m2: float = 0.0
    seen_2_m2: float = 0.0
    share_of_seen_1: float = 0.0
    share_of_seen_2: float = 0.0
    on_interpolated_m2: float = 0.0
    dsm_offset_m: float = math.nan
    holes_inside_m2: float = 0.0
    holes_inside_n: float = 0.0
    largest_hole_m2: float = 0.0
    occluded_m2: float = 0.0
    source: Path | None = None
    seamlines: Path | None = None


# ---------------------------------------------------------------------------------------------
# the whole mosaic


def _grid(
    boxes: Sequence[tuple[float, float, float, float]],
    surface: Surface,
    resolution_m: float,
) -> tuple[Affine, tuple[int, int]]:
    xmin = min(b[0] for b in boxes)
    ymin = min(b[1] for b in boxes)
    xmax = max(b[2] for b in boxes)
    ymax = max(b[3] for b in boxes)
    if isinstance(surface, GridSurface) and not surface.extend:
        sx0, sy0, sx1, sy1 = surface.bounds
        xmin, ymin, xmax, ymax = max(xmin, sx0), max(ymin, sy0), min(xmax, sx1), min(ymax, sy1)
    r = resolution_m
    x0, y1 = math.floor(xmin / r) * r, math.ceil(ymax / r) * r
    cols, rows = int(math.ceil((xmax - x0) / r)), int(math.ceil((y1 - ymin) / r))
    return Affine(r, 0, x0, 0, -r, y1), (rows, cols)


@dataclass(frozen=True)
class MosaicOptions:
    """How the mosaic is made: ortho's options, grouped (their defaults are ortho's too)."""

    seams: SeamMethod = "graphcut"
    balance: Balance = "channels"
    blend: Blend = "multiband"
    max_hole_px: int = 64
    compress: Compression = "DEFLATE"
    interpolation: Interpolation = "bilinear"
    tile_px: int = 1024
    #: False skips the line-of-sight test: a plain, not true, orthophoto (faster; the tests
    #: compare against it to show that walls do not ghost).
    occlusion: bool = True
    workers: int = 0

    def check(self) -> None:
        if (
            self.seams not in SEAMS
            or self.balance not in BALANCE
            or self.blend not in BLEND
            or self.compress.upper() not in COMPRESS
        ):
            raise InputError(
                f"choose seams from {SEAMS}, balance from {BALANCE}, blend from {BLEND}, compress from {COMPRESS}"
            )
        if self.interpolation not in _INTERPOLATION:
            raise InputError(f"interpolation {self.interpolation!r} is not one of {', '.join(INTERPOLATION)}")


def mosaic(
    cams: Sequence[PosedCamera],
    surface: Surface,
    crs: CRS,
    output: str | os.PathLike[str],
    resolution_m: float | None = None,
    options: MosaicOptions = MosaicOptions(),
    *,
    preview: str | os.PathLike[str] | None = None,
    poses: str = "given",
    notes: Sequence[str] = (),
    skipped: Sequence[tuple[str, str]] = (),
    dsm_source: str | os.PathLike[str] | None = None,
    dsm_offset_m: float = math.nan,
    feedback: Feedback | None = None,
) -> OrthoResult:
    """Orthorectify posed photos onto ``surface`` and mosaic them into a COG at ``output``.

    The stages: place each photo on the surface, choose the resolution and the grid, the
    occlusion grids, seams and gains (on a coarse grid), render the tiles in parallel, write
    the COG and the report."""
    fb = as_feedback(feedback)
    options.check()
    output = Path(output)
    started = time.time()
    try:
        return _mosaic(cams, surface, crs, output, resolution_m, options, preview, poses, notes, skipped, dsm_source,
                       dsm_offset_m, fb)  # fmt: skip
    except BaseException:
        # canceled or failed after some products were written (the COG, then its source raster,
        # seamlines and report): none of this run's is left, as if it had not started
        report = output.with_name(output.stem + "_report.json")
        shown = Path(preview) if preview is not None else None
        for path in (output, source_path(output), seamlines_path(output), report, shown):
            with contextlib.suppress(OSError):
                if path is not None and path.is_file() and path.stat().st_mtime >= started - 1.0:
                    path.unlink()
        raise


def _mosaic(
    cams: Sequence[PosedCamera],
    surface: Surface,
    crs: CRS,
    output: Path,
    resolution_m: float | None,
    options: MosaicOptions,
    preview: str | os.PathLike[str] | None,
    poses: str,
    notes: Sequence[str],
    skipped: Sequence[tuple[str, str]],
    dsm_source: str | os.PathLike[str] | None,
    dsm_offset_m: float,
    fb: Feedback,
) -> OrthoResult:
    times: dict[str, float] = {}
    t0 = time.perf_counter()
    notes = list(notes)
    skipped = list(skipped)
    st_vis, st_plan, st_tiles, st_write = split(fb, [2, 2, 10, 1])
    placed = without_other_flights(place_photos(cams, surface, fb), fb)
    skipped += placed.skipped
    resolution_m, median_gsd = mosaic_resolution(resolution_m, placed.gsds, notes, fb)
    transform, shape = _grid(placed.boxes, surface, resolution_m)
    if shape[0] * shape[1] > 4e9:
        raise InputError(f"the mosaic would be {shape[1]}x{shape[0]} px: give a coarser resolution")
    plan, totals, used, preview_path = _build_mosaic(
        placed, surface, crs, transform, shape, output, options, preview, resolution_m, (t0, times),
        (st_vis, st_plan, st_tiles), fb,
    )  # fmt: skip
    skipped += plan.skipped
    notes.extend(plan.notes)
    st_write.progress(1.0)

    cover = measure_coverage(output, placed.cams, surface, Path(dsm_source) if dsm_source is not None else None)
    notes.extend(_coverage_notes(cover, fb))
    raw, bal = _ratio(totals, "seam_raw", "seam_n"), _ratio(totals, "seam_bal", "seam_n")
    if options.balance != "none" and math.isfinite(raw) and math.isfinite(bal) and bal >= raw:
        notes.append(f"colour balance did not lower the colour mismatch across seams ({raw:.2f} → {bal:.2f} DN)")
        fb.warning(notes[-1])

    result = OrthoResult(
        output=output,
        preview=preview_path,
        report=output.with_name(output.stem + "_report.json"),
        crs=crs_to_text(crs),
        resolution_m=resolution_m,
        median_gsd_m=median_gsd,
        width_px=shape[1],
        height_px=shape[0],
        n_photos=len(cams),
        n_used=len(used),
        coverage_px=int(totals.get("coverage", 0)),
        holes_filled_px=int(totals.get("filled", 0)),
        holes_left_px=int(totals.get("holes_left", 0)),
        seam_mismatch_raw=raw,
        seam_mismatch_balanced=bal,
        poses=poses,
        surface=_describe(surface),
        skipped=tuple(skipped),
        notes=tuple(notes),
        seconds=times,
        dsm_offset_m=dsm_offset_m,
        source=source_path(output),
        seamlines=seamlines_path(output),
        **cover,
    )
    gains = {c.name: [float(g) for g in plan.gains[i]] for i, c in enumerate(placed.cams)}
    unused = sorted(c.name for i, c in enumerate(placed.cams) if i not in used)
    _write_report(result, totals, gains, time.perf_counter() - t0, plan.views_held_max, unused)
    fb.info(
        f"ortho: {output} ({shape[1]}x{shape[0]} px, {result.n_used} photos used); seam mismatch "
        f"{result.seam_mismatch_raw:.1f} → {result.seam_mismatch_balanced:.1f} DN after balancing"
    )
    return result


def _held_once(surface: Surface, folder: str | os.PathLike[str]) -> Surface:
    """A DSM kept in a mapped file in ``folder`` (:meth:`GridSurface.mapped`), so that the pool
    workers map the same pages instead of each holding a copy; flat ground as it is. Posix only:
    Windows cannot remove a file still mapped when its folder goes."""
    if isinstance(surface, GridSurface) and os.name == "posix":
        return surface.mapped(folder)
    return surface


def _build_mosaic(
    placed: Any,
    surface: Surface,
    crs: CRS,
    transform: Affine,
    shape: tuple[int, int],
    output: Path,
    options: MosaicOptions,
    preview: str | os.PathLike[str] | None,
    resolution_m: float,
    clock: tuple[float, dict[str, float]],
    steps: tuple[Feedback, Feedback, Feedback],
    fb: Feedback,
) -> tuple[Any, dict[str, float], set[int], Path | None]:
    """Visibility, seams and gains, the tiles, the COG: the mosaic's plan, its tile totals, the
    photos used and the preview written. The temporaries (visibility grids, the tiled mosaic) sit
    beside the output, on the same disk. ``clock``: the mosaic's start (the visibility's seconds
    count the placing of the photos too, as the report always has) and the seconds of each step."""
    st_vis, st_plan, st_tiles = steps
    t0, times = clock
    output.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix=temp_prefix(output.name), dir=output.parent) as work_dir:
        surface = _held_once(surface, work_dir)  # a direct mosaic() call's DSM: the workers share it
        vis = _visibility(placed, surface, options, Path(work_dir), st_vis)
        times["visibility"] = time.perf_counter() - t0

        t1 = time.perf_counter()
        plan = _seams_and_gains(placed, surface, vis, transform, shape, options, st_plan)
        bad = {name for name, _ in plan.skipped}
        box_windows = tuple(
            None if c.name in bad else bounds_window(transform, shape, b) for c, b in zip(placed.cams, placed.boxes)
        )
        times["seams_and_balance"] = time.perf_counter() - t1
        fb.info(
            f"mosaic {shape[1]}x{shape[0]} px at {resolution_m * 100:.2f} cm, {len(placed.cams) - len(bad)} photos; "
            f"gains {plan.gains.min():.3f}..{plan.gains.max():.3f}"
        )

        t2 = time.perf_counter()
        ctx = TileContext(
            placed.cams, box_windows, vis, surface, transform, shape, plan, options.blend, int(options.max_hole_px),
            2 ** (BANDS + 1), _INTERPOLATION[options.interpolation],
        )  # fmt: skip
        tiled = Path(work_dir) / "mosaic.tif"
        sources = SourceWriter(Path(work_dir), crs, transform, shape)
        try:
            totals, used = _render(ctx, crs, tiled, options, st_tiles, sources)
        finally:
            sources.close()
        times["tiles"] = time.perf_counter() - t2
        t3 = time.perf_counter()
        _write_cog(tiled, output, options.compress.upper())
        preview_path = _write_preview(output, Path(preview)) if preview else None
        sources.finish(source_path(output), [c.name for c in placed.cams])
        times["cog"] = time.perf_counter() - t3
    t4 = time.perf_counter()
    _, n_regions = write_seamlines(
        source_path(output), placed.cams, placed.gsds, placed.taken_at, seamlines_path(output)
    )
    totals["seamline_photos"] = float(n_regions)
    times["seamlines"] = time.perf_counter() - t4
    return plan, totals, used, preview_path


def _visibility(
    placed: Any, surface: Surface, options: MosaicOptions, work_dir: Path, fb: Feedback
) -> tuple[VisibilityGrid | None, ...]:
    """Each photo's occlusion grid over its window of the DSM (None on flat ground or when off)."""
    if not (options.occlusion and isinstance(surface, GridSurface)):
        return (None,) * len(placed.cams)
    jobs = [
        (cam, box, str(work_dir / f"visibility_{i}.npy")) for i, (cam, box) in enumerate(zip(placed.cams, placed.boxes))
    ]
    # a photo's rays march over its DSM window: seconds a photo on a fine DSM, so in parallel
    return tuple(
        map_ordered(
            visibility_task,
            jobs,
            workers=options.workers,
            initializer=init_visibility,
            # the skip levels made here once (full-grid passes), sent with the DSM (1/64 of it)
            initargs=(surface, block_tops(surface)),
            feedback=fb,
        )
    )


def _seams_and_gains(
    placed: Any,
    surface: Surface,
    vis: tuple[VisibilityGrid | None, ...],
    transform: Affine,
    shape: tuple[int, int],
    options: MosaicOptions,
    fb: Feedback,
) -> Any:
    # Seams and gains are decided on cells 8x coarser (and no more than 2 Mpx): the graph cut's time
    # grows with the cells in the seam bands.
    factor = max(8, int(math.ceil(math.sqrt(shape[0] * shape[1] / 2.0e6))))
    return plan_seams(
        list(placed.cams),
        list(placed.boxes),
        list(placed.gsds),
        surface,
        list(vis),
        transform,
        shape,
        factor,
        seams=options.seams,
        balance=options.balance,
        feedback=fb,
    )


def _coverage_notes(cover: dict[str, Any], fb: Feedback) -> list[str]:
    """The orthophoto's area against the ground its photos saw; a warning when it misses some."""
    notes = [
        f"the orthophoto shows {cover['area_m2']:,.0f} m²: {cover['share_of_seen_1']:.1%} of the "
        f"{cover['seen_1_m2']:,.0f} m² its photos saw, {cover['share_of_seen_2']:.1%} of the "
        f"{cover['seen_2_m2']:,.0f} m² seen by >= 2; {cover['on_interpolated_m2']:,.0f} m² of it on an "
        f"interpolated surface, {cover['occluded_m2']:,.1f} m² seen by no photo (occluded: drawn from the "
        "seen ground round it, marked in the source raster)"
    ]
    fb.info(notes[-1])
    if cover["holes_inside_m2"] > 0:
        notes.append(
            f"{cover['holes_inside_n']:.0f} holes inside the orthophoto, {cover['holes_inside_m2']:,.1f} m² "
            f"(the largest {cover['largest_hole_m2']:,.1f} m²)"
        )
        fb.warning(notes[-1])
    if cover["share_of_seen_1"] < MIN_SHARE_OF_SEEN:
        notes.append(
            f"the orthophoto misses {1 - cover['share_of_seen_1']:.0%} of the ground its photos saw "
            f"(less than {MIN_SHARE_OF_SEEN:.0%} covered)"
        )
        fb.warning(notes[-1])
    return notes


def _ratio(totals: dict[str, float], a: str, n: str) -> float:
    """A mean over the tiles: the sum of ``a`` over the count ``n`` (NaN when nothing was counted)."""
    return totals.get(a, 0.0) / totals[n] if totals.get(n) else math.nan


def _write_report(
    result: OrthoResult,
    totals: dict[str, float],
    gains_bgr: dict[str, list[float]],
    seconds_total: float,
    coarse_views_held_max: int,
    unused: list[str],
) -> None:
    """``<name>_report.json``: the result's figures, and the seam and gain details behind them."""
    write_json(
        result.report,
        {
            **{k: v for k, v in result.__dict__.items() if k not in ("skipped", "notes")},
            "skipped": [{"image": n, "reason": w} for n, w in result.skipped],
            # placed on the surface, but no pixel of theirs in the mosaic (others' views were chosen)
            "not_in_mosaic": unused,
            "notes": list(result.notes),
            "seam_step_dn": _ratio(totals, "step_seam", "step_n"),
            "texture_step_dn": _ratio(totals, "step_other", "other_n"),
            "seam_pixels": int(totals.get("seam_n", 0)),
            # seam pixels where the two balanced photos differ by more than VISIBLE_SEAM_DN (low-passed):
            # the seam one can see, which a long seam through agreeing ground does not inflate
            "seam_visible_pixels": int(totals.get("seam_visible", 0)),
            "gains_bgr": gains_bgr,
            # the seam pass streams photos: how many coarse views it held at once (memory)
            "coarse_views_held_max": coarse_views_held_max,
            "seconds_total": seconds_total,
        },
    )


def _render(
    ctx: TileContext, crs: CRS, target: Path, options: MosaicOptions, progress: Feedback, sources: SourceWriter
) -> tuple[dict[str, float], set[int]]:
    """Every tile rendered (in parallel) into the tiled GeoTIFF ``target``, each pixel's source
    into ``sources``.

    Returns the tiles' summed statistics and the photos used."""
    import rasterio
    from rasterio.enums import ColorInterp

    shape, tile_px = ctx.shape, options.tile_px
    tiles = [
        Window(c, r, min(tile_px, shape[1] - c), min(tile_px, shape[0] - r))
        for r in range(0, shape[0], tile_px)
        for c in range(0, shape[1], tile_px)
    ]
    totals: dict[str, float] = {}
    used: set[int] = set()
    profile = {
        "driver": "GTiff",
        "width": shape[1],
        "height": shape[0],
        "count": 4,
        "dtype": "uint8",
        "crs": crs,
        "transform": ctx.transform,
        "tiled": True,
        "blockxsize": 512,
        "blockysize": 512,
        "BIGTIFF": "IF_SAFER",
    }
    with rasterio.open(target, "w", **profile) as dst:
        dst.colorinterp = [ColorInterp.red, ColorInterp.green, ColorInterp.blue, ColorInterp.alpha]
        for win, rgba, source, stats in imap_ordered(
            render_tile, tiles, workers=options.workers, initializer=init_worker, initargs=(ctx,), feedback=progress
        ):
            dst.write(rgba, window=win)
            sources.write(source, win)
            used |= stats.pop("used")  # type: ignore[arg-type]
            for k, v in stats.items():
                totals[k] = totals.get(k, 0.0) + v
    return totals, used


def _describe(surface: Surface) -> str:
    if isinstance(surface, FlatSurface):
        return f"flat ground at {surface.elevation_m:.2f} m"
    cell = surface.cell_m if isinstance(surface, GridSurface) else math.nan
    return f"DSM, cells of {cell:g}"


def _write_cog(src_path: Path, target: Path, compress: str) -> None:
    """The finished mosaic as a COG: RGBA with DEFLATE, or RGB + mask with JPEG (JPEG has no alpha)."""
    import rasterio
    from rasterio.shutil import copy as rio_copy

    opts: dict[str, Any] = {
        "driver": "COG",
        "compress": compress,
        "blocksize": 512,
        "BIGTIFF": "IF_SAFER",
        "overview_resampling": "average",
        "num_threads": "ALL_CPUS",
    }
    with atomic_path(target) as tmp:
        if compress == "JPEG":
            rgb_mask = src_path.with_name("rgb_mask.tif")
            with rasterio.Env(GDAL_TIFF_INTERNAL_MASK=True), rasterio.open(src_path) as src:
                prof = {**src.profile, "count": 3}
                with rasterio.open(rgb_mask, "w", **prof) as dst:
                    for _, w in src.block_windows(1):
                        dst.write(src.read((1, 2, 3), window=w), window=w)
                        dst.write_mask(src.read(4, window=w), window=w)
            with rasterio.Env(GDAL_TIFF_INTERNAL_MASK=True):
                rio_copy(rgb_mask, tmp, quality=90, **opts)
        else:
            rio_copy(src_path, tmp, predictor=2, **opts)


def _write_preview(ortho_path: Path, target: Path, max_side_px: int = 2048) -> Path:
    """A PNG of the whole mosaic, read from the COG's overviews."""
    import rasterio
    from rasterio.enums import Resampling

    with rasterio.open(ortho_path) as src:
        scale = max(1.0, max(src.width, src.height) / max_side_px)
        h, w = max(1, int(src.height / scale)), max(1, int(src.width / scale))
        rgb = src.read((1, 2, 3), out_shape=(3, h, w), resampling=Resampling.average)
        alpha = src.dataset_mask(out_shape=(h, w))
    return write_png(target, np.dstack([rgb[2], rgb[1], rgb[0], alpha]))


# ---------------------------------------------------------------------------------------------
# the algorithm


def ortho(
    images: Path,
    output: Path,
    sfm: Path | None = None,
    dsm: Path | None = None,
    resolution_m: float | None = None,
    crs: CRS | None = None,
    ground_elevation_m: float | None = None,
    takeoff_elevation_m: float | None = None,
    seams: SeamMethod = MosaicOptions.seams,
    balance: Balance = MosaicOptions.balance,
    blend: Blend = MosaicOptions.blend,
    max_hole_px: int = MosaicOptions.max_hole_px,
    compress: Compression = MosaicOptions.compress,
    preview: Path | None = None,
    interpolation: Interpolation = MosaicOptions.interpolation,
    tile_px: int = MosaicOptions.tile_px,
    workers: int = MosaicOptions.workers,
    flight_height_m: float | None = None,
    gps_altitude: GpsAltitude = "auto",
    dsm_offset: DsmOffset = "correct",
    max_dsm_offset_m: float = 1.0,
    *,
    feedback: Feedback | None = None,
) -> OrthoResult:
    """Orthophoto mosaic: photos orthorectified on the DSM, seams, colour balance, blending, hole fill, COG.

    Poses come from an sfm output folder or, without one, from the photo
    metadata (GPS, altitude, gimbal: a direct-georeferencing mosaic for a field
    check). The surface is the DSM when given (occlusions handled: a true
    orthophoto), else flat ground.

    Parameters
    ----------
    images : Path
        Folder of photos.
    output : Path
        Orthophoto GeoTIFF (COG, RGB + alpha; JPEG: RGB + mask). A report
        ``<name>_report.json`` is written beside it.
    sfm : Path
        Output folder of the sfm algorithm (poses and calibrated cameras).
    dsm : Path
        Surface model to rectify on (e.g. from the dem algorithm).
    resolution_m : float
        Ground size of an output pixel, metres; default (or 0): the photos' median GSD.
    crs : CRS
        Output CRS (projected); default the SfM model's or the photos' UTM zone.
    ground_elevation_m : float
        Flat ground elevation when no DSM is given (default: the SfM points'
        median height, or the take-off elevation).
    takeoff_elevation_m : float
        Ground elevation of the take-off point, in the vertical datum of the ground
        model (the DSM, the ground elevation or the GCPs). Default: worked out from the
        photos (absolute − relative altitude, checked against the
        ground model; else the ground under the flight), and said.
    seams : str
        graphcut (seams moved onto low-difference paths) or voronoi (best-seeing photo).
    balance : str
        channels (per-photo RGB gains solved over all overlaps), gain (one gain per photo) or none.
    blend : str
        multiband, feather or none across seams.
    max_hole_px : int
        Holes inside the coverage up to this width (px) are inpainted; wider ones stay transparent.
    compress : str
        DEFLATE (lossless, RGBA) or JPEG (quality 90, RGB + mask).
    preview : Path
        Also write a PNG preview (at most 2048 px a side).
    interpolation : str
        How photos are sampled: bilinear, bicubic, lanczos or nearest.
    tile_px : int
        Side of the processing tiles (memory grows with its square).
    workers : int
        Processes for the tiles (0 = every core).
    flight_height_m : float
        For poses from metadata: flight height above the take-off ground, instead of the
        photos' altitudes (cameras that write only a sea-level GPS altitude).
    gps_altitude : str
        For poses from metadata without RelativeAltitude: what GPSAltitude holds (auto,
        above-takeoff, orthometric, ellipsoidal).
    dsm_offset : str
        With sfm and a DSM: the DSM's vertical offset from the SfM points is measured; beyond
        max_dsm_offset_m it is corrected (the DSM moved onto the points), refused, or ignored.
    max_dsm_offset_m : float
        Largest vertical offset between the DSM and the SfM points taken as agreement.
    """

    fb = as_feedback(feedback)
    images = Path(images)
    notes: list[str] = []
    skipped: list[tuple[str, str]] = []
    if dsm_offset not in DSM_OFFSET:
        raise InputError(f"dsm_offset {dsm_offset!r} is not one of {', '.join(DSM_OFFSET)}")
    pts = None
    if sfm is not None:
        cams, out_crs, pts, skipped = cameras_from_sfm(sfm, images, crs)
        poses = f"sfm ({Path(sfm)})"
        default_ground = float(np.median(pts[:, 2])) if len(pts) else None
    else:
        # one photo without an altitude is skipped, as in footprints, not the end of the mosaic
        photoset = photos_with_altitude(images, None, flight_height_m, fb, fb)
        skipped = list(photoset.skipped)
        out_crs = working_crs(photoset.photos, crs)
        cams, default_ground, poses = None, None, "photo metadata (direct georeferencing)"
    if abs(horizontal_unit_m(out_crs) - 1.0) > 1e-9:
        # poses, heights and resolution_m are metres: a feet grid would be silently mis-scaled
        raise InputError(
            f"the orthophoto is made in a CRS in metres and {crs_to_text(out_crs)} is not: "
            "give crs in metres (and reproject the product if feet are wanted)"
        )
    measured_offset = math.nan
    surface = given_surface(dsm, ground_elevation_m, default_ground, out_crs, notes, fb)
    if cams is None:
        placed, heights = photo_cameras(
            photoset.photos, out_crs, surface, takeoff_elevation_m, flight_height_m=flight_height_m,
            gps_altitude=gps_altitude,
        )  # fmt: skip
        cams = list(placed)
        surface = heights.surface
        notes.append(f"heights: {heights.method}; vertical datum: {heights.datum}")
        for note in heights.notes:
            notes.append(note)
            fb.warning(note)
    elif isinstance(surface, GridSurface) and pts is not None and len(pts):
        flown_m = float(np.median([c.pose.center[2] for c in cams]) - np.median(pts[:, 2])) if len(cams) else math.nan
        surface, measured_offset = check_dsm_against_points(
            surface, pts, dsm_offset, max_dsm_offset_m, notes, fb, flown_m
        )
    if len(cams) == 0:
        raise InputError("no registered photo to rectify", path=sfm or images)
    options = MosaicOptions(
        seams=seams, balance=balance, blend=blend, max_hole_px=max_hole_px, compress=compress,
        interpolation=interpolation, tile_px=tile_px, workers=workers,
    )  # fmt: skip
    Path(output).parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix=temp_prefix(Path(output).name), dir=Path(output).parent) as held:
        surface = _held_once(surface, held)  # from here on this process holds no copy of its own
        return mosaic(
            cams, surface, out_crs, output, resolution_m, options, preview=preview, poses=poses, notes=notes,
            skipped=skipped, dsm_source=source_path(dsm) if dsm is not None else None, dsm_offset_m=measured_offset,
            feedback=fb,
        )  # fmt: skip
