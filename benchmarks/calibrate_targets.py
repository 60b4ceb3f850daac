"""Calibration of gcp-find's model-fit thresholds on real backgrounds: how they were chosen.

Positives: a target (checkerboard, cross, circle, or a coded ArUco marker) rendered into a crop
of a real drone photo (``../shared/data/real``: toledo, Brighton, Mini 4 Pro, findgcp) — 8 × 8
supersampled from :func:`geoortho.gcp.markers.target_reflectance`, as neutral paint (the same level in
each channel of the colour crop), then the whole crop motion-blurred
with synth's kernel (half the trials, up to half the marker side), a saturating glare spot on a
third, sensor noise and JPEG — at a random size (10–40 px), rotation, perspective shear and
contrast, predicted a few pixels off as gcp-find would; saved as a colour JPEG (chroma at half
resolution) and fitted as gcp-find fits it (coded markers in grey, other targets in
:func:`geoortho.gcp.detect.paint_channel`). Impostors: the same crops with nothing
rendered (real texture), another target type rendered (a wrong ``--target``), or for coded
markers another id. Every fit's measures are kept, so the printout shows the separation each
threshold leaves (``geoortho.gcp.targets.THRESHOLDS``), not just the outcome.

    python benchmarks/calibrate_targets.py [--trials 200] [--kinds checkerboard,cross,circle,aruco]
        [--csv fits.csv] [--seed 0] [--near]

Accepted = what gcp-find would write. Recall counts targets accepted within 1 px of the truth;
precision counts impostors accepted and targets accepted > 3 px off as wrong.
"""

from __future__ import annotations

import argparse
import csv
import math
import sys
import time
import zlib
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np

REAL = Path(__file__).resolve().parents[2] / "shared" / "data" / "real"
CROP = 640  # the photo's blur is estimated on the whole crop, as on a photo
DICTIONARY = "DICT_4X4_50"


def real_photos() -> list[Path]:
    return sorted(p for p in REAL.glob("*/images/*") if p.suffix.lower() in (".jpg", ".jpeg"))


def trial(args: tuple[int, str, str, bool]) -> dict:
    """One fit: ``role`` positive (target rendered), texture (nothing), wrong-kind or wrong-id.
    ``near``: searched as gcp-find searches a coded marker the photo's other markers place (the
    place known to about a pixel: :func:`geoortho.gcp.detect.local_prediction`)."""
    seed, kind, role, near = args
    from geoortho.gcp.blur import estimate_motion_blur, motion_kernel
    from geoortho.gcp.detect import paint_channel
    from geoortho.gcp.look import marker_affine
    from geoortho.gcp.markers import CODED, TARGETS, marker_cells, paint_target, target_half_extent
    from geoortho.gcp.targets import THRESHOLDS, fit_target

    rng = np.random.default_rng(seed)
    photos = real_photos()
    photo = cv2.imread(str(photos[seed % len(photos)]), cv2.IMREAD_COLOR)
    h, w = photo.shape[:2]
    y0, x0 = int(rng.integers(0, h - CROP)), int(rng.integers(0, w - CROP))
    img = photo[y0 : y0 + CROP, x0 : x0 + CROP].astype(np.float64)
    side = float(rng.uniform(10, 40))
    yaw = rng.uniform(0, 2 * math.pi)
    rot = np.array([[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]])
    tilt = np.diag([1.0, -1.0]) @ np.array([[1.0, rng.normal(0, 0.05)], [0.0, 1 + rng.normal(0, 0.08)]])
    base = side * rot @ tilt  # pixels per side along east and north, as a SearchWindow gives it
    cx, cy = CROP / 2 + rng.uniform(-60, 60), CROP / 2 + rng.uniform(-60, 60)
    marker_id = int(rng.integers(0, 50))
    cells = marker_cells(DICTIONARY, marker_id) if kind in CODED else None
    painted = {"positive": kind, "wrong-kind": None, "wrong-id": kind, "texture": None}[role]
    if role == "wrong-kind":
        painted = str(rng.choice([k for k in TARGETS if k not in (kind, "apriltag")]))
    if painted is not None:
        p_cells = cells
        if painted in CODED:
            other = marker_id if role != "wrong-id" else int((marker_id + rng.integers(1, 50)) % 50)
            p_cells = marker_cells(DICTIONARY, other)
        white, black = rng.uniform(150, 250), rng.uniform(5, 70)
        if painted == "cross":
            white = rng.uniform(200, 250)  # white paint on the ground
        A_true = marker_affine(base, float(rng.uniform(0, 360)), float(1 + rng.normal(0, 0.04)), 0.0, 0.0)
        for c in range(3):  # neutral paint: the same level in every channel, over coloured ground
            paint_target(img[:, :, c], painted, cx, cy, A_true, p_cells, white, black)
    blur_px = float(rng.uniform(side / 6, side / 2)) if rng.random() < 0.5 else 0.0
    glare = painted is not None and rng.random() < 0.3
    if glare:
        gx, gy = cx + rng.normal(0, 0.25) * side, cy + rng.normal(0, 0.25) * side
        sigma = side * rng.uniform(0.15, 0.3)
        yy, xx = np.mgrid[0:CROP, 0:CROP]
        img += (255 * rng.uniform(0.5, 1.0) * np.exp(-((xx - gx) ** 2 + (yy - gy) ** 2) / (2 * sigma**2)))[:, :, None]
    if blur_px > 0:
        img = cv2.filter2D(img.astype(np.float32), -1, motion_kernel(blur_px, float(rng.uniform(0, 180))))
    img = np.clip(img + rng.normal(0, 2.0, img.shape), 0, 255).astype(np.uint8)
    # colour JPEG as a drone writes it (chroma at half resolution, 4:2:0)
    img = cv2.imdecode(cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 90])[1], cv2.IMREAD_COLOR)
    gray = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    est = estimate_motion_blur(gray)
    img = gray if kind in CODED else paint_channel(img)  # what gcp-find fits in
    err = side * 0.3
    px, py = cx + rng.normal(0, err), cy + rng.normal(0, err)
    radius = 1.5 * side + rng.uniform(4, 30)
    place = None
    if near:  # from a stream of its own: the scene is the same trial's
        dx, dy = np.random.default_rng([seed, 2]).normal(0, 1.0, 2)
        px, py = cx + dx, cy + dy
        tol = max(0.25 * side, 4.0)
        place = (px, py, tol)
        radius = tol + np.abs(base).sum(axis=1).max() * target_half_extent(kind) * 1.2 + est[0] / 2 + 3
    box = (
        max(0, int(px - radius)),
        max(0, int(py - radius)),
        min(CROP, int(px + radius) + 1),
        min(CROP, int(py + radius) + 1),
    )
    t = time.perf_counter()
    fit = fit_target(
        img,
        box,
        kind,
        base,
        cells=cells,
        dictionary=DICTIONARY if kind in CODED else "",
        marker_id=marker_id,
        blur=est,
        predicted_xy=(px, py),
        near=place,
    )
    if fit is not None and place is not None and not fit.reason:
        off = math.hypot(fit.x_px - px, fit.y_px - py)
        if off > place[2]:  # as gcp-find refuses it
            fit = replace(fit, reason=f"{off:.1f} px from the place")
    row = dict(kind=kind, role=role, painted=painted or "", side_px=side, blur_px=blur_px, glare=glare, seed=seed)
    row["seconds"] = time.perf_counter() - t
    if fit is None:
        return row | dict(accepted=False, reason="no fit")
    measures = (
        "score",
        "contrast_dn",
        "worst_part",
        "shape_margin",
        "id_margin",
        "id_score",
        "position_margin",
        "reason",
    )
    row |= {k: getattr(fit, k) for k in measures}
    row["fit_blur_px"] = fit.blur_px
    row["est_blur_px"] = est[0]
    row["accepted"] = not fit.reason
    row["error_px"] = math.hypot(fit.x_px - cx, fit.y_px - cy) if role == "positive" else math.nan
    row["thresholds"] = ";".join(f"{k}={v}" for k, v in THRESHOLDS.items())
    return row


def summarise(rows: list[dict]) -> None:
    from geoortho.gcp.targets import THRESHOLDS

    print("thresholds:", ", ".join(f"{k} {v}" for k, v in THRESHOLDS.items()))
    for kind in sorted({r["kind"] for r in rows}):
        mine = [r for r in rows if r["kind"] == kind]
        pos = [r for r in mine if r["role"] == "positive"]
        acc = [r for r in pos if r["accepted"]]
        good = [r for r in acc if r["error_px"] <= 1.0]
        off = [r for r in acc if r["error_px"] > 3.0]
        imp = [r for r in mine if r["role"] != "positive"]
        imp_acc = [r for r in imp if r["accepted"]]
        n_wrong = len(off) + len(imp_acc)
        n_acc = len(acc) + len(imp_acc)
        print(
            f"{kind}: positives {len(pos)}, recall {len(good) / max(1, len(pos)):.3f}, "
            f"mean error {np.mean([r['error_px'] for r in good]) if good else math.nan:.3f} px; "
            f"impostors {len(imp)} ({', '.join(sorted({r['role'] for r in imp}))}), accepted {len(imp_acc)}; "
            f"precision {(n_acc - n_wrong) / max(1, n_acc):.3f} "
            f"(accepted 1-3 px off: {len(acc) - len(good) - len(off)}); "
            f"{np.mean([r['seconds'] for r in mine]):.2f} s per fit"
        )
        # separation per measure: the true targets' low end against the impostors' high end
        for key in ("score", "contrast_dn", "worst_part", "shape_margin", "id_margin"):
            tv = [r[key] for r in pos if key in r and np.isfinite(r.get(key, math.nan)) and r["error_px"] <= 1.0]
            iv = [r[key] for r in imp if key in r and np.isfinite(r.get(key, math.nan))]
            if tv and iv:
                print(
                    f"  {key:13s} targets p5 {np.percentile(tv, 5):7.3f} min {min(tv):7.3f}   "
                    f"impostors p95 {np.percentile(iv, 95):7.3f} max {max(iv):7.3f}"
                )
        misses = [r for r in pos if not (r["accepted"] and r["error_px"] <= 1.0)]
        for r in misses[:8]:
            print(
                f"  miss: side {r['side_px']:.0f} blur {r['blur_px']:.1f} glare {r['glare']} "
                f"err {r.get('error_px', math.nan):.2f}: {r.get('reason', '')}"
            )
        for r in imp_acc[:8]:
            print(f"  impostor accepted: {r['role']} {r['painted']} side {r['side_px']:.0f} score {r['score']:.2f}")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=200, help="per kind and role")
    ap.add_argument("--kinds", default="checkerboard,cross,circle,aruco")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--csv", type=Path)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--near", action="store_true", help="fit where the photo's other markers place it")
    args = ap.parse_args()
    if not real_photos():
        print(f"no real photos under {REAL}", file=sys.stderr)
        return 2
    jobs = []
    for kind in args.kinds.split(","):
        roles = ["positive", "texture", "wrong-kind"] + (["wrong-id"] if kind in ("aruco", "apriltag") else [])
        for role in roles:
            for i in range(args.trials):
                seed = zlib.crc32(f"{args.seed} {kind} {role} {i}".encode())
                jobs.append((seed, kind, role, args.near))
    t = time.perf_counter()
    with ProcessPoolExecutor(args.workers) as ex:
        rows = list(ex.map(trial, jobs, chunksize=4))
    print(f"{len(rows)} fits in {time.perf_counter() - t:.0f} s")
    summarise(rows)
    if args.csv:
        keys = sorted({k for r in rows for k in r})
        with args.csv.open("w", newline="") as f:
            wr = csv.DictWriter(f, fieldnames=keys)
            wr.writeheader()
            wr.writerows(rows)
    return 0


if __name__ == "__main__":
    sys.exit(main())
