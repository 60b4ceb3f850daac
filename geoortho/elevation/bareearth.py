"""A DTM that is bare earth: objects found on the DSM whatever their size, their rims taken in,
ground cells that disagree with their neighbourhood dropped, and a fill that does not spike.

The ground filter (SMRF) classifies points; gridding its ground points leaves three artefacts a
surveyor sees at once in a hillshade (issue 74, measured on the demo survey and on real photos):

* **rims**: a photogrammetric cloud has points halfway up walls and crowns; those within the
  filter's threshold of its provisional surface are called ground, and the DTM keeps a ring of
  half-height cells around every building and tree;
* **cusps**: a harmonic fill pinned to a single ground cell is a cone (a harmonic function is
  logarithmic about a point), a dark and a bright dot in the hillshade;
* **canopy called ground**: under an object wider than any filter window.

Here, on the DSM's own grid:

1. The ground's lower envelope is the DTM opened by a disc (``RIM_RADIUS_M``, on blocks of
   ``ENVELOPE_CELL_M``), the objects found so far left out of it: a rim resting on an object's
   interpolated plateau falls to the ground outside it; open ground is unchanged.
2. Objects are seeded where the DSM (its 5 x 5 median) stands ``OBJECT_SEED_M`` above both the
   envelope and the filter's DTM over ``SEED_MIN_M2``, and grown (hysteresis, scikit-image) through
   every connected cell ``OBJECT_GROW_M`` above the envelope within ``RIM_REACH_M`` of a seed, then
   by one cell: a wall's half-height cells join its roof, whatever the object's size; the terrace a
   bank holds up beside it does not.
3. Ground cells are the DTM's measured cells off the objects, within ``RIM_TOLERANCE_M`` of the
   envelope beside them; spikes off their own median, small blobs off a local plane fit and small
   islands off a surface through the rest are dropped before they pin anything. A long
   disagreement (a kerb, a bank's brow) is a breakline and stays. Ground on under
   ``MIN_GROUND_SHARE`` of the cells, or rough as crowns are, is no ground seen at all: a plane
   through the lowest cells, said so.
4. Everything else is filled as a thin plate (:func:`geoortho.core.gapfill.fill_smooth`) resting on
   ground ``FILL_CLEARANCE_M`` off each object, then the speckle is smoothed where the ground is
   smooth (a local plane fit over ``SMOOTH_M``, kept past ``BREAK_SIGMAS`` noise sigmas), and the
   DTM is kept under the DSM within twice the noise.
5. Cells under an object farther from any ground cell than a fill can honestly bridge are "under
   an object, no ground seen" (their own code in the source raster): a guess, said so. How far is
   judged on the ground's own relief around each object (:func:`bridgeable_m`): up to ``BRIDGE_M``
   on smooth ground, down to ``BRIDGE_MIN_M`` on rolling ground or beside a bank.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from scipy import ndimage

from geoortho.core.gapfill import block_means, block_sums, distance_cells, fill_harmonic, fill_smooth

__all__ = [
    "BRIDGE_M",
    "OBJECT_GROW_M",
    "OBJECT_SEED_M",
    "BareEarth",
    "bare_earth",
    "ground_noise_m",
    "despiked",
    "follow_breaklines",
    "lower_envelope",
    "object_mask",
]

#: The lower envelope's disc radius: wider than a rim (a wall's smeared foot: 1-2 m), narrower
#: than a terrace or a bank's top.
RIM_RADIUS_M = 2.0
#: The envelope is found on cells at least this large.
ENVELOPE_CELL_M = 0.2
#: The smoothing's strips of rows (memory follows a strip, not the grid).
STRIP_ROWS = 512
#: An object stands this far above the envelope somewhere (a car: 1.45 m, a hedge: 1.2 m)...
OBJECT_SEED_M = 0.5
#: ... and reaches as far as the DSM stands this far above it (or the ground's noise times 4).
OBJECT_GROW_M = 0.15
#: Objects found, then found again on the envelope without them.
ENVELOPE_PASSES = 3
#: An object seeds where it stands clear over at least this area (a bush; a car is 8 m²).
SEED_MIN_M2 = 0.5
#: An object's cells reach at most this far from where it stands clear of the ground filter's DTM.
RIM_REACH_M = 2.5
#: A DTM cell further above the envelope than this (or 4 noise) is no ground: a rim.
RIM_TOLERANCE_M = 0.15
#: Islands of ground smaller than this that disagree with the rest are dropped...
ISLAND_M2 = 4.0
#: ... and islands objects enclose, up to this area, standing this far above the ground round them
#: (a crown's smooth top inside a wood; a tree is higher, a courtyard is at the ground's height).
ENCLOSED_ISLAND_M2 = 400.0
ENCLOSED_ISLAND_M = 1.5
#: The DTM is smoothed over this scale (a Gaussian's sigma) where it is smooth: a photogrammetric
#: cloud's speckle is a few centimetres at 0.1-1 m (demo: 2.6 cm RMS less the 1 m median)...
SMOOTH_M = 0.5
#: ... and kept where it differs from the smoothed surface by many times that noise (a breakline).
BREAK_SIGMAS = 3.0
#: A blob of ground cells under this area that stands off its neighbourhood (smoothed over
#: BLOB_SMOOTH_M) by BLOB_SIGMAS noise sigmas, and at least BLOB_MIN_M, is a mismatch: dropped.
BLOB_M2 = 2.0
BLOB_SMOOTH_M = 1.0
BLOB_SIGMAS = 5.0
BLOB_MIN_M = 0.05
BLOB_JOIN_M = 0.3
#: "Ground" rougher than this (its speckle's robust sigma) is no ground: a canopy's top (its
#: crowns 0.1-0.5 m apart at 0.5 m), where bare or grassed ground measures 1-3 cm.
NOT_GROUND_NOISE_M = 0.2
#: ... or rougher than this at CROWN_SCALE_M (a closed canopy's crowns, 2-3 m across, 1-2.5 m deep;
#: gentle ground and a field's furrows: a few cm, a bank a line of cells, not the median's).
CROWN_SCALE_M = 2.0
NOT_GROUND_ROUGH_M = 0.25
#: Ground kept on less than this share of the DTM's cells is no ground seen (an all-canopy cloud:
#: 21 of 92 k cells, its crowns' troughs).
MIN_GROUND_SHARE = 0.02
#: With no ground seen, the fallback plane runs through each block's lowest cell, blocks this wide.
BLOCK_M = 5.0
#: The fill under an object rests on the ground at least this far from it.
FILL_CLEARANCE_M = 1.0
#: Under an object, farther than this from the nearest ground cell, the DTM is a guess of its own
#: code: a building's floor (half-width 4-8 m) is bridged honestly, a wood's middle is not...
BRIDGE_M = 10.0
#: ... and nearer, where the ground's own relief says a fill that far from it is off by more than
#: this (RMS; see :func:`bridgeable_m`), never nearer than BRIDGE_MIN_M.
BRIDGE_TOLERANCE_M = 0.10
BRIDGE_MIN_M = 2.0
#: The distances tried, and the blocks the ground is sampled on for it.
BRIDGE_STEPS_M = (2.0, 2.5, 3.0, 4.0, 5.0, 6.0, 8.0, 10.0)
BRIDGE_BLOCK_M = 0.5
#: A gap's fill follows a breakline that crosses it (a bank under a tree): ground at least this
#: steep (rise over run, on the ground smoothed over BREAK_SMOOTH_M; the synthetic banks 0.5-1,
#: rolling ground under 0.15)...
BREAK_SLOPE = 0.35
BREAK_SMOOTH_M = 0.3
#: ... within this of the gap, on both sides of it along the breakline, its gradients this
#: coherent in direction (1: all one way; a hill's flanks round a gap: near 0)...
BREAK_RING_M = 5.0
BREAK_COHERENCE = 0.8
#: ... and straight: its direction is sought within this of the gradients' (in steps of half a
#: degree) as the one along which the ground's profile across it agrees on the gap's two sides.
BREAK_TURN_DEG = 15.0
#: ... and its profile across, where the ground enters the gap, is the profile where it leaves
#: within this (RMS, a straight line across taken out), over at least this much of the profile
BREAK_PROFILE_M = 0.15
BREAK_PROFILE_SEEN_M = 2.0
#: ... on at least this much ground (a bank 1.5 m high is a strip 1.5 m wide), for gaps this large.
BREAK_MIN_M2 = 1.0
BREAK_GAP_M2 = 2.0
#: Gaps joined by a strip narrower than twice this are judged apart.
BREAK_NECK_M = 0.75
#: The fill along a breakline bridges at most this far between the ground on either side.
BREAK_SPAN_M = 40.0
#: The ground's relief is judged over this neighbourhood at least (a Gaussian's sigma).
BRIDGE_LOCAL_M = 5.0
#: A distance is judged on at least this many ground blocks whose ring is ground.
BRIDGE_MIN_SAMPLES = 50


@dataclass(frozen=True)
class BareEarth:
    """The cleaned DTM and what was found on the way (all on the input grid)."""

    z: np.ndarray  # float32, NaN where the input DTM had no value and no fill reached
    ground: np.ndarray  # bool: ground cells kept as measured (the rest of the valid cells are filled)
    objects: np.ndarray  # bool: cells under an object
    no_ground: np.ndarray  # bool: under an object, farther than bridge_m from any ground
    noise_m: float  # the ground's speckle (robust sigma less its smoothed self), metres
    n_rim: int  # measured DTM cells dropped as rims or inside objects
    n_islands: int  # ground cells dropped as islands that disagree
    bridge_m: float = BRIDGE_M  # how far from the ground a fill under an object is trusted (median over them)


def ground_noise_m(z: np.ndarray, ground: np.ndarray, cell_m: float, scale_m: float = 0.0) -> float:
    """The robust sigma of a surface less its smoothed self (over ``scale_m``, default
    ``SMOOTH_M``) on ``ground`` cells: the speckle a hillshade shows (0 when fewer than 50 cells)."""
    if int(ground.sum()) < 50:
        return 0.0
    diff = (z - _smoothed(z, np.isfinite(z), cell_m, scale_m))[ground]
    diff = diff[np.isfinite(diff)]
    return float(1.4826 * np.median(np.abs(diff - np.median(diff)))) if diff.size else 0.0


def _smoothed(z: np.ndarray, valid: np.ndarray, cell_m: float, sigma_m: float = 0.0) -> np.ndarray:
    """The plane fitted about each cell to the ``valid`` cells within a Gaussian of sigma ``sigma_m``
    (default ``SMOOTH_M``), at that cell (normalised convolution of the first order, OpenCV's
    separable filters): a slope is kept to the grid's edge and past a gap's rim, where a plain
    Gaussian bends it (0.1 m at a survey's edge on a 0.2 slope). NaN where no valid cell is near.
    In strips of rows (with a halo of 3 sigma): nine whole-grid sums took 0.45 GB on the demo."""
    sigma_px = max(0.5, (sigma_m or SMOOTH_M) / cell_m)
    half = int(math.ceil(3 * sigma_px))
    ref = float(np.nanmedian(z[valid])) if valid.any() else 0.0
    out = np.full(z.shape, np.nan)
    for r0 in range(0, z.shape[0], STRIP_ROWS):
        r1 = min(z.shape[0], r0 + STRIP_ROWS)
        a, b = max(0, r0 - half), min(z.shape[0], r1 + half)
        part = _plane_fit(z[a:b], valid[a:b], sigma_px, half, ref)
        out[r0:r1] = part[r0 - a : r1 - a]
    return out


def _plane_fit(z: np.ndarray, valid: np.ndarray, sigma_px: float, half: int, ref: float) -> np.ndarray:
    t = np.arange(-half, half + 1, dtype=np.float64)
    g = np.exp(-0.5 * (t / sigma_px) ** 2)
    g1, g2 = g * t, g * t * t
    v = valid.astype(np.float64)
    zv = np.where(valid, z - ref, 0.0)

    def conv(img: np.ndarray, kx: np.ndarray, ky: np.ndarray) -> np.ndarray:
        return np.asarray(cv2.sepFilter2D(img, cv2.CV_64F, kx, ky, borderType=cv2.BORDER_CONSTANT), np.float64)

    s0, sx, sy = conv(v, g, g), conv(v, g1, g), conv(v, g, g1)
    sxx, syy, sxy = conv(v, g2, g), conv(v, g, g2), conv(v, g1, g1)
    z0, zx, zy = conv(zv, g, g), conv(zv, g1, g), conv(zv, g, g1)
    # the plane's value at the cell: Cramer's rule on the 3 x 3 normal equations
    det = s0 * (sxx * syy - sxy * sxy) - sx * (sx * syy - sxy * sy) + sy * (sx * sxy - sxx * sy)
    num = z0 * (sxx * syy - sxy * sxy) - sx * (zx * syy - sxy * zy) + sy * (zx * sxy - sxx * zy)
    with np.errstate(invalid="ignore", divide="ignore"):
        plane = num / det
        mean = z0 / s0
    # too few cells around to fit a slope (a lone cell, a line): their mean
    weak = ~np.isfinite(plane) | (np.abs(det) < 1e-9 * np.maximum(s0, 1e-12) ** 3)
    out = np.where(weak, mean, plane) + ref
    return np.where(s0 > 1e-6, out, np.nan)


def lower_envelope(
    z: np.ndarray, cell_m: float, radius_m: float = RIM_RADIUS_M, exclude: np.ndarray | None = None
) -> np.ndarray:
    """``z`` (NaN: none) opened by a disc of ``radius_m``, the ``exclude`` cells (objects) left out
    of it (their envelope is filled harmonically from around them).

    Left out, an object's cells cannot hold up the envelope beside it: a ring of raised "ground"
    round a tree's crown rests on the interpolated plateau under the crown in a plain opening,
    and falls to the ground outside it here."""
    known = np.isfinite(z)
    skip = ~known if exclude is None else (~known | np.asarray(exclude, bool))
    if skip.all():
        return np.asarray(z, np.float64)
    # on a grid of at least ENVELOPE_CELL_M: a 2 m disc at 5 cm cells is 81 x 81 (6 s an opening on
    # the demo's 6 M cells); the envelope is smooth at that scale, and the hysteresis stays fine
    f = max(1, int(ENVELOPE_CELL_M / cell_m))
    if f > 1:
        coarse = _block_min(np.where(skip, np.nan, z), f)
        env = lower_envelope(coarse, cell_m * f, radius_m)
        h, w = z.shape
        up = cv2.resize(env.astype(np.float32), (env.shape[1] * f, env.shape[0] * f), interpolation=cv2.INTER_LINEAR)
        return np.asarray(up[:h, :w], np.float64)
    # cells with no value (or left out) take their nearest value's for the morphology's sake, then
    # are neutral in it: +inf in the erosion (a minimum), -inf in the dilation (a maximum)
    nearest = ndimage.distance_transform_edt(skip, return_distances=False, return_indices=True)
    base = np.asarray(z, np.float64)[tuple(nearest)].astype(np.float32)
    r = max(1, int(round(radius_m / cell_m)))
    k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
    eroded = cv2.erode(np.where(skip, np.inf, base).astype(np.float32), k)
    eroded[skip] = -np.inf
    opened = cv2.dilate(eroded, k).astype(np.float64)
    bad = ~np.isfinite(opened) | skip
    if bad.any():
        opened = fill_harmonic(np.where(bad, np.nan, opened), ~bad)
    return opened


def _crown_roughness_m(dtm: np.ndarray, measured: np.ndarray, cell_m: float) -> float:
    """:func:`ground_noise_m` at CROWN_SCALE_M, on blocks of ENVELOPE_CELL_M (their mean where most
    of the block is measured): a crown is metres across, and a 2 m plane fit at 0.1 m cells took
    10 s on toledo."""
    f = max(1, int(ENVELOPE_CELL_M / cell_m))
    if f == 1:
        return ground_noise_m(dtm, measured, cell_m, CROWN_SCALE_M)
    coarse = block_means(dtm, measured, f)
    return ground_noise_m(coarse, np.isfinite(coarse), cell_m * f, CROWN_SCALE_M)


def _block_min(z: np.ndarray, f: int) -> np.ndarray:
    """The lowest value of each f x f block (NaN where the block has none)."""
    h, w = z.shape
    hp, wp = -(-h // f) * f, -(-w // f) * f
    padded = np.full((hp, wp), np.inf)
    padded[:h, :w] = np.where(np.isfinite(z), z, np.inf)
    low = padded.reshape(hp // f, f, wp // f, f).min(axis=(1, 3))
    return np.where(np.isfinite(low), low, np.nan)


def despiked(dsm: np.ndarray, hole_value: float | None = None) -> np.ndarray:
    """The DSM's 5 x 5 median (OpenCV), NaN where it has no value: its own speckle (a real meadow's
    tufts and mismatches, single cells metres up) seeds no object. Its holes enter the median as
    ``hole_value`` (default: the DSM's median height)."""
    ok = np.isfinite(dsm)
    fill = hole_value if hole_value is not None else (float(np.nanmedian(dsm[ok])) if ok.any() else 0.0)
    return np.where(ok, cv2.medianBlur(np.where(ok, dsm, fill).astype(np.float32), 5), np.nan)


def object_mask(
    dsm: np.ndarray,
    envelope: np.ndarray,
    dtm: np.ndarray,
    cell_m: float,
    seed_m: float = OBJECT_SEED_M,
    grow_m: float = OBJECT_GROW_M,
) -> np.ndarray:
    """Cells of objects: seeded where the DSM (:func:`despiked`) stands more than ``seed_m`` above
    both the envelope and the ground filter's DTM (it is no ground to the filter either) over
    SEED_MIN_M2 at least (a bush), grown through every connected cell above the envelope by
    ``grow_m`` within ``RIM_REACH_M`` of a seed (a wall's smeared foot, not the terrace a bank holds
    up beside a hall), then by one cell."""
    from skimage.filters import apply_hysteresis_threshold

    ok = np.isfinite(dsm) & np.isfinite(envelope)
    above = np.where(ok, dsm - envelope, 0.0)
    with np.errstate(invalid="ignore"):
        seeds = (above > seed_m) & ~(dsm - dtm <= seed_m)
    if seeds.any():
        labels, _ = ndimage.label(seeds, structure=np.ones((3, 3), bool))
        big = np.bincount(labels.ravel()) * cell_m * cell_m >= SEED_MIN_M2
        big[0] = False
        seeds = big[labels]
    if not seeds.any():
        return np.zeros(dsm.shape, bool)
    reach = distance_cells(~seeds) * cell_m <= RIM_REACH_M
    # hysteresis on the reachable cells: the seeds' own height, the rest at most the seed threshold
    level = np.where(seeds, np.maximum(above, seed_m + 1.0), np.where(reach, np.minimum(above, seed_m), 0.0))
    found = np.asarray(apply_hysteresis_threshold(level, grow_m, seed_m), dtype=np.bool_)
    return np.asarray(ndimage.binary_dilation(found, structure=np.ones((3, 3), bool)))


def bare_earth(dsm: np.ndarray, dtm: np.ndarray, measured: np.ndarray, cell_m: float) -> BareEarth:
    """The DTM ``dtm`` (NaN: none) made bare earth against the DSM ``dsm`` on the same grid.

    ``measured``: the DTM's cells measured from ground points (the rest were filled). Returns the
    cleaned DTM over the same cells as ``dtm`` (see the module's steps)."""
    dtm = np.asarray(dtm, np.float64)
    valid = np.isfinite(dtm)
    measured = np.asarray(measured, bool) & valid
    if not measured.any():
        none = np.zeros(dtm.shape, bool)
        return BareEarth(dtm.astype(np.float32), none, none, none, 0.0, 0, 0)
    noise = ground_noise_m(dtm, measured, cell_m)
    # crowns are rough at a couple of metres where ground (a field's furrows included) is not
    if noise > NOT_GROUND_NOISE_M or _crown_roughness_m(dtm, measured, cell_m) > NOT_GROUND_ROUGH_M:
        return _no_ground_seen(dtm, valid, cell_m, noise)
    seed_m, grow_m = max(OBJECT_SEED_M, 8 * noise), max(OBJECT_GROW_M, 4 * noise)
    # the objects found on a plain opening, then again on the opening that leaves them out (a rim
    # resting on an object's interpolated plateau falls to the ground outside it)
    objects = np.zeros(dtm.shape, bool)
    smooth_dsm = despiked(dsm)
    for _ in range(ENVELOPE_PASSES):
        envelope = lower_envelope(dtm, cell_m, exclude=objects)
        objects = object_mask(smooth_dsm, envelope, dtm, cell_m, seed_m, grow_m)
    with np.errstate(invalid="ignore"):
        near_envelope = dtm - envelope <= max(RIM_TOLERANCE_M, 4 * noise)
    # a rim lies beside an object: elsewhere the envelope only undercuts the ground's own edges (a
    # bank's brow, by up to 0.4 m at 45 deg), and the ground stands
    beside = distance_cells(~objects) * cell_m <= RIM_REACH_M
    ground = measured & ~objects & (near_envelope | ~beside)
    n_rim = int(measured.sum() - ground.sum())
    ground, n_islands = _drop_islands(dtm, ground, objects, cell_m, max(RIM_TOLERANCE_M, 4 * noise))
    ground, n_blobs = _drop_blobs(dtm, ground, cell_m, max(BLOB_MIN_M, BLOB_SIGMAS * noise))
    n_islands += n_blobs
    # nothing is ground, or a few stray cells of it (an all-canopy survey's troughs that the
    # filter kept): never the objects' tops called ground
    if int(ground.sum()) < MIN_GROUND_SHARE * int(valid.sum()):
        return _no_ground_seen(dtm, valid, cell_m, noise)
    # the fill rests on the ground a little way off each object: the ring just beside it holds
    # what is left of the rim, and a thin plate carries a ring's slope far into the gap
    off_objects = distance_cells(~objects) * cell_m > FILL_CLEARANCE_M
    kept = ground & off_objects
    z = fill_smooth(dtm, kept, valid & ~kept)
    z = follow_breaklines(z, kept, valid & ~kept, cell_m)
    z = _denoise(z, valid, cell_m, noise)
    # the ground is never above the surface: a fill bridged under brush from a rise beside it stood
    # up to a metre over toledo's DSM (1.5 % of its cells 0.2 m over); within the noise it may be
    ok = np.isfinite(dsm) & valid
    surface = despiked(dsm, hole_value=float(np.nanmax(z))).astype(np.float64)  # holes: no lower bound
    z = np.where(ok, np.minimum(z, surface + 2.0 * noise), z)
    dist_m = distance_cells(~ground) * cell_m
    bridge_m = bridgeable_m(dtm, ground, cell_m)
    no_ground = objects & valid & (dist_m > bridge_m)
    under = objects & valid
    typical_m = float(np.median(bridge_m[under])) if under.any() else BRIDGE_M
    ground = kept
    return BareEarth(z.astype(np.float32), ground, under, no_ground, noise, n_rim, n_islands, typical_m)


def bridgeable_m(
    z: np.ndarray, ground: np.ndarray, cell_m: float, tolerance_m: float = BRIDGE_TOLERANCE_M
) -> np.ndarray:
    """How far from the ground seen a fill under an object is still within ``tolerance_m`` (RMS),
    per cell of ``z``'s grid, judged on the ground's own relief around it.

    Each ground block (``BRIDGE_BLOCK_M``) is predicted by the mean of the ground on a ring twice
    the distance round it: what a fill gives in the middle of a gap that wide. Its error's RMS is
    taken over the blocks near each place (a Gaussian of the ring's radius, at least
    ``BRIDGE_LOCAL_M``; where none is near, the survey's robust figure), so an object on a bank
    or a cutting is judged by the bank. The bridge is the largest of ``BRIDGE_STEPS_M`` within the
    tolerance at every smaller step (at least ``BRIDGE_MIN_M``); ``BRIDGE_M`` where too little
    ground is seen to judge any step.

    A fixed bridge called the middle of a 60 m wood over rolling ground "interpolated": 0.31 m
    RMS 5-10 m from its edge, 0.51 m at 10-15 m (the synthetic scenes survey). The fill's error
    at a distance d from the ground was close to this ring test's at 2 d on the three synthetic
    surveys (demo, scenes, breaklines). On ground of one steady bend (a crest) the thin plate is
    exact and the test is pessimistic."""
    f = max(1, int(round(BRIDGE_BLOCK_M / cell_m)))
    block_m = f * cell_m
    coarse = block_means(np.asarray(z, np.float64), ground, f)
    known = np.isfinite(coarse)
    values = np.where(known, coarse, 0.0).astype(np.float32)
    weight = known.astype(np.float32)
    bridge = np.zeros(coarse.shape, np.float32)
    open_ = np.ones(coarse.shape, bool)  # within the tolerance at every step so far
    judged_any = False
    for step_m in BRIDGE_STEPS_M:
        r = 2.0 * step_m / block_m
        half = int(math.ceil(r)) + 1
        yy, xx = np.mgrid[-half : half + 1, -half : half + 1]
        ring = (np.abs(np.hypot(yy, xx) - r) < 0.5).astype(np.float32)
        total = cv2.filter2D(values, -1, ring, borderType=cv2.BORDER_CONSTANT)
        n = cv2.filter2D(weight, -1, ring, borderType=cv2.BORDER_CONSTANT)
        judged = known & (n >= 0.9 * float(ring.sum()))
        if int(judged.sum()) < BRIDGE_MIN_SAMPLES:
            break  # too little ground this wide to judge: what was judged stands
        judged_any = True
        err2 = np.where(judged, (coarse - total / np.maximum(n, 1e-6)) ** 2, 0.0).astype(np.float32)
        overall = 1.4826 * float(np.median(np.sqrt(err2[judged])))
        sigma = max(BRIDGE_LOCAL_M, 2.0 * step_m) / block_m
        num = cv2.GaussianBlur(err2, (0, 0), sigma, borderType=cv2.BORDER_CONSTANT)
        den = cv2.GaussianBlur(judged.astype(np.float32), (0, 0), sigma, borderType=cv2.BORDER_CONSTANT)
        near = den > 0.05
        local = np.where(near, np.sqrt(num / np.maximum(den, 1e-6)), overall)
        open_ &= local <= tolerance_m
        bridge[open_] = step_m
        if not open_.any():
            break
    if not judged_any:
        return np.full(z.shape, BRIDGE_M, np.float32)
    if open_.any() and step_m == BRIDGE_STEPS_M[-1]:
        bridge[open_] = BRIDGE_M
    bridge = np.maximum(bridge, BRIDGE_MIN_M)
    h, w = z.shape
    return np.repeat(np.repeat(bridge, f, axis=0), f, axis=1)[:h, :w]


def follow_breaklines(z: np.ndarray, ground: np.ndarray, gaps: np.ndarray, cell_m: float) -> np.ndarray:
    """``z`` with each gap (connected ``gaps`` cells) that a breakline crosses filled along it.

    A thin plate has the least bend: where a bank or a cutting's side runs under a tree or a
    building, it rounds the step into a ramp the width of the gap, too high on one side and too
    low on the other (the synthetic breaklines survey: 0.51 m RMS under trees on its banks, 0.26 m
    on the cells filled beside them). A breakline is straight at a gap's scale: each gap cell is
    the linear interpolation between the ground on either side of it along the breakline's
    direction: near the steep ground's dominant gradient (a structure tensor) round the gap, the
    one along which the ground's profile across the breakline is the same where it enters the gap
    and where it leaves (on the breaklines survey within 0.5 deg of the drawn bank's, where the
    gradients alone were up to 7 deg off); only where that steep ground lies on both sides of the
    gap, coherent in direction, and the two profiles agree. Elsewhere,
    and where the line finds no ground within ``BREAK_SPAN_M`` on a side, the thin plate stands."""
    # gaps joined by a thin strip (a survey's edge, filled along it) are judged each on its own:
    # the strips are opened away and keep the thin plate
    r = max(1, int(round(BREAK_NECK_M / cell_m)))
    disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
    cores = cv2.morphologyEx(np.asarray(gaps, np.uint8), cv2.MORPH_OPEN, disc) > 0
    labels, n = ndimage.label(cores, structure=np.ones((3, 3), bool))
    if n == 0:
        return z
    out = np.array(z, np.float64, copy=True)
    ring_px = int(math.ceil(BREAK_RING_M / cell_m))
    sizes = np.bincount(labels.ravel())
    for i, box in enumerate(ndimage.find_objects(labels), start=1):
        if box is None or sizes[i] * cell_m * cell_m < BREAK_GAP_M2:
            continue
        r0, r1 = max(0, box[0].start - ring_px), min(z.shape[0], box[0].stop + ring_px)
        c0, c1 = max(0, box[1].start - ring_px), min(z.shape[1], box[1].stop + ring_px)
        gap = labels[r0:r1, c0:c1] == i
        filled = _along_breakline(out[r0:r1, c0:c1], ground[r0:r1, c0:c1], gap, cell_m, ring_px)
        if filled is not None:
            part = out[r0:r1, c0:c1]
            take = gap & np.isfinite(filled)
            part[take] = filled[take]
    return out


def _along_breakline(
    z: np.ndarray, ground: np.ndarray, gap: np.ndarray, cell_m: float, ring_px: int
) -> np.ndarray | None:
    """The ``gap`` cells of a window interpolated along the breakline crossing it (NaN where the
    line meets no ground), or None when no breakline crosses it."""
    ring = ground & (distance_cells(~gap) <= ring_px)
    if int(ring.sum()) * cell_m * cell_m < BREAK_MIN_M2:
        return None
    sigma = max(0.5, BREAK_SMOOTH_M / cell_m)
    # the ground's slope only: blurred over the ground cells alone (normalised), away from the gap
    # (whose values are the thin plate's) and from the data's edge
    have = ground.astype(np.float64)
    ref = float(np.median(z[ground]))
    num = cv2.GaussianBlur(np.where(ground, z - ref, 0.0), (0, 0), sigma)
    den = cv2.GaussianBlur(have, (0, 0), sigma)
    smooth = num / np.maximum(den, 1e-6)
    gy, gx = (np.asarray(g, np.float64) for g in np.gradient(smooth, cell_m))
    steep = ring & (np.hypot(gx, gy) > BREAK_SLOPE) & (distance_cells(ground) > 2 * sigma)
    if int(steep.sum()) * cell_m * cell_m < BREAK_MIN_M2:
        return None
    jxx, jyy, jxy = (float(np.sum(a[steep])) for a in (gx * gx, gy * gy, gx * gy))
    coherence = math.hypot(jxx - jyy, 2 * jxy) / max(jxx + jyy, 1e-12)
    if coherence < BREAK_COHERENCE:
        return None
    theta = 0.5 * math.atan2(2 * jxy, jxx - jyy)  # the gradient's direction, (x: columns, y: rows)
    # the breakline passes through the gap: steep ground on both sides of it along the line, level
    # with it across
    gr, gc = np.nonzero(gap)
    sr, sc = np.nonzero(steep)
    a_gap, q_gap = _line_frame(gr, gc, theta)
    a_steep, q_steep = _line_frame(sr, sc, theta)
    level = (q_steep >= q_gap.min()) & (q_steep <= q_gap.max())
    before, after = level & (a_steep < a_gap.min()), level & (a_steep > a_gap.max())
    if not (before.any() and after.any()):
        return None
    # the direction again: the one along which the ground's profile across the breakline where it
    # enters the gap is the profile where it leaves (the gradients' direction is a few degrees off
    # a bank's, a metre and more across a gap 20 m long)
    best = _matching_direction(z, ring, gap, theta, cell_m)
    if best is None:
        return None  # the ground entering and leaving is no one straight breakline
    return _interpolate_along(z, ground, gap, -math.sin(best), math.cos(best), cell_m)


def _matching_direction(z: np.ndarray, ring: np.ndarray, gap: np.ndarray, theta: float, cell_m: float) -> float | None:
    """The gradient direction (radians) within BREAK_TURN_DEG of ``theta`` along whose
    perpendicular the ``ring`` ground's profile across the gap, on the gap's two sides, agrees best
    (less a straight line across: the ground's slope along the breakline); None when the best
    still disagrees by more than BREAK_PROFILE_M (RMS, a straight line across taken out), or too
    little of the profile is seen."""
    rr, cc = np.nonzero(ring)
    zr = z[rr, cc]
    gr, gc = np.nonzero(gap)
    step = max(1, len(gr) // 20000)
    gr, gc = gr[::step], gc[::step]
    bin_px = 2.0
    best, best_cost = None, math.inf
    for dtheta in np.radians(np.arange(-BREAK_TURN_DEG, BREAK_TURN_DEG + 0.01, 0.5)):
        t = theta + float(dtheta)
        a, q = _line_frame(rr, cc, t)
        a_gap, q_gap = _line_frame(gr, gc, t)
        q0, q1 = float(q_gap.min()), float(q_gap.max())
        level = (q >= q0) & (q <= q1)
        sides = [level & (a < a_gap.min()), level & (a > a_gap.max())]
        n_bins = int((q1 - q0) / bin_px) + 1
        means = []
        for side in sides:
            k = ((q[side] - q0) / bin_px).astype(np.int64)
            n = np.bincount(k, minlength=n_bins)
            total = np.bincount(k, zr[side], minlength=n_bins)
            means.append(np.where(n >= 3, total / np.maximum(n, 1), np.nan))
        d = means[1] - means[0]
        seen = np.isfinite(d)
        if int(seen.sum()) * bin_px * cell_m < BREAK_PROFILE_SEEN_M:
            continue
        # less a straight line across: the ground's slope along the breakline, and its bend (the
        # two sides 10-20 m apart on rolling ground tilt differently)
        x = np.flatnonzero(seen).astype(np.float64)
        fit = np.polyval(np.polyfit(x, d[seen], 1), x)
        cost = float(np.sqrt(np.mean((d[seen] - fit) ** 2)))
        if cost < best_cost:
            best, best_cost = t, cost
    return best if best_cost <= BREAK_PROFILE_M else None


def _line_frame(rows: np.ndarray, cols: np.ndarray, theta: float) -> tuple[np.ndarray, np.ndarray]:
    """Cells' coordinates (cells) along a breakline whose gradient points at ``theta`` (radians,
    x: columns, y: rows) and across it."""
    ux, uy = -math.sin(theta), math.cos(theta)
    return cols * ux + rows * uy, -cols * uy + rows * ux


def _interpolate_along(
    z: np.ndarray, ground: np.ndarray, gap: np.ndarray, ux: float, uy: float, cell_m: float
) -> np.ndarray:
    """Each ``gap`` cell linearly between the nearest ``ground`` on either side along (ux, uy), on
    lines one cell apart (the window resampled into the line's frame and back, scipy)."""
    h, w = z.shape
    corners = np.array([[0, 0], [0, h], [w, 0], [w, h]], np.float64)
    a_c, q_c = corners @ [ux, uy], corners @ [-uy, ux]
    a = np.arange(math.floor(a_c.min()) - 1, math.ceil(a_c.max()) + 2, dtype=np.float64)
    q = np.arange(math.floor(q_c.min()) - 1, math.ceil(q_c.max()) + 2, dtype=np.float64)
    aa, qq = np.meshgrid(a, q)  # one row a line along the breakline
    cols, rows = aa * ux - qq * uy, aa * uy + qq * ux
    known = ndimage.map_coordinates(ground.astype(np.float32), [rows, cols], order=0, cval=0.0) > 0.5
    values = ndimage.map_coordinates(np.where(ground, z, 0.0), [rows, cols], order=0, cval=0.0)
    idx = np.arange(len(a))[None, :].repeat(len(q), axis=0)
    left = np.maximum.accumulate(np.where(known, idx, -1), axis=1)
    right = np.minimum.accumulate(np.where(known, idx, len(a))[:, ::-1], axis=1)[:, ::-1]
    ok = (left >= 0) & (right < len(a)) & ((right - left) * cell_m <= BREAK_SPAN_M)
    lc, rc = np.clip(left, 0, len(a) - 1), np.clip(right, 0, len(a) - 1)
    zl, zr = np.take_along_axis(values, lc, 1), np.take_along_axis(values, rc, 1)
    t = np.where(right > left, (idx - left) / np.maximum(right - left, 1), 0.0)
    line = np.where(ok, zl + (zr - zl) * t, np.nan)
    # back to the window's cells: bilinear in the line frame (NaN next to a line with no ground)
    rr, cc = np.nonzero(gap)
    a_at = cc * ux + rr * uy - a[0]
    q_at = -cc * uy + rr * ux - q[0]
    out = np.full(z.shape, np.nan)
    out[rr, cc] = ndimage.map_coordinates(line, [q_at, a_at], order=1, cval=np.nan)
    return out


def _no_ground_seen(dtm: np.ndarray, valid: np.ndarray, cell_m: float, noise_m: float) -> BareEarth:
    """What "ground" the filter kept is rougher than any ground (a survey all canopy: the crowns'
    floor called ground): the DTM is the least-squares plane through each BLOCK_M block's lowest
    cell, every cell under an object with no ground seen."""
    f = max(1, int(round(BLOCK_M / cell_m)))
    low = _block_min(np.where(valid, dtm, np.nan), f)
    rows, cols = np.nonzero(np.isfinite(low))
    z = np.full(dtm.shape, np.nan)
    if len(rows):
        x, y = (cols + 0.5) * f, (rows + 0.5) * f
        a = np.c_[np.ones(len(x)), x, y] if len(x) >= 3 else np.ones((len(x), 1))
        coef, *_ = np.linalg.lstsq(a, low[rows, cols], rcond=None)
        rr, cc = np.nonzero(valid)
        terms = np.c_[np.ones(len(rr)), cc + 0.5, rr + 0.5] if len(coef) == 3 else np.ones((len(rr), 1))
        z[rr, cc] = terms @ coef
    none = np.zeros(dtm.shape, bool)
    return BareEarth(z.astype(np.float32), none, valid.copy(), valid.copy(), noise_m, int(valid.sum()), 0)


def _drop_blobs(z: np.ndarray, ground: np.ndarray, cell_m: float, tolerance_m: float) -> tuple[np.ndarray, int]:
    """``ground`` without the small blobs (under BLOB_M2) of cells that stand off their smoothed
    neighbourhood by more than ``tolerance_m``: a depth map's mismatches at a photo's edge, each a
    bump or a pit a few decimetres across inside measured ground. A breakline disagrees with its
    smoothed self too, but along its whole length: it is no small blob, and stays."""
    if not ground.any():
        return ground, 0
    base = np.where(ground, z, np.nan)
    fill = float(np.nanmedian(base))
    despiked = np.where(ground, cv2.medianBlur(np.where(ground, base, fill).astype(np.float32), 5), np.nan)
    # spikes and pits a few cells across first: off their own 5 x 5 median (a bank's ramp is its
    # own median, a kink nearly so)
    with np.errstate(invalid="ignore"):
        spikes = ground & (np.abs(z - despiked) > tolerance_m)
    n_spikes = 0
    if spikes.any():
        spiked = np.asarray(ndimage.binary_dilation(spikes, iterations=1)) & ground
        n_spikes = int(spiked.sum())
        ground = ground & ~spiked
    with np.errstate(invalid="ignore"):
        off = ground & (np.abs(z - _smoothed(despiked, ground, cell_m, BLOB_SMOOTH_M)) > tolerance_m)
    if not off.any():
        return ground, n_spikes
    # pieces within BLOB_JOIN_M of each other are one: a bank's brow, broken by noise into pieces
    # that each disagree with the plane fitted across it, is a line, not a row of blobs
    joined = ndimage.binary_dilation(off, iterations=max(1, int(round(BLOB_JOIN_M / cell_m))))
    labels, n = ndimage.label(joined, structure=np.ones((3, 3), bool))
    sizes = np.bincount(labels[off].ravel(), minlength=n + 1)
    extent = np.bincount(labels.ravel(), minlength=n + 1)
    small = np.flatnonzero((sizes * cell_m * cell_m < BLOB_M2) & (extent * cell_m * cell_m < 4 * BLOB_M2))
    small = small[small > 0]
    if not len(small):
        return ground, n_spikes
    # the blob and a ring of a cell or two round it: its foot is as wrong, just less
    dropped = ndimage.binary_dilation(np.isin(labels, small) & off, iterations=2) & ground
    return ground & ~dropped, n_spikes + int(dropped.sum())


def _coarse_harmonic(z: np.ndarray, known: np.ndarray, cell_m: float) -> np.ndarray:
    """A harmonic surface through the ``known`` cells, solved on blocks of ENVELOPE_CELL_M (their
    means) and carried back bilinearly: a reference to judge islands by, in a fraction of the
    memory of a fine solve."""
    f = max(1, int(ENVELOPE_CELL_M / cell_m))
    if f == 1:
        return fill_harmonic(z, known)
    h, w = z.shape
    hp, wp = -(-h // f) * f, -(-w // f) * f
    total, n = block_sums(z, known, f)
    coarse = fill_harmonic(np.where(n > 0, total / np.maximum(n, 1), np.nan), n > 0)
    coarse = np.where(np.isfinite(coarse), coarse, np.nanmean(coarse))
    return np.asarray(cv2.resize(coarse.astype(np.float64), (wp, hp), interpolation=cv2.INTER_LINEAR)[:h, :w])


def _drop_islands(
    z: np.ndarray, ground: np.ndarray, objects: np.ndarray, cell_m: float, tolerance_m: float
) -> tuple[np.ndarray, int]:
    """``ground`` without its islands that stand off a harmonic surface through the rest of the
    ground: small ones (under ISLAND_M2) off by more than ``tolerance_m``, and ones that objects
    enclose (under ENCLOSED_ISLAND_M2) standing more than ENCLOSED_ISLAND_M above it.

    A wood matched well (the synthetic wide wood at full resolution) leaves a smooth crown top of
    8 m² inside it called ground, 7.4 m up: the thin plate rose 5 m round it. A courtyard or a
    clearing is ground at the ground's height and stays."""
    labels, n = ndimage.label(ground, structure=np.ones((3, 3), bool))
    if n <= 1:
        return ground, 0
    sizes = np.bincount(labels.ravel())
    small = np.flatnonzero(sizes * cell_m * cell_m < ISLAND_M2)
    enclosed_cells = ndimage.binary_fill_holes(objects) & ~objects
    inside_share = ndimage.mean(enclosed_cells, labels, np.arange(n + 1))
    enclosed = np.flatnonzero((np.asarray(inside_share) >= 0.9) & (sizes * cell_m * cell_m < ENCLOSED_ISLAND_M2))
    candidates = np.union1d(small, enclosed)
    candidates = candidates[candidates > 0]
    if not len(candidates):
        return ground, 0
    is_candidate = np.isin(labels, candidates)
    rest = _coarse_harmonic(z, ground & ~is_candidate, cell_m)
    with np.errstate(invalid="ignore"):
        off = np.abs(z - rest) > tolerance_m
        high = z - rest > max(tolerance_m, ENCLOSED_ISLAND_M)
    # an island is dropped when most of it stands off the rest
    drop_small = small[np.asarray(ndimage.mean(off, labels, small)) > 0.5] if len(small) else small
    drop_enclosed = enclosed[np.asarray(ndimage.mean(high, labels, enclosed)) > 0.5] if len(enclosed) else enclosed
    drop = np.union1d(drop_small, drop_enclosed)
    drop = drop[drop > 0]
    if not len(drop):
        return ground, 0
    dropped = np.isin(labels, drop)
    return ground & ~dropped, int(dropped.sum())


def _denoise(z: np.ndarray, valid: np.ndarray, cell_m: float, noise_m: float) -> np.ndarray:
    """The DTM smoothed (:func:`_smoothed`) where it is smooth, kept where it is not: each cell
    moves to the smoothed value by a weight that falls as the two differ by more than
    ``BREAK_SIGMAS`` times the ground's noise. Speckle averages out; a step of many noise sigmas
    (a bank, a kerb, a cutting's edge) stays."""
    if noise_m <= 0 or not valid.any():
        return z
    # single-cell spikes and pits first (a 5 x 5 median, OpenCV): they stand many sigmas off the
    # smoothed surface, and the rule below would keep them as it keeps a breakline
    fill = float(np.nanmedian(z[valid]))
    z = np.where(valid, cv2.medianBlur(np.where(valid, z, fill).astype(np.float32), 5), np.nan).astype(np.float64)
    smooth = _smoothed(z, valid, cell_m)
    with np.errstate(invalid="ignore"):
        w = np.exp(-(((z - smooth) / (BREAK_SIGMAS * noise_m)) ** 2))
    out = np.where(np.isfinite(w), w * smooth + (1 - w) * z, z)
    return np.where(valid, out, np.nan)
