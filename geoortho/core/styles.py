"""QGIS styles of the products, in QGIS's documented style XML (no QGIS needed to write them).

Each product's look is written where QGIS finds a layer's default, by the stage that writes the
product: ``<name>.qml`` beside a raster (:func:`write_raster_style`), a row of a GeoPackage's
``layer_styles`` table for each vector layer (:func:`vector_qml`, given to
:func:`geoortho.core.outputs.write_vector`). A layer dragged into QGIS alone, or added to the map by
the Processing toolbox, then looks as it does in the run's project
(:mod:`geoortho.chain.qgis_project`), which draws it with the same builders.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

__all__ = [
    "QGIS_VERSION",
    "TERRAIN",
    "element",
    "hillshade",
    "line",
    "marker",
    "outline",
    "overlap",
    "paletted",
    "percentiles",
    "product_renderer",
    "product_styles",
    "pipe",
    "raster_qml",
    "rgba",
    "terrain",
    "vector_qml",
    "write_raster_style",
]

#: The QGIS version whose format is written (3.40 LTR reads it, and so do later releases).
QGIS_VERSION = "3.40.0-Bratislava"
#: Elevation colours, low to high (a terrain ramp).
TERRAIN = ("#2b83ba", "#abdda4", "#ffffbf", "#fdae61", "#d7191c")

_DOCTYPE = "<!DOCTYPE qgis PUBLIC 'http://mrcc.com/qgis.dtd' 'SYSTEM'>\n"


def element(
    tag: str, attrs: dict[str, Any] | None = None, *children: ET.Element, text: str | None = None
) -> ET.Element:
    e = ET.Element(tag, {k: str(v) for k, v in (attrs or {}).items()})
    e.extend(children)
    if text is not None:
        e.text = text
    return e


def pipe(renderer: ET.Element) -> ET.Element:
    return element("pipe", None, renderer, element("brightnesscontrast", {"brightness": 0, "contrast": 0, "gamma": 1}))


def rgba() -> ET.Element:
    return pipe(
        element(
            "rasterrenderer",
            {"type": "multibandcolor", "redBand": 1, "greenBand": 2, "blueBand": 3, "alphaBand": 4, "opacity": 1},
        )
    )


def paletted(band: int, colours: dict[int, str], labels: dict[int, str]) -> ET.Element:
    """A band of codes drawn in ``colours``, each code's meaning (the table the raster was written
    from) its legend entry."""
    palette = element("colorPalette")
    for code, colour in sorted(colours.items()):
        palette.append(element("paletteEntry", {"value": code, "color": colour, "alpha": 255, "label": labels[code]}))
    return pipe(element("rasterrenderer", {"type": "paletted", "band": band, "opacity": 1, "alphaBand": -1}, palette))


def percentiles(path: Path, band: int = 1) -> tuple[float, float]:
    """The 2nd and 98th percentiles of a band (read from a small overview): the colour ramp's ends."""
    import rasterio

    with rasterio.open(path) as ds:
        f = max(1, int(np.ceil(max(ds.width, ds.height) / 1024)))
        a = ds.read(band, out_shape=(max(1, ds.height // f), max(1, ds.width // f)), masked=True)
    v = np.asarray(a.compressed(), float)
    v = v[np.isfinite(v)]
    if not v.size:
        return 0.0, 1.0
    lo, hi = np.percentile(v, [2, 98])
    return float(lo), float(hi if hi > lo else lo + 1.0)


def ramp(lo: float, hi: float, colours: tuple[str, ...], unit: str) -> ET.Element:
    shader = element(
        "colorrampshader",
        {"colorRampType": "INTERPOLATED", "classificationMode": 1, "clip": 0, "minimumValue": lo, "maximumValue": hi},
    )
    for i, colour in enumerate(colours):
        value = lo + (hi - lo) * i / (len(colours) - 1)
        shader.append(
            element("item", {"value": f"{value:.3f}", "color": colour, "alpha": 255, "label": f"{value:.1f}{unit}"})
        )
    return element("rastershader", None, shader)


def terrain(path: Path) -> ET.Element:
    lo, hi = percentiles(path)
    attrs = {
        "type": "singlebandpseudocolor",
        "band": 1,
        "opacity": 1,
        "alphaBand": -1,
        "classificationMin": lo,
        "classificationMax": hi,
    }
    return pipe(element("rasterrenderer", attrs, ramp(lo, hi, TERRAIN, " m")))


def overlap(path: Path) -> ET.Element:
    _, hi = percentiles(path)
    hi = max(hi, 2.0)
    attrs = {
        "type": "singlebandpseudocolor",
        "band": 1,
        "opacity": 1,
        "alphaBand": -1,
        "classificationMin": 1,
        "classificationMax": hi,
    }
    return pipe(
        element("rasterrenderer", attrs, ramp(1.0, hi, ("#d7191c", "#fdae61", "#a6d96a", "#1a9641"), " photos"))
    )


def hillshade() -> ET.Element:
    attrs = {
        "type": "hillshade",
        "band": 1,
        "opacity": 1,
        "alphaBand": -1,
        "azimuth": 315,
        "angle": 45,
        "zfactor": 1,
        "multidirection": 0,
    }
    return pipe(element("rasterrenderer", attrs))


def _options(values: dict[str, Any]) -> ET.Element:
    return element(
        "Option",
        {"type": "Map"},
        *(element("Option", {"name": k, "type": "QString", "value": v}) for k, v in values.items()),
    )


def _single(kind: str, layer_class: str, values: dict[str, Any]) -> ET.Element:
    symbol = element(
        "symbol",
        {"type": kind, "name": 0, "alpha": 1, "clip_to_extent": 1, "force_rhr": 0},
        element("layer", {"class": layer_class, "enabled": 1, "locked": 0, "pass": 0}, _options(values)),
    )
    return element(
        "renderer-v2",
        {"type": "singleSymbol", "symbollevels": 0, "enableorderby": 0, "forceraster": 0},
        element("symbols", None, symbol),
    )


def _rgb(colour: str) -> str:
    return ",".join(str(int(colour[i : i + 2], 16)) for i in (1, 3, 5)) + ",255"


def marker(colour: str, shape: str, size_mm: float) -> ET.Element:
    return _single(
        "marker",
        "SimpleMarker",
        {"color": _rgb(colour), "name": shape, "size": size_mm, "outline_color": "35,35,35,255", "outline_width": 0.2},
    )


def outline(colour: str, width_mm: float) -> ET.Element:
    return _single(
        "fill",
        "SimpleFill",
        {
            "color": "0,0,0,0",
            "style": "no",
            "outline_color": _rgb(colour),
            "outline_width": width_mm,
            "outline_style": "solid",
        },
    )


def line(colour: str, width_mm: float) -> ET.Element:
    return _single("line", "SimpleLine", {"line_color": _rgb(colour), "line_width": width_mm, "line_style": "solid"})


#: A difference of two surfaces: lower (removed, cut) red, higher (added, fill) blue, no change white.
DIVERGING = ("#d7191c", "#fdae61", "#f7f7f7", "#abd9e9", "#2c7bb6")


def difference(path: Path) -> ET.Element:
    """A difference raster (second minus first) on a ramp symmetric about zero, to its 98th
    percentile of the magnitude: no change white, whatever the sign of the larger change."""
    lo, hi = percentiles(path)
    m = max(abs(lo), abs(hi), 0.01)
    attrs = {
        "type": "singlebandpseudocolor",
        "band": 1,
        "opacity": 1,
        "alphaBand": -1,
        "classificationMin": -m,
        "classificationMax": m,
    }
    return pipe(element("rasterrenderer", attrs, ramp(-m, m, DIVERGING, " m")))


def raster_qml(raster_pipe: ET.Element) -> str:
    """A raster layer's style document (a ``.qml``) for its pipe."""
    doc = element(
        "qgis",
        {"version": QGIS_VERSION, "styleCategories": "AllStyleCategories"},
        raster_pipe,
        element("blendMode", text="0"),
    )
    return _DOCTYPE + ET.tostring(doc, encoding="unicode") + "\n"


def write_raster_style(raster: str | Path, raster_pipe: ET.Element) -> Path:
    """``raster_pipe`` as the raster's default style, ``<name>.qml`` beside it (atomic)."""
    from geoortho.core.outputs import write_text

    return write_text(Path(raster).with_suffix(".qml"), raster_qml(raster_pipe))


def vector_qml(renderer: ET.Element) -> str:
    """A vector layer's style document for its renderer (a GeoPackage keeps it in
    ``layer_styles``)."""
    doc = element("qgis", {"version": QGIS_VERSION, "styleCategories": "AllStyleCategories"}, renderer)
    return _DOCTYPE + ET.tostring(doc, encoding="unicode") + "\n"


#: Each product's vector layer (by its layer name) as the project and its GeoPackage draw it.
_VECTOR_LOOKS: dict[str, Callable[[], ET.Element]] = {
    "footprints": lambda: outline("#377eb8", 0.3),
    "left_out": lambda: outline("#e41a1c", 0.6),  # photos the SfM did not place: ground the products lack
    "seamlines": lambda: outline("#ff7f00", 0.4),
    "cameras": lambda: marker("#e41a1c", "circle", 1.8),
    "detections": lambda: marker("#ffff33", "cross2", 3.0),
    "gcps": lambda: marker("#ff7f00", "triangle", 3.5),
    "residuals": lambda: line("#d7191c", 0.6),
    "contours": lambda: line("#5a3a1a", 0.2),
    "volumes": lambda: outline("#984ea3", 0.6),  # stockpiles and pits measured
    "change": lambda: categorized("kind", {"cut": DIVERGING[0], "fill": DIVERGING[-1]}),  # removed, added
}


def categorized(attribute: str, looks: dict[str, str]) -> ET.Element:
    """Polygons filled by the value of ``attribute`` (value → colour), half transparent."""
    categories = element("categories")
    symbols = element("symbols")
    for i, (value, colour) in enumerate(looks.items()):
        categories.append(element("category", {"value": value, "symbol": i, "label": value, "render": "true"}))
        fill = {
            "color": _rgb(colour).rsplit(",", 1)[0] + ",110",
            "style": "solid",
            "outline_color": _rgb(colour),
            "outline_width": 0.4,
            "outline_style": "solid",
        }
        symbols.append(
            element(
                "symbol",
                {"type": "fill", "name": i, "alpha": 1, "clip_to_extent": 1, "force_rhr": 0},
                element("layer", {"class": "SimpleFill", "enabled": 1, "locked": 0, "pass": 0}, _options(fill)),
            )
        )
    return element(
        "renderer-v2",
        {"type": "categorizedSymbol", "attr": attribute, "symbollevels": 0, "enableorderby": 0, "forceraster": 0},
        categories,
        symbols,
    )


def product_renderer(layer: str) -> ET.Element:
    """The renderer of a product's vector layer, by the layer's name (``footprints``, ``left_out``, ``cameras``,
    ``detections``, ``seamlines``, ``contours``, ``gcps``, ``residuals``, ``volumes``, ``change``)."""
    return _VECTOR_LOOKS[layer]()


def product_styles(*layers: str) -> dict[str, str]:
    """The style documents of these product layers, for :func:`geoortho.core.outputs.write_vector`."""
    return {name: vector_qml(product_renderer(name)) for name in layers}
