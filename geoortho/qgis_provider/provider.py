"""The Processing provider ``geoortho``: one algorithm per registry entry.

Where the algorithm list comes from, in order: a description handed in (tests),
the live registry of geoortho's interpreter (``describe --json``, cached in the
QGIS profile), and the ``algorithms.json`` that ``make plugin`` bundles, so the
algorithms show even before the interpreter is set (running one then says how
to set it).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from qgis.core import Qgis, QgsApplication, QgsMessageLog, QgsProcessingProvider
from qgis.PyQt.QtGui import QIcon

from .algorithm import OUTPUT_BUILDERS, PARAMETER_BUILDERS, GeoorthoAlgorithm
from .interpreter import InterpreterError, find_interpreter, load_description

__all__ = ["GeoorthoProvider", "SETTING_PYTHON", "SETTING_IN_PROCESS"]

SETTING_PYTHON = "GEOORTHO_PYTHON"
SETTING_IN_PROCESS = "GEOORTHO_IN_PROCESS"
_HERE = Path(__file__).resolve().parent
BUNDLED_DESCRIPTION = _HERE / "algorithms.json"


def _log(message: str, level: Any = Qgis.Info) -> None:
    QgsMessageLog.logMessage(message, "geoortho", level)


def _processing_config() -> tuple[Any, Any]:
    """Processing's ProcessingConfig and Setting, or (None, None) outside a full Processing (bare pyqgis)."""
    try:
        from processing.core.ProcessingConfig import ProcessingConfig, Setting
    except ImportError:
        return None, None
    return ProcessingConfig, Setting


class GeoorthoProvider(QgsProcessingProvider):  # type: ignore[misc]  # QGIS is not typed here
    def __init__(self, description: dict[str, Any] | None = None) -> None:
        super().__init__()
        self._given_description = description
        self.description: dict[str, Any] | None = None
        self.description_source = ""

    # --- identity -------------------------------------------------------------
    def id(self) -> str:
        return "geoortho"

    def name(self) -> str:
        return "geoortho"

    def longName(self) -> str:  # noqa: N802 (QGIS API names)
        version = (self.description or {}).get("version")
        return f"geoortho {version}" if version else "geoortho"

    def icon(self) -> QIcon:
        return QIcon(str(_HERE / "icon.svg"))

    def svgIconPath(self) -> str:  # noqa: N802
        return str(_HERE / "icon.svg")

    def supportedOutputRasterLayerExtensions(self) -> list[str]:  # noqa: N802
        return ["tif"]  # geoortho writes Cloud-Optimized GeoTIFF only

    def supportedOutputVectorLayerExtensions(self) -> list[str]:  # noqa: N802
        return ["gpkg", "geojson", "fgb", "shp", "csv"]

    def defaultVectorFileExtension(self, hasGeometry: bool = True) -> str:  # noqa: N802, N803
        return "gpkg"

    def defaultRasterFileExtension(self) -> str:  # noqa: N802
        return "tif"

    # --- settings -------------------------------------------------------------
    def load(self) -> bool:
        config, setting = _processing_config()
        if config is not None:
            config.settingIcons[self.name()] = self.icon()
            config.addSetting(
                setting(
                    self.name(),
                    SETTING_PYTHON,
                    "geoortho Python interpreter (empty: $GEOORTHO_PYTHON, else found automatically)",
                    "",
                    valuetype=setting.FILE,
                )
            )
            config.addSetting(
                setting(
                    self.name(),
                    SETTING_IN_PROCESS,
                    "Run geoortho in the QGIS process (only when its libraries do not clash with QGIS's)",
                    False,
                )
            )
            config.readSettings()
        self.refreshAlgorithms()
        return True

    def unload(self) -> None:
        config, _ = _processing_config()
        if config is not None:
            for key in (SETTING_PYTHON, SETTING_IN_PROCESS):
                config.removeSetting(key)

    def _setting(self, key: str, default: Any) -> Any:
        config, _ = _processing_config()
        if config is None:
            return default
        value = config.getSetting(key)
        return default if value is None else value

    def settings(self) -> dict[str, Any]:
        """What the algorithms read at run time (so a changed setting applies at once)."""
        configured = str(self._setting(SETTING_PYTHON, "") or "")
        in_process = self._setting(SETTING_IN_PROCESS, False)
        if isinstance(in_process, str):
            in_process = in_process.strip().lower() in ("1", "true", "yes")
        return {"interpreter": lambda: find_interpreter(configured), "in_process": bool(in_process)}

    # --- algorithms -----------------------------------------------------------
    def _load_description(self) -> tuple[dict[str, Any] | None, str]:
        if self._given_description is not None:
            return self._given_description, "given"
        settings = self.settings()
        if settings["in_process"]:
            try:  # here: QGIS's own Python may not have geoortho's dependencies
                from geoortho.processing.registry import describe

                return describe(), "the geoortho imported in QGIS"
            except ImportError as e:
                _log(f"run in the QGIS process is on, but geoortho cannot be imported ({e})", Qgis.Warning)
        try:
            interpreter = settings["interpreter"]()
            cache = Path(QgsApplication.qgisSettingsDirPath()) / "geoortho" / "description.json"
            return load_description(interpreter, cache), interpreter
        except InterpreterError as e:
            _log(str(e), Qgis.Warning)
        if BUNDLED_DESCRIPTION.is_file():
            return json.loads(BUNDLED_DESCRIPTION.read_text(encoding="utf-8")), str(BUNDLED_DESCRIPTION)
        return None, ""

    def loadAlgorithms(self) -> None:  # noqa: N802
        self.description, self.description_source = self._load_description()
        if self.description is None:
            _log("geoortho: no algorithms (no interpreter found and no bundled description)", Qgis.Critical)
            return
        added = 0
        for spec in self.description["algorithms"]:
            unknown = sorted(
                {p["type"] for p in spec["parameters"]} - set(PARAMETER_BUILDERS)
                | {o["type"] for o in spec["outputs"]} - set(OUTPUT_BUILDERS)
            )
            if unknown:  # a geoortho newer than this plugin: skip the one algorithm, keep the rest
                _log(
                    f"geoortho:{spec['id']} is left out: this plugin does not know the type(s) "
                    f"{', '.join(unknown)}; build the plugin of the same geoortho version (make plugin)",
                    Qgis.Warning,
                )
                continue
            self.addAlgorithm(GeoorthoAlgorithm(spec, self.settings))
            added += 1
        _log(f"{added} algorithms from {self.description_source}")
