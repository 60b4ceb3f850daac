"""geoortho: drone photos to survey products, georeference first.

The public API is the plain core functions, re-exported here lazily so that
``import geoortho`` stays cheap (OpenCV, pycolmap and GDAL load on first use).
"""

from __future__ import annotations

import importlib
import logging
from typing import Any

from geoortho.version import __version__ as __version__  # the package's own attribute

logging.getLogger(__name__).addHandler(logging.NullHandler())

# name -> module that defines it. Every algorithm is here under its own name
# (no module is named like a function, so loading the registry or the CLI can
# never replace one of these with a submodule), with its result dataclass.
_EXPORTS = {
    # the algorithms, in the order of the chain
    "synth": "geoortho.synthetic.survey",
    "footprints": "geoortho.photos.footprint",
    "gcp_find": "geoortho.gcp.find",
    "sfm": "geoortho.reconstruction.sparse",
    "dense": "geoortho.reconstruction.dense",
    "copc": "geoortho.products3d.copc",
    "dem": "geoortho.elevation.gridding",
    "ortho": "geoortho.orthophoto.mosaic",
    "mesh": "geoortho.products3d.mesh",
    "volume": "geoortho.measure.volume",
    "change": "geoortho.measure.change",
    "run": "geoortho.chain.pipeline",
    "report": "geoortho.chain.reporting",
    "demo": "geoortho.chain.demonstration",
    "plan": "geoortho.planning.plan",
    "check_plan": "geoortho.planning.check",
    # what they return
    "SynthResult": "geoortho.synthetic.survey",
    "FootprintResult": "geoortho.photos.footprint",
    "GcpFindResult": "geoortho.gcp.find",
    "SfmResult": "geoortho.reconstruction.sparse",
    "DenseResult": "geoortho.reconstruction.dense",
    "CopcResult": "geoortho.products3d.copc",
    "DemResult": "geoortho.elevation.gridding",
    "OrthoResult": "geoortho.orthophoto.mosaic",
    "MeshResult": "geoortho.products3d.mesh",
    "VolumeResult": "geoortho.measure.volume",
    "ChangeResult": "geoortho.measure.change",
    "RunResult": "geoortho.chain.pipeline",
    "ReportResult": "geoortho.chain.reporting",
    "DemoResult": "geoortho.chain.demonstration",
    "PlanResult": "geoortho.planning.plan",
    "PlanCheckResult": "geoortho.planning.check",
    # the building blocks around them
    "run_algorithm": "geoortho.processing.registry",
    "read_photos": "geoortho.photos.metadata",
    "read_photo": "geoortho.photos.metadata",
    "Photo": "geoortho.photos.metadata",
    "read_gcp_file": "geoortho.gcp.io",
    "GcpSet": "geoortho.gcp.io",
    "Feedback": "geoortho.feedback",
    "TerminalFeedback": "geoortho.feedback",
    "GeoorthoError": "geoortho.errors",
    "InputError": "geoortho.errors",
    "CanceledError": "geoortho.errors",
}

__all__ = list(_EXPORTS)


#: The algorithms, whose arguments are checked against their declared types at the call.
_ALGORITHMS = frozenset(
    {
        "synth",
        "footprints",
        "gcp_find",
        "sfm",
        "dense",
        "copc",
        "dem",
        "ortho",
        "mesh",
        "volume",
        "change",
        "run",
        "report",
        "demo",
        "plan",
        "check_plan",
    }
)


def __getattr__(name: str) -> Any:
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'geoortho' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    if name in _ALGORITHMS:
        value = _checked(value, f"{module}:{name}")
    globals()[name] = value
    return value


def _checked(function: Any, ref: str) -> Any:
    """``function`` with its arguments' types checked at the door (geoortho.processing.registry)."""
    import functools
    import inspect

    signature = inspect.signature(function)

    @functools.wraps(function)
    def door(*args: Any, **kwargs: Any) -> Any:
        from geoortho.processing.registry import check_call  # here: `import geoortho` stays light

        try:
            bound = signature.bind(*args, **kwargs)
        except TypeError as e:
            from geoortho.errors import InputError  # here: as above

            raise InputError(f"{function.__name__}(): {e}") from None
        bound.arguments.update(check_call(ref, bound.arguments))  # each CRS parsed here, once
        return function(*bound.args, **bound.kwargs)

    return door


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
