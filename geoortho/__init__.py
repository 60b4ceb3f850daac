"""geoortho: drone photos to survey products, georeference first.

The public API is the plain core functions, re-exported here lazily so that
``import geoortho`` stays cheap (OpenCV, pycolmap and GDAL load on first use).
"""

from __future__ import annotations

import importlib
import logging
from typing import Any

__version__ = "0.1.0"

logging.getLogger(__name__).addHandler(logging.NullHandler())

# name -> module that defines it
_EXPORTS = {
    "synth": "geoortho.synth",
    "demo": "geoortho.demo",
    "run_algorithm": "geoortho.processing.registry",
    "footprints": "geoortho.footprint",
    "read_photos": "geoortho.photos",
    "read_photo": "geoortho.photos",
    "GeoorthoError": "geoortho.errors",
    "InputError": "geoortho.errors",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str) -> Any:
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'geoortho' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value
