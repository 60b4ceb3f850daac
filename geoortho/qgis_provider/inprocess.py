"""Run in QGIS's own Python: a geoortho Feedback that talks to QgsProcessingFeedback.

Only for the "run in the QGIS process" setting; safe only where geoortho's
compiled dependencies do not clash with QGIS's GDAL/GEOS/PROJ (see the README).
"""

from __future__ import annotations

from typing import Any

from geoortho.feedback import Feedback

__all__ = ["feedback_adapter"]


class _QgisFeedback(Feedback):
    def __init__(self, qgis_feedback: Any) -> None:
        super().__init__()
        self._qgis = qgis_feedback

    def set_progress(self, fraction: float) -> None:
        self._qgis.setProgress(100.0 * fraction)

    def info(self, message: str) -> None:
        self._qgis.pushInfo(message)

    def warning(self, message: str) -> None:
        self._qgis.pushWarning(message)

    def stage(self, name: str, index: int, count: int, start: float, width: float) -> None:
        self._qgis.setProgressText(f"[{index}/{count}] {name}")

    def is_canceled(self) -> bool:
        return super().is_canceled() or bool(self._qgis.isCanceled())


def feedback_adapter(qgis_feedback: Any) -> Feedback:
    """A geoortho Feedback reporting to ``qgis_feedback`` and canceled by it."""
    return _QgisFeedback(qgis_feedback)
