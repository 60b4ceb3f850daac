"""Spike for issue 20: rectified pairs + OpenCV SGBM -> dense cloud; measured against the truth.

python dense_spike.py SFM_DIR IMAGES OUT_DIR TRUTH_DIR [max_image_size]
"""

import json
import sys
import time
from pathlib import Path

import cv2
import numpy as np

from geoortho.orthophoto.cameras import cameras_from_sfm


def scaled_K(intr, s):
    K = intr.matrix.copy()
    K[0, 0] *= s
    K[1, 1] *= s
    K[0, 2] = (K[0, 2] + 0.5) * s - 0.5
    K[1, 2] = (K[1, 2] + 0.5) * s - 0.5
    return K


def load(cam, s):
    img = cv2.imread(str(cam.path), cv2.IMREAD_COLOR)
    if s != 1.0:
        img = cv2.resize(img, None, fx=s, fy=s, interpolation=cv2.INTER_AREA)
    return img


def pair_points(A, B, imgA, imgB, s, zrange, origin):
    KA, KB = scaled_K(A.intrinsics, s), scaled_K(B.intrinsics, s)
    dA, dB = A.intrinsics.dist_coeffs, B.intrinsics.dist_coeffs
    size = (imgA.shape[1], imgA.shape[0])
    RA, RB = A.pose.rotation, B.pose.rotation
    R = RB.T @ RA
    T = RB.T @ (A.pose.center - B.pose.center)
    R1, R2, P1, P2, Q, _, _ = cv2.stereoRectify(KA, dA.reshape(-1, 1), KB, dB.reshape(-1, 1), size, R, T.reshape(3, 1), flags=cv2.CALIB_ZERO_DISPARITY, alpha=0)
    horizontal = abs(P2[0, 3]) > abs(P2[1, 3])
    sign = P2[0, 3] if horizontal else P2[1, 3]
    if sign > 0:
        return None  # the other order of the pair does it
    m1 = cv2.initUndistortRectifyMap(KA, dA, R1, P1, size, cv2.CV_32FC1)
    m2 = cv2.initUndistortRectifyMap(KB, dB, R2, P2, size, cv2.CV_32FC1)
    L = cv2.remap(imgA, *m1, cv2.INTER_LINEAR)
    Rr = cv2.remap(imgB, *m2, cv2.INTER_LINEAR)
    validL = cv2.remap(np.full(imgA.shape[:2], 255, np.uint8), *m1, cv2.INTER_NEAREST)
    if not horizontal:
        L, Rr, validL = cv2.transpose(L), cv2.transpose(Rr), cv2.transpose(validL)
    f = P1[0, 0]
    baseline = abs(sign) / f
    zmin, zmax = zrange
    dmin, dmax = f * baseline / zmax, f * baseline / zmin
    mind = int(np.floor(dmin * 0.85))
    num = int(np.ceil((dmax * 1.15 - mind) / 16.0)) * 16
    num = max(16, num)
    if num > 1024 or mind < 0 or f > 20 * KA[0, 0]:
        print("skip pair", A.name, B.name, f, baseline, zrange, mind, num)
        return None
    if num > L.shape[1] // 2:
        print("skip wide pair", A.name, B.name, mind, num, L.shape)
        return None
    # The right image shifted by the smallest disparity: SGBM searches only the range that matters.
    shifted = np.zeros_like(Rr)
    shifted[:, mind:] = Rr[:, : Rr.shape[1] - mind]
    Rr = shifted
    bs = 5
    sgbm = cv2.StereoSGBM_create(minDisparity=0, numDisparities=num, blockSize=bs, P1=8 * 3 * bs * bs,
                                 P2=32 * 3 * bs * bs, disp12MaxDiff=1, uniquenessRatio=10, speckleWindowSize=100,
                                 speckleRange=2, mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY)
    raw = sgbm.compute(L, Rr)
    disp = raw.astype(np.float32) / 16.0 + mind
    ok = (raw > 0) & (validL > 0)
    if not horizontal:
        disp, ok, L = cv2.transpose(disp), cv2.transpose(ok.astype(np.uint8)).astype(bool), cv2.transpose(L)
    rr, cc = np.nonzero(ok)
    d = disp[rr, cc]
    Z = f * baseline / d
    cx, cy = P1[0, 2], P1[1, 2]
    X = (cc - cx) * Z / f
    Y = (rr - cy) * Z / f
    rect = np.c_[X, Y, Z]
    camA = rect @ R1  # R1^T applied row-wise: rect = R1 camA
    world = camA @ RA.T + (A.pose.center - origin)
    col = L[rr, cc][:, ::-1]
    keep = (Z > zmin * 0.8) & (Z < zmax * 1.2)
    return world[keep], col[keep]


MIN_VIEWS = 2
TOL = 0.01


def main():
    sfm_dir, images, out, truth = map(Path, sys.argv[1:5])
    max_size = int(sys.argv[5]) if len(sys.argv) > 5 else 1024
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    cams, crs, pts, _ = cameras_from_sfm(sfm_dir, images)
    origin = np.round(np.mean([c.pose.center for c in cams], axis=0), -2)
    n = len(cams)
    s = min(1.0, max_size / max(cams[0].intrinsics.width_px, cams[0].intrinsics.height_px))
    # visibility of the sparse points
    vis = []
    depths = []
    for c in cams:
        px, dep = c.project(pts)
        w, h = c.intrinsics.width_px, c.intrinsics.height_px
        v = (dep > 0) & (px[:, 0] >= 0) & (px[:, 0] < w) & (px[:, 1] >= 0) & (px[:, 1] < h)
        vis.append(v)
        depths.append(dep)
    centers = np.array([c.pose.center for c in cams])
    pairs = []
    for i in range(n):
        h = np.median(depths[i][vis[i]])
        cand = []
        for j in range(n):
            if j == i:
                continue
            shared = (vis[i] & vis[j]).sum()
            if shared < 30:
                continue
            b = np.linalg.norm(centers[i] - centers[j])
            ratio = b / h
            ang = np.degrees(np.arccos(np.clip(cams[i].pose.rotation[:, 2] @ cams[j].pose.rotation[:, 2], -1, 1)))
            if ratio < 0.08 or ang > 20:
                continue
            score = shared * min(1.0, ratio / 0.25)
            cand.append((score, j))
        cand.sort(reverse=True)
        for _, j in cand[:3]:
            pairs.append((i, j))
    print(f"{n} cameras, {len(pairs)} pairs, scale {s:.3f}; setup {time.perf_counter() - t0:.1f}s")
    t1 = time.perf_counter()
    cache = {}

    def img(k):
        if k not in cache:
            if len(cache) > 8:
                cache.pop(next(iter(cache)))
            cache[k] = load(cams[k], s)
        return cache[k]

    neigh = {}
    for i, j in pairs:
        neigh.setdefault(i, []).append(j)
    allp, allc = [], []
    n_raw = 0
    for i, js in neigh.items():
        if len(js) < MIN_VIEWS:
            continue
        w = int(round(cams[i].intrinsics.width_px * s))
        h = int(round(cams[i].intrinsics.height_px * s))
        zmaps, per_pair = [], []
        for j in js:
            shared = vis[i] & vis[j]
            zr = (np.percentile(depths[i][shared], 1), np.percentile(depths[i][shared], 99))
            r = pair_points(cams[i], cams[j], img(i), img(j), s, zr, origin)
            if r is None:
                r = pair_points(cams[j], cams[i], img(j), img(i), s, zr, origin)
            if r is None or not len(r[0]):
                continue
            n_raw += len(r[0])
            px, dep = cams[i].project(r[0] + origin)
            c = np.round((px[:, 0] + 0.5) * s - 0.5).astype(np.int64)
            rr = np.round((px[:, 1] + 0.5) * s - 0.5).astype(np.int64)
            inside = (c >= 0) & (c < w) & (rr >= 0) & (rr < h) & (dep > 0)
            z = np.full(h * w, np.inf)
            np.minimum.at(z, rr[inside] * w + c[inside], dep[inside])
            zmaps.append(np.where(np.isfinite(z), z, np.nan))
            per_pair.append((r[0], r[1], rr * w + c, dep, inside))
        if len(zmaps) < MIN_VIEWS:
            continue
        stack = np.vstack(zmaps)
        med = np.nanmedian(stack, axis=0)
        tol = TOL * med
        agree = (np.abs(stack - med) <= tol).sum(axis=0)
        for pts_w, col, idx, dep, inside in per_pair:
            k = inside.copy()
            k[inside] = (agree[idx[inside]] >= MIN_VIEWS) & (np.abs(dep[inside] - med[idx[inside]]) <= tol[idx[inside]])
            allp.append(pts_w[k])
            allc.append(col[k])
    P = np.concatenate(allp) + origin
    C = np.concatenate(allc)
    t_pairs = time.perf_counter() - t1
    print(f"{len(neigh)} reference photos, {n_raw} raw points, {len(P)} consistent in {t_pairs:.1f}s")
    from geoortho.core.pointcloud import write_las

    write_las(out / "dense.laz", P, crs=crs, rgb=C.astype(np.float64) / 255.0)
    print(json.dumps({"points": len(P), "seconds": time.perf_counter() - t0}))


if __name__ == "__main__":
    main()
