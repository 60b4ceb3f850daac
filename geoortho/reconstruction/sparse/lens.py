"""The lens test after mapping: the focal length's drift from the metadata, and distortion held at
zero where the photos do not support it (a trial adjustment on thinned points)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace
from typing import Any

import numpy as np

from geoortho.core.colmap import load_pycolmap
from geoortho.reconstruction.sparse.adjust import (
    Mapped,
    adjusted_copy,
    ba_options,
    camera_focal_px,
    mean_reprojection_error_px,
)


def focal_drift(rec: Any, priors_px: dict[int, float]) -> dict[int, float]:
    """Camera id → focal length change from its prior, percent."""
    return {
        cid: 100.0 * (camera_focal_px(cam) / priors_px[cid] - 1.0)
        for cid, cam in rec.cameras.items()
        if cid in priors_px and priors_px[cid] > 0
    }


def probe_free_focal(rec: Any, refine_distortion: bool = True) -> dict[int, float]:
    """Focal lengths a bundle adjustment reaches when it may refine them (on a copy)."""
    pc = load_pycolmap()
    opts = ba_options(refine_distortion=refine_distortion, robust=True)
    probe = adjusted_copy(rec, opts, pc.BundleAdjustmentGauge.TWO_CAMS_FROM_WORLD)
    return {cid: camera_focal_px(cam) for cid, cam in probe.cameras.items()}


#: A camera's lens distortion is held at zero when holding it costs less than this share of the
#: block's mean reprojection error. Measured: the synthetic survey's distortion-free camera
#: reprojects 0.1578/0.1578 px (seed 3) and 0.1454/0.1453 px (seed 6) with k1, k2 refined/held,
#: while the refined k1 (-0.0027, -0.0038) domed the open ground +0.34/+0.51 GSD; toledo's
#: FC6310 (k1 -0.10) reprojects 0.76 px refined and 2.51 px held, the hard preset's camera (k1
#: -0.02) 0.220 and 0.262 px. The test costs 5 % of the sfm stage (hard preset: 2.7 of 50.5 s).
DISTORTION_SUPPORT_PCT = 1.0
#: The trial adjustments start from the mapper's converged block: a few iterations settle them.
DISTORTION_TRIAL_ITERATIONS = 10


def hold_unsupported_distortion(mapped: Mapped, notes: list[str]) -> Mapped:
    """Hold at zero the lens distortion the photos cannot tell from none.

    On a nadir block, radial distortion trades against a dome of the whole block: a camera with
    none is given a k1 by the GPS priors' or the mapper's path, which bends the ground by a
    fraction of a GSD and that no reprojection residual shows. Each camera's distortion is tested
    on copies: the block adjusted with it refined, against it zeroed and held (the other cameras
    as they are). Both trials refine the focal length, even where the mapping held it: a focal
    length held wrong (a bad EXIF value) is otherwise partly absorbed by the distortion, which then
    looks supported (synthetic, EXIF focal 11 % long: 0.172 px held, 0.169 px refined). Where holding
    the distortion costs under DISTORTION_SUPPORT_PCT of the reprojection error, it is held at zero
    from here on (the block continues from that adjustment, its focal length held as before)."""
    pc = load_pycolmap()
    rec = mapped.rec
    cams = [cid for cid, cam in rec.cameras.items() if len(cam.extra_params_idxs())]
    if not cams or rec.num_reg_images() < 3:
        return mapped
    # split-merge: the submodels tested each lens on blocks of the same flight; where they agree,
    # the merged block (the test's time grows with photos^1.45) takes their answer
    decided = {cid: mapped.distortion_decided[cid] for cid in cams if cid in mapped.distortion_decided}
    for cid, (held_there, _, n_subs) in sorted(decided.items()):
        decided_by = f"its {n_subs} submodels each decided" if n_subs > 1 else "its submodel decided"
        notes.append(
            f"camera {cid}: lens distortion {'held at zero' if held_there else 'refined'} as {decided_by} "
            "(not tested again on the merged block)"
        )
    cams = [cid for cid in cams if cid not in decided]
    gauge = pc.BundleAdjustmentGauge.TWO_CAMS_FROM_WORLD
    trial = DISTORTION_TRIAL_ITERATIONS

    def zeroed(src: Any, ids: Sequence[int]) -> Any:
        out = pc.Reconstruction(src)
        for cid in ids:
            cam = out.camera(cid)
            params = np.array(cam.params)
            params[list(cam.extra_params_idxs())] = 0.0
            cam.params = params
        return out

    # The trials compare two adjustments of the same points: a sample of them, spread over every
    # photo's frame (where distortion shows), tells the same (see TRIAL_POINTS_PER_PHOTO).
    test: dict[int, tuple[float, float]] = {cid: figures for cid, (_, figures, _) in decided.items()}
    if cams:
        sample = _thinned(rec, TRIAL_POINTS_PER_PHOTO)
        refined_px = mean_reprojection_error_px(adjusted_copy(sample, ba_options(iterations=trial), gauge))
        for cid in cams:
            held_copy = adjusted_copy(
                zeroed(sample, [cid]), ba_options(refine_distortion=False, iterations=trial), gauge
            )
            test[cid] = (refined_px, mean_reprojection_error_px(held_copy))
    tested = frozenset(cid for cid in cams if test[cid][1] <= test[cid][0] * (1.0 + DISTORTION_SUPPORT_PCT / 100.0))
    held = tested | frozenset(cid for cid, (held_there, _, _) in decided.items() if held_there)
    if not held:
        return replace(mapped, distortion_test=test)
    opts = ba_options(refine_focal=not mapped.focal_held, refine_distortion=False)
    block = adjusted_copy(zeroed(rec, sorted(held)), opts, gauge)
    for cid in sorted(tested):
        a, b = test[cid]
        notes.append(
            f"camera {cid}: lens distortion held at zero: the photos do not support it (reprojection "
            f"{a:.3f} px refined, {b:.3f} px without, over a sample of {sample.num_points3D()} points; "
            "refined, it would bend the block into a dome)"
        )
    return replace(mapped, rec=block, distortion_test=test, distortion_held=held)


#: The distortion trials adjust at most this many points per photo, the longest tracks in each
#: cell of a TRIAL_GRID over its frame. Measured (the test's time, the held/refined ratio of
#: reprojection, all points → the sample): the medium survey 60 → 36 s, held both ways (1.000);
#: toledo 21 → 12 s, refined both ways (1.26 → 1.30 and 3.21 → 3.35), GCP RMSE unchanged. The
#: sample's reprojection is not the block's (toledo 0.88 against 0.75 px): only the ratio counts.
TRIAL_POINTS_PER_PHOTO = 1200
TRIAL_GRID = (8, 6)


def _thinned(rec: Any, per_photo: int) -> Any:
    """A copy of the block keeping, for each photo, at most ``per_photo`` of the points it sees:
    in each cell of a TRIAL_GRID over its frame, those of longest track (the strongest ties)."""
    pc = load_pycolmap()
    nx, ny = TRIAL_GRID
    per_cell = max(1, per_photo // (nx * ny))
    track = {pid: p.track.length() for pid, p in rec.points3D.items()}
    keep: set[int] = set()
    for iid in rec.reg_image_ids():
        im = rec.image(iid)
        cam = rec.camera(im.camera_id)
        seen = [(q.point3D_id, q.xy) for q in im.points2D if q.has_point3D()]
        if len(seen) <= per_photo:
            keep.update(pid for pid, _ in seen)
            continue
        ids = np.array([pid for pid, _ in seen], np.int64)
        xy = np.array([xy for _, xy in seen], float)
        cell = np.clip((xy[:, 0] * nx / cam.width).astype(int), 0, nx - 1) * ny + np.clip(
            (xy[:, 1] * ny / cam.height).astype(int), 0, ny - 1
        )
        length = np.array([track[int(pid)] for pid in ids])
        order = np.lexsort((-length, cell))  # by cell, longest track first within it
        rank = np.arange(order.size) - np.searchsorted(cell[order], cell[order], side="left")
        keep.update(int(pid) for pid in ids[order[rank < per_cell]])
    out = pc.Reconstruction(rec)
    for pid in track:
        if pid not in keep:
            out.delete_point3D(pid)
    return out
