"""Orthophoto mosaic: rectify on the DSM, seamlines, colour balance, blending, hole fill, COG."""

from geoortho.orthophoto.cameras import cameras_from_metadata
from geoortho.orthophoto.mosaic import MosaicOptions, OrthoResult, mosaic, ortho

__all__ = ["MosaicOptions", "OrthoResult", "cameras_from_metadata", "mosaic", "ortho"]
