"""Coded ground markers: OpenCV's predefined ArUco and AprilTag dictionaries."""

from __future__ import annotations

from functools import cache

import cv2
import numpy as np

from .errors import InputError

__all__ = ["DICTIONARIES", "get_dictionary", "marker_cells"]

#: Every predefined dictionary OpenCV offers, by its usual name (``DICT_4X4_50`` …).
DICTIONARIES: tuple[str, ...] = tuple(
    sorted(n for n in dir(cv2.aruco) if n.startswith("DICT_") and n == n.upper())
)


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
