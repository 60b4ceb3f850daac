"""The algorithm registry: one declarative spec per algorithm.

The CLI (:mod:`geoortho.processing.cli`) and the QGIS provider are generated
from these specs. Nothing here imports QGIS.
"""

from .spec import PARAM_TYPES, Algorithm, Output, Param
from .registry import get_algorithm, list_algorithms, run_algorithm, describe

__all__ = [
    "PARAM_TYPES",
    "Algorithm",
    "Output",
    "Param",
    "get_algorithm",
    "list_algorithms",
    "run_algorithm",
    "describe",
]
