"""The QGIS plugin: registers the provider (qgis_process calls only initProcessing)."""

from __future__ import annotations

from typing import Any

from qgis.core import QgsApplication

from .provider import GeoorthoProvider


class GeoorthoPlugin:
    def __init__(self, iface: Any) -> None:
        self.iface = iface
        self.provider: GeoorthoProvider | None = None

    def initProcessing(self) -> None:  # noqa: N802 (QGIS's name)
        if self.provider is None:  # the desktop calls both entry points
            self.provider = GeoorthoProvider()
            QgsApplication.processingRegistry().addProvider(self.provider)

    def initGui(self) -> None:  # noqa: N802
        self.initProcessing()

    def unload(self) -> None:
        if self.provider is not None:
            QgsApplication.processingRegistry().removeProvider(self.provider)
            self.provider = None
