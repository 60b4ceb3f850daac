"""One pair's depths: the two photos rectified (``cv2.stereoRectify``), the disparity range probed,
matched by semi-global block matching (``cv2.StereoSGBM``, left-right checked) where there is texture,
and its points.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from geoortho.errors import InputError
from geoortho.reconstruction.dense_pairs import View

MIN_PAIR_POINTS = 100  # a pair that gives fewer points matched a sliver or nothing
# Local contrast (grey-level standard deviation over 7 x 7 px) below which a pixel has no texture to
# match: SGBM's smoothness term would fill such areas (calm water, snow, fresh tarmac) from their
# edges with made-up depths. A flat synthetic pond measures ~1 DN (90th percentile 1.5); real fields
# 2-5 DN at the 5th percentile (toledo_dji: 3 DN would drop 4 % of the DSM cells, 2 DN 1 %).
_MIN_TEXTURE_DN = 2.0
_TEXTURE_WINDOW_PX = 7
#: SGBM's block (px, at the working size). A wider block fattens the nearer surface: a roof or a
#: crown grows by about half a block over the ground beside it, and pairs of one reference fatten
#: alike, so the agreement test keeps it. Issue 74, demo survey (DSM |dZ| p95 within 3 m of
#: objects): block 5 and tolerance 0.01 0.72 m; block 3 0.63; tolerance 0.005 0.61; both 0.53;
#: block 3 and tolerance 0.003 0.47. Real photos (toledo_dji): measured DSM cells 66.8 -> 64.1 %,
#: DTM cells off its 5 m median 0.57 -> 0.44 %, dense 173 -> 109 s.
_BLOCK_PX = 3


def read_view(view: View) -> np.ndarray:
    img = cv2.imread(str(view.path), cv2.IMREAD_COLOR)
    if img is None:
        raise InputError("cannot be decoded", path=view.path)
    if (img.shape[1], img.shape[0]) != view.size:
        img = cv2.resize(img, view.size, interpolation=cv2.INTER_AREA)
    return img


def _sgbm(left: np.ndarray, right: np.ndarray, min_d: int, n_d: int) -> np.ndarray:
    """Disparities (px, float; 0 or less where none) of ``left`` against ``right`` in
    ``[min_d, min_d + n_d)``: the right image shifted by the smallest disparity, so that SGBM
    searches only the range that matters (and an image narrower than minDisparity +
    numDisparities makes OpenCV fail)."""
    shifted = np.zeros_like(right)
    shifted[:, min_d:] = right[:, : right.shape[1] - min_d]
    bs = _BLOCK_PX
    sgbm = cv2.StereoSGBM.create(
        minDisparity=0,
        numDisparities=n_d,
        blockSize=bs,
        P1=8 * 3 * bs * bs,
        P2=32 * 3 * bs * bs,
        disp12MaxDiff=1,
        uniquenessRatio=10,
        speckleWindowSize=100,
        speckleRange=2,
        mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY,
    )
    raw = sgbm.compute(left, shifted)
    return np.where(raw > 0, raw.astype(np.float32) / 16.0 + min_d, 0.0).astype(np.float32)


#: Objects may stand this share of the depth above the ground the tie points bound: a wood
#: whose crowns gave no tie point (fine repetitive leaves) stands 7-12 m under a 30 m flight.
_MAX_RELIEF_SHARE = 0.45
#: Disparities found on this share of a probe's valid pixels nearer than the tie points widen
#: the search: fewer are mismatches.
_MIN_PROBE_SHARE = 0.002


def _probe_near(
    left: np.ndarray, right: np.ndarray, valid: np.ndarray, f: float, baseline: float, zmin: float, zmax: float
) -> float:
    """The nearest depth really in the pair, searched down to ``_MAX_RELIEF_SHARE`` above the
    ground (or as near as the canvas allows) at half resolution: a quarter of the pixels and half
    the disparities, an eighth of a full search per level. ``zmin`` when nothing nearer is found.

    The depth range comes from the SfM's tie points, and a wood or a car park may have none:
    searched only there, its crowns matched the ground below and were dropped as inconsistent
    (the synthetic wood: 5 % of its cells measured, the DSM 9.6 m low over it)."""
    small_l = cv2.resize(left, None, fx=0.5, fy=0.5, interpolation=cv2.INTER_AREA)
    small_r = cv2.resize(right, None, fx=0.5, fy=0.5, interpolation=cv2.INTER_AREA)
    fh, width = 0.5 * f, small_l.shape[1]
    # as near as the half-size canvas can search (and the full one, which searches the answer):
    # worked out for the full canvas alone, the half one's range, rounded up to 16 disparities, was
    # wider than it on most pairs of a small photo and the probe was skipped, so whether a roof
    # without tie points stood in the DSM turned on a rounding (the tiny survey: in one run of two)
    z_probe = max(
        (1.0 - _MAX_RELIEF_SHARE) * zmax,
        _nearest_searchable(width, fh, baseline, zmax),
        _nearest_searchable(left.shape[1], f, baseline, zmax),
    )
    if z_probe >= zmin * 0.97:
        return zmin
    min_d, n_d = _disparity_range(fh, baseline, z_probe, zmax)
    n_d = min(n_d, (width // 2) // 16 * 16)  # the rounding's last 16, where z_probe is the canvas's limit
    if n_d < 16 or min_d + n_d >= width:
        return zmin
    small_v = cv2.resize(valid, (width, small_l.shape[0]), interpolation=cv2.INTER_NEAREST) > 0
    disp = _sgbm(small_l, small_r, min_d, n_d)
    ok = (disp > 0) & small_v
    z = fh * baseline / disp[ok]
    near = z[z < zmin * 0.97]
    if len(near) < max(1.0, _MIN_PROBE_SHARE * ok.sum()):
        return zmin
    return max(z_probe, float(np.percentile(near, 1)) * 0.95)


def _disparity_range(f: float, baseline: float, zmin: float, zmax: float) -> tuple[int, int]:
    """SGBM's smallest disparity and number of disparities (a multiple of 16) for depths
    ``zmin``..``zmax``, with 15 % to spare each way."""
    min_d = max(0, int(math.floor(f * baseline / zmax * 0.85)))
    return min_d, max(16, int(math.ceil((f * baseline / zmin * 1.15 - min_d) / 16.0)) * 16)


def _nearest_searchable(width_px: int, f: float, baseline: float, zmax: float) -> float:
    """The nearest depth a canvas ``width_px`` wide can search: at most half its width of
    disparities beyond the farthest depth's."""
    min_d, _ = _disparity_range(f, baseline, zmax, zmax)
    return f * baseline * 1.15 / (min_d + (width_px // 2) // 16 * 16)


def pair_points(
    a: View, b: View, img_a: np.ndarray, img_b: np.ndarray, depth_range: tuple[float, float]
) -> tuple[np.ndarray, np.ndarray, float] | None:
    """Points (local frame) and colours (BGR) of one rectified pair, ``a`` as the left image, and
    the nearest depth searched (the tie points', or nearer where a probe found relief);
    None when the pair rectifies the other way round (then ``b`` must be the left image)."""
    rect = _rectify(a, b)
    if rect is None:
        return None
    R1, R2, P1, P2, size = rect
    horizontal = abs(P2[0, 3]) > abs(P2[1, 3])
    shift = P2[0, 3] if horizontal else P2[1, 3]
    if shift > 0:
        return None
    f = float(P1[0, 0])
    baseline = abs(float(shift)) / f
    zmin, zmax = depth_range
    if not 0 < zmin <= zmax:  # points behind or at the camera: a broken pose, not a stereo pair
        return None
    map_a = cv2.initUndistortRectifyMap(a.K, a.dist, R1, P1, size, cv2.CV_32FC1)
    map_b = cv2.initUndistortRectifyMap(b.K, b.dist, R2, P2, size, cv2.CV_32FC1)  # one canvas for both
    left = cv2.remap(img_a, map_a[0], map_a[1], cv2.INTER_LINEAR)
    right = cv2.remap(img_b, map_b[0], map_b[1], cv2.INTER_LINEAR)
    # Texture is measured in the photo (its border reflected), not on the canvas: there the black
    # beyond the photo's edge lends texture to a flat pond cut by the edge. SGBM's blocks that
    # straddle the edge match the black too, so the photo's edge band is dropped as well.
    inside = cv2.remap(np.full(img_a.shape[:2], 255, np.uint8), map_a[0], map_a[1], cv2.INTER_NEAREST)
    inside = cv2.erode(inside, np.ones((_TEXTURE_WINDOW_PX, _TEXTURE_WINDOW_PX), np.uint8))
    textured = cv2.remap(textured_mask(img_a).astype(np.uint8) * 255, map_a[0], map_a[1], cv2.INTER_NEAREST)
    valid = np.minimum(inside, textured)
    if not horizontal:  # vertical pairs: transposed, SGBM searches along rows
        left, right, valid = cv2.transpose(left), cv2.transpose(right), cv2.transpose(valid)
    # A search range past the canvas (toledo, two bodies: the smallest disparity alone was
    # wider than the image): SGBM cannot search it and the overlap is a sliver at best.
    min_d, n_d = _disparity_range(f, baseline, zmin, zmax)
    if n_d > left.shape[1] // 2 or min_d + n_d >= left.shape[1]:
        return None
    zmin = _probe_near(left, right, valid, f, baseline, zmin, zmax)
    min_d, n_d = _disparity_range(f, baseline, zmin, zmax)
    disp = _sgbm(left, right, min_d, n_d)
    ok = (disp > 0) & (valid > 0)
    if not horizontal:
        disp = np.asarray(cv2.transpose(disp))
        ok = np.asarray(cv2.transpose(ok.astype(np.uint8))) > 0
        left = np.asarray(cv2.transpose(left))
    rr, cc = np.nonzero(ok)
    z = f * baseline / disp[rr, cc]
    keep = (z > zmin * 0.8) & (z < zmax * 1.2)  # loose: a's rectified depth, the range is ref's
    rr, cc, z = rr[keep], cc[keep], z[keep]

    rect = np.c_[(cc - P1[0, 2]) * z / f, (rr - P1[1, 2]) * z / f, z]
    world = (rect @ R1) @ a.R.T + a.C  # rectified -> camera a -> local frame
    return world.astype(np.float32), left[rr, cc], zmin


#: A rectified canvas holds at most this many times the reference photo's pixels (the focal
#: length is lowered to fit): a pair turned 45 degrees needs about twice.
_MAX_CANVAS_RATIO = 2.5


def _rectify(a: View, b: View) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, tuple[int, int]] | None:
    """Rectifying rotations and projections of the pair (``a`` left) on a canvas that holds the
    part of ``a`` that ``b`` can match, at ``a``'s own focal length.

    OpenCV's ``stereoRectify`` keeps the photo's size and zooms until the canvas holds only valid
    pixels (alpha 0): for a pair whose headings differ (a camera turning freely from photo to
    photo), that zoom reached 5 to 20 times, and the disparities left the canvas. Its rotations
    are kept; the projections are made here."""
    R = b.R.T @ a.R
    T = (b.R.T @ (a.C - b.C)).reshape(3, 1)
    R1, R2, _, _, _, _, _ = cv2.stereoRectify(
        a.K, a.dist, b.K, b.dist, a.size, R, T, flags=cv2.CALIB_ZERO_DISPARITY, alpha=-1
    )
    t = (R2 @ T).ravel()  # a's centre in the rectified frame of b
    horizontal = abs(t[0]) > abs(t[1])
    f = float(a.K[0, 0])

    def extent(v: View, rot: np.ndarray) -> np.ndarray:
        w, h = v.size
        n = 16
        edge = np.linspace(0, 1, n)
        xs = np.r_[edge * (w - 1), np.full(n, w - 1.0), edge[::-1] * (w - 1), np.zeros(n)]
        ys = np.r_[np.zeros(n), edge * (h - 1), np.full(n, h - 1.0), edge[::-1] * (h - 1)]
        P = np.array([[f, 0, 0], [0, f, 0], [0, 0, 1]], float)
        out = cv2.undistortPoints(np.c_[xs, ys].reshape(-1, 1, 2).astype(np.float64), v.K, v.dist, R=rot, P=P)
        pts = out.reshape(-1, 2)
        return np.array([pts[:, 0].min(), pts[:, 1].min(), pts[:, 0].max(), pts[:, 1].max()])

    ea, eb = extent(a, R1), extent(b, R2)
    if not (np.isfinite(ea).all() and np.isfinite(eb).all()):
        return None
    # across the baseline both photos must hold the row; along it, a's pixels are the ones matched
    if horizontal:
        x0, x1, y0, y1 = ea[0], ea[2], max(ea[1], eb[1]), min(ea[3], eb[3])
    else:
        x0, x1, y0, y1 = max(ea[0], eb[0]), min(ea[2], eb[2]), ea[1], ea[3]
    if x1 - x0 < 32 or y1 - y0 < 32:
        return None
    scale = min(1.0, math.sqrt(_MAX_CANVAS_RATIO * a.size[0] * a.size[1] / ((x1 - x0) * (y1 - y0))))
    fs = f * scale
    size = (int(math.ceil((x1 - x0) * scale)) + 1, int(math.ceil((y1 - y0) * scale)) + 1)
    P1 = np.array([[fs, 0, -x0 * scale, 0], [0, fs, -y0 * scale, 0], [0, 0, 1, 0]], float)
    P2 = P1.copy()
    P2[0, 3] = fs * t[0] if horizontal else 0.0
    P2[1, 3] = 0.0 if horizontal else fs * t[1]
    return R1, R2, P1, P2, size


def textured_mask(img: np.ndarray) -> np.ndarray:
    """Pixels with enough local contrast to be matched (see ``_MIN_TEXTURE_DN``)."""
    grey = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY).astype(np.float32)
    k = (_TEXTURE_WINDOW_PX, _TEXTURE_WINDOW_PX)
    mean = cv2.blur(grey, k)
    var = cv2.blur(grey * grey, k) - mean * mean
    return np.asarray(var >= _MIN_TEXTURE_DN**2)
