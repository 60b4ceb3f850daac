"""geoortho's QGIS Processing provider and plugin: the only place that imports qgis.

The algorithms are built from the registry description (``python -m geoortho
describe --json``) and run geoortho's CLI in a subprocess, so this package
needs neither geoortho nor its dependencies inside QGIS. ``make plugin``
packs this folder as the QGIS plugin ``geoortho_qgis``.
"""


def classFactory(iface):  # noqa: N802 (QGIS's name)
    """QGIS plugin entry point."""
    from geoortho.qgis_provider.plugin import GeoorthoPlugin

    return GeoorthoPlugin(iface)
