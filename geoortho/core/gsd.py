"""Ground sampling distance and focal length in pixels: the one place for their formulas.

Metres throughout (centimetres only in the ``*_cm`` fields users read). Each formula keeps the
order of its operations as its callers had it, so that moving it here changed no result by a bit.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["depth_gsd_m", "focal_length_px", "gsd_at_height_m", "height_for_gsd_m", "marker_gsd_m", "ray_gsd_m"]


def focal_length_px(focal_mm: float, sensor_width_mm: float, width_px: float) -> float:
    """The focal length in pixels of a sensor ``sensor_width_mm`` wide imaged on ``width_px``
    pixels (the long side: a portrait photo's height)."""
    return focal_mm / sensor_width_mm * width_px


def depth_gsd_m(depth_m: float, focal_px: float) -> float:
    """A pixel's side on a surface square to the ray at ``depth_m`` along the optical axis."""
    return depth_m / focal_px


def ray_gsd_m(
    range_m: np.ndarray, cos_off_axis: np.ndarray, cos_incidence: np.ndarray, focal: np.ndarray
) -> np.ndarray:
    """The side of the ground area a pixel covers, locally level ground: range · sqrt(cos³θ / cos i) / f,
    θ the ray's angle off the optical axis, i its incidence on the ground (the footprints' slant form)."""
    gsd: np.ndarray = range_m * np.sqrt(cos_off_axis**3 / cos_incidence) / focal
    return gsd


def marker_gsd_m(depth_m: np.ndarray, focal_px: float | np.ndarray, above_m: np.ndarray) -> np.ndarray:
    """A pixel's size on the horizontal plane of a flat target ``above_m`` below the camera at
    ``depth_m`` along its axis: sqrt(depth³ / (f² · height)), the geometric mean of the two
    directions (constant across a nadir photo, growing with obliquity; behind the camera, 0)."""
    gsd: np.ndarray = depth_m / focal_px * np.sqrt(np.maximum(depth_m, 0) / above_m)
    return gsd


def height_for_gsd_m(gsd_m: float, focal_px: float, tilt_rad: float) -> float:
    """Height above the ground giving ``gsd_m`` at the centre of a photo tilted ``tilt_rad`` off
    nadir (slant range r = gsd · f · sqrt(cos i)): the inverse of :func:`gsd_at_height_m`."""
    return gsd_m * focal_px * math.sqrt(math.cos(tilt_rad)) * math.cos(tilt_rad)


def gsd_at_height_m(height_m: float, focal_px: float, tilt_rad: float) -> float:
    """The GSD at the centre of a photo tilted ``tilt_rad`` off nadir from ``height_m`` above the ground."""
    return height_m / (focal_px * math.sqrt(math.cos(tilt_rad)) * math.cos(tilt_rad))
