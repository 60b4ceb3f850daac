"""``mesh``: a 2.5D textured mesh of the site from the DSM and the orthophoto, as glTF binary, as
OBJ+MTL and as Cesium 3D Tiles with levels of detail (which QGIS opens as a tiled scene layer).

The surface is :mod:`.raster_mesh`'s: the DSM's cells thinned by quadric edge collapse, a tile at
a time, until each tile is within the error asked of the DSM (measured, and stated). The texture
is the orthophoto: each ground cell already coloured by the photo that sees it most directly,
with line of sight tested, colour-balanced, its seamlines on open ground. The orthophoto sees a
wall edge-on: given the sfm and the photos, the walls are coloured from the photos on an atlas of
their own (:mod:`.walls`); without them, and in the 3D Tiles, they take the colours of their
tops' and feet's edges.

Choices of library: ``fast-simplification`` (quadric collapse with the border held, so tiles
meet with no crack), ``pygltflib`` (a glTF binary as the spec lays it out: unlit, JPEG inside),
pyproj (the tiles' Earth frame); the OBJ is written here (:mod:`.gltf` says why); no ``xatlas``:
see :mod:`.walls`; no ``py3dtiles``: see :mod:`.tiles3d`.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from geoortho.core.crs import crs_to_text, heights_label, heights_of, horizontal_unit_m
from geoortho.core.outputs import remove_stale_temporaries, write_json, write_png
from geoortho.core.parallel import map_ordered
from geoortho.errors import InputError, ParameterError
from geoortho.feedback import Feedback, as_feedback, split
from geoortho.products3d.raster_mesh import TILE_CELLS, DsmGrid, TileMesh, mesh_tile, used_vertices
from geoortho.products3d.texture import Bounds, ortho_texture, uv_of
from geoortho.products3d.tileset import write_tileset
from geoortho.products3d.walls import WallTexture, ortho_gains, photo_walls, wall_mask, wall_summary

__all__ = ["MeshResult", "mesh"]


@dataclass(frozen=True)
class MeshResult:
    """The mesh made.

    Attributes
    ----------
    output : Path
        The glTF binary (local frame: x east, y up, z south, metres from ``offset``).
    obj : Path | None
        The OBJ (east, north, up from ``offset``), with its .mtl and .jpg beside it.
    tileset : Path | None
        The 3D Tiles' tileset.json.
    view : Path | None
        The oblique picture (PNG).
    georeference : Path
        The JSON beside the glTF that states its CRS and offset.
    n_faces : int
        Faces of the whole mesh.
    n_vertices : int
        Its vertices (a tile's border vertices once for each tile).
    rmse_m : float
        The mesh's heights against the DSM's, over every DSM cell with a height (metres).
    max_error_m : float
        The largest of those differences (at a wall, where the mesh's slope is one cell wide).
    max_rmse_m : float
        The error asked (each tile's RMSE is at most this).
    faces_per_ha : float
        Faces per hectare of the DSM's cells with a height.
    mb_per_ha : float
        The glTF binary's megabytes per hectare.
    texture_px : tuple[int, int]
        The glTF's texture, width and height.
    texture_cell_m : float
        Ground size of a texture pixel.
    offset : tuple[float, float, float]
        The local frame's origin in the CRS (x, y, z).
    n_tiles : int
        The 3D Tiles' tiles with content (0 without a tileset).
    n_levels : int
        Their levels of detail.
    wall_faces : int
        Faces steeper than 60 degrees on the walls' own atlas, coloured from the photos (0 without
        ``sfm`` and ``images``: the walls then take the orthophoto's colours).
    wall_photo_share : float
        The share of those faces' area a photo sees (the rest: the orthophoto's colours); NaN
        without them.
    crs : str
        CRS of the mesh's offset and of the DSM.
    seconds : float
        Time taken.
    """

    output: Path
    obj: Path | None
    tileset: Path | None
    view: Path | None
    georeference: Path
    n_faces: int
    n_vertices: int
    rmse_m: float
    max_error_m: float
    max_rmse_m: float
    faces_per_ha: float
    mb_per_ha: float
    texture_px: tuple[int, int]
    texture_cell_m: float
    offset: tuple[float, float, float]
    n_tiles: int
    n_levels: int
    wall_faces: int
    wall_photo_share: float
    crs: str
    seconds: float


def mesh(
    dsm: Path,
    ortho: Path,
    output: Path,
    *,
    obj: Path | None = None,
    tileset: Path | None = None,
    view: Path | None = None,
    max_error_m: float | None = None,
    texture_max_px: int = 8192,
    sfm: Path | None = None,
    images: Path | None = None,
    workers: int = 0,
    feedback: Feedback | None = None,
) -> MeshResult:
    """A textured 2.5D mesh of the DSM, coloured by the orthophoto.

    Parameters
    ----------
    dsm : Path
        The surface (GeoTIFF, north up, square cells).
    ortho : Path
        The orthophoto that colours it (same CRS; any resolution).
    output : Path
        The glTF binary (.glb); a JSON with its CRS and offset is written beside it.
    obj : Path
        Also an OBJ (with its .mtl and .jpg).
    tileset : Path
        Also Cesium 3D Tiles: the tileset.json (its tiles in a folder beside it).
    view : Path
        Also an oblique picture of the mesh (PNG).
    max_error_m : float
        Each tile's mesh within this RMSE of the DSM (metres; default one DSM cell: a photogrammetric
        DSM's noise on roofs is about that, and a mesh that follows it is twice as heavy).
    texture_max_px : int
        The glTF's texture at most this many pixels a side (default 8192: what web viewers load).
    sfm : Path
        The sfm output whose cameras took ``images``: with both, the walls (faces steeper than 60
        degrees, which the orthophoto sees edge-on) are coloured from the photos that see them
        most directly, on an atlas of their own; without, they take the orthophoto's colours at
        their tops and feet.
    images : Path
        The photos' folder.
    workers : int
        Processes for the tiles (0: one per core).
    """
    import rasterio

    fb = as_feedback(feedback)
    started = time.perf_counter()
    output = Path(output)
    if output.suffix.lower() != ".glb":
        raise ParameterError("output", f"{output}: the mesh is written as glTF binary (.glb)")
    if tileset is not None and Path(tileset).name.lower() != "tileset.json":
        raise ParameterError("tileset", f"{tileset}: a 3D Tiles tileset is named tileset.json")
    from pyproj import CRS

    from geoortho.core.crs import horizontal_of
    from geoortho.core.surface import height_unit, refuse_unless_north_up

    with rasterio.open(dsm) as ds:
        if ds.crs is None:
            raise InputError("the DSM has no CRS: a mesh must say where it is", path=dsm)
        t = ds.transform
        refuse_unless_north_up(t, dsm)
        crs = CRS.from_user_input(ds.crs)
        grid = DsmGrid(str(dsm), t.c + t.a / 2, t.f + t.e / 2, t.a, ds.height, ds.width)
    with rasterio.open(ortho) as o:
        if o.crs is None or horizontal_of(CRS.from_user_input(o.crs)) != horizontal_of(crs):
            raise InputError(f"the orthophoto's CRS is not the DSM's ({crs_to_text(crs)})", path=ortho)
        ortho_cell = abs(o.transform.a)
    unit_m = horizontal_unit_m(crs)
    max_rmse = (max_error_m / unit_m) if max_error_m else grid.cell
    if max_rmse <= 0:
        raise ParameterError("max_error_m", "the mesh's error must be more than 0")

    fb.info(f"meshing {grid.rows} x {grid.cols} cells, {TILE_CELLS} a tile (RMSE at most {max_rmse * unit_m:.3g} m)")
    jobs = [(grid, r, c, max_rmse) for r in range(0, max(grid.rows - 1, 1), TILE_CELLS)
            for c in range(0, max(grid.cols - 1, 1), TILE_CELLS)]  # fmt: skip
    fb_tiles, fb_set = split(fb, [1.0, 1.0 if tileset is not None else 0.0])
    tiles = map_ordered(mesh_tile, jobs, workers=workers, feedback=fb_tiles)
    sq = sum(tm.error_sq_sum for tm in tiles)
    n_cells = sum(tm.n_cells for tm in tiles)
    if n_cells == 0:
        raise InputError("the DSM has no heights", path=dsm)
    verts, faces = _joined(tiles)
    rmse = math.sqrt(sq / n_cells) * unit_m
    max_err = max(tm.max_error for tm in tiles) * unit_m

    vmin, vmax = verts.min(axis=0), verts.max(axis=0)
    offset = (round(float((vmin[0] + vmax[0]) / 2)), round(float((vmin[1] + vmax[1]) / 2)),
              round(float(np.median(verts[:, 2]))))  # fmt: skip
    bounds = (vmin[0] - grid.cell / 2, vmin[1] - grid.cell / 2, vmax[0] + grid.cell / 2, vmax[1] + grid.cell / 2)
    texture, texture_cell = ortho_texture(ortho, bounds, texture_max_px, ortho_cell)
    z_unit = height_unit(crs)[1]
    scale = np.array([unit_m, unit_m, z_unit])
    walls = None
    ground = faces
    if sfm is not None and images is not None:
        walls, ground = _photo_walls(verts, faces, scale, Path(sfm), Path(images), dsm, crs, ortho,
                                     texture_cell, texture_max_px, (texture, bounds), fb)  # fmt: skip
    from geoortho.products3d.gltf import Part, encode_jpeg, write_glb, write_obj

    gv, gf = used_vertices(verts, ground)
    parts = [Part("ground", (gv - offset) * scale, gf, uv_of(gv, bounds), encode_jpeg(texture))]
    if walls is not None:
        parts.append(Part("walls", (walls.vertices - offset) * scale, walls.faces, walls.uv, encode_jpeg(walls.image)))

    remove_stale_temporaries(output.parent)
    georef = _georeference(crs, offset, unit_m, z_unit)
    write_glb(output, parts, georef)
    georef_path = write_json(output.with_name(output.stem + "_georeference.json"), georef)
    if obj is not None:
        write_obj(Path(obj), parts, _obj_header(georef))

    n_tiles = n_levels = 0
    if tileset is not None:
        origin = (offset[0], offset[1], offset[2] * z_unit)  # the glTF's offset: the tiles' frame too
        n_tiles, n_levels = write_tileset(Path(tileset), grid, crs, tiles, jobs, ortho, origin, workers, fb_set)
    if view is not None:
        from geoortho.products3d.view import render_oblique

        textures = [texture] + ([walls.image] if walls is not None else [])
        write_png(Path(view), render_oblique(parts, textures)[:, :, ::-1])  # RGB to OpenCV's BGR
    fb.progress(1.0)
    area_ha = n_cells * (grid.cell * unit_m) ** 2 / 1e4
    size_mb = output.stat().st_size / 1e6
    fb.info(
        f"{len(faces):,} faces ({len(faces) / area_ha:,.0f} a hectare, {size_mb / area_ha:.2f} MB a hectare), "
        f"RMSE {rmse:.3f} m against the DSM (max {max_err:.2f} m); texture {texture.shape[1]} x "
        f"{texture.shape[0]} px at {texture_cell * unit_m:.3g} m: {output.name}"
    )
    return MeshResult(
        output, Path(obj) if obj is not None else None, Path(tileset) if tileset is not None else None,
        Path(view) if view is not None else None, georef_path, len(faces), sum(len(p.enu) for p in parts), rmse,
        max_err,
        max_rmse * unit_m, len(faces) / area_ha, size_mb / area_ha, (texture.shape[1], texture.shape[0]),
        texture_cell * unit_m, offset, n_tiles, n_levels, *wall_summary(walls), crs_to_text(crs),
        time.perf_counter() - started,
    )  # fmt: skip


def _photo_walls(
    verts: np.ndarray,
    faces: np.ndarray,
    scale: np.ndarray,
    sfm: Path,
    images: Path,
    dsm: Path,
    crs: Any,
    ortho: Path,
    texel: float,
    max_px: int,
    fallback: tuple[np.ndarray, Bounds],
    fb: Feedback,
) -> tuple[WallTexture | None, np.ndarray]:
    """The walls on their own atlas coloured from the photos, and the faces left to the orthophoto."""
    from geoortho.core.sfm_model import cameras_from_sfm
    from geoortho.core.surface import read_surface

    wall = wall_mask(verts * scale, faces)
    if not wall.any():
        return None, faces
    if np.any(scale != 1.0):
        # the cameras are posed in metres: a DSM in feet keeps the orthophoto's colours on its walls
        fb.info("walls: the DSM is not in metres; they take the orthophoto's colours")
        return None, faces
    cams, _, _, _ = cameras_from_sfm(sfm, images, crs)
    surface = read_surface(dsm, crs)
    walls = photo_walls(verts, faces[wall], cams, surface, ortho_gains(ortho), texel, max_px, fallback)
    if walls is not None:
        fb.info(
            f"walls: {len(walls.faces):,} faces, {walls.area_m2:,.0f} m², {walls.photo_area_m2 / walls.area_m2:.0%} "
            f"of it coloured from {walls.n_photos} photos ({walls.image.shape[1]} x {walls.image.shape[0]} px at "
            f"{walls.texel_m:.3g} m), the rest from the orthophoto"
        )
    return walls, faces[~wall]


def _joined(tiles: list[TileMesh]) -> tuple[np.ndarray, np.ndarray]:
    """The tiles' meshes as one (their shared border vertices are kept twice: they are the same
    points, so the surface is whole)."""
    verts, faces, base = [], [], 0
    for tm in tiles:
        verts.append(tm.vertices)
        faces.append(tm.faces + base)
        base += len(tm.vertices)
    return np.concatenate(verts), np.concatenate(faces).astype(np.int32)


def _georeference(crs: Any, offset: tuple[float, float, float], unit_m: float, z_unit_m: float) -> dict[str, Any]:
    """What a reader needs to put the mesh back on the map."""
    return {
        "crs": crs_to_text(crs),
        "crs_wkt": crs.to_wkt(),
        "heights": heights_label(heights_of(crs)),
        "offset": list(offset),
        "offset_units": "the CRS's",
        "units": "metre",
        "axes": {"glb": "x east, y up, z south (glTF)", "obj": "x east, y north, z up"},
        "to_crs": f"x_crs = offset_x + east / {unit_m:.10g}; y_crs = offset_y + north / {unit_m:.10g}; "
        f"z = offset_z + up / {z_unit_m:.10g}",
    }


def _obj_header(georef: dict[str, Any]) -> str:
    x, y, z = georef["offset"]
    return (
        f"geoortho mesh: x east, y north, z up, metres from the offset\n"
        f"CRS: {georef['crs']}\noffset: {x} {y} {z}\nheights: {georef['heights']}"
    )
