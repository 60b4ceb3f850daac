"""Benchmark: throughput per worker — photos per minute, per worker, for each stage on a Dask
cluster of 1, 2 and 4 worker processes (issue 78).

One ``distributed`` scheduler with worker processes (``LocalCluster``: a scheduler and workers as
separate processes, one thread each), scaled from one worker to the next count between runs; each
stage runs as ``python -m geoortho STAGE --scheduler ADDRESS`` in a fresh process (its start-up
counted), on the same survey: gcp-find, sfm with split-merge (its submodels are the tasks),
dense, footprints and ortho. Printed per stage and worker count: seconds, photos per minute,
photos per minute per worker, and the speed-up against one worker. The machine's cores are
printed first: workers past the core count share cores, and their throughput per worker falls
by design.

    python benchmarks/bench_workers.py [--workers 1,2,4] [--survey DIR | --preset small]
        [--split 20] [--stages gcp-find,sfm,dense,footprints,ortho]
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import tempfile
from pathlib import Path

from bench_scale import stage_argv
from bench_sfm import OURS, _child

STAGES = ("gcp-find", "sfm", "dense", "footprints", "ortho")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--workers", default="1,2,4")
    ap.add_argument("--survey", type=Path, default=None, help="a synth survey (default: made here)")
    ap.add_argument("--preset", default="small")
    ap.add_argument("--split", type=int, default=20, help="sfm split-merge: submodels of at most this many photos")
    ap.add_argument("--stages", default=",".join(STAGES))
    args = ap.parse_args()
    from distributed import Client, LocalCluster

    import geoortho

    counts = [int(x) for x in args.workers.split(",")]
    stages = [s for s in args.stages.split(",") if s]
    cpu = platform.processor() or platform.machine()
    print(f"machine: {os.cpu_count()} cores, {cpu}, Python {platform.python_version()}")
    with tempfile.TemporaryDirectory() as d:
        survey = args.survey
        if survey is None:
            survey = Path(d) / "survey"
            geoortho.synth(survey, preset=args.preset, seed=1)
        n = sum(1 for p in (survey / "images").iterdir() if p.suffix.lower() in (".jpg", ".jpeg"))
        print(f"survey: {n} photos ({survey})", flush=True)
        rows: dict[str, dict[int, float]] = {s: {} for s in stages}
        with LocalCluster(n_workers=0, threads_per_worker=1, processes=True, dashboard_address=None) as cluster:
            with Client(cluster) as client:
                for k in counts:
                    cluster.scale(k)
                    client.wait_for_workers(k, timeout=120)
                    out = Path(d) / f"w{k}"
                    out.mkdir()
                    sfm_options = ["--max-image-size", "1024", "--max-features", "4096", "--split", str(args.split)]
                    argvs = stage_argv(survey, out, sfm_options, survey / "truth" / "dsm.tif")
                    for st in stages:
                        argv = [
                            *argvs[st],
                            "--scheduler",
                            cluster.scheduler_address,
                            "--quiet",
                        ]
                        dt, _, _ = _child(OURS, ["geoortho", *argv])
                        rows[st][k] = dt
                        print(
                            f"  {k} worker(s) {st:10s} {dt:7.1f} s  {60 * n / dt:6.1f} photos/min  "
                            f"{60 * n / dt / k:6.1f} per worker",
                            flush=True,
                        )
    print("\nstage       " + "".join(f"{f'{k} worker(s)':>26s}" for k in counts))
    print("            " + "".join(f"{'photos/min  /worker  x1':>26s}" for _ in counts))
    for st in stages:
        cells = ""
        for k in counts:
            dt = rows[st][k]
            cells += f"{60 * n / dt:14.1f} {60 * n / dt / k:8.1f} {rows[st][counts[0]] / dt:4.2f}"
        print(f"{st:10s}  {cells}")
    print("(photos per minute on the cluster, per worker, and the speed-up against the first count)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
