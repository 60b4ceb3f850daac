"""Cameras and their sensors, in one place: the makers' published specifications (what a flight
plan needs: sensor size, focal length, image size), the sensor widths of DJI and survey payloads
read by EXIF model, and OpenSfM's public table of 3,709 cameras (geoortho/data) behind them."""

from __future__ import annotations

import functools
import math
from pathlib import Path

__all__ = ["CAMERA_SPECS", "SENSOR_WIDTHS_MM", "opensfm_sensor_table", "sensor_width_from_table"]

# Published maker specifications: sensor width x height (mm), focal length (mm), image (px).
# The names are what surveyors call them; the second is the EXIF Model the camera writes.
CAMERA_SPECS: tuple[tuple[str, str, float, float, float, int, int], ...] = (
    ("DJI Phantom 4 Pro", "FC6310", 13.2, 8.8, 8.8, 5472, 3648),
    ("DJI Phantom 4 RTK", "FC6310R", 13.2, 8.8, 8.8, 5472, 3648),
    ("DJI Phantom 4", "FC330", 6.17, 4.55, 3.61, 4000, 3000),
    ("DJI Phantom 3 Professional", "FC300X", 6.17, 4.55, 3.61, 4000, 3000),
    ("DJI Mavic Pro", "FC220", 6.17, 4.55, 4.73, 4000, 3000),
    ("DJI Mavic 2 Pro", "L1D-20c", 13.2, 8.8, 10.26, 5472, 3648),
    ("DJI Mavic 3 Enterprise", "M3E", 17.3, 13.0, 12.29, 5280, 3956),
    ("DJI Air 2S", "FC3411", 13.2, 8.8, 8.38, 5472, 3648),
    ("DJI Mini 3 Pro", "FC3582", 9.7, 7.3, 6.72, 4032, 3024),
    ("DJI Mini 4 Pro", "FC8482", 9.7, 7.3, 6.72, 4032, 3024),
    ("DJI Zenmuse P1 35mm", "ZenmuseP1", 35.9, 24.0, 35.0, 8192, 5460),
    ("senseFly S.O.D.A.", "SODA", 13.2, 8.8, 10.6, 5472, 3648),
    ("Sony RX1R II (WingtraOne)", "DSC-RX1RM2", 35.9, 24.0, 35.0, 7952, 5304),
)

# Sensor width (mm) by EXIF Model, lower case: DJI and survey payloads, looked up before
# OpenSfM's table of 3,709 cameras (geoortho/data). Published sensor sizes; the width spans
# the full image width, also for 16:9 crops of a 4:3 sensor.
_WIDTHS_ONLY_MM: dict[str, float] = {
    # Phantom 3 / 4 family, Inspire 1
    "fc300s": 6.17,
    "fc300c": 6.17,
    "fc300se": 6.17,
    "fc350": 6.17,
    "fc6310s": 13.2,
    "fc6360": 4.87,
    # Mavic / Air / Mini family
    "fc2103": 6.17,
    "fc2204": 6.17,
    "fc3170": 6.4,
    "fc7203": 6.17,
    "fc7303": 6.17,
    "fc3682": 9.7,
    "fc4170": 17.3,
    "l2d-20c": 17.3,
    "fc3682s": 9.7,
    # Enterprise: Mavic 3E/3T, M30, Matrice 4E, Phantom 4 RTK
    "m3t": 6.4,
    "m3m": 17.3,
    "m30": 6.4,
    "m30t": 6.4,
    "m4e": 17.3,
    "m4t": 9.7,
    "fc6310r_rtk": 13.2,
    # Zenmuse
    "zenmusel1": 13.2,
    "zenmusel2": 17.3,
    "fc6510": 13.2,
    "fc6520": 17.3,
    "fc6540": 23.5,
    "fc550": 17.3,
    "fc550raw": 17.3,
    "zenmuseh20": 7.6,
    "zenmuseh20t": 7.6,
    # Fixed-wing survey payloads missing from OpenSfM's table (EXIF Model as Sony writes it)
    "ilce-7rm4": 35.7,  # WingtraOne / eBee X A7R IV
    "ilce-7rm4a": 35.7,
    "ilce-7rm5": 35.7,
    "rededge-m": 4.8,  # MicaSense, 1280 px × 3.75 µm
}

#: Sensor width (mm) by EXIF model (lower case, no spaces): the specifications' first, then the
#: widths known without the rest of a specification.
SENSOR_WIDTHS_MM: dict[str, float] = {
    **{model.lower().replace(" ", ""): width for _, model, width, *_ in CAMERA_SPECS},
    **_WIDTHS_ONLY_MM,
}


@functools.lru_cache(maxsize=1)
def opensfm_sensor_table() -> dict[str, float]:
    """OpenSfM's public table (3,709 cameras, "MAKE MODEL" → width mm; geoortho/data/README.md),
    keyed in lower case with single spaces."""
    import json

    raw = json.loads((Path(__file__).parents[1] / "data" / "sensor_data.json").read_text())
    return {" ".join(k.lower().split()): float(v) for k, v in raw.items() if float(v) > 0}


def sensor_width_from_table(make: str, model: str) -> float:
    """Sensor width (mm) of a camera by its EXIF Make and Model: geoortho's DJI table (by model),
    then OpenSfM's by "make model" (also the make's first word: "NIKON CORPORATION" → "nikon",
    and the model alone where it already names the make); NaN when unknown."""
    key = model.lower().replace(" ", "")
    if key in SENSOR_WIDTHS_MM:
        return SENSOR_WIDTHS_MM[key]
    table = opensfm_sensor_table()
    mk, md = " ".join(make.lower().split()), " ".join(model.lower().split())
    if not md:
        return math.nan
    for k in (f"{mk} {md}", f"{mk.split()[0]} {md}" if mk else "", md):
        if k and k in table:
            return table[k]
    return math.nan
