"""Benchmark: geoortho dense against the sfm stage on the same survey, same run.

Makes (or takes) a synthetic survey, runs ``python -m geoortho sfm`` (GCPs from gcp-find, as the
demo does) and then ``python -m geoortho dense`` on its model, each in a child process, and prints:

* wall time of each, and dense / sfm (issue 46: <= 1), each at its own defaults as ``run``
  uses them (``--sfm-max-image-size`` to change sfm's);
* depth-map megapixels per second (the photos at ``--max-image-size``, one map per photo);
* fusion points per second (consistent points merged into voxels per second of merging);
* peak memory: the dense process, its largest worker, and their sum for the workers in flight
  (target: < 2 GB on medium).

    python benchmarks/bench_dense.py [--preset small|medium] [--survey DIR] [--max-image-size 1024]
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from pathlib import Path

from bench_sfm import OURS, _child


def _geoortho(*args: str) -> tuple[float, int]:
    """Run ``geoortho args`` in a child (bench_sfm's runner); wall seconds and its own peak RSS (kB)."""
    dt, _, peak_kb = _child(OURS, ["geoortho", *args, "--quiet"])
    return dt, peak_kb


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--preset", default="small")
    ap.add_argument("--survey", type=Path, help="an existing synth output folder")
    ap.add_argument("--max-image-size", type=int, default=1024, help="dense's (its default)")
    ap.add_argument("--sfm-max-image-size", type=int, help="default: sfm's own, as run uses it")
    ap.add_argument("--workers", type=int, default=0)
    args = ap.parse_args()
    work = Path(tempfile.mkdtemp(prefix="bench_dense_"))
    survey = args.survey or work / "survey"
    if args.survey is None:
        t = time.perf_counter()
        _geoortho("synth", "--output", str(survey), "--preset", args.preset, "--seed", "1")
        print(f"synth {args.preset}: {time.perf_counter() - t:.0f} s")
    images = survey / "images"
    n_photos = len(list(images.glob("*.JPG")))
    _geoortho(
        "gcp-find", "--images", str(images), "--gcp-file", str(survey / "truth" / "gcp_utm.txt"),
        "--output", str(work / "gcp_list.txt"),
    )  # fmt: skip
    t_sfm, rss_sfm = _geoortho(
        "sfm", "--images", str(images), "--output", str(work / "sfm"), "--gcp-list", str(work / "gcp_list.txt"),
        "--workers", str(args.workers),
        *(["--max-image-size", str(args.sfm_max_image_size)] if args.sfm_max_image_size else []),
    )  # fmt: skip
    t_dense, rss_dense = _geoortho(
        "dense", "--sfm", str(work / "sfm"), "--images", str(images), "--output", str(work / "dense.laz"),
        "--max-image-size", str(args.max_image_size), "--workers", str(args.workers),
    )  # fmt: skip
    rep = json.loads((work / "dense_report.json").read_text())
    sec = rep["seconds"]
    workers = args.workers or os.cpu_count() or 1
    worker_mb = rep["peak_memory_mb"]["largest_worker"]
    sfm_px = args.sfm_max_image_size or "sfm's default"
    print(
        f"survey: {survey} ({n_photos} photos), sfm at {sfm_px} px, depth maps at {args.max_image_size} px, "
        f"{workers} workers"
    )
    print(f"sfm   : {t_sfm:7.1f} s   peak {rss_sfm / 1024:6.0f} MB")
    print(
        f"dense : {t_dense:7.1f} s   peak {rss_dense / 1024:6.0f} MB (main) + {worker_mb:.0f} MB (largest worker)"
        f" -> <= {rss_dense / 1024 + workers * worker_mb:.0f} MB with {workers} in flight"
    )
    print(f"dense / sfm: {t_dense / t_sfm:.2f} (target <= 1)")
    print(
        f"depth maps: {rep['depth_maps']} of {rep['photos']} photos, {rep['depth_map_megapixels']:.1f} Mpx in "
        f"{sec['depth_maps']:.1f} s = {rep['depth_map_megapixels'] / sec['depth_maps']:.2f} Mpx/s"
    )
    print(
        f"fusion: {rep['points_consistent']:,} consistent points -> {rep['points_written']:,} in {sec['fusion']:.1f} s"
        f" = {rep['points_consistent'] / max(sec['fusion'], 1e-9) / 1e6:.1f} M points/s"
    )
    print(f"outputs in {work}")


if __name__ == "__main__":
    main()
