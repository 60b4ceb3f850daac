"""``copc``: a point cloud (LAS/LAZ, the dense cloud or a lidar survey) as a Cloud-Optimized Point
Cloud, which QGIS (3.34 and later) opens as a point cloud layer and streams by its octree, with no
indexing step, and which web viewers (Potree, plas.io) read over HTTP.

The octree and the file are :mod:`geoortho.core.copc`'s; here the algorithm checks what it is given,
says what it made; the writer reads the file back and checks that it has every point of the source.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

from pyproj import CRS

from geoortho.core.copc import COPC_SUFFIX, is_copc_path, write_copc
from geoortho.core.crs import crs_to_text
from geoortho.errors import InputError, ParameterError
from geoortho.feedback import Feedback, as_feedback

__all__ = ["CopcResult", "copc"]


@dataclass(frozen=True)
class CopcResult:
    """The COPC file written.

    Attributes
    ----------
    output : Path
        The cloud as COPC (LAZ 1.4, point format 7 with colours or 6 without).
    n_points : int
        Points written: every point of the source.
    n_nodes : int
        Octree nodes holding points.
    depth : int
        The deepest octree level (0: the root alone).
    spacing : float
        The root level's point spacing, in the CRS's units: each level below halves it.
    crs : str
        CRS of the cloud.
    seconds : float
        Time taken.
    """

    output: Path
    n_points: int
    n_nodes: int
    depth: int
    spacing: float
    crs: str
    seconds: float


def copc(
    points: Path,
    output: Path,
    crs: CRS | None = None,
    *,
    feedback: Feedback | None = None,
) -> CopcResult:
    """Rewrite a point cloud as a Cloud-Optimized Point Cloud (COPC).

    Every point is kept, with its coordinates, colours, class and returns; the octree's first
    levels are an even thinning of the whole cloud, so a viewer shows the site at once and
    fills it in as it zooms.

    Parameters
    ----------
    points : Path
        The cloud (LAS or LAZ).
    output : Path
        The COPC file (its name ends in .copc.laz).
    crs : CRS
        The cloud's CRS when its header holds none.
    """
    fb = as_feedback(feedback)
    started = time.perf_counter()
    if not is_copc_path(output):
        raise ParameterError("output", f"{output}: a COPC file's name ends in {COPC_SUFFIX}")
    if Path(points).suffix.lower() not in (".las", ".laz"):
        raise InputError("a COPC file is made from a LAS or LAZ cloud", path=points)
    written = write_copc(Path(points), Path(output), crs_wkt=crs.to_wkt("WKT1_GDAL") if crs is not None else None)
    if not written.crs_wkt:
        fb.warning(f"{Path(points).name} says no CRS and none was given: the COPC file has none either")
    fb.progress(1.0)
    fb.info(
        f"{written.n_points:,} points in {written.n_nodes:,} octree nodes, {written.depth + 1} levels "
        f"(spacing {written.spacing:.3g} at the root): {Path(output).name}"
    )
    text = crs_to_text(CRS.from_wkt(written.crs_wkt)) if written.crs_wkt else ""
    return CopcResult(
        Path(output), written.n_points, written.n_nodes, written.depth, written.spacing, text,
        time.perf_counter() - started,
    )  # fmt: skip
