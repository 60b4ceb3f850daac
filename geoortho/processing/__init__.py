"""The algorithm registry: one declarative spec per algorithm.

The CLI (:mod:`geoortho.processing.cli`) and the QGIS provider are generated
from these specs. Nothing here imports QGIS.
"""

from geoortho.processing.registry import describe, get_algorithm, list_algorithms, run_algorithm
from geoortho.processing.spec import PARAM_TYPES, Algorithm, Output, Param

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
