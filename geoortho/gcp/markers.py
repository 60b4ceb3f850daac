"""Coded ground markers: OpenCV's predefined ArUco and AprilTag dictionaries."""

from __future__ import annotations

import math
from functools import cache
from typing import Literal, get_args

import cv2
import numpy as np

from geoortho.errors import InputError

__all__ = [
    "DICTIONARIES",
    "TARGETS",
    "coded_cells_at",
    "get_dictionary",
    "marker_cells",
    "target_half_extent",
    "target_reflectance",
]

#: Every predefined dictionary OpenCV offers, by its usual name (a test checks it against cv2.aruco).
Dictionary = Literal[
    "DICT_4X4_100",
    "DICT_4X4_1000",
    "DICT_4X4_250",
    "DICT_4X4_50",
    "DICT_5X5_100",
    "DICT_5X5_1000",
    "DICT_5X5_250",
    "DICT_5X5_50",
    "DICT_6X6_100",
    "DICT_6X6_1000",
    "DICT_6X6_250",
    "DICT_6X6_50",
    "DICT_7X7_100",
    "DICT_7X7_1000",
    "DICT_7X7_250",
    "DICT_7X7_50",
    "DICT_APRILTAG_16H5",
    "DICT_APRILTAG_25H9",
    "DICT_APRILTAG_36H10",
    "DICT_APRILTAG_36H11",
    "DICT_ARUCO_MIP_36H12",
    "DICT_ARUCO_ORIGINAL",
]
DICTIONARIES: tuple[str, ...] = get_args(Dictionary)


@cache
def get_dictionary(name: str) -> cv2.aruco.Dictionary:
    """OpenCV dictionary by name (case-insensitive, ``DICT_`` prefix optional)."""
    key = name.strip().upper()
    if not key.startswith("DICT_"):
        key = "DICT_" + key
    if key not in DICTIONARIES:
        raise InputError(f"unknown marker dictionary {name!r}; choose one of {', '.join(DICTIONARIES)}")
    return cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, key))


def marker_cells(name: str, marker_id: int) -> np.ndarray:
    """The marker's cells including its black border, as a bool array (True = white).

    A 4×4 marker gives a 6×6 array.
    """
    d = get_dictionary(name)
    if not 0 <= marker_id < d.bytesList.shape[0]:
        raise InputError(f"marker id {marker_id} is not in {name} (0..{d.bytesList.shape[0] - 1})")
    side = d.markerSize + 2
    img = cv2.aruco.generateImageMarker(d, int(marker_id), side, borderBits=1)
    return img > 127


#: What is on the ground at a GCP. ``aruco``/``apriltag``: a coded marker of the dictionary; the
#: others carry no id and are told apart by where they are predicted.
Target = Literal["aruco", "apriltag", "checkerboard", "cross", "circle"]
TARGETS: tuple[str, ...] = get_args(Target)
#: What gcp-find looks for: a target type, or ``auto`` (each tried on the first photos, the one found most kept).
FindTarget = Literal["aruco", "apriltag", "checkerboard", "cross", "circle", "auto"]
CODED = ("aruco", "apriltag")

#: Width of a cross target's bars, as a share of its span (the fit frees it within 0.08–0.45).
CROSS_BAR = 0.2
#: A circle target: a black disc of diameter ``side`` on a white board this many sides wide.
CIRCLE_BOARD = 1.5


def target_half_extent(kind: str, cells: np.ndarray | int | None = None) -> float:
    """Half the side of the square the target occupies, in marker sides (the board with its quiet zone).

    ``cells``: a coded marker's cells (or their count across, border included; 6 when not given)."""
    if kind in CODED:
        n = 6 if cells is None else cells if isinstance(cells, int) else cells.shape[0]
        return 0.5 + 1.0 / n
    if kind == "circle":
        return CIRCLE_BOARD / 2
    return 0.5


def coded_cells_at(u: np.ndarray, v: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Where marker-frame points fall on a coded marker of ``n`` cells across (border included):
    on its board (quiet zone included), on a cell, and that cell's row-major index (0 off the cells)."""
    half = target_half_extent("aruco", n)
    board = (np.abs(u) <= half) & (np.abs(v) <= half)
    ci = np.floor((u + 0.5) * n).astype(int)
    ri = np.floor((0.5 - v) * n).astype(int)
    inside = board & (ci >= 0) & (ci < n) & (ri >= 0) & (ri < n)
    return board, inside, np.where(inside, ri * n + ci, 0)


def target_reflectance(
    kind: str, u: np.ndarray, v: np.ndarray, cells: np.ndarray | None = None, bar: float = CROSS_BAR
) -> np.ndarray:
    """Reflectance (0 black … 1 white) of a target at marker-frame points, NaN where the ground shows.

    ``u`` to the target's right and ``v`` to its top, in marker sides from its centre. Coded
    markers: the black square of ``cells`` (True = white, border included) in a one-cell white quiet
    zone. Checkerboard: 2 × 2 squares, black top-left. Cross: white bars ``bar`` wide and one side
    long, painted on the ground. Circle: a black disc one side across on a white board.
    """
    u = np.asarray(u, float)
    v = np.asarray(v, float)
    out = np.full(np.broadcast(u, v).shape, np.nan)
    half = target_half_extent(kind, cells)
    if kind in CODED:
        if cells is None:
            raise ValueError("a coded marker needs its cells")
        board, inside, index = coded_cells_at(u, v, cells.shape[0])
        out[board] = 1.0
        out[inside] = np.where(cells.ravel()[index[inside]], 1.0, 0.0)
    elif kind == "checkerboard":
        board = (np.abs(u) <= 0.5) & (np.abs(v) <= 0.5)
        out[board] = ((u[board] >= 0) == (v[board] >= 0)).astype(float)
    elif kind == "cross":
        span = (np.abs(u) <= 0.5) & (np.abs(v) <= 0.5)
        bars = span & ((np.abs(u) <= bar / 2) | (np.abs(v) <= bar / 2))
        out[bars] = 1.0
    elif kind == "circle":
        board = (np.abs(u) <= half) & (np.abs(v) <= half)
        out[board] = np.where(u[board] ** 2 + v[board] ** 2 <= 0.25, 0.0, 1.0)
    else:
        raise InputError(f"unknown target {kind!r}; choose one of {', '.join(TARGETS)}")
    return out


def paint_target(
    img: np.ndarray,
    kind: str,
    cx: float,
    cy: float,
    A: np.ndarray,
    cells: np.ndarray | None,
    white: float,
    black: float,
) -> None:
    """Paint a target into a float image in place, 8 × 8 samples a pixel (tests and calibration).

    ``(cx, cy)``: its centre (pixel-centre convention); ``A``: marker frame (u right, v up, in
    sides) → pixel offsets; ``white``/``black``: grey levels. The ground shows where it does."""
    reach = int(math.ceil(np.abs(A).sum(axis=1).max() * target_half_extent(kind, cells) + 2))
    x0, x1 = max(0, int(cx) - reach), min(img.shape[1], int(cx) + reach + 2)
    y0, y1 = max(0, int(cy) - reach), min(img.shape[0], int(cy) + reach + 2)
    ys, xs = np.mgrid[y0:y1, x0:x1]
    sub = (np.arange(8) + 0.5) / 8 - 0.5
    sx, sy = np.meshgrid(sub, sub)
    px = xs.ravel()[:, None] + sx.ravel()[None] - cx
    py = ys.ravel()[:, None] + sy.ravel()[None] - cy
    inv = np.linalg.inv(A)
    u, v = inv[0, 0] * px + inv[0, 1] * py, inv[1, 0] * px + inv[1, 1] * py
    r = target_reflectance(kind, u, v, cells)
    bg = img[y0:y1, x0:x1].reshape(-1, 1)
    val = np.where(np.isnan(r), bg, black + (white - black) * np.nan_to_num(r))
    img[y0:y1, x0:x1] = val.mean(axis=1).reshape(ys.shape)
