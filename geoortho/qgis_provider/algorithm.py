"""A QgsProcessingAlgorithm built from one algorithm of the registry description.

The description is the JSON of ``python -m geoortho describe --json``; nothing
here imports geoortho (QGIS's Python may not have it). Two lookup tables carry
the whole translation: parameter type -> QGIS parameter, and output type ->
QGIS output. Values go back to geoortho as CLI strings, which the registry's
converters validate exactly as on the command line.
"""

from __future__ import annotations

import html
import json
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

from qgis.core import (
    QgsProcessing,
    QgsProcessingAlgorithm,
    QgsProcessingContext,
    QgsProcessingException,
    QgsProcessingOutputFile,
    QgsProcessingOutputFolder,
    QgsProcessingOutputNumber,
    QgsProcessingOutputRasterLayer,
    QgsProcessingOutputString,
    QgsProcessingOutputVectorLayer,
    QgsProcessingParameterBoolean,
    QgsProcessingParameterCrs,
    QgsProcessingParameterDefinition,
    QgsProcessingParameterEnum,
    QgsProcessingParameterFile,
    QgsProcessingParameterFileDestination,
    QgsProcessingParameterFolderDestination,
    QgsProcessingParameterNumber,
    QgsProcessingParameterRasterDestination,
    QgsProcessingParameterRasterLayer,
    QgsProcessingParameterString,
    QgsProcessingParameterVectorDestination,
    QgsProcessingParameterVectorLayer,
    QgsProviderRegistry,
)

from .interpreter import HOW_TO_SET
from .runner import RunCanceled, RunFailed, run_geoortho

__all__ = ["GeoorthoAlgorithm", "PARAMETER_BUILDERS", "OUTPUT_BUILDERS", "label_of", "point_clouds_as_layers"]

Spec = dict[str, Any]

try:  # QGIS >= 3.36 moved these enums to Qgis
    from qgis.core import Qgis

    _FILE = Qgis.ProcessingFileParameterBehavior.File
    _FOLDER = Qgis.ProcessingFileParameterBehavior.Folder
    _DOUBLE = Qgis.ProcessingNumberParameterType.Double
    _INTEGER = Qgis.ProcessingNumberParameterType.Integer
    _ADVANCED = Qgis.ProcessingParameterFlag.Advanced
except AttributeError:  # pragma: no cover - older QGIS
    _FILE = QgsProcessingParameterFile.File
    _FOLDER = QgsProcessingParameterFile.Folder
    _DOUBLE = QgsProcessingParameterNumber.Double
    _INTEGER = QgsProcessingParameterNumber.Integer
    _ADVANCED = QgsProcessingParameterDefinition.FlagAdvanced


_PATH_TYPES = frozenset({"folder", "file", "raster", "vector", "pointcloud"})
_ACRONYMS = {"dsm": "DSM", "dtm": "DTM", "crs": "CRS", "gcp": "GCP", "sfm": "SfM", "gps": "GPS", "gsd": "GSD"}
_UNIT_SUFFIXES = {"_m": "m", "_cm": "cm", "_mm": "mm", "_deg": "deg", "_px": "px"}


def label_of(p: Spec) -> str:
    """'ground_elevation_m' -> 'Ground elevation (m)': the unit once, at the end."""
    name = p["name"]
    unit = p.get("unit")
    for suffix, suffix_unit in _UNIT_SUFFIXES.items():
        if name.endswith(suffix):
            name = name[: -len(suffix)]
            unit = unit or suffix_unit
    words = [_ACRONYMS.get(w, w) for w in name.split("_") if w]
    text = " ".join(words)
    text = text[:1].upper() + text[1:]
    return f"{text} ({unit})" if unit else text


def _optional(p: Spec) -> bool:
    return not p["required"] and p["default"] in (None, "")


def _file_filter(p: Spec, kind: str) -> str:
    exts = p.get("extensions") or []
    if not exts:
        return ""
    pattern = " ".join(f"*{e}" for e in exts)
    return f"{kind} ({pattern});;All files (*)"


def point_clouds_as_layers() -> bool:
    """QGIS opens LAS/LAZ as layers only with its PDAL provider (absent on Debian 12)."""
    return QgsProviderRegistry.instance().providerMetadata("pdal") is not None


def _is_layer(kind: str) -> bool:
    """Whether parameters of this geoortho type are QGIS map layers (else plain paths)."""
    return kind in ("raster", "vector") or (kind == "pointcloud" and point_clouds_as_layers())


def _folder(p: Spec) -> QgsProcessingParameterDefinition:
    if p["output"]:
        return QgsProcessingParameterFolderDestination(p["qgis_name"], label_of(p), None, _optional(p))
    return QgsProcessingParameterFile(p["qgis_name"], label_of(p), _FOLDER, "", p["default"], _optional(p))


def _file(p: Spec, kind: str = "Files") -> QgsProcessingParameterDefinition:
    if p["output"]:
        return QgsProcessingParameterFileDestination(
            p["qgis_name"], label_of(p), _file_filter(p, kind), None, _optional(p), not _optional(p)
        )
    return QgsProcessingParameterFile(
        p["qgis_name"], label_of(p), _FILE, "", p["default"], _optional(p), _file_filter(p, kind)
    )


def _raster(p: Spec) -> QgsProcessingParameterDefinition:
    if p["output"]:
        return QgsProcessingParameterRasterDestination(
            p["qgis_name"], label_of(p), None, _optional(p), not _optional(p)
        )
    return QgsProcessingParameterRasterLayer(p["qgis_name"], label_of(p), None, _optional(p))


def _vector(p: Spec) -> QgsProcessingParameterDefinition:
    if p["output"]:
        return QgsProcessingParameterVectorDestination(
            p["qgis_name"], label_of(p), QgsProcessing.TypeVectorAnyGeometry, None, _optional(p), not _optional(p)
        )
    return QgsProcessingParameterVectorLayer(p["qgis_name"], label_of(p), [], None, _optional(p))


def _pointcloud(p: Spec) -> QgsProcessingParameterDefinition:
    if point_clouds_as_layers():
        from qgis.core import (
            QgsProcessingParameterPointCloudDestination,
            QgsProcessingParameterPointCloudLayer,
        )

        if p["output"]:
            return QgsProcessingParameterPointCloudDestination(
                p["qgis_name"], label_of(p), None, _optional(p), not _optional(p)
            )
        return QgsProcessingParameterPointCloudLayer(p["qgis_name"], label_of(p), None, _optional(p))
    return _file(p, "Point clouds")


def _number(p: Spec, number_type: Any) -> QgsProcessingParameterDefinition:
    q = QgsProcessingParameterNumber(p["qgis_name"], label_of(p), number_type, p["default"], _optional(p))
    if p.get("minimum") is not None:
        q.setMinimum(p["minimum"])
    if p.get("maximum") is not None:
        q.setMaximum(p["maximum"])
    return q


def _enum(p: Spec) -> QgsProcessingParameterDefinition:
    # Static strings: the value is the choice itself ("smrf"), as on the CLI,
    # so qgis_process and scripts pass names, not indices.
    return QgsProcessingParameterEnum(
        p["qgis_name"], label_of(p), list(p["choices"]), False, p["default"], _optional(p), True
    )


#: One builder per geoortho parameter type (a test checks every type has one).
PARAMETER_BUILDERS: dict[str, Callable[[Spec], QgsProcessingParameterDefinition]] = {
    "folder": _folder,
    "file": _file,
    "raster": _raster,
    "vector": _vector,
    "pointcloud": _pointcloud,
    "number": lambda p: _number(p, _DOUBLE),
    "integer": lambda p: _number(p, _INTEGER),
    "enum": _enum,
    "bool": lambda p: QgsProcessingParameterBoolean(p["qgis_name"], label_of(p), bool(p["default"]), False),
    "crs": lambda p: QgsProcessingParameterCrs(p["qgis_name"], label_of(p), p["default"], _optional(p)),
    "string": lambda p: QgsProcessingParameterString(p["qgis_name"], label_of(p), p["default"], False, _optional(p)),
}


def _output_pointcloud(name: str, text: str) -> Any:
    if point_clouds_as_layers():
        from qgis.core import QgsProcessingOutputPointCloudLayer

        return QgsProcessingOutputPointCloudLayer(name, text)
    return QgsProcessingOutputFile(name, text)


try:  # QGIS >= 3.32: JSON outputs reach scripts as dicts, not text
    from qgis.core import QgsProcessingOutputVariant as _JsonOutput

    _JSON_AS_TEXT = False
except ImportError:  # pragma: no cover
    _JsonOutput = QgsProcessingOutputString
    _JSON_AS_TEXT = True


#: One QGIS output per geoortho output type.
OUTPUT_BUILDERS: dict[str, Callable[[str, str], Any]] = {
    "folder": QgsProcessingOutputFolder,
    "file": QgsProcessingOutputFile,
    "raster": QgsProcessingOutputRasterLayer,
    "vector": QgsProcessingOutputVectorLayer,
    "pointcloud": _output_pointcloud,
    "number": QgsProcessingOutputNumber,
    "integer": QgsProcessingOutputNumber,
    "string": QgsProcessingOutputString,
    "json": _JsonOutput,
}


class GeoorthoAlgorithm(QgsProcessingAlgorithm):  # type: ignore[misc]  # QGIS is not typed here
    """One geoortho algorithm: parameters from its spec, run by geoortho's CLI.

    ``settings`` is a callable returning the provider's current settings:
    ``interpreter`` (a callable giving the python path, raising when there is
    none) and ``in_process`` (run the core function in QGIS's own Python).
    """

    def __init__(self, spec: Spec, settings: Callable[[], dict[str, Any]]) -> None:
        super().__init__()
        self._spec = spec
        self._settings = settings
        self._destinations = [p for p in spec["parameters"] if p["output"]]

    # --- identity and help ----------------------------------------------------
    def createInstance(self) -> GeoorthoAlgorithm:  # noqa: N802 (QGIS API names)
        return GeoorthoAlgorithm(self._spec, self._settings)

    def name(self) -> str:
        result: str = self._spec["id"]
        return result

    def displayName(self) -> str:  # noqa: N802
        result: str = self._spec["title"]
        return result

    def group(self) -> str:
        result: str = self._spec["group"]
        return result

    def groupId(self) -> str:  # noqa: N802
        return "".join(c for c in self._spec["group"].lower() if c.isalnum())

    def shortDescription(self) -> str:  # noqa: N802
        result: str = self._spec["short_help"]
        return result

    def shortHelpString(self) -> str:  # noqa: N802
        paragraphs = [html.escape(" ".join(block.split())) for block in self._spec["help"].split("\n\n")]
        cli = f"python -m geoortho {self._spec['id']} --help"
        return "".join(f"<p>{p}</p>" for p in paragraphs if p) + f"<p>Command line: <code>{cli}</code></p>"

    def helpUrl(self) -> str:  # noqa: N802
        return ""

    def tags(self) -> list[str]:
        return ["geoortho", "drone", "uav", "photogrammetry", self._spec["id"]]

    # --- parameters -----------------------------------------------------------
    def initAlgorithm(self, config: dict[str, Any] | None = None) -> None:  # noqa: N802
        for p in self._spec["parameters"]:
            q = PARAMETER_BUILDERS[p["type"]](p)
            if p.get("help"):
                q.setHelp(p["help"])
            if p.get("advanced"):
                q.setFlags(q.flags() | _ADVANCED)
            self.addParameter(q)
        destinations = {p["qgis_name"] for p in self._destinations}
        for o in self._spec["outputs"]:
            name = o["name"].upper()
            if name not in destinations:  # a destination parameter already made this output
                self.addOutput(OUTPUT_BUILDERS[o["type"]](name, o.get("help") or label_of(o)))

    # --- values -> geoortho ---------------------------------------------------
    def _given(self, parameters: dict[str, Any], name: str) -> bool:
        value = parameters.get(name)
        return value is not None and value != "" and not (hasattr(value, "isNull") and value.isNull())

    def _layer_path(self, layer: Any, name: str) -> str:
        parts = QgsProviderRegistry.instance().decodeUri(layer.providerType(), layer.source())
        path = parts.get("path") or ""
        if not path or not Path(path).exists():
            raise QgsProcessingException(
                f"{name}: geoortho reads files; layer '{layer.name()}' is not a file ({layer.source()})"
            )
        return path

    def values(self, parameters: dict[str, Any], context: QgsProcessingContext) -> dict[str, Any]:
        """The geoortho values (strings, bools) of the given parameters, by spec name."""
        values: dict[str, Any] = {}
        for p in self._spec["parameters"]:
            name, kind = p["qgis_name"], p["type"]
            if _optional(p) and not self._given(parameters, name):
                continue
            if p["output"]:
                if _is_layer(kind):
                    value = self.parameterAsOutputLayer(parameters, name, context)
                else:
                    value = self.parameterAsFileOutput(parameters, name, context)
                if value:
                    Path(value).parent.mkdir(parents=True, exist_ok=True)
            elif _is_layer(kind):
                as_layer = {
                    "raster": self.parameterAsRasterLayer,
                    "vector": self.parameterAsVectorLayer,
                    "pointcloud": self.parameterAsPointCloudLayer,
                }[kind]
                layer = as_layer(parameters, name, context)
                value = self._layer_path(layer, name) if layer is not None else None
            elif kind in ("folder", "file", "pointcloud"):
                value = self.parameterAsFile(parameters, name, context)
            elif kind == "number":
                value = repr(self.parameterAsDouble(parameters, name, context))
            elif kind == "integer":
                value = str(self.parameterAsInt(parameters, name, context))
            elif kind == "enum":
                value = self.parameterAsEnumString(parameters, name, context)
            elif kind == "bool":
                value = self.parameterAsBoolean(parameters, name, context)
            elif kind == "crs":
                crs = self.parameterAsCrs(parameters, name, context)
                value = (crs.authid() or crs.toWkt()) if crs.isValid() else None
            else:
                value = self.parameterAsString(parameters, name, context)
            if value is None or value == "":
                if p["required"]:
                    raise QgsProcessingException(f"{name} is required")
                continue
            if kind in _PATH_TYPES:
                value = os.path.abspath(value)  # geoortho runs in another folder
            values[p["name"]] = value
        return values

    def arguments(self, values: dict[str, Any]) -> list[str]:
        """CLI arguments for ``values`` (spec name -> value)."""
        args: list[str] = []
        for p in self._spec["parameters"]:
            if p["name"] not in values:
                continue
            value = values[p["name"]]
            if p["type"] == "bool":
                args.append(p["cli"] if value else "--no-" + p["cli"][2:])
            else:
                args.append(f"{p['cli']}={value}")
        return args

    # --- run ------------------------------------------------------------------
    def processAlgorithm(
        self,
        parameters: dict[str, Any],
        context: QgsProcessingContext,  # noqa: N802
        feedback: Any,
    ) -> dict[str, Any]:
        values = self.values(parameters, context)
        settings = self._settings()
        if settings.get("in_process"):
            outputs = self._run_in_process(values, feedback)
        else:
            try:
                interpreter = settings["interpreter"]()
            except Exception as e:  # InterpreterError, with how to set it
                raise QgsProcessingException(str(e)) from None
            destinations = [values[p["name"]] for p in self._destinations if p["name"] in values]
            try:
                outputs = run_geoortho(
                    interpreter, self._spec["id"], self.arguments(values), feedback, destinations=destinations
                )
            except RunCanceled as e:
                raise QgsProcessingException(f"{e}; no output was written") from None
            except RunFailed as e:
                message = str(e)
                if "No module named geoortho" in message:
                    message += f" ({interpreter} has no geoortho); {HOW_TO_SET}"
                raise QgsProcessingException(message) from None
        return self._results(values, outputs, context)

    def _run_in_process(self, values: dict[str, Any], feedback: Any) -> dict[str, Any]:
        try:  # here: QGIS's own Python may not have geoortho's dependencies (the default runs our interpreter)
            from geoortho.errors import CanceledError, GeoorthoError, interrupted
            from geoortho.processing.registry import run_algorithm
        except ImportError as e:
            raise QgsProcessingException(
                f"'run in the QGIS process' is on, but geoortho cannot be imported here ({e}); "
                "turn the setting off to run geoortho's own interpreter"
            ) from None
        from .inprocess import feedback_adapter  # here: only the in-process setting needs it

        if "workers" in {p["name"] for p in self._spec["parameters"]} and "workers" not in values:
            # Worker processes would be spawned with sys.executable, which inside
            # QGIS is QGIS itself (or whatever python3 is on PATH), not a Python.
            values = dict(values, workers=1)
        canceled = f"geoortho {self._spec['id']}: canceled; no output was written"
        try:
            return run_algorithm(self._spec["id"], values, feedback_adapter(feedback))
        except CanceledError:
            raise QgsProcessingException(canceled) from None
        except GeoorthoError as e:
            raise QgsProcessingException(f"geoortho {self._spec['id']}: error: {e}") from None
        except Exception as e:
            if interrupted(e):  # a cancel a library wrapped in its own error (pybind11, pycolmap)
                raise QgsProcessingException(canceled) from None
            raise

    def _results(
        self, values: dict[str, Any], outputs: dict[str, Any], context: QgsProcessingContext
    ) -> dict[str, Any]:
        # Every destination parameter given is a result under its own name (dem's
        # OUTPUT is its "dsm"): QGIS loads and models chain by these names.
        results: dict[str, Any] = {
            p["qgis_name"]: str(values[p["name"]]) for p in self._destinations if p["name"] in values
        }
        param_names = {p["name"] for p in self._destinations}
        for o in self._spec["outputs"]:
            value = outputs.get(o["name"])
            if value is None:
                continue
            if o["type"] == "json" and _JSON_AS_TEXT:
                value = json.dumps(value)
            results[o["name"].upper()] = value
            # Layers that are not destination parameters (which QGIS loads itself):
            # open them too when the run comes from the toolbox.
            if o["name"] not in param_names and o["type"] in ("raster", "vector") and context.project():
                details = QgsProcessingContext.LayerDetails(
                    f"{self._spec['id']} {o['name']}", context.project(), o["name"].upper()
                )
                context.addLayerToLoadOnCompletion(str(value), details)
        return results
