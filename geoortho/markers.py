"""Coded ground markers: OpenCV's predefined ArUco and AprilTag dictionaries."""

from __future__ import annotations

from functools import cache
from typing import Literal, get_args

import cv2
import numpy as np

from .errors import InputError

__all__ = ["DICTIONARIES", "get_dictionary", "marker_cells"]

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
