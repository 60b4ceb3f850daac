"""A run's products as one QGIS project, styled, and each product's style beside it.

``project.qgz`` (QGIS's own zipped ``.qgs`` XML, paths relative to it) holds every product of a
run as a layer, grouped and in a sensible order: the survey's vectors over the orthophoto, the
DSM and DTM coloured over their hillshades, the source rasters paletted with a legend. Each
raster's style is also written where QGIS looks for a layer's default, ``<name>.qml`` beside it,
so a raster dragged into QGIS alone looks the same (the GeoPackages' styles are the project's only).
No QGIS is needed to write them: the XML is QGIS's documented project and style format.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from geoortho.core.outputs import atomic_path, write_text
from geoortho.elevation.coverage import FALLBACK, INTERPOLATED, MEASURED, SOURCE_NAMES, UNDER_OBJECT
from geoortho.orthophoto.provenance import INPAINTED, OCCLUDED, SEEN, SOURCE_KINDS

__all__ = ["PROJECT_NAME", "write_qgis_project"]

PROJECT_NAME = "project.qgz"
#: The QGIS version whose format is written (3.40 LTR reads it, and so do later releases).
QGIS_VERSION = "3.40.0-Bratislava"

#: Colours of the DEM source codes and of the orthophoto's "how" codes (band 2 of its source raster).
_SOURCE_COLOURS = {MEASURED: "#1a9641", INTERPOLATED: "#fdae61", FALLBACK: "#d7191c", UNDER_OBJECT: "#7b3294"}
_HOW_COLOURS = {SEEN: "#1a9641", OCCLUDED: "#7b3294", INPAINTED: "#d7191c"}
#: Elevation colours, low to high (a terrain ramp).
_TERRAIN = ("#2b83ba", "#abdda4", "#ffffbf", "#fdae61", "#d7191c")


@dataclass(frozen=True)
class _Layer:
    """One layer of the project: where it is (relative to the project), how it is drawn."""

    name: str
    path: Path  # absolute
    kind: str  # "raster" or "vector"
    pipe: ET.Element | None = None  # a raster's renderer
    renderer: ET.Element | None = None  # a vector's renderer
    layer: str = ""  # a GeoPackage's layer
    geometry: str = ""  # Point, Line, Polygon
    visible: bool = True
    blend_multiply: bool = False


def write_qgis_project(project: Path) -> Path | None:
    """Write ``project.qgz`` into the run's ``project`` folder and each product's default style;
    return the project file (None when the run made no product to show)."""
    project = Path(project)
    groups = _groups(project)
    if not any(layers for _, layers in groups):
        return None
    crs_wkt, authid, extent = _crs_and_extent([layer for _, layers in groups for layer in layers])
    for _, layers in groups:
        for layer in layers:
            _write_default_style(layer)
    root = _project_xml(project, groups, crs_wkt, authid, extent)
    target = project / PROJECT_NAME
    with atomic_path(target) as tmp, zipfile.ZipFile(tmp, "w", zipfile.ZIP_DEFLATED) as z:
        z.writestr("project.qgs", ET.tostring(root, encoding="unicode", xml_declaration=False))
    return target


# ---------------------------------------------------------------------------------------------
# which layers


def _groups(project: Path) -> list[tuple[str, list[_Layer]]]:
    """The products found, grouped, top of the layer tree first."""
    survey: list[_Layer] = []
    for path, layer, geom, name, renderer in (
        (project / "gcp_residuals.gpkg", "residuals", "Line", "GCP residuals (exaggerated)", _line("#d7191c", 0.6)),
        (project / "gcp_residuals.gpkg", "gcps", "Point", "GCPs and checkpoints", _marker("#ff7f00", "triangle", 3.5)),
        (project / "sfm" / "cameras.gpkg", "cameras", "Point", "cameras (SfM)", _marker("#e41a1c", "circle", 1.8)),
        (
            project / "gcp-find" / "detections.gpkg",
            "detections",
            "Point",
            "GCP detections",
            _marker("#ffff33", "cross2", 3.0),
        ),
        (project / "footprints" / "footprints.gpkg", "footprints", "Polygon", "footprints", _outline("#377eb8", 0.3)),
        (project / "ortho" / "ortho_seamlines.gpkg", "seamlines", "Polygon", "seamlines", _outline("#ff7f00", 0.4)),
    ):
        if path.is_file():
            visible = layer not in ("seamlines", "footprints")
            survey.append(_Layer(name, path, "vector", renderer=renderer, layer=layer, geometry=geom, visible=visible))
    ortho: list[_Layer] = []
    if (p := project / "ortho" / "ortho.tif").is_file():
        ortho.append(_Layer("orthophoto", p, "raster", pipe=_rgba()))
    if (p := project / "ortho" / "ortho_source.tif").is_file():
        ortho.insert(
            0,
            _Layer(
                "orthophoto: how each pixel was drawn",
                p,
                "raster",
                pipe=_paletted(2, _HOW_COLOURS, SOURCE_KINDS),
                visible=False,
            ),
        )
    surfaces: list[_Layer] = []
    if (p := project / "dem" / "contours.gpkg").is_file():
        surfaces.append(
            _Layer(
                "DTM contours",
                p,
                "vector",
                renderer=_line("#5a3a1a", 0.2),
                layer="contours",
                geometry="Line",
                visible=False,
            )
        )
    for name in ("dtm", "dsm"):
        if (p := project / "dem" / f"{name}.tif").is_file():
            label = name.upper()
            surfaces.append(
                _Layer(f"{label} hillshade", p, "raster", pipe=_hillshade(), visible=False, blend_multiply=True)
            )
            surfaces.append(_Layer(label, p, "raster", pipe=_terrain(p), visible=False))
    for name in ("dsm_source", "dtm_source"):
        if (p := project / "dem" / f"{name}.tif").is_file():
            surfaces.append(
                _Layer(
                    name.replace("_", " "), p, "raster", pipe=_paletted(1, _SOURCE_COLOURS, SOURCE_NAMES), visible=False
                )
            )
    if (p := project / "footprints" / "overlap.tif").is_file():
        surfaces.append(_Layer("overlap (photos a point)", p, "raster", pipe=_overlap(p), visible=False))
    return [("Survey", survey), ("Orthophoto", ortho), ("Surfaces", surfaces)]


# ---------------------------------------------------------------------------------------------
# styles


def _el(tag: str, attrs: dict[str, Any] | None = None, *children: ET.Element, text: str | None = None) -> ET.Element:
    e = ET.Element(tag, {k: str(v) for k, v in (attrs or {}).items()})
    e.extend(children)
    if text is not None:
        e.text = text
    return e


def _pipe(renderer: ET.Element) -> ET.Element:
    return _el("pipe", None, renderer, _el("brightnesscontrast", {"brightness": 0, "contrast": 0, "gamma": 1}))


def _rgba() -> ET.Element:
    return _pipe(
        _el(
            "rasterrenderer",
            {"type": "multibandcolor", "redBand": 1, "greenBand": 2, "blueBand": 3, "alphaBand": 4, "opacity": 1},
        )
    )


def _paletted(band: int, colours: dict[int, str], labels: dict[int, str]) -> ET.Element:
    """A band of codes drawn in ``colours``, each code's meaning (the table the raster was written
    from) its legend entry."""
    palette = _el("colorPalette")
    for code, colour in sorted(colours.items()):
        palette.append(_el("paletteEntry", {"value": code, "color": colour, "alpha": 255, "label": labels[code]}))
    return _pipe(_el("rasterrenderer", {"type": "paletted", "band": band, "opacity": 1, "alphaBand": -1}, palette))


def _percentiles(path: Path, band: int = 1) -> tuple[float, float]:
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


def _ramp(lo: float, hi: float, colours: tuple[str, ...], unit: str) -> ET.Element:
    shader = _el(
        "colorrampshader",
        {"colorRampType": "INTERPOLATED", "classificationMode": 1, "clip": 0, "minimumValue": lo, "maximumValue": hi},
    )
    for i, colour in enumerate(colours):
        value = lo + (hi - lo) * i / (len(colours) - 1)
        shader.append(
            _el("item", {"value": f"{value:.3f}", "color": colour, "alpha": 255, "label": f"{value:.1f}{unit}"})
        )
    return _el("rastershader", None, shader)


def _terrain(path: Path) -> ET.Element:
    lo, hi = _percentiles(path)
    attrs = {
        "type": "singlebandpseudocolor",
        "band": 1,
        "opacity": 1,
        "alphaBand": -1,
        "classificationMin": lo,
        "classificationMax": hi,
    }
    return _pipe(_el("rasterrenderer", attrs, _ramp(lo, hi, _TERRAIN, " m")))


def _overlap(path: Path) -> ET.Element:
    _, hi = _percentiles(path)
    hi = max(hi, 2.0)
    attrs = {
        "type": "singlebandpseudocolor",
        "band": 1,
        "opacity": 1,
        "alphaBand": -1,
        "classificationMin": 1,
        "classificationMax": hi,
    }
    return _pipe(_el("rasterrenderer", attrs, _ramp(1.0, hi, ("#d7191c", "#fdae61", "#a6d96a", "#1a9641"), " photos")))


def _hillshade() -> ET.Element:
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
    return _pipe(_el("rasterrenderer", attrs))


def _options(values: dict[str, Any]) -> ET.Element:
    return _el(
        "Option",
        {"type": "Map"},
        *(_el("Option", {"name": k, "type": "QString", "value": v}) for k, v in values.items()),
    )


def _single(kind: str, layer_class: str, values: dict[str, Any]) -> ET.Element:
    symbol = _el(
        "symbol",
        {"type": kind, "name": 0, "alpha": 1, "clip_to_extent": 1, "force_rhr": 0},
        _el("layer", {"class": layer_class, "enabled": 1, "locked": 0, "pass": 0}, _options(values)),
    )
    return _el(
        "renderer-v2",
        {"type": "singleSymbol", "symbollevels": 0, "enableorderby": 0, "forceraster": 0},
        _el("symbols", None, symbol),
    )


def _rgb(colour: str) -> str:
    return ",".join(str(int(colour[i : i + 2], 16)) for i in (1, 3, 5)) + ",255"


def _marker(colour: str, shape: str, size_mm: float) -> ET.Element:
    return _single(
        "marker",
        "SimpleMarker",
        {"color": _rgb(colour), "name": shape, "size": size_mm, "outline_color": "35,35,35,255", "outline_width": 0.2},
    )


def _outline(colour: str, width_mm: float) -> ET.Element:
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


def _line(colour: str, width_mm: float) -> ET.Element:
    return _single("line", "SimpleLine", {"line_color": _rgb(colour), "line_width": width_mm, "line_style": "solid"})


# ---------------------------------------------------------------------------------------------
# the project


def _crs_and_extent(layers: list[_Layer]) -> tuple[str, str, tuple[float, float, float, float]]:
    """The survey's CRS (the first raster's, else the first vector's) and the products' extent in it."""
    import pyogrio
    import rasterio

    crs_wkt, authid = "", ""
    boxes = []
    for layer in layers:
        if layer.kind == "raster":
            with rasterio.open(layer.path) as ds:
                boxes.append(tuple(ds.bounds))
                if not crs_wkt and ds.crs:
                    from pyproj import CRS

                    from geoortho.core.crs import horizontal_of

                    # the map's: a DEM's heights' datum is its layer's own
                    horizontal = horizontal_of(CRS.from_user_input(ds.crs.to_wkt()))
                    code = horizontal.to_epsg()
                    crs_wkt, authid = horizontal.to_wkt(), (f"EPSG:{code}" if code else ds.crs.to_string())
        else:
            info = pyogrio.read_info(layer.path, layer=layer.layer, force_total_bounds=True)
            if info.get("total_bounds") is not None and info.get("features"):
                boxes.append(tuple(info["total_bounds"]))
    if not crs_wkt:
        from pyproj import CRS

        first = next(layer for layer in layers if layer.kind == "vector")
        crs = CRS.from_user_input(pyogrio.read_info(first.path, layer=first.layer)["crs"])
        crs_wkt, authid = crs.to_wkt(), crs.to_string()
    b = np.array(boxes, float)
    return crs_wkt, authid, (float(b[:, 0].min()), float(b[:, 1].min()), float(b[:, 2].max()), float(b[:, 3].max()))


def _srs(crs_wkt: str, authid: str) -> ET.Element:
    return _el("spatialrefsys", {"nativeFormat": "Wkt"}, _el("wkt", text=crs_wkt), _el("authid", text=authid))


def _source(layer: _Layer, project: Path) -> str:
    rel = "./" + layer.path.relative_to(project).as_posix()
    return f"{rel}|layername={layer.layer}" if layer.kind == "vector" else rel


def _layer_id(layer: _Layer, index: int) -> str:
    return f"{layer.name.replace(' ', '_').replace(':', '')}_{index:02d}"


def _own_crs(layer: _Layer) -> tuple[str, str] | None:
    """A raster's own CRS where it says more than the map's (a DEM's heights' datum), else None."""
    if layer.kind != "raster":
        return None
    import rasterio
    from pyproj import CRS

    with rasterio.open(layer.path) as ds:
        if ds.crs is None:
            return None
        crs = CRS.from_user_input(ds.crs.to_wkt())
    if not (crs.is_compound or len(crs.axis_info) == 3):
        return None
    from geoortho.core.crs import crs_to_text

    return crs.to_wkt(), crs_to_text(crs)


def _map_layer(layer: _Layer, lid: str, project: Path, crs_wkt: str, authid: str) -> ET.Element:
    attrs = {"type": layer.kind, "hasScaleBasedVisibilityFlag": 0}
    if layer.kind == "vector":
        attrs["geometry"] = layer.geometry
    e = _el(
        "maplayer",
        attrs,
        _el("id", text=lid),
        _el("datasource", text=_source(layer, project)),
        _el("layername", text=layer.name),
        _el("srs", None, _srs(*(_own_crs(layer) or (crs_wkt, authid)))),
    )
    if layer.kind == "vector":
        e.append(_el("provider", {"encoding": "UTF-8"}, text="ogr"))
        assert layer.renderer is not None
        e.append(layer.renderer)
    else:
        e.append(_el("provider", text="gdal"))
        assert layer.pipe is not None
        e.append(layer.pipe)
    e.append(_el("blendMode", text="6" if layer.blend_multiply else "0"))  # Qgis::BlendMode: 6 multiply
    return e


def _project_xml(
    project: Path,
    groups: list[tuple[str, list[_Layer]]],
    crs_wkt: str,
    authid: str,
    extent: tuple[float, float, float, float],
) -> ET.Element:
    root = _el("qgis", {"projectname": f"geoortho: {project.name}", "version": QGIS_VERSION})
    root.append(_el("title", text=f"geoortho: {project.name}"))
    root.append(_el("projectCrs", None, _srs(crs_wkt, authid)))
    tree = _el("layer-tree-group", None, _el("customproperties"))
    layers_xml = _el("projectlayers")
    order = _el("custom-order", {"enabled": 0})
    index = 0
    for group_name, layers in groups:
        if not layers:
            continue
        group = _el("layer-tree-group", {"name": group_name, "checked": "Qt::Checked", "expanded": 1})
        for layer in layers:
            lid = _layer_id(layer, index)
            index += 1
            checked = "Qt::Checked" if layer.visible else "Qt::Unchecked"
            provider = "ogr" if layer.kind == "vector" else "gdal"
            group.append(
                _el(
                    "layer-tree-layer",
                    {
                        "id": lid,
                        "name": layer.name,
                        "source": _source(layer, project),
                        "providerKey": provider,
                        "checked": checked,
                        "expanded": 0,
                    },
                )
            )
            layers_xml.append(_map_layer(layer, lid, project, crs_wkt, authid))
            order.append(_el("item", text=lid))
        tree.append(group)
    tree.append(order)
    root.append(tree)
    xmin, ymin, xmax, ymax = extent
    box = _el("extent", None, *(_el(k, text=repr(v)) for k, v in zip(("xmin", "ymin", "xmax", "ymax"), extent)))
    root.append(
        _el(
            "mapcanvas",
            {"name": "theMapCanvas", "annotationsVisible": 1},
            _el("units", text="meters"),
            box,
            _el("rotation", text="0"),
            _el("destinationsrs", None, _srs(crs_wkt, authid)),
        )
    )
    root.append(layers_xml)
    paths = _el("Paths", None, _el("Absolute", {"type": "bool"}, text="false"))
    # QGIS reads the project's CRS only where its projections are said to be on
    srs = _el("SpatialRefSys", None, _el("ProjectionsEnabled", {"type": "int"}, text="1"))
    root.append(_el("properties", None, paths, srs))
    return root


def _write_default_style(layer: _Layer) -> None:
    """A raster's style where QGIS looks for its default (``<name>.qml`` beside it), for the
    layer that is the raster's own look (a hillshade is the project's second view of a DEM)."""
    if layer.kind != "raster" or layer.blend_multiply or layer.pipe is None:
        return
    doc = _el(
        "qgis",
        {"version": QGIS_VERSION, "styleCategories": "AllStyleCategories"},
        layer.pipe,
        _el("blendMode", text="0"),
    )
    write_text(
        layer.path.with_suffix(".qml"),
        "<!DOCTYPE qgis PUBLIC 'http://mrcc.com/qgis.dtd' 'SYSTEM'>\n" + ET.tostring(doc, encoding="unicode") + "\n",
    )
