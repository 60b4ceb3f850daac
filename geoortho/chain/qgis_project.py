"""A run's products as one QGIS project, styled, and each product's style beside it.

``project.qgz`` (QGIS's own zipped ``.qgs`` XML, paths relative to it) holds every product of a
run as a layer, grouped and in a sensible order: the survey's vectors over the orthophoto, the
DSM and DTM coloured over their hillshades, the source rasters paletted with a legend. The
stages write each product's style where QGIS looks for a layer's default (:mod:`geoortho.core.styles`:
``<name>.qml`` beside a raster, ``layer_styles`` in a GeoPackage), so a product dragged into QGIS
alone looks the same; the project draws each layer with the same builders.
No QGIS is needed to write them: the XML is QGIS's documented project and style format.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from geoortho.core.outputs import atomic_path
from geoortho.core.styles import (
    QGIS_VERSION,
    difference,
    element,
    hillshade,
    overlap,
    product_renderer,
    rgba,
    terrain,
    write_raster_style,
)
from geoortho.elevation.coverage import source_style
from geoortho.orthophoto.provenance import how_style

__all__ = ["PROJECT_NAME", "write_qgis_project"]

PROJECT_NAME = "project.qgz"


@dataclass(frozen=True)
class _Layer:
    """One layer of the project: where it is (relative to the project), how it is drawn."""

    name: str
    path: Path  # absolute
    kind: str  # "raster", "vector", "pointcloud" (a COPC file: QGIS's own reader, no PDAL) or "tiledscene" (3D Tiles)
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
    for path, layer, geom, name in (
        (project / "gcp_residuals.gpkg", "residuals", "Line", "GCP residuals (exaggerated)"),
        (project / "gcp_residuals.gpkg", "gcps", "Point", "GCPs and checkpoints"),
        (project / "sfm" / "cameras.gpkg", "cameras", "Point", "cameras (SfM)"),
        (project / "gcp-find" / "detections.gpkg", "detections", "Point", "GCP detections"),
        (project / "footprints" / "footprints.gpkg", "footprints", "Polygon", "footprints"),
        (project / "ortho" / "ortho_seamlines.gpkg", "seamlines", "Polygon", "seamlines"),
        (project / "volume" / "volumes.gpkg", "volumes", "Polygon", "volumes (stockpiles, pits)"),
        (project / "change" / "change.gpkg", "change", "Polygon", "change: cut and fill areas"),
    ):
        if path.is_file():
            renderer = product_renderer(layer)
            visible = layer not in ("seamlines", "footprints")
            survey.append(_Layer(name, path, "vector", renderer=renderer, layer=layer, geometry=geom, visible=visible))
    ortho: list[_Layer] = []
    if (p := project / "change" / "change.tif").is_file():
        ortho.append(_Layer("change since the earlier survey (m)", p, "raster", pipe=difference(p)))
    if (p := project / "ortho" / "ortho.tif").is_file():
        ortho.append(_Layer("orthophoto", p, "raster", pipe=rgba()))
    if (p := project / "ortho" / "ortho_source.tif").is_file():
        ortho.insert(
            0,
            _Layer(
                "orthophoto: how each pixel was drawn",
                p,
                "raster",
                pipe=how_style(),
                visible=False,
            ),
        )
    surfaces: list[_Layer] = []
    if (p := project / "mesh" / "tileset" / "tileset.json").is_file():
        surfaces.append(_Layer("3D mesh (3D Tiles)", p, "tiledscene", visible=False))
    if (p := project / "dense" / "dense.copc.laz").is_file():
        surfaces.append(_Layer("dense cloud", p, "pointcloud", visible=False))
    if (p := project / "dem" / "contours.gpkg").is_file():
        surfaces.append(
            _Layer(
                "DTM contours",
                p,
                "vector",
                renderer=product_renderer("contours"),
                layer="contours",
                geometry="Line",
                visible=False,
            )
        )
    for name in ("dtm", "dsm"):
        if (p := project / "dem" / f"{name}.tif").is_file():
            label = name.upper()
            surfaces.append(
                _Layer(f"{label} hillshade", p, "raster", pipe=hillshade(), visible=False, blend_multiply=True)
            )
            surfaces.append(_Layer(label, p, "raster", pipe=terrain(p), visible=False))
    for name in ("dsm_source", "dtm_source"):
        if (p := project / "dem" / f"{name}.tif").is_file():
            surfaces.append(_Layer(name.replace("_", " "), p, "raster", pipe=source_style(), visible=False))
    if (p := project / "footprints" / "overlap.tif").is_file():
        surfaces.append(_Layer("overlap (photos a point)", p, "raster", pipe=overlap(p), visible=False))
    return [("Survey", survey), ("Orthophoto", ortho), ("Surfaces", surfaces)]


# ---------------------------------------------------------------------------------------------
# styles


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
        elif layer.kind == "vector":
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
    return element(
        "spatialrefsys", {"nativeFormat": "Wkt"}, element("wkt", text=crs_wkt), element("authid", text=authid)
    )


def _source(layer: _Layer, project: Path) -> str:
    rel = "./" + layer.path.relative_to(project).as_posix()
    return f"{rel}|layername={layer.layer}" if layer.kind == "vector" else rel


def _layer_id(layer: _Layer, index: int) -> str:
    return f"{layer.name.replace(' ', '_').replace(':', '')}_{index:02d}"


def _own_crs(layer: _Layer) -> tuple[str, str] | None:
    """A raster's own CRS where it says more than the map's (a DEM's heights' datum), 3D Tiles'
    (on the Earth's frame: QGIS gives them longitude, latitude and height), else None."""
    from pyproj import CRS

    if layer.kind == "tiledscene":
        return CRS.from_epsg(4979).to_wkt(), "EPSG:4979"
    if layer.kind != "raster":
        return None
    import rasterio

    with rasterio.open(layer.path) as ds:
        if ds.crs is None:
            return None
        crs = CRS.from_user_input(ds.crs.to_wkt())
    if not (crs.is_compound or len(crs.axis_info) == 3):
        return None
    from geoortho.core.crs import crs_to_text

    return crs.to_wkt(), crs_to_text(crs)


def _map_layer(layer: _Layer, lid: str, project: Path, crs_wkt: str, authid: str) -> ET.Element:
    kind = {"pointcloud": "point-cloud", "tiledscene": "tiled-scene"}.get(layer.kind, layer.kind)
    attrs = {"type": kind, "hasScaleBasedVisibilityFlag": 0}
    if layer.kind == "vector":
        attrs["geometry"] = layer.geometry
    e = element(
        "maplayer",
        attrs,
        element("id", text=lid),
        element("datasource", text=_source(layer, project)),
        element("layername", text=layer.name),
        element("srs", None, _srs(*(_own_crs(layer) or (crs_wkt, authid)))),
    )

    if layer.kind == "vector":
        e.append(element("provider", {"encoding": "UTF-8"}, text="ogr"))
        assert layer.renderer is not None
        e.append(layer.renderer)
    elif layer.kind == "pointcloud":
        e.append(element("provider", text="copc"))
        e.append(_cloud_colours())
    elif layer.kind == "tiledscene":
        e.append(element("provider", text="cesiumtiles"))
    else:
        e.append(element("provider", text="gdal"))
        assert layer.pipe is not None
        e.append(layer.pipe)
    e.append(element("blendMode", text="6" if layer.blend_multiply else "0"))  # Qgis::BlendMode: 6 multiply
    return e


def _cloud_colours() -> ET.Element:
    """A coloured cloud drawn in its own colours: LAS colours are 16-bit, stretched from 0-65535
    (without the stretch QGIS clips them at 255: a white cloud; without a renderer it draws only
    the cloud's outline)."""

    def stretch(band: str) -> ET.Element:
        return element(
            f"{band}ContrastEnhancement",
            None,
            element("minValue", text="0"),
            element("maxValue", text="65535"),
            element("algorithm", text="StretchToMinimumMaximum"),
        )

    attrs = {"type": "rgb", "red": "Red", "green": "Green", "blue": "Blue", "pointSize": 2, "pointSizeUnit": "Pixel"}
    return element("renderer", attrs, stretch("red"), stretch("green"), stretch("blue"))


def _project_xml(
    project: Path,
    groups: list[tuple[str, list[_Layer]]],
    crs_wkt: str,
    authid: str,
    extent: tuple[float, float, float, float],
) -> ET.Element:
    root = element("qgis", {"projectname": f"geoortho: {project.name}", "version": QGIS_VERSION})
    root.append(element("title", text=f"geoortho: {project.name}"))
    root.append(element("projectCrs", None, _srs(crs_wkt, authid)))
    tree = element("layer-tree-group", None, element("customproperties"))
    layers_xml = element("projectlayers")
    order = element("custom-order", {"enabled": 0})
    index = 0
    for group_name, layers in groups:
        if not layers:
            continue
        group = element("layer-tree-group", {"name": group_name, "checked": "Qt::Checked", "expanded": 1})
        for layer in layers:
            lid = _layer_id(layer, index)
            index += 1
            checked = "Qt::Checked" if layer.visible else "Qt::Unchecked"
            provider = {"vector": "ogr", "pointcloud": "copc", "tiledscene": "cesiumtiles"}.get(layer.kind, "gdal")
            group.append(
                element(
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
            order.append(element("item", text=lid))
        tree.append(group)
    tree.append(order)
    root.append(tree)
    xmin, ymin, xmax, ymax = extent
    box = element("extent", None, *(element(k, text=repr(v)) for k, v in zip(("xmin", "ymin", "xmax", "ymax"), extent)))
    root.append(
        element(
            "mapcanvas",
            {"name": "theMapCanvas", "annotationsVisible": 1},
            element("units", text="meters"),
            box,
            element("rotation", text="0"),
            element("destinationsrs", None, _srs(crs_wkt, authid)),
        )
    )
    root.append(layers_xml)
    paths = element("Paths", None, element("Absolute", {"type": "bool"}, text="false"))
    # QGIS reads the project's CRS only where its projections are said to be on
    srs = element("SpatialRefSys", None, element("ProjectionsEnabled", {"type": "int"}, text="1"))
    root.append(element("properties", None, paths, srs))
    return root


def _write_default_style(layer: _Layer) -> None:
    """A raster's style where QGIS looks for its default (``<name>.qml`` beside it), for the
    layer that is the raster's own look (a hillshade is the project's second view of a DEM),
    when the stage that made it did not write it (products of an older geoortho)."""
    if layer.kind != "raster" or layer.blend_multiply or layer.pipe is None:
        return
    if not layer.path.with_suffix(".qml").is_file():
        write_raster_style(layer.path, layer.pipe)
