"""A 2.5D triangle mesh from a DSM, a tile at a time: dense where the surface bends, sparse where
it is flat, with its height error against the DSM measured, not assumed.

Each tile's cells become a regular grid of vertices (one per cell centre, two triangles per
square of four valid cells), which quadric edge collapse (``fast-simplification``) thins with
the tile's border held: neighbouring tiles keep the same border vertices, so the tiles join with
no crack and a site-wide mesh is their union. A tile is thinned to a face count, not an error;
the count is raised until the tile's mesh, drawn back onto the DSM's cells, is within the error
asked (RMSE) of the DSM: flat ground ends with a few faces, a roof's edge keeps its vertices.

A wall is as steep as the DSM's edge: the two vertices either side of it are one cell apart.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from geoortho.core.kernels import compiled

#: A tile's cells a side (the mesh is made, and the 3D Tiles' finest level cut, a tile at a time).
TILE_CELLS = 256
#: A tile's mesh starts at this share of its grid's faces (about what its border alone keeps) ...
START_SHARE = 0.02
#: ... and, where that is not within the error, raised by what the error predicts (error / asked,
#: at least twice): on the demo survey's DSM, 0.50 M faces in 13.7 s, where raising by three each
#: time gave 0.66 M in 15 s and by the error squared 0.60 M in 14.2 s.
MIN_RAISE = 2.0


#: Quadric collapse's aggressiveness (fast-simplification's default: quality against speed).
AGGRESSIVENESS = 7.0


@dataclass(frozen=True)
class DsmGrid:
    """A north-up DSM's grid: the file, its first cell centre, cell size, shape (the CRS's units)."""

    path: str
    x0: float
    y0: float
    cell: float
    rows: int
    cols: int


@dataclass(frozen=True)
class TileMesh:
    """One tile's thinned mesh, in the DSM's CRS (metres or the CRS's units, heights as the DSM's).

    ``error_sq_sum`` and ``n_cells`` let a site's RMSE be summed over its tiles."""

    vertices: np.ndarray  # (n, 3) float64: x, y, z
    faces: np.ndarray  # (m, 3) int32
    rmse: float  # against the DSM's valid cells in the tile
    max_error: float
    error_sq_sum: float
    n_cells: int
    n_grid_faces: int  # before thinning


def grid_faces(z: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Two triangles per square of four valid cell centres (vertex i = row * cols + col),
    counter-clockwise seen from above, split along the diagonal of least height difference: a
    roof's edge at 45 degrees then follows the cells instead of a sawtooth across them."""
    rows, cols = valid.shape
    if rows < 2 or cols < 2:
        return np.zeros((0, 3), np.int32)
    idx = np.arange(rows * cols, dtype=np.int32).reshape(rows, cols)
    ok = valid[:-1, :-1] & valid[:-1, 1:] & valid[1:, :-1] & valid[1:, 1:]
    a, b, c, d = idx[:-1, :-1][ok], idx[:-1, 1:][ok], idx[1:, :-1][ok], idx[1:, 1:][ok]
    zf = np.where(valid, z, 0.0).ravel()
    ad = (np.abs(zf[a] - zf[d]) < np.abs(zf[b] - zf[c]))[:, None]  # a-d the flatter diagonal
    f1 = np.where(ad, np.stack([a, c, d], 1), np.stack([a, c, b], 1))
    f2 = np.where(ad, np.stack([a, d, b], 1), np.stack([b, c, d], 1))
    return np.concatenate([f1, f2]).astype(np.int32)


def tile_mesh(
    z: np.ndarray,
    x0: float,
    y0: float,
    cell: float,
    max_rmse: float,
) -> TileMesh:
    """The thinned mesh of one tile of a north-up DSM: ``z`` (rows, cols) float with NaN where it
    has no height, its first cell centre at (``x0``, ``y0``), square cells of ``cell``.

    The face count is raised (from :data:`START_SHARE` of the grid's, as the error measured
    predicts: :data:`MIN_RAISE`) until the mesh is within ``max_rmse`` of the DSM over the tile's
    valid cells; the tile's border vertices are kept as they are."""
    import fast_simplification

    rows, cols = z.shape
    valid = np.isfinite(z)
    full = grid_faces(z, valid)
    cc, rr = np.meshgrid(np.arange(cols), np.arange(rows))
    # in the tile's own frame: quadrics of map coordinates (millions of metres) lose the precision to
    # tell a flat tile from a bent one (a tile of the tiny survey kept 10 times the faces)
    verts = np.stack([cc.ravel() * cell, -rr.ravel() * cell, np.where(valid, z, 0.0).ravel()], axis=1)
    n_cells = int(valid.sum())
    if len(full) == 0:
        return TileMesh(np.zeros((0, 3)), np.zeros((0, 3), np.int32), 0.0, 0.0, 0.0, 0, 0)
    share = START_SHARE
    while True:
        target = max(int(len(full) * share), 2)
        if share >= 1.0 or target >= len(full):
            v, f = used_vertices(verts, full)
        else:
            v, f = fast_simplification.simplify(verts, full, target_count=target, agg=AGGRESSIVENESS,
                                                preserve_border=True)  # fmt: skip
        drawn = draw_heights(v, f.astype(np.int32), 0.0, 0.0, cell, rows, cols)
        err = (drawn - z)[valid]
        err = np.where(np.isfinite(err), err, 0.0)  # a cell no face covers: its own grid square is
        sq = float(np.sum(err * err))  # gone with a neighbour's NaN, as in the unthinned grid
        rmse = math.sqrt(sq / max(n_cells, 1))
        if rmse <= max_rmse or share >= 1.0:
            v = np.asarray(v, np.float64) + (x0, y0, 0.0)
            return TileMesh(v, np.asarray(f, np.int32), rmse,
                            float(np.max(np.abs(err))) if err.size else 0.0, sq, n_cells, len(full))  # fmt: skip
        share = min(share * max(MIN_RAISE, rmse / max_rmse), 1.0)


def mesh_tile(job: tuple[DsmGrid, int, int, float]) -> TileMesh:
    """One tile's mesh (a pool's task): :data:`TILE_CELLS` cells a side from row and column
    (``r``, ``c``), and one more, so that the next tile starts on its last vertices."""
    grid, r, c, max_rmse = job
    z = read_block(grid, r, c, TILE_CELLS + 1)
    return tile_mesh(z, grid.x0 + c * grid.cell, grid.y0 - r * grid.cell, grid.cell, max_rmse)


def merged_mesh(job: tuple[float, float, list[TileMesh], float]) -> tuple[np.ndarray, np.ndarray]:
    """Tiles' meshes joined into one (their shared border vertices welded) and thinned to
    ``share`` of their faces, its own outer border held (a pool's task: a coarser level of detail
    made from four tiles of the level below). ``x0``, ``y0``: a point near it, for precision."""
    import fast_simplification

    x0, y0, parts, share = job
    parts = [p for p in parts if len(p.faces)]
    if not parts:
        return np.zeros((0, 3)), np.zeros((0, 3), np.int32)
    verts = np.concatenate([p.vertices for p in parts])
    faces, base = [], 0
    for p in parts:
        faces.append(p.faces + base)
        base += len(p.vertices)
    local = verts - (x0, y0, 0.0)
    # a border vertex of two tiles is the same cell centre, reached by two sums: equal to 0.1 mm
    key = np.round(local[:, :2] * 1e4).astype(np.int64)
    _, first, inverse = np.unique(key, axis=0, return_index=True, return_inverse=True)
    welded = local[first]
    f = inverse.ravel()[np.concatenate(faces)].astype(np.int32)
    f = f[(f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2])]
    target = int(len(f) * share)
    if target >= 4:
        welded, f = fast_simplification.simplify(welded, f, target_count=target, agg=AGGRESSIVENESS,
                                                 preserve_border=True)  # fmt: skip
    return np.asarray(welded, np.float64) + (x0, y0, 0.0), np.asarray(f, np.int32)


def read_block(grid: DsmGrid, r: int, c: int, size: int) -> np.ndarray:
    """The DSM's heights (NaN where none) from (``r``, ``c``), ``size`` cells a side at most."""
    import rasterio
    from rasterio.windows import Window

    h, w = min(size, grid.rows - r), min(size, grid.cols - c)
    with rasterio.open(grid.path) as ds:
        return np.asarray(ds.read(1, window=Window(c, r, w, h), masked=True).astype(np.float64).filled(np.nan))


def used_vertices(verts: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The vertices faces use, and the faces renumbered onto them."""
    used = np.unique(faces)
    remap = np.full(len(verts), -1, np.int64)
    remap[used] = np.arange(len(used))
    return verts[used], remap[faces].astype(np.int32)


def draw_heights(
    vertices: np.ndarray, faces: np.ndarray, x0: float, y0: float, cell: float, rows: int, cols: int
) -> np.ndarray:
    """The mesh's height at each cell centre of a grid (first centre at ``x0``, ``y0``), the highest
    face where faces overlap; NaN where no face covers the cell."""
    px = (vertices[:, 0] - x0) / cell
    py = (y0 - vertices[:, 1]) / cell
    screen = np.ascontiguousarray(np.stack([px, py], axis=1), np.float64)
    depth = np.ascontiguousarray(-vertices[:, 2], np.float64)
    attrs = np.ascontiguousarray(vertices[:, 2:3], np.float64)
    _, out = rasterize(screen, depth, attrs, np.ascontiguousarray(faces, np.int64), rows, cols)
    return out[:, :, 0]


def rasterize(
    screen: np.ndarray,
    depth: np.ndarray,
    attrs: np.ndarray,
    faces: np.ndarray,
    rows: int,
    cols: int,
    dtype: type = np.float64,
) -> tuple[np.ndarray, np.ndarray]:
    """Triangles drawn onto a grid of pixel centres (pixel (r, c) at screen (c, r)), the nearest
    (least ``depth``) kept, with their vertex ``attrs`` interpolated: (depth (rows, cols), attrs
    (rows, cols, k)), inf and NaN where nothing is drawn; both of ``dtype`` (float32 halves a
    large atlas' memory)."""
    zbuf: np.ndarray = np.full((rows, cols), np.inf, dtype)
    out: np.ndarray = np.full((rows, cols, attrs.shape[1]), np.nan, dtype)
    kernel = compiled(_rasterize) or _rasterize
    kernel(screen, depth, attrs, faces, zbuf, out)
    return zbuf, out


def _rasterize(
    screen: np.ndarray, depth: np.ndarray, attrs: np.ndarray, faces: np.ndarray, zbuf: np.ndarray, out: np.ndarray
) -> None:
    """:func:`rasterize`'s loop (compiled: see :func:`geoortho.core.kernels.compiled`): a triangle at
    a time over the pixel centres in its box, by barycentric weights (edges shared by two
    triangles draw each centre once: a centre on an edge goes to both, the nearer wins)."""
    rows, cols = zbuf.shape
    k = attrs.shape[1]
    for t in range(faces.shape[0]):
        i0, i1, i2 = faces[t, 0], faces[t, 1], faces[t, 2]
        x0, y0 = screen[i0, 0], screen[i0, 1]
        x1, y1 = screen[i1, 0], screen[i1, 1]
        x2, y2 = screen[i2, 0], screen[i2, 1]
        area = (x1 - x0) * (y2 - y0) - (x2 - x0) * (y1 - y0)
        if area == 0.0 or math.isnan(area):
            continue
        c_lo = max(int(math.ceil(min(x0, x1, x2))), 0)
        c_hi = min(int(math.floor(max(x0, x1, x2))), cols - 1)
        r_lo = max(int(math.ceil(min(y0, y1, y2))), 0)
        r_hi = min(int(math.floor(max(y0, y1, y2))), rows - 1)
        eps = 1e-9 * abs(area)
        for r in range(r_lo, r_hi + 1):
            for c in range(c_lo, c_hi + 1):
                w0 = ((x1 - c) * (y2 - r) - (x2 - c) * (y1 - r)) / area
                w1 = ((x2 - c) * (y0 - r) - (x0 - c) * (y2 - r)) / area
                w2 = 1.0 - w0 - w1
                if w0 < -eps or w1 < -eps or w2 < -eps:
                    continue
                d = w0 * depth[i0] + w1 * depth[i1] + w2 * depth[i2]
                if d < zbuf[r, c]:
                    zbuf[r, c] = d
                    for j in range(k):
                        out[r, c, j] = w0 * attrs[i0, j] + w1 * attrs[i1, j] + w2 * attrs[i2, j]


def warm() -> None:
    """Compile the rasterizer into numba's cache (``make`` runs it ahead)."""
    kernel = compiled(_rasterize)
    if kernel is None:
        return
    screen = np.array([[0.0, 0.0], [2.0, 0.0], [0.0, 2.0]])
    for dtype in (np.float64, np.float32):  # the mesh's and the walls' atlas'
        kernel(screen, np.zeros(3), np.zeros((3, 1)), np.array([[0, 1, 2]], np.int64),
               np.full((3, 3), np.inf, dtype), np.zeros((3, 3, 1), dtype))  # fmt: skip
