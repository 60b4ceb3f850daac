"""Atomic writers: every product is written to a temporary name beside its
target and renamed when complete, so an interrupted run leaves no half file.

This module owns raster (COG) and vector writing.
"""

from __future__ import annotations

import contextlib
import glob
import json
import os
import re
import tempfile
import warnings
from collections.abc import Callable, Iterator
from contextlib import closing
from pathlib import Path
from typing import Any

import numpy as np

from geoortho.errors import InputError

__all__ = [
    "atomic_path",
    "atomic_paths",
    "temp_prefix",
    "remove_stale_temporaries",
    "write_cog",
    "write_vector",
    "write_layer_styles",
    "write_text",
    "write_json",
    "write_png",
    "json_text",
    "strict",
    "VECTOR_DRIVERS",
    "work_folder",
    "append_by_tile",
]


@contextlib.contextmanager
def atomic_path(target: str | os.PathLike[str]) -> Iterator[Path]:
    """Yield a temporary path beside ``target``; rename it onto ``target`` on success.

    The temporary name keeps the extension so that drivers chosen by extension
    (GDAL, OGR) still work. On any exception the temporary file is removed.
    """
    target = Path(target)
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp_name = tempfile.mkstemp(prefix=temp_prefix(target.stem), suffix=target.suffix, dir=target.parent)
    os.close(fd)
    tmp = Path(tmp_name)
    tmp.unlink()  # let the writer create it (some drivers refuse an existing file)
    try:
        yield tmp
        if not tmp.exists():
            raise RuntimeError(f"writer produced no file for {target}")
        # Multi-file formats (Shapefile: .dbf .shx .prj .cpg; ENVI .hdr; ...) write sidecars named
        # like the temporary file: each moves to the final name with it, before the main file.
        for side in _sidecars(tmp):
            if not side.name.endswith(".aux.xml"):  # GDAL's statistics cache stays behind (removed)
                os.replace(side, target.with_name(target.stem + side.name[len(tmp.stem) :]))
        os.replace(tmp, target)
    finally:
        for leftover in [tmp, *_sidecars(tmp)]:
            if leftover.exists():
                leftover.unlink()


@contextlib.contextmanager
def atomic_paths(*targets: str | os.PathLike[str] | None, commit_check: Any = None) -> Iterator[list[Path | None]]:
    """Temporaries for several products that appear together or not at all: ``commit_check``
    (e.g. a feedback's ``check_canceled``) runs after the last is written and before the first
    rename, so a run canceled while writing leaves none of them. None targets stay None."""
    with contextlib.ExitStack() as stack:
        temps = [stack.enter_context(atomic_path(t)) if t is not None else None for t in targets]
        yield temps
        if commit_check is not None:
            commit_check()


def _sidecars(tmp: Path) -> list[Path]:
    """Files beside ``tmp`` named ``<tmp stem>.<anything>`` other than ``tmp`` itself."""
    return [p for p in tmp.parent.glob(glob.escape(tmp.stem) + ".*") if p != tmp and p.is_file()]


def temp_prefix(name: str) -> str:
    """The name start of every temporary geoortho writes beside a product: hidden, and carrying the
    writer's pid so that the next run can tell a dead run's leftovers from a live run's work."""
    return f".{name}.tmp-{os.getpid()}-"


_TEMP = re.compile(r"^\..+\.tmp-(\d+)-")


def remove_stale_temporaries(folder: str | os.PathLike[str]) -> list[Path]:
    """Remove the temporaries (files and folders) in ``folder`` left by runs whose process is gone
    (killed, or the machine stopped); a live run's are kept."""
    import shutil

    removed: list[Path] = []
    folder = Path(folder)
    if not folder.is_dir():
        return removed
    for p in folder.glob(".*.tmp-*"):
        m = _TEMP.match(p.name)
        if m is None or _alive(int(m.group(1))):
            continue
        try:
            shutil.rmtree(p) if p.is_dir() and not p.is_symlink() else p.unlink()
            removed.append(p)
        except OSError:
            pass
    return removed


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OverflowError):
        return True
    return True


def write_text(target: str | os.PathLike[str], text: str) -> Path:
    with atomic_path(target) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return Path(target)


def write_json(target: str | os.PathLike[str], obj: Any) -> Path:
    return write_text(target, json_text(obj, indent=2) + "\n")


def write_png(target: str | os.PathLike[str], image: np.ndarray) -> Path:
    """An image (grey, BGR or BGRA: OpenCV's order) as PNG, atomically."""
    import cv2

    ok, buf = cv2.imencode(".png", np.ascontiguousarray(image))
    if not ok:
        raise InputError("cannot encode the image as PNG", path=Path(target))
    with atomic_path(target) as tmp:
        tmp.write_bytes(buf.tobytes())
    return Path(target)


def json_text(obj: Any, indent: int | None = None, sort_keys: bool = False) -> str:
    """``obj`` as strict JSON (RFC 8259): what was not measured (NaN) or has no bound (infinity) is
    ``null``, numpy values are plain numbers and lists, paths are strings. Python's own ``json``
    writes bare ``NaN``, which JavaScript's ``JSON.parse`` and other strict readers refuse."""
    return json.dumps(strict(obj), indent=indent, sort_keys=sort_keys, allow_nan=False)


def strict(obj: Any) -> Any:
    """``obj`` with every non-finite float as None, numpy values as Python's, paths as strings."""
    if isinstance(obj, dict):
        return {str(k) if isinstance(k, Path) else k: strict(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [strict(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return strict(obj.tolist())
    if isinstance(obj, np.generic):
        obj = obj.item()
    if isinstance(obj, float):
        return obj if np.isfinite(obj) else None
    if isinstance(obj, Path):
        return str(obj)
    if isinstance(obj, (str, int, bool)) or obj is None:
        return obj
    raise TypeError(f"not JSON serialisable: {type(obj).__name__}")


def write_cog(
    target: str | os.PathLike[str],
    array: np.ndarray,
    *,
    transform: Any,
    crs: Any,
    nodata: float | None = None,
    compress: str = "DEFLATE",
    alpha: np.ndarray | None = None,
    band_names: tuple[str, ...] = (),
    overview_resampling: str | None = None,
    units: str = "",
) -> Path:
    """Write a (bands, rows, cols) or (rows, cols) array as a Cloud-Optimized GeoTIFF.

    Float rasters get the floating-point predictor; ``alpha`` (uint8, 0/255)
    is added as a last band flagged as alpha.
    """
    from rasterio.enums import ColorInterp
    from rasterio.io import MemoryFile
    from rasterio.shutil import copy as rio_copy

    data = array[np.newaxis] if array.ndim == 2 else array
    if alpha is not None:
        data = np.concatenate([data, alpha[np.newaxis].astype(data.dtype)], axis=0)
    count, rows, cols = data.shape
    is_float = np.issubdtype(data.dtype, np.floating)
    profile = {
        "driver": "GTiff",
        "width": cols,
        "height": rows,
        "count": count,
        "dtype": data.dtype.name,
        "crs": crs,
        "transform": transform,
    }
    if nodata is not None:
        profile["nodata"] = nodata
    with MemoryFile() as mem:
        with mem.open(**profile) as ds:
            ds.write(data)
            if alpha is not None:
                interp = (
                    [ColorInterp.red, ColorInterp.green, ColorInterp.blue][: count - 1]
                    if count == 4
                    else [ColorInterp.gray] * (count - 1)
                )
                ds.colorinterp = [*interp, ColorInterp.alpha]
            for i, name in enumerate(band_names, 1):
                ds.set_band_description(i, name)
            if units:
                for i in range(1, count + 1):
                    ds.set_band_unit(i, units)
        with mem.open() as src, atomic_path(target) as tmp:
            rio_copy(src, tmp, driver="COG", **cog_options(compress, is_float, overview_resampling))
    return Path(target)


def cog_options(compress: str, is_float: bool, overview_resampling: str | None = None) -> dict[str, Any]:
    """GDAL COG driver options for a raster: the floating-point predictor for floats, overviews by
    average (by nearest for floats: elevations are not to be blended)."""
    options: dict[str, Any] = {
        "compress": compress,
        "overview_resampling": overview_resampling or ("average" if not is_float else "nearest"),
        "BIGTIFF": "IF_SAFER",
    }
    if compress.upper() in ("DEFLATE", "LZW", "ZSTD"):
        options["predictor"] = 3 if is_float else 2
    return options


#: OGR driver by file extension.
VECTOR_DRIVERS = {
    ".gpkg": "GPKG",
    ".geojson": "GeoJSON",
    ".json": "GeoJSON",
    ".shp": "ESRI Shapefile",
    ".fgb": "FlatGeobuf",
    ".csv": "CSV",
    ".kml": "KML",
    ".gml": "GML",
}


def write_layer_styles(gpkg: str | os.PathLike[str], styles: dict[str, str]) -> None:
    """Each layer's style (layer name → QGIS style document) as its default, in the GeoPackage's
    ``layer_styles`` table, where QGIS looks when the layer is opened alone (the table, columns
    and registration QGIS itself writes with "Save as default"). Plain SQLite: the file is a
    GeoPackage already written, and its styles need no GDAL."""
    import sqlite3

    with closing(sqlite3.connect(os.fspath(gpkg))) as con, con:
        con.execute(
            "CREATE TABLE IF NOT EXISTS layer_styles (id INTEGER PRIMARY KEY AUTOINCREMENT, "
            "f_table_catalog TEXT(256), f_table_schema TEXT(256), f_table_name TEXT(256), "
            "f_geometry_column TEXT(256), styleName TEXT(30), styleQML TEXT, styleSLD TEXT, "
            "useAsDefault BOOLEAN, description TEXT, owner TEXT(30), ui TEXT(30), "
            "update_time DATETIME DEFAULT (strftime('%Y-%m-%dT%H:%M:%fZ','now')))"
        )
        con.execute(
            "INSERT OR IGNORE INTO gpkg_contents (table_name, data_type, identifier, last_change) "
            "VALUES ('layer_styles', 'attributes', 'layer_styles', strftime('%Y-%m-%dT%H:%M:%fZ','now'))"
        )
        geometry = dict(con.execute("SELECT table_name, column_name FROM gpkg_geometry_columns").fetchall())
        for name, qml in styles.items():
            con.execute("DELETE FROM layer_styles WHERE f_table_name = ? AND styleName = ?", (name, name))
            con.execute(
                "INSERT INTO layer_styles (f_table_catalog, f_table_schema, f_table_name, f_geometry_column, "
                "styleName, styleQML, styleSLD, useAsDefault, description, owner, ui) "
                "VALUES ('', '', ?, ?, ?, ?, '', 1, ?, '', '')",
                (name, geometry.get(name, "geom"), name, qml, "geoortho's style of this product"),
            )


def write_vector(
    target: str | os.PathLike[str],
    layers: dict[str, Any],
    styles: dict[str, str] | None = None,
    empty_as: dict[str, str] | None = None,
) -> Path:
    """Write one or more GeoDataFrames (layer name → frame) atomically.

    The format follows the extension; several layers need a multi-layer format
    (GeoPackage). ``styles`` (layer name → QGIS style document) go into a GeoPackage as the layers'
    default styles (:func:`write_layer_styles`); other formats have no place for them.
    ``empty_as`` (layer name → geometry type): a layer with no feature gets this type, not
    "Unknown", which QGIS opens with no renderer (its style unused).
    """
    target = Path(target)
    driver = VECTOR_DRIVERS.get(target.suffix.lower())
    if driver is None:
        raise InputError(
            f"unknown vector format {target.suffix!r}; use one of {', '.join(sorted(VECTOR_DRIVERS))}",
            path=target,
        )
    with atomic_path(target) as tmp:
        for i, (name, frame) in enumerate(layers.items()):
            if driver != "GPKG" and i > 0:
                break  # single-layer formats keep the first (main) layer
            kwargs: dict[str, Any] = {"driver": driver, "engine": "pyogrio"}
            if driver in ("GPKG", "KML", "GML", "GeoJSON", "FlatGeobuf"):
                kwargs["layer"] = name  # else the layer is named after the temporary file
            if driver == "CSV":
                kwargs["GEOMETRY"] = "AS_WKT"  # the CSV driver writes no geometry otherwise
            if i > 0:
                kwargs["mode"] = "a"
            if not len(frame) and empty_as and name in empty_as:
                kwargs["geometry_type"] = empty_as[name]
            with warnings.catch_warnings():
                # Shapefile: field names are cut to 10 characters, as the format has it; said once
                # per field by geopandas and by pyogrio, to stderr, it is noise
                warnings.filterwarnings("ignore", message=".*(Column names longer|laundered field name)")
                frame.to_file(tmp, **kwargs)
        if styles and driver == "GPKG":
            write_layer_styles(tmp, {k: v for k, v in styles.items() if k in layers})
    return target


def work_folder(near: Path) -> tempfile.TemporaryDirectory[str]:
    """A temporary folder for the tile files beside the output (the same disk as the products),
    named as every geoortho temporary is, so that a killed run's is removed by the next run. The
    output's folder is made first, as the whole-grid path's writes make it (a new folder ended a
    tiled dem in an unexpected FileNotFoundError)."""
    parent = Path(near).absolute().parent
    parent.mkdir(parents=True, exist_ok=True)
    return tempfile.TemporaryDirectory(prefix=temp_prefix(Path(near).name), dir=parent)


def append_by_tile(rows: np.ndarray, tile: np.ndarray, file_of: Callable[[int], Path]) -> None:
    """Append each row to the file of its tile (``tile``: an integer per row), one write a tile."""
    order = np.argsort(tile, kind="stable")
    tile, rows = tile[order], rows[order]
    cuts = np.flatnonzero(np.diff(tile)) + 1
    for part, k in zip(np.split(rows, cuts), tile[np.r_[0, cuts]] if len(tile) else []):
        with open(file_of(int(k)), "ab") as fh:
            part.tofile(fh)
