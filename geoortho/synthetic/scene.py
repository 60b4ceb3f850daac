"""The synthetic scene: terrain with breaklines, land cover, buildings and trees, the GCP markers on
their pads, water and cover, with the exact DSM, DTM and colours."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import cv2
import numpy as np
from affine import Affine
from pyproj import CRS

from geoortho.core.crs import transformer, utm_crs_for
from geoortho.core.surface import GridSurface, sample_grid
from geoortho.errors import InputError
from geoortho.gcp.markers import (
    get_dictionary,
    marker_cells,
    target_half_extent,
    target_reflectance,
)
from geoortho.synthetic.cover import (
    CoverGround,
    add_canopy,
    add_car_park,
    add_hall,
    add_hedge,
    add_second_epoch,
    add_stockpiles,
    leaf_texture,
)
from geoortho.synthetic.movers import Mover
from geoortho.synthetic.presets import (
    BANK_M,
    CUTTING_M,
    FOCAL_MM,
    SENSOR_WIDTH_MM,
    SLOPE_AZIMUTH_DEG,
    WATER_RADIUS_M,
    WATER_RGB,
    WIDE_WOOD_RADIUS_M,
    SynthPreset,
)


@dataclass(frozen=True)
class Marker:
    marker_id: int
    name: str
    x: float
    y: float
    z: float
    angle_deg: float
    decoy: bool = False


@dataclass(eq=False)
class Scene:
    crs: CRS
    transform: Affine  # of the DSM/DTM grids (cell corners)
    dsm: np.ndarray
    dtm: np.ndarray
    landcover: np.ndarray  # (rows, cols, 3) float32 colours on the DSM grid, 0..1
    objects: np.ndarray  # (rows, cols, 3) float32 colours of roofs/trees
    noise: tuple[np.ndarray, ...]
    noise_cells_m: tuple[float, ...]
    markers: tuple[Marker, ...]
    marker_size_m: float
    dictionary: str
    flight_box: tuple[float, float, float, float]  # xmin, ymin, xmax, ymax
    home: tuple[float, float, float]  # take-off point (x, y, ground z)
    marker_cells: dict[int, np.ndarray] = field(default_factory=dict)
    water: tuple[float, float, float] | None = None  # x, y, radius (m): one flat colour there
    target: str = "aruco"  # what the markers look like (markers.TARGETS)
    canopy: np.ndarray | None = None  # (rows, cols) bool on the DSM grid: a wood's crowns, leaf-textured
    canopy_style: str = "pattern"  # how the leaves are drawn (cover.CANOPY_STYLES)
    cover: dict[str, dict[str, Any]] = field(default_factory=dict)  # canopy/cars: where they are
    movers: tuple[Mover, ...] = ()  # moving cars and people (not in the truth's rasters)
    buildings: np.ndarray | None = None  # (rows, cols) bool on the DSM grid: the buildings' cells
    building_records: tuple[dict[str, float], ...] = ()  # each building's rectangle and eave height
    facade_style: str = ""  # how walls are painted (FACADE_STYLES); "": as their roofs

    @property
    def surface(self) -> GridSurface:
        """The DSM as a surface, kept while the DSM is the same array: its coarse maxima, which
        every ray march needs, are then worked out once (at 1,000 photos, 45 s of the truth's)."""
        kept = self.__dict__.get("_surface")
        if kept is None or kept[0] is not self.dsm:
            kept = (self.dsm, GridSurface(self.dsm, self.transform, self.crs))
            self.__dict__["_surface"] = kept
        return kept[1]

    def colrow(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        t = self.transform
        return (x - t.c) / t.a - 0.5, (y - t.f) / t.e - 0.5

    def color(self, x: np.ndarray, y: np.ndarray, z: np.ndarray) -> np.ndarray:
        """Ground colour (N, 3) float 0..1 at world points: the procedural texture."""
        c, r = self.colrow(x, y)
        c32, r32 = c.astype(np.float32), r.astype(np.float32)
        base = remap3(self.landcover, c32, r32)
        ground = sample_grid(self.dtm, c32, r32)
        above = (z - ground) > 0.25
        if above.any():
            base[above] = remap3(self.objects, c32[above], r32[above])
        detail = np.ones(len(x), np.float32)
        for grid, cell, amp in zip(self.noise, self.noise_cells_m, (0.22, 0.18, 0.14)):
            detail += amp * _wrap_sample(grid, x / cell, y / cell)
        if self.canopy is not None and above.any():
            leafy = np.zeros(len(x), bool)
            ci = np.clip(np.rint(c[above]).astype(np.int64), 0, self.canopy.shape[1] - 1)
            ri = np.clip(np.rint(r[above]).astype(np.int64), 0, self.canopy.shape[0] - 1)
            leafy[above] = self.canopy[ri, ci]
            if leafy.any():
                base[leafy] *= leaf_texture(self.canopy_style, x[leafy], y[leafy], self.noise[1])[:, None]
        if self.facade_style and above.any():
            wall = above & self._on_wall(c, r, z)
            if wall.any():
                base[wall] = facade_colour(self.facade_style, z[wall] - ground[wall], x[wall], y[wall])
        out = base * detail[:, None]
        if self.water is not None:
            wx, wy, wr = self.water
            out[(x - wx) ** 2 + (y - wy) ** 2 <= wr * wr] = WATER_RGB
        self._paint_markers(x, y, z, out)
        return np.clip(out, 0.0, 1.0)

    def _on_wall(self, c: np.ndarray, r: np.ndarray, z: np.ndarray) -> np.ndarray:
        """Points on a building's wall: beside a building's cell and more than a quarter metre under
        the highest of the four cell centres round them (the DSM steps there; on a roof it does not)."""
        assert self.buildings is not None
        rows, cols = self.dsm.shape
        c0 = np.clip(np.floor(c).astype(np.int64), 0, cols - 2)
        r0 = np.clip(np.floor(r).astype(np.int64), 0, rows - 2)
        top = np.full(len(c), -np.inf, np.float32)
        near = np.zeros(len(c), bool)
        for dr in (0, 1):
            for dc in (0, 1):
                top = np.maximum(top, self.dsm[r0 + dr, c0 + dc])
                near |= self.buildings[r0 + dr, c0 + dc]
        return np.asarray(near & (top - z > 0.25))

    def _paint_markers(self, x: np.ndarray, y: np.ndarray, z: np.ndarray, out: np.ndarray) -> None:
        s = self.marker_size_m
        reach = s * max(target_half_extent(self.target), target_half_extent("aruco")) * 1.5
        if not len(x):
            return
        # only the markers whose reach meets these points' box: a photo sees a few of a wide survey's
        x0, x1, y0, y1 = float(np.min(x)), float(np.max(x)), float(np.min(y)), float(np.max(y))
        for m in self.markers:
            if m.x + reach < x0 or m.x - reach > x1 or m.y + reach < y0 or m.y - reach > y1:
                continue
            near = (np.abs(x - m.x) < reach) & (np.abs(y - m.y) < reach) & (np.abs(z - m.z) < 0.2)
            if not near.any():
                continue
            a = math.radians(m.angle_deg)
            dx, dy = x[near] - m.x, y[near] - m.y
            # marker frame: u to the marker's right, v to its top (rotated by angle, clockwise)
            u = dx * math.cos(a) - dy * math.sin(a)
            v = dx * math.sin(a) + dy * math.cos(a)
            refl = target_reflectance(self.target, u / s, v / s, self.marker_cells.get(m.marker_id))
            painted = np.isfinite(refl)
            idx = np.nonzero(near)[0][painted]
            out[idx] = (0.08 + 0.84 * refl[painted]).astype(np.float32)[:, None]


#: How the facades pathology paints walls: storeys of windows, or cladding in courses.
FACADE_STYLES = ("windows", "courses")


def facade_colour(style: str, height_m: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """A facade's colour (N, 3) float 0..1 at points ``height_m`` above the ground (and x, y: where
    along the wall, for the windows)."""
    if style == "windows":
        storey = np.mod(height_m, 3.0) / 3.0
        along = np.mod(x + y, 2.4) / 2.4
        window = (storey > 0.35) & (storey < 0.8) & (along > 0.25) & (along < 0.75)
        out = np.where(window[:, None], [0.12, 0.16, 0.24], [0.86, 0.80, 0.66])
    elif style == "courses":
        course = np.mod(height_m, 2.0)
        out = np.where((course < 1.0)[:, None], [0.70, 0.34, 0.22], [0.30, 0.16, 0.12])
        out = np.where((np.mod(height_m, 1.0) < 0.12)[:, None], [0.88, 0.86, 0.80], out)  # the joints
    else:
        raise ValueError(f"unknown facade style {style!r}")
    return np.asarray(out, np.float32)


def remap3(img: np.ndarray, c: np.ndarray, r: np.ndarray) -> np.ndarray:
    out = np.empty((len(c), 3), np.float32)
    for k in range(3):
        v = sample_grid(img[..., k], c, r)
        out[:, k] = np.nan_to_num(v, nan=0.5)
    return out


def _wrap_sample(grid: np.ndarray, fx: np.ndarray, fy: np.ndarray) -> np.ndarray:
    n0, n1 = grid.shape[0] - 1, grid.shape[1] - 1  # the grid carries one wrapped row/column
    c = np.mod(fx, n1).astype(np.float32)
    r = np.mod(-fy, n0).astype(np.float32)
    v = sample_grid(grid, c, r)
    result: np.ndarray = np.nan_to_num(v)
    return result


def _smooth_noise(rng: np.random.Generator, shape: tuple[int, int], blur: float) -> np.ndarray:
    from scipy.ndimage import gaussian_filter

    n = gaussian_filter(rng.standard_normal(shape), blur, mode="wrap").astype(np.float32)
    n /= n.std() + 1e-9
    # One wrapped row/column extra so bilinear sampling never reads past the edge.
    return np.pad(n, ((0, 1), (0, 1)), mode="wrap")


def build_scene(
    preset: SynthPreset,
    rng: np.random.Generator,
    *,
    lat: float,
    lon: float,
    dictionary: str,
    marker_size_m: float,
    slope_deg: float = 0.0,
    bank_deg: float = 0.0,
) -> Scene:
    """The DTM, DSM, texture layers and marker layout for a preset.

    The stages draw from ``rng`` in a fixed order (terrain, landcover, markers, buildings and
    trees, texture noise): the same seed gives the same scene, byte for byte. ``slope_deg``
    tilts the terrain (rising towards SLOPE_AZIMUTH_DEG) and draws nothing."""
    g = _scene_grid(preset, lat, lon)
    dtm = _terrain(g, preset, rng)
    if slope_deg:
        lx, ly = g.local
        az = math.radians(SLOPE_AZIMUTH_DEG)
        dtm = dtm + math.tan(math.radians(slope_deg)) * (lx * math.sin(az) + ly * math.cos(az))
    breaks: dict[str, Any] = {}
    if bank_deg:
        dtm, breaks = _breaklines(g, dtm, bank_deg, np.random.default_rng([int(1000 * bank_deg), 29]))
    landcover, n_fields = _landcover(g, preset, rng)
    taken = _Occupancy()
    markers, pad_r = _place_markers(g, preset, rng, dictionary, marker_size_m, taken)
    objects, height, buildings, records = _buildings_and_trees(g, preset, rng, dtm, taken)
    dtm, markers = _marker_pads(g, dtm, markers, pad_r)
    dsm = (dtm + height).astype(np.float32)
    noise_cells = (0.02, 0.09, 0.45)
    noise = tuple(_smooth_noise(rng, (s, s), 1.0) for s in (1021, 1031, 1009))
    hx, hy = g.flight_box[0] - 5.0, g.flight_box[1] - 5.0
    home_z = float(sample_grid(dtm, *_cr(g.transform, hx, hy))[0])
    scene = Scene(
        g.crs,
        g.transform,
        dsm,
        dtm,
        landcover.astype(np.float32),
        objects.astype(np.float32),
        noise,
        noise_cells,
        tuple(markers),
        marker_size_m,
        dictionary,
        g.flight_box,
        (hx, hy, home_z),
    )
    scene.marker_cells = {m.marker_id: marker_cells(dictionary, m.marker_id) for m in markers}
    scene.buildings, scene.building_records = buildings, tuple(records)
    if breaks:
        scene.cover["breaklines"] = breaks
    return scene


def _breaklines(
    g: _SceneGrid, dtm: np.ndarray, bank_deg: float, rng: np.random.Generator
) -> tuple[np.ndarray, dict[str, Any]]:
    """A bank across the scene (the ground BANK_M higher on one side, sloping at ``bank_deg``) and a
    road cutting parallel to it on its low side, CUTTING_M deep and wide with 45 deg sides, a third
    of the flight area away: the DTM with them, and where they are (their offsets along one normal)."""
    lx, ly = g.local
    ang = float(rng.uniform(0, np.pi))
    d = lx * math.cos(ang) + ly * math.sin(ang)  # distance along the normal from the centre
    span = min(g.area_m)
    # the cutting on the bank's low side: the ground between them is a terrace below the bank, not
    # a strip standing above the ground on both sides (an embankment, which every ground filter
    # takes for an object); the bank near the middle, its high side wider than SMRF's reach (a
    # terrace 10 m wide at a survey's edge, 2 m up, is an object to it)
    bank_at = -0.05 * span
    cut_at = bank_at - max(0.3 * span, 12.0)  # a shelf of 6 m or more between the bank and the cutting
    run = BANK_M[0] / math.tan(math.radians(bank_deg))
    bank = BANK_M[0] * np.clip((d - bank_at) / run + 0.5, 0.0, 1.0)
    depth, road = CUTTING_M
    cut = np.clip(depth - np.maximum(np.abs(d - cut_at) - road / 2, 0.0), 0.0, depth)  # 45 deg sides
    where = {"normal_deg": math.degrees(ang), "bank_offset_m": bank_at, "bank_deg": bank_deg,
             "bank_height_m": BANK_M[0], "cutting_offset_m": cut_at, "cutting_depth_m": depth,
             "cutting_width_m": road}  # fmt: skip
    return (dtm + bank - cut).astype(np.float64), where


@dataclass(frozen=True)
class _SceneGrid:
    """The scene's raster grid: the survey area with a margin the photos' footprints fit in."""

    crs: CRS
    e0: float  # scene centre, easting and northing (rounded to 10 m)
    n0: float
    area_m: tuple[float, float]
    margin_m: float
    xmin: float
    ymin: float
    cell: float
    rows: int
    cols: int
    transform: Affine
    X: np.ndarray  # cell centres
    Y: np.ndarray

    @property
    def flight_box(self) -> tuple[float, float, float, float]:
        aw, ah = self.area_m
        return self.e0 - aw / 2, self.n0 - ah / 2, self.e0 + aw / 2, self.n0 + ah / 2

    @property
    def local(self) -> tuple[np.ndarray, np.ndarray]:
        return self.X - self.e0, self.Y - self.n0

    def window(self, x: float, y: float, radius_m: float) -> tuple[slice, slice]:
        """The rows and columns whose cell centres may lie within ``radius_m`` of (x, y): an object
        is drawn there alone, not over the whole grid (a 1,000-photo scene has a thousand objects)."""
        reach = radius_m + self.cell
        c0 = max(int(math.floor((x - reach - self.xmin) / self.cell)), 0)
        c1 = min(int(math.ceil((x + reach - self.xmin) / self.cell)) + 1, self.cols)
        top = self.ymin + self.rows * self.cell
        r0 = max(int(math.floor((top - (y + reach)) / self.cell)), 0)
        r1 = min(int(math.ceil((top - (y - reach)) / self.cell)) + 1, self.rows)
        return slice(r0, max(r0, r1)), slice(c0, max(c0, c1))


def _scene_grid(preset: SynthPreset, lat: float, lon: float) -> _SceneGrid:
    crs = utm_crs_for(lon, lat)
    e0, n0 = transformer(CRS.from_epsg(4326), crs).transform(lon, lat)
    e0, n0 = round(e0 / 10) * 10, round(n0 / 10) * 10
    aw, ah = preset.area_m
    fw, fh = footprint_size_m(preset)
    margin = max(fw, fh) * 0.6 + 25.0
    if preset.n_oblique:
        margin = max(margin, preset.altitude_m / math.tan(math.radians(16.0)) + 20.0)
    cell = preset.cell_m
    xmin, ymin = e0 - aw / 2 - margin, n0 - ah / 2 - margin
    cols = int(math.ceil((aw + 2 * margin) / cell))
    rows = int(math.ceil((ah + 2 * margin) / cell))
    transform = Affine(cell, 0, xmin, 0, -cell, ymin + rows * cell)
    xs = xmin + (np.arange(cols) + 0.5) * cell
    ys = ymin + rows * cell - (np.arange(rows) + 0.5) * cell
    X, Y = np.meshgrid(xs, ys)
    return _SceneGrid(crs, e0, n0, (aw, ah), margin, xmin, ymin, cell, rows, cols, transform, X, Y)


_BASE_Z = 110.0


def _terrain(g: _SceneGrid, preset: SynthPreset, rng: np.random.Generator) -> np.ndarray:
    """Gentle slopes and a ridge (metres, ellipsoidal)."""
    lx, ly = g.local
    ph = rng.uniform(0, 2 * np.pi, 4)
    dtm = (
        _BASE_Z
        + 2.5 * np.sin(lx / 70 + ph[0]) * np.cos(ly / 90 + ph[1])
        + 1.2 * np.sin(lx / 31 + ph[2])
        + 0.02 * lx
        - 0.015 * ly
    )
    ang = rng.uniform(0, np.pi)
    d_ridge = (lx * np.cos(ang) + ly * np.sin(ang)) - rng.uniform(-0.3, 0.3) * g.area_m[0]
    return dtm + 4.0 * np.exp(-0.5 * (d_ridge / 12.0) ** 2)  # type: ignore[no-any-return]


def _landcover(g: _SceneGrid, preset: SynthPreset, rng: np.random.Generator) -> tuple[np.ndarray, int]:
    """Landcover colours: Voronoi fields with stripes, roads, paths and clutter; and the number of fields."""
    from scipy.spatial import cKDTree

    lx, ly = g.local
    rows, cols, cell = g.rows, g.cols, g.cell
    palette = np.array(
        [
            [0.42, 0.55, 0.25],
            [0.55, 0.60, 0.30],
            [0.70, 0.65, 0.38],
            [0.52, 0.40, 0.28],
            [0.35, 0.48, 0.22],
            [0.62, 0.52, 0.35],
            [0.47, 0.58, 0.36],
        ],
        np.float32,
    )
    n_fields = max(6, int((g.area_m[0] + 2 * g.margin_m) * (g.area_m[1] + 2 * g.margin_m) / 700))
    seeds = np.c_[rng.uniform(0, cols, n_fields), rng.uniform(0, rows, n_fields)]
    _, label = cKDTree(seeds).query(
        np.c_[np.repeat(np.arange(cols)[None], rows, 0).ravel(), np.repeat(np.arange(rows)[:, None], cols, 1).ravel()]
    )
    label = label.reshape(rows, cols)
    field_col = palette[rng.integers(0, len(palette), n_fields)]
    landcover = field_col[label].copy()
    stripe_angle = rng.uniform(0, np.pi, n_fields)[label]
    stripe_period = rng.uniform(1.2, 3.5, n_fields)[label]
    stripes = np.sin(2 * np.pi * (lx * np.cos(stripe_angle) + ly * np.sin(stripe_angle)) / stripe_period)
    landcover *= (1.0 + 0.10 * stripes)[..., None].astype(np.float32)
    canvas = np.ascontiguousarray(landcover)
    px_per_m = 1.0 / cell
    aw, ah = g.area_m

    def to_px(x: float, y: float) -> tuple[int, int]:
        return int(round((x - g.xmin) * px_per_m * 16)), int(round((g.ymin + rows * cell - y) * px_per_m * 16))

    for _ in range(2):  # roads through the scene
        a = rng.uniform(0, np.pi)
        off = rng.uniform(-0.4, 0.4) * np.array([aw, ah])
        c = np.array([g.e0, g.n0]) + off
        d = np.array([np.cos(a), np.sin(a)]) * 2000
        p1, p2 = to_px(*(c - d)), to_px(*(c + d))
        cv2.line(canvas, p1, p2, (0.36, 0.36, 0.38), int(5.0 * px_per_m), cv2.LINE_AA, shift=4)
        cv2.line(canvas, p1, p2, (0.85, 0.85, 0.80), max(1, int(0.15 * px_per_m)), cv2.LINE_AA, shift=4)
    for _ in range(int(n_fields * 1.5)):  # clutter: sheds, cars, bushes, patches
        x, y = rng.uniform(g.xmin, g.xmin + cols * cell), rng.uniform(g.ymin, g.ymin + rows * cell)
        colr = tuple(float(v) for v in rng.uniform(0.1, 0.9, 3))
        if rng.random() < 0.5:
            cv2.circle(canvas, to_px(x, y), int(rng.uniform(0.4, 2.0) * px_per_m * 16), colr, -1, cv2.LINE_AA, shift=4)
        else:
            w, h, an = rng.uniform(0.8, 4.0), rng.uniform(0.6, 2.5), rng.uniform(0, 180)
            box = cv2.boxPoints(((x, y), (w, h), an))
            pts = np.array([to_px(*p) for p in box], np.int32)
            cv2.fillPoly(canvas, [pts], colr, cv2.LINE_AA, shift=4)
    return canvas, n_fields


class _Occupancy:
    """Discs already taken by markers, buildings and trees: new objects keep clear of them."""

    def __init__(self) -> None:
        self.discs: list[tuple[float, float, float]] = []

    def free(self, x: float, y: float, r: float) -> bool:
        return all(math.hypot(x - ox, y - oy) > r + orad for ox, oy, orad in self.discs)

    def take(self, x: float, y: float, r: float) -> None:
        self.discs.append((x, y, r))


def _place_markers(
    g: _SceneGrid,
    preset: SynthPreset,
    rng: np.random.Generator,
    dictionary: str,
    marker_size_m: float,
    taken: _Occupancy,
) -> tuple[list[Marker], float]:
    """Markers on flat pads, then decoys (ids never in a GCP file); and the pads' radius."""
    fx0, fy0, fx1, fy1 = g.flight_box
    aw, ah = g.area_m
    n_ids = get_dictionary(dictionary).bytesList.shape[0]
    n_total = preset.n_markers + preset.n_decoys
    if n_total * 2 > n_ids:
        raise InputError(f"dictionary {dictionary} has too few ids for {n_total} markers")
    ids = rng.permutation(np.arange(1, n_ids))[:n_total]  # id 0 is never placed
    markers: list[Marker] = []
    pad_r = marker_size_m * 0.95 + 0.6
    spacing_m = min(8.0, math.sqrt(aw * ah / n_total) * 0.6)
    for k, mid in enumerate(ids):
        for _try in range(500):
            mx = rng.uniform(fx0 + 3, fx1 - 3)
            my = rng.uniform(fy0 + 3, fy1 - 3)
            if taken.free(mx, my, pad_r + 2.0) and all(math.hypot(mx - m.x, my - m.y) > spacing_m for m in markers):
                break
        else:
            raise InputError("could not place all markers; use fewer or a larger area")
        taken.take(mx, my, pad_r)
        decoy = k >= preset.n_markers
        markers.append(
            Marker(int(mid), f"GCP{int(mid):02d}", float(mx), float(my), 0.0, float(rng.uniform(0, 360)), decoy)
        )
    return markers, pad_r


def _buildings_and_trees(
    g: _SceneGrid, preset: SynthPreset, rng: np.random.Generator, dtm: np.ndarray, taken: _Occupancy
) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[dict[str, float]]]:
    """Buildings (gabled or flat) and trees, clear of each other and of the markers: colours,
    heights, the buildings' cells and their rectangles (centre, length, width, angle, eave height
    above the ground)."""
    fx0, fy0, fx1, fy1 = g.flight_box
    objects = np.zeros((g.rows, g.cols, 3), np.float32)
    height = np.zeros((g.rows, g.cols), np.float64)
    buildings = np.zeros((g.rows, g.cols), bool)
    records: list[dict[str, float]] = []
    for _ in range(preset.n_buildings):
        for _try in range(50):
            bx, by = rng.uniform(fx0 - 5, fx1 + 5), rng.uniform(fy0 - 5, fy1 + 5)
            bl, bw = rng.uniform(9, 16), rng.uniform(7, 11)
            if taken.free(bx, by, math.hypot(bl, bw) / 2 + 2):
                break
        else:
            continue
        taken.take(bx, by, math.hypot(bl, bw) / 2)
        ba = rng.uniform(0, np.pi)
        win = g.window(bx, by, math.hypot(bl, bw) / 2)
        X, Y = g.X[win], g.Y[win]
        u = (X - bx) * np.cos(ba) + (Y - by) * np.sin(ba)
        v = -(X - bx) * np.sin(ba) + (Y - by) * np.cos(ba)
        inside = (np.abs(u) <= bl / 2) & (np.abs(v) <= bw / 2)
        eave = rng.uniform(4.5, 9.0)
        if rng.random() < 0.6:
            roof = eave + rng.uniform(1.5, 3.0) * (1 - np.abs(v) / (bw / 2))
        else:
            roof = np.full_like(u, eave)
        ground_top = float(dtm[win][inside].max()) if inside.any() else _BASE_Z
        h = ground_top + roof - dtm[win]
        height[win] = np.where(inside, np.maximum(height[win], h), height[win])
        buildings[win] |= inside
        records.append({"x": bx, "y": by, "length_m": bl, "width_m": bw, "angle_deg": math.degrees(ba),
                        "eave_m": eave})  # fmt: skip
        rc = np.array(
            rng.choice([[0.62, 0.30, 0.22], [0.45, 0.45, 0.48], [0.70, 0.68, 0.62], [0.35, 0.30, 0.28]]), np.float32
        )
        shade = np.where(v > 0, 1.0, 0.82)[..., None].astype(np.float32)  # gable sides lit differently
        objects[win] = np.where(inside[..., None], rc * shade, objects[win])
    for _ in range(preset.n_trees):
        for _try in range(50):
            tx, ty = rng.uniform(fx0 - 10, fx1 + 10), rng.uniform(fy0 - 10, fy1 + 10)
            tr = rng.uniform(2.0, 3.5)
            if taken.free(tx, ty, tr + 1):
                break
        else:
            continue
        taken.take(tx, ty, tr)
        th = rng.uniform(5, 9)
        # the crown (bump > 0.3) ends where exp(-d²/2σ²) = 0.3/th: within σ·sqrt(2 ln(th/0.3))
        sigma = tr / 1.6
        win = g.window(tx, ty, sigma * math.sqrt(2 * math.log(th / 0.3)))
        X, Y = g.X[win], g.Y[win]
        bump = th * np.exp(-0.5 * ((X - tx) ** 2 + (Y - ty) ** 2) / sigma**2)
        crown = bump > 0.3
        height[win] = np.where(crown, np.maximum(height[win], bump), height[win])
        objects[win] = np.where(crown[..., None], np.array([0.20, 0.34, 0.14], np.float32), objects[win])
        buildings[win] &= ~crown
    return objects, height, buildings, records


def _marker_pads(
    g: _SceneGrid, dtm: np.ndarray, markers: list[Marker], pad_r: float
) -> tuple[np.ndarray, list[Marker]]:
    """Flat pads under the markers, blending into the terrain over 2 m; the markers at their pads' height."""
    placed = []
    dtm = np.array(dtm, dtype=np.float64)
    for m in markers:
        win = g.window(m.x, m.y, pad_r + 2.0)
        r = np.hypot(g.X[win] - m.x, g.Y[win] - m.y)
        # the bilinear sample reads the 2 x 2 cells round the marker, all inside its window; the
        # whole grid's float32 position less a whole number of cells is exact, so the same sample
        col, row = (v.astype(np.float32) for v in _cr(g.transform, m.x, m.y))
        z_pad = float(sample_grid(dtm[win].astype(np.float32), col - win[1].start, row - win[0].start)[0])
        w = np.clip((r - pad_r) / 2.0, 0.0, 1.0)
        w = w * w * (3 - 2 * w)
        dtm[win] = np.where(r < pad_r + 2.0, z_pad * (1 - w) + dtm[win] * w, dtm[win])
        placed.append(replace(m, z=z_pad))
    return dtm.astype(np.float32), placed


def _cr(transform: Affine, x: float, y: float) -> tuple[np.ndarray, np.ndarray]:
    return np.array([(x - transform.c) / transform.a - 0.5]), np.array([(y - transform.f) / transform.e - 0.5])


def footprint_size_m(preset: SynthPreset) -> tuple[float, float]:
    w = preset.altitude_m * SENSOR_WIDTH_MM / FOCAL_MM
    return w, w * preset.image_px[1] / preset.image_px[0]


def place_water(scene: Scene) -> tuple[float, float, float]:
    """The pond: the open-ground spot of the flight area farthest from buildings, trees and markers
    (no random draw, so the rest of the survey is the one the seed gives without it)."""
    from scipy.ndimage import distance_transform_edt

    t = scene.transform
    cell = t.a
    taken = (scene.dsm - scene.dtm) > 0.05
    for m in scene.markers:
        c, r = scene.colrow(np.array([m.x]), np.array([m.y]))
        taken[int(round(r[0])), int(round(c[0]))] = True
    clear_m = np.asarray(distance_transform_edt(~taken)) * cell
    rows, cols = np.indices(taken.shape)
    xs, ys = (np.asarray(v) for v in t * (cols + 0.5, rows + 0.5))
    fx0, fy0, fx1, fy1 = scene.flight_box
    inside = (xs > fx0 + 0.25 * (fx1 - fx0)) & (xs < fx1 - 0.25 * (fx1 - fx0))
    inside &= (ys > fy0 + 0.25 * (fy1 - fy0)) & (ys < fy1 - 0.25 * (fy1 - fy0))
    best = np.argmax(np.where(inside, clear_m, -1.0))
    radius = min(WATER_RADIUS_M, 0.5 * float(clear_m.flat[best]), 0.15 * min(fx1 - fx0, fy1 - fy0))
    return float(xs.flat[best]), float(ys.flat[best]), radius


def add_cover(
    scene: Scene, pathologies: Sequence[str], rng: np.random.Generator, canopy_style: str, seed: int = 0
) -> None:
    """The wood and the car park, each on the open ground left by what stands there already; a
    wide wood and a hall over it; a hedge on what is left; a yard of stockpiles and a pit."""
    markers_xy = [(m.x, m.y) for m in scene.markers]

    def ground() -> CoverGround:  # as each cover before has left it
        s = scene
        return CoverGround(s.transform, s.dsm, s.dtm, s.objects, s.landcover, s.flight_box, markers_xy)

    if "wide-wood" in pathologies:
        scene.dsm, scene.objects, scene.canopy, patch = add_canopy(
            ground(), rng, canopy_style, radius_m=WIDE_WOOD_RADIUS_M
        )
        scene.canopy_style = str(patch.detail["style"])
        scene.cover["wide_wood"] = patch.record()
    if "hall" in pathologies:
        scene.dsm, scene.objects, patch = add_hall(ground(), rng, seed % 2 == 1, avoid=scene.canopy)
        scene.cover["hall"] = patch.record()
    if "canopy" in pathologies:
        scene.dsm, scene.objects, wood, patch = add_canopy(ground(), rng, canopy_style)
        scene.canopy = wood if scene.canopy is None else (scene.canopy | wood)
        scene.canopy_style = str(patch.detail["style"])
        scene.cover["canopy"] = patch.record()
    if "cars" in pathologies:
        scene.dsm, scene.objects, scene.landcover, patch = add_car_park(ground(), rng)
        scene.cover["cars"] = patch.record()
    if "hedge" in pathologies:
        scene.dsm, scene.objects, hedge, patch = add_hedge(ground(), rng)
        scene.canopy = hedge if scene.canopy is None else (scene.canopy | hedge)
        scene.cover["hedge"] = patch.record()
    if "stockpiles" in pathologies:
        scene.dsm, scene.dtm, scene.landcover, patch = add_stockpiles(ground(), rng, lumpy=seed % 2 == 1)
        scene.cover["stockpiles"] = patch.record()
    if "second-epoch" in pathologies:
        scene.dsm, scene.dtm, scene.objects, scene.landcover, patch = add_second_epoch(
            ground(), rng, scene.cover.get("stockpiles")
        )
        scene.cover["second_epoch"] = patch.record()
