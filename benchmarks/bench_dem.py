"""Benchmark: DSM gridding and ground filtering throughput, peak memory.

Makes a synthetic cloud (rolling terrain, buildings, trees; default 10 M
points) as a LAS file, then in one run:

* gridding alone (max per cell, one core) against the plain baseline —
  ``scipy.stats.binned_statistic_2d(..., "max")`` on the same arrays;
  target >= 5 M points/s;
* the whole ``dem`` run (read LAS in chunks, DSM, SMRF, DTM, fill, COGs)
  in a child process, so its peak memory is its own;
* the same cloud with 10 far outliers (100 km off, one 10 km up): same DSM and DTM, and
  the peak memory against the clean run (issue 23);
* the same DSM + DTM run made in tiles (``geoortho.elevation.tiles``, which ``dem`` uses on its own
  past 8 M cells) and held whole, each in a child: peak memory, time, and how far the
  grids differ (issue 25: < 1 GB for 50 M points at any resolution; ``--points 50e6``).

    python benchmarks/bench_dem.py [--points 10e6] [--resolution-m 0.25] [--skip-outliers]
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
from bench_sfm import OURS


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
    ap.add_argument("--outliers", type=int, default=10, help="far outlier points in the outlier comparison")
    ap.add_argument("--skip-outliers", action="store_true", help="not the outlier comparison (long at 50 M points)")
    args = ap.parse_args()
    n = int(args.points)
    from scipy.stats import binned_statistic_2d

    from geoortho.elevation.gridding import Grid, grid_points

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
            cmd = [sys.executable, "-c", OURS, json.dumps(argv)]
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
        _tiles_vs_whole(las, Path(d), args.resolution_m, n)
        if not args.skip_outliers:
            _outliers(las, Path(d), args.resolution_m, args.outliers)
    return 0


def _tiles_vs_whole(las: Path, d: Path, resolution_m: float, n: int) -> None:
    """The DSM + DTM run in tiles and held whole: memory, time, and the grids' differences."""
    import rasterio

    runs = {}
    for label, cells in (("tiles", 0), ("whole", 10**12)):
        out, dtm = d / f"{label}.tif", d / f"{label}_dtm.tif"
        tiles = f"set:geoortho.elevation.tiles.WHOLE_GRID_MAX_CELLS={cells}"
        argv = ["geoortho", tiles, "dem", "--points", str(las), "--output", str(out)]
        dt, peak_kb, _ = _run_dem([*argv, "--dtm", str(dtm), "--resolution-m", str(resolution_m), "--json", "--quiet"])
        with rasterio.open(out) as a, rasterio.open(dtm) as b:
            runs[label] = (dt, peak_kb, a.read(1).astype(float), b.read(1).astype(float), a.width * a.height)
        print(f"dem DSM + DTM {label}: {dt:.1f} s, peak RSS {peak_kb / 1024:.0f} MB")
    (t1, m1, s1, d1, cells), (t2, m2, s2, d2, _) = runs["tiles"], runs["whole"]
    for name, a, b in (("DSM", s1, s2), ("DTM", d1, d2)):
        both = (a != -9999) & (b != -9999)
        diff = np.abs(a - b)[both]
        print(
            f"  {name}: nodata differs in {int(((a == -9999) != (b == -9999)).sum())} of {cells:,} cells; "
            f"|tiles - whole| p99.9 {np.percentile(diff, 99.9):.4f}, max {diff.max():.3f}"
        )
    print(
        f"dem in tiles, {n / 1e6:.0f} M points, {cells / 1e6:.0f} M cells: peak RSS {m1 / 1024:.0f} MB vs "
        f"{m2 / 1024:.0f} MB whole (x{m1 / m2:.2f}; target < 1024 MB), time x{t1 / t2:.2f}"
    )


def _run_dem(argv: list[str]) -> tuple[float, int, dict]:
    """Seconds, peak RSS (kB) and the JSON result of one dem run in a child process."""
    t = time.perf_counter()
    r = subprocess.run([sys.executable, "-c", OURS, json.dumps(argv)], capture_output=True, text=True)
    dt = time.perf_counter() - t
    if r.returncode:
        raise SystemExit(r.stderr)
    return dt, int(r.stderr.strip().splitlines()[-1].split()[-1]), json.loads(r.stdout)


def _outliers(las: Path, d: Path, resolution_m: float, k: int) -> None:
    """Issue 23: the same cloud with ``k`` points 100 km away (one 10 km up) gives the same DSM and
    DTM, at the explicit resolution and the automatic one, in about the same memory."""
    import laspy
    import rasterio

    far = d / "outliers.las"
    with laspy.open(str(las)) as r, laspy.open(str(far), mode="w", header=r.header) as w:
        first = None
        for pts in r.chunk_iterator(2_000_000):
            first = pts[:k] if first is None else first
            w.write_points(pts)
        extra = laspy.ScaleAwarePointRecord.zeros(k, header=r.header)
        extra.x = np.asarray(first.x) + np.r_[np.full(k - 1, 100_000.0), 0.0]
        extra.y = np.asarray(first.y)
        extra.z = np.asarray(first.z) + np.r_[np.zeros(k - 1), 10_000.0]
        w.write_points(extra)
    for res in (str(resolution_m), "0"):
        peaks, grids = [], []
        for name, src in (("clean", las), ("outliers", far)):
            out = d / f"{name}_{res}.tif"
            dtm = d / f"{name}_{res}_dtm.tif"
            argv = ["geoortho", "dem", "--points", str(src), "--output", str(out), "--dtm", str(dtm)]
            dt, peak_kb, _ = _run_dem([*argv, "--resolution-m", res, "--json", "--quiet"])
            peaks.append(peak_kb)
            with rasterio.open(out) as a, rasterio.open(dtm) as b:
                grids.append((a.transform, a.read(1), b.read(1)))
            print(
                f"  {name} (resolution {res if res != '0' else 'auto'}): {dt:.1f} s, peak RSS {peak_kb / 1024:.0f} MB"
            )
        same = grids[0][0] == grids[1][0] and all(np.array_equal(grids[0][i], grids[1][i]) for i in (1, 2))
        print(
            f"dem with {k} far outliers (resolution {res if res != '0' else 'auto'}): same DSM and DTM as without: "
            f"{same}; peak memory x{peaks[1] / peaks[0]:.3f} of the clean run (target: same, within 10 %)"
        )


if __name__ == "__main__":
    sys.exit(main())
