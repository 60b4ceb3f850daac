"""Ground control: coordinate files, where each GCP is in each photo, marker detection.

The coordinate files' names are re-exported lazily: a detection worker imports this package for
its detector and model fits only, and the files' reader brings pyproj (a seventh of a second at
a worker's start, which the first photos wait for).
"""

from __future__ import annotations

import importlib
from typing import Any

__all__ = ["GcpSet", "GroundControlPoint", "marker_id_of", "read_gcp_file"]


def __getattr__(name: str) -> Any:
    if name not in __all__:
        raise AttributeError(f"module 'geoortho.gcp' has no attribute {name!r}")
    value = getattr(importlib.import_module("geoortho.gcp.io"), name)
    globals()[name] = value
    return value
