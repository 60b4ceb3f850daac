"""Cloud-Optimized Point Clouds: a LAS/LAZ cloud rewritten as COPC (``.copc.laz``), which QGIS
(3.34 and later) and web viewers stream by its octree, with no indexing step.

copc-lib (``copclib``) writes the file: its LAZ chunks, one per octree node, its hierarchy and its
info record. What copc-lib leaves to the caller is which point goes to which node; it is decided
here, with NumPy, a cloud at a time that need not fit in memory:

- each level of the octree keeps, of the points not taken above it, the first in each cell of a
  grid ``CELLS`` to a node's side (so a level is a spatially even sample, and a viewer drawing
  the first levels sees the whole site thinly);
- a node with few points left under it takes them all and ends there;
- the levels above ``split`` are made in one streamed pass over the cloud; below them, the points
  go to one scratch file per node of level ``split`` and each such subtree is made on its own:
  memory holds one subtree, not the cloud.

Every point of the source is written once, with its coordinates (same scale and offset), colours
and class; the CRS goes in as the LAS 1.4 WKT record.
"""

from __future__ import annotations

import math
import os
import shutil
import struct
import tempfile
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from geoortho.core.outputs import atomic_path
from geoortho.errors import GeoorthoError, InputError

__all__ = ["COPC_SUFFIX", "CopcWritten", "is_copc_path", "write_copc"]

#: How a COPC file's name ends: what makes an output path a COPC file.
COPC_SUFFIX = ".copc.laz"

CELLS = 128  # grid cells to a node's side: a level's sample spacing is the node's side over this
LEAF_POINTS = 50_000  # a node with at most this many points left under it takes them all
SUBTREE_POINTS = 4_000_000  # the largest subtree held in memory (what ``split`` is chosen for)
CHUNK_POINTS = 2_000_000  # points read from the source at a time
MAX_DEPTH = 13  # 128 << 13 cells a side: the ids hold 21 bits an axis


def is_copc_path(path: str | os.PathLike[str]) -> bool:
    return Path(path).name.lower().endswith(COPC_SUFFIX)


@dataclass(frozen=True)
class CopcWritten:
    """A COPC file written: its points, octree nodes and levels, and the cube it spans."""

    path: Path
    n_points: int
    n_nodes: int
    depth: int  # the deepest level holding points (0: the root alone)
    spacing: float  # the root level's sample spacing, in the CRS's units
    crs_wkt: str


@dataclass(frozen=True)
class _Cube:
    lo: np.ndarray  # the cube's lowest corner (x, y, z)
    side: float

    def cells(self, xyz: np.ndarray, level: int, per_node: int) -> np.ndarray:
        """Integer grid coordinates (N, 3) at ``level`` with ``per_node`` cells to a node's side."""
        n = per_node << level
        out: np.ndarray = np.clip(((xyz - self.lo) / self.side * n).astype(np.int64), 0, n - 1)
        return out


def _ids(ijk: np.ndarray) -> np.ndarray:
    """One int64 per cell (21 bits an axis: 2 million cells a side, level 13 at 128 a node)."""
    out: np.ndarray = (ijk[:, 0] << 42) | (ijk[:, 1] << 21) | ijk[:, 2]
    return out


def _groups(ids: np.ndarray) -> Iterator[tuple[int, np.ndarray]]:
    """Each distinct id and the indices holding it (in their order)."""
    order = np.argsort(ids, kind="stable")
    cut = np.nonzero(np.diff(ids[order]))[0] + 1
    for group in np.split(order, cut):
        if len(group):
            yield int(ids[group[0]]), group


def _key(node_id: int) -> tuple[int, int, int]:
    mask = (1 << 21) - 1
    return (node_id >> 42) & mask, (node_id >> 21) & mask, node_id & mask


def _first_in_cells(ids: np.ndarray, taken_before: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """Which of ``ids`` are the first of their cell, also among the cells ``taken_before`` (sorted
    ids of cells already holding a point); and the cells taken, sorted, with them."""
    uniq, first = np.unique(ids, return_index=True)
    if taken_before is not None and len(taken_before):
        fresh = ~np.isin(uniq, taken_before, assume_unique=True)
        uniq, first = uniq[fresh], first[fresh]
    mask = np.zeros(len(ids), bool)
    mask[first] = True
    merged = uniq if taken_before is None else np.union1d(taken_before, uniq)
    return mask, merged


def _subtree(
    xyz: np.ndarray, cube: _Cube, top: int, max_depth: int, leaf_points: int
) -> Iterator[tuple[tuple[int, int, int, int], np.ndarray]]:
    """The nodes of the points ``xyz`` (all under one node of level ``top``) from level ``top``
    down: each node's key (level, x, y, z) and the indices of its points."""
    remaining = np.arange(len(xyz))
    for level in range(top, max_depth + 1):
        if not len(remaining):
            return
        cells = cube.cells(xyz[remaining], level, CELLS)
        take, _ = _first_in_cells(_ids(cells), None)
        nodes = cells // CELLS
        node_ids = _ids(nodes)
        if level == max_depth:
            take[:] = True
        else:
            # a node with few points left under it takes them all
            rest = ~take
            uniq, inverse, counts = np.unique(node_ids[rest], return_inverse=True, return_counts=True)
            small = np.zeros(len(remaining), bool)
            small[np.nonzero(rest)[0]] = counts[inverse] <= leaf_points
            take |= small
        idx = np.nonzero(take)[0]
        for node_id, group in _groups(node_ids[idx]):
            yield (level, *_key(node_id)), remaining[idx[group]]
        remaining = remaining[~take]


def _with_wkt_vlr(source: Path, target: Path, wkt: str) -> None:
    """``source`` (a COPC file) copied to ``target`` with the CRS's WKT also as a header VLR.

    copc-lib writes the WKT as an extended VLR, after the points; QGIS's COPC reader looks for
    it among the header's VLRs only (``QgsLazInfo::parseCrs``), and showed the cloud with no
    CRS. Inserted after the last VLR, it moves every absolute offset behind it by its size: the
    points' start, the LAZ chunk table's pointer, the first extended VLR, the COPC info's root
    hierarchy page and each hierarchy entry."""
    data = wkt.encode() + b"\0"
    vlr = struct.pack("<H16sHH32s", 0, b"LASF_Projection", 2112, len(data), b"OGC WKT") + data
    shift = len(vlr)
    with open(source, "rb") as src, open(target, "wb") as dst:
        head = bytearray(src.read(375))
        header_size, point_start, n_vlrs = struct.unpack_from("<HII", head, 94)
        evlr_start = struct.unpack_from("<Q", head, 235)[0]  # after the waveform start (227)
        src.seek(header_size)
        vlrs = bytearray(src.read(point_start - header_size))
        struct.pack_into("<II", head, 96, point_start + shift, n_vlrs + 1)
        struct.pack_into("<Q", head, 235, evlr_start + shift)
        # the COPC info VLR comes first: its root hierarchy page's offset at 40 bytes into its data
        root_offset, root_size = struct.unpack_from("<QQ", vlrs, 54 + 40)
        struct.pack_into("<Q", vlrs, 54 + 40, root_offset + shift)
        dst.write(head[:header_size])
        dst.write(vlrs)
        dst.write(vlr)
        src.seek(point_start)
        shutil.copyfileobj(src, dst, 16 << 20)
    with open(target, "r+b") as f:
        f.seek(point_start + shift)  # the LAZ chunk table's absolute offset opens the point data
        (table,) = struct.unpack("<q", f.read(8))
        f.seek(point_start + shift)
        f.write(struct.pack("<q", table + shift))
        pages = [(root_offset + shift, root_size)]
        while pages:
            at, size = pages.pop()
            f.seek(at)
            page = bytearray(f.read(size))
            for e in range(0, size, 32):
                offset, _, count = struct.unpack_from("<Qii", page, e + 16)
                struct.pack_into("<Q", page, e + 16, offset + shift)
                if count == -1:  # a child page
                    pages.append((offset + shift, struct.unpack_from("<i", page, e + 24)[0]))
            f.seek(at)
            f.write(page)


def write_copc(source: Path, output: Path, *, crs_wkt: str | None = None) -> CopcWritten:
    """``source`` (LAS/LAZ) rewritten as a COPC file at ``output`` (atomic), every point once,
    its colours and classes kept; ``crs_wkt``: the CRS when the source's header holds none."""
    import copclib
    import laspy

    with laspy.open(str(source)) as reader:
        header = reader.header
        n = int(header.point_count)
        if n == 0:
            raise InputError("the cloud has no point: a COPC file needs one", path=source)
        crs = header.parse_crs()
        wkt = crs.to_wkt("WKT1_GDAL") if crs is not None else (crs_wkt or "")
        lo, hi = np.asarray(header.mins, float), np.asarray(header.maxs, float)
        scales, offsets = np.asarray(header.scales, float), np.asarray(header.offsets, float)
        dimensions = set(header.point_format.dimension_names)
        has_rgb = "red" in dimensions
    side = float(max((hi - lo).max(), 1e-3)) * (1 + 1e-9)
    cube = _Cube(lo - (side - (hi - lo)) / 2, side)
    # the levels made in the streamed pass: a node of level ``split`` holds about SUBTREE_POINTS or fewer
    # (a surface: four times the nodes a level)
    split = min(MAX_DEPTH, max(0, math.ceil(math.log(max(n / SUBTREE_POINTS, 1.0), 4))))
    point_format = 7 if has_rgb else 6
    out_header = laspy.LasHeader(point_format=point_format, version="1.4")
    out_header.scales, out_header.offsets = scales, offsets
    config = copclib.CopcConfigWriter(point_format, copclib.Vector3(*scales), copclib.Vector3(*offsets), wkt)
    centre = cube.lo + side / 2
    config.copc_info.center_x, config.copc_info.center_y, config.copc_info.center_z = map(float, centre)
    config.copc_info.halfsize = side / 2
    config.copc_info.spacing = side / CELLS
    n_nodes = depth = 0

    with tempfile.TemporaryDirectory(prefix="copc-", dir=Path(output).parent) as scratch, atomic_path(output) as tmp:
        written = os.path.join(scratch, "written.copc.laz")
        writer = copclib.FileWriter(written, config)
        record_dtype = laspy.ScaleAwarePointRecord.zeros(0, header=out_header).array.dtype

        shared = [d for d in out_header.point_format.dimension_names if d in dimensions and d not in ("X", "Y", "Z")]

        def records(chunk: laspy.ScaleAwarePointRecord) -> np.ndarray:
            rec = laspy.ScaleAwarePointRecord.zeros(len(chunk), header=out_header)
            rec.X, rec.Y, rec.Z = chunk.X, chunk.Y, chunk.Z  # the integers: no rounding again
            for d in shared:
                rec[d] = chunk[d]
            # a LAS 1.4 reader expects a first return of one at least (a photo cloud records none)
            rec.return_number[:] = np.maximum(np.asarray(rec.return_number), 1)
            rec.number_of_returns[:] = np.maximum(np.asarray(rec.number_of_returns), np.asarray(rec.return_number))
            return np.asarray(rec.array)

        def add(key: tuple[int, int, int, int], rows: np.ndarray) -> None:
            nonlocal n_nodes, depth
            raw = np.ascontiguousarray(rows).view(np.int8)  # the records' bytes, as copc-lib's chars
            writer.AddNode(copclib.VoxelKey(*key), copclib.VectorChar(raw))
            n_nodes += 1
            depth = max(depth, key[0])

        # the streamed pass: the levels above ``split``, and every other point to its subtree's file
        taken: list[np.ndarray | None] = [None] * split
        upper: dict[tuple[int, int, int, int], list[np.ndarray]] = {}
        buckets: dict[tuple[int, int, int], str] = {}
        with laspy.open(str(source)) as reader:
            for chunk in reader.chunk_iterator(CHUNK_POINTS):
                rows = records(chunk)
                xyz = np.column_stack([chunk.x, chunk.y, chunk.z])
                left = np.ones(len(rows), bool)
                for level in range(split):
                    at = np.nonzero(left)[0]
                    cells = cube.cells(xyz[at], level, CELLS)
                    take, taken[level] = _first_in_cells(_ids(cells), taken[level])
                    chosen = at[take]
                    for node_id, group in _groups(_ids(cells[take] // CELLS)):
                        upper.setdefault((level, *_key(node_id)), []).append(rows[chosen[group]])
                    left[chosen] = False
                at = np.nonzero(left)[0]
                for node_id, group in _groups(_ids(cube.cells(xyz[at], split, 1))):
                    name = buckets.setdefault(_key(node_id), os.path.join(scratch, f"{len(buckets)}.bin"))
                    with open(name, "ab") as f:
                        f.write(rows[at[group]].tobytes())
        for key, parts in sorted(upper.items()):
            add(key, np.concatenate(parts))
        del upper, taken
        for _, name in sorted(buckets.items()):
            rows = np.fromfile(name, dtype=record_dtype)
            os.remove(name)
            xyz = np.column_stack([rows[c] * s + o for c, s, o in zip(("X", "Y", "Z"), scales, offsets)])
            for node, idx in _subtree(xyz, cube, split, MAX_DEPTH, LEAF_POINTS):
                add(node, rows[idx])
        out = writer.copc_config.las_header
        out.min, out.max = copclib.Vector3(*lo), copclib.Vector3(*hi)
        writer.Close()
        if wkt:
            _with_wkt_vlr(Path(written), Path(tmp), wkt)
        else:
            shutil.move(written, tmp)
        with laspy.open(str(tmp)) as check:  # read back: every point of the source is in the file
            if int(check.header.point_count) != n:
                raise GeoorthoError(f"the COPC file holds {check.header.point_count:,} points of {n:,}: not kept")
    return CopcWritten(Path(output), n, n_nodes, depth, side / CELLS, wkt)
