"""Benchmark: the command line's start-up, as a user meets it (a fresh process each time).

Times ``python -m geoortho --help`` and ``python -m geoortho describe --json`` over several
fresh processes, against the plain baseline of a bare ``python -c pass`` (the interpreter's own
start-up), and the description read from the sources instead of ready-made
(``GEOORTHO_NO_READY_MADE=1``: what ``--help`` paid before). Prints the median wall time and the
peak memory of each, and geoortho's ratio over the bare interpreter. Goal: ``--help`` <= 0.15 s
on a quiet machine.

    python benchmarks/bench_startup.py [--runs 15]
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import time


def _time(cmd: list[str], runs: int, env: dict[str, str]) -> tuple[float, float]:
    """Median wall seconds and the largest peak RSS (MB) over ``runs`` fresh processes."""
    walls, peaks = [], []
    for _ in range(runs + 1):  # the first run warms the file cache and is not counted
        t0 = time.perf_counter()
        proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, env=env)
        _, status, usage = os.wait4(proc.pid, 0)
        walls.append(time.perf_counter() - t0)
        peaks.append(usage.ru_maxrss / 1024)
        proc.returncode = os.waitstatus_to_exitcode(status)
        if proc.returncode:
            raise SystemExit(f"{' '.join(cmd)} exited {proc.returncode}")
    return statistics.median(walls[1:]), max(peaks[1:])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", type=int, default=15)
    args = ap.parse_args()
    env = dict(os.environ)
    sources = {**env, "GEOORTHO_NO_READY_MADE": "1"}
    py = sys.executable
    rows = [
        ("python -c pass (baseline)", [py, "-c", "pass"], env),
        ("geoortho --help", [py, "-m", "geoortho", "--help"], env),
        ("geoortho describe --json", [py, "-m", "geoortho", "describe", "--json"], env),
        ("geoortho --help, read from the sources", [py, "-m", "geoortho", "--help"], sources),
    ]
    base = None
    print(f"{'command':<42} {'median s':>9} {'peak MB':>8} {'x baseline':>10}")
    for name, cmd, e in rows:
        wall, peak = _time(cmd, args.runs, e)
        base = base or wall
        print(f"{name:<42} {wall:9.3f} {peak:8.0f} {wall / base:10.2f}")


if __name__ == "__main__":
    main()
