"""geoortho's QGIS Processing provider and plugin: the only place that imports qgis.

The algorithms are built from the registry description (``python -m geoortho
describe --json``) and run geoortho's CLI in a subprocess, so this package
needs neither geoortho nor its dependencies inside QGIS. ``make plugin``
packs this folder as the QGIS plugin ``geoortho_qgis``: its modules import each other
relatively, as the only package in geoortho that does, because the zip renames it.
"""

from typing import Any


def classFactory(iface: Any) -> Any:  # noqa: N802 (QGIS's name)
    """QGIS plugin entry point."""
    from .plugin import GeoorthoPlugin  # here: QGIS imports this package before its GUI is up

    return GeoorthoPlugin(iface)
