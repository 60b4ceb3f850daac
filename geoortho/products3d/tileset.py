"""The mesh as Cesium 3D Tiles with levels of detail: a quadtree whose leaves are the mesh's own
tiles (full detail, the orthophoto at its resolution up to :data:`TILE_TEXTURE_PX`) and whose
every level above joins four tiles of the level below and thins them to a quarter of their faces
(each tile then about as heavy to draw as any other), its texture a quarter as sharp, up to one
root tile.

A tile's geometric error is measured, not set: the 99th percentile of its heights' distance from
the DSM's full-resolution cells (walls included), which is what a viewer shows wrong when it
draws that tile instead of its children. The leaves' is 0.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np
from pyproj import CRS

from geoortho.core.crs import heights_label, heights_of, horizontal_of
from geoortho.core.outputs import atomic_path, json_text, work_folder
from geoortho.core.parallel import map_ordered
from geoortho.errors import DependencyError
from geoortho.feedback import Feedback
from geoortho.products3d.gltf import Part, encode_jpeg, glb_bytes
from geoortho.products3d.raster_mesh import TILE_CELLS, DsmGrid, TileMesh, draw_heights, merged_mesh, read_block
from geoortho.products3d.texture import ortho_texture, uv_of
from geoortho.products3d.tiles3d import LocalFrame, Tile, local_frame, tileset_json, to_local

#: A 3D tile's texture, at most this many pixels a side (what every viewer loads).
TILE_TEXTURE_PX = 2048
#: The share of a tile's cells whose error its geometric error leaves out (a spike, not a wall).
ERROR_PERCENTILE = 99.0

#: A level's tiles keep this share of the faces of the four they are made of.
LEVEL_SHARE = 0.25

#: A tile of the tree: its first DSM row and column, and its DSM cells a side / TILE_CELLS.
Key = tuple[int, int, int]


def write_tileset(
    path: Path,
    grid: DsmGrid,
    crs: CRS,
    leaves: list[TileMesh],
    leaf_jobs: list[tuple[DsmGrid, int, int, float]],
    ortho: Path,
    origin: tuple[float, float, float],
    workers: int,
    fb: Feedback,
) -> tuple[int, int]:
    """The tileset.json at ``path`` and its tiles in ``tiles/`` beside it; returns (tiles with
    content, levels). ``leaves`` are the mesh's tiles, made for ``leaf_jobs``; ``origin`` (x, y in
    the CRS, height in metres) the east-north-up frame's."""
    import rasterio

    from geoortho.core.surface import height_unit

    with rasterio.open(ortho) as o:
        ortho_cell = abs(o.transform.a)
    z_unit = height_unit(crs)[1]
    frame = local_frame(horizontal_of(crs), *origin)
    lift_m, lift_note = _ellipsoid_lift(crs, frame)

    levels: list[list[tuple[Key, TileMesh]]] = [[((r, c, 1), tm) for (_, r, c, _), tm in zip(leaf_jobs, leaves)]]
    step = 1
    while len(levels[-1]) > 1:
        step *= 2
        span = TILE_CELLS * step
        groups: dict[tuple[int, int], list[TileMesh]] = {}
        for (r, c, _), tm in levels[-1]:
            groups.setdefault((r // span * span, c // span * span), []).append(tm)
        keys = [(r, c, step) for r, c in groups]
        jobs = [(grid.x0 + c * grid.cell, grid.y0 - r * grid.cell, groups[(r, c)], LEVEL_SHARE) for r, c, _ in keys]
        merged = map_ordered(merged_mesh, jobs, workers=workers)
        levels.append([(k, TileMesh(v, f, 0.0, 0.0, 0.0, 0, 0)) for k, (v, f) in zip(keys, merged)])

    folder = path.parent
    folder.mkdir(parents=True, exist_ok=True)
    n_done, n_all = 0, sum(len(lv) for lv in levels)
    with work_folder(folder / "tiles") as tmp_name:
        tmp = Path(tmp_name)
        made: dict[tuple[int, int, int], Tile] = {}
        for depth, level in enumerate(levels):
            for key, tm in level:
                r, c, step = key
                tile = _write_tile(tmp, depth, key, tm, grid, crs, frame, z_unit, lift_m, ortho, ortho_cell)
                if depth > 0:  # its children: the tiles of the level below inside its cells
                    span = TILE_CELLS * step
                    kids = [t for (d, rr, cc), t in made.items() if d == depth - 1 and r <= rr < r + span
                            and c <= cc < c + span and (t.content is not None or t.children)]  # fmt: skip
                    tile.children = kids
                    for k in kids:  # a parent is never nearer the truth than its children
                        tile.lo, tile.hi = np.minimum(tile.lo, k.lo), np.maximum(tile.hi, k.hi)
                        tile.geometric_error = max(tile.geometric_error, k.geometric_error)
                made[(depth, r, c)] = tile
                n_done += 1
                fb.progress(n_done / n_all)
        root = made[(len(levels) - 1, 0, 0)]
        extras = {"crs": crs.to_string(), "heights": heights_label(heights_of(crs)), "ellipsoid_lift_m": lift_m,
                  "heights_note": lift_note}  # fmt: skip
        (tmp / "tileset.json").write_text(json_text(tileset_json(root, frame, extras), indent=1), encoding="utf-8")
        target = folder / "tiles"
        if target.exists():
            import shutil

            shutil.rmtree(target)
        os.replace(tmp / "tiles", target) if (tmp / "tiles").exists() else target.mkdir()
        with atomic_path(path) as out:
            os.replace(tmp / "tileset.json", out)
    n_content = sum(1 for t in made.values() if t.content is not None)
    return n_content, len(levels)


def _write_tile(
    folder: Path, depth: int, key: Key, tm: TileMesh, grid: DsmGrid, crs: CRS, frame: LocalFrame, z_unit: float,
    lift_m: float, ortho: Path, ortho_cell: float,
) -> Tile:  # fmt: skip
    """One tile's glTF (east, north, up in the tileset's frame) and its entry."""
    r, c, step = key
    if len(tm.faces) == 0:
        return Tile(None, np.array([np.inf] * 3), np.array([-np.inf] * 3), 0.0)
    half = grid.cell / 2  # the texture covers the tile's cells, whose centres are its vertices
    lo, hi = tm.vertices[:, :2].min(axis=0), tm.vertices[:, :2].max(axis=0)
    bounds = (lo[0] - half, lo[1] - half, hi[0] + half, hi[1] + half)
    texture, _ = ortho_texture(ortho, bounds, TILE_TEXTURE_PX, ortho_cell * step)
    xyz = tm.vertices * [1.0, 1.0, z_unit] + [0.0, 0.0, lift_m]
    enu = to_local(frame, horizontal_of(crs), xyz)
    name = f"tiles/{depth}/{r}_{c}.glb"
    (folder / name).parent.mkdir(parents=True, exist_ok=True)
    part = Part("ground", enu, tm.faces, uv_of(tm.vertices, bounds), encode_jpeg(texture))
    (folder / name).write_bytes(glb_bytes([part], {"level": depth}))
    error = 0.0 if step == 1 else _geometric_error(tm, grid, r, c, TILE_CELLS * step + 1) * z_unit
    return Tile(name, enu.min(axis=0), enu.max(axis=0), error)


def _geometric_error(tm: TileMesh, grid: DsmGrid, r: int, c: int, size: int) -> float:
    """The coarse tile's heights against the DSM's own cells (the 99th percentile of the distance)."""
    z = read_block(grid, r, c, size)
    x0, y0 = grid.x0 + c * grid.cell, grid.y0 - r * grid.cell
    drawn = draw_heights(tm.vertices, tm.faces, x0, y0, grid.cell, z.shape[0], z.shape[1])
    d = np.abs(drawn - z)
    d = d[np.isfinite(d)]
    return float(np.percentile(d, ERROR_PERCENTILE)) if d.size else 0.0


def _ellipsoid_lift(crs: CRS, frame: LocalFrame) -> tuple[float, str]:
    """What to add to the DSM's heights for heights above the ellipsoid (the Earth frame's): the
    EGM96 geoid's height at the site where they are a vertical datum's, else nothing."""
    heights: Any = heights_of(crs)
    if heights is None or isinstance(heights, str):
        return 0.0, "heights taken as above the ellipsoid" if heights is None else "ellipsoidal heights"
    try:
        from geoortho.core.crs import geoid_undulation_m

        n = float(geoid_undulation_m(frame.lon_deg, frame.lat_deg))
    except DependencyError:
        return 0.0, f"{heights.name} heights taken as above the ellipsoid (no geoid grid here)"
    return n, f"{heights.name} heights raised by the EGM96 geoid's {n:.2f} m at the site"
