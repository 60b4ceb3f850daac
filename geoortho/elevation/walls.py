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

Which side is tested against the SfM's tie points where they fall in a gap: a crown the dense
matcher found no match on (at a wood's edge, where no closing encloses it) has tie points at the
crown's height, and hidden ground has none above the ground. Each tie point votes for the fill it
is nearer to; where ``VOTE_MIN`` votes within ``VOTE_M`` agree (and outnumber the others), the
cells under an object take their side. A tie point only chooses between the two fills, it sets
no height (one that is wrong costs no spike).

A gap (connected filled cells) is filled again, whole, when it comes within ``REACH_M`` of an
object's measured cells and is no larger than ``WHOLE_GAP_M2``; larger gaps (a lake, the photos'
fringe filled by :func:`geoortho.elevation.coverage.complete_grid`) keep their first fill: a part
of one filled again would meet the rest with a step.
"""

from __future__ import annotations

import cv2
import numpy as np
from scipy import ndimage

from geoortho.core.gapfill import distance_cells, fill_harmonic, fill_smooth

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
#: A tie point votes for the object when it stands this far above the ground's fill at least,
#: nearer the object's fill than the ground's (and for the ground, nearer it, the object's fill this
#: far above it)...
VOTE_ABOVE_M = 0.5
#: The object's fill through its tie points leaves out its measured cells within this of the
#: ground's fill (the ground the objects' outline takes in, a cell or three beside it).
GROUND_BAND_M = 0.2
#: ... and the cells under an object within this of at least VOTE_MIN agreeing votes take their side
#: (more votes than the other side's there). A wood's unmatched edge crowns held 0.3 tie points a
#: m² (the synthetic scenes survey), a crown is 2-3 m across.
VOTE_M = 2.5
VOTE_MIN = 2
#: Each stretch of cells is filled in a window this much wider than it: the closing that finds what
#: is enclosed must see past it (a narrower margin called the window's edge enclosed).
MARGIN_M = ENCLOSED_M + 1.0


def fill_beside_objects(
    z: np.ndarray, measured: np.ndarray, objects: np.ndarray, cell_m: float, tie_points: np.ndarray | None = None
) -> tuple[np.ndarray, int]:
    """``z`` (a filled DSM, NaN: none) with its gaps (the cells not ``measured``) that reach
    ``objects`` filled again, each cell from its own side. Returns the DSM and how many cells changed.

    ``tie_points``: (row, col, z) of the SfM's tie points on the grid (fractional cells), to vote
    on the side where they fall in a gap.

    The gaps are filled a group at a time (those within two ``MARGIN_M`` of each other), each group in
    its window: a fill over the whole grid held 120 bytes a cell (0.7 GB on the demo survey's), fixed
    tiles left a seam where a gap crossed their edge, and a window for each gap made 420 windows
    (20 s) on a survey with a wood."""
    have = np.isfinite(z)
    known = measured & have
    object_known = known & objects
    if not object_known.any() or not (known & ~objects).any():
        return z, 0
    to_object = distance_cells(~object_known)
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
    groups, _ = ndimage.label(distance_cells(~cells) <= margin)
    out = np.array(z, np.float32, copy=True)
    pts = _points_in_cells(tie_points, cells)
    for i, box in enumerate(ndimage.find_objects(groups), start=1):
        if box is None:
            continue
        mine = cells[box] & (groups[box] == i)
        votes = None
        if pts is not None:
            r, c = pts[:, 0].astype(np.int64), pts[:, 1].astype(np.int64)
            inside = (r >= box[0].start) & (r < box[0].stop) & (c >= box[1].start) & (c < box[1].stop)
            inside[inside] = mine[r[inside] - box[0].start, c[inside] - box[1].start]
            if inside.any():
                votes = np.c_[r[inside] - box[0].start, c[inside] - box[1].start, pts[inside, 2]]
        new = _fill_window(z[box], known[box], objects[box], mine, cell_m, votes)
        out[box][mine] = new[mine]
    return out, int(cells.sum())


def _points_in_cells(points: np.ndarray | None, cells: np.ndarray) -> np.ndarray | None:
    """The (row, col, z) points that fall on ``cells`` (None when none do)."""
    if points is None or not len(points):
        return None
    p = np.asarray(points, np.float64)
    p = p[np.isfinite(p).all(axis=1)]
    r, c = np.floor(p[:, 0]).astype(np.int64), np.floor(p[:, 1]).astype(np.int64)
    ok = (r >= 0) & (r < cells.shape[0]) & (c >= 0) & (c < cells.shape[1])
    ok[ok] = cells[r[ok], c[ok]]
    return np.c_[r[ok], c[ok], p[ok, 2]] if ok.any() else None


def _fill_window(
    z: np.ndarray,
    known: np.ndarray,
    objects: np.ndarray,
    cells: np.ndarray,
    cell_m: float,
    votes: np.ndarray | None = None,
) -> np.ndarray:
    """One window's DSM with ``cells`` (filled cells near its objects) filled again; ``votes``:
    (row, col, z) of the tie points on them."""
    object_known = known & objects
    ground_known = known & ~objects
    out = np.array(z, np.float32, copy=True)
    if not object_known.any() or not ground_known.any():
        return out
    to_object = distance_cells(~object_known)
    to_ground = distance_cells(~ground_known)
    # inside the object's outline: its measured cells closed by a disc (two distance transforms); past
    # a straight wall nothing is, so hidden ground there stays ground up to the wall
    # (padded: past the grid's edge is not the object)
    pad = int(np.ceil(ENCLOSED_M / cell_m)) + 1
    grown = np.pad(to_object * cell_m <= ENCLOSED_M, pad, constant_values=False)
    enclosed = (distance_cells(grown) * cell_m > ENCLOSED_M)[pad:-pad, pad:-pad]
    object_side = cells & objects & ((enclosed & (to_object * OBJECT_SIDE_RATIO < to_ground)) | (to_object <= 1.0))
    # anchored on the ground's measured cells (and the fill of gaps not touched, off the objects)
    anchors = (np.isfinite(z) & ~objects & ~known & ~cells) | ground_known
    object_z, object_fixed = np.where(object_known, z, np.nan), object_known
    if votes is not None and (cells & objects).any():
        object_side, pinned, raised = _voted(object_side, cells & objects, votes, z, object_known, anchors, cell_m)
        if pinned is not None:
            # the object's fill rests on the tie points that voted for it too (from one side only, at
            # a wood's edge, a thin plate through the crowns ran 2-5 m under their tie points), and
            # not on the ground cells the objects' outline takes in (a ramp down to them)
            r, c = pinned[:, 0].astype(np.int64), pinned[:, 1].astype(np.int64)
            object_fixed = object_known & raised
            object_fixed[r, c] = True
            object_z = np.where(object_fixed, z, np.nan)
            object_z[r, c] = pinned[:, 2]
    ground_side = cells & ~object_side
    if object_side.any():
        inside = fill_smooth(object_z, object_fixed, object_side & ~object_fixed)
        out[object_side & ~object_fixed] = inside[object_side & ~object_fixed]
        pins = object_side & object_fixed
        out[pins] = object_z[pins]
    if ground_side.any():
        beside = fill_harmonic(np.where(anchors, z, np.nan), anchors, ground_side)
        out[ground_side] = beside[ground_side]
    return out


def _voted(
    object_side: np.ndarray,
    under: np.ndarray,
    votes: np.ndarray,
    z: np.ndarray,
    object_known: np.ndarray,
    anchors: np.ndarray,
    cell_m: float,
) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
    """``object_side`` with the ``under`` cells (gap cells under an object) near agreeing tie points
    given to the side they vote for (see the module); the tie points (row, col, z) that voted for
    the object where it won (None: none); and where the surface stands GROUND_BAND_M over the
    ground's fill."""
    on_object = fill_smooth(np.where(object_known, z, np.nan), object_known, under)
    on_ground = fill_harmonic(np.where(anchors, z, np.nan), anchors, under | object_known)
    with np.errstate(invalid="ignore"):
        raised = ~(z - on_ground <= GROUND_BAND_M)
    r, c = votes[:, 0].astype(np.int64), votes[:, 1].astype(np.int64)
    pz, zo, zg = votes[:, 2], on_object[r, c], on_ground[r, c]
    ok = np.isfinite(zo) & np.isfinite(zg)
    for_object = ok & (pz - zg > VOTE_ABOVE_M) & (np.abs(pz - zo) < np.abs(pz - zg))
    for_ground = ok & (zo - zg > VOTE_ABOVE_M) & (np.abs(pz - zg) < np.abs(pz - zo))
    if not (for_object.any() or for_ground.any()):
        return object_side, None, raised
    rad = max(1, int(round(VOTE_M / cell_m)))
    disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * rad + 1, 2 * rad + 1)).astype(np.float32)

    def count(which: np.ndarray) -> np.ndarray:
        marks = np.zeros(z.shape, np.float32)
        np.add.at(marks, (r[which], c[which]), 1.0)
        return np.asarray(cv2.filter2D(marks, -1, disc, borderType=cv2.BORDER_CONSTANT))

    n_object, n_ground = count(for_object), count(for_ground)
    to_object = under & (n_object >= VOTE_MIN - 0.5) & (n_object > n_ground + 0.5)
    to_ground = under & (n_ground >= VOTE_MIN - 0.5) & (n_ground > n_object + 0.5)
    side = (object_side | to_object) & ~to_ground
    pinned = for_object & side[r, c]
    return side, (votes[pinned] if pinned.any() else None), raised
