"""The DSM beside and under objects: walls where the points put them, not ramps.

A photogrammetric DSM has no points at the foot of most walls (the ground there is hidden from
the photos on the far side, and the depth maps drop what their pairs disagree on) nor on crowns
the matcher found no texture on. Filled as one surface through every measured cell, the gap
beside a wall becomes a ramp from the roof down to the ground: a building 1-2 m wider than it is,
with sloping sides, and an orthophoto that smears the ground up them (issue 74, the demo survey:
92 % of the interpolated cells 0.25-1 m outside a wall were more than 0.3 m off).

Each filled cell next to an object is given to one side (the objects come from
:func:`geoortho.elevation.bareearth.bare_earth`, which finds them on the DSM against the ground's
lower envelope):

* to the object when it is inside the object's outline (its measured cells closed by a disc of
  ``ENCLOSED_M``) and far closer to them than to the ground's (``OBJECT_SIDE_RATIO``), or next to
  them: a gap inside a roof or a crown, filled as a thin plate
  through the object's own cells (it keeps a crown's dome, where a harmonic fill sags to a cone);
* to the ground otherwise: hidden ground, filled from the ground's measured cells only, so that the
  wall stands at the object's last measured cell.

A gap (connected filled cells) is filled again, whole, when it comes within ``REACH_M`` of an
object's measured cells and is no larger than ``WHOLE_GAP_M2``; larger gaps (a lake, the photos'
fringe filled by :func:`geoortho.elevation.coverage.complete_grid`) keep their first fill: a part
of one filled again would meet the rest with a step.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from geoortho.core.gapfill import fill_harmonic, fill_smooth

__all__ = ["ENCLOSED_M", "MARGIN_M", "OBJECT_SIDE_RATIO", "REACH_M", "WHOLE_GAP_M2", "fill_beside_objects"]

#: A filled cell belongs to the object when its distance to the object's measured cells, times
#: this, is less than its distance to the ground's. Hidden ground beside a wall is closer to the
#: ground it continues; a gap inside a roof or a crown is surrounded by the object. Measured on
#: the demo survey (DSM |dZ| p95 within 3 m of objects): 1 -> 0.99 m, 2 -> 0.73, 3 -> 0.72, 5 -> 0.78.
OBJECT_SIDE_RATIO = 3.0
#: A gap is inside an object where its measured cells closed by a disc of this radius cover it (a
#: crown's untextured top, a roof's plain patch); past a straight wall they do not reach.
ENCLOSED_M = 4.0
#: A gap is filled again when it comes this close to an object's measured cells.
REACH_M = 3.0
#: ... and is no larger than this.
WHOLE_GAP_M2 = 2000.0
#: Each stretch of cells is filled in a window this much wider than it: the closing that finds what
#: is enclosed must see past it (a narrower margin called the window's edge enclosed).
MARGIN_M = ENCLOSED_M + 1.0


def fill_beside_objects(
    z: np.ndarray, measured: np.ndarray, objects: np.ndarray, cell_m: float
) -> tuple[np.ndarray, int]:
    """``z`` (a filled DSM, NaN: none) with its gaps (the cells not ``measured``) that reach
    ``objects`` filled again, each cell from its own side. Returns the DSM and how many cells changed.

    The gaps are filled a group at a time (those within two ``MARGIN_M`` of each other), each group in
    its window: a fill over the whole grid held 120 bytes a cell (0.7 GB on the demo survey's), fixed
    tiles left a seam where a gap crossed their edge, and a window for each gap made 420 windows
    (20 s) on a survey with a wood."""
    have = np.isfinite(z)
    known = measured & have
    object_known = known & objects
    if not object_known.any() or not (known & ~objects).any():
        return z, 0
    to_object = np.asarray(ndimage.distance_transform_edt(~object_known), np.float32)
    filled = have & ~known
    reached = filled & (to_object * cell_m <= REACH_M)
    del to_object
    # each gap that reaches an object is filled again whole, when it is small: a part of it only
    # would rest on the rest, ramped up to the roof by the first fill (a crease where the reach ends)
    gaps, n_gaps = ndimage.label(filled, structure=np.ones((3, 3), bool))
    size_m2 = np.bincount(gaps.ravel(), minlength=n_gaps + 1) * cell_m * cell_m
    chosen = np.zeros(n_gaps + 1, bool)
    chosen[np.unique(gaps[reached])] = True
    chosen &= size_m2 <= WHOLE_GAP_M2
    chosen[0] = False
    cells = chosen[gaps]
    del gaps
    # the gaps are filled a group at a time: those within two margins of each other share a window
    margin = int(np.ceil(MARGIN_M / cell_m))
    groups, _ = ndimage.label(ndimage.distance_transform_edt(~cells) <= margin)
    out = np.array(z, np.float32, copy=True)
    for i, box in enumerate(ndimage.find_objects(groups), start=1):
        if box is None:
            continue
        mine = cells[box] & (groups[box] == i)
        new = _fill_window(z[box], known[box], objects[box], mine, cell_m)
        out[box][mine] = new[mine]
    return out, int(cells.sum())


def _fill_window(z: np.ndarray, known: np.ndarray, objects: np.ndarray, cells: np.ndarray, cell_m: float) -> np.ndarray:
    """One window's DSM with ``cells`` (filled cells near its objects) filled again."""
    object_known = known & objects
    ground_known = known & ~objects
    out = np.array(z, np.float32, copy=True)
    if not object_known.any() or not ground_known.any():
        return out
    to_object = np.asarray(ndimage.distance_transform_edt(~object_known), np.float32)
    to_ground = np.asarray(ndimage.distance_transform_edt(~ground_known), np.float32)
    # inside the object's outline: its measured cells closed by a disc (two distance transforms); past
    # a straight wall nothing is, so hidden ground there stays ground up to the wall
    # (padded: past the grid's edge is not the object)
    pad = int(np.ceil(ENCLOSED_M / cell_m)) + 1
    grown = np.pad(to_object * cell_m <= ENCLOSED_M, pad, constant_values=False)
    enclosed = (np.asarray(ndimage.distance_transform_edt(grown)) * cell_m > ENCLOSED_M)[pad:-pad, pad:-pad]
    object_side = cells & objects & ((enclosed & (to_object * OBJECT_SIDE_RATIO < to_ground)) | (to_object <= 1.0))
    ground_side = cells & ~object_side
    if object_side.any():
        inside = fill_smooth(np.where(object_known, z, np.nan), object_known, object_side)
        out[object_side] = inside[object_side]
    if ground_side.any():
        # anchored on the ground's measured cells (and the fill of gaps not touched, off the objects)
        anchors = (np.isfinite(z) & ~objects & ~known & ~cells) | ground_known
        beside = fill_harmonic(np.where(anchors, z, np.nan), anchors, ground_side)
        out[ground_side] = beside[ground_side]
    return out
