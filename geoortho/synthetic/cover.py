"""Land cover that broke the dense surface on real photos: a wood of closed canopy and a car park.

Both are drawn on the scene's DSM grid (heights, colours and, for the wood, a mask that the
renderer gives its leaf texture) with a generator of their own, so that a survey without them
is the one its seed always gave. Each is placed on the open ground of the flight area that is
farthest from the buildings, trees and markers already there, as the pond is.

The canopy is what matching finds hardest: crowns that overlap and hide each other, a fine leaf
texture that repeats from crown to crown, and deep shade between them. It is rendered one of two
ways (``CANOPY_STYLES``): leaves as a regular pattern (even seeds), or as noise blobs (odd ones).
The cars stand in rows on tarmac with their shadows cast on it (the sun in the south-west).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from affine import Affine

__all__ = [
    "CANOPY_STYLES",
    "CoverGround",
    "CoverPatch",
    "add_canopy",
    "add_car_park",
    "add_hall",
    "add_hedge",
    "add_stockpiles",
    "leaf_texture",
]

CANOPY_STYLES = ("pattern", "blobs")
SUN_AZIMUTH_DEG = 225.0  # from the south-west: shadows fall to the north-east
SUN_ELEVATION_DEG = 45.0
CAR_LENGTH_M, CAR_WIDTH_M = 4.4, 1.8
CAR_BODY_M, CAR_ROOF_M = 0.85, 1.45  # body and cabin heights
BAY_WIDTH_M = 2.5
CAR_COLOURS = np.array(
    [[0.92, 0.92, 0.90], [0.08, 0.08, 0.09], [0.66, 0.67, 0.70], [0.70, 0.10, 0.08], [0.12, 0.22, 0.55],
     [0.30, 0.31, 0.33]],
    np.float32,
)  # fmt: skip
TARMAC_RGB = (0.30, 0.30, 0.32)
SHADOW_GAIN = 0.45


@dataclass(frozen=True)
class CoverPatch:
    """Where a cover was put: centre and half-sizes (m), what it holds; survey.json records it."""

    kind: str
    x: float
    y: float
    half_w_m: float
    half_h_m: float
    detail: dict[str, Any]

    def record(self) -> dict[str, Any]:
        return {"x": self.x, "y": self.y, "half_w_m": self.half_w_m, "half_h_m": self.half_h_m, **self.detail}


@dataclass(frozen=True)
class CoverGround:
    """The scene's grids a cover is drawn on (the DSM grid's cells), and what it must keep clear."""

    transform: Affine
    dsm: np.ndarray
    dtm: np.ndarray
    objects: np.ndarray  # (rows, cols, 3) colours of what stands
    landcover: np.ndarray  # (rows, cols, 3) colours of the ground
    flight_box: tuple[float, float, float, float]
    markers_xy: list[tuple[float, float]]

    def centres(self) -> tuple[np.ndarray, np.ndarray]:
        return _centres(self.transform, self.dsm.shape)


def _centres(transform: Affine, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    rows, cols = np.indices(shape)
    x = transform.c + (cols + 0.5) * transform.a + (rows + 0.5) * transform.b
    y = transform.f + (cols + 0.5) * transform.d + (rows + 0.5) * transform.e
    return np.asarray(x, float), np.asarray(y, float)


def _open_spot(
    g: CoverGround, want_radius_m: float, inset: float, standing: np.ndarray | None = None
) -> tuple[float, float, float]:
    """The open-ground point of the flight area (inset by a share of it) farthest from anything
    standing and from the markers, and the clear radius there (at most ``want_radius_m``).
    ``standing``: the surface whose objects count (default the DSM)."""
    from scipy.ndimage import distance_transform_edt

    taken = ((g.dsm if standing is None else standing) - g.dtm) > 0.05
    for mx, my in g.markers_xy:
        c, r = ~g.transform * (mx, my)
        taken[int(r), int(c)] = True
    clear_m = np.asarray(distance_transform_edt(~taken)) * g.transform.a
    xs, ys = g.centres()
    fx0, fy0, fx1, fy1 = g.flight_box
    inside = (xs > fx0 + inset * (fx1 - fx0)) & (xs < fx1 - inset * (fx1 - fx0))
    inside &= (ys > fy0 + inset * (fy1 - fy0)) & (ys < fy1 - inset * (fy1 - fy0))
    best = int(np.argmax(np.where(inside, clear_m, -1.0)))
    return float(xs.flat[best]), float(ys.flat[best]), min(want_radius_m, float(clear_m.flat[best]) - 1.0)


def _clear_of_markers(
    x: np.ndarray, y: np.ndarray, markers_xy: list[tuple[float, float]], clear_m: float = 1.5
) -> np.ndarray:
    """Cells farther than ``clear_m`` from every marker: no cover may hide a GCP."""
    out = np.ones(x.shape, bool)
    for mx, my in markers_xy:
        out &= np.hypot(x - mx, y - my) > clear_m
    return out


def add_canopy(
    g: CoverGround,
    rng: np.random.Generator,
    style: str = CANOPY_STYLES[0],
    radius_m: float | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, CoverPatch]:
    """A wood of overlapping crowns: the new DSM and object colours, the canopy mask, and where
    (its leaves drawn in ``style``, one of ``CANOPY_STYLES``). ``radius_m``: a wood that wide,
    placed over whatever stands there (default: on the open ground, as wide as it allows)."""
    fx0, fy0, fx1, fy1 = g.flight_box
    if radius_m is None:
        want = 0.15 * min(fx1 - fx0, fy1 - fy0) + 1.5
        cx, cy, radius = _open_spot(g, want, inset=0.3)
        radius = max(radius, 2.0)
    else:  # a wood that wide covers what stands there: only the markers are kept clear
        cx, cy, _ = _open_spot(g, standing=g.dtm, want_radius_m=radius_m, inset=0.35)
        radius = radius_m
    xs, ys = g.centres()
    near = np.hypot(xs - cx, ys - cy) < radius + 4.0
    r0, r1 = np.nonzero(near.any(axis=1))[0][[0, -1]]
    c0, c1 = np.nonzero(near.any(axis=0))[0][[0, -1]]
    win = np.s_[r0 : r1 + 1, c0 : c1 + 1]
    X, Y, ground = xs[win], ys[win], g.dtm[win]
    top = np.zeros_like(ground, dtype=np.float32)
    colour = np.zeros((*ground.shape, 3), np.float32)
    crown_id = np.full(ground.shape, -1, np.int32)
    n_crowns = max(6, int(math.pi * radius**2 / 5.0))  # closed canopy: a crown per 5 m2
    greens = np.array([[0.16, 0.30, 0.11], [0.22, 0.36, 0.13], [0.28, 0.40, 0.16], [0.13, 0.25, 0.12]], np.float32)
    for k in range(n_crowns):
        a, d = rng.uniform(0, 2 * np.pi), radius * math.sqrt(rng.uniform(0, 1))
        tx, ty = cx + d * math.cos(a), cy + d * math.sin(a)
        tr, th = rng.uniform(1.6, 3.2), rng.uniform(7.0, 12.0)
        q = 1.0 - ((X - tx) ** 2 + (Y - ty) ** 2) / tr**2
        dome = np.where(q > 0, th - 2.5 + 2.5 * np.sqrt(np.clip(q, 0, 1)), 0.0)  # a crown 2.5 m deep
        higher = dome > top
        top = np.where(higher, dome, top)
        crown_id = np.where(higher, k, crown_id)
        colour = np.where(higher[..., None], greens[rng.integers(0, len(greens))] * rng.uniform(0.85, 1.15), colour)
    # leaf clumps: a rough crown surface, finer than a crown and coarser than a leaf
    rough = rng.normal(0.0, 0.12, top.shape).astype(np.float32)
    crown = (top > 0.5) & _clear_of_markers(X, Y, g.markers_xy)  # a clearing round a marker
    height = np.where(crown, top + rough, 0.0)
    # the sun on the crowns' slopes (and deep shade where a crown dips under its neighbour)
    gy, gx = np.gradient(height, -g.transform.a, g.transform.a)  # rows run south
    sun_az, sun_el = math.radians(SUN_AZIMUTH_DEG), math.radians(SUN_ELEVATION_DEG)
    sun = np.array([math.sin(sun_az) * math.cos(sun_el), math.cos(sun_az) * math.cos(sun_el), math.sin(sun_el)])
    norm = np.sqrt(gx**2 + gy**2 + 1.0)
    lit = np.clip((-gx * sun[0] - gy * sun[1] + sun[2]) / norm, 0.15, 1.0)
    colour *= (0.35 + 0.75 * lit)[..., None].astype(np.float32)
    new_dsm, new_objects = g.dsm.copy(), g.objects.copy()
    new_dsm[win] = np.where(crown, np.maximum(g.dsm[win], ground + height), g.dsm[win])
    new_objects[win] = np.where(crown[..., None], colour, g.objects[win])
    mask = np.zeros(g.dsm.shape, bool)
    mask[win] = crown
    patch = CoverPatch("canopy", cx, cy, radius, radius, {"crowns": n_crowns, "style": style})
    return new_dsm.astype(np.float32), new_objects, mask, patch


def leaf_texture(style: str, x: np.ndarray, y: np.ndarray, noise: np.ndarray) -> np.ndarray:
    """Brightness of the leaves at world points (about 0.35–1.3): the same texture in every crown.

    ``pattern``: crossed waves of 0.45 and 1.3 m, which repeat exactly; ``blobs``: clumps of the
    noise grid thresholded, dark gaps between bright clumps."""
    if style == "pattern":
        w = np.sin(2 * np.pi * x / 0.45) * np.sin(2 * np.pi * y / 0.45) + 0.6 * np.sin(2 * np.pi * (x + y) / 1.3)
        result: np.ndarray = (0.85 + 0.28 * w).astype(np.float32)
        return result
    n = noise.shape[0]
    fx, fy = np.mod(x / 0.06, n), np.mod(y / 0.06, n)
    v = noise[fy.astype(np.int64) % n, fx.astype(np.int64) % n]
    return np.where(v > 0.15, 1.25, np.where(v < -0.35, 0.35, 0.85)).astype(np.float32)


def add_car_park(
    g: CoverGround,
    rng: np.random.Generator,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, CoverPatch]:
    """Two rows of bays on tarmac, most of them taken by a car with its shadow: the new DSM,
    object colours and ground colours, and where."""
    fx0, fy0, fx1, fy1 = g.flight_box
    want = 0.25 * min(fx1 - fx0, fy1 - fy0) + 3.0
    cx, cy, radius = _open_spot(g, want, inset=0.1)
    radius = max(radius, 3.0)
    rows_of_bays = (-1, 1) if radius > 5.5 else (0,)  # two rows nose to nose, or one
    half_depth = (CAR_LENGTH_M + 0.5) * len(rows_of_bays) / 2
    n_bays = max(2, int(2 * math.sqrt(max(radius**2 - half_depth**2, 1.0)) // BAY_WIDTH_M))
    half_len = n_bays * BAY_WIDTH_M / 2
    angle = rng.uniform(0, np.pi)
    ca, sa = math.cos(angle), math.sin(angle)
    xs, ys = g.centres()
    u = (xs - cx) * ca + (ys - cy) * sa  # along the rows
    v = -(xs - cx) * sa + (ys - cy) * ca  # across them
    tarmac = (np.abs(u) <= half_len + 0.5) & (np.abs(v) <= half_depth + 0.5)
    ground = g.landcover.copy()
    ground[tarmac] = TARMAC_RGB
    bay_line = tarmac & (np.abs(np.mod(u + half_len, BAY_WIDTH_M)) < g.transform.a) & (np.abs(v) > 0.3)
    ground[bay_line] = (0.88, 0.88, 0.84)
    height = np.zeros(g.dsm.shape, np.float32)
    colour = np.zeros_like(g.objects)
    shade = np.zeros(g.dsm.shape, bool)
    reach = CAR_ROOF_M / math.tan(math.radians(SUN_ELEVATION_DEG))
    sx, sy = -reach * math.sin(math.radians(SUN_AZIMUTH_DEG)), -reach * math.cos(math.radians(SUN_AZIMUTH_DEG))
    n_cars = 0
    clear = _clear_of_markers(xs, ys, g.markers_xy)
    for row in rows_of_bays:
        for b in range(n_bays):
            if rng.random() < 0.2:  # an empty bay
                continue
            bu = -half_len + (b + 0.5) * BAY_WIDTH_M + rng.uniform(-0.2, 0.2)
            bv = row * (half_depth / 2 + 0.1) + rng.uniform(-0.2, 0.2)  # (one row: on the middle)
            cu, cv = u - bu, v - bv  # the car's frame: its length across the rows
            body = (np.abs(cv) <= CAR_LENGTH_M / 2) & (np.abs(cu) <= CAR_WIDTH_M / 2)
            if not clear[body].all():  # no car parked on a marker
                continue
            cabin = body & (np.abs(cv + 0.2 * row) <= 0.28 * CAR_LENGTH_M) & (np.abs(cu) <= 0.42 * CAR_WIDTH_M)
            h = np.where(cabin, CAR_ROOF_M, np.where(body, CAR_BODY_M, 0.0)).astype(np.float32)
            height = np.maximum(height, h)
            paint = CAR_COLOURS[rng.integers(0, len(CAR_COLOURS))]
            glass = cabin & (np.abs(cv + 0.2 * row) > 0.18 * CAR_LENGTH_M)  # windscreen and rear window
            colour[body] = paint
            colour[glass] = (0.10, 0.12, 0.15)
            # the shadow: the car's outline moved away from the sun by its height's reach
            su, sv = sx * ca + sy * sa, -sx * sa + sy * ca
            shade |= (np.abs(cv - sv) <= CAR_LENGTH_M / 2) & (np.abs(cu - su) <= CAR_WIDTH_M / 2)
            n_cars += 1
    ground[shade & (height == 0)] *= SHADOW_GAIN
    standing = height > 0
    new_dsm = np.where(standing, np.maximum(g.dsm, g.dtm + height), g.dsm).astype(np.float32)
    new_objects = np.where(standing[..., None], colour, g.objects).astype(np.float32)
    half_w = abs(half_len * ca) + abs(half_depth * sa) + 0.5
    half_h = abs(half_len * sa) + abs(half_depth * ca) + 0.5
    patch = CoverPatch(
        "cars", cx, cy, half_w, half_h, {"cars": n_cars, "bays": 2 * n_bays, "angle_deg": math.degrees(angle)}
    )
    return new_dsm, new_objects, ground.astype(np.float32), patch


#: A hall: a large flat or mono-pitched roof (the seed's parity), its footprint in metres.
HALL_SIZE_M = (40.0, 24.0)
HALL_EAVE_M = 7.0
HALL_PITCH_RISE_M = 1.5
HALL_ROOF_RGB = (0.55, 0.56, 0.58)
#: A hedge line: its crown height, width and length (metres).
HEDGE_M = (1.4, 1.2, 35.0)


def add_hall(
    g: CoverGround,
    rng: np.random.Generator,
    pitched: bool,
    avoid: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, CoverPatch]:
    """A hall wider than any ground filter's window (40 x 24 m, or half the flight area's width):
    a flat roof, or one pitched along its width (``pitched``), over whatever stood there but the
    ``avoid`` cells; the markers are kept clear. The new DSM and object colours, and where."""
    fx0, fy0, fx1, fy1 = g.flight_box
    length = min(HALL_SIZE_M[0], 0.5 * (fx1 - fx0))
    width = min(HALL_SIZE_M[1], 0.5 * (fy1 - fy0))
    # over whatever stands there but the cells to ``avoid`` (a wide wood)
    taken = g.dtm if avoid is None else np.where(avoid, g.dtm + 1.0, g.dtm)
    cx, cy, _ = _open_spot(g, standing=taken, want_radius_m=length / 2, inset=0.2)
    angle = float(rng.uniform(-0.3, 0.3))
    xs, ys = g.centres()
    u = (xs - cx) * math.cos(angle) + (ys - cy) * math.sin(angle)
    v = -(xs - cx) * math.sin(angle) + (ys - cy) * math.cos(angle)
    inside = (np.abs(u) <= length / 2) & (np.abs(v) <= width / 2) & _clear_of_markers(xs, ys, g.markers_xy, 2.5)
    base = float(g.dtm[inside].max()) if inside.any() else float(np.median(g.dtm))
    roof = base + HALL_EAVE_M + (HALL_PITCH_RISE_M * (0.5 + v / width) if pitched else 0.0)
    new_dsm = np.where(inside, roof, g.dsm).astype(np.float32)
    # a roof of panels: seams every 2.5 m give it texture to match
    panel = np.where(np.mod(u, 2.5) < 0.15, 0.8, 1.0)[..., None]
    new_objects = np.where(inside[..., None], np.array(HALL_ROOF_RGB, np.float32) * panel, g.objects)
    detail = {"length_m": length, "width_m": width, "angle_deg": math.degrees(angle), "pitched": pitched}
    half_w = abs(length / 2 * math.cos(angle)) + abs(width / 2 * math.sin(angle))
    half_h = abs(length / 2 * math.sin(angle)) + abs(width / 2 * math.cos(angle))
    return new_dsm, new_objects.astype(np.float32), CoverPatch("hall", cx, cy, half_w, half_h, detail)


def add_hedge(
    g: CoverGround,
    rng: np.random.Generator,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, CoverPatch]:
    """A hedge line across open ground (1.4 m high, 1.2 m wide, 35 m long or the flight area's
    width), its crown rough and leaf-textured: the new DSM, object colours, its canopy mask, and
    where."""
    height, width, length = HEDGE_M
    fx0, fy0, fx1, fy1 = g.flight_box
    length = min(length, 0.7 * (fx1 - fx0))
    cx, cy, _ = _open_spot(g, length / 2, inset=0.25)
    angle = float(rng.uniform(0, np.pi))
    xs, ys = g.centres()
    u = (xs - cx) * math.cos(angle) + (ys - cy) * math.sin(angle)
    v = -(xs - cx) * math.sin(angle) + (ys - cy) * math.cos(angle)
    q = 1.0 - (v / (width / 2)) ** 2
    along = np.clip((length / 2 - np.abs(u)) / 0.6, 0.0, 1.0)  # rounded ends
    top = np.where(q > 0, height * np.sqrt(np.clip(q, 0, 1)) * along, 0.0)
    top = top + np.where(top > 0, rng.normal(0.0, 0.06, top.shape), 0.0)
    crown = (top > 0.2) & _clear_of_markers(xs, ys, g.markers_xy)
    new_dsm = np.where(crown, np.maximum(g.dsm, g.dtm + top), g.dsm).astype(np.float32)
    new_objects = np.where(crown[..., None], np.array([0.18, 0.33, 0.12], np.float32), g.objects)
    detail = {"length_m": length, "angle_deg": math.degrees(angle), "height_m": height}
    half = length / 2 + width
    patch = CoverPatch("hedge", cx, cy, half, half, detail)
    return new_dsm, new_objects.astype(np.float32), crown, patch


#: Stockpiles: a cone's radius at most (m) and its height over its radius (a 27 degree heap); a pit's
#: depth at most.
PILE_RADIUS_M = 6.0
PILE_SLOPE = 0.5
PIT_DEPTH_M = 1.5
GRAVEL_RGB = (0.58, 0.53, 0.46)


def add_stockpiles(
    g: CoverGround,
    rng: np.random.Generator,
    lumpy: bool,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, CoverPatch]:
    """A graded yard on open ground: a cone of gravel, an irregular pile (two heaps run together:
    smooth, or ``lumpy`` with spoil in its flanks) and a pit, each a part of the ground (DSM and DTM
    alike).
    The new DSM, DTM and ground colours, and where, with each one's true volume above (a pile) or
    below (the pit) the ground that was there, summed over the grid's cells."""
    cx, cy, clear = _open_spot(g, 6.2 * PILE_RADIUS_M, inset=0.2)
    # the heap at the spot, the cone to its west and the pit to its south, each one's polygon (its
    # foot and a margin of 0.4 r) clear of the others'
    r = min(PILE_RADIUS_M, clear / 6.2)
    margin = 0.4 * r
    xs, ys = g.centres()
    cell_m2 = abs(g.transform.a * g.transform.e)
    # a yard is graded: its ground a plane (the terrain's own tilt kept, its curvature taken out) out
    # to 5.2 r, past every polygon, met by the terrain by 6.2 r: a pile stands on ground its edge tells
    d = np.hypot(xs - cx, ys - cy)
    yard = d < 6.2 * r
    coef, *_ = np.linalg.lstsq(np.column_stack([np.ones(yard.sum()), xs[yard] - cx, ys[yard] - cy]),
                               g.dtm[yard].astype(np.float64), rcond=None)  # fmt: skip
    plane = coef[0] + coef[1] * (xs - cx) + coef[2] * (ys - cy)
    blend = np.clip((6.2 * r - d) / r, 0.0, 1.0)
    graded = g.dtm + blend * (plane - g.dtm)
    kx, ky = cx - 3.7 * r, cy
    cone = np.clip(PILE_SLOPE * (r - np.hypot(xs - kx, ys - ky)), 0.0, None)
    d1 = ((xs - cx + 0.35 * r) / 1.3) ** 2 + ((ys - cy) / 0.8) ** 2
    d2 = ((xs - cx - 0.45 * r) / 0.9) ** 2 + ((ys - cy - 0.2 * r) / 1.1) ** 2
    s2 = (0.33 * r) ** 2
    heaps = PILE_SLOPE * r * (np.exp(-d1 / (2 * s2)) + 0.7 * np.exp(-d2 / (2 * s2)))
    if lumpy:  # spoil tipped in loads: lumps a quarter of the pile's radius across
        from scipy.ndimage import gaussian_filter

        lumps = gaussian_filter(rng.normal(0.0, 1.0, heaps.shape), sigma=0.25 * r / abs(g.transform.a))
        heaps = heaps * (1.0 + 0.35 * lumps / max(float(np.abs(lumps).max()), 1e-9))
    heaps = np.where((heaps > 0.02 * r) & (np.hypot(xs - cx, ys - cy) < 1.9 * r), heaps, 0.0)  # its foot
    qx, qy = cx, cy - 3.5 * r
    rp = 0.8 * r
    # dug with sides at the piles' slope, at most PIT_DEPTH_M deep (a narrower, steeper pit is one
    # the dense matcher's window smooths: the volume then says less than was dug)
    pit = -np.minimum(PILE_SLOPE * np.clip(rp - np.hypot(xs - qx, ys - qy), 0.0, None), PIT_DEPTH_M)
    clear_xy = _clear_of_markers(xs, ys, g.markers_xy, 2.0)
    delta = np.where(clear_xy, cone + heaps + pit, 0.0)
    new_dtm = (graded + delta).astype(np.float32)
    new_dsm = (g.dsm + (graded - g.dtm) + delta).astype(np.float32)
    grain = 0.85 + 0.3 * rng.random(delta.shape)
    tint = np.where((delta > 0)[..., None], np.array(GRAVEL_RGB, np.float32) * grain[..., None], g.landcover)
    tint = np.where((delta < 0)[..., None], np.array([0.42, 0.33, 0.25], np.float32) * grain[..., None], tint)

    def volume(part: np.ndarray, sign: float) -> float:
        return float(sign * np.sum(np.where(clear_xy, part, 0.0)) * cell_m2)

    items = [
        {"name": "cone", "kind": "pile", "x": kx, "y": ky, "radius_m": r + margin, "volume_m3": volume(cone, 1.0)},
        {"name": "heap", "kind": "pile", "x": cx, "y": cy, "radius_m": 1.9 * r + margin,
         "volume_m3": volume(heaps, 1.0), "lumpy": lumpy},
        {"name": "pit", "kind": "pit", "x": qx, "y": qy, "radius_m": rp + margin, "volume_m3": volume(pit, -1.0)},
    ]  # fmt: skip
    half = 6.2 * r
    patch = CoverPatch("stockpiles", cx, cy, half, half, {"pile_radius_m": r, "items": items})
    return new_dsm, new_dtm, tint.astype(np.float32), patch


#: The second epoch's changes at most (m): a pile's radius, a trench's length, width at the bottom and
#: depth (its sides at the piles' slope: a trench with vertical sides is narrower than the dense
#: matcher's window, which smooths it), a new building's length, width and height.
EPOCH_PILE_RADIUS_M = 4.0
EPOCH_TRENCH_M = (14.0, 2.0, 1.0)
EPOCH_BUILDING_M = (9.0, 6.0, 4.0)
#: The second flight's GPS is off the first's by this much (east, north, up; m): two flights on
#: consumer GPS alone, the normal case between epochs.
EPOCH_GPS_OFFSET_M = (1.6, -1.2, 0.5)
EPOCH_ROOF_RGB = (0.66, 0.36, 0.28)


def add_second_epoch(
    g: CoverGround, rng: np.random.Generator, stockpiles: dict[str, Any] | None
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, CoverPatch]:
    """The site as a second flight finds it: a pile moved (the stockpiles' cone, where the yard has
    one, else a new pile), a trench dug and a new building, each on open ground and clear of the
    markers. The new DSM, DTM, object and ground colours, and each change with its true volume
    (positive: added; negative: removed), summed over the grid's cells."""
    xs, ys = g.centres()
    cell_m2 = abs(g.transform.a * g.transform.e)
    clear_xy = _clear_of_markers(xs, ys, g.markers_xy, 2.0)
    dsm, dtm = g.dsm.astype(np.float64), g.dtm.astype(np.float64)
    objects, landcover = g.objects.copy(), g.landcover.copy()
    changed = np.zeros(dsm.shape, bool)
    items: list[dict[str, Any]] = []

    def spot(radius_m: float) -> tuple[float, float, float]:
        # open ground away from what stands and from the changes made already
        return _open_spot(replace(g, dsm=np.where(changed, dtm + 1.0, dsm)), radius_m, inset=0.15)

    def volume(delta: np.ndarray) -> float:
        return float(np.sum(np.where(clear_xy, delta, 0.0)) * cell_m2)

    def ground(delta: np.ndarray, rgb: tuple[float, float, float]) -> None:
        nonlocal dsm, dtm, landcover
        delta = np.where(clear_xy, delta, 0.0)
        dsm, dtm = dsm + delta, dtm + delta
        grain = 0.85 + 0.3 * rng.random(delta.shape)
        landcover = np.where((delta != 0)[..., None], np.array(rgb, np.float32) * grain[..., None], landcover)
        changed[delta != 0] = True

    if stockpiles:  # the yard's cone carted off (the ground it stood on is the yard's plane)
        cone_item = next(i for i in stockpiles["items"] if i["name"] == "cone")
        r0 = float(stockpiles["pile_radius_m"])
        old = np.clip(PILE_SLOPE * (r0 - np.hypot(xs - cone_item["x"], ys - cone_item["y"])), 0.0, None)
        ground(-old, (0.45, 0.40, 0.33))
        items.append({"name": "cone removed", "kind": "cut", "x": cone_item["x"], "y": cone_item["y"],
                      "radius_m": r0 * 1.4, "volume_m3": -volume(old)})  # fmt: skip
    px, py, clear = spot(2.5 * EPOCH_PILE_RADIUS_M)
    r = max(1.5, min(EPOCH_PILE_RADIUS_M, clear / 2.5))
    pile = np.clip(PILE_SLOPE * (r - np.hypot(xs - px, ys - py)), 0.0, None)
    ground(pile, GRAVEL_RGB)
    items.append({"name": "pile moved here" if stockpiles else "pile", "kind": "fill", "x": px, "y": py,
                  "radius_m": r * 1.4, "volume_m3": volume(pile)})  # fmt: skip
    length, width, depth = EPOCH_TRENCH_M
    tx, ty, clear = spot(0.6 * length)
    length = max(4.0, min(length, 2.0 * clear - 2.0))
    angle = float(rng.uniform(0, np.pi))
    u = (xs - tx) * math.cos(angle) + (ys - ty) * math.sin(angle)
    v = -(xs - tx) * math.sin(angle) + (ys - ty) * math.cos(angle)
    # a floor ``width`` across, its sides rising at the piles' slope to the ground
    beyond = np.maximum(np.abs(v) - width / 2, 0.0) + np.maximum(np.abs(u) - length / 2, 0.0)
    trench = -np.clip(depth - PILE_SLOPE * beyond, 0.0, depth)
    ground(trench, (0.42, 0.33, 0.25))
    reach = width / 2 + depth / PILE_SLOPE
    items.append({"name": "trench", "kind": "cut", "x": tx, "y": ty, "radius_m": length / 2 + reach + 0.5,
                  "volume_m3": volume(trench)})  # fmt: skip
    bl, bw, bh = EPOCH_BUILDING_M
    bx, by, clear = spot(0.7 * bl)
    bl = max(4.0, min(bl, 1.4 * clear - 1.0))
    bw = min(bw, bl)
    ba = float(rng.uniform(0, np.pi))
    u = (xs - bx) * math.cos(ba) + (ys - by) * math.sin(ba)
    v = -(xs - bx) * math.sin(ba) + (ys - by) * math.cos(ba)
    inside = (np.abs(u) <= bl / 2) & (np.abs(v) <= bw / 2) & clear_xy
    roof = float(dtm[inside].max()) + bh if inside.any() else float(np.median(dtm)) + bh
    added = np.where(inside, roof - dsm, 0.0)
    dsm = dsm + added
    objects = np.where(inside[..., None], np.array(EPOCH_ROOF_RGB, np.float32), objects)
    items.append({"name": "new building", "kind": "fill", "x": bx, "y": by, "radius_m": math.hypot(bl, bw) / 2 + 1.0,
                  "volume_m3": float(np.sum(added) * cell_m2)})  # fmt: skip
    detail = {"gps_offset_m": list(EPOCH_GPS_OFFSET_M), "items": items}
    fx0, fy0, fx1, fy1 = g.flight_box
    patch = CoverPatch("second_epoch", (fx0 + fx1) / 2, (fy0 + fy1) / 2, (fx1 - fx0) / 2, (fy1 - fy0) / 2, detail)
    return (dsm.astype(np.float32), dtm.astype(np.float32), objects.astype(np.float32),
            landcover.astype(np.float32), patch)  # fmt: skip
