"""Benchmark: photo metadata reading and footprint computation.

Prints photos per second, peak memory, and the ratio to the issue's targets
(metadata >= 500 photos/s warm; footprints >= 20,000/s flat, >= 1,000/s on a DSM)
and, for metadata, to exifread (a plain pure-Python reader) on the same files.

    python benchmarks/bench_footprints.py [--photos 10000]
"""

from __future__ import annotations

import argparse
import os
import resource
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import shapely


def peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def bench_metadata(n: int, work: Path) -> None:
    from geoortho.photos.metadata import read_photos
    from geoortho.synthetic.survey import synth

    survey = synth(work / "survey", preset="tiny", seed=7)
    sources = sorted(survey.images.iterdir())
    folder = work / "many"
    folder.mkdir()
    for i in range(n):  # hard links: a warm disk, as the target says
        os.link(sources[i % len(sources)], folder / f"P{i:06d}.JPG")
    t = time.perf_counter()
    ps = read_photos(folder)
    dt = time.perf_counter() - t
    rate = len(ps.photos) / dt
    # baseline: exifread, in-process, on a sample
    import exifread

    sample = sorted(folder.iterdir())[:500]
    t = time.perf_counter()
    for p in sample:
        with open(p, "rb") as f:
            exifread.process_file(f, details=False)
    base = len(sample) / (time.perf_counter() - t)
    print(
        f"metadata: {len(ps.photos)} photos in {dt:.2f} s = {rate:,.0f} photos/s "
        f"(target 500: x{rate / 500:.1f}; exifread alone {base:,.0f}/s: x{rate / base:.1f}); "
        f"peak RSS {peak_rss_mb():.0f} MB"
    )


def synthetic_cameras(n: int, rng: np.random.Generator):
    from geoortho.core.camera import Intrinsics, Pose, PosedCamera

    intr = Intrinsics(5472, 3648, 3666.7)
    side = int(np.ceil(np.sqrt(n)))
    cams = []
    for i in range(n):
        x, y = (i % side) * 20.0 + 500, (i // side) * 20.0 + 500
        pose = Pose.from_ypr(
            (x, y, 150.0 + rng.normal(0, 1)), rng.uniform(-180, 180), -90 + rng.normal(0, 3), rng.normal(0, 1)
        )
        cams.append(PosedCamera(intr, pose))
    return cams, side


def bench_footprints(n: int) -> None:
    from rasterio.transform import from_origin

    from geoortho.core.surface import FlatSurface, GridSurface
    from geoortho.photos.footprint import compute_footprints

    rng = np.random.default_rng(0)
    cams, side = synthetic_cameras(n, rng)
    for label, surface, target in [
        ("flat", FlatSurface(0.0), 20_000),
        ("DSM", None, 1_000),
    ]:
        if surface is None:
            extent = side * 20.0 + 1000
            cells = int(extent / 0.5)
            yy, xx = np.mgrid[0:cells, 0:cells] * 0.5
            grid = (5 * np.sin(xx / 80) + 4 * np.cos(yy / 60)).astype(np.float32)
            grid[(xx % 50 < 10) & (yy % 50 < 10)] += 8.0  # buildings
            surface = GridSurface(grid, from_origin(0.0, extent, 0.5, 0.5))
            compute_footprints(cams[:10], surface)  # warm the coarse-max cache
        t = time.perf_counter()
        table = compute_footprints(cams, surface)
        polys = shapely.polygons(table.rings)
        dt = time.perf_counter() - t
        rate = n / dt
        # baseline: the same code called one photo at a time (a plain per-photo loop)
        k = min(n, 300)
        t = time.perf_counter()
        for c in cams[:k]:
            shapely.polygons(compute_footprints([c], surface).rings)
        base = k / (time.perf_counter() - t)
        print(
            f"footprints on {label}: {n} photos in {dt:.2f} s = {rate:,.0f} photos/s "
            f"(target {target:,}: x{rate / target:.1f}; per-photo loop {base:,.0f}/s: x{rate / base:.1f}); "
            f"valid {shapely.is_valid(polys).mean():.3f}; peak RSS {peak_rss_mb():.0f} MB"
        )


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--photos", type=int, default=10_000)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as d:
        bench_metadata(args.photos, Path(d))
    bench_footprints(args.photos)
    return 0


if __name__ == "__main__":
    sys.exit(main())
