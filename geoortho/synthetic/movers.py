"""Moving cars and people for ``synth`` (the ``moving-cars`` pathology, issue 75).

Each mover drives (or walks) to and fro along a straight track on open ground while the drone
flies: a photo shows it where it was at that photo's exposure, so overlapping photos disagree
where it went. The scene's truth (DSM, orthophoto) is the static scene without them: a true
orthophoto may show a mover once, whole, or not at all; never a ghost or half of one.

A mover is drawn on the rendered photo as a box (its silhouette from the camera: the convex hull
of its eight corners, the sides shaded) under its lit top, drawn one of two ways by the seed's
parity: a car with a darker windscreen band (even), or a plain box with a light roof stripe
(odd). People are boxes 0.5 m across and 1.7 m tall walking at 1.4 m/s.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any

import cv2
import numpy as np

from geoortho.core.camera import Intrinsics, Pose, project_points

__all__ = ["Mover", "draw_movers", "place_movers"]

#: Cars and people per survey, their sizes (length, width, height, m) and speeds (m/s).
N_CARS, N_PEOPLE = 4, 2
CAR_SIZE_M, CAR_SPEED_MPS = (4.4, 1.8, 1.45), 4.0
PERSON_SIZE_M, PERSON_SPEED_MPS = (0.5, 0.5, 1.7), 1.4
#: A car's track is this long (m) and clear of anything standing by this much either side; a
#: person's is shorter and closer.
TRACK_M, CLEARANCE_M = 30.0, 3.0
PERSON_TRACK_M, PERSON_CLEARANCE_M = 12.0, 1.5
MOVER_COLOURS = ((0.85, 0.12, 0.10), (0.10, 0.25, 0.80), (0.93, 0.93, 0.90), (0.95, 0.75, 0.10), (0.15, 0.60, 0.75))


@dataclass(frozen=True)
class Mover:
    """One car or person: its track (x0, y0 to x0 + TRACK along heading), speed and look."""

    kind: str  # "car" or "person"
    x0: float
    y0: float
    z0: float  # the ground under the track's start (m; the track is on open, gently sloping ground)
    heading_deg: float  # of the track, clockwise from north
    track_m: float
    speed_mps: float
    phase_m: float  # where along the to-and-fro it is at time 0
    length_m: float
    width_m: float
    height_m: float
    colour: tuple[float, float, float]
    style: str  # "car" (windscreen band) or "box" (roof stripe)

    def where(self, t_s: float, ground: Any) -> tuple[float, float, float, float]:
        """Centre (x, y), ground height under it and heading (deg) at ``t_s`` seconds."""
        period = 2.0 * self.track_m
        s = (self.phase_m + self.speed_mps * t_s) % period
        along, back = (s, False) if s <= self.track_m else (period - s, True)
        h = math.radians(self.heading_deg)
        x, y = self.x0 + along * math.sin(h), self.y0 + along * math.cos(h)
        z = float(ground(np.array([x]), np.array([y]))[0])
        return x, y, z, (self.heading_deg + (180.0 if back else 0.0)) % 360.0

    def record(self) -> dict[str, Any]:
        return asdict(self)


def place_movers(
    dsm: np.ndarray,
    dtm: np.ndarray,
    transform: Any,
    flight_box: tuple[float, float, float, float],
    markers_xy: list[tuple[float, float]],
    rng: np.random.Generator,
    style: str,
) -> list[Mover]:
    """Tracks on open ground inside the flight area, clear of anything standing, of the markers
    and of each other; as many of N_CARS and N_PEOPLE as fit."""
    from scipy.ndimage import distance_transform_edt

    taken = (dsm - dtm) > 0.05
    for mx, my in markers_xy:
        c, r = ~transform * (mx, my)
        if 0 <= int(r) < taken.shape[0] and 0 <= int(c) < taken.shape[1]:
            taken[int(r), int(c)] = True
    clear_m = np.asarray(distance_transform_edt(~taken)) * transform.a
    fx0, fy0, fx1, fy1 = flight_box
    movers: list[Mover] = []
    kinds = ["car"] * N_CARS + ["person"] * N_PEOPLE
    for i, kind in enumerate(kinds):
        size, speed = (CAR_SIZE_M, CAR_SPEED_MPS) if kind == "car" else (PERSON_SIZE_M, PERSON_SPEED_MPS)
        track_m, clearance_m = (TRACK_M, CLEARANCE_M) if kind == "car" else (PERSON_TRACK_M, PERSON_CLEARANCE_M)
        for _try in range(200):
            heading = float(rng.uniform(0.0, 360.0))
            h = math.radians(heading)
            x0 = float(rng.uniform(fx0 + 5.0, fx1 - 5.0))
            y0 = float(rng.uniform(fy0 + 5.0, fy1 - 5.0))
            s = np.linspace(0.0, track_m, 31)
            xs, ys = x0 + s * math.sin(h), y0 + s * math.cos(h)
            if not ((xs > fx0 + 3) & (xs < fx1 - 3) & (ys > fy0 + 3) & (ys < fy1 - 3)).all():
                continue
            cols, rows = ~transform * (xs, ys)
            ci, ri = np.asarray(cols, int), np.asarray(rows, int)
            if (ci < 0).any() or (ri < 0).any() or (ci >= dsm.shape[1]).any() or (ri >= dsm.shape[0]).any():
                continue
            if (clear_m[ri, ci] < clearance_m).any():
                continue
            if any(_tracks_within(m, xs, ys, CLEARANCE_M + clearance_m) for m in movers):
                continue
            movers.append(
                Mover(
                    kind=kind,
                    x0=x0,
                    y0=y0,
                    z0=float(dtm[ri[0], ci[0]]),
                    heading_deg=heading,
                    track_m=track_m,
                    speed_mps=speed,
                    phase_m=float(rng.uniform(0.0, 2.0 * track_m)),
                    length_m=size[0],
                    width_m=size[1],
                    height_m=size[2],
                    colour=MOVER_COLOURS[i % len(MOVER_COLOURS)],
                    style=style,
                )  # fmt: skip
            )
            break
    return movers


def _tracks_within(m: Mover, xs: np.ndarray, ys: np.ndarray, gap_m: float) -> bool:
    h = math.radians(m.heading_deg)
    s = np.linspace(0.0, m.track_m, 31)
    mx, my = m.x0 + s * math.sin(h), m.y0 + s * math.cos(h)
    d = np.hypot(xs[:, None] - mx[None, :], ys[:, None] - my[None, :])
    return bool(d.min() < gap_m)


def _box(x: float, y: float, z: float, heading_deg: float, size: tuple[float, float, float]) -> np.ndarray:
    """The box's 8 corners (bottom 4, then top 4), world metres."""
    length, width, height = size
    h = math.radians(heading_deg)
    fwd, side = np.array([math.sin(h), math.cos(h)]), np.array([math.cos(h), -math.sin(h)])
    signs = ((1, 1), (1, -1), (-1, -1), (-1, 1))  # front left, front right, back right, back left
    base = [np.array([x, y]) + a * fwd * length / 2 + b * side * width / 2 for a, b in signs]
    return np.array([[*p, z] for p in base] + [[*p, z + height] for p in base])


def draw_movers(
    img: np.ndarray, movers: list[Mover], t_s: float, intr: Intrinsics, pose: Pose, ground: Any, depth: np.ndarray
) -> None:
    """Draw each mover where it is at ``t_s`` on ``img`` (H, W, 3 float 0..1, changed in place),
    nearest last; hidden where the scene's own surface (``depth``: H x W, distance along the
    camera's axis of each pixel's hit, NaN none) lies in front of it."""
    h_px, w_px = img.shape[:2]
    placed = []
    for m in movers:
        x, y, z, heading = m.where(t_s, ground)
        corners = _box(x, y, z, heading, (m.length_m, m.width_m, m.height_m))
        pix, d = project_points(corners, intr, pose)
        if not np.isfinite(pix).all() or (d <= 0).any():
            continue
        placed.append((float(d.mean()), m, corners, pix, d))
    for _, m, _corners, pix, d in sorted(placed, key=lambda p: -p[0]):
        lo, hi = np.floor(pix.min(axis=0)).astype(int), np.ceil(pix.max(axis=0)).astype(int)
        if hi[0] < 0 or hi[1] < 0 or lo[0] >= w_px or lo[1] >= h_px:
            continue
        x0, y0 = max(lo[0], 0), max(lo[1], 0)
        x1, y1 = min(hi[0] + 1, w_px), min(hi[1] + 1, h_px)
        mask = np.zeros((y1 - y0, x1 - x0), np.uint8)
        hull = cv2.convexHull((pix - [x0, y0]).astype(np.float32)).astype(np.int32)
        cv2.fillConvexPoly(mask, hull, 1, lineType=cv2.LINE_8)
        top = np.zeros_like(mask)
        cv2.fillConvexPoly(top, np.round(pix[4:] - [x0, y0]).astype(np.int32), 1, lineType=cv2.LINE_8)
        colour = np.asarray(m.colour, np.float32)
        patch = np.where(mask[..., None] > 0, colour * 0.55, 0.0)  # the sides, in shade
        patch = np.where(top[..., None] > 0, colour, patch)
        # its look: a windscreen band across the front of a car's top, or a light stripe along a box's
        band = np.zeros_like(mask)
        a, b, c_, d_ = pix[4], pix[5], pix[6], pix[7]
        if m.style == "car":
            near_front = np.array([a, b, b + 0.3 * (c_ - b), a + 0.3 * (d_ - a)])
            cv2.fillConvexPoly(band, np.round(near_front - [x0, y0]).astype(np.int32), 1)
            patch = np.where((band[..., None] > 0) & (top[..., None] > 0), np.float32(0.12), patch)
        else:
            stripe = np.array([a + (b - a) / 3, a + 2 * (b - a) / 3, d_ + 2 * (c_ - d_) / 3, d_ + (c_ - d_) / 3])
            cv2.fillConvexPoly(band, np.round(stripe - [x0, y0]).astype(np.int32), 1)
            patch = np.where((band[..., None] > 0) & (top[..., None] > 0), np.float32(0.95), patch)
        # hidden behind what stands nearer the camera (a tree's crown over the road)
        behind = depth[y0:y1, x0:x1] < float(d.min()) - 0.5
        show = (mask > 0) & ~np.nan_to_num(behind, nan=False).astype(bool)
        view = img[y0:y1, x0:x1]
        view[show] = patch[show]
