"""Benchmark: DSM gridding and ground filtering throughput, peak memory.

Makes a synthetic cloud (rolling terrain, buildings, trees; default 10 M
points) as a LAS file, then in one run:

* gridding alone (max per cell, one core) against the plain baseline —
  ``scipy.stats.binned_statistic_2d(..., "max")`` on the same arrays;
  target >= 5 M points/s;
* the whole ``dem`` run (read LAS in chunks, DSM, SMRF, DTM, fill, COGs)
  in a child process, so its peak memory is its own.

    python benchmarks/bench_dem.py [--points 10e6] [--resolution-m 0.25]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

# the CLI in a child that reports its own peak memory on its last stderr line
CHILD = """
import json, resource, runpy, sys
sys.argv = json.loads(sys.argv[1])
try:
    runpy.run_module("geoortho", run_name="__main__")
finally:
    print("peak_rss_kb", resource.getrusage(resource.RUSAGE_SELF).ru_maxrss, file=sys.stderr)
"""


def make_cloud(path: Path, n: int, seed: int = 0) -> float:
    """A LAS of ``n`` points over a square of ~8 points/m²; returns the side in metres."""
    import laspy
    from pyproj import CRS

    rng = np.random.default_rng(seed)
    side = float(np.sqrt(n / 8.0))
    header = laspy.LasHeader(point_format=1, version="1.4")
    header.offsets = [500000.0, 4000000.0, 0.0]
    header.scales = [0.001, 0.001, 0.001]
    header.add_crs(CRS.from_epsg(32629))
    with laspy.open(str(path), mode="w", header=header) as w:
        for start in range(0, n, 2_000_000):
            k = min(2_000_000, n - start)
            x, y = rng.uniform(0, side, k), rng.uniform(0, side, k)
            z = 100 + 3 * np.sin(x / 60) * np.cos(y / 80)
            z = z + np.where((x % 50 < 20) & (y % 50 < 20), 8.0, 0.0)  # buildings 20 m across, every 50 m
            p = laspy.ScaleAwarePointRecord.zeros(k, header=header)
            p.x, p.y, p.z = x + 500000, y + 4000000, z
            w.write_points(p)
    return side


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--points", type=float, default=10e6)
    ap.add_argument("--resolution-m", type=float, default=0.5)
    args = ap.parse_args()
    n = int(args.points)
    from scipy.stats import binned_statistic_2d

    from geoortho.elevation import Grid, grid_points

    with tempfile.TemporaryDirectory() as d:
        las = Path(d) / "cloud.las"
        t = time.perf_counter()
        side = make_cloud(las, n)
        print(f"cloud: {n:,} points over {side:.0f} m x {side:.0f} m, written in {time.perf_counter() - t:.1f} s")

        rng = np.random.default_rng(1)
        m = min(n, 10_000_000)
        x, y = rng.uniform(0, side, m), rng.uniform(0, side, m)
        z = rng.normal(100, 5, m)
        grid = Grid.covering(0, 0, side, side, args.resolution_m)
        t = time.perf_counter()
        ours = grid_points(x, y, z, grid, "max")
        t_ours = time.perf_counter() - t
        t = time.perf_counter()
        base = binned_statistic_2d(
            x,
            y,
            z,
            "max",
            bins=[grid.cols, grid.rows],
            range=[[grid.x0, grid.x0 + grid.cols * grid.cell], [grid.y0 - grid.rows * grid.cell, grid.y0]],
        ).statistic
        t_base = time.perf_counter() - t
        same = np.allclose(np.nan_to_num(np.flipud(base.T)), np.nan_to_num(ours))
        print(
            f"gridding (max, {grid.cols} x {grid.rows} cells, one core): {m / t_ours / 1e6:.1f} M points/s; "
            f"scipy binned_statistic_2d: {m / t_base / 1e6:.2f} M points/s; ratio x{t_base / t_ours:.1f}; "
            f"same grid: {same} (target >= 5 M points/s)"
        )
        del x, y, z, ours, base

        for label, extra in (("DSM only", []), ("DSM + SMRF + DTM", ["--dtm", str(Path(d) / "dtm.tif")])):
            argv = [
                "geoortho",
                "dem",
                "--points",
                str(las),
                "--output",
                str(Path(d) / "dsm.tif"),
                "--resolution-m",
                str(args.resolution_m),
                "--json",
                "--quiet",
                *extra,
            ]
            cmd = [sys.executable, "-c", CHILD, json.dumps(argv)]
            t = time.perf_counter()
            r = subprocess.run(cmd, capture_output=True, text=True)
            dt = time.perf_counter() - t
            if r.returncode:
                print(r.stderr)
                return 1
            peak_kb = int(r.stderr.strip().splitlines()[-1].split()[-1])
            res = json.loads(r.stdout)
            print(
                f"dem {label}: {dt:.1f} s, {n / dt / 1e6:.2f} M points/s end to end (read, grid, fill, write), "
                f"peak RSS {peak_kb / 1024:.0f} MB; ground {res['n_ground']:,} of {res['n_points']:,}"
            )
    return 0


if __name__ == "__main__":
    sys.exit(main())
