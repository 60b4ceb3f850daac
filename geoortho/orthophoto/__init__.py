"""Orthophoto mosaic: rectify on the DSM, seamlines, colour balance, blending, hole fill, COG."""

from .cameras import OrthoCamera, cameras_from_metadata, cameras_from_sfm
from .mosaic import MosaicOptions, OrthoResult, mosaic, ortho

__all__ = [
    "MosaicOptions",
    "OrthoCamera",
    "OrthoResult",
    "cameras_from_metadata",
    "cameras_from_sfm",
    "mosaic",
    "ortho",
]
