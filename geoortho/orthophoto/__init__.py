"""Orthophoto mosaic: rectify on the DSM, seamlines, colour balance, blending, hole fill, COG.

Cameras placed from the photo metadata alone (direct georeferencing) are
:func:`geoortho.photos.footprint.photo_cameras`'s; an ``sfm`` output is read by
:mod:`geoortho.core.sfm_model`."""

from geoortho.orthophoto.mosaic import MosaicOptions, OrthoResult, mosaic, ortho

__all__ = ["MosaicOptions", "OrthoResult", "mosaic", "ortho"]
